"""The planner service's state machine without a bus: newest inputs in, command and field messages out.

``PlannerCore`` owns a :class:`HarmonicPlanner` on a fixed map-frame extent. Inputs are latest-value
(``on_pose``, ``on_map_to_odom``, ``on_target``, ``on_calibration``, ``on_sonar_points``: each keeps the
newest message); ``on_population(FlyPopulation)`` folds the fittest flies (:func:`common.fly.selection.
fittest`) inside the trusted depth band into the evidence grid with the camera's view;
``cycle(stamp_ns)`` applies a new target, folds a new sonar scan, solves within the budget (a converged
field at most ``solve_hz`` times a second) and returns the ``VelocityCommand``;
``field_message(stamp_ns)`` is the ``HarmonicField`` with its descent path.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from common import messages as m
from common.fly.selection import fittest
from common.geometry import planar_from_transform, so3_log, transform_points
from common.planning.config import Command, PlannerConfig, SensorView, SolveReport
from common.planning.planner import HarmonicPlanner

log = logging.getLogger("flyslam.planner")


@dataclass
class PlannerServiceConfig:
    """The live planner's settings outside :class:`PlannerConfig` (grid extent, rates, evidence filters)."""
    target: tuple[float, float] | None = field(default=None, metadata={
        "help": "target X Y in the map frame (overrides the bus)", "nargs": 2, "metavar": ("X", "Y")})
    target_radius: float = field(default=0.4, metadata={"help": "radius (m) of the --target region"})
    extent: tuple[float, float, float, float] = field(default=(-2.0, -6.0, 26.0, 6.0), metadata={
        "help": "map-frame extent of the planning grid (m)", "metavar": ("XMIN", "YMIN", "XMAX", "YMAX")})
    look_omega: float = field(default=0.3, metadata={
        "help": "turn rate (rad/s) on 'no path' so the camera looks again (0: stop)"})
    rate: float = field(default=10.0, metadata={"help": "command rate (Hz)"})
    field_hz: float = field(default=1.0, metadata={"help": "field publication rate (Hz)"})
    solve_ms: float = field(default=40.0, metadata={"help": "relaxation budget per cycle (ms)"})
    solve_hz: float = field(default=2.0, metadata={
        "help": "most updates of a converged field per second (Hz); between them commands descend the last one"})
    sonar_range: float = field(default=0.8, metadata={
        "help": "sonar echoes nearer than this (m from base_link) are obstacles; farther ones are unused"})
    keep_fraction: float = field(default=0.5, metadata={
        "help": "fittest fraction of each population used as obstacle evidence"})
    fly_range: float = field(default=5.0, metadata={
        "help": "farthest camera depth (m) at which flies are evidence; the camera's view ends here"})
    fly_near: float = field(default=0.3, metadata={"help": "nearest camera depth (m) at which flies are evidence"})
    min_fitness: float = field(default=0.05, metadata={"help": "flies below this fitness are never obstacles"})
    new_view_m: float = field(default=0.1, metadata={
        "help": "a population counts as a whole new view of the flies once the camera moved this far (m), ..."})
    new_view_deg: float = field(default=5.0, metadata={"help": "... or turned this much (deg), ..."})
    new_view_s: float = field(default=2.0, metadata={
        "help": "... or this long (s) passed since the last population; less of any: evidence in proportion"})
    # Below occupied_weight (2): the Parisian population breeds tight clusters of near-copies of one fly,
    # and one wrong match copied 16 times is still one wrong match.
    view_cell_cap: float = field(default=1.5, metadata={
        "help": "most evidence one whole view adds to a grid cell (below occupied_weight: one view is no obstacle)"})
    wait_for_map: bool = field(default=True, metadata={
        "help": "stay still and fold no flies until the localiser has a map (its first slam/map_to_odom); false: use fusion/pose alone"})

    def __post_init__(self):
        if not (isinstance(self.solve_hz, (int, float)) and math.isfinite(self.solve_hz) and self.solve_hz > 0):
            raise ValueError(f"solve_hz must be a positive number, got {self.solve_hz!r}")
        if not min(self.new_view_m, self.new_view_deg, self.new_view_s) > 0:
            raise ValueError(f"new_view_m, new_view_deg and new_view_s must be > 0, got {self.new_view_m}, "
                             f"{self.new_view_deg} and {self.new_view_s}")
        if not (isinstance(self.view_cell_cap, (int, float)) and math.isfinite(self.view_cell_cap)
                and self.view_cell_cap > 0):
            raise ValueError(f"view_cell_cap must be a positive number, got {self.view_cell_cap!r}")

    def planner_config(self, base: PlannerConfig) -> PlannerConfig:
        """``base`` with the grid set to ``extent``."""
        import dataclasses
        x0, y0, x1, y1 = self.extent
        return dataclasses.replace(base, size_m=(x1 - x0, y1 - y0), origin=(x0, y0))


