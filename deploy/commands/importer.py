"""`flyslam import FORMAT PATH --out FILE.mcap`: convert a public stereo dataset into a recording.

    flyslam import kitti  /data/kitti/odometry --sequence 05 --out kitti05.mcap
    flyslam import euroc  /data/euroc/MH_01_easy --out mh01.mcap
    flyslam import middlebury /data/middlebury/Motorcycle-perfect --scale 0.25 --out moto.mcap

The recording replays like a live source (`flyslam replay`): rectified frames on stereo/frame (PNG by
default: lossless), the calibration on stereo/calibration and as metadata, ground truth on truth/pose
(and truth/depth for Middlebury). Frames and conventions: common/importers/base.py.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from common.importers import FORMATS, DatasetLayoutError, write_recording


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="flyslam import", description=__doc__.split("\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n", 2)[2])
    p.add_argument("format", choices=FORMATS)
    p.add_argument("path", help="dataset folder (KITTI: root with --sequence, or the sequence folder; "
                                "EuRoC: the folder holding mav0; Middlebury: the scene folder)")
    p.add_argument("--out", "-o", required=True, help="MCAP file to write")
    p.add_argument("--sequence", help="KITTI sequence number (with a dataset root)")
    p.add_argument("--max-frames", type=int, default=None, help="import only the first N frames")
    p.add_argument("--encoding", choices=("png", "jpeg"), default="png", help="frame compression (default: png)")
    p.add_argument("--quality", type=int, default=95, help="JPEG quality")
    p.add_argument("--robot", default="rig", help="key prefix of the recording (default: rig)")
    p.add_argument("--scale", type=float, default=1.0, help="Middlebury: resize factor in (0, 1]")
    p.add_argument("--repeat", type=int, default=1, help="Middlebury: write the pair N times, 10 Hz")
    return p


def load(args):
    if args.format == "kitti":
        from common.importers.kitti import load_kitti
        return load_kitti(args.path, sequence=args.sequence, max_frames=args.max_frames)
    if args.format == "euroc":
        from common.importers.euroc import load_euroc
        return load_euroc(args.path, max_frames=args.max_frames)
    from common.importers.middlebury import load_middlebury
    return load_middlebury(args.path, scale=args.scale, repeat=args.repeat)


class _Progress:
    """'frames done/total' on stderr, at most twice a second and at the end."""

    def __init__(self):
        self.last = 0.0

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        if done == total or now - self.last >= 0.5:
            self.last = now
            print(f"frames {done}/{total}", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.max_frames is not None and args.max_frames < 1:
        print("flyslam import: --max-frames must be at least 1", file=sys.stderr)
        return 2
    try:
        dataset = load(args)
    except (DatasetLayoutError, ValueError) as e:  # CalibrationError is a ValueError too
        print(f"flyslam import: {e}", file=sys.stderr)
        return 2
    print(f"importing {dataset.name} → {args.out}", file=sys.stderr, flush=True)
    out = Path(args.out)
    try:
        summary = write_recording(dataset, out, robot=args.robot, encoding=args.encoding,
                                  quality=args.quality, progress=_Progress())
    except (DatasetLayoutError, ValueError) as e:  # e.g. an unreadable image half-way
        out.unlink(missing_ok=True)  # no half-written recording that looks complete
        print(f"flyslam import: {e}", file=sys.stderr)
        return 2
    print(summary.format())
    return 0


if __name__ == "__main__":
    sys.exit(main())
