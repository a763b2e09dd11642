"""`flyslam simulate`: write a simulated run (a scenario's scripted path) to a recording, offline.

Runs as fast as the machine allows, deterministically for a scenario and seed; the recording replays
like any other (`flyslam replay`) and carries ground truth (`truth/pose`, optionally `truth/depth`).
"""
from __future__ import annotations

import argparse
import sys
import time

from common.sim.offline import simulate_to_recording
from common.sim.scenario import ScenarioError
from deploy.progress import Progress


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="flyslam simulate", description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--scenario", default="corridor", help="name in recordings/scenarios/ or a TOML path")
    p.add_argument("--out", "-o", required=True, help="MCAP file to write")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seconds", type=float, default=None, help="stop after this much simulated time (default: end of path)")
    p.add_argument("--fps", type=float, default=None, help="camera rate (default: the scenario's)")
    p.add_argument("--width", type=int, default=None)
    p.add_argument("--height", type=int, default=None)
    p.add_argument("--encoding", default="jpeg", choices=["rgb8", "jpeg", "png"])
    p.add_argument("--quality", type=int, default=90, help="JPEG quality")
    p.add_argument("--depth", action="store_true", help="include ground-truth depth maps")
    p.add_argument("--truth-tum", default=None, help="also write the ground-truth trajectory as TUM text")
    args = p.parse_args(argv)
    t0 = time.monotonic()
    bar = Progress("simulate")

    def progress(sim_s, frames):
        bar.update(frames, f"frames, {sim_s:.1f} s simulated")

    try:
        summary = simulate_to_recording(args.scenario, args.out, seed=args.seed, seconds=args.seconds, fps=args.fps,
                                        width=args.width, height=args.height, encoding=args.encoding,
                                        quality=args.quality, depth=args.depth, progress=progress,
                                        truth_tum=args.truth_tum)
    except (ScenarioError, FileNotFoundError) as e:
        print(f"flyslam simulate: {e}", file=sys.stderr)
        return 2
    bar.done()
    print(f"wrote {summary['frames']} frames ({summary['seconds']:.1f} s simulated, {summary['width']}×{summary['height']}, "
          f"{summary['encoding']}) to {summary['out']} in {time.monotonic() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
