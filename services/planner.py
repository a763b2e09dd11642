"""Planner service: harmonic-function obstacle avoidance steering the robot towards a target.

Folds the newest ``flies/population`` (placed in the map with its odometry pose and the newest
map→odom, or with the fused pose) and the sonar echoes ``fusion/sonar_points`` into the evidence grid of
:class:`common.planning.core.PlannerCore`, keeps the harmonic field up to date and publishes
``planner/cmd_vel`` at ``--rate`` from the best pose ``fusion/pose``, towards ``planner/target``
(latched) or ``--target X Y``. A stop says why in the command; the field and its descent path go to
``planner/field`` at ``--field-hz``.
"""
from __future__ import annotations

import logging
import sys
import time

from common import messages as m
from common import streams as S
from common.config_args import add_config_arguments
from common.planning import PlannerConfig
from common.planning.core import PlannerCore, PlannerServiceConfig, velocity_command, warm_up  # noqa: F401 (API)
from services.base import config_or_exit, load_kernels_ahead, run_service, service_parser, survive

log = logging.getLogger("flyslam.planner")
PLANNER_FLAGS = ["resolution", "robot_radius", "v_max", "omega_max", "slow_clearance_m", "unseen_half_life_s"]
RENAME = {"slow_clearance_m": "slow-clearance", "unseen_half_life_s": "unseen-half-life"}


def build_parser():
    p = service_parser("planner", __doc__.splitlines()[0])
    add_config_arguments(p, PlannerServiceConfig)
    add_config_arguments(p, PlannerConfig, only=PLANNER_FLAGS, rename=RENAME, helps={
        "resolution": "grid cell size (m)", "robot_radius": "robot radius (m)",
        "v_max": "top speed (m/s)", "omega_max": "top turn rate (rad/s)",
        "slow_clearance_m": "free space (m) beyond the inflated obstacles under which the robot slows down",
        "unseen_half_life_s": "half-life (s) of evidence outside the sensors' view"})
    return p


def body(node, args) -> int:
    settings = config_or_exit(PlannerServiceConfig, args)
    core = PlannerCore(config_or_exit(PlannerConfig, args, only=PLANNER_FLAGS, rename=RENAME), settings)
    # The core keeps only the newest pose and sonar points: taken once per cycle, the 30 Hz pose stream's
    # other samples stay in Zenoh instead of costing a callback and a decode each.
    latest = [(node.subscribe_latest(stream, polled=True), handler) for stream, handler in (
        (S.FUSION_POSE, core.on_pose), (S.FUSION_SONAR_POINTS, core.on_sonar_points))]
    calibration = node.latched(S.STEREO_CALIBRATION)
    target = None
    if settings.target is not None:
        core.on_target(m.Target(x=settings.target[0], y=settings.target[1], radius_m=settings.target_radius))
    else:
        target = node.latched(S.PLANNER_TARGET, retry_s=float("inf"))   # a target may never come: ask once
    # map->odom: the newest one, also the one the supervisor latches for a restarted planner (or it would
    # wait for the localiser's next one: none while that is restarting or relocalising too).
    map_to_odom = node.latched(S.SLAM_MAP_TO_ODOM, retry_s=float("inf"))
    populations = node.subscribe_latest(S.FLIES_POPULATION, polled=True)   # taken once per cycle
    cmd_pub, field_pub = node.publisher(S.PLANNER_CMD_VEL), node.publisher(S.PLANNER_FIELD)
    last_field, last_reason = 0.0, ""
    while not node.stopping:
        t_cycle = time.monotonic()
        if target is not None and target.get() is not None:
            with survive(node, "target", log):
                core.on_target(target.get())
        for subscription, handler in latest:
            msg = subscription.take()
            if msg is not None:
                handler(msg)
        newest_map_to_odom = map_to_odom.take()
        if newest_map_to_odom is not None:
            core.on_map_to_odom(newest_map_to_odom)
        if calibration.get() is not None:
            with survive(node, "calibration", log):
                core.on_calibration(calibration.get())
        pop = populations.take()
        if pop is not None:
            with survive(node, "population", log):
                core.on_population(pop)
        cmd = core.stop_command(time.time_ns(), "planner error")   # what the robot gets if the cycle fails
        with survive(node, "cycle", log):
            cmd = core.cycle(time.time_ns())
        cmd_pub.publish(cmd)
        if cmd.reason != last_reason:
            log.info("command: %s", cmd.reason)
            last_reason = cmd.reason
        node.progress += 1
        node.rates["solve_ms"] = float(core.report.elapsed_ms)
        if time.monotonic() - last_field > 1.0 / settings.field_hz:
            last_field = time.monotonic()
            field_pub.publish(core.field_message(time.time_ns()))
        node.sleep(max(0.0, 1.0 / settings.rate - (time.monotonic() - t_cycle)))
    cmd_pub.publish(core.stop_command(time.time_ns()))
    return 0


def load_kernels(args) -> None:
    """Before joining the bus (common.planning.core.warm_up), as the evolver does."""
    from common.planning import harmonic, multigrid, multigrid_hierarchy
    config = config_or_exit(PlannerConfig, args, only=PLANNER_FLAGS, rename=RENAME)
    load_kernels_ahead(log, lambda: warm_up(config), "the first cycles",
                       probes=[harmonic.flood_from_target, multigrid._cycle, multigrid_hierarchy.fine_system])


def main(argv=None) -> int:
    return run_service("planner", build_parser(), body, argv, prepare=load_kernels)


if __name__ == "__main__":
    sys.exit(main())
