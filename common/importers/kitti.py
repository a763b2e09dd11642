"""KITTI odometry: ``sequences/NN/{image_0,image_1,calib.txt,times.txt}`` and ``poses/NN.txt``.

The grey cameras 0 (left) and 1 (right) are already rectified; ``calib.txt`` rows ``P0:`` and ``P1:``
are their 3×4 projections (baseline = (P0[0,3] − P1[0,3]) / fx). ``times.txt`` holds seconds since the
sequence start; ``poses/NN.txt`` (sequences 00–10) the left camera's pose in the first camera's frame,
converted to base_link in map per common.importers.base, base_link on the road under the left camera.

KITTI's colour download has ``image_2``/``image_3`` instead (rows ``P2:``/``P3:``): without the grey
pair the colour one is read, and the poses (of grey camera 0) are carried to colour camera 2, which
sits ``K⁻¹·P2[:, 3]`` from it in the same rectified orientation.
"""
from __future__ import annotations

from decimal import Decimal, InvalidOperation
from pathlib import Path

import cv2
import numpy as np

from common.camera import StereoCalibration
from common.geometry import R_BODY_OPTICAL, make_transform
from common.importers.base import DatasetLayoutError, StereoDataset, map_poses_from_camera, require

# The KITTI car's left grey camera is 1.65 m above the road (Geiger et al., IJRR 2013, Fig. 3):
# base_link is on the road under it (REP-103), so the localiser's height band starts at the road.
CAMERA_HEIGHT_M = 1.65
T_BASE_CAMERA = make_transform(R_BODY_OPTICAL, [0.0, 0.0, CAMERA_HEIGHT_M])
from common.trajectory import read_kitti


# (left folder, right folder, left projection row, right projection row): the grey pair, else the colour one
CAMERA_PAIRS = (("image_0", "image_1", "P0", "P1"), ("image_2", "image_3", "P2", "P3"))


def parse_calib(path: Path, keys=("P0", "P1")) -> dict[str, np.ndarray]:
    """``KEY: v1 v2 ...`` rows of a KITTI calib.txt → {KEY: float array}; ``keys`` must be 12-number rows."""
    rows = {}
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        key, sep, values = line.partition(":")
        if not sep:
            raise DatasetLayoutError(f"KITTI: {path}:{lineno}: expected 'KEY: numbers', got {line[:40]!r}")
        try:
            rows[key.strip()] = np.array([float(v) for v in values.split()])
        except ValueError:
            raise DatasetLayoutError(f"KITTI: {path}:{lineno}: non-numeric value") from None
    for key in keys:
        if key not in rows or rows[key].size != 12:
            raise DatasetLayoutError(f"KITTI: {path} has no 12-number {key} row")
    return rows


def parse_times(path: Path) -> np.ndarray:
    """times.txt (decimal seconds, one per line) → int64 ns, exactly (no float rounding)."""
    out = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if line.strip():
            try:
                out.append(int((Decimal(line.strip()) * 1_000_000_000).to_integral_value()))
            except InvalidOperation:
                raise DatasetLayoutError(f"KITTI: {path}:{lineno}: {line.strip()!r} is not a time in seconds") from None
    return np.array(out, np.int64)


def calibration_from_projections(P0: np.ndarray, P1: np.ndarray, width: int, height: int) -> StereoCalibration:
    P0, P1 = P0.reshape(3, 4), P1.reshape(3, 4)
    fx = P0[0, 0]
    return StereoCalibration(width=width, height=height, fx=float(fx), fy=float(P0[1, 1]),
                             cx_left=float(P0[0, 2]), cx_right=float(P1[0, 2]), cy=float(P0[1, 2]),
                             baseline=float((P0[0, 3] - P1[0, 3]) / fx), K_left=P0[:, :3].copy(),
                             K_right=P1[:, :3].copy(), T_base_camera=T_BASE_CAMERA.copy())


