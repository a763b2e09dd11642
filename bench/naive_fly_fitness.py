"""Reference fly fitness in plain numpy fancy indexing — the yardstick for the numba kernel.

Computes exactly what ``common.fly.fitness.image_fitness`` computes in its default mode (left window at
the nearest pixel, right window at the exact sub-pixel disparity, linear along the epipolar line; the same
window weights, noise floor and gradient normaliser G), but by gathering an (N, n², C) block of samples.
"""
from __future__ import annotations

import numpy as np

from common.camera import StereoCalibration
from common.fly.fitness import PreparedFrame


def naive_fitness(frame: PreparedFrame, calib: StereoCalibration, positions: np.ndarray) -> np.ndarray:
    L, R, G = frame.left, frame.right, frame.gradient_norm
    H, W, C = L.shape
    n = frame.weights.shape[0]
    h = n // 2
    p = np.asarray(positions, np.float64)
    z = p[:, 2]
    ok = z > 0
    zs = np.where(ok, z, 1.0)
    ul = calib.fx * p[:, 0] / zs + calib.cx_left
    ur = calib.fx * (p[:, 0] - calib.baseline) / zs + calib.cx_right
    v = calib.fy * p[:, 1] / zs + calib.cy
    xn = np.floor(ul + 0.5)
    xs = ur - (ul - xn)
    xr0 = np.floor(xs)
    yn = np.floor(v + 0.5)
    ok &= (np.floor(ul) >= h) & (np.floor(ul) <= W - 2 - h) & (np.floor(ur) >= h) & (np.floor(ur) <= W - 2 - h)
    ok &= (np.floor(v) >= h) & (np.floor(v) <= H - 2 - h) & (xn <= W - 1 - h) & (xr0 >= h) & (xr0 <= W - 2 - h)
    ok &= yn + h <= H - 1
    out = np.full(len(p), -np.inf, np.float32)
    idx = np.nonzero(ok)[0]
    if len(idx) == 0:
        return out
    dy, dx = np.mgrid[-h:h + 1, -h:h + 1]
    dy, dx = dy.ravel(), dx.ravel()
    yy = yn[idx, None].astype(np.int64) + dy                     # (M, n²)
    xl = xn[idx, None].astype(np.int64) + dx
    xr = xr0[idx, None].astype(np.int64) + dx
    bx = (xs[idx] - xr0[idx]).astype(np.float32)[:, None, None]
    left = L[yy, xl]                                               # (M, n², C)
    r0, r1 = R[yy, xr], R[yy, xr + 1]
    diff = left - (r0 + bx * (r1 - r0))
    msd = np.einsum("mkc,k->m", diff * diff, frame.weights.ravel())
    g = G[yn[idx].astype(np.int64), xn[idx].astype(np.int64)]
    out[idx] = g / (1.0 + msd * np.float32(frame.inv_floor))
    return out
