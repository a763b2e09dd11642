"""The evolver service's state machine without a bus: messages in, populations out.

``EvolverCore`` is what both the live ``services/evolver.py`` and ``common/lockstep.py`` (``flyslam
eval``) run, so a change to the per-frame step reaches both:

* ``on_calibration(StereoCalibrationMsg)`` latches the calibration; the next frame applies it (a new
  size, fx or baseline re-creates the evolver; a bad one is refused with a reason).
* ``on_odometry(stamp_ns, T_odom_base)`` and ``on_sonar(SonarScan)`` feed the odometry history and the
  sonar fitness term.
* ``on_frame(StereoFrame)`` decodes and checks the pair, moves the flies by the camera's motion since
  the previous frame, re-scores them on the new images, evolves them (``settle``: a
  :class:`SettlePolicy` live, a fixed number of generations in lockstep) and returns a
  :class:`FrameResult` with the ``FlyPopulation`` and the ``EvolverTrace`` of that frame.
  ``settle_scale`` < 1 (from the service's ``common.fly.scheduling.CpuGovernor`` when the machine is
  overloaded) shortens a live settle's time budget: the frame is published sooner, its CPU left to the
  localiser.
* ``step()`` evolves one generation between frames; ``population()`` is the current answer.

Not thread-safe: the service serialises calls.
"""
from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Callable

import cv2
import numpy as np

from common import messages as m
from common.camera import CalibrationError, StereoCalibration
from common.fly.config import EvolverConfig
from common.fly.evolver import FlyEvolver
from common.fly.fitness import FrameImages
from common.fly.scheduling import CpuGovernor, SettlePolicy, population_quality, settle
from common.geometry import invert
from common.images import frame_images
from common.core_inputs import LatchedInputs
from common.pose_buffer import PoseBuffer

log = logging.getLogger("flyslam.evolver")


NO_ODOMETRY_MIN_GENERATIONS = 30
# A frame's settle is done when the population is back to the best quality of this many recent frames,
# not merely the previous one's: against the previous frame alone each settle may end 1 - recovery
# lower than the last, and with no evolution between frames (degraded) the quality decays geometrically.
QUALITY_REFERENCE_FRAMES = 10


@dataclass
class EvolverServiceConfig:
    """The live evolver's scheduling (the algorithm's own settings are :class:`EvolverConfig`)."""
    settle_ms: float = field(default=40.0, metadata={"help": "longest evolution on a new frame before publishing (ms)"})
    min_generations: int = field(default=SettlePolicy.min_generations, metadata={
        "help": "generations on a new frame before it may be published"})
    recovery: float = field(default=SettlePolicy.recovery, metadata={
        "help": "publish once mean fitness is back to this fraction of the best of the last frames'"})
    publish_hz: float = field(default=10.0, metadata={"help": "republish rate between frames (Hz)"})
    duty: float = field(default=0.7, metadata={"help": "fraction of wall time spent evolving between frames"})
    cpu_budget: float = field(default=0.35, metadata={
        "help": "evolve between frames only while the last second's CPU is under this fraction of a core"})
    degraded_share: float = field(default=0.6, metadata={
        "help": "run degraded (no evolution between frames, shorter settles) below this CPU share "
                "and free_cpu_floor idle"})
    free_cpu_floor: float = field(default=0.1, metadata={
        "help": "run degraded only while the machine has less than this much of a core idle"})
    sonar_weight: float = field(default=0.0, metadata={"help": "weight of the sonar fitness term (0 = off)"})
    seed: int = field(default=0, metadata={"help": "random seed of the evolver"})

    def __post_init__(self):
        if not 0 <= self.cpu_budget <= 1 or not 0 < self.degraded_share <= 1 or not self.free_cpu_floor >= 0:
            raise ValueError(f"cpu_budget must be in [0, 1], degraded_share in (0, 1] and free_cpu_floor >= 0, got "
                             f"{self.cpu_budget}, {self.degraded_share} and {self.free_cpu_floor}")

    def settle_policy(self) -> SettlePolicy:
        return SettlePolicy(self.settle_ms / 1000, self.min_generations, self.recovery)

    def governor(self) -> CpuGovernor:
        return CpuGovernor(budget=self.cpu_budget, degraded_below=self.degraded_share,
                           recovered_above=min(1.0, self.degraded_share + 0.15), free_floor=self.free_cpu_floor)


