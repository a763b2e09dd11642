"""Benchmark: rendered stereo pairs (left + right + depth) per second on the default corridor.

Drives the scripted corridor path and renders a frame at every camera-due event, one process, as the
sim service would.  Prints figures; with --json the last stdout line is one JSON object:
``frames_per_s`` (wall clock), ``cpu_ms_per_frame`` (process CPU time — robust to other load on the
machine; with NUMBA_NUM_THREADS=1 it is the single-core cost), ``load_avg_1min`` (how busy the machine was), ``sim_step_ms_per_frame`` (motion + odometry + sonar between frames), ``compile_s`` (first
render, numba JIT or cache load), image size and thread count.  ``--png`` saves one left/right pair.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numba
import numpy as np

from common.sim import CameraDue, Simulator, load_scenario, scenario_path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="corridor")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--png", default=None, help="save the last left|right pair here (e.g. /tmp/sim_pair.png)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)

    scn = load_scenario(scenario_path(args.scenario))
    sim = Simulator(scn, seed=args.seed, width=args.width, height=args.height)
    t = time.perf_counter()
    sim.render()
    compile_s = time.perf_counter() - t
    print(f"first render (JIT compile or cache load): {compile_s:.2f} s", file=sys.stderr)

    frames, render_wall, render_cpu, step_wall = 0, 0.0, 0.0, 0.0
    last = None
    while frames < args.frames:
        if sim.finished:  # wrap around: restart the path so long benchmarks keep moving
            sim = Simulator(scn, seed=args.seed, width=args.width, height=args.height, world=sim.world)
        t = time.perf_counter()
        events = sim.advance(0.02)
        step_wall += time.perf_counter() - t
        for ev in events:
            if isinstance(ev, CameraDue):
                t, c = time.perf_counter(), time.process_time()
                last = sim.render(ev.stamp_ns)
                render_wall += time.perf_counter() - t
                render_cpu += time.process_time() - c
                frames += 1
                if frames % 10 == 0:
                    print(f"{frames} frames, {frames / render_wall:.1f} frames/s", file=sys.stderr)
    if args.png and last is not None:
        import cv2
        cv2.imwrite(args.png, np.hstack([last.left, last.right])[..., ::-1])
        print(f"saved {args.png}", file=sys.stderr)

    result = {
        "scenario": args.scenario,
        "width": args.width,
        "height": args.height,
        "frames": frames,
        "frames_per_s": round(frames / render_wall, 2),
        "ms_per_frame": round(1000 * render_wall / frames, 2),
        "cpu_ms_per_frame": round(1000 * render_cpu / frames, 2),
        "sim_step_ms_per_frame": round(1000 * step_wall / frames, 2),
        "compile_s": round(compile_s, 2),
        "threads": numba.get_num_threads(),
        "load_avg_1min": round(os.getloadavg()[0], 2),  # other processes sharing the cores
        "quads": len(sim.world.quads),
    }
    for k, v in result.items():
        print(f"{k:>22}: {v}")
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
