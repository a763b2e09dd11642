"""Variants of a real clip that look like the sequences flyslam has not seen: a faster vehicle, a robot
driving backwards, other cameras, a rig mounted elsewhere.  ``bench/real.py --variants`` runs each
beside the clip itself, so a setting tuned to the clip shows up as a variant that fails.

Each variant is a :class:`common.importers.StereoDataset` made from the clip's own files, with the
ground truth re-expressed for it (poses of the frames kept, in the variant's base frame):

* ``stride2`` / ``stride3``: every 2nd / 3rd frame, at the clip's frame interval × 2 / × 3 (KITTI 00:
  1.7 / 2.6 m a frame, a car at 60 / 90 km/h);
* ``reverse``: the frames backwards (the camera drives backwards through the same street);
* ``outback``: there and back again: the frames forwards, the last one held for OUTBACK_STOP frames (the
  car stops), then backwards to the first (it reverses down the same street): the way back revisits
  every place of the way out, so loop closure on real images is exercised, and the end should meet
  the start;
* ``laps``: the ``outback`` journey LAPS times over, held still at both ends (a robot patrolling one
  street: a long run that keeps revisiting its own map, so keyframes, loop closures and graph
  corrections pile up as they do over a real day's driving), each frame with its own sensor noise
  (σ = LAPS_NOISE grey levels): a revisit sees the place from the same spot, but never the very
  pixels of an earlier visit;
* ``half``: images and intrinsics at half resolution (a 620×188 camera);
* ``crop640``: the central 640 columns (a narrower field of view: 48° instead of 82°);
* ``mount0``: the rig's ``T_base_camera`` without its height (base_link at the camera, as a
  calibration without a mounting gives it);
* ``noisy``: Gaussian sensor noise of σ = 6 grey levels, independent in every image (a cheaper camera,
  a darker scene);
* ``gain``: the right camera 20 % less exposed and 10 grey levels offset (two auto-exposures that do
  not agree, common on hobby stereo rigs);
* ``exposure``: both cameras' exposure swinging ±30 % over a few frames (auto-exposure driving in and
  out of shade);
* ``sway``: the rig pitching ±SWAY_DEG about its baseline, one swing every SWAY_PERIOD frames (a
  hand-held rig, a robot on rough ground).  Both images are warped by K·Rₓᵀ·K⁻¹ (a rotation about the
  baseline keeps a rectified pair rectified, so the warp is exact) and lose the rows the warp can leave
  black along the top and bottom edges (a 1241×294 camera; a few black pixels remain in the corners,
  at most 15 a row).  The rig pivots about the left camera, so base_link (1.65 m below it on KITTI)
  swings ±9 cm fore and aft with it: a level-base assumption would be wrong here, as it would be for a
  hand-held rig.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Callable

import cv2
import numpy as np

from common.geometry import invert, make_transform, rot_x
from common.importers import StereoDataset
from common.importers.base import C_BODY_OPTICAL

VARIANTS = ("stride2", "stride3", "reverse", "outback", "laps", "half", "crop640", "mount0", "noisy", "gain",
            "exposure", "sway")
SWAY_DEG, SWAY_PERIOD = 3.0, 12
OUTBACK_STOP = 5
LAPS, LAPS_NOISE = 3, 2.0


def sway_pitch(frame: int) -> float:
    """The ``sway`` variant's pitch (rad) of the rig at a frame of the clip, about the optical x axis
    (positive: nose up)."""
    return float(np.radians(SWAY_DEG) * np.sin(2.0 * np.pi * frame / SWAY_PERIOD))


def _rectified_K(calib, side: str, y_shift: float) -> np.ndarray:
    """3×3 intrinsics of one rectified camera of ``calib``, its principal point ``y_shift`` rows lower."""
    cx = calib.cx_left if side == "left" else calib.cx_right
    return np.array([[calib.fx, 0.0, cx], [0.0, calib.fy, calib.cy + y_shift], [0.0, 0.0, 1.0]])


def _sway_margin(calib) -> int:
    """Rows the sway's warp can leave black at the top or bottom of the image (the edges' largest
    inward move at ±SWAY_DEG), plus one."""
    K = _rectified_K(calib, "left", 0)
    u = np.linspace(0, calib.width - 1, 33)
    edges = np.concatenate([np.stack([u, np.zeros_like(u), np.ones_like(u)]),
                            np.stack([u, np.full_like(u, calib.height - 1), np.ones_like(u)])], axis=1)
    inward = 0.0
    for angle in (np.radians(SWAY_DEG), -np.radians(SWAY_DEG)):
        p = K @ rot_x(angle).T @ np.linalg.inv(K) @ edges
        v = p[1] / p[2]
        inward = max(inward, v[:33].max(), (calib.height - 1 - v[33:]).max())
    return int(np.ceil(inward)) + 1



def variant(load: Callable[[], StereoDataset], name: str) -> StereoDataset:
    """The clip ``load()`` gives, changed as ``name`` says (one of VARIANTS)."""
    if name not in VARIANTS:
        raise ValueError(f"unknown variant {name!r} (use one of {', '.join(VARIANTS)})")
    ds = load()
    if len(ds.truth_stamps_ns) != len(ds.stamps_ns) or not np.array_equal(ds.truth_stamps_ns, ds.stamps_ns):
        raise ValueError(f"{ds.name}: variants need one ground-truth pose per frame")
    calib, n = ds.calibration, len(ds.stamps_ns)
    index = np.arange(n)
    step_ns = int(np.median(np.diff(ds.stamps_ns))) if n > 1 else 100_000_000
    stride = int(name[6:]) if name.startswith("stride") else 1
    index = index[::stride] if stride > 1 else index[::-1] if name == "reverse" else index
    if name == "outback":
        index = np.r_[index, np.full(OUTBACK_STOP, n - 1), index[-2::-1]]
    if name == "laps":
        lap = np.r_[index, np.full(OUTBACK_STOP, n - 1), index[-2::-1], np.full(OUTBACK_STOP, 0)]
        index = np.r_[np.tile(lap, LAPS), index[:1]]
    scale = 0.5 if name == "half" else 1.0
    x0 = (calib.width - 640) // 2 if name == "crop640" else 0
    if scale != 1.0:
        calib = calib.scaled(scale)
    y0 = _sway_margin(calib) if name == "sway" else 0
    if y0:      # rows the warp can leave black, cut off: a swaying camera sees the scene there
        K_left, K_right = calib.K_left.copy(), calib.K_right.copy()
        K_left[1, 2] -= y0
        K_right[1, 2] -= y0
        calib = replace(calib, height=calib.height - 2 * y0, cy=calib.cy - y0, K_left=K_left, K_right=K_right)
    if x0:
        K_left, K_right = calib.K_left.copy(), calib.K_right.copy()
        K_left[0, 2] -= x0
        K_right[0, 2] -= x0
        calib = replace(calib, width=640, cx_left=calib.cx_left - x0, cx_right=calib.cx_right - x0,
                        K_left=K_left, K_right=K_right)
    T_base_camera = C_BODY_OPTICAL if name == "mount0" else ds.calibration.T_base_camera
    calib = replace(calib, T_base_camera=np.asarray(T_base_camera, float).copy())
    # truth: T_map_base of the frames kept, re-based on the first kept frame and on the new mounting
    T_map_cam = ds.truth_poses[index] @ ds.calibration.T_base_camera
    if name == "sway":
        T_map_cam = np.stack([T @ make_transform(rot_x(sway_pitch(int(k)))) for T, k in zip(T_map_cam, index)])
    T_cam0_cam = invert(T_map_cam[0]) @ T_map_cam
    truth = calib.T_base_camera @ T_cam0_cam @ invert(calib.T_base_camera)
    stamps = ds.stamps_ns[0] + np.arange(len(index), dtype=np.int64) * step_ns * stride

    def load_pair(i: int):
        left, right = ds.load_pair(int(index[i]))
        if scale != 1.0:
            size = (calib.width, calib.height)
            left, right = (cv2.resize(img, size, interpolation=cv2.INTER_AREA) for img in (left, right))
        if x0:
            left, right = (np.ascontiguousarray(img[:, x0:x0 + 640]) for img in (left, right))
        if name in ("noisy", "laps"):      # noisy: per place; laps: per visit
            rng = np.random.default_rng(int(index[i]) if name == "noisy" else i)
            sigma = 6.0 if name == "noisy" else LAPS_NOISE
            left, right = (np.clip(img + rng.normal(0.0, sigma, img.shape), 0, 255).astype(np.uint8)
                           for img in (left, right))
        if name == "exposure":
            g = 1.0 + 0.3 * np.sin(int(index[i]) / 2.0)
            left, right = (np.clip(img.astype(np.float32) * g, 0, 255).astype(np.uint8) for img in (left, right))
        if name == "gain":
            right = np.clip(right.astype(np.float32) * 0.8 + 10.0, 0, 255).astype(np.uint8)
        if name == "sway":   # a point X in the clip's camera is Rₓᵀ·X in the swayed one
            R = rot_x(sway_pitch(int(index[i])))
            warps = [_rectified_K(calib, side, 0) @ R.T @ np.linalg.inv(_rectified_K(calib, side, y0))
                     for side in ("left", "right")]
            left, right = (cv2.warpPerspective(img, H, (calib.width, calib.height), flags=cv2.INTER_LINEAR)
                           for img, H in zip((left, right), warps))
        return left, right

    return StereoDataset(f"{ds.name}, {name}", calib, stamps, load_pair, stamps, truth)