def _read_image(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetLayoutError(f"KITTI: cannot read image {path}")
    if img.dtype != np.uint8:
        raise DatasetLayoutError(f"KITTI: {path} is {img.dtype}, expected 8-bit")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if img.ndim == 3 else img


def load_kitti(path, sequence: str | None = None, max_frames: int | None = None) -> StereoDataset:
    """A KITTI odometry sequence: ``path`` is the dataset root (with ``sequence``) or the sequence folder."""
    path = Path(path)
    require(path, "KITTI")
    if (path / "sequences").is_dir():
        if sequence is None:
            raise DatasetLayoutError(f"KITTI: {path} is a dataset root; say which sequence (--sequence NN)")
        sequence = str(sequence).zfill(2)
        seq_dir = require(path / "sequences" / sequence, "KITTI")
        poses_file = path / "poses" / f"{sequence}.txt"
    else:
        seq_dir, sequence = path, path.name
        poses_file = path.parent.parent / "poses" / f"{sequence}.txt"
    left_name, right_name, P_left, P_right = next(
        (pair for pair in CAMERA_PAIRS if (seq_dir / pair[0]).is_dir()), CAMERA_PAIRS[0])
    if not (seq_dir / left_name).is_dir():
        raise DatasetLayoutError(f"KITTI: {seq_dir / left_name} not found (nor the colour cameras' "
                                 f"{seq_dir / CAMERA_PAIRS[1][0]})")
    left_dir = seq_dir / left_name
    right_dir = require(seq_dir / right_name, "KITTI")
    calib_rows = parse_calib(require(seq_dir / "calib.txt", "KITTI"), (P_left, P_right))
    stamps = parse_times(require(seq_dir / "times.txt", "KITTI"))
    lefts, rights = sorted(left_dir.glob("*.png")), sorted(right_dir.glob("*.png"))
    if not lefts:
        raise DatasetLayoutError(f"KITTI: no .png images in {left_dir}")
    unpaired_left = sorted({p.name for p in lefts} - {p.name for p in rights})
    unpaired_right = sorted({p.name for p in rights} - {p.name for p in lefts})
    if unpaired_left or unpaired_right:
        have, lack, names = ((left_dir, right_dir, unpaired_left) if unpaired_left
                             else (right_dir, left_dir, unpaired_right))
        raise DatasetLayoutError(f"KITTI: {lack / names[0]} not found ({len(names)} image(s) of {have} have no pair)")
    if len(stamps) != len(lefts):
        raise DatasetLayoutError(f"KITTI: {seq_dir / 'times.txt'} has {len(stamps)} times for {len(lefts)} images")
    n = len(lefts) if max_frames is None else min(len(lefts), int(max_frames))
    first = _read_image(lefts[0])
    calib = calibration_from_projections(calib_rows[P_left], calib_rows[P_right], first.shape[1], first.shape[0])
    truth_stamps, truth = np.zeros(0, np.int64), np.zeros((0, 4, 4))
    notes = []
    if poses_file.is_file():
        poses = read_kitti(poses_file)
        if len(poses) != len(lefts):
            raise DatasetLayoutError(f"KITTI: {poses_file} has {len(poses)} poses for {len(lefts)} images")
        if P_left != "P0":      # the poses are grey camera 0's; the left camera here sits beside it
            P = calib_rows[P_left].reshape(3, 4)
            T_cam0_left = make_transform(np.eye(3), -np.linalg.solve(P[:, :3], P[:, 3]))
            poses = np.asarray(poses) @ T_cam0_left
        truth_stamps, truth = stamps[:n], map_poses_from_camera(poses[:n], reference=poses[0],
                                                             T_base_camera=T_BASE_CAMERA)
    else:
        notes.append(f"no ground truth ({poses_file} not found)")

    def load_pair(i: int):
        return _read_image(lefts[i]), _read_image(rights[i])

    return StereoDataset(f"KITTI odometry sequence {sequence} ({n} of {len(lefts)} frames)", calib, stamps[:n],
                         load_pair, truth_stamps, truth, notes=notes)