def velocity_command(c: Command, look_omega: float) -> m.VelocityCommand:
    """The bus command for a planner Command. 'no path' becomes a slow turn on the spot (when
    ``look_omega`` > 0): a phantom obstacle remembered outside the view then comes back into view, where
    it fades unless flies keep landing on it."""
    if c.stop and c.reason == "no path" and look_omega > 0:
        return m.VelocityCommand(linear_mps=0.0, angular_radps=float(look_omega), stop=False,
                                 reason="no path: turning to look again")
    return m.VelocityCommand(linear_mps=float(c.v), angular_radps=float(c.omega), stop=bool(c.stop), reason=c.reason)


def camera_view(T_map_cam: np.ndarray, calib, near_m: float, range_m: float) -> SensorView:
    """The ground wedge the left camera saw (map frame): its position, the heading of its optical axis
    (z), half its horizontal field of view, and the trusted depth band."""
    fx, cx = float(calib.left.P[0, 0]), float(calib.left.P[0, 2])     # the rectified image (K: the raw camera's)
    half_fov = math.atan2(max(cx, calib.width - cx), fx)
    return SensorView(x=float(T_map_cam[0, 3]), y=float(T_map_cam[1, 3]),
                      yaw=math.atan2(float(T_map_cam[1, 2]), float(T_map_cam[0, 2])),
                      half_fov_rad=half_fov, range_m=float(range_m), near_m=float(near_m))


def population_pose(pop: m.FlyPopulation, map_to_odom: m.TransformMsg | None, T_map_base: np.ndarray | None,
                    T_base_camera: np.ndarray) -> np.ndarray | None:
    """Camera pose in the map at the population's frame: odometry pose at that frame + newest map→odom
    (exact for the frame); else the newest fused pose (approximate when the robot moved since)."""
    if pop.T_odom_camera is not None:
        T_map_odom = m.transform_of(map_to_odom) if map_to_odom is not None else np.eye(4)
        return T_map_odom @ pop.T_odom_camera
    if T_map_base is not None:
        return T_map_base @ np.asarray(T_base_camera)
    return None


