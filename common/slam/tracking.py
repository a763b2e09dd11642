"""Photometric tracking against a keyframe: what a keyframe keeps of its flies' image neighbourhoods,
and the fix a new image gets from them.

A keyframe's :class:`ReferenceView` holds its fittest flies in its left optical frame, their fitness
and the left image they were evaluated on. :func:`photometric_fix` aligns those flies into a new left
image (common.registration.photometric), starting from a predicted camera pose, and returns the new
base pose in the map with its covariance, or None with the reason it was refused. The pyramid of a
view is built on first use and dropped with the view.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from common.fly.selection import fittest, spread_fittest
from common.geometry import invert, scaled_motion, transform_points
from common.registration.photometric import align_flies, coarse_candidates, level_intrinsics, pyramid

# Lattice starts fully aligned when the motion is unknown (distinct basins of the coarse score).  A
# later start wins only with a clearly better fit: on one plane the motions that map it alike fit
# within ~10 % of each other and the lattice's order is the better guide; on the first frames of the
# KITTI clip the true motion's residual was 0.3-0.75 of the wrong basin's the lattice ranked first.
SEARCH_STARTS = 3
SWITCH_RESIDUAL_RATIO = 0.8


@dataclass
class ReferenceView:
    T_map_cam: np.ndarray           # left optical frame of the keyframe in the map
    points: np.ndarray              # (K, 3) float32 fittest flies, keyframe left optical frame
    weights: np.ndarray             # (K,) float32 their fitness
    image: np.ndarray               # (H, W) uint8 left image
    levels: int = 4
    _pyramid: list | None = field(default=None, repr=False)
    smooth_px: float = 0.0          # the pyramid's level-0 smoothing (photometric.pyramid)

    def pyramid(self) -> list[np.ndarray]:
        if self._pyramid is None:
            self._pyramid = pyramid(self.image, self.levels, self.smooth_px)
        return self._pyramid


def reference_view(T_map_cam, positions_cam, fitness, image, count: int, near_m: float, levels: int,
                   image_pyramid: list[np.ndarray] | None = None, K: np.ndarray | None = None,
                   trusted_fraction: float = 1.0, smooth_px: float = 0.0) -> ReferenceView:
    """``count`` flies in front of the camera (beyond ``near_m``) with their image (and its pyramid,
    when the caller already built it from that image).  With the intrinsics ``K`` they are the
    trusted (``fittest(fitness, trusted_fraction)``) flies spread over the image
    (common.fly.selection.spread_fittest), else simply the fittest.  ``image_pyramid``, when given, was
    built with ``smooth_px``."""
    P = np.asarray(positions_cam, np.float32)
    f = np.asarray(fitness, np.float32)
    ok = np.isfinite(P).all(1) & np.isfinite(f) & (f > 0) & (P[:, 2] > near_m)
    grey = image if image.ndim == 2 else image.mean(axis=2).astype(np.uint8)
    if K is None:
        ok = np.flatnonzero(ok)
        keep = ok[np.argsort(-f[ok], kind="stable")[:count]]
    else:
        trusted = fittest(f, trusted_fraction)
        trusted = trusted[ok[trusted]]
        z = P[trusted, 2].astype(np.float64)
        u = K[0, 0] * P[trusted, 0] / z + K[0, 2]
        v = K[1, 1] * P[trusted, 1] / z + K[1, 2]
        keep = trusted[spread_fittest(u, v, f[trusted], count, grey.shape[1], grey.shape[0])]
    return ReferenceView(np.asarray(T_map_cam, float).copy(), P[keep].copy(), f[keep].copy(),
                         np.ascontiguousarray(grey), levels, image_pyramid, smooth_px)


def adjoint(T: np.ndarray) -> np.ndarray:
    """6×6 adjoint of a rigid transform for twists ordered (translation, rotation)."""
    R, p = T[:3, :3], T[:3, 3]
    P = np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[:3, 3:] = P @ R
    A[3:, 3:] = R
    return A


@dataclass
class Fix:
    T_map_base: np.ndarray
    covariance: np.ndarray          # 6×6 over map-frame position (x, y, z) and rotation (about x, y, z)
    inliers: float
    residual: float


def _accepted(al, min_inliers: float) -> bool:
    return al.ok and al.inliers >= min_inliers and np.isfinite(al.residual)


def best_alignment(points, weights, ref_pyramid, new_pyramid, K, starts, min_inliers: float):
    """align_flies from each of ``starts`` in turn, in order of preference: a later start replaces the
    current choice when it is accepted (ok, ``min_inliers``) and the choice is not, or when it fits
    clearly better (residual under SWITCH_RESIDUAL_RATIO × the choice's)."""
    al = None
    for T in starts:
        alt = align_flies(points, weights, ref_pyramid, new_pyramid, K, T)
        if al is None or (_accepted(alt, min_inliers)
                          and (not _accepted(al, min_inliers) or alt.residual < SWITCH_RESIDUAL_RATIO * al.residual)):
            al = alt
    return al


def reverse_motion(view: ReferenceView, points, weights, new_pyramid: list[np.ndarray], K: np.ndarray,
                   min_inliers: float) -> np.ndarray | None:
    """T_new_ref found the other way round, when the motion is unknown: the new image's flies (its left
    optical frame) aligned back into ``view``'s image from the lattice's starts; None when that fails."""
    starts = coarse_candidates(points, weights, new_pyramid, view.pyramid(), K, np.eye(4), SEARCH_STARTS)
    al = best_alignment(points, weights, new_pyramid, view.pyramid(), K, starts, min_inliers)
    return invert(al.T) if _accepted(al, min_inliers) else None


def photometric_fix(view: ReferenceView, new_pyramid: list[np.ndarray], K: np.ndarray, T_map_base_pred: np.ndarray,
                    T_base_camera: np.ndarray, min_inliers: float, search: bool = False) -> tuple[Fix | None, str]:
    """Align ``view``'s flies into the new image from the predicted pose (with ``search``, when the
    motion is unknown: from the lattice search's starts around it, chosen by :func:`best_alignment`);
    (fix, '') or (None, why)."""
    T_map_cam_pred = T_map_base_pred @ T_base_camera
    T_init = invert(T_map_cam_pred) @ view.T_map_cam                 # T_new_ref
    starts = coarse_candidates(view.points, view.weights, view.pyramid(), new_pyramid, K, T_init,
                               SEARCH_STARTS) if search else [T_init]
    al = best_alignment(view.points, view.weights, view.pyramid(), new_pyramid, K, starts, min_inliers)
    if not al.ok:
        return None, al.reason
    if al.inliers < min_inliers:
        return None, f"photometric alignment has {100 * al.inliers:.0f} % inliers (< {100 * min_inliers:.0f} %)"
    T_map_cam = view.T_map_cam @ invert(al.T)
    T_map_base = T_map_cam @ invert(T_base_camera)
    # al.covariance: right perturbation ξ of T_new_ref; T_map_cam = T_map_ref · T⁻¹, so the new camera
    # moves by −Ad(T)ξ in its own frame; its position and heading errors in the map are that twist's
    # translation and rotation turned by R_map_cam (the camera-to-base lever arm is neglected).
    R = np.zeros((6, 6))
    R[:3, :3] = R[3:, 3:] = T_map_cam[:3, :3]
    A = R @ adjoint(al.T)
    cov = A @ al.covariance @ A.T
    return Fix(T_map_base, 0.5 * (cov + cov.T), al.inliers, al.residual), ""


def half_resolution_K(K: np.ndarray) -> np.ndarray:
    """Intrinsics of an image halved by cv2.pyrDown: those of photometric.pyramid's level 1."""
    Kh = np.array(K, dtype=float, copy=True)
    Kh[0, 0], Kh[1, 1], Kh[0, 2], Kh[1, 2] = level_intrinsics(K, 1)
    return Kh


def align_keyframes(old, new, K: np.ndarray, T_base_camera: np.ndarray, starts_map_base: list[np.ndarray],
                    levels: int, min_inliers: float):
    """The new keyframe's base pose in the map from the two keyframes' fly neighbourhoods (both keyframes'
    ``image``: half-resolution grey, so ``K`` is halved here and ``levels`` counts from half resolution;
    pyrDown smoothed them already, so no ``smooth_px``), from each of ``starts_map_base`` (candidate poses
    of the new keyframe; :func:`best_alignment` picks).  (T_map_base, '') or (None, why).

    Aligned both ways, the old keyframe's flies into the new image and the new keyframe's flies back
    into the old image, and the pose halfway between the two kept when both are accepted (either alone
    when only one is).  Each way rests on one keyframe's fly depths and sees the scene change scale the
    opposite way, so each errs along the view on its own side; their midpoint cancels much of it."""
    T_bc = np.asarray(T_base_camera, float)
    Kh = half_resolution_K(K)
    old_pyramid, new_pyramid = pyramid(old.image, levels), pyramid(new.image, levels)
    T_map_oldcam = old.T_map_base @ T_bc
    starts = [invert(T @ T_bc) @ T_map_oldcam for T in starts_map_base]          # T_newcam_oldcam
    forward = best_alignment(transform_points(invert(T_bc), old.points.astype(np.float64)), old.fitness,
                             old_pyramid, new_pyramid, Kh, starts, min_inliers)
    backward = best_alignment(transform_points(invert(T_bc), new.points.astype(np.float64)), new.fitness,
                              new_pyramid, old_pyramid, Kh, [invert(S) for S in starts], min_inliers)
    ways = []                   # the new keyframe's base pose in the map, as each accepted way has it
    if _accepted(forward, min_inliers):
        ways.append(T_map_oldcam @ invert(forward.T) @ invert(T_bc))
    if _accepted(backward, min_inliers):
        ways.append(T_map_oldcam @ backward.T @ invert(T_bc))
    if not ways:
        return None, f"old into new: {_refusal(forward, min_inliers)}; new into old: {_refusal(backward, min_inliers)}"
    if len(ways) == 1:
        return ways[0], ""
    return ways[0] @ scaled_motion(invert(ways[0]) @ ways[1], 0.5), ""


def _refusal(al, min_inliers: float) -> str:
    """Why an alignment was not accepted (see _accepted)."""
    return al.reason or f"{100 * al.inliers:.0f} % inliers (< {100 * min_inliers:.0f} %)"
