"""Localiser service (SLAM): registers each newest fly population against a map of keyframe populations.

Takes ``flies/population`` (latest value: it always localises the newest population) and the odometry
pose ``fusion/odom`` as prior; publishes ``slam/pose`` (base_link in map with covariance; status says
when a registration was rejected and odometry carried on) and ``slam/map_to_odom`` (REP-105), serves
the keyframe map on the queryable ``slam/map``, and writes the trajectory as TUM text (``--tum``).
The algorithm is ``common.slam.FlyLocaliser``; this module only moves messages.
"""
from __future__ import annotations

import logging
import sys
import threading
import time

import numpy as np
import zenoh

from common import messages as m
from common.geometry import invert, pose_from_transform
from common.pose_buffer import PoseBuffer
from common.slam import FlyLocaliser, LocaliserConfig, LocaliserError
from common.trajectory import write_tum
from services.base import run_service, service_parser

log = logging.getLogger("flyslam.localiser")


def build_parser():
    p = service_parser("localiser", __doc__.splitlines()[0])
    p.add_argument("--tum", default=None, help="write the estimated trajectory (TUM) here, updated every 5 s and on exit")
    p.add_argument("--max-keyframes", type=int, default=LocaliserConfig.max_keyframes)
    p.add_argument("--max-depth", type=float, default=LocaliserConfig.max_depth_m)
    return p


def map_message(loc: FlyLocaliser, stamp_ns: int) -> m.FlyMap:
    kfs = []
    for kf in list(loc.keyframes):
        p, q = pose_from_transform(kf.T_map_base)
        kfs.append(m.Keyframe(id=kf.id, stamp_ns=kf.stamp_ns, position=p, orientation=q, points=kf.points,
                              fitness=kf.fitness))
    return m.FlyMap(keyframes=kfs, header=m.header(0, stamp_ns, m.MAP))


def body(node, args) -> int:
    odom = PoseBuffer(maxlen=1000)
    lock = threading.Lock()

    def on_odom(msg: m.PoseEstimate):
        with lock:
            odom.add(msg.header.stamp_ns, m.transform_of(msg))

    node.subscribe("fusion/odom", m.PoseEstimate, on_odom)
    calib_msg = [None]
    node.subscribe("stereo/calibration", m.StereoCalibrationMsg, lambda msg: calib_msg.__setitem__(0, msg))
    calib_msg[0] = calib_msg[0] or node.query_latest("stereo/calibration", m.StereoCalibrationMsg, timeout=1.0)
    last_calib_query = time.monotonic()
    populations = node.subscribe_latest("flies/population", m.FlyPopulation)
    pose_pub = node.publisher("slam/pose")
    tf_pub = node.publisher("slam/map_to_odom", latched=True)
    config = LocaliserConfig(max_keyframes=args.max_keyframes, max_depth_m=args.max_depth)
    state = {"loc": None}

    def serve_map(query: zenoh.Query):
        loc = state["loc"]
        if loc is not None:
            with lock:
                payload = m.encode(map_message(loc, time.time_ns()))
            query.reply(query.key_expr, payload)

    node.session.declare_queryable(node.key("slam/map"), serve_map)
    stamps, poses = [], []
    last_tum = time.monotonic()
    last_seq = None
    while not node.stopping:
        pop = populations.wait(timeout=0.5)
        if pop is None:
            continue
        if pop.source_seq == last_seq:
            continue        # a republished population of a frame already localised
        last_seq = pop.source_seq
        if state["loc"] is None:
            if calib_msg[0] is None and time.monotonic() - last_calib_query > 1.0:
                # A source publishes its calibration rarely (a replay: once); ask its latched publisher.
                calib_msg[0] = node.query_latest("stereo/calibration", m.StereoCalibrationMsg, timeout=0.5)
                last_calib_query = time.monotonic()
            if calib_msg[0] is None:
                node.counters.add("populations_without_calibration")
                continue
            state["loc"] = FlyLocaliser(calib_msg[0].T_base_camera, config,
                                        calibration=m.calibration_from_msg(calib_msg[0]))
        loc = state["loc"]
        stamp = pop.header.stamp_ns
        T_odom_base = None
        if pop.T_odom_camera is not None:
            T_odom_base = pop.T_odom_camera @ invert(loc.T_base_camera)
        else:
            with lock:
                T_odom_base = odom.at(stamp)
        try:
            with lock:
                est = loc.update(stamp, pop.positions, pop.fitness, T_odom_base, pop.generation)
        except LocaliserError as e:
            node.counters.add("bad_populations")
            log.warning("population %d rejected: %s", pop.source_seq, e)
            continue
        node.counters.add("registrations_ok" if est.registered else "registrations_rejected")
        if est.keyframe_added:
            node.counters.add("keyframes")
        pose_pub.publish(m.pose_msg(est.T_map_base, est.covariance, stamp_ns=stamp, status=est.status,
                                    source_seq=pop.source_seq))
        p, q = pose_from_transform(est.T_map_odom)
        tf_pub.publish(m.TransformMsg(child_frame_id=m.ODOM, translation=p, rotation=q, header=m.header(0, stamp, m.MAP)))
        stamps.append(stamp)
        poses.append(est.T_map_base)
        node.progress += 1
        node.rates["keyframes"] = float(len(loc.keyframes))
        if args.tum and time.monotonic() - last_tum > 5.0:
            write_tum(args.tum, np.array(stamps, np.int64), np.array(poses))
            last_tum = time.monotonic()
    if args.tum and stamps:
        write_tum(args.tum, np.array(stamps, np.int64), np.array(poses))
        log.info("wrote %d poses to %s", len(stamps), args.tum)
    return 0


def main(argv=None) -> int:
    return run_service("localiser", build_parser(), body, argv)


if __name__ == "__main__":
    sys.exit(main())