class PlannerCore:
    def __init__(self, config: PlannerConfig, settings: PlannerServiceConfig | None = None):
        self.settings = s = settings or PlannerServiceConfig()
        self.planner = HarmonicPlanner(s.planner_config(config))
        self.pose: m.PoseEstimate | None = None
        self.map_to_odom: m.TransformMsg | None = None
        self.target: m.Target | None = None
        self.calibration: m.StereoCalibrationMsg | None = None
        self.sonar: m.FlyPopulation | None = None
        self.report: SolveReport | None = None
        self._current_target: tuple[float, float, float] | None = None
        self._converged_once = False      # the descent direction of a field never converged can point anywhere
        self._last_sonar_seq: int | None = None
        self._last_view: tuple[np.ndarray, int] | None = None   # camera pose and stamp of the last population folded
        self._last_solve_ns: int | None = None

    # Latest-value inputs (single assignments: safe from a subscription thread).
    def on_pose(self, msg: m.PoseEstimate) -> None:
        self.pose = msg

    def on_map_to_odom(self, msg: m.TransformMsg) -> None:
        self.map_to_odom = msg

    def on_target(self, msg: m.Target) -> None:
        self.target = msg

    def on_calibration(self, msg: m.StereoCalibrationMsg) -> None:
        self.calibration = msg

    def on_sonar_points(self, msg: m.FlyPopulation) -> None:
        self.sonar = msg

    @property
    def T_map_base(self) -> np.ndarray | None:
        pose = self.pose
        return m.transform_of(pose) if pose is not None else None

    def on_population(self, pop: m.FlyPopulation) -> bool:
        """Fold a population's fittest in-band flies into the grid; False when its pose is unknown."""
        cal, s = self.calibration, self.settings
        if cal is None or (s.wait_for_map and self.map_to_odom is None):
            return False     # before the map: flies not yet converged (the localiser waits for them too)
        T_map_cam = population_pose(pop, self.map_to_odom, self.T_map_base, cal.T_base_camera)
        if T_map_cam is None:
            return False
        keep = fittest(pop.fitness, s.keep_fraction, s.min_fitness)
        depth = pop.positions[keep, 2]
        keep = keep[(depth >= s.fly_near) & (depth <= s.fly_range)]
        self.planner.update_flies(transform_points(T_map_cam, pop.positions[keep].astype(np.float64)),
                                  pop.fitness[keep], pop.header.stamp_ns,
                                  view=camera_view(T_map_cam, cal, s.fly_near, s.fly_range),
                                  weight=self._view_novelty(T_map_cam, pop.header.stamp_ns),
                                  cell_cap=s.view_cell_cap)
        return True

    def _view_novelty(self, T_map_cam: np.ndarray, stamp_ns: int) -> float:
        """How much of a new view this population is, in [0, 1]: the camera's motion since the last one
        folded, against new_view_m / new_view_deg / new_view_s.  A population republished 10 times a
        second from a standing robot re-reports the same flies: counted whole, one fly stuck at a wrong
        depth became an obstacle within a second; a surface seen from moving viewpoints is evidence."""
        s, last = self.settings, self._last_view
        self._last_view = (T_map_cam.copy(), stamp_ns)
        if last is None:
            return 1.0
        T0, t0 = last
        moved = float(np.linalg.norm(T_map_cam[:3, 3] - T0[:3, 3]))
        turned = math.degrees(float(np.linalg.norm(so3_log(T0[:3, :3].T @ T_map_cam[:3, :3]))))
        waited = max(0.0, (stamp_ns - t0) * 1e-9)
        return float(min(1.0, max(moved / s.new_view_m, turned / s.new_view_deg, waited / s.new_view_s)))

    def _apply_target(self) -> None:
        tgt = self.target
        if tgt is not None and (tgt.x, tgt.y, tgt.radius_m) != self._current_target:
            self.planner.set_target(tgt.x, tgt.y, max(tgt.radius_m, self.planner.resolution))
            self._current_target = (tgt.x, tgt.y, tgt.radius_m)
            self._converged_once = False
            log.info("target (%.2f, %.2f) r=%.2f", *self._current_target)

    def _fold_sonar(self, T_map_base: np.ndarray | None) -> None:
        scan, s = self.sonar, self.settings
        if scan is None or scan.header.seq == self._last_sonar_seq or T_map_base is None:
            return
        self._last_sonar_seq = scan.header.seq
        near = np.linalg.norm(scan.positions[:, :2], axis=1) < s.sonar_range
        pts = transform_points(T_map_base, scan.positions[near].astype(np.float64))
        # Every scan, echoes or not: inside the disc it observed, old sonar evidence it did not renew is
        # forgotten; outside, it stays (an echo from a textureless wall the flies never see).
        self.planner.update_sonar(pts[:, :2], scan.header.stamp_ns,
                                  view=SensorView(float(T_map_base[0, 3]), float(T_map_base[1, 3]), 0.0, math.pi,
                                                  s.sonar_range))

    def cycle(self, stamp_ns: int) -> m.VelocityCommand:
        """Target, sonar, one solve within the budget, and the command for the newest pose."""
        self._apply_target()
        T_map_base = self.T_map_base
        self._fold_sonar(T_map_base)
        # Until the field has converged once the robot waits, and the solver gets a larger budget.
        budget = self.settings.solve_ms if self._converged_once else 5 * self.settings.solve_ms
        # A converged field follows the evidence at solve_hz (evidence builds up over several populations;
        # re-solving for every flicker of it near the threshold cost most of the planner's CPU).  A new
        # target, or a field still converging, is solved every cycle.
        # (_converged_once implies a solve has run, so report and _last_solve_ns are set)
        settled = self._converged_once and self.report.converged
        if not settled or not 0 <= stamp_ns - self._last_solve_ns < 1e9 / self.settings.solve_hz:
            self.report = self.planner.solve(max_ms=budget)
            self._last_solve_ns = stamp_ns
        self._converged_once = self._converged_once or self.report.converged
        if T_map_base is None:
            cmd = m.VelocityCommand(stop=True, reason="no pose")
        elif self.settings.wait_for_map and self.map_to_odom is None:
            # Driving before the map exists bakes the odometry's drift of those metres into the map's
            # frame (the target's frame): a start-up that takes 4 s costs the whole run 3° of heading.
            cmd = m.VelocityCommand(stop=True, reason="waiting for the localiser's map")
        elif self._current_target is not None and not self._converged_once:
            cmd = m.VelocityCommand(stop=True, reason="planning: field not converged yet")
        else:
            cmd = velocity_command(self.planner.command(planar_from_transform(T_map_base)),
                                   self.settings.look_omega)
        cmd.header = m.header(0, stamp_ns, m.BASE_LINK)
        return cmd

    def field_message(self, stamp_ns: int) -> m.HarmonicField:
        T_map_base = self.T_map_base
        path = self.planner.path_from(T_map_base[0, 3], T_map_base[1, 3]) if T_map_base is not None else None
        return m.HarmonicField(values=self.planner.field.astype(np.float32),
                               origin_xy=np.array(self.planner.grid_origin, float),
                               resolution_m=self.planner.resolution,
                               path_xy=None if path is None or len(path) == 0 else path,
                               header=m.header(0, stamp_ns, m.MAP))

    @staticmethod
    def stop_command(stamp_ns: int, reason: str = "planner stopped") -> m.VelocityCommand:
        return m.VelocityCommand(stop=True, reason=reason, header=m.header(0, stamp_ns, m.BASE_LINK))


