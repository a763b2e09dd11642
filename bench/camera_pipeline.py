"""Camera driver benchmark: cost per stereo pair of rectification (two remaps) and of each encoding.

For 640×480 and 1280×720 RGB pairs through a distorted, slightly rotated rig: milliseconds per pair for
rectify only, and rectify + StereoFrame build + msgpack encode for rgb8, jpeg (q90) and png; the
payload size of each. The sustainable frame rate of `flyslam camera` on one core is about 1000 / ms.

Figures only, no pass/fail. Progress on stderr; with --json the last stdout line is one JSON object.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from common.geometry import rot_x, rot_y  # noqa: E402
from common.messages import encode  # noqa: E402
from common.stereo_rectify import RawStereoRig, rectify_rig  # noqa: E402
from services.camera import StereoPipeline  # noqa: E402


def rig(width: int, height: int) -> RawStereoRig:
    f = 0.9 * width
    K1 = np.array([[f, 0, width / 2 - 3], [0, f, height / 2 + 2], [0, 0, 1]])
    K2 = np.array([[f * 1.01, 0, width / 2 + 4], [0, f * 1.01, height / 2 - 1], [0, 0, 1]])
    return RawStereoRig(width, height, K1, [-0.2, 0.05, 0.001, 0, 0], K2, [-0.18, 0.04, 0, 0.001, 0],
                        rot_y(0.02) @ rot_x(0.005), [-0.12, 0.001, 0.0])


def time_per_call(fn, repeats: int) -> float:
    fn()  # warm-up
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - t0) / repeats * 1000


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    cv2.setNumThreads(1)  # one core: what one camera process costs on a shared machine
    rng = np.random.default_rng(0)
    results = {}
    for width, height in ((640, 480), (1280, 720)):
        calib = rectify_rig(rig(width, height))
        tex = cv2.GaussianBlur(rng.integers(0, 256, (height, width, 3), dtype=np.uint8), (0, 0), 1.5)
        left_bgr, right_bgr = tex, np.roll(tex, -12, axis=1)
        row = {}
        pipe = StereoPipeline(calib, "rgb8")
        row["rectify_ms"] = time_per_call(lambda: pipe.rectify(left_bgr, right_bgr), args.repeats)
        for enc in ("rgb8", "jpeg", "png"):
            pipe = StereoPipeline(calib, enc)
            print(f"{width}x{height} {enc}", file=sys.stderr, flush=True)
            row[f"{enc}_ms"] = time_per_call(lambda: encode(pipe.frame(left_bgr, right_bgr, 1, 0)), args.repeats)
            row[f"{enc}_kB"] = len(encode(pipe.frame(left_bgr, right_bgr, 1, 0))) / 1000
        results[f"{width}x{height}"] = row
    for size, row in results.items():
        print(f"{size}: rectify {row['rectify_ms']:.2f} ms/pair; " + "; ".join(
            f"{enc} {row[enc + '_ms']:.2f} ms ({row[enc + '_kB']:.0f} kB)" for enc in ("rgb8", "jpeg", "png")))
    if args.json:
        print(json.dumps({"benchmark": "camera_pipeline", "threads": 1, "results": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
