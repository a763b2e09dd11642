"""Occupancy evidence grid for the harmonic planner: flies and sonar returns in, obstacles out.

Evidence per cell is a decaying, capped sum of weights.  Flies count only in the robot's height band and
weigh their fitness, normalised by the mean positive fitness of the update (so the scale of the fitness
function does not matter and an average fly weighs 1).  Sonar returns weigh ``sonar_weight`` each.  All
evidence halves every ``evidence_half_life_s`` of stamp time, so cells whose flies moved away are freed.
"""
from __future__ import annotations

import cv2
import numpy as np

from .config import PlannerConfig, PlannerInputError


class EvidenceGrid:
    def __init__(self, config: PlannerConfig):
        self.cfg = config
        self.shape = config.shape
        self.evidence = np.zeros(self.shape, dtype=np.float32)
        self.stamp_ns: int | None = None
        self.version = 0          # bumped on every change, so the planner knows when to re-derive

    # -- input ---------------------------------------------------------------------------------------
    def _decay_to(self, stamp_ns: int) -> None:
        stamp_ns = int(stamp_ns)
        if self.stamp_ns is not None and stamp_ns > self.stamp_ns:
            dt = (stamp_ns - self.stamp_ns) * 1e-9
            self.evidence *= np.float32(0.5 ** (dt / self.cfg.evidence_half_life_s))
        # Out-of-order messages (older stamp) are added without decaying, and never move the clock back.
        if self.stamp_ns is None or stamp_ns > self.stamp_ns:
            self.stamp_ns = stamp_ns

    def cells_of(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(row, col, inside) of map-frame (N, 2) points."""
        res = self.cfg.resolution
        col = np.floor((xy[:, 0] - self.cfg.origin[0]) / res).astype(np.int64)
        row = np.floor((xy[:, 1] - self.cfg.origin[1]) / res).astype(np.int64)
        inside = (row >= 0) & (row < self.shape[0]) & (col >= 0) & (col < self.shape[1])
        return row, col, inside

    def _add(self, xy: np.ndarray, weights: np.ndarray) -> None:
        row, col, inside = self.cells_of(xy)
        if inside.any():
            flat = row[inside] * self.shape[1] + col[inside]
            add = np.bincount(flat, weights=weights[inside], minlength=self.evidence.size)
            self.evidence += add.reshape(self.shape).astype(np.float32)
        np.minimum(self.evidence, np.float32(self.cfg.evidence_cap), out=self.evidence)
        self.version += 1

    def add_flies(self, points_map, fitness, stamp_ns: int) -> int:
        """Add flies ((N, 3) map-frame points, (N,) fitness).  Returns how many fell in the height band
        and inside the grid."""
        pts = np.asarray(points_map, dtype=np.float64)
        fit = np.asarray(fitness, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise PlannerInputError(f"fly points must be (N, 3) map-frame points, got shape {pts.shape}")
        if fit.shape != (pts.shape[0],):
            raise PlannerInputError(f"fitness must be ({pts.shape[0]},) to match the points, got {fit.shape}")
        self._decay_to(stamp_ns)
        ok = np.isfinite(pts).all(axis=1) & np.isfinite(fit) & (fit > 0)
        ok &= (pts[:, 2] >= self.cfg.fly_z_min) & (pts[:, 2] <= self.cfg.fly_z_max)
        if not ok.any():
            self.version += 1
            return 0
        w = fit[ok] / fit[ok].mean()
        self._add(pts[ok, :2], w)
        return int(self.cells_of(pts[ok, :2])[2].sum())

    def add_sonar(self, points_xy, stamp_ns: int) -> None:
        """Add sonar returns ((M, 2) map-frame points of the echoes)."""
        pts = np.asarray(points_xy, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise PlannerInputError(f"sonar points must be (M, 2) map-frame x, y, got shape {pts.shape}")
        self._decay_to(stamp_ns)
        ok = np.isfinite(pts).all(axis=1)
        self._add(pts[ok], np.full(int(ok.sum()), self.cfg.sonar_weight))

    # -- output --------------------------------------------------------------------------------------
    def occupied(self) -> np.ndarray:
        return self.evidence >= self.cfg.occupied_weight

    def clearance_m(self, occupied: np.ndarray) -> np.ndarray:
        """Distance (m) from every cell centre to the nearest occupied cell centre (large if none)."""
        if not occupied.any():
            return np.full(self.shape, np.float32(1e6))
        free = np.ascontiguousarray((~occupied).astype(np.uint8))
        return cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * np.float32(self.cfg.resolution)
