"""Stereo calibration from chessboard image pairs (pure: images in, :class:`RawStereoRig` out).

The recipe reproduces OpenCV's reference numbers on its own stereo chessboard set: corners by
``cv2.findChessboardCorners`` refined with ``cv2.cornerSubPix``; each camera calibrated on its own
(``cv2.calibrateCamera``, k1 k2 p1 p2 k3); then ``cv2.stereoCalibrate`` with ``CALIB_FIX_INTRINSIC``
estimates only R, T. Fixing the intrinsics keeps each camera's focal length its own (the joint solve
with shared-focal flags would pull them together) and makes the stereo RMS an honest check of the
extrinsics. Object points are in metres, so T comes out in metres.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterable

import cv2
import numpy as np

from common.camera import CalibrationError
from common.stereo_rectify import RawStereoRig

SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
MIN_PAIRS = 3


def parse_board(text: str) -> tuple[int, int]:
    """'9x6' → (9, 6): inner corners per row and per column."""
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise CalibrationError(f"board must be COLSxROWS inner corners, e.g. 9x6, got {text!r}") from None
    if cols < 2 or rows < 2:
        raise CalibrationError(f"a chessboard needs at least 2×2 inner corners, got {text!r}")
    return cols, rows


def board_points(pattern: tuple[int, int], square_m: float) -> np.ndarray:
    """(cols·rows, 3) float32 corner positions on the board plane (z=0), metres, row-major like OpenCV."""
    cols, rows = pattern
    pts = np.zeros((cols * rows, 3), np.float32)
    pts[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    return pts


def find_corners(gray: np.ndarray, pattern: tuple[int, int]) -> np.ndarray | None:
    """Sub-pixel inner corners (N, 1, 2) float32 of a greyscale image, or None when the board is not found."""
    if gray.ndim != 2:
        gray = cv2.cvtColor(gray, cv2.COLOR_RGB2GRAY)
    found, corners = cv2.findChessboardCorners(
        gray, pattern, cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not found:
        return None
    refined = cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), SUBPIX_CRITERIA)
    return np.asarray(refined, np.float32).reshape(-1, 1, 2)  # OpenCV 5 may return (N, 2)


def _detect_pair(left, right, pattern, size) -> tuple[np.ndarray, np.ndarray] | str:
    """Corners of both images, or why the pair cannot be used."""
    if left.shape[:2] != right.shape[:2]:
        return f"left {left.shape[1]}×{left.shape[0]} and right {right.shape[1]}×{right.shape[0]} differ"
    if size is not None and (left.shape[1], left.shape[0]) != size:
        return f"{left.shape[1]}×{left.shape[0]} differs from the first pair's {size[0]}×{size[1]}"
    cl = find_corners(left, pattern)
    if cl is None:
        return f"no {pattern[0]}x{pattern[1]} board in the left image"
    cr = find_corners(right, pattern)
    if cr is None:
        return f"no {pattern[0]}x{pattern[1]} board in the right image"
    return cl, cr


@dataclass
class ChessboardCalibration:
    """Result of :func:`calibrate_stereo`; ``rig`` is ready for ``save_stereo_yaml``/``rectify_rig``."""
    rig: RawStereoRig
    rms_left: float
    rms_right: float
    rms_stereo: float
    used: list[str] = field(default_factory=list)
    rejected: list[tuple[str, str]] = field(default_factory=list)  # (pair name, reason)
    # Raw corners of the used pairs, for checks: lists of (N, 1, 2) float32.
    corners_left: list[np.ndarray] = field(default_factory=list)
    corners_right: list[np.ndarray] = field(default_factory=list)

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.rig.T))


def calibrate_stereo(pairs: Iterable[tuple[str, np.ndarray, np.ndarray]], pattern: tuple[int, int],
                     square_m: float, progress: Callable[[str], None] | None = None,
                     total: int | None = None) -> ChessboardCalibration:
    """Calibrate a stereo rig from (name, left image, right image) chessboard pairs.

    A pair is rejected (and reported) when the board is not found in both images or its images do not
    have the size of the first pair. ``progress`` gets one line per pair ("[i/total] name: ok") and per
    stage. Raises CalibrationError with fewer than MIN_PAIRS usable pairs.
    """
    if not np.isfinite(square_m) or square_m <= 0:
        raise CalibrationError(f"square size must be a positive length in metres, got {square_m}")
    say = progress or (lambda _text: None)
    obj = board_points(pattern, square_m)
    size = None
    used, rejected, left_pts, right_pts = [], [], [], []
    for i, (name, left, right) in enumerate(pairs, start=1):
        found = _detect_pair(left, right, pattern, size)
        if isinstance(found, str):
            rejected.append((name, found))
            say(f"[{i}/{total or '?'}] {name}: rejected: {found}")
            continue
        size = size or (left.shape[1], left.shape[0])
        used.append(name)
        left_pts.append(found[0])
        right_pts.append(found[1])
        say(f"[{i}/{total or '?'}] {name}: ok")
    if len(used) < MIN_PAIRS:
        raise CalibrationError(f"only {len(used)} usable chessboard pair(s) (need {MIN_PAIRS}); "
                               + "; ".join(f"{n}: {r}" for n, r in rejected[:5]))
    objs = [obj] * len(used)
    say(f"calibrating the left camera on {len(used)} views")
    rms_l, K1, D1, _, _ = cv2.calibrateCamera(objs, left_pts, size, None, None)
    say(f"calibrating the right camera on {len(used)} views")
    rms_r, K2, D2, _, _ = cv2.calibrateCamera(objs, right_pts, size, None, None)
    say("stereo calibration (intrinsics fixed)")
    rms_s, K1, D1, K2, D2, R, T, _E, _F = cv2.stereoCalibrate(
        objs, left_pts, right_pts, K1, D1, K2, D2, size, flags=cv2.CALIB_FIX_INTRINSIC,
        criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-6))
    rig = RawStereoRig(width=size[0], height=size[1], K1=K1, D1=D1, K2=K2, D2=D2, R=R, T=T.ravel())
    return ChessboardCalibration(rig, float(rms_l), float(rms_r), float(rms_s), used, rejected,
                                 left_pts, right_pts)
