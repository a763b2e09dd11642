"""Planner service: harmonic-function obstacle avoidance steering the robot towards a target.

Folds the newest ``flies/population`` (moved into the map frame with the population's odometry pose and
the newest map→odom, or with the fused pose) and sonar echoes (``fusion/sonar_points``) into the
planner's evidence grid — flies only between --fly-near and --fly-range camera depth, each population with
the camera's view and each scan with the sonar's disc, so evidence is forgotten quickly only where the
sensors look again and obstacles that left their view stay — keeps the harmonic field up to date
(warm-started), and publishes
``planner/cmd_vel`` at ``--rate`` from the best current pose ``fusion/pose``. The target comes from
``planner/target`` (latched; set by the launch file, the simulator's scenario or a user) or ``--target
X Y``. It stops with a stated reason ('target reached', 'no path', 'no target', ...) in the command, and
publishes the field with its descent path on ``planner/field`` at ``--field-hz``.
"""
from __future__ import annotations

import logging
import math
import sys
import threading
import time

import numpy as np

from common import messages as m
from common.geometry import planar_from_transform, transform_points
from common.planning import SensorView, HarmonicPlanner, PlannerConfig
from services.base import run_service, service_parser

log = logging.getLogger("flyslam.planner")


def build_parser():
    p = service_parser("planner", __doc__.splitlines()[0])
    p.add_argument("--target", type=float, nargs=2, metavar=("X", "Y"), help="target in the map frame (overrides the bus)")
    p.add_argument("--target-radius", type=float, default=0.4)
    p.add_argument("--extent", type=float, nargs=4, default=[-2.0, -6.0, 26.0, 6.0], metavar=("XMIN", "YMIN", "XMAX", "YMAX"),
                   help="map-frame extent of the planning grid (m)")
    p.add_argument("--resolution", type=float, default=0.1, help="grid cell size (m)")
    p.add_argument("--robot-radius", type=float, default=0.22)
    p.add_argument("--v-max", type=float, default=0.4)
    p.add_argument("--omega-max", type=float, default=1.0)
    p.add_argument("--slow-clearance", type=float, default=0.25,
                   help="free space (m) beyond the inflated obstacles under which the robot slows down; at the "
                        "library's 0.5 m a third of the commands of a recorded corridor run crawled straight "
                        "ahead at under half speed, the mapped walls of a 2 m corridor being that close")
    p.add_argument("--look-omega", type=float, default=0.3,
                   help="turn rate (rad/s) on 'no path': the robot turns on the spot so the camera sees the "
                        "blocked region again and evidence nobody renews there fades (0: stop instead). On a "
                        "recorded run a phantom wall across the corridor, seen once and then out of view, kept "
                        "a stopped robot at 'no path' for 100 s")
    p.add_argument("--rate", type=float, default=10.0, help="command rate (Hz)")
    p.add_argument("--field-hz", type=float, default=1.0, help="field publication rate (Hz)")
    p.add_argument("--solve-ms", type=float, default=40.0, help="relaxation budget per cycle")
    p.add_argument("--sonar-range", type=float, default=0.8,
                   help="sonar echoes nearer than this (m from base_link) are obstacles; farther ones are not "
                        "used: an echo only says the nearest surface is somewhere on the beam's arc, and the "
                        "arcs of oblique walls land inside the corridor. At 1.3 m, on a recorded run, arcs from "
                        "the wall and an oblique box put evidence 0.3 m inside the real surfaces and closed the "
                        "0.7 m passage beside the box")
    p.add_argument("--keep-fraction", type=float, default=0.5,
                   help="fittest fraction of each population used as obstacle evidence")
    p.add_argument("--fly-range", type=float, default=5.0,
                   help="flies farther than this (m, camera depth) are not obstacles, and the camera's view "
                        "for forgetting evidence ends here: stereo depth error grows with the square of depth "
                        "and on a recorded corridor run a quarter of the fit in-band flies beyond 5 m sat in "
                        "the free corridor (under 1 %% between 3 and 5 m)")
    p.add_argument("--fly-near", type=float, default=0.3, help="nearest camera depth at which flies are evidence (m)")
    p.add_argument("--unseen-half-life", type=float, default=60.0,
                   help="half-life (s) of fly evidence outside the camera's view (inside: 2 s)")
    p.add_argument("--min-fitness", type=float, default=0.05,
                   help="flies below this fitness are never obstacles (converged flies score ~0.1-0.6, "
                        "random ones ~0.01)")
    return p


