"""Fly-based SLAM: localise each new fly population against a map of keyframe populations.

Per update (no I/O; the localiser service and ``flyslam eval`` both drive this class, through
common.slam.core):

1. keep the population's fittest flies (``keep_fraction``) nearer than ``max_depth_m``, in base_link;
2. predict the pose: ``T_map_odom · T_odom_base`` from wheel odometry, or a 6-DoF constant-velocity
   model of the localiser's own estimates (``odometry = "visual"``, or no odometry given);
3. while wheel odometry says the robot turns faster than ``max_turn_rate_radps``, only the
   photometric tracking below may fix the pose (no δ, no keyframe); else odometry carries it;
4. with the frame's left image: track photometrically — align the reference view's flies into the
   image on their neighbourhoods (common.slam.tracking), from the prediction, or after a coarse lattice
   search when no motion is known yet;
5. else (no image, no reference, or tracking refused): register the flies against the *local map* —
   the keyframes that see most of the predicted view, merged in the map frame — with the paper's δ in
   the plane (x, y, θ), within a window of 3 σ of the prediction, gated against it; an accepted
   registration is refined photometrically when it can be;
6. add a keyframe where none is both near and looking the same way (voxel-thinned, a bounded window;
   with ``pose_graph`` every keyframe is also a node of common.slam.backend's graph, whose corrections
   move the map and the estimate), and renew the tracking reference once the camera has left it.

A refused fix leaves map→odom as it was (odometry carries on) and the estimate's status says why.
Design: docs/design/localiser.md.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from common.fly.selection import fittest
from common.geometry import (invert, orthonormalised, planar_from_transform, planar_pose, scaled_motion, so3_log,
                             transform_points)
from common.registration import PopulationError, register_planar
from common.registration.register import StereoModel
from common.registration.photometric import pyramid
from common.registration.weights import visible_mask
from common.slam.backend import KeyframeGraph, LoopClosure, odometry_sigmas
from common.slam.config import LocaliserConfig
from common.slam.posegraph import UNCONSTRAINED_SIGMA, PoseGraphError, planar_covariance
from common.slam.tracking import (SWITCH_RESIDUAL_RATIO, ReferenceView, align_keyframes, photometric_fix,
                                  reference_view, reverse_motion)


POOR_FIT_RATIO = 1.5   # a fix whose residual scale exceeds the recent median by this much is tried from other starts
MIN_FITS_TO_JUDGE = 5  # recent fixes needed before a fit is called poor (or good enough to outrank the motion model)


class LocaliserError(ValueError):
    """Malformed input to the localiser (shapes, NaN poses)."""


@dataclass
class Keyframe:
    id: int
    stamp_ns: int
    T_map_base: np.ndarray
    points: np.ndarray        # (K, 3) float32 in this keyframe's base_link
    fitness: np.ndarray       # (K,) float32
    points_map: np.ndarray = None   # (K, 3) float32, the same points in the map frame (cached)
    image: np.ndarray | None = None   # the frame's grey left image at half resolution (photometric loops)

    def __post_init__(self):
        if self.points_map is None:
            self.points_map = transform_points(self.T_map_base, self.points.astype(np.float64)).astype(np.float32)


@dataclass
class Estimate:
    stamp_ns: int
    T_map_base: np.ndarray
    T_map_odom: np.ndarray
    covariance: np.ndarray    # 6×6 over (x, y, z, roll, pitch, yaw)
    status: str               # 'ok', 'initialised', 'rejected: ...', 'odometry only: ...'
    registered: bool
    keyframe_added: bool = False
    delta: float = float("nan")


@dataclass
class _Tracking:
    last_T_map_base: np.ndarray | None = None
    last_stamp: int | None = None
    last_motion: np.ndarray | None = None      # body-frame motion over the last update
    last_dt: float = 0.0
    last_fix: tuple | None = None              # (stamp, T_map_base) of the last registered update


def voxel_thin(points: np.ndarray, fitness: np.ndarray, voxel: float):
    """Keep the fittest point of each voxel (vectorised: sort by fitness, unique voxel keys)."""
    if len(points) == 0:
        return points, fitness
    order = np.argsort(-fitness, kind="stable")
    keys = np.floor(points[order] / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    keep = order[np.sort(first)]
    return points[keep], fitness[keep]


def _between(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A⁻¹·B for rigid transforms (N, 4, 4), batched."""
    out = np.zeros(np.broadcast_shapes(A.shape, B.shape))
    out[:, :3, :3] = np.swapaxes(A[:, :3, :3], 1, 2) @ B[:, :3, :3]
    out[:, :3, 3] = np.einsum("nji,nj->ni", A[:, :3, :3], B[:, :3, 3] - A[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def _blend(A: np.ndarray, B: np.ndarray, share: np.ndarray) -> np.ndarray:
    """Poses (N, 4, 4) ``share`` of the way from A to B (rotation on its geodesic, translation in A's
    frame scaled: :func:`common.geometry.scaled_motion`, batched); A where share is 0."""
    out = A.copy()
    k = np.flatnonzero(share > 0)
    if len(k) == 0:
        return out
    step = _between(A[k], B[k])
    rotvec = Rotation.from_matrix(step[:, :3, :3]).as_rotvec() * share[k, None]
    step[:, :3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    step[:, :3, 3] *= share[k, None]
    out[k] = A[k] @ step
    return out


class FlyLocaliser:
    def __init__(self, T_base_camera: np.ndarray, config: LocaliserConfig | None = None, seed: int = 0,
                 calibration=None):
        self.T_base_camera = np.asarray(T_base_camera, dtype=float)
        self.config = config or LocaliserConfig()
        self.calibration = calibration
        if self.config.odometry not in ("wheels", "visual"):
            raise LocaliserError(f"odometry must be 'wheels' or 'visual', got {self.config.odometry!r}")
        self.max_depth_m = self.config.max_depth_m
        if self.max_depth_m is None:
            self.max_depth_m = 0.3 * calibration.fx * calibration.baseline if calibration is not None else 8.0
        self.stereo = (StereoModel(calibration, depth_range=(0.3, self.max_depth_m))
                       if calibration is not None and self.config.use_stereo_model else None)
        self._driven_since_fix = 0.0
        self._turned_since_fix = 0.0
        self._fast_turn_since_fix = 0.0  # signed odometry yaw (rad) turned faster than max_turn_rate_radps
        self._last_fix_stamp: int | None = None
        self.graph_failures = 0          # keyframes the pose graph could not solve (their front-end poses stand)
        self.slips_undone = 0            # fixes that took the prediction without a too-fast odometry turn
        self.map_restarts = 0            # one-keyframe maps restarted (see _first_fix_too_late)
        self.map_loaded = False      # started from a saved map (load_map): never restarted
        self._pinned_hint = np.zeros(3, bool)      # see LocaliserConfig.tracking_recheck_pinned
        self._pinned_streak = 0
        self._last_odom: np.ndarray | None = None
        self._last_odom_stamp: int | None = None
        self._turn_rate = 0.0
        self._next_id = 0
        self._rng = np.random.default_rng(seed)
        self._empty_map()

    def _empty_map(self, archive=None) -> None:
        """The map and the tracking state of a new localiser (which a map restart returns to);
        ``archive``: the back-end's size bound (None: its default)."""
        self._updates_since_fix = 0      # the constant-velocity prediction's uncertainty grows with it
        self._steps_since_fix = 1.0      # ... and with the time since the last fix (see _prediction_steps)
        # The visibility count runs on every update over the whole keyframe window: the concatenated map
        # is rebuilt only when the window changed, and the count for the last pose asked is kept (the
        # local map and the coverage test of a rejected update ask about the same predicted pose).
        self._map_cache: tuple | None = None
        self._visible_cache: tuple | None = None
        self.keyframes: deque[Keyframe] = deque(maxlen=self.config.max_keyframes)
        self.T_map_odom = np.eye(4)
        self._track = _Tracking()
        self._reference: ReferenceView | None = None      # photometric tracking reference (see _renew_reference)
        self._fit_residuals: deque[float] = deque(maxlen=20)   # residual scales of the recent photometric fixes
        self._newest_view: tuple | None = None    # (T_map_cam, view flies) of the newest registered update
                                                  # (or the first, which defines the map)
        cal = self.calibration
        camera = (cal.fx, cal.baseline, invert(self.T_base_camera)) if cal is not None else None
        self.backend = (KeyframeGraph(self.config, planar=self.config.odometry == "wheels", archive=archive,
                                      camera=camera)
                        if self.config.pose_graph else None)
        # every estimate as (stamp, anchor keyframe, pose relative to it): trajectory() re-expresses the
        # whole run in the keyframes' current (optimised) poses
        self._history: list[tuple[int, Keyframe | None, np.ndarray]] = []
        # keyframe id -> the keyframe made next on the same run of estimates (a run ends at a
        # relocalisation or a loaded map): (next keyframe, this one's pose relative to it when it was made,
        # stamp of this one's first estimate in that run); trajectory() blends the two keyframes'
        # corrections over the estimates from that stamp to the next keyframe
        self._next_in_chain: dict[int, tuple[Keyframe, np.ndarray, int]] = {}
        self._anchor_since: tuple[int, int] | None = None   # (newest keyframe id, stamp of its first
                                                            # estimate since the run began)
        self._pool_list: list[Keyframe] | None = None
        # the old keyframe the newest accepted loop closure or relocalisation tied the pose to (see
        # _tracking_mask); None: only the recent keyframes track
        self._revisit_anchor: int | None = None

    # ------------------------------------------------------------------------------ selection
    def select_flies(self, positions_cam: np.ndarray, fitness: np.ndarray):
        """Fittest, near enough, off the floor: (points in base_link (M, 3), fitness (M,))."""
        P = np.asarray(positions_cam, dtype=np.float64)
        f = np.asarray(fitness, dtype=np.float64)
        if P.ndim != 2 or P.shape[1] != 3 or f.shape != (len(P),):
            raise LocaliserError(f"population must be (N,3) with (N,) fitness, got {P.shape} and {f.shape}")
        c = self.config
        ok = np.isfinite(P).all(axis=1) & np.isfinite(f) & (P[:, 2] > 0) & (P[:, 2] < self.max_depth_m)
        P, f = P[ok], f[ok]
        if len(P) == 0:
            return np.zeros((0, 3)), np.zeros(0)
        keep = fittest(f, c.keep_fraction)
        base = transform_points(self.T_base_camera, P[keep])
        band = (base[:, 2] > c.min_height_m) & (base[:, 2] < c.max_height_m)
        return base[band], f[keep][band]

    # ------------------------------------------------------------------------------------ map
    @property
    def _pool(self):
        """Keyframes the local map is chosen from: with the back-end and loop closure every archived
        keyframe (a place seen again is registered against what was mapped there), else the window."""
        if self.backend is not None and self.config.loop_closure and self.config.local_map_from_archive:
            archive = self.backend.archive      # (the size bound drops old keyframes as new ones come)
            if (self._pool_list is None or len(self._pool_list) != len(archive)
                    or (archive and self._pool_list[-1].id != next(reversed(archive)))):
                self._pool_list = list(archive.values())
            return self._pool_list
        return self.keyframes

    def _map_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All keyframe points in the map frame (float32), the index of the keyframe each belongs to and
        each keyframe's size; rebuilt only when the keyframe window changed."""
        ids = tuple(kf.id for kf in self._pool)
        if self._map_cache is None or self._map_cache[0] != ids:
            sizes = np.array([len(kf.points_map) for kf in self._pool], dtype=np.int64)
            pts = np.concatenate([kf.points_map for kf in self._pool]).astype(np.float32)
            self._map_cache = (ids, pts, np.repeat(np.arange(len(sizes)), sizes), sizes)
        return self._map_cache[1:]

    def _tracking_mask(self) -> np.ndarray:
        """(len(pool),) bool: the keyframes the pose may be tracked against.  With loop closure on, a
        keyframe more than ``loop_min_separation`` keyframes older than the newest is a place mapped
        long ago: it comes back in through _close_loop (its wide window, a robust factor), unless it
        is near (in keyframe ids) the old keyframe the newest accepted loop closure or relocalisation
        tied the pose to.  Tracked against with a window sized for one update's drift, such a keyframe
        meets the whole loop's drift, and the heading absorbs it."""
        pool = self._pool
        ids = np.fromiter((kf.id for kf in pool), dtype=np.int64, count=len(pool))
        if self.backend is None or not self.config.loop_closure or len(ids) == 0:
            return np.ones(len(ids), bool)
        sep = self.config.loop_min_separation
        allowed = ids >= ids.max() - sep
        if self._revisit_anchor is not None:
            allowed |= np.abs(ids - self._revisit_anchor) <= sep
        return allowed

    def _in_view(self, points_map: np.ndarray, T_map_base: np.ndarray) -> np.ndarray:
        """(N,) bool: which map-frame points the camera of a robot at ``T_map_base`` sees (both images,
        within the trusted depth; without a calibration a forward cone of fallback_half_fov_rad)."""
        cam = transform_points(invert(T_map_base @ self.T_base_camera), points_map)
        if self.calibration is not None:
            return visible_mask(cam, self.calibration, (0.3, self.max_depth_m), margin=0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            return ((cam[:, 2] > 0.3) & (cam[:, 2] < self.max_depth_m)
                    & (np.abs(cam[:, 0] / cam[:, 2]) < np.tan(self.config.fallback_half_fov_rad)))

    def _visible_per_keyframe(self, T_map_base: np.ndarray) -> np.ndarray:
        """How many of each keyframe's points a camera at ``T_map_base`` would see (vectorised over the
        whole map: one transform, one projection, one bincount; the last answer is reused for the same
        pose and keyframes)."""
        if not self.keyframes:
            return np.zeros(0, dtype=np.int64)
        pts, owner, _ = self._map_arrays()
        key = (np.asarray(T_map_base, dtype=float).tobytes(), self._map_cache[0], self._revisit_anchor)
        if self._visible_cache is not None and self._visible_cache[0] == key:
            return self._visible_cache[1]
        seen = self._in_view(pts, T_map_base)
        visible = np.bincount(owner[seen], minlength=len(self._pool)) * self._tracking_mask()
        self._visible_cache = (key, visible)
        return visible

    def _local_keyframes(self, T_map_base: np.ndarray) -> tuple[list[int], float]:
        """Indices of the keyframes that see most of what a camera at ``T_map_base`` sees, and the best
        keyframe's visible fraction (how well the map covers the view).

        Chosen by view overlap, not by distance: a robot that turns on the spot has a dozen keyframes at
        the same place looking every way, and the nearest ones were as likely to look behind it (a
        closed-loop run that turned around registered against an empty view for minutes and drifted)."""
        visible = self._visible_per_keyframe(T_map_base)
        if len(visible) == 0 or visible.max() == 0:
            return [], 0.0
        sizes = np.maximum(self._map_arrays()[2], 1)
        order = np.argsort(-visible, kind="stable")[: self.config.local_keyframes]
        chosen = [int(i) for i in order if visible[i] > 0]
        return chosen, float((visible / sizes).max())

    def local_map(self, T_map_base: np.ndarray) -> np.ndarray:
        """Points of the keyframes that best see the view from ``T_map_base``, in the map frame
        (subsampled to max_map_points)."""
        chosen, _ = self._local_keyframes(T_map_base)
        if not chosen:
            return np.zeros((0, 3))
        pts = np.concatenate([self._pool[i].points_map.astype(np.float64) for i in chosen])
        if len(pts) > self.config.max_map_points:
            pts = pts[self._rng.choice(len(pts), self.config.max_map_points, replace=False)]
        return pts

    def _distance_to_map(self, T_map_base: np.ndarray) -> float:
        if not self.keyframes:
            return np.inf
        return float(min(np.linalg.norm(kf.T_map_base[:2, 3] - T_map_base[:2, 3]) for kf in self._pool))

    def _needs_keyframe(self, T_map_base: np.ndarray) -> bool:
        if not self.keyframes:
            return True
        x, y, yaw = planar_from_transform(T_map_base)
        for kf, tracked in zip(self._pool, self._tracking_mask()):
            if not tracked:      # a place mapped long ago gets a new keyframe: its loop closure
                continue
            kx, ky, kyaw = planar_from_transform(kf.T_map_base)
            dyaw = abs((yaw - kyaw + np.pi) % (2 * np.pi) - np.pi)
            if np.hypot(x - kx, y - ky) < self.config.keyframe_distance_m and dyaw < self.config.keyframe_angle_rad:
                return False
        return True

    def _add_keyframe(self, stamp_ns: int, T_map_base: np.ndarray, points: np.ndarray, fitness: np.ndarray,
                      image: np.ndarray | None = None) -> Keyframe:
        pts, fit = voxel_thin(points, fitness, self.config.voxel_m)
        half = None
        if image is not None and self._keeps_images():
            grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
            half = cv2.pyrDown(np.ascontiguousarray(grey, np.uint8))
        kf = Keyframe(self._next_id, stamp_ns, T_map_base.copy(), pts.astype(np.float32), fit.astype(np.float32),
                      image=half)
        self.keyframes.append(kf)
        self._next_id += 1
        return kf

    # ------------------------------------------------------------------------------ back-end
    @property
    def graph_failed_updates(self) -> int:
        """iSAM2 updates that raised and were solved again from the whole graph (see common.slam.posegraph)."""
        return self.backend.graph.failed_updates if self.backend is not None else 0

    @property
    def loop_closures(self) -> list[LoopClosure]:
        return self.backend.loops if self.backend is not None else []

    def _graph_keyframe(self, kf: Keyframe, links: list[int], fix_cov) -> np.ndarray:
        """Put a new keyframe into the pose graph (and try a loop closure); returns the newest
        keyframe's correction C (map frame) after optimising."""
        be = self.backend
        be.add(kf, links, fix_cov)
        old = be.loop_candidate(kf, exclude=set()) if self.config.loop_closure else None
        handle = self._close_loop(old, kf) if old is not None else None
        C = self._optimise_graph(kf.id)
        if handle is not None:
            edge = be.graph.edge(handle)
            if be.drop_if_outvoted(handle):
                be.loops[-1].accepted, be.loops[-1].reason = False, "outvoted by the graph"
                C = self._optimise_graph(kf.id) @ C
                be.outvoted.append((edge, len(be.loops) - 1))
                C = self._loops_together(kf.id) @ C
            else:
                be.outvoted.clear()
                self._revisit_anchor = old.id
        self._map_cache = self._visible_cache = None
        return C

    def _loops_together(self, newest_id: int) -> np.ndarray:
        """Let the last LOOP_GROUP outvoted loops vote together against the loops accepted just before
        them (new keyframes within ``loop_min_separation`` of theirs): those are taken out, the group put
        in and the graph solved in batch.  If the group then holds (none of it down-weighted), each loop
        taken out goes back in and stays only if the graph does not down-weight it; else everything is
        as it was and the group waits for the next loop.  A Cauchy kernel cannot do this alone: from
        poses that satisfy one tight loop, loops 0.4 m away are 40 σ off, nearly ignored, and each new
        one is outvoted in turn.  Returns the newest keyframe's correction."""
        be, c = self.backend, self.config
        group = be.outvoted_group()
        if not group:
            return np.eye(4)
        first_new = min(e.j for e, _ in group)
        accepted = {(lc.old_id, lc.new_id) for lc in be.loops if lc.accepted}
        rivals = [(h, e) for h, e in be.graph.edges().items()
                  if e.kind == "registration" and (e.i, e.j) in accepted and e.j >= first_new - c.loop_min_separation]
        for h, _ in rivals:
            be.graph.remove_factor(h)
        handles = [be.graph.add_edge(e) for e, _ in group]
        C = self._optimise_graph(newest_id, batch=True)
        if any(be.graph.report(h).downweighted for h in handles):
            for h in handles:
                be.graph.remove_factor(h)
            for _, e in rivals:
                be.graph.add_edge(e)
            return self._optimise_graph(newest_id, batch=True) @ C
        be.outvoted.clear()
        for _, i in group:
            be.loops[i].accepted, be.loops[i].reason = True, f"with {len(group) - 1} later loops that agree"
        back = [(be.graph.add_edge(e), e) for _, e in rivals]
        if back:
            C = self._optimise_graph(newest_id) @ C
            lost = {(e.i, e.j) for h, e in back if be.drop_if_outvoted(h)}
            for lc in be.loops:
                if lc.accepted and (lc.old_id, lc.new_id) in lost:
                    lc.accepted, lc.reason = False, f"outvoted by {len(group)} later loops that agree"
            if lost:
                C = self._optimise_graph(newest_id) @ C
        self._revisit_anchor = group[-1][0].i
        return C

    def _optimise_graph(self, newest_id: int, batch: bool = False) -> np.ndarray:
        """The back-end's correction of the newest keyframe (identity when the graph cannot be solved).
        iSAM2 refuses a system it cannot eliminate (a front end that diverged hands it factors that
        contradict everything): start it again from a damped batch solve, and if even that fails keep
        the front end's poses; the localiser carries on either way.  ``batch``: solve in batch at once."""
        try:
            return self.backend.optimise(newest_id, batch=batch)
        except PoseGraphError:
            try:
                return self.backend.optimise(newest_id, batch=True)
            except PoseGraphError:
                self.graph_failures += 1
                return np.eye(4)

    def _close_loop(self, old: Keyframe, kf: Keyframe) -> int | None:
        """A loop factor old→kf, or None (the attempt and its outcome go to ``backend.loops``).  It is
        measured on the two keyframes' fly neighbourhoods (:meth:`_photometric_loop`), from kf's tracked
        pose and, when that does not align, from δ's; without keyframe images δ's minimum is the factor."""
        if self._loop_is_photometric(old, kf):
            T_new, why = self._photometric_loop(old, kf, kf.T_map_base)
            T_delta = sig = None
            if T_new is None:
                T_delta, sig, why_delta = self._delta_loop(old, kf)
                if T_delta is not None:
                    T_new, why_from_delta = self._photometric_loop(old, kf, T_delta)
                    why = f"{why}; from δ's minimum: {why_from_delta}"
                elif why_delta:
                    why = f"{why}; δ: {why_delta}"
            if T_new is None and self.config.odometry == "wheels" and T_delta is not None:
                # on wheels δ's loops held on the corridor: a loop the images cannot align is still δ's
                return self._add_delta_loop(old, kf, T_delta, sig)
            if T_new is None:
                self.backend.loops.append(LoopClosure(old.id, kf.id, 0.0, False, f"photometric: {why}"))
                return None
            return self._add_loop(old, kf, T_new, self.backend.tracked_cov(invert(old.T_map_base) @ T_new, kf))
        T_delta, sig, why = self._delta_loop(old, kf)
        if T_delta is None:
            if why is not None:        # (None: the views share too few flies to try)
                self.backend.loops.append(LoopClosure(old.id, kf.id, 0.0, False, why))
            return None
        return self._add_delta_loop(old, kf, T_delta, sig)

    def _add_delta_loop(self, old: Keyframe, kf: Keyframe, T_delta: np.ndarray, sig: np.ndarray) -> int:
        return self._add_loop(old, kf, T_delta, self._delta_covariance(np.diag(sig ** 2)))

    def _add_loop(self, old: Keyframe, kf: Keyframe, T_new: np.ndarray, cov: np.ndarray) -> int:
        """The loop factor old→kf saying kf is at T_new (map), recorded with how far it moves kf."""
        moved = float(np.linalg.norm(planar_from_transform(invert(kf.T_map_base) @ T_new)[:2]))
        self.backend.loops.append(LoopClosure(old.id, kf.id, moved, True))
        return self.backend.add_loop(old, kf, T_new, cov)

    def _delta_loop(self, old: Keyframe, kf: Keyframe):
        """(kf's pose in the map, its per-axis σ, '') from kf's flies registered against the old
        keyframe's (δ, planar, around kf's pose), or (None, None, why) (why None when the views share
        too few flies to try).  Axes whose minimum sits on the window's edge (along a corridor) are pinned and
        their sigma made loose.

        Only the two views' overlap registers: kf's flies the old camera sees, against the old flies
        kf's camera sees.  Two keyframes metres apart along a corridor share a small part of the nearer
        one's flies; the rest, with no counterpart, slide it to the window's edge along the corridor, and
        the heading and lateral offset then take what the pinned axis cannot.

        The old side is the old keyframe with its neighbours (``local_keyframes`` of them, by id: poses
        registered one to the next, so consistent with each other), as tracking registers against a local
        map, not one keyframe: on the loop scenario a new keyframe 2.5 m behind the first one shared 275 of
        its flies with it, and δ against that one keyframe's flies was 2.8° and 0.23 m off; against the
        three keyframes around it, 0.1° and 0.02 m."""
        c = self.config
        half = c.local_keyframes // 2
        near = [k for k in self.backend.archive.values()       # (old enough to close a loop, like old)
                if abs(k.id - old.id) <= half and k.id <= max(old.id, kf.id - c.loop_min_separation)]
        A_map = transform_points(kf.T_map_base, kf.points.astype(np.float64))
        in_a = np.zeros(len(A_map), bool)
        for k in near:
            in_a |= self._in_view(A_map, k.T_map_base)
        old_map = np.concatenate([k.points_map for k in near]).astype(np.float64)
        in_b = self._in_view(old_map, kf.T_map_base)
        if min(in_a.sum(), in_b.sum()) < c.min_flies:
            return None, None, None
        A = kf.points[in_a].astype(np.float64)
        B = transform_points(invert(kf.T_map_base), old_map[in_b])
        weights_a = kf.fitness[in_a] / max(float(kf.fitness.max()), 1e-12)
        window = np.array(c.loop_window, dtype=float)

        def register(win):
            return register_planar(A, B, plane="body", window=tuple(win), eps=c.eps, weights_a=weights_a,
                                   stereo=self.stereo, seed=int(kf.stamp_ns % (2**31)), lattice=(7, 7, 7),
                                   curvature=False)
        try:
            res = register(window)
            pinned = np.zeros(3, bool)
            if (not res.ok and res.reason.startswith("minimum on the search window boundary")
                    and np.all(np.isfinite(res.params))):
                pinned = np.abs(res.params) > 0.98 * window
                if not pinned.all():
                    res = register(np.where(pinned, 0.0, window))
        except PopulationError as e:
            return None, None, str(e)
        if self._information(res) is None:
            return None, None, res.reason
        sig = np.where(pinned, 1.0, np.asarray(c.registration_sigma, dtype=float))
        return kf.T_map_base @ invert(planar_pose(*res.params)), sig, ""

    def _keeps_images(self) -> bool:
        """Whether keyframes keep their images: only for the loops that align on them."""
        c = self.config
        return self.backend is not None and c.loop_closure and c.loop_photometric

    def _loop_is_photometric(self, old: Keyframe, kf: Keyframe) -> bool:
        """Whether a loop between these keyframes is measured on their fly neighbourhoods: with a
        calibration and both keyframes' images (not a map saved without them).  On deep street scenes
        δ's loop minima are biased by the far flies' depth errors, and the graph bent the tracked
        trajectory to them (docs/design/localiser.md)."""
        return (self.config.loop_photometric and self.backend.camera is not None
                and old.image is not None and kf.image is not None)

    def _photometric_loop(self, old: Keyframe, kf: Keyframe, T_start: np.ndarray):
        """(kf's pose in the map, '') from the two keyframes aligned on each other's flies from the start
        ``T_start`` (common.slam.tracking.align_keyframes), or (None, why): when they do not align, or
        land beyond the loop window from kf's tracked pose (a basin δ's window would not have searched)."""
        c = self.config
        T_new, why = align_keyframes(old, kf, self.calibration.K_rectified, self.T_base_camera, [T_start],
                                     max(1, c.photometric_levels - 1), c.photometric_min_inliers)
        if T_new is None:
            return None, why
        moved = planar_from_transform(invert(kf.T_map_base) @ T_new)
        if np.any(np.abs(moved) > np.asarray(c.loop_window, dtype=float)):
            return None, f"aligned {np.round(moved, 2).tolist()} from the tracked pose, beyond the loop window"
        return T_new, ""

    def _delta_covariance(self, cov3: np.ndarray) -> np.ndarray:
        """6×6 covariance of a δ registration, which measures x, y and yaw in the body plane: on wheels
        the plane holds z, roll and pitch; without, δ says nothing of them (UNCONSTRAINED_SIGMA): a
        planar robot's tight out-of-plane sigmas would pin a car's loop factors to its drifted height."""
        if self.config.odometry == "wheels":
            return planar_covariance(cov3)
        return planar_covariance(cov3, *UNCONSTRAINED_SIGMA)

    def _apply_correction(self, C: np.ndarray) -> None:
        """Move the state that lives in the map frame (map→odom, tracking, reference view) by C."""
        self.T_map_odom = orthonormalised(C @ self.T_map_odom)
        if self._track.last_T_map_base is not None:
            self._track.last_T_map_base = orthonormalised(C @ self._track.last_T_map_base)
        if self._reference is not None:
            self._reference.T_map_cam = orthonormalised(C @ self._reference.T_map_cam)

    def map_keyframes(self) -> list[Keyframe]:
        """Every keyframe of the map: the back-end's archive (all of them), else the sliding window."""
        return list(self.backend.archive.values()) if self.backend is not None else list(self.keyframes)

    def map_edges(self) -> list:
        return list(self.backend.graph.edges().values()) if self.backend is not None else []

    def load_map(self, data) -> None:
        """Start from a saved map (common.slam.mapfile.FlyMapData): its keyframes (the newest
        ``max_keyframes`` in the window) and, with the back-end, its graph.  Only before the first update."""
        if self.keyframes or self._history:
            raise LocaliserError("a map can only be loaded into a fresh localiser")
        kfs = sorted(data.keyframes, key=lambda k: k.id)
        for mk in kfs:
            image = getattr(mk, "image", None)
            if not (self._keeps_images() and image is not None and self.calibration is not None
                    and image.shape == ((self.calibration.height + 1) // 2, (self.calibration.width + 1) // 2)):
                image = None            # (another camera's image would align with the wrong intrinsics)
            kf = Keyframe(int(mk.id), int(mk.stamp_ns), np.asarray(mk.T_map_base, float).copy(),
                          np.asarray(mk.points, np.float32), np.asarray(mk.fitness, np.float32), image=image)
            self.keyframes.append(kf)
            if self.backend is not None:
                self.backend.archive[kf.id] = kf
                self.backend.graph.add_keyframe(kf.id, kf.T_map_base)
        if self.backend is not None and kfs:
            for e in data.edges:
                self.backend.graph.add_edge(e)
            if not any(e.kind == "prior" for e in data.edges):
                first = self.backend.archive[kfs[0].id]
                self.backend.graph.add_prior(first.id, first.T_map_base, np.diag([1e-3] * 3 + [1e-4] * 3) ** 2)
            self.backend._last_id = kfs[-1].id
            self._optimise_graph(kfs[-1].id)     # unsolvable: the saved poses stand
        self._next_id = max((k.id for k in kfs), default=-1) + 1
        self.map_loaded = bool(kfs)
        self._anchor_since = None        # (the saved keyframes' stamps are another run's clock)
        self._map_cache = self._visible_cache = None

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps, T_map_base (N, 4, 4)) of every estimate, re-expressed in the current (optimised) poses
        of the keyframes around it: the one newest when it was made and the next one made on the same
        run of estimates, blended by the share of the way between the two the robot had come (driven
        and turned, :meth:`_motion`, step by step: a robot that waits or turns back keeps its share).
        After a loop closure this is the corrected trajectory, with no step where one keyframe's
        correction hands over to the next's.  A run ends at a relocalisation or a loaded map: no
        estimate follows a keyframe made after its run, and the newest estimates follow their keyframe
        alone.  Vectorised: the live localiser rewrites the whole trajectory every few seconds."""
        if not self._history:
            return np.zeros(0, np.int64), np.zeros((0, 4, 4))
        stamp_list, anchors, rel_list = zip(*self._history)
        stamps = np.array(stamp_list, np.int64)
        rel = np.array(rel_list, dtype=float)
        ids = np.array([-1 if kf is None else kf.id for kf in anchors], np.int64)
        firsts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
        lasts = np.r_[firsts[1:], len(ids)] - 1
        group = np.repeat(np.arange(len(firsts)), lasts - firsts + 1)
        # per group of consecutive estimates on one keyframe: that keyframe's pose, the pose the next
        # keyframe gives them, the keyframe relative to the next as made, and the stamp the blend starts
        # at (never, without a next keyframe)
        own_kf, via_kf, in_next = (np.tile(np.eye(4), (len(firsts), 1, 1)) for _ in range(3))
        start = np.full(len(firsts), np.iinfo(np.int64).max)
        for g, first in enumerate(firsts):
            kf = anchors[first]
            if kf is None:
                continue
            own_kf[g] = via_kf[g] = kf.T_map_base
            if kf.id in self._next_in_chain:
                kf_next, in_next[g], start[g] = self._next_in_chain[kf.id]
                via_kf[g] = kf_next.T_map_base @ in_next[g]
        # the way come since the run's first estimate on the keyframe, against the whole way to the next
        moving = stamps > start[group]
        step = np.zeros(len(ids))
        step[1:] = self._motion(_between(rel[:-1], rel[1:]))
        step[~moving] = 0.0
        step[firsts] = 0.0
        come = np.cumsum(step)
        come -= come[firsts][group]
        way = (come[lasts] + self._motion(in_next @ rel[lasts]))[group]     # (a motion and its inverse: as far)
        share = np.where(moving & (way > 0), np.clip(come / np.where(way > 0, way, 1.0), 0.0, 1.0), 0.0)
        return stamps, _blend(own_kf[group] @ rel, via_kf[group] @ rel, share)

    def _motion(self, rel: np.ndarray) -> np.ndarray:
        """How far poses (N, 4, 4) are from the identity, in keyframe spacings: metres over
        ``keyframe_distance_m`` plus angle over ``keyframe_angle_rad`` (the front end drifts while it
        turns on the spot as well as while it drives)."""
        c = self.config
        angle = np.arccos(np.clip((np.trace(rel[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))
        return np.linalg.norm(rel[:, :3, 3], axis=1) / c.keyframe_distance_m + angle / c.keyframe_angle_rad

    def relocalised(self, stamp_ns: int, T_map_base: np.ndarray, T_odom_base: np.ndarray | None = None) -> None:
        """Restart tracking from a pose found by a global search over the map (relocalisation): the
        motion model forgets its velocity, the tracking reference is dropped (the next update builds one
        at this pose) and map→odom is re-anchored when odometry is known.  The map is not touched; the
        trajectory starts a new run of estimates (see :meth:`trajectory`)."""
        T_map_base = orthonormalised(np.asarray(T_map_base, dtype=float))
        self._anchor_since = None
        self._track = _Tracking()
        self._track_update(stamp_ns, T_map_base)
        self._reference = None
        self._last_fix_stamp = stamp_ns
        self._updates_since_fix = 0
        self._driven_since_fix = self._turned_since_fix = self._fast_turn_since_fix = 0.0
        pool = self._pool
        if pool:     # the map's nearest keyframe: tracking may use the old keyframes around it
            self._revisit_anchor = min(pool, key=lambda kf: np.linalg.norm(kf.T_map_base[:2, 3] - T_map_base[:2, 3])).id
        if T_odom_base is not None:
            T_odom_base = np.asarray(T_odom_base, dtype=float)
            self.T_map_odom = orthonormalised(T_map_base @ invert(T_odom_base))
            self._last_odom, self._last_odom_stamp = T_odom_base.copy(), stamp_ns

    # ------------------------------------------------------------------------------ prediction
    def _predict(self, stamp_ns: int, T_odom_base: np.ndarray | None) -> tuple[np.ndarray, str]:
        if T_odom_base is None:
            # No odometry, no measured turn rate: a rate left over from the last odometry would keep
            # refusing registrations (with a stale reason) for as long as odometry is missing.
            self._turn_rate = 0.0
        else:
            T = self.T_map_odom @ T_odom_base
            if self._last_odom is not None:
                # Motion since the previous update from odometry alone: a correction of map->odom is not
                # motion, and counting it as turning tripped the turn-rate limit after every fix.
                rel = invert(self._last_odom) @ T_odom_base
                self._driven_since_fix += float(np.linalg.norm(rel[:2, 3]))
                yaw = float(np.arctan2(rel[1, 0], rel[0, 0]))
                turned = abs(yaw)
                self._turned_since_fix += turned
                dt = (stamp_ns - self._last_odom_stamp) * 1e-9
                self._turn_rate = turned / dt if dt > 1e-3 else self._turn_rate
                if self._turn_rate > self.config.max_turn_rate_radps:
                    self._fast_turn_since_fix += yaw
            self._last_odom, self._last_odom_stamp = T_odom_base.copy(), stamp_ns
            return T, "odometry"
        tr = self._track
        if tr.last_T_map_base is None:
            return np.eye(4), "none"
        if tr.last_motion is None:
            return tr.last_T_map_base.copy(), "none"
        dt = (stamp_ns - tr.last_stamp) * 1e-9
        return tr.last_T_map_base @ scaled_motion(tr.last_motion, dt / tr.last_dt), "constant velocity"

    def _prediction_steps(self, stamp_ns: int) -> float:
        """How far the constant-velocity prediction reaches past the last fix, in model steps: the
        updates since it, or the time since it over the last step's when populations were skipped
        (a live localiser busy with one population misses the next ones)."""
        steps, tr = 1.0 + self._updates_since_fix, self._track
        if tr.last_fix is not None and tr.last_dt > 0:
            steps = max(steps, (stamp_ns - tr.last_fix[0]) * 1e-9 / tr.last_dt)
        return steps

    def _track_update(self, stamp_ns: int, T_map_base: np.ndarray, registered: bool = True) -> None:
        """Teach the constant-velocity model this pose.  A fix after unregistered updates (which only
        carried the prediction on) measures the motion since the last fix, over all that time: from
        the last placeholder it would be that whole correction in one step."""
        tr = self._track
        if tr.last_T_map_base is not None and stamp_ns > tr.last_stamp:
            t0, T0 = tr.last_stamp, tr.last_T_map_base
            if registered and tr.last_fix is not None and tr.last_fix[0] < tr.last_stamp:
                t0, T0 = tr.last_fix
            tr.last_dt = (stamp_ns - t0) * 1e-9
            tr.last_motion = orthonormalised(invert(T0) @ T_map_base)
        tr.last_T_map_base, tr.last_stamp = orthonormalised(T_map_base), stamp_ns
        if registered:
            tr.last_fix = (stamp_ns, tr.last_T_map_base)

    # ---------------------------------------------------------------------------------- update
    def update(self, stamp_ns: int, positions_cam: np.ndarray, fitness: np.ndarray,
               T_odom_base: np.ndarray | None = None, generation: int | None = None,
               image: np.ndarray | None = None, next_frame: bool = False) -> Estimate:
        """Localise one population (left optical frame) seen at ``stamp_ns``; see the module doc.

        ``generation``: the evolver's generation count; the map starts only from a population that has
        evolved ``min_generations``. ``image``: the grey left image the flies were evaluated on; with it
        the pose is tracked on the flies' neighbourhoods (against the tracking reference view).
        ``next_frame``: this population is of the camera frame right after the previous one (no frame
        skipped, no stall: LocaliserCore decides); then a first fix is tried however long after the
        map's origin it comes, since no population could have come sooner (see _first_fix_too_late)."""
        if T_odom_base is not None:
            T_odom_base = np.asarray(T_odom_base, dtype=float)
            if T_odom_base.shape != (4, 4):
                raise LocaliserError(f"T_odom_base must be a 4×4 transform, got shape {T_odom_base.shape}")
            if not np.all(np.isfinite(T_odom_base)):
                raise LocaliserError("T_odom_base is not finite")
        c = self.config
        if c.odometry == "visual":
            T_odom_base = None
        points, fit = self.select_flies(positions_cam, fitness)
        T_pred, source = self._predict(stamp_ns, T_odom_base)
        self._steps_since_fix = self._prediction_steps(stamp_ns)
        cov_pred = np.diag([0.05, 0.05, 1e-6, 1e-6, 1e-6, 0.02]) ** 2
        new_pyramid = view_flies = None
        if image is not None and c.photometric and self.calibration is not None:
            image = np.asarray(image)
            if image.shape[:2] != (self.calibration.height, self.calibration.width):
                raise LocaliserError(f"image is {image.shape[1]}x{image.shape[0]}, the calibration "
                                     f"{self.calibration.width}x{self.calibration.height}")
            new_pyramid = pyramid(image, c.photometric_levels, c.photometric_smooth_px)
            view_flies = (positions_cam, fitness, image, new_pyramid)

        def finish(T_map_base, status, registered, cov, delta=float("nan"), may_add=True, links=()):
            # every estimate rigid: it becomes keyframes, references and corrections, where the rounding
            # of a slightly skewed rotation doubled with each keyframe until the evolver refused it
            T_map_base = orthonormalised(T_map_base)
            added = False
            # Registered poses extend the map; so does odometry when the map no longer covers the robot
            # (a long featureless stretch), or the map would stop growing.
            far = self._distance_to_map(T_map_base) > 2 * c.keyframe_distance_m
            # (the coverage test projects the whole map: asked last, and only when it decides)
            if (may_add and len(points) >= c.min_flies and self._needs_keyframe(T_map_base)
                    and (registered or far or self._local_keyframes(T_map_base)[1] < c.min_view_coverage)):
                prev = self.keyframes[-1] if self.keyframes else None
                kf = self._add_keyframe(stamp_ns, T_map_base, points, fit,
                                        view_flies[2] if view_flies is not None else None)
                if prev is not None:
                    since = self._anchor_since
                    self._next_in_chain[prev.id] = (
                        kf, invert(T_map_base) @ prev.T_map_base,
                        since[1] if since is not None and since[0] == prev.id else stamp_ns)
                added = True
                if self.backend is not None:
                    C = self._graph_keyframe(kf, list(links) if registered else [], cov if registered else None)
                    if not np.array_equal(C, np.eye(4)):
                        T_map_base = orthonormalised(C @ T_map_base)
                        self._apply_correction(C)
            if T_odom_base is not None:
                self.T_map_odom = orthonormalised(T_map_base @ invert(T_odom_base))
            # Before the map exists the pose is a placeholder, not a measurement: it must neither teach
            # the motion model a velocity (live, the first populations come seconds apart while the
            # flies converge, and a 'standing' camera then refuses the first true motion), nor anchor a
            # tracking reference at the map's origin, nor enter the trajectory.
            if self.keyframes:
                if view_flies is not None and (registered or self._reference is None):
                    self._renew_reference(T_map_base, view_flies)
                    self._newest_view = (T_map_base @ self.T_base_camera, view_flies)
                self._track_update(stamp_ns, T_map_base, registered)
                self._updates_since_fix = 0 if registered else self._updates_since_fix + 1
                anchor = self.keyframes[-1]       # the trajectory starts with the map
                self._history.append((stamp_ns, anchor, invert(anchor.T_map_base) @ T_map_base))
                if self._anchor_since is None or self._anchor_since[0] != anchor.id:
                    self._anchor_since = (anchor.id, stamp_ns)
            return Estimate(stamp_ns, T_map_base, self.T_map_odom.copy(), cov, status, registered, added, delta)

        def fixed(T_map_base, cov, delta=float("nan"), links=(), may_add=True):
            self._last_fix_stamp = stamp_ns
            self._driven_since_fix = 0.0
            self._turned_since_fix = 0.0
            self._fast_turn_since_fix = 0.0
            return finish(T_map_base, "ok", True, cov, delta, may_add=may_add, links=links)

        if not self.keyframes and generation is not None and generation < c.min_generations:
            return finish(T_pred, f"odometry only: waiting for the flies to converge (generation "
                                  f"{generation} < {c.min_generations})", False, cov_pred, may_add=False)
        # Turning faster than max_turn_rate_radps (wheel odometry), δ and keyframes wait for the turn to
        # end, but the neighbourhoods may still track it (below, from the odometry's prediction).  No map
        # starts then: a map started from a population evolved while turning fast is the worst case of
        # the bent map this limit prevents.
        turning_fast = self._turn_rate > c.max_turn_rate_radps
        if turning_fast and not self.keyframes:
            return finish(T_pred, f"odometry only: turning at {np.rad2deg(self._turn_rate):.0f}°/s "
                                  f"(> {np.rad2deg(c.max_turn_rate_radps):.0f}°/s)", False, cov_pred, may_add=False)
        restarted = "" if next_frame else self._first_fix_too_late(stamp_ns, source)
        if restarted:
            self._restart_map()
            T_pred, source = self._predict(stamp_ns, T_odom_base)
        if not self.keyframes:
            if len(points) < c.min_flies:
                return finish(T_pred, f"odometry only: {len(points)} usable flies to start a map", False, cov_pred)
            return finish(T_pred, f"initialised{restarted}", False, np.zeros((6, 6)))
        photometric_reason = ""
        if new_pyramid is not None:
            # no motion known yet (the first frames of a visual-only run): search the lattice first
            fix, photometric_reason = self._photometric(new_pyramid, T_pred, T_pred, source,
                                                        search=source == "none")
            # the reference lost from view (or the motion unknown), not a fix the prediction
            # disbelieves: the newest view, aligned from the same prediction, would only find a
            # minimum nearer to it
            lost = fix is None and (source == "none"
                                    or self._reference_share_in_view(T_pred) < c.photometric_min_inliers)
            if fix is None and lost:
                fix = self._photometric_from_newest_view(new_pyramid, T_pred, source)
            if source == "none" and view_flies is not None:
                fix = self._from_both_sides(new_pyramid, view_flies, T_pred, fix)
            if source == "constant velocity" and (fix is None or self._poorly_fitted(fix)):
                fix, why = self._best_of_starts(new_pyramid, T_pred, source, fix)
                photometric_reason = why or photometric_reason
            if source == "odometry" and 0 < abs(self._fast_turn_since_fix) <= c.max_slip_rad:
                fix = self._slip_hypothesis(new_pyramid, T_pred, fix)
            if fix is not None:
                self._fit_residuals.append(fix.residual)
                return fixed(fix.T_map_base, fix.covariance, may_add=not turning_fast)
        if turning_fast:
            return finish(T_pred, f"odometry only: turning at {np.rad2deg(self._turn_rate):.0f}°/s "
                                  f"(> {np.rad2deg(c.max_turn_rate_radps):.0f}°/s)", False, cov_pred, may_add=False)
        if len(points) < c.min_flies:
            why = f"; photometric: {photometric_reason}" if photometric_reason else ""
            return finish(T_pred, f"odometry only: {len(points)} usable flies (< {c.min_flies}){why}", False, cov_pred)
        # B: the local map in the predicted base frame; A: the flies in the (unknown) true base frame.
        B = transform_points(invert(T_pred), self.local_map(T_pred))
        links = [self._pool[i].id for i in self._local_keyframes(T_pred)[0]]
        if source == "odometry":
            sxy, syaw = self._prior_sigmas()
            window = np.clip(3.0 * np.array([sxy, sxy, syaw]), c.window, c.max_window)
        else:
            window = np.array((1.0, 1.0, np.deg2rad(20)), dtype=float)

        tracking = (source == "odometry" and self._last_fix_stamp is not None
                    and 0 <= (stamp_ns - self._last_fix_stamp) * 1e-9 <= c.tracking_gap_s
                    and self._turn_rate <= c.tracking_max_turn_rate_radps)
        lattice = (1, 1, 1) if tracking else (7, 7, 7)

        def register(win):
            return register_planar(points, B, plane="body", window=tuple(win), eps=c.eps, weights_a=fit / fit.max(),
                                   stereo=self.stereo, seed=int(stamp_ns % (2**31)), lattice=lattice,
                                   curvature=False)   # the measurement model is registration_sigma (see _information)
        try:
            res, pinned = self._register_pinning_edges(register, window, tracking)
        except PopulationError as e:   # e.g. a degenerate map; odometry carries on
            return finish(T_pred, f"rejected: {e}", False, cov_pred)
        info = self._information(res)
        if info is None:
            return finish(T_pred, f"rejected: {res.reason}", False, cov_pred, res.delta)
        info[pinned, :] = 0.0
        info[:, pinned] = 0.0
        fused = self._fuse_with_prior(res.params, info, source)
        if fused is None:
            return finish(T_pred, "rejected: registration disagrees with odometry beyond the gate", False,
                          cov_pred, res.delta)
        f_post, cov3 = fused
        # f maps B's frame (predicted base) into A's frame (true base): T_true_pred.
        T_map_base = T_pred @ invert(planar_pose(*f_post))
        if new_pyramid is not None:       # δ found the basin; the neighbourhoods pin the pose in it
            fix, _ = self._photometric(new_pyramid, T_map_base, T_pred, source)
            if fix is not None and source != "odometry" and self._poorly_fitted(fix):
                # without wheels nothing else vouches for δ's basin, and a neighbourhood fit this poor
                # says it is the wrong one (a car backing up after a stop)
                return finish(T_pred, f"rejected: δ registration's neighbourhoods fit poorly (residual "
                                      f"{fix.residual:.1f}, recent {np.median(self._fit_residuals):.1f})",
                              False, cov_pred, res.delta)
            if fix is not None:
                self._fit_residuals.append(fix.residual)
                return fixed(fix.T_map_base, fix.covariance, res.delta, links)
        if source != "odometry":
            # δ alone, unconfirmed by the neighbourhoods, is held to what the motion model allows: with
            # only a weak constant-velocity prior its χ² gate lets a wrong minimum turn the pose by 15°+
            # (a turn's end in a corridor), and the next prediction then doubles that turn.
            why = self._implausible(T_pred, T_map_base, source)
            if why:
                return finish(T_pred, f"rejected: δ registration {why}", False, cov_pred, res.delta)
        return fixed(T_map_base, self._delta_covariance(cov3), res.delta, links)

    def _first_fix_too_late(self, stamp_ns: int, source: str) -> str:
        """Why the map restarts from this population ('' when it does not): no motion is known yet
        (visual-only, the map holds only its origin) and this population came more than
        ``first_fix_gap_s`` (doubled at each restart) after the origin.  Not asked of a population
        of the camera's next frame (``update``'s ``next_frame``): no population can come sooner.

        The unknown-motion search reaches ~0.25 × the flies' median depth (common.registration.
        photometric.coarse_candidates): a live start whose first frame was slow put a car's first fix
        at the edge of that reach, where it sometimes settled metres short.  Later populations come a
        frame apart, and the doubling lets a machine slower than the limit still start.  A camera
        slower than the limit would only lose its first frame to a restart."""
        if (self.config.odometry != "visual" or source != "none" or len(self.keyframes) != 1
                or len(self._history) != 1 or self.map_loaded):
            return ""   # (wheels: a population without odometry is a gap in it, not an unknown motion)
        gap_s = (stamp_ns - self._history[0][0]) * 1e-9
        limit = self.config.first_fix_gap_s * 2.0 ** self.map_restarts
        if gap_s <= limit:
            return ""
        return f" (the map restarted: {gap_s:.2f} s after its origin, > {limit:.2f} s with the motion unknown)"

    def _restart_map(self) -> None:
        """Forget the one-keyframe map and its origin: the next update starts a map again."""
        self.map_restarts += 1
        self._empty_map(self.backend.archive_config if self.backend is not None else None)

    def _renew_reference(self, T_map_base: np.ndarray, view_flies) -> None:
        """Make this population the tracking reference once the camera has left the current one's
        neighbourhood: moved ``photometric_reference_spacing`` × its flies' median depth, or turned."""
        c = self.config
        T_map_cam = T_map_base @ self.T_base_camera
        ref = self._reference
        if ref is not None:
            rel = invert(ref.T_map_cam) @ T_map_cam
            depth = float(np.median(ref.points[:, 2])) if len(ref.points) else 1.0
            if (np.linalg.norm(rel[:3, 3]) < c.photometric_reference_spacing * depth
                    and np.linalg.norm(so3_log(rel[:3, :3])) < c.photometric_reference_angle_rad):
                return
        positions, fit, image, image_pyramid = view_flies
        self._reference = reference_view(T_map_cam, positions, fit, image, c.photometric_flies, 0.3,
                                         c.photometric_levels, image_pyramid, smooth_px=c.photometric_smooth_px)

    def _poorly_fitted(self, fix) -> bool:
        """Whether a photometric fix's residual scale is well above that of the recent fixes: a wrong
        minimum.  Its share of inliers cannot tell (the inlier threshold scales with the residual); on a
        hand-held rig that stopped to turn, the alignment from the constant-velocity prediction ended
        with σ̂ = 7.4 grey levels at 0.3 m / 4° off, against 2.7 from the true pose."""
        if len(self._fit_residuals) < MIN_FITS_TO_JUDGE:
            return False
        return fix.residual > POOR_FIT_RATIO * float(np.median(self._fit_residuals))

    def _fits_well(self, fix) -> bool:
        """Whether enough recent fixes exist to judge and this one fits as well as they do."""
        return len(self._fit_residuals) >= MIN_FITS_TO_JUDGE and not self._poorly_fitted(fix)

    def _best_of_starts(self, new_pyramid, T_pred: np.ndarray, source: str, fix):
        """(the best-fitting fix, '') of ``fix`` and alignments from other starts than the constant-
        velocity prediction — the last pose (the camera stopped: a pause, a turn on the spot) and the
        lattice search around the prediction —, or (None, why) when none gives one."""
        candidates, why = [fix] if fix is not None else [], ""
        if self._track.last_T_map_base is not None:
            alt, why = self._photometric(new_pyramid, self._track.last_T_map_base, T_pred, source, any_fitted=True)
            candidates.append(alt)
        alt, why_search = self._photometric(new_pyramid, T_pred, T_pred, source, search=True, any_fitted=True)
        candidates.append(alt)
        candidates = [f for f in candidates if f is not None]
        # a fix beyond the motion model's limit only when nothing within it fits well
        near = [f for f in candidates if not self._implausible(T_pred, f.T_map_base, source)]
        if near and not all(self._poorly_fitted(f) for f in near):
            candidates = near
        if not candidates:
            return None, why_search or why
        return min(candidates, key=lambda f: f.residual), ""

    def _from_both_sides(self, new_pyramid, view_flies, T_pred: np.ndarray, fix):
        """The motion unknown (the map's first fix), ``fix`` or a fix aligned from the motion found the
        other way round — this population's flies aligned back into the reference image —, whichever
        fits clearly better.  Live, the population the map starts from may have had only ~30
        generations on its own frame while the camera moved a metre a frame; the newer one has more,
        and from the lattice the reference's weaker flies sometimes took a sideways step with a turn
        for the forward motion."""
        ref, c = self._reference, self.config
        if ref is None:
            return fix
        positions, fit, image, image_pyramid = view_flies
        back = reference_view(np.eye(4), positions, fit, image, c.photometric_flies, 0.3, c.photometric_levels,
                              image_pyramid, smooth_px=c.photometric_smooth_px)
        T_new_ref = reverse_motion(ref, back.points, back.weights, new_pyramid, self.calibration.K_rectified,
                                   c.photometric_min_inliers)
        if T_new_ref is None:
            return fix
        T_start = ref.T_map_cam @ invert(T_new_ref) @ invert(self.T_base_camera)
        alt, _ = self._photometric(new_pyramid, T_start, T_pred, "none")
        if alt is not None and (fix is None or alt.residual < SWITCH_RESIDUAL_RATIO * fix.residual):
            return alt
        return fix

    def _reference_share_in_view(self, T_map_base: np.ndarray) -> float:
        """Share of the tracking reference's flies inside the left image of a camera at ``T_map_base``."""
        ref = self._reference
        if ref is None or len(ref.points) == 0:
            return 0.0
        T_cam_ref = invert(T_map_base @ self.T_base_camera) @ ref.T_map_cam
        cal = self.calibration
        u, _, v = cal.project(transform_points(T_cam_ref, ref.points.astype(np.float64)))   # NaN behind
        with np.errstate(invalid="ignore"):
            inside = (u >= 0) & (u < cal.width) & (v >= 0) & (v < cal.height)
        return float(np.mean(inside))

    def _photometric_from_newest_view(self, new_pyramid, T_pred: np.ndarray, source: str):
        """A fix against the newest registered view when the tracking reference lost sight of the
        flies, or None.

        The reference is renewed only every few frames, and its fittest flies may crowd at one image
        edge (one well-textured near wall): a robot turning away from that edge loses sight of them all
        within a frame or two while the view itself is still well tracked.  The newest view, with its
        trusted flies spread over the image, overlaps the new image most; it becomes the reference when
        it gives the fix."""
        if self._newest_view is None or self._reference is None:
            return None
        T_map_cam, (positions, fit, image, image_pyramid) = self._newest_view
        c = self.config
        held = self._reference
        self._reference = reference_view(T_map_cam, positions, fit, image, c.photometric_flies, 0.3,
                                         c.photometric_levels, image_pyramid, K=self.calibration.K_rectified,
                                         trusted_fraction=c.keep_fraction, smooth_px=c.photometric_smooth_px)
        fix, _ = self._photometric(new_pyramid, T_pred, T_pred, source)
        if fix is None and source != "odometry":
            fix, _ = self._photometric(new_pyramid, T_pred, T_pred, source, search=True)
        if fix is None:
            self._reference = held
        return fix

    def _photometric(self, new_pyramid, T_start: np.ndarray, T_pred: np.ndarray, source: str, search: bool = False,
                     any_fitted: bool = False):
        """(Fix, '') from aligning the tracking reference's flies into the new image from ``T_start``,
        or (None, why); a fix implausibly far from the prediction is refused, unless ``any_fitted`` and
        it fits as well as the recent fixes do (within what the unknown-motion search spans): after a
        stop, the constant-velocity model's limit refused the exact fix of a car backing up."""
        if self._reference is None:
            return None, "no reference view yet"
        c = self.config
        fix, why = photometric_fix(self._reference, new_pyramid, self.calibration.K_rectified, T_start,
                                   self.T_base_camera, c.photometric_min_inliers, search=search)
        if fix is None:
            return None, why
        why = self._implausible(T_pred, fix.T_map_base, source)
        if why and any_fitted and self._fits_well(fix):
            why = self._implausible(T_pred, fix.T_map_base, "none")
        return (None, f"photometric fix {why}") if why else (fix, "")

    def _slip_hypothesis(self, new_pyramid, T_pred: np.ndarray, fix):
        """The better of ``fix`` (from the odometry's prediction) and a fix from the prediction without
        the turn the odometry reported faster than ``max_turn_rate_radps`` since the last fix: a wheel
        spinning on a slippery patch reports a turn that never happened, and tracking from a heading
        5-10° off then settles in a wrong minimum that every later fix inherits.  The alternative is
        held to the prior around its own prediction; it wins on the larger share of inliers.  Only for
        turns up to ``max_slip_rad``: a real fast turn of 90° (a scripted corner) leaves the reference
        view behind, so the odometry's fix fails for want of overlap, and an alternative facing the old
        way would win by default."""
        T_unslipped = T_pred @ planar_pose(0.0, 0.0, -self._fast_turn_since_fix)
        alt, _ = self._photometric(new_pyramid, T_unslipped, T_unslipped, "odometry")
        if alt is not None and (fix is None or alt.inliers > fix.inliers):
            self.slips_undone += 1
            return alt
        return fix

    def _implausible(self, T_pred: np.ndarray, T_fix: np.ndarray, source: str) -> str:
        """Why a fix is too far from the prediction to believe ('' when it is not).  With odometry: 4 σ
        of the prior.  With constant velocity: a change of speed up to half the last step and 5° of
        turn per update, growing with the updates since the last fix, or with the time since it in
        model steps when populations were skipped (the prediction's uncertainty grows while nothing
        confirms it; a fixed limit would never let go of a turn that has ended)."""
        jump = invert(T_pred) @ T_fix
        moved = np.linalg.norm(jump[:3, 3])
        turned = np.degrees(np.linalg.norm(so3_log(jump[:3, :3])))
        if source == "odometry":
            sxy, syaw = self._prior_sigmas()
            limit_m, limit_deg = max(4 * sxy, 0.05), max(np.degrees(4 * syaw), 1.0)
        elif source == "none":       # what the lattice search spans
            limit_m, limit_deg = np.inf, 10.0
        else:
            step = np.linalg.norm(self._track.last_motion[:3, 3]) if self._track.last_motion is not None else 1.0
            grown = self._steps_since_fix
            limit_m, limit_deg = (0.3 + 0.5 * step) * grown, 5.0 * grown
        if moved > limit_m or turned > limit_deg:
            return f"{moved:.2f} m / {turned:.1f}° from the prediction (limit {limit_m:.2f} m / {limit_deg:.1f}°)"
        return ""

    def _register_pinning_edges(self, register, window: np.ndarray, tracking: bool):
        """(result, pinned mask) of ``register(window)``.  A minimum on the window's edge in some
        parameters (typically along a corridor, where nothing pins the position) says nothing about
        them: they are pinned at the prediction and the rest registered again.  While tracking, what the
        previous frame pinned is pinned from the start, except every ``tracking_recheck_pinned`` frames
        (see LocaliserConfig)."""
        hint = self._pinned_hint if tracking else np.zeros(3, bool)
        if hint.any() and self._pinned_streak >= self.config.tracking_recheck_pinned:
            hint = np.zeros(3, bool)               # try the full window again
        if hint.any():
            res, pinned = register(np.where(hint, 0.0, window)), hint
        else:
            res = register(window)
            pinned = np.abs(res.params) > 0.98 * window if np.all(np.isfinite(res.params)) else np.zeros(3, bool)
            if not res.ok and res.reason.startswith("minimum on the search window boundary") and not pinned.all():
                res = register(np.where(pinned, 0.0, window))
            else:
                pinned = np.zeros(3, bool)
        self._pinned_hint = pinned
        self._pinned_streak = self._pinned_streak + 1 if hint.any() else 0
        return res, pinned

    # ------------------------------------------------------------------------------ fusion
    def _information(self, res) -> np.ndarray | None:
        """Information (inverse covariance of f's x, y, θ in the robot frame) a registration carries.

        Measured on the simulated corridor (tests/test_slam.py, bench/paper.py): registering a forward-
        looking population against the map pins the lateral position (≈1–3 cm) and the heading (≈0.1–0.5°)
        but hardly the position along the line of sight — walls parallel to the motion look the same
        when slid along (the aperture problem; errors of 0.1–0.3 m, biased by the partial overlap of the
        two views). The Hessian of the objective at that minimum does not show it reliably, and the
        sandwich covariance is over-confident, so the measurement model is a fixed per-axis noise in the
        robot frame (``registration_sigma``); the odometry prior then carries the longitudinal position.
        Minima on the window boundary and ambiguous ones carry no information.
        """
        if not np.all(np.isfinite(res.params)):
            return None
        reason = res.reason or ""
        if reason.startswith(("minimum on the search window boundary", "ambiguous", "too few", "degenerate")):
            return None
        return np.diag(1.0 / np.square(self.config.registration_sigma))

    def _prior_sigmas(self) -> tuple[float, float]:
        """Standard deviations (m, rad) of the odometry prediction since the last accepted registration."""
        return odometry_sigmas(self.config, self._driven_since_fix, self._turned_since_fix)

    def _fuse_with_prior(self, params: np.ndarray, info: np.ndarray, source: str):
        """Posterior of f's (x, y, θ) from the prediction (f = identity, covariance growing with the
        distance driven and the angle turned since the last fix) and the registration (params,
        information); None when the two disagree beyond the χ² gate."""
        c = self.config
        if source == "odometry":
            sxy, syaw = self._prior_sigmas()
        else:  # constant velocity or nothing: a weak prior
            sxy, syaw = 0.5, np.deg2rad(10)
        prior_info = np.diag([1 / sxy**2, 1 / sxy**2, 1 / syaw**2])
        p = np.asarray(params, dtype=float)
        if not np.all(np.isfinite(p)):
            return None
        post_info = prior_info + info
        post_cov = np.linalg.inv(post_info)
        # Mahalanobis² of the registration w.r.t. the prediction: pᵀ (Σ0 + I⁻¹)⁻¹ p = pᵀ I (Λ0 + I)⁻¹ Λ0 p.
        chi2 = float(p @ info @ post_cov @ prior_info @ p)
        if chi2 > c.gate_chi2:
            return None
        return post_cov @ info @ p, post_cov