def warm_up(config: PlannerConfig) -> float:
    """Load the planner's numba kernels before the service joins the bus: flies and sonar echoes folded
    into a small grid, the field solved, a command and a descent path taken, as a cycle does.  numba
    compiles them once per install (common.warmup) but loads each from its cache on first use, which
    otherwise lands in the first cycles with a population (0.5 s of CPU on the pipeline bench).
    Returns the seconds spent."""
    t0 = time.perf_counter()
    planner = HarmonicPlanner(replace(config, size_m=(6.0, 6.0), origin=(-3.0, -3.0)))
    planner.set_target(2.0, 0.0, max(0.3, planner.resolution))
    rng = np.random.default_rng(0)
    flies = np.c_[rng.uniform(0.5, 2.5, 300), rng.uniform(-2.5, 2.5, 300), rng.uniform(0.0, 1.0, 300)]
    view = SensorView(0.0, 0.0, 0.0, 0.6, 3.0, 0.3)
    for stamp in (1, 2):
        planner.update_flies(flies, np.ones(len(flies), np.float32), stamp, view=view)
        planner.update_sonar(flies[:20, :2], stamp, view=view)
        planner.solve()
        planner.command((0.0, 0.0, 0.0))
        planner.path_from(0.0, 0.0)
        planner.field.astype(np.float32)
    # What a long run reaches later: an object cutting cells out of the solved field, and a rebase.
    solver = planner._solver
    solver.block(solver.cells[:1])
    solver.rebase()
    return time.perf_counter() - t0
