"""The `flyslam` command: one entry point, one subcommand per tool or service.

Every subcommand is a module with ``main(argv) -> int`` that owns its argument parser, so
``flyslam <command> --help`` documents that command fully and ``python -m <module>`` behaves the same.

Errors are one line on stderr, ``flyslam <command>: <what and where>``, never a traceback unless
``flyslam --debug <command> ...``. Exit status, for every command:

- 0: done; 1: failed (a required service gave up, an internal error);
- 2: usage or bad input (a flag, a launch/scenario/calibration/config file that cannot be used);
- 3: a damaged recording (read up to the damage);
- 130: interrupted (Ctrl-C).
"""
from __future__ import annotations

import importlib
import sys

from common.recording import RecordingError

EXIT_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 1, 2, 130
# What bad input raises: the project's errors are ValueErrors naming the file and field (LaunchError,
# BusConfigError, CalibrationError, ScenarioError, ...), OSError a file that cannot be read.
BAD_INPUT = (ValueError, OSError, RecordingError)

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
    "certs": ("deploy.commands.certs", "make a CA and per-host TLS certificates for deploy/zenoh/secured.json5"),
    "eval": ("deploy.commands.evaluate", "run evolver and localiser in lockstep on a recording and score the trajectory"),
}


def usage() -> str:
    width = max(len(n) for n in COMMANDS)
    lines = ["usage: flyslam [--debug] <command> [options]   (flyslam <command> --help for details)", "",
             "The Fly algorithm for robot stereovision and SLAM, as processes on a Zenoh bus.", "", "commands:"]
    lines += [f"  {name:<{width}}  {text}" for name, (_, text) in COMMANDS.items()]
    lines += ["", "--debug: print the traceback of an error instead of one line",
              "exit status: 0 done, 1 failed, 2 usage or bad input, 3 damaged recording, 130 interrupted"]
    return "\n".join(lines)


def describe(e: BaseException) -> str:
    """One line for an error: the project's messages name file and field already; an OSError gets its
    file name and reason; anything else its type."""
    if isinstance(e, OSError) and e.strerror:
        return f"{e.filename}: {e.strerror}" if e.filename else e.strerror
    text = " ".join(str(e).split())
    if isinstance(e, BAD_INPUT) and text:
        return text
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    debug = bool(argv) and argv[0] == "--debug"
    if debug:
        argv = argv[1:]
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
    if debug:
        return int(module.main(rest) or 0)
    try:
        return int(module.main(rest) or 0)
    except KeyboardInterrupt:
        print(f"flyslam {name}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BAD_INPUT as e:
        print(f"flyslam {name}: {describe(e)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as e:  # noqa: BLE001 - the top level: one line, the traceback with --debug
        print(f"flyslam {name}: internal error, {describe(e)} (flyslam --debug {name} ... shows the traceback)",
              file=sys.stderr)
        return EXIT_FAILED


if __name__ == "__main__":
    sys.exit(main())
