"""The `flyslam` command: one entry point, one subcommand per tool or service.

Every subcommand is a module with ``main(argv) -> int`` that owns its argument parser, so
``flyslam <command> --help`` documents that command fully and ``python -m <module>`` behaves the same.
"""
from __future__ import annotations

import importlib
import sys

# name -> (module, one-line help). Order is the order shown in --help.
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("deploy.supervisor", "start a pipeline from a launch file (default: the shipped demo) and supervise it"),
    "record": ("services.recorder", "record bus keys to an MCAP file"),
    "replay": ("services.replay", "publish a recording on the bus as a live source would"),
    "info": ("deploy.commands.info", "summarise a recording: channels, counts, duration, rates"),
    "sim": ("services.sim", "run the world simulator as a live source"),
    "simulate": ("deploy.commands.simulate", "write a simulated run to a recording, offline and deterministic"),
    "evolver": ("services.evolver", "run the fly evolver service"),
    "fusion": ("services.fusion", "run the odometry and sonar fusion service"),
    "localiser": ("services.localiser", "run the localiser (SLAM) service"),
    "planner": ("services.planner", "run the harmonic planner service"),
    "bridge": ("services.bridge", "run the Rerun bridge (live viewer and/or .rrd file)"),
    "camera": ("services.camera", "run a real stereo camera (or video files) as a live source"),
    "calibrate": ("deploy.commands.calibrate", "stereo calibration from chessboard image pairs"),
    "import": ("deploy.commands.importer", "convert a public dataset (kitti, euroc, middlebury) to a recording"),
    "eval": ("deploy.commands.evaluate", "run evolver and localiser in lockstep on a recording and score the trajectory"),
}


def usage() -> str:
    width = max(len(n) for n in COMMANDS)
    lines = ["usage: flyslam <command> [options]   (flyslam <command> --help for details)", "",
             "The Fly algorithm for robot stereovision and SLAM, as processes on a Zenoh bus.", "", "commands:"]
    lines += [f"  {name:<{width}}  {text}" for name, (_, text) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"flyslam: unknown command {name!r}\n\n{usage()}", file=sys.stderr)
        return 2
    module_name = COMMANDS[name][0]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        if e.name == module_name:
            print(f"flyslam {name}: not available in this build ({module_name} is missing)", file=sys.stderr)
            return 2
        raise
    sys.argv[0] = f"flyslam {name}"
    return int(module.main(rest) or 0)


if __name__ == "__main__":
    sys.exit(main())