@dataclass
class FrameResult:
    """What one frame gave: the population (None when the frame was refused, ``reason`` says why)."""
    population: m.FlyPopulation | None = None
    trace: m.EvolverTrace | None = None
    generations: int = 0
    reason: str | None = None           # 'no calibration', 'bad calibration: ...', 'bad frame: ...'
    without_odometry: bool = False      # odometry was missing for this frame (no motion compensation)
    T_odom_base: np.ndarray | None = None


def _same_geometry(a: StereoCalibration | None, b: StereoCalibration) -> bool:
    return a is not None and (a.width, a.height, a.fx, a.baseline) == (b.width, b.height, b.fx, b.baseline)


def warm_up(config: EvolverConfig) -> float:
    """Load the per-frame numba kernels before the first frame: a few generations with ``config`` (500
    flies) on a small synthetic pair, in colour and in mono.  numba compiles them once per install
    (common.warmup) but loads each from its cache on first use, which a live start's first frame
    otherwise pays for: frames the camera or replay sends meanwhile are skipped, and the localiser's
    first fix has to span them.  Returns the seconds spent."""
    from common.fly.synthetic import textured_plane_pair
    t0 = time.perf_counter()
    calib, left, right, _ = textured_plane_pair()
    small = replace(config, population=min(int(config.population), 500), depth_min=None, depth_max=None)
    for pair in ((left, right), (np.ascontiguousarray(left[:, :, 0]), np.ascontiguousarray(right[:, :, 0]))):
        evolver = FlyEvolver(calib, small, seed=0)
        evolver.set_images(*pair)
        evolver.step(4)
        evolver.move_flies(np.eye(4))
        evolver.step(1)
    return time.perf_counter() - t0


