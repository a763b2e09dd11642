"""Relocalisation: find a population's pose in a known fly map when nothing says where the robot is.

Global search, no I/O (LocaliserCore runs it while it is "relocalising"):

1. rank the keyframes by a layout descriptor (the flies' plan view, a fitness-weighted forward ×
   lateral histogram, compared by cosine under a lattice of robot-from-keyframe offsets); in a
   corridor every view looks much alike, so it only chooses which ``candidates`` to search on a
   large map;
2. register the flies with the localiser's own δ (``register_planar``, planar, stereo model) around
   each candidate keyframe's pose over ``window`` (the windows tile the mapped path; a minimum on a
   window's edge moves it, ``chase`` times), against one voxel-thinned merge of the map for the whole
   search; every distinct answer is re-scored with the window closed, so answers from different
   guesses compare;
3. accept only a clear, confirmed answer: the best (lowest δ) is an interior, unambiguous minimum; no
   other answer comes within ``rival_margin`` × |δ| of it, nor a registration stopped on a window
   edge, nor the best itself moved ``pin_check_m`` along its view (walls do not pin the position
   along a corridor and far structure pins it loosely: δ has a flat valley or a second basin there);
   and the same pose wins ``confirmations`` + 1 searches in a row (the previous best, carried by
   odometry, is searched from too; a restart's hint agreeing confirms at once).  δ has secondary
   minima a box or a door further on and which one wins flips while the flies settle: one wrong
   pose poisons every keyframe after it, while waiting costs frames.

Only populations evolved ``min_generations`` are used: younger flies are still biased in depth, which
moves the answer along the line of sight.  Map keyframes keep no images, so the search uses geometry
only; photometric tracking restarts from the found pose (FlyLocaliser.relocalised).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.ndimage

from common.geometry import invert, planar_from_transform, planar_pose, transform_points, wrap_angle
from common.registration import PopulationError, register_planar
from common.slam.localiser import voxel_thin


@dataclass
class RelocaliserConfig:
    candidates: int = 10                 # best-ranked keyframes whose poses are searched around
    reach_m: float = 12.0                # map points this near a guess (and not behind it) are registered against
    voxel_m: float = 0.04                # the merged map is thinned to one point per voxel
    map_points: int = 8000               # ... and each guess's part of it subsampled to this many
    window: tuple = (1.0, 0.5, np.deg2rad(15.0))    # δ half-widths around a keyframe's pose
    hint_window: tuple = (0.6, 0.6, np.deg2rad(12.0))   # ... around a hinted pose (a restart)
    hint_frames: int = 10                # searches near a hint before the whole map is searched
    lattice: tuple = (7, 7, 7)
    chase: int = 2                       # re-centrings on a window-edge minimum
    offsets_x: tuple = (-1.5, 1.5, 0.5)  # descriptor lattice of robot-in-keyframe offsets: forward (m) ...
    offsets_y: tuple = (-0.5, 0.5, 0.25)     # ... lateral (m) ...
    offsets_yaw: tuple = (-np.deg2rad(20.0), np.deg2rad(20.0), np.deg2rad(5.0))   # ... and heading (rad)
    bin_m: tuple = (0.5, 0.25)           # descriptor cells: forward, lateral (m)
    extent_m: tuple = (10.0, 4.0)        # descriptor covers forward 0..10 m, lateral ±4 m
    agree_m: float = 0.15                # two answers this near ...
    agree_rad: float = np.deg2rad(2.0)   # ... and this aligned are the same pose
    confirm_rad: float = np.deg2rad(5.0)   # ... the previous answer carried by odometry may differ this much in
                                           # heading (a wheel-slip burst turns odometry by degrees in a frame)
    rival_margin: float = 0.15           # an answer elsewhere must be worse than the best by this × |δ|
    pin_check_m: float = 0.6             # the best must also beat itself moved this far along its view
    confirmations: int = 2               # ... and the same pose must win this many more searches in a row
    min_generations: int = 250           # younger populations are not searched with (see the module doc)
    confirm_gap_s: float = 0.5           # without odometry, the previous answer confirms only this soon after
    min_flies: int = 150
    eps: float = 0.05


PREVIOUS = -1


@dataclass
class Candidate:
    keyframe_id: int                     # PREVIOUS: the previous search's answer
    score: float                         # descriptor cosine
    T_guess: np.ndarray
    T_map_base: np.ndarray | None = None
    delta: float = float("nan")
    reason: str = ""                     # '' when the registration is usable


@dataclass
class Relocalisation:
    T_map_base: np.ndarray | None        # None: not relocalised (see reason)
    reason: str                          # why not, or how it was confirmed
    keyframe_id: int | None = None
    delta: float = float("nan")
    candidates: list = field(default_factory=list)
    best: np.ndarray | None = None       # the best answer, accepted or not (the next search's ``previous``)
    streak: int = 0                      # searches in a row whose best agreed with the previous one


def _descriptor_grid(cfg: RelocaliserConfig):
    nx = int(round(cfg.extent_m[0] / cfg.bin_m[0]))
    ny = int(round(2 * cfg.extent_m[1] / cfg.bin_m[1]))
    return nx, ny


def _histograms(points_xy: np.ndarray, weights: np.ndarray, cfg: RelocaliserConfig) -> np.ndarray:
    """Descriptors of (H, N, 2) plan-view point sets: (H, nx·ny) unit vectors (zeros when empty)."""
    nx, ny = _descriptor_grid(cfg)
    H = points_xy.shape[0]
    ix = np.floor(points_xy[..., 0] / cfg.bin_m[0]).astype(np.int64)
    iy = np.floor((points_xy[..., 1] + cfg.extent_m[1]) / cfg.bin_m[1]).astype(np.int64)
    inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    cell = np.arange(H)[:, None] * (nx * ny) + ix * ny + iy
    w = np.broadcast_to(weights, inside.shape)
    hist = np.bincount(cell[inside], weights=w[inside], minlength=H * nx * ny).reshape(H, nx, ny)
    hist = scipy.ndimage.gaussian_filter(np.sqrt(hist), sigma=(0, 0.7, 0.7), mode="constant")
    flat = hist.reshape(H, -1)
    norm = np.linalg.norm(flat, axis=1, keepdims=True)
    return np.where(norm > 0, flat / np.where(norm > 0, norm, 1.0), 0.0)


def _offsets(cfg: RelocaliserConfig) -> np.ndarray:
    axes = [np.arange(lo, hi + 0.5 * step, step) for lo, hi, step in (cfg.offsets_x, cfg.offsets_y, cfg.offsets_yaw)]
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([m.ravel() for m in mesh], 1)


class Relocaliser:
    """Global search of populations against one map's keyframes (see the module docstring).  The
    keyframes' descriptors are computed once; a map whose keyframes moved (the back-end optimised
    them) only changes their poses, which are read at each search."""

    def __init__(self, keyframes, config: RelocaliserConfig | None = None, stereo=None, seed: int = 0):
        self.config = config or RelocaliserConfig()
        self.keyframes = [kf for kf in keyframes if len(kf.points) > 0]
        self.stereo = stereo
        self._rng = np.random.default_rng(seed)
        self._seed = seed
        self._offsets = _offsets(self.config)
        pts = [kf.points_map for kf in self.keyframes]
        fit = [kf.fitness for kf in self.keyframes]
        self._map_points = (voxel_thin(np.concatenate(pts).astype(np.float64), np.concatenate(fit), self.config.voxel_m)[0]
                            if pts else np.zeros((0, 3)))
        if self.keyframes:
            self._descriptors = np.concatenate([
                _histograms(kf.points[None, :, :2].astype(np.float64), weights_of(kf.fitness), self.config) for kf in self.keyframes])
        else:
            self._descriptors = np.zeros((0, int(np.prod(_descriptor_grid(self.config)))))

    # --------------------------------------------------------------------------------- ranking
    def rank(self, points: np.ndarray, fitness: np.ndarray) -> list[Candidate]:
        """The ``candidates`` keyframes whose view the flies' layout resembles most (each scored at its
        best offset), best first; each guesses its own pose."""
        if not self.keyframes:
            return []
        off = self._offsets
        co, so = np.cos(off[:, 2]), np.sin(off[:, 2])
        # the robot's flies seen from the keyframe, for each offset: R(yaw) p + t
        px = co[:, None] * points[None, :, 0] - so[:, None] * points[None, :, 1] + off[:, 0:1]
        py = so[:, None] * points[None, :, 0] + co[:, None] * points[None, :, 1] + off[:, 1:2]
        q = _histograms(np.stack([px, py], -1), weights_of(fitness), self.config)     # (H, B)
        scores = (self._descriptors @ q.T).max(axis=1)                                # (K,)
        best = np.argsort(-scores, kind="stable")[: self.config.candidates]
        return [Candidate(self.keyframes[k].id, float(scores[k]), self.keyframes[k].T_map_base.copy()) for k in best]

    def near(self, T_hint: np.ndarray) -> list[Candidate]:
        """The keyframe nearest to a hinted pose (within ``reach_m``), guessing the hint itself."""
        d = [float(np.hypot(*(kf.T_map_base[:2, 3] - T_hint[:2, 3]))) for kf in self.keyframes]
        k = int(np.argmin(d))
        return [Candidate(self.keyframes[k].id, -d[k], np.asarray(T_hint, float).copy())] if d[k] < self.config.reach_m else []

    # ------------------------------------------------------------------------------ registering
    def _search_map(self, guesses: list[np.ndarray]) -> np.ndarray:
        """The map points (map frame) within ``reach_m`` of any guess, subsampled to ``map_points``."""
        c = self.config
        near = np.zeros(len(self._map_points), bool)
        for T in guesses:
            near |= np.hypot(*(self._map_points[:, :2] - T[:2, 3]).T) < c.reach_m
        pts = self._map_points[near]
        if len(pts) > c.map_points:
            pts = pts[np.random.default_rng(self._seed).choice(len(pts), c.map_points, replace=False)]
        return pts

    def _register(self, points, fitness, B_map: np.ndarray, T_guess: np.ndarray, window):
        """(T_map_base or None, δ, reason) of registering the flies against ``B_map`` around
        ``T_guess``; a minimum on the window's edge moves the guess there and registers again
        (``chase`` times)."""
        c = self.config
        for _ in range(c.chase + 1):
            try:
                res = register_planar(points, transform_points(invert(T_guess), B_map), plane="body",
                                      window=tuple(window), eps=c.eps, weights_a=weights_of(fitness),
                                      stereo=self.stereo, seed=self._seed, lattice=c.lattice, curvature=False)
            except PopulationError as e:
                return None, float("nan"), str(e)
            if not np.all(np.isfinite(res.params)):
                return None, float(res.delta), res.reason or "registration failed"
            T = T_guess @ invert(planar_pose(*res.params))
            if res.ok:
                return T, float(res.delta), ""
            if not res.reason.startswith("minimum on the search window boundary"):
                return None, float(res.delta), res.reason
            T_guess = T
        return None, float(res.delta), res.reason

    def _score(self, points, fitness, B_map: np.ndarray, T: np.ndarray) -> float:
        """δ of the flies against the map seen from ``T`` (the window closed): one objective for all."""
        res = register_planar(points, transform_points(invert(T), B_map), plane="body", window=(0.0, 0.0, 0.0),
                              eps=self.config.eps, weights_a=weights_of(fitness), stereo=self.stereo,
                              seed=self._seed, lattice=(1, 1, 1), curvature=False)
        return float(res.delta)

    # ----------------------------------------------------------------------------------- search
    def search(self, points: np.ndarray, fitness: np.ndarray, hint: np.ndarray | None = None,
               previous: np.ndarray | None = None, streak: int = 0) -> Relocalisation:
        """Pose of a population (``points`` (M, 3) in base_link, ``fitness`` (M,)) in the map, or None
        with the reason.  ``hint``: a pose near which to search (restart); ``previous``: the previous
        search's best answer carried to this frame by odometry (searched from too), which ``streak``
        searches in a row had already agreed with (see ``confirmations``)."""
        c = self.config
        points = np.asarray(points, np.float64)
        fitness = np.asarray(fitness, np.float64)
        if not self.keyframes:
            return Relocalisation(None, "the map has no keyframes")
        if len(points) < c.min_flies:
            return Relocalisation(None, f"{len(points)} usable flies (< {c.min_flies})")
        if hint is not None:
            cands, window = self.near(hint), c.hint_window
            if not cands:
                return Relocalisation(None, f"the hinted pose is farther than {c.reach_m} m from the map")
        else:
            cands, window = self.rank(points, fitness), c.window
        if previous is not None:
            cands.append(Candidate(PREVIOUS, float("nan"), np.asarray(previous, float).copy()))
        B_map = self._search_map([k.T_guess for k in cands])
        if len(B_map) < c.min_flies:
            return Relocalisation(None, f"{len(B_map)} map points near the guesses", candidates=cands)
        for cand in cands:
            cand.T_map_base, cand.delta, cand.reason = self._register(points, fitness, B_map, cand.T_guess, window)
        answers = [k for k in cands if k.T_map_base is not None]
        if not answers:
            why = cands[0].reason if cands else "no candidate"
            return Relocalisation(None, f"no candidate registered ({why})", candidates=cands)
        distinct = []
        for k in answers:                       # one score per distinct answer
            twin = next((d for d in distinct if _agree(d.T_map_base, k.T_map_base, c)), None)
            if twin is None:
                k.delta = self._score(points, fitness, B_map, k.T_map_base)
                distinct.append(k)
            else:
                k.delta = twin.delta
        good = sorted(distinct, key=lambda k: k.delta)
        best = good[0]
        margin = c.rival_margin * abs(best.delta)
        beyond = [k for k in cands if k.T_map_base is None and k.delta < best.delta - margin
                  and k.reason.startswith("minimum on the search window boundary")]
        if beyond:
            return Relocalisation(None, f"unclear: a better fit lies beyond a search window ({beyond[0].reason[:40]})",
                                  best.keyframe_id, best.delta, cands, best.T_map_base.copy())
        for r in good[1:]:
            if not _agree(r.T_map_base, best.T_map_base, c) and r.delta - best.delta < margin:
                return Relocalisation(None, f"ambiguous: two poses {_distance(r.T_map_base, best.T_map_base):.2f} m "
                                            f"apart fit nearly as well", best.keyframe_id, best.delta, cands,
                                      best.T_map_base.copy())
        for dx in (-c.pin_check_m, c.pin_check_m):      # pinned along the line of sight?
            if self._score(points, fitness, B_map, best.T_map_base @ planar_pose(dx, 0.0, 0.0)) - best.delta < margin:
                return Relocalisation(None, f"not pinned along the view: {dx:+.1f} m fits nearly as well",
                                      best.keyframe_id, best.delta, cands, best.T_map_base.copy())
        agrees = previous is not None and _agree(previous, best.T_map_base, c, c.confirm_rad)
        streak = streak + 1 if agrees else 0
        out = Relocalisation(None, "", best.keyframe_id, best.delta, cands, best.T_map_base.copy(), streak)
        if hint is not None and _agree(hint, best.T_map_base, c, c.confirm_rad):
            out.T_map_base, out.reason = best.T_map_base.copy(), "confirmed by the hinted pose"
        elif streak >= c.confirmations:
            out.T_map_base, out.reason = best.T_map_base.copy(), f"the same pose won {streak + 1} frames in a row"
        else:
            out.reason = f"unconfirmed: {streak + 1} of {c.confirmations + 1} frames in a row agree"
        return out


def weights_of(fitness: np.ndarray) -> np.ndarray:
    return fitness / max(float(fitness.max()), 1e-12)


def _distance(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.linalg.norm(A[:2, 3] - B[:2, 3]))


def _agree(A: np.ndarray, B: np.ndarray, cfg: RelocaliserConfig, max_rad: float | None = None) -> bool:
    dyaw = abs(wrap_angle(planar_from_transform(A)[2] - planar_from_transform(B)[2]))
    return _distance(A, B) <= cfg.agree_m and dyaw <= (cfg.agree_rad if max_rad is None else max_rad)


__all__ = ["Candidate", "PREVIOUS", "Relocalisation", "Relocaliser", "RelocaliserConfig"]