class Latest:
    """The newest value of a callback stream, thread-safe."""

    def __init__(self):
        self._lock = threading.Lock()
        self.value = None

    def set(self, v):
        with self._lock:
            self.value = v

    def get(self):
        with self._lock:
            return self.value


def body(node, args) -> int:
    x0, y0, x1, y1 = args.extent
    planner = HarmonicPlanner(PlannerConfig(resolution=args.resolution, size_m=(x1 - x0, y1 - y0), origin=(x0, y0),
                                            robot_radius=args.robot_radius, v_max=args.v_max,
                                            omega_max=args.omega_max,
                                            unseen_half_life_s=args.unseen_half_life,
                                            slow_clearance_m=args.slow_clearance))
    pose, map_to_odom, target, sonar, calib = Latest(), Latest(), Latest(), Latest(), Latest()
    node.subscribe("fusion/pose", m.PoseEstimate, pose.set)
    node.subscribe("slam/map_to_odom", m.TransformMsg, map_to_odom.set)
    node.subscribe("planner/target", m.Target, target.set)
    node.subscribe("fusion/sonar_points", m.FlyPopulation, sonar.set)
    node.subscribe("stereo/calibration", m.StereoCalibrationMsg, calib.set)
    populations = node.subscribe_latest("flies/population", m.FlyPopulation)
    cmd_pub = node.publisher("planner/cmd_vel", reliable=True)
    field_pub = node.publisher("planner/field")
    if args.target is not None:
        target.set(m.Target(x=args.target[0], y=args.target[1], radius_m=args.target_radius))
    else:
        t = node.query_latest("planner/target", m.Target, timeout=1.0)
        if t is not None:
            target.set(t)
    if calib.get() is None:
        calib.set(node.query_latest("stereo/calibration", m.StereoCalibrationMsg, timeout=1.0))

    current_target = None
    converged_once = False   # the descent direction of a field that never converged can point anywhere
    last_sonar_seq = None
    last_field = 0.0
    last_cmd_reason = ""
    period = 1.0 / args.rate
    while not node.stopping:
        t_cycle = time.monotonic()
        tgt = target.get()
        if tgt is not None and (tgt.x, tgt.y, tgt.radius_m) != current_target:
            planner.set_target(tgt.x, tgt.y, max(tgt.radius_m, args.resolution))
            current_target = (tgt.x, tgt.y, tgt.radius_m)
            converged_once = False
            log.info("target (%.2f, %.2f) r=%.2f", *current_target)
        fused = pose.get()
        T_map_base = m.transform_of(fused) if fused is not None else None
        pop = populations.take()
        cal = calib.get()
        if pop is not None and cal is not None:
            T_map_cam = _population_pose(pop, map_to_odom.get(), T_map_base, cal.T_base_camera)
            if T_map_cam is not None:
                keep = fittest(pop.fitness, args.keep_fraction, args.min_fitness)
                depth = pop.positions[keep, 2]
                keep = keep[(depth >= args.fly_near) & (depth <= args.fly_range)]
                planner.update_flies(transform_points(T_map_cam, pop.positions[keep].astype(np.float64)),
                                     pop.fitness[keep], pop.header.stamp_ns,
                                     view=camera_view(T_map_cam, cal, args.fly_near, args.fly_range))
        scan = sonar.get()
        if scan is not None and scan.header.seq != last_sonar_seq and T_map_base is not None:
            last_sonar_seq = scan.header.seq
            near = np.linalg.norm(scan.positions[:, :2], axis=1) < args.sonar_range
            pts = transform_points(T_map_base, scan.positions[near].astype(np.float64))
            # Every scan, echoes or not: inside the disc it observed, old sonar evidence it did not renew
            # is forgotten; outside, it stays (an echo from a textureless wall the flies never see).
            planner.update_sonar(pts[:, :2], scan.header.stamp_ns,
                                 view=SensorView(float(T_map_base[0, 3]), float(T_map_base[1, 3]), 0.0, math.pi,
                                                 args.sonar_range))
        # Until the field has converged once the robot waits, and the solver gets a larger budget.
        report = planner.solve(max_ms=args.solve_ms if converged_once else 5 * args.solve_ms)
        converged_once = converged_once or report.converged
        if T_map_base is None:
            cmd = m.VelocityCommand(stop=True, reason="no pose")
        elif current_target is not None and not converged_once:
            cmd = m.VelocityCommand(stop=True, reason="planning: field not converged yet")
        else:
            cmd = velocity_command(planner.command(planar_from_transform(T_map_base)), args.look_omega)
        cmd.header = m.header(0, time.time_ns(), m.BASE_LINK)
        cmd_pub.publish(cmd)
        if cmd.reason != last_cmd_reason:
            log.info("command: %s", cmd.reason)
            last_cmd_reason = cmd.reason
        node.progress += 1
        node.rates["solve_ms"] = float(report.elapsed_ms)
        if time.monotonic() - last_field > 1.0 / args.field_hz:
            last_field = time.monotonic()
            path = None
            if T_map_base is not None:
                path = planner.path_from(T_map_base[0, 3], T_map_base[1, 3])
            values = planner.field.astype(np.float32)
            field_pub.publish(m.HarmonicField(values=values, origin_xy=np.array(planner.grid_origin, float),
                                              resolution_m=planner.resolution,
                                              path_xy=None if path is None or len(path) == 0 else path,
                                              header=m.header(0, time.time_ns(), m.MAP)))
        node.sleep(max(0.0, period - (time.monotonic() - t_cycle)))
    cmd_pub.publish(m.VelocityCommand(stop=True, reason="planner stopped", header=m.header(0, time.time_ns(), m.BASE_LINK)))
    return 0


