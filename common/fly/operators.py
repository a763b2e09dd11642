"""Genetic operators and 2-D sharing of the Fly algorithm, vectorised over whole batches of flies.

Flies are 3-D points, but mutation works in (u_left, v, disparity) — the coordinates in which stereo
uncertainty is isotropic-ish — so that a Gaussian step has the same meaning near and far.
"""
from __future__ import annotations

import numpy as np

from common.camera import StereoCalibration


def project_uvd(calib: StereoCalibration, positions: np.ndarray):
    """(u_left, v, disparity) float32 arrays of (N, 3) points; NaN for points with z ≤ 0."""
    p = np.asarray(positions, dtype=np.float32)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        iz = np.where(z > 0, np.float32(1.0) / z, np.float32(np.nan))
        u = np.float32(calib.fx) * p[:, 0] * iz + np.float32(calib.cx_left)
        v = np.float32(calib.fy) * p[:, 1] * iz + np.float32(calib.cy)
        d = np.float32(calib.fx * calib.baseline) * iz - np.float32(calib.doffs)
    return u, v, d


def backproject_uvd(calib: StereoCalibration, u, v, d) -> np.ndarray:
    """(N, 3) float32 points from left pixel (u, v) and pixel disparity d (d + doffs must be > 0)."""
    with np.errstate(divide="ignore"):
        z = np.float32(calib.fx * calib.baseline) / (np.asarray(d, np.float32) + np.float32(calib.doffs))
    x = (np.asarray(u, np.float32) - np.float32(calib.cx_left)) * z / np.float32(calib.fx)
    y = (np.asarray(v, np.float32) - np.float32(calib.cy)) * z / np.float32(calib.fy)
    return np.stack([x, y, z], axis=1).astype(np.float32, copy=False)


def mutate(calib: StereoCalibration, positions: np.ndarray, sigma_px: float, sigma_d: np.ndarray,
           d_range: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """Gaussian mutation: left pixel moves by N(0, sigma_px²) per axis, disparity by N(0, sigma_d²)
    (per fly), disparity clipped to ``d_range``.  Returns new (N, 3) float32 points."""
    u, v, d = project_uvd(calib, positions)
    n = len(u)
    u = u + rng.standard_normal(n, dtype=np.float32) * np.float32(sigma_px)
    v = v + rng.standard_normal(n, dtype=np.float32) * np.float32(sigma_px)
    d = d + rng.standard_normal(n, dtype=np.float32) * np.asarray(sigma_d, np.float32)
    d = np.clip(d, d_range[0], d_range[1])
    return backproject_uvd(calib, u, v, d)


def crossover2(p1: np.ndarray, p2: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Barycentric 2-parent crossover: λ·p1 + (1 − λ)·p2, λ ~ U(0, 1) — children on the parents' segment
    (so a population on a straight edge fills it in)."""
    lam = rng.random((len(p1), 1), dtype=np.float32)
    return (lam * p1 + (1 - lam) * p2).astype(np.float32, copy=False)


def crossover3(p1: np.ndarray, p2: np.ndarray, p3: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Barycentric 3-parent crossover with weights uniform on the simplex — children in the parents'
    triangle, hence in their plane (a population on a planar surface fills it in)."""
    w = rng.dirichlet((1.0, 1.0, 1.0), len(p1)).astype(np.float32)
    return (w[:, :1] * p1 + w[:, 1:2] * p2 + w[:, 2:] * p3).astype(np.float32, copy=False)


class SharingGrid:
    """2-D fitness sharing over square cells of the left image.

    A fly in a cell holding ``count`` flies where ``expected`` would be the even share has its fitness
    divided by ``1 + strength · max(0, count/expected − 1)`` (negative fitness is multiplied instead), so
    crowded image areas lose selection pressure and flies spread over the whole image.
    """

    def __init__(self, width: int, height: int, cell_px: float, strength: float):
        if not cell_px > 0:
            raise ValueError(f"sharing cell size must be positive, got {cell_px}")
        self.cell = float(cell_px)
        self.cols = int(np.ceil(width / self.cell))
        self.rows = int(np.ceil(height / self.cell))
        self.strength = float(strength)
        self.counts = np.zeros(self.cols * self.rows, np.int64)
        self.expected = 1.0

    def cells(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Cell index per fly; −1 for flies outside the image (or NaN)."""
        cu = np.floor(np.asarray(u, np.float64) / self.cell)
        cv = np.floor(np.asarray(v, np.float64) / self.cell)
        ok = (cu >= 0) & (cu < self.cols) & (cv >= 0) & (cv < self.rows)
        idx = np.full(len(cu), -1, np.int64)
        idx[ok] = cv[ok].astype(np.int64) * self.cols + cu[ok].astype(np.int64)
        return idx

    def update(self, cells: np.ndarray) -> None:
        inside = cells[cells >= 0]
        self.counts = np.bincount(inside, minlength=self.cols * self.rows)
        self.expected = max(len(inside) / (self.cols * self.rows), 1e-9)

    def factor(self, cells: np.ndarray, extra: np.ndarray | int = 0) -> np.ndarray:
        """Crowding divisor (≥ 1) of flies in ``cells`` (with ``extra`` flies added to their count)."""
        c = np.where(cells >= 0, self.counts[np.maximum(cells, 0)] + extra, 0)
        return (1.0 + self.strength * np.maximum(0.0, c / self.expected - 1.0)).astype(np.float32)

    @staticmethod
    def apply(fitness: np.ndarray, factor: np.ndarray) -> np.ndarray:
        f = np.asarray(fitness, np.float32)
        return np.where(f > 0, f / factor, f * factor).astype(np.float32, copy=False)
