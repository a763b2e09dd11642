"""Localiser service (SLAM): registers each newest fly population against a map of keyframe populations.

Takes ``flies/population`` (latest value), the odometry pose ``fusion/odom`` as prior and the latched
``stereo/calibration``; publishes ``slam/pose`` (base_link in map with covariance; the status says when
a registration was rejected and odometry carried on) and ``slam/map_to_odom`` (REP-105), answers the
queryable ``slam/map`` and writes the trajectory as TUM text (``--tum``) and the map as ``map.mcap`` next to it
(every ``map_period_s`` and on exit, atomically); ``--map FILE`` starts from a saved map. The state machine is
:class:`common.slam.core.LocaliserCore`, the same one ``flyslam eval`` runs.
"""
from __future__ import annotations

import logging
import sys
import threading
import time
from pathlib import Path

from common import messages as m
from common import streams as S
from common.config_args import add_config_arguments
from common.slam import LocaliserConfig
from common.slam.core import LocaliserCore, LocaliserOutput, LocaliserServiceConfig
from common.slam.mapfile import MapFileError, load_map
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
    initial_map = None
    if run.map:
        try:
            initial_map = load_map(run.map)
        except MapFileError as e:
            log.error("%s", e)
            return 2
        log.info("starting from %s: %d keyframes, %d edges", run.map, len(initial_map.keyframes), len(initial_map.edges))
    core = LocaliserCore(config_or_exit(LocaliserConfig, args, only=LOCALISER_FLAGS, rename=RENAME), seed=run.seed,
                         initial_map=initial_map)
    map_path = Path(run.tum).parent / "map.mcap" if run.tum else None
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
    last_tum = last_map = time.monotonic()
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
        if map_path is not None and time.monotonic() - last_map > run.map_period_s:
            with lock:
                save_map_logged(core, map_path, quiet=True)
            last_map = time.monotonic()
    if run.tum and core.localised:
        write_tum(run.tum, *core.trajectory())
        log.info("wrote %d poses to %s", core.localised, run.tum)
    if map_path is not None:
        save_map_logged(core, map_path)
    return 0


def save_map_logged(core: LocaliserCore, path: Path, quiet: bool = False) -> None:
    """Write map.mcap; a failure (disk full, bad folder) is logged, never fatal."""
    try:
        if core.save_map(path) and not quiet:
            log.info("wrote the map (%d keyframes) to %s", len(core.localiser.map_keyframes()), path)
    except (MapFileError, OSError) as e:
        log.warning("could not write the map to %s: %s", path, e)


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
