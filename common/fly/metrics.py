"""Accuracy of a fly population against ground-truth disparity (used by tests, benches and services).

The measure: take the fittest ``keep`` fraction of the flies; a fly is an *inlier* when its disparity
(u_left − u_right, sub-pixel) is within ``tol_px`` of the ground truth at its left projection rounded to
the nearest pixel.  Kept flies whose ground truth is unknown (inf/NaN) are *skipped* — removed from both
numerator and denominator.  Kept flies that project outside the image or lie behind the camera count as
outliers (they are part of the answer and are wrong).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.camera import StereoCalibration


@dataclass
class InlierStats:
    fraction: float   # inliers / counted (NaN when nothing was counted)
    kept: int         # flies in the fittest `keep` fraction
    counted: int      # kept flies with a known ground truth (or outside the image)
    inliers: int
    skipped_unknown_gt: int


def inlier_stats(positions: np.ndarray, fitness: np.ndarray, calib: StereoCalibration,
                 gt_disparity: np.ndarray, keep: float = 0.8, tol_px: float = 1.0) -> InlierStats:
    pos = np.asarray(positions, dtype=np.float64)
    fit = np.asarray(fitness, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 3 or fit.shape != (len(pos),):
        raise ValueError(f"positions must be (N, 3) and fitness (N,), got {pos.shape} and {fit.shape}")
    if not 0 < keep <= 1:
        raise ValueError(f"keep must be in (0, 1], got {keep}")
    gt = np.asarray(gt_disparity)
    if gt.shape != (calib.height, calib.width):
        raise ValueError(f"gt_disparity is {gt.shape}, calibration is {calib.height}×{calib.width}")
    n_keep = int(np.ceil(keep * len(pos)))
    order = np.argsort(-np.nan_to_num(fit, nan=-np.inf), kind="stable")[:n_keep]
    ul, ur, v = calib.project(pos[order])
    d = ul - ur
    with np.errstate(invalid="ignore"):
        iu, iv = np.floor(ul + 0.5), np.floor(v + 0.5)
        inside = (iu >= 0) & (iu < calib.width) & (iv >= 0) & (iv < calib.height) & np.isfinite(d)
    g = np.full(n_keep, np.nan)
    g[inside] = gt[iv[inside].astype(int), iu[inside].astype(int)]
    unknown = inside & ~np.isfinite(g)
    good = inside & np.isfinite(g) & (np.abs(d - np.where(np.isfinite(g), g, 0)) <= tol_px)
    counted = n_keep - int(unknown.sum())
    return InlierStats(float(good.sum() / counted) if counted else float("nan"), n_keep, counted,
                       int(good.sum()), int(unknown.sum()))


def inlier_fraction(positions: np.ndarray, fitness: np.ndarray, calib: StereoCalibration,
                    gt_disparity: np.ndarray, keep: float = 0.8, tol_px: float = 1.0) -> float:
    """Fraction of the fittest ``keep`` flies within ``tol_px`` of the ground-truth disparity."""
    return inlier_stats(positions, fitness, calib, gt_disparity, keep, tol_px).fraction