def velocity_command(c, look_omega: float) -> m.VelocityCommand:
    """The bus command for a planner Command. 'no path' becomes a slow turn on the spot (when
    ``look_omega`` > 0): with evidence remembered outside the sensors' view, a phantom obstacle that closed
    the way and then left the view would otherwise keep a stopped robot blocked indefinitely; turning
    brings it back into view, where it fades unless flies keep landing on it."""
    if c.stop and c.reason == "no path" and look_omega > 0:
        return m.VelocityCommand(linear_mps=0.0, angular_radps=float(look_omega), stop=False,
                                 reason="no path: turning to look again")
    return m.VelocityCommand(linear_mps=float(c.v), angular_radps=float(c.omega), stop=bool(c.stop), reason=c.reason)


def fittest(fitness: np.ndarray, fraction: float, min_fitness: float = 0.0) -> np.ndarray:
    """Indices of the fittest ``fraction`` of flies above ``min_fitness``. Unconverged flies — a young
    population, fresh immigrants, most of them drawn close to the camera since 1/z is uniform — must not
    become obstacles: measured on a recorded run, they walled the robot in during its first seconds."""
    if len(fitness) == 0:
        return np.zeros(0, dtype=int)
    threshold = max(min_fitness, float(np.quantile(fitness, 1.0 - fraction)))
    return np.flatnonzero(fitness > threshold)


def camera_view(T_map_cam: np.ndarray, calib, near_m: float, range_m: float) -> SensorView:
    """The ground wedge the left camera saw (map frame): its position, the heading of its optical axis
    (z), half its horizontal field of view, and the trusted depth band."""
    fx, cx = float(calib.left.K[0, 0]), float(calib.left.K[0, 2])
    half_fov = math.atan2(max(cx, calib.width - cx), fx)
    return SensorView(x=float(T_map_cam[0, 3]), y=float(T_map_cam[1, 3]),
                      yaw=math.atan2(float(T_map_cam[1, 2]), float(T_map_cam[0, 2])),
                      half_fov_rad=half_fov, range_m=float(range_m), near_m=float(near_m))


def _population_pose(pop: m.FlyPopulation, map_to_odom, T_map_base, T_base_camera):
    """Camera pose in the map at the population's frame: odometry pose at that frame + newest map→odom
    (exact for the frame); else the newest fused pose (approximate when the robot moved since)."""
    if pop.T_odom_camera is not None:
        T_map_odom = m.transform_of(map_to_odom) if map_to_odom is not None else np.eye(4)
        return T_map_odom @ pop.T_odom_camera
    if T_map_base is not None:
        return T_map_base @ np.asarray(T_base_camera)
    return None


def main(argv=None) -> int:
    return run_service("planner", build_parser(), body, argv)


if __name__ == "__main__":
    sys.exit(main())
