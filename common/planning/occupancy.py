"""Occupancy evidence grid for the harmonic planner: flies and sonar returns in, obstacles out.

Evidence per cell is a decaying, capped sum of weights.  Flies count only in the robot's height band and
weigh their fitness, normalised by the mean positive fitness of the update (so the scale of the fitness
function does not matter and an average fly weighs 1).  Sonar returns weigh ``sonar_weight`` each.  A cell
is occupied when its fly and sonar evidence together reach ``occupied_weight``.

Sonar evidence halves every ``evidence_half_life_s`` of stamp time.  Fly evidence does too when a population
comes without a :class:`SensorView`; with one, it is forgotten at that rate only inside the view (a cell the
camera sees and no fly lands on is free) and at ``unseen_half_life_s`` outside it, so obstacles that left
the view (the walls beside the robot) stay in the map instead of opening gaps behind the camera.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from .config import SensorView, PlannerConfig, PlannerInputError


class _DecayingLayer:
    """One kind of evidence with its own stamp clock."""

    def __init__(self, shape):
        self.values = np.zeros(shape, dtype=np.float32)
        self.stamp_ns: int | None = None

    def elapsed_s(self, stamp_ns: int) -> float:
        """Seconds since the layer's clock, which then moves to ``stamp_ns``.  Out-of-order messages (older
        stamp) get 0 (added without decaying) and never move the clock back."""
        stamp_ns = int(stamp_ns)
        dt = 0.0
        if self.stamp_ns is not None and stamp_ns > self.stamp_ns:
            dt = (stamp_ns - self.stamp_ns) * 1e-9
        if self.stamp_ns is None or stamp_ns > self.stamp_ns:
            self.stamp_ns = stamp_ns
        return dt


class EvidenceGrid:
    def __init__(self, config: PlannerConfig):
        self.cfg = config
        self.shape = config.shape
        self._flies = _DecayingLayer(self.shape)
        self._sonar = _DecayingLayer(self.shape)
        self.version = 0          # bumped on every change, so the planner knows when to re-derive
        h, w = self.shape
        res = config.resolution
        self._xs = (config.origin[0] + (np.arange(w) + 0.5) * res)[None, :]
        self._ys = (config.origin[1] + (np.arange(h) + 0.5) * res)[:, None]

    @property
    def evidence(self) -> np.ndarray:
        """(H, W) fly + sonar evidence per cell."""
        return self._flies.values + self._sonar.values

    # -- input ---------------------------------------------------------------------------------------
    def view_mask(self, view: SensorView) -> np.ndarray:
        """(H, W) bool: cells whose centre lies in the view's ground wedge (near_m..range_m, +-half_fov)."""
        dx, dy = self._xs - view.x, self._ys - view.y
        d2 = dx * dx + dy * dy
        inside = (d2 <= view.range_m ** 2) & (d2 >= view.near_m ** 2)
        if view.half_fov_rad >= np.pi:
            return inside
        along = dx * np.cos(view.yaw) + dy * np.sin(view.yaw)
        return inside & (along > 0) & (along * along >= d2 * np.cos(view.half_fov_rad) ** 2)

    def _decay(self, layer: _DecayingLayer, stamp_ns: int, view: SensorView | None) -> None:
        """Age a layer to ``stamp_ns``: everywhere at evidence_half_life_s without a view; with one, at that
        rate inside it and at unseen_half_life_s outside."""
        if view is not None and not isinstance(view, SensorView):
            raise PlannerInputError(f"view must be a SensorView or None, got {type(view).__name__}")
        dt = layer.elapsed_s(stamp_ns)
        if dt <= 0:
            return
        seen = np.float32(0.5 ** (dt / self.cfg.evidence_half_life_s))
        if view is None:
            layer.values *= seen
            return
        unseen = np.float32(0.5 ** (dt / self.cfg.unseen_half_life_s))
        layer.values *= np.where(self.view_mask(view), seen, unseen)

    def cells_of(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(row, col, inside) of map-frame (N, 2) points."""
        res = self.cfg.resolution
        col = np.floor((xy[:, 0] - self.cfg.origin[0]) / res).astype(np.int64)
        row = np.floor((xy[:, 1] - self.cfg.origin[1]) / res).astype(np.int64)
        inside = (row >= 0) & (row < self.shape[0]) & (col >= 0) & (col < self.shape[1])
        return row, col, inside

    def _add(self, layer: _DecayingLayer, xy: np.ndarray, weights: np.ndarray, cell_cap: float | None = None,
             scale: float = 1.0) -> None:
        """Add ``weights`` at the cells of ``xy``: per cell at most ``cell_cap`` (None: no limit), then
        times ``scale``."""
        row, col, inside = self.cells_of(xy)
        if inside.any():
            flat = row[inside] * self.shape[1] + col[inside]
            add = np.bincount(flat, weights=weights[inside], minlength=layer.values.size)
            if cell_cap is not None:
                np.minimum(add, cell_cap, out=add)
            layer.values += (scale * add).reshape(self.shape).astype(np.float32)
        np.minimum(layer.values, np.float32(self.cfg.evidence_cap), out=layer.values)
        self.version += 1

    def add_flies(self, points_map, fitness, stamp_ns: int, view: SensorView | None = None,
                  weight: float = 1.0, cell_cap: float | None = None) -> int:
        """Add flies ((N, 3) map-frame points, (N,) fitness).  ``view``: where the camera looked (see the
        module docstring); without it all fly evidence decays alike.  ``weight`` scales this population's
        evidence (how new its viewpoint is).  ``cell_cap``: the most evidence this population adds to one
        cell before ``weight`` (None: no limit); below ``occupied_weight`` it takes two views to make an
        obstacle.  Returns how many flies fell in the height band and inside the grid."""
        if cell_cap is not None and not (math.isfinite(cell_cap) and cell_cap > 0):
            raise PlannerInputError(f"cell_cap must be a positive number or None, got {cell_cap!r}")
        pts = np.asarray(points_map, dtype=np.float64)
        fit = np.asarray(fitness, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise PlannerInputError(f"fly points must be (N, 3) map-frame points, got shape {pts.shape}")
        if fit.shape != (pts.shape[0],):
            raise PlannerInputError(f"fitness must be ({pts.shape[0]},) to match the points, got {fit.shape}")
        self._decay(self._flies, stamp_ns, view)
        ok = np.isfinite(pts).all(axis=1) & np.isfinite(fit) & (fit > 0)
        ok &= (pts[:, 2] >= self.cfg.fly_z_min) & (pts[:, 2] <= self.cfg.fly_z_max)
        if not ok.any():
            self.version += 1
            return 0
        self._add(self._flies, pts[ok, :2], fit[ok] / fit[ok].mean(), cell_cap, float(weight))
        return int(self.cells_of(pts[ok, :2])[2].sum())

    def add_sonar(self, points_xy, stamp_ns: int, view: SensorView | None = None) -> None:
        """Add sonar returns ((M, 2) map-frame points of the echoes; M may be 0).  ``view``: the region the
        scan observed (a disc around the robot for a sonar ring), as for the flies."""
        pts = np.asarray(points_xy, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise PlannerInputError(f"sonar points must be (M, 2) map-frame x, y, got shape {pts.shape}")
        self._decay(self._sonar, stamp_ns, view)
        ok = np.isfinite(pts).all(axis=1)
        self._add(self._sonar, pts[ok], np.full(int(ok.sum()), self.cfg.sonar_weight))

    # -- output --------------------------------------------------------------------------------------
    def occupied(self) -> np.ndarray:
        return self.evidence >= np.float32(self.cfg.occupied_weight)

    def clearance_m(self, occupied: np.ndarray) -> np.ndarray:
        """Distance (m) from every cell centre to the nearest occupied cell centre (large if none)."""
        if not occupied.any():
            return np.full(self.shape, np.float32(1e6))
        free = np.ascontiguousarray((~occupied).astype(np.uint8))
        return cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * np.float32(self.cfg.resolution)