class EvolverCore(LatchedInputs):
    """One fly population kept on the newest frame (see the module docstring).

    ``settle`` is a :class:`SettlePolicy` (live: evolve until good enough or out of time) or an int (a
    fixed number of generations per frame, deterministic)."""

    def __init__(self, config: EvolverConfig | None = None, settle: SettlePolicy | int = 30, seed: int = 0,
                 sonar_weight: float = 0.0, odometry: PoseBuffer | None = None,
                 clock: Callable[[], int] = time.monotonic_ns):
        self.config = config or EvolverConfig()
        self.settle = settle
        self.seed = seed
        self.sonar_weight = sonar_weight
        # Extrapolated at constant velocity: visual odometry (the localiser's estimates relayed by fusion)
        # only knows frames already localised, one or two frame periods before the new one.
        super().__init__(odometry if odometry is not None else PoseBuffer(maxlen=400, max_extrapolation_ns=500_000_000,
                                                                          extrapolate=True))
        self.clock = clock
        self.evolver: FlyEvolver | None = None
        self.calibration: StereoCalibration | None = None
        self._applied_msg: m.StereoCalibrationMsg | None = None
        self._sonar: m.SonarScan | None = None
        self._last_T_odom_cam: np.ndarray | None = None
        self._current: tuple[int, int, np.ndarray | None] | None = None   # seq, stamp, T_odom_cam
        self._left_grey: np.ndarray | None = None
        self._recent_quality: deque[float] = deque(maxlen=QUALITY_REFERENCE_FRAMES)

    # ------------------------------------------------------------------------------- inputs

    def on_sonar(self, msg: m.SonarScan) -> None:
        self._sonar = msg

    # ------------------------------------------------------------------------------ frames
    def _apply_calibration(self) -> str | None:
        """Bring the evolver in line with the latched calibration; the reason when there is none usable."""
        msg = self._calibration_msg
        if msg is None:
            return "no calibration"
        if msg is self._applied_msg:
            return None
        try:
            calib = m.calibration_from_msg(msg)
        except CalibrationError as e:
            return f"bad calibration: {e}"
        self._applied_msg = msg
        if not _same_geometry(self.calibration, calib):
            self.calibration = calib
            self.evolver = FlyEvolver(calib, self.config, seed=self.seed)
            if self.sonar_weight > 0:
                self._attach_sonar(self.evolver, calib)
            self._last_T_odom_cam = None
            self._current = None
            self._recent_quality.clear()
            log.info("calibration %dx%d f=%.1f B=%.3f: %d flies", calib.width, calib.height, calib.fx,
                     calib.baseline, self.config.population)
        return None

    def on_frame(self, frame: m.StereoFrame, settle_scale: float = 1.0,
                 images: FrameImages | None = None) -> FrameResult:
        """Move the flies by the odometry, load the frame and settle (see the module doc).  ``images``:
        ``common.fly.evolver.images_ahead`` of this frame's decoded images, when a caller prepared them."""
        reason = self._apply_calibration()
        if reason is not None:
            return FrameResult(reason=reason)
        evolver, calib = self.evolver, self.calibration
        t_take = self.clock()
        try:
            left, right = frame_images(frame)
            calib.check_image(left, "stereo frame")
        except (m.DecodeError, CalibrationError) as e:
            return FrameResult(reason=f"bad frame: {e}")
        t_decoded = self.clock()
        reference = None
        if self._current is not None:
            self._recent_quality.append(population_quality(evolver.fitness))
            reference = max(self._recent_quality)
        stamp = frame.header.stamp_ns
        T_odom_base = self.odometry.at(stamp)
        T_odom_cam = None if T_odom_base is None else T_odom_base @ calib.T_base_camera
        without_odometry = T_odom_cam is None and self._last_T_odom_cam is not None
        if T_odom_cam is not None and self._last_T_odom_cam is not None:
            # T_new_old: flies follow the camera's motion; set_images re-scores them.
            evolver.move_flies(invert(T_odom_cam) @ self._last_T_odom_cam, rescore=False)
        if T_odom_cam is not None:
            self._last_T_odom_cam = T_odom_cam
        evolver.set_images(left, right, images)
        self._current = (frame.header.seq, stamp, T_odom_cam)
        self._left_grey = left if left.ndim == 2 else cv2.cvtColor(left, cv2.COLOR_RGB2GRAY)
        t_ready = self.clock()
        if isinstance(self.settle, SettlePolicy):
            policy = self.settle
            if T_odom_cam is None:
                # No odometry yet (a camera without wheels before the localiser's first fixes): the flies
                # were not moved with the camera and must re-converge, so this frame gets 4× the budget.
                policy = replace(policy, budget_s=4 * policy.budget_s,
                                 min_generations=max(policy.min_generations, NO_ODOMETRY_MIN_GENERATIONS))
            if settle_scale < 1.0:
                policy = replace(policy, budget_s=policy.budget_s * max(settle_scale, 0.0))
            generations = settle(evolver, reference, policy)
        else:
            evolver.step(int(self.settle))
            generations = int(self.settle)
        pop = self.population(with_image=True)
        t_published = self.clock()
        trace = m.EvolverTrace(take_ns=t_take, decoded_ns=t_decoded, ready_ns=t_ready, published_ns=t_published,
                               generations=int(generations), reference=reference,
                               quality=population_quality(evolver.fitness),
                               header=m.header(frame.header.seq, stamp, frame.header.frame_id))
        return FrameResult(population=pop, trace=trace, generations=generations,
                           without_odometry=without_odometry, T_odom_base=T_odom_base)

    # ------------------------------------------------------------------------- between frames
    @property
    def has_population(self) -> bool:
        return self._current is not None

    def step(self) -> None:
        """One generation on the current frame (anytime: between frames)."""
        self.evolver.step(1)

    def evolve(self, generations: int) -> None:
        """``generations`` more generations on the current frame."""
        if generations > 0:
            self.evolver.step(int(generations))

    @property
    def generation(self) -> int:
        return int(self.evolver.generation) if self.evolver is not None else 0

    def population(self, with_image: bool = False) -> m.FlyPopulation:
        """The current population on the frame it was last evaluated on (with that frame's grey left
        image for a frame's first publication, ``with_image``)."""
        seq, stamp, T_odom_cam = self._current
        ev = self.evolver
        return m.FlyPopulation(positions=ev.positions, fitness=ev.fitness, generation=int(ev.generation),
                               source_seq=int(seq), T_odom_camera=T_odom_cam,
                               image=self._left_grey if with_image else None,
                               header=m.header(0, stamp, m.CAMERA_LEFT_OPTICAL))

    # --------------------------------------------------------------------------------- sonar
    def _attach_sonar(self, evolver: FlyEvolver, calib: StereoCalibration) -> None:
        """Plug the sonar fitness term into the evolver, fed by the newest scan."""
        from common.fusion.sonar import SonarScanError
        from common.fusion.sonar_term import SonarTerm

        term = SonarTerm()
        seen = {"scan": None}

        def fn(positions):
            scan = self._sonar
            if scan is not None and scan is not seen["scan"]:
                seen["scan"] = scan
                try:
                    term.update(scan, calib.T_base_camera)
                except SonarScanError as e:
                    log.warning("sonar scan ignored: %s", e)
            return term(positions)

        evolver.add_fitness_term("sonar", fn, self.sonar_weight)
