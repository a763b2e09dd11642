"""Drawing fresh flies (initialisation and immigration) inside both cameras' fields of view.

A fly is drawn with its inverse depth 1/z uniform in [1/depth_max, 1/depth_min] (restricted to depths at
which the two fields of view overlap at all), then a left-image position uniform over the part of the
image whose point at that depth is also seen by the right camera — i.e. uniform over the cross-section of
the FOV intersection at that depth.  ``margin`` keeps the N×N window inside both images.
"""
from __future__ import annotations

import numpy as np

from common.camera import StereoCalibration


class SamplingError(ValueError):
    """No fly can be drawn: the depth range and the image margin leave no common field of view."""


def disparity_bounds(calib: StereoCalibration, depth_min: float, depth_max: float) -> tuple[float, float]:
    """Pixel disparities (low, high) of depth_max and depth_min (depth_max may be inf)."""
    fb = calib.fx * calib.baseline
    return fb / depth_max - calib.doffs, fb / depth_min - calib.doffs


def sample_flies(calib: StereoCalibration, n: int, depth_min: float, depth_max: float,
                 rng: np.random.Generator, margin: float = 0.0) -> np.ndarray:
    """(n, 3) float32 left-optical points, 1/z uniform, inside both images with ``margin`` pixels spare."""
    fb = calib.fx * calib.baseline
    W, H = calib.width, calib.height
    lo_px, hi_px = margin, W - 1 - margin          # admissible u range in both images
    if hi_px <= lo_px or H - 1 - 2 * margin <= 0:
        raise SamplingError(f"margin {margin} px leaves no room in a {W}×{H} image")
    d_lo, d_hi = disparity_bounds(calib, depth_min, depth_max)
    # u_right = u_left − d must fit in [lo_px, hi_px] as well: |d| < hi_px − lo_px.
    span = hi_px - lo_px
    d_lo_ok, d_hi_ok = max(d_lo, -span), min(d_hi, span)
    if d_hi_ok <= d_lo_ok:
        raise SamplingError(
            f"depth range [{depth_min}, {depth_max}] m gives disparities [{d_lo:.1f}, {d_hi:.1f}] px, "
            f"none of which is seen by both {W}-px-wide cameras")
    iz_lo, iz_hi = (d_lo_ok + calib.doffs) / fb, (d_hi_ok + calib.doffs) / fb
    # depth_max = inf: 1/z may be drawn as 0; keep flies finite (at most ~10⁶ times the nearest depth).
    iz = np.maximum(rng.uniform(iz_lo, iz_hi, n), 1e-6 * iz_hi)
    d = fb * iz - calib.doffs
    u_min = np.maximum(lo_px, lo_px + d)
    u_max = np.minimum(hi_px, hi_px + d)
    u = u_min + rng.random(n) * (u_max - u_min)
    v = rng.uniform(margin, H - 1 - margin, n)
    z = 1.0 / iz
    x = (u - calib.cx_left) * z / calib.fx
    y = (v - calib.cy) * z / calib.fy
    return np.stack([x, y, z], axis=1).astype(np.float32)
