"""The localiser's back-end: every keyframe a node of a pose graph (common.slam.posegraph), consecutive
keyframes joined by an odometry factor, the registrations that made a keyframe by registration factors,
and loop closures (a new keyframe registered against an old one near it) by robust loop factors.

Invariants: the keyframes the localiser made stay in ``archive`` (the sliding window only bounds the
local map) up to ``ArchiveConfig.max_archive_keyframes``: past it, :meth:`KeyframeGraph.bound` drops the
most redundant old ones and rebuilds the graph without them, so memory stays bounded on a long run (and
so does map.mcap, which saves the archive); after :meth:`KeyframeGraph.optimise` every archived
keyframe's ``T_map_base`` and ``points_map`` are the graph's.  Factors (flyslam order, frame j, see posegraph):

- odometry i→j: the relative pose the localiser estimated; on wheels σ grows with the distance driven
  and the angle turned between them (the same model as the localiser's odometry prior); tracked by the
  camera alone, σ comes from the camera (:func:`tracked_motion_cov`);
- registration i→j: the fix's covariance (map-frame position rotated into keyframe j's base);
- loop i→j: the two keyframes aligned on the old one's fly neighbourhoods, with the camera's σ
  (:meth:`tracked_cov`), or δ's planar registration with its per-axis noise (``registration_sigma``)
  where the keyframes have no images.  Cauchy-robust; a loop factor the optimised graph down-weights
  is removed again.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry import invert, orthonormalised, planar_from_transform, planar_pose, transform_points
from common.slam.config import ArchiveConfig
from common.slam.posegraph import PoseGraph, PoseGraphError, planar_covariance

_MIN_SIGMA = (0.005, np.deg2rad(0.05))    # floor on a factor's position (m) and rotation (rad) sigma
# Loops outvoted one after another are tried again together once this many agree (ORB-SLAM asks a loop
# to be consistent over three keyframes): one wrong loop the graph accepted must not outvote, one at a
# time, every correct loop that follows it.
LOOP_GROUP = 3


@dataclass
class LoopClosure:
    old_id: int
    new_id: int
    correction_m: float        # how far the closure moved the new keyframe
    accepted: bool
    reason: str = ""


def odometry_sigmas(config, distance_m: float, turned_rad: float) -> tuple[float, float]:
    """σ (m, rad) of odometry over ``distance_m`` driven and ``turned_rad`` turned (LocaliserConfig's
    prior_sigma_* model): the localiser's prior since its last fix and the graph's odometry factors."""
    sxy = config.prior_sigma_xy[0] + config.prior_sigma_xy[1] * distance_m
    syaw = config.prior_sigma_yaw[0] + config.prior_sigma_yaw[1] * distance_m + config.prior_sigma_yaw_per_rad * turned_rad
    return sxy, syaw


def tracked_motion_cov(T_i_j: np.ndarray, depth_m: float, fx: float, baseline_m: float,
                       disparity_px: float) -> np.ndarray:
    """6×6 covariance of the motion between two keyframes tracked by the camera alone, from what limits
    it: the flies' depths, each known to ``disparity_px`` of disparity, scale the translation by a relative
    error of disparity_px / (median disparity) = disparity_px · depth / (fx · baseline); the rotation is
    known to disparity_px / fx.  Floored by _MIN_SIGMA.  The wheel model (odometry_sigmas) would give a
    camera's roll and pitch the heading's loose σ, and loop factors could then bend the chain."""
    relative = disparity_px * max(depth_m, 0.0) / (fx * baseline_m)
    st = max(_MIN_SIGMA[0], float(np.linalg.norm(T_i_j[:3, 3])) * relative)
    sr = max(_MIN_SIGMA[1], disparity_px / fx)
    return np.diag([st, st, st, sr, sr, sr]) ** 2


class KeyframeGraph:
    """Pose graph over the localiser's keyframes.  ``planar``: a wheeled robot (z, roll, pitch held)."""

    def __init__(self, config, planar: bool, archive: ArchiveConfig | None = None, camera: tuple | None = None):
        self.config = config
        self.planar = planar
        self.archive_config = archive or ArchiveConfig()
        self.graph = PoseGraph(robust="cauchy", planar=planar)
        self.archive: dict = {}            # id -> Keyframe, the keyframes kept (see ArchiveConfig)
        self.loops: list[LoopClosure] = []
        # the loop factors outvoted since the last accepted loop, newest last: (Edge, index in loops)
        self.outvoted: list = []
        self.dropped = 0                   # keyframes dropped by the size bound
        self._last_id: int | None = None
        self.camera = camera               # (fx, baseline, T_camera_base): the camera's measurement model

    # --------------------------------------------------------------------------- factors
    def _odometry_cov(self, T_i_j: np.ndarray, kf=None) -> np.ndarray:
        """Without wheels (a 6-DoF graph) the camera tracked the motion: its model; on wheels the wheels'."""
        if self.camera is not None and not self.planar and kf is not None and len(kf.points):
            return self.tracked_cov(T_i_j, kf)
        sxy, syaw = odometry_sigmas(self.config, float(np.linalg.norm(T_i_j[:3, 3])),
                                    abs(planar_from_transform(T_i_j)[2]))
        if self.planar:
            return planar_covariance(np.diag([sxy, sxy, syaw]) ** 2)
        return np.diag([sxy, sxy, sxy, syaw, syaw, syaw]) ** 2

    def tracked_cov(self, T_i_j: np.ndarray, kf) -> np.ndarray:
        """Covariance of a motion the camera measured on the flies' neighbourhoods (tracking without
        wheels, a loop aligned photometrically): :func:`tracked_motion_cov` at ``kf``'s flies' median
        depth (needs ``camera``); in a planar graph its (x, y, yaw) block."""
        fx, baseline, T_camera_base = self.camera
        depth = float(np.median(transform_points(T_camera_base, kf.points.astype(np.float64))[:, 2]))
        cov = tracked_motion_cov(T_i_j, depth, fx, baseline, self.config.tracked_disparity_px)
        return planar_covariance(cov[np.ix_([0, 1, 5], [0, 1, 5])]) if self.planar else cov

    def _body_cov(self, cov_map: np.ndarray, T_map_base: np.ndarray) -> np.ndarray:
        """A map-frame (position, rotation) 6×6 covariance in the base frame, floored so no axis is exact."""
        R = np.zeros((6, 6))
        R[:3, :3] = R[3:, 3:] = T_map_base[:3, :3].T
        cov = R @ np.asarray(cov_map, dtype=float) @ R.T
        floor = np.r_[np.full(3, _MIN_SIGMA[0]), np.full(3, _MIN_SIGMA[1])] ** 2
        cov = 0.5 * (cov + cov.T) + np.diag(floor)
        if self.planar:      # the planar prior holds z, roll, pitch; a fix says nothing about them
            cov[2, :] = cov[:, 2] = cov[3, :] = cov[:, 3] = cov[4, :] = cov[:, 4] = 0.0
            cov[2, 2] = cov[3, 3] = cov[4, 4] = 1e-2
        return cov

    def _node_pose(self, T_map_base: np.ndarray) -> np.ndarray:
        """A pose as the graph holds it: levelled (z 0, no roll or pitch) in a planar graph.  The front
        end's 6-DoF fixes wander a few cm and tenths of a degree off the plane; factors built from them
        would contradict the planar priors by tens of their tight z/roll/pitch sigmas, and the robust
        kernel would then discount the whole factor, x, y and yaw included, leaving a keyframe free to
        swing metres away."""
        return planar_pose(*planar_from_transform(T_map_base)) if self.planar else orthonormalised(T_map_base)

    def _relative(self, T_map_i: np.ndarray, T_map_j: np.ndarray) -> np.ndarray:
        return orthonormalised(invert(self._node_pose(T_map_i)) @ self._node_pose(T_map_j))

    def add(self, kf, registered_to: list[int] = (), fix_cov: np.ndarray | None = None) -> None:
        """A new keyframe (initialised at its registered pose) with its odometry and registration factors."""
        self.archive[kf.id] = kf
        T0 = self._node_pose(kf.T_map_base)
        self.graph.add_keyframe(kf.id, T0)
        if self._last_id is None:
            self.graph.add_prior(kf.id, T0, np.diag([1e-3] * 3 + [1e-4] * 3) ** 2)
        else:
            prev = self.archive[self._last_id]
            T = self._relative(prev.T_map_base, kf.T_map_base)
            self.graph.add_odometry(prev.id, kf.id, T, self._odometry_cov(T, kf))
            if fix_cov is not None:
                cov = self._body_cov(fix_cov, kf.T_map_base)
                for i in registered_to:
                    if i in self.archive and i != kf.id:
                        self.graph.add_registration(i, kf.id, self._relative(self.archive[i].T_map_base,
                                                                             kf.T_map_base), cov)
        self._last_id = kf.id

    def loop_candidate(self, kf, exclude: set[int]):
        """The old keyframe nearest to ``kf`` (within ``loop_radius_m``, looking within
        ``loop_max_angle_rad`` the same way, at least ``loop_min_separation`` keyframes older, not in
        ``exclude``), or None.

        The radius defaults to the keyframe spacing: a loop is measured where the new keyframe is about
        where the map would have put one, so the two views nearly coincide.  Farther apart the scene
        changes scale between them and the alignment errs along the view: on the simulated loop a
        closure 2.5 m behind the first keyframe was 115 mm off and left the lap worse than none, while
        the keyframe made 1.5 m later, near it, ended every seed's lap 1-3 mm from the truth (ATE
        6.5-7.6 mm).  Until a loop has closed, old keyframes do not stop new ones (_needs_keyframe), so
        a revisit gets that keyframe."""
        c = self.config
        radius = c.keyframe_distance_m if c.loop_radius_m is None else c.loop_radius_m
        x, y, yaw = planar_from_transform(kf.T_map_base)
        best, best_d = None, np.inf
        for old in self.archive.values():
            if old.id in exclude or old.id > kf.id - c.loop_min_separation:
                continue
            ox, oy, oyaw = planar_from_transform(old.T_map_base)
            d = float(np.hypot(x - ox, y - oy))
            if d < min(best_d, radius) and abs((yaw - oyaw + np.pi) % (2 * np.pi) - np.pi) < c.loop_max_angle_rad:
                best, best_d = old, d
        return best

    def add_loop(self, old, kf, T_map_base_new: np.ndarray, cov_body: np.ndarray) -> int:
        return self.graph.add_registration(old.id, kf.id, self._relative(old.T_map_base, T_map_base_new), cov_body)

    # ------------------------------------------------------------------------ optimising
    def optimise(self, newest_id: int, batch: bool = False) -> np.ndarray:
        """Optimise and move every keyframe to its graph pose; returns the newest keyframe's correction
        C (T_new = C · T_old, map frame), which the caller applies to its current estimate.  ``batch``:
        Levenberg-Marquardt over the whole graph, iSAM2 restarted from it (see PoseGraph.optimise)."""
        before = self.archive[newest_id].T_map_base.copy()
        self.graph.optimise(batch=batch)
        for kf_id, T in self.graph.poses().items():
            kf = self.archive.get(kf_id)
            if kf is not None and not np.allclose(T, kf.T_map_base, atol=1e-7):   # (round-off moves nothing)
                kf.T_map_base = T
                kf.points_map = transform_points(T, kf.points.astype(np.float64)).astype(np.float32)
        C = orthonormalised(self.archive[newest_id].T_map_base @ invert(before))
        return np.eye(4) if np.allclose(C, np.eye(4), atol=1e-7) else C

    # ----------------------------------------------------------------------------- the bound
    def bound(self, keep: set[int] = frozenset()) -> list[int]:
        """Enforce ``max_archive_keyframes``: once it is exceeded drop ``drop_fraction`` of it (never the
        ids in ``keep``, the localiser's window, nor the newest keyframe) and return their ids.

        Least useful first: a keyframe with a younger twin (another within ``keyframe_distance_m`` and
        ``keyframe_angle_rad``: the same view mapped again) before the oldest.  The graph is rebuilt on
        the kept keyframes at their current poses with the edges among them; consecutive kept keyframes
        that lost their link are joined by an odometry factor of their current relative pose (the
        chain stays connected), and the oldest kept one takes the prior when its holder was dropped.
        A dropped keyframe's flies are released (an estimate anchored on it keeps only its pose)."""
        limit = int(self.archive_config.max_archive_keyframes)
        if len(self.archive) <= limit:
            return []
        n_drop = len(self.archive) - limit + int(self.archive_config.drop_fraction * limit)
        protected = set(keep) | {self._last_id}
        ids = sorted(k for k in self.archive if k not in protected)
        n_drop = min(n_drop, len(ids))
        poses = np.array([planar_from_transform(self.archive[k].T_map_base) for k in ids]).reshape(-1, 3)
        young = np.array([planar_from_transform(self.archive[k].T_map_base) for k in self.archive]).reshape(-1, 3)
        young_ids = np.array(list(self.archive))
        twin = np.zeros(len(ids), bool)
        for n, (k, (x, y, yaw)) in enumerate(zip(ids, poses)):
            near = (np.hypot(young[:, 0] - x, young[:, 1] - y) < self.config.keyframe_distance_m) & (
                np.abs((young[:, 2] - yaw + np.pi) % (2 * np.pi) - np.pi) < self.config.keyframe_angle_rad)
            twin[n] = bool(np.any(near & (young_ids > k)))
        order = sorted(range(len(ids)), key=lambda n: (not twin[n], ids[n]))
        drop = sorted(ids[n] for n in order[:n_drop])
        self._rebuild(set(drop))
        return drop

    def _rebuild(self, drop: set[int]) -> None:
        kept = sorted(k for k in self.archive if k not in drop)
        old_edges = list(self.graph.edges().values())
        graph = PoseGraph(robust="cauchy", planar=self.planar)
        for k in kept:
            graph.add_keyframe(k, self._node_pose(self.archive[k].T_map_base))
        linked = set()
        has_prior = False
        for e in old_edges:
            if e.i in drop or e.j in drop:
                continue
            graph.add_edge(e)
            has_prior |= e.kind == "prior"
            linked.add((min(e.i, e.j), max(e.i, e.j)))
        for a, b in zip(kept[:-1], kept[1:]):
            if (a, b) not in linked:
                T = self._relative(self.archive[a].T_map_base, self.archive[b].T_map_base)
                graph.add_odometry(a, b, T, self._odometry_cov(T))
        if not has_prior and kept:
            graph.add_prior(kept[0], self._node_pose(self.archive[kept[0]].T_map_base),
                            np.diag([1e-3] * 3 + [1e-4] * 3) ** 2)
        for k in drop:
            kf = self.archive.pop(k)
            kf.points, kf.points_map = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
            kf.fitness, kf.image = np.zeros(0, np.float32), None
        graph.failed_updates = self.graph.failed_updates
        self.graph = graph        # optimised with the next keyframe (whose correction the localiser applies)
        self.dropped += len(drop)

    def drop_if_outvoted(self, handle: int) -> bool:
        """Remove a factor the optimised graph down-weighted (an outlier); True if it was removed."""
        if self.graph.report(handle).downweighted:
            self.graph.remove_factor(handle)
            return True
        return False

    def outvoted_group(self) -> list:
        """The last LOOP_GROUP outvoted loops (Edge, loop index) whose keyframes are all still in the
        graph, or [] when there are fewer."""
        group = [(e, i) for e, i in self.outvoted[-LOOP_GROUP:] if e.i in self.archive and e.j in self.archive]
        return group if len(group) == LOOP_GROUP else []


__all__ = ["LOOP_GROUP", "ArchiveConfig", "KeyframeGraph", "LoopClosure", "PoseGraphError"]
