"""Localiser service (SLAM): registers each newest fly population against a map of keyframe populations.

Takes ``flies/population`` (latest value), the odometry pose ``fusion/odom`` as prior and the latched
``stereo/calibration``; publishes ``slam/pose`` (base_link in map with covariance; the status says when
a registration was rejected and odometry carried on) and ``slam/map_to_odom`` (REP-105), answers the
queryable ``slam/map`` and writes the trajectory as TUM text (``--tum``). The state machine is
:class:`common.slam.core.LocaliserCore`, the same one ``flyslam eval`` runs.
"""
from __future__ import annotations

import logging
import sys
import threading
import time

from common import messages as m
from common import streams as S
from common.config_args import add_config_arguments
from common.slam import LocaliserConfig
from common.slam.core import LocaliserCore, LocaliserOutput, LocaliserServiceConfig
from common.trajectory import write_tum
from services.base import config_or_exit, run_service, service_parser

log = logging.getLogger("flyslam.localiser")
LOCALISER_FLAGS = ["max_keyframes", "max_depth_m", "odometry"]
RENAME = {"max_depth_m": "max-depth"}


def build_parser():
    p = service_parser("localiser", __doc__.splitlines()[0])
    add_config_arguments(p, LocaliserServiceConfig)
    add_config_arguments(p, LocaliserConfig, only=LOCALISER_FLAGS, rename=RENAME, helps={
        "max_keyframes": "keyframes kept in the map (oldest dropped)",
        "max_depth_m": "flies farther than this (m, camera depth) are not used (default: 0.3 f B)",
        "odometry": "'wheels' (fusion/odom predicts) or 'visual' (no wheels: constant velocity)"})
    return p


def body(node, args) -> int:
    run = config_or_exit(LocaliserServiceConfig, args)
    core = LocaliserCore(config_or_exit(LocaliserConfig, args, only=LOCALISER_FLAGS, rename=RENAME), seed=run.seed)
    lock = threading.Lock()

    def on_odom(msg: m.PoseEstimate) -> None:
        with lock:
            core.on_odometry(msg.header.stamp_ns, m.transform_of(msg))

    def serve_map():
        with lock:
            return core.map_message(time.time_ns())

    node.subscribe(S.FUSION_ODOM, callback=on_odom)
    calibration = node.latched(S.STEREO_CALIBRATION)
    node.queryable(S.SLAM_MAP, serve_map)
    populations = node.subscribe_latest(S.FLIES_POPULATION)
    pubs = node.publisher(S.SLAM_POSE), node.publisher(S.SLAM_MAP_TO_ODOM)
    last_tum = time.monotonic()
    while not node.stopping:
        pop = populations.wait(timeout=0.5)
        if pop is None:
            continue
        with lock:
            if not core.has_calibration and calibration.get() is not None:
                core.on_calibration(calibration.get())
            out = core.on_population(pop)
        publish(node, out, pop, *pubs)
        node.rates["keyframes"] = float(len(core.keyframes))
        if run.tum and time.monotonic() - last_tum > run.tum_period_s:
            write_tum(run.tum, *core.trajectory())
            last_tum = time.monotonic()
    if run.tum and core.stamps:
        write_tum(run.tum, *core.trajectory())
        log.info("wrote %d poses to %s", len(core.stamps), run.tum)
    return 0


def publish(node, out: LocaliserOutput, pop: m.FlyPopulation, pose_pub, tf_pub) -> None:
    """Publish a localised population's pose and map→odom; count and log a refused one."""
    if out.estimate is None:
        if out.reason != "republished":
            node.counters.add("populations_without_calibration" if out.reason == "no calibration"
                              else "bad_populations")
            log.log(logging.DEBUG if out.reason == "no calibration" else logging.WARNING,
                    "population %d: %s", pop.source_seq, out.reason)
        return
    node.counters.add("registrations_ok" if out.estimate.registered else "registrations_rejected")
    node.counters.add("keyframes", int(out.estimate.keyframe_added))
    pose_pub.publish(out.pose)
    tf_pub.publish(out.map_to_odom)
    node.progress += 1


def main(argv=None) -> int:
    return run_service("localiser", build_parser(), body, argv)


if __name__ == "__main__":
    sys.exit(main())
