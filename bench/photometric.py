"""CPU cost of the localiser's photometric tracking (align_flies, coarse_candidates) on a real recording.

The recording is run through `flyslam eval`'s code path (common.lockstep.run_lockstep: evolver and
localiser in lockstep) with the localiser's calls to align_flies and coarse_candidates recorded; those calls
are then replayed ``--passes`` times on the same inputs. Every figure is process CPU time
(``time.process_time``, all threads), which a loaded machine inflates far less than the wall clock.

Figures:
  align_calls                  align_flies calls the run made
  align_cpu_ms_in_run          mean CPU-ms per call inside the run (caches as the run had them)
  align_cpu_ms_per_call        replay: mean CPU-ms per call, the best pass (median_pass: the median pass)
  align_iterations_per_call    mean Gauss-Newton iterations per call (all pyramid levels)
  coarse_calls / coarse_cpu_ms_per_call   the same for coarse_candidates (replayed; 0 calls → null)
  load_average_1min            before the run and after the replay

The last stdout line with --json is one JSON object.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

DEFAULT_RECORDING = Path(".cache/real/kitti-00-frames-0-99.mcap")


def record_calls(recording: Path, max_frames: int | None, generations: int):
    """Run the lockstep chain on ``recording`` with the tracking calls recorded: (kind, args, kwargs, cpu_s)."""
    from common.lockstep import run_lockstep
    from common.recording import RecordingReader
    from common.slam import tracking

    calls = []
    originals = {"align": tracking.align_flies, "coarse": tracking.coarse_candidates}

    def recorder(kind):
        def call(*args, **kwargs):
            t = time.process_time()
            out = originals[kind](*args, **kwargs)
            calls.append((kind, args, kwargs, time.process_time() - t))
            return out
        return call

    tracking.align_flies, tracking.coarse_candidates = recorder("align"), recorder("coarse")
    try:
        result = run_lockstep(RecordingReader(str(recording)).messages(), generations_per_frame=generations,
                              max_frames=max_frames)
    finally:
        tracking.align_flies, tracking.coarse_candidates = originals["align"], originals["coarse"]
    return calls, result.frames


def replay(calls, passes: int):
    """CPU-s per call of each pass over ``calls`` (warm: every kernel already ran in the recording)."""
    from common.registration.photometric import align_flies, coarse_candidates
    fn = {"align": align_flies, "coarse": coarse_candidates}
    per_pass, out = [], None
    for _ in range(passes):
        t = time.process_time()
        out = [fn[kind](*args, **kwargs) for kind, args, kwargs, _ in calls]
        per_pass.append((time.process_time() - t) / max(len(calls), 1))
    return per_pass, out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recording", type=Path, default=DEFAULT_RECORDING)
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--generations", type=int, default=30, help="evolver generations per frame (eval's default)")
    ap.add_argument("--passes", type=int, default=3, help="replays of the recorded calls")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if not args.recording.is_file():
        print(f"bench/photometric.py: no recording at {args.recording} (flyslam import kitti, or --recording)",
              file=sys.stderr)
        return 2
    load0 = os.getloadavg()[0]
    calls, frames = record_calls(args.recording, args.max_frames, args.generations)
    figures = {"recording": str(args.recording), "frames": frames}
    for kind in ("align", "coarse"):
        mine = [c for c in calls if c[0] == kind]
        figures[f"{kind}_calls"] = len(mine)
        if not mine:
            figures[f"{kind}_cpu_ms_per_call"] = None
            continue
        per_pass, out = replay(mine, args.passes)
        figures[f"{kind}_cpu_ms_in_run"] = round(1000 * float(np.mean([c[3] for c in mine])), 3)
        figures[f"{kind}_cpu_ms_per_call"] = round(1000 * min(per_pass), 3)
        figures[f"{kind}_cpu_ms_per_call_median_pass"] = round(1000 * float(np.median(per_pass)), 3)
        if kind == "align":
            figures["align_iterations_per_call"] = round(float(np.mean([a.iterations for a in out])), 2)
            figures["align_ok_fraction"] = round(float(np.mean([a.ok for a in out])), 3)
    figures["load_average_1min"] = [round(load0, 2), round(os.getloadavg()[0], 2)]
    for k, v in figures.items():
        print(f"{k:36s} {v}")
    if args.json:
        print(json.dumps(figures))
    return 0


if __name__ == "__main__":
    sys.exit(main())
