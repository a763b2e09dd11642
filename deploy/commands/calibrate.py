"""`flyslam calibrate`: stereo calibration from chessboard image pairs → calibration YAML.

    flyslam calibrate --left 'pairs/left*.jpg' --right 'pairs/right*.jpg' --board 9x6 --square-m 0.025 \\
        --out stereo.yaml

Pairs are matched by sorted file name. Progress goes to stderr, the summary to stdout; the YAML is what
``flyslam camera --calibration`` reads (format: common/stereo_rectify.py).
"""
from __future__ import annotations

import argparse
import glob
import sys
from pathlib import Path

import cv2

from common.camera import CalibrationError
from common.chessboard_calibration import calibrate_stereo, parse_board
from common.stereo_rectify import rectify_rig, save_stereo_yaml


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="flyslam calibrate", description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--left", required=True, help="glob of the left images (quote it)")
    p.add_argument("--right", required=True, help="glob of the right images (quote it)")
    p.add_argument("--board", default="9x6", help="inner corners per row x per column")
    p.add_argument("--square-m", type=float, required=True, help="chessboard square size in metres")
    p.add_argument("--out", "-o", required=True, help="calibration YAML to write")
    return p


def _pairs(left_paths, right_paths):
    for lp, rp in zip(left_paths, right_paths):
        left, right = cv2.imread(lp, cv2.IMREAD_GRAYSCALE), cv2.imread(rp, cv2.IMREAD_GRAYSCALE)
        if left is None or right is None:
            raise CalibrationError(f"cannot read image {lp if left is None else rp}")
        yield f"{Path(lp).name}+{Path(rp).name}", left, right


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    left_paths, right_paths = sorted(glob.glob(args.left)), sorted(glob.glob(args.right))
    try:
        pattern = parse_board(args.board)
        if not left_paths or not right_paths:
            raise CalibrationError(f"no images match {args.left if not left_paths else args.right}")
        if len(left_paths) != len(right_paths):
            raise CalibrationError(f"{len(left_paths)} left images ({args.left}) but {len(right_paths)} "
                                   f"right images ({args.right}); pairs are matched by sorted name")
        total = len(left_paths)
        result = calibrate_stereo(_pairs(left_paths, right_paths), pattern, args.square_m,
                                  lambda text: print(text, file=sys.stderr, flush=True), total=total)
        calib = rectify_rig(result.rig)
        save_stereo_yaml(args.out, result.rig, info={
            "square_size_m": float(args.square_m), "board": args.board, "rms_left_px": result.rms_left,
            "rms_right_px": result.rms_right, "rms_stereo_px": result.rms_stereo,
            "pairs_used": len(result.used)})
    except CalibrationError as e:
        print(f"flyslam calibrate: {e}", file=sys.stderr)
        return 2
    K1, K2 = result.rig.K1, result.rig.K2
    print(f"pairs used     {len(result.used)} of {total}" + (f", rejected {len(result.rejected)}:" if result.rejected else ""))
    for name, reason in result.rejected:
        print(f"  {name}: {reason}")
    print(f"left   RMS {result.rms_left:.3f} px  fx {K1[0, 0]:.2f} fy {K1[1, 1]:.2f} cx {K1[0, 2]:.2f} cy {K1[1, 2]:.2f}")
    print(f"right  RMS {result.rms_right:.3f} px  fx {K2[0, 0]:.2f} fy {K2[1, 1]:.2f} cx {K2[0, 2]:.2f} cy {K2[1, 2]:.2f}")
    print(f"stereo RMS {result.rms_stereo:.3f} px  baseline {result.baseline_m * 1000:.2f} mm")
    print(f"rectified  {calib.width}x{calib.height} fx {calib.fx:.2f} cx {calib.cx_left:.2f} cy {calib.cy:.2f} "
          f"baseline {calib.baseline * 1000:.2f} mm")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
