"""The localiser service's state machine without a bus: populations in, pose messages out.

``LocaliserCore`` wraps :class:`common.slam.FlyLocaliser` (public API only) and is what both the live
``services/localiser.py`` and ``common/lockstep.py`` run:

* ``on_calibration(StereoCalibrationMsg)`` latches the calibration; the localiser is created at the
  first population after it (later calibrations are kept for reference only: the map is in one frame).
* ``on_odometry(stamp_ns, T_odom_base)``: the odometry prior for populations without ``T_odom_camera``.
* ``on_population(FlyPopulation)`` → a :class:`LocaliserOutput` (``slam/pose`` PoseEstimate,
  ``slam/map_to_odom`` TransformMsg once the map exists — before its first keyframe there is no map
  frame to relate odom to —, the Estimate) or one with ``reason`` set: a population republished
  for the frame of the last population received (same ``source_seq`` and stamp) is skipped, one
  before any calibration or a malformed one is refused.  A population of the camera frame right after
  the last one localised (``source_seq`` + 1, at most ``max_frame_interval_s`` later) is told to the
  localiser as such: its first fix does not restart the map however slow the camera.
* ``map_message(stamp_ns)`` is the ``slam/map`` FlyMap; ``trajectory()`` the trajectory so far (as the
  back-end now has it); ``save_map(path)`` writes map.mcap, ``initial_map`` starts from a saved one.

Relocalising: started with ``initial_map`` the robot's pose in that map is unknown, so the core first
searches the map (common.slam.relocalise) with each population.  Until a search succeeds it returns a
``slam/pose`` whose status is ``'relocalising: <why>'`` (at the best guess so far, covariance 1e4 m²,
rad²: fusion fuses only status 'ok') and no ``map_to_odom`` (fusion and the planner take that one as
is); the localiser is not updated, so it adds no keyframe and records no trajectory.  Once found,
``FlyLocaliser.relocalised`` restarts tracking there and the same population is localised as usual.
``hint_map_to_odom`` (a restart: the last map→odom published) makes the search a narrow one around
``hint · T_odom_base``; after ``RelocaliserConfig.hint_frames`` searches without success, a global one.

Not thread-safe: the service serialises calls.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from common import messages as m
from common.geometry import invert, pose_from_transform
from common.core_inputs import LatchedInputs
from common.pose_buffer import PoseBuffer
from common.slam.config import ArchiveConfig, LocaliserConfig, LocaliserServiceConfig
from common.slam.localiser import Estimate, FlyLocaliser, LocaliserError
from common.slam.mapfile import FlyMapData, save_map
from common.slam.relocalise import Relocalisation, Relocaliser, RelocaliserConfig
from common.slam.standin import UNKNOWN_COVARIANCE


def warm_up(config: LocaliserConfig) -> float:
    """Load the localiser's numba kernels (and GTSAM's first solve) before the first population: a few
    visual-only updates with ``config`` on a small synthetic textured plane, with and without its image.
    Cold, the map's first fix takes about twice as long, and the populations the evolver publishes
    meanwhile are skipped, so the second fix has to span them too.  Returns the seconds spent."""
    from dataclasses import replace

    from common.fly.synthetic import textured_plane_pair
    t0 = time.perf_counter()
    disparity = 12.0
    calib, left, _, _ = textured_plane_pair(disparity)
    v, u = np.mgrid[4:calib.height - 4:3, 4:calib.width - 4:3].reshape(2, -1).astype(float)
    flies = calib.backproject(u, v, np.full(u.shape, disparity))
    fitness = np.ones(len(flies))
    grey = np.ascontiguousarray(left.mean(axis=2).astype(np.uint8))
    anywhere = dict(max_depth_m=None, min_height_m=-np.inf, max_height_m=np.inf)    # the plane's flies all count
    localiser = FlyLocaliser(calib.T_base_camera, replace(config, odometry="visual", min_flies=10, **anywhere),
                             calibration=calib)
    for k, image in enumerate((grey, grey, grey, None)):
        localiser.update(k * 100_000_000, flies, fitness, generation=10**6, image=image)
    return time.perf_counter() - t0


@dataclass
class LocaliserOutput:
    pose: m.PoseEstimate | None = None
    map_to_odom: m.TransformMsg | None = None
    estimate: Estimate | None = None
    reason: str | None = None       # 'republished', 'no calibration', 'bad population: ...', 'relocalising: ...'


class LocaliserCore(LatchedInputs):
    def __init__(self, config: LocaliserConfig | None = None, seed: int = 0, odometry: PoseBuffer | None = None,
                 initial_map: FlyMapData | None = None, relocaliser: RelocaliserConfig | None = None,
                 hint_map_to_odom: np.ndarray | None = None, archive: ArchiveConfig | None = None):
        """``initial_map``: a saved map (common.slam.mapfile.load_map) the localiser starts from, at an
        unknown pose (relocalising); ``hint_map_to_odom``: where a restart believes odom is in the map;
        ``archive``: the map's size bound (common.slam.backend.ArchiveConfig)."""
        self.config = config or LocaliserConfig()
        self.initial_map = initial_map
        self.seed = seed
        self.archive_config = archive or ArchiveConfig()
        super().__init__(odometry if odometry is not None else PoseBuffer(maxlen=1000))
        self.localiser: FlyLocaliser | None = None
        self._last_source: tuple[int, int] | None = None      # (source_seq, stamp) of the last population
        self._last_localised: tuple[int, int] | None = None   # ... and of the last one localised
        self.localised = 0              # populations localised so far
        self.relocalising = initial_map is not None and len(initial_map.keyframes) > 0
        self.relocaliser_config = relocaliser or RelocaliserConfig()
        self.relocalisation: Relocalisation | None = None     # the last search (the successful one, once found)
        self.searches = 0               # relocalisation searches run
        self._relocaliser: Relocaliser | None = None
        self._hint = None if hint_map_to_odom is None else np.asarray(hint_map_to_odom, float)
        self._previous: tuple | None = None   # (best T_map_base, T_odom_base, stamp, streak) of the last search


    @property
    def keyframes(self):
        return self.localiser.keyframes if self.localiser is not None else ()

    def _is_next_frame(self, source: tuple[int, int]) -> bool:
        """Whether (source_seq, stamp) is the camera frame right after the last one localised: the next
        seq, and a gap a camera's frame interval can be (a longer one is a stall or a restart)."""
        if self._last_localised is None:
            return False
        seq, stamp = self._last_localised
        gap_s = (source[1] - stamp) * 1e-9
        return source[0] == seq + 1 and 0.0 < gap_s <= self.config.max_frame_interval_s

    def on_population(self, pop: m.FlyPopulation) -> LocaliserOutput:
        source = (pop.source_seq, pop.header.stamp_ns)
        if source == self._last_source:
            return LocaliserOutput(reason="republished")
        if self.localiser is None and self._calibration_msg is None:
            return LocaliserOutput(reason="no calibration")     # (not remembered: sent again, it counts)
        self._last_source = source
        next_frame = self._is_next_frame(source)
        if self.localiser is None:
            cmsg = self._calibration_msg
            self.localiser = FlyLocaliser(cmsg.T_base_camera, self.config, seed=self.seed,
                                          calibration=m.calibration_from_msg(cmsg))
            if self.localiser.backend is not None:
                self.localiser.backend.archive_config = self.archive_config
            if self.initial_map is not None:
                self.localiser.load_map(self.initial_map)
                self._bound_map()
        loc = self.localiser
        stamp = pop.header.stamp_ns
        T_odom_base = self.odom_base_of(pop, loc.T_base_camera)
        try:
            if self.relocalising:
                searched = self._relocalise(pop, T_odom_base)
                if searched is not None:
                    return searched
            est = loc.update(stamp, pop.positions, pop.fitness, T_odom_base, pop.generation, image=pop.image,
                             next_frame=next_frame)
        except LocaliserError as e:
            return LocaliserOutput(reason=f"bad population: {e}")
        self._last_localised = source
        if est.keyframe_added:
            self._bound_map()
        p, q = pose_from_transform(est.T_map_odom)
        self.localised += 1
        return LocaliserOutput(
            pose=m.pose_msg(est.T_map_base, est.covariance, stamp_ns=stamp, status=est.status,
                            source_seq=pop.source_seq),
            map_to_odom=m.TransformMsg(child_frame_id=m.ODOM, translation=p, rotation=q,
                                       header=m.header(0, stamp, m.MAP)) if loc.keyframes else None,
            estimate=est)

    def _bound_map(self) -> None:
        """Hold the back-end's archive to ``archive.max_archive_keyframes`` (the window is kept)."""
        loc = self.localiser
        if loc.backend is not None:
            loc.backend.bound(keep={kf.id for kf in loc.keyframes})

    def _relocalise(self, pop: m.FlyPopulation, T_odom_base: np.ndarray | None) -> LocaliserOutput | None:
        """One relocalisation step: None once found (the localiser restarted there), else the
        'relocalising' output.  Raises LocaliserError on a malformed population."""
        loc, c = self.localiser, self.config
        stamp = pop.header.stamp_ns
        if self._relocaliser is None:
            self._relocaliser = Relocaliser(loc.map_keyframes(), self.relocaliser_config, stereo=loc.stereo,
                                            seed=self.seed)
        points, fit = loc.select_flies(pop.positions, pop.fitness)
        need = max(c.min_generations, self.relocaliser_config.min_generations)
        if pop.generation is not None and pop.generation < need:
            result = Relocalisation(None, f"waiting for the flies to converge (generation {pop.generation} < {need})")
        else:
            use_hint = self._hint is not None and T_odom_base is not None and self.searches < self.relocaliser_config.hint_frames
            hint = self._hint @ T_odom_base if use_hint else None
            previous = self._carried(T_odom_base, stamp)
            result = self._relocaliser.search(points, fit, hint=hint, previous=previous,
                                              streak=self._previous[3] if previous is not None else 0)
            self.searches += 1
        self.relocalisation = result
        if result.T_map_base is not None:
            loc.relocalised(stamp, result.T_map_base, T_odom_base)
            self.relocalising = False
            self._previous = None
            return None
        guess = result.best
        self._previous = None if guess is None else (guess, T_odom_base, stamp, result.streak)
        shown = guess if guess is not None else (self._hint @ T_odom_base if self._hint is not None
                                                 and T_odom_base is not None else np.eye(4))
        status = f"relocalising: {result.reason}"
        return LocaliserOutput(pose=m.pose_msg(shown, UNKNOWN_COVARIANCE, stamp_ns=stamp, status=status,
                                               source_seq=pop.source_seq), reason=status)

    def _carried(self, T_odom_base: np.ndarray | None, stamp_ns: int) -> np.ndarray | None:
        """The previous search's best answer moved to now: by odometry, or (none) as it was when the
        two are at most ``RelocaliserConfig.confirm_gap_s`` apart."""
        if self._previous is None:
            return None
        T, odom_then, then, _ = self._previous
        if T_odom_base is not None and odom_then is not None:
            return T @ invert(odom_then) @ T_odom_base
        return T if 0 <= (stamp_ns - then) * 1e-9 <= self.relocaliser_config.confirm_gap_s else None

    def map_message(self, stamp_ns: int) -> m.FlyMap | None:
        if self.localiser is None:
            return None
        kfs = []
        for kf in list(self.localiser.keyframes):
            p, q = pose_from_transform(kf.T_map_base)
            kfs.append(m.Keyframe(id=kf.id, stamp_ns=kf.stamp_ns, position=p, orientation=q, points=kf.points,
                                  fitness=kf.fitness))
        return m.FlyMap(keyframes=kfs, header=m.header(0, stamp_ns, m.MAP))

    def save_map(self, path) -> bool:
        """Write the map (every keyframe, the pose graph's edges) to ``path`` atomically; False when there
        is no map yet."""
        if self.localiser is None or not self.localiser.keyframes:
            return False
        loc = self.localiser
        save_map(path, loc.map_keyframes(), loc.map_edges(),
                 meta={"odometry": self.config.odometry, "pose_graph": self.config.pose_graph,
                       "loop_closures": sum(lc.accepted for lc in loc.loop_closures)})
        return True

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps (N,) int64, T_map_base (N, 4, 4)) of every localised population so far, in the map as
        the back-end now knows it (a loop closure corrects the poses before it too)."""
        if self.localiser is None:
            return np.zeros(0, np.int64), np.zeros((0, 4, 4))
        return self.localiser.trajectory()
