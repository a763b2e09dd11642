"""Simulator readings → wire messages, shared by the live sim service and the offline recorder."""
from __future__ import annotations

import numpy as np

from common import messages as m
from common.images import make_frame
from common.sim.sensors import OdometryReading, SonarReading
from common.sim.simulator import StereoImages


def odometry_message(ev: OdometryReading, stamp_ns: int) -> m.WheelOdometry:
    return m.WheelOdometry(
        wheel_speeds=np.asarray(ev.wheel_speeds, float), ticks=np.asarray(ev.ticks, np.int64),
        ticks_per_rev=float(ev.ticks_per_rev), wheel_radius_m=float(ev.wheel_radius),
        track_width_m=float(ev.track_width), pose_xyyaw=np.asarray(ev.pose_xyyaw_integrated, float),
        header=m.header(0, stamp_ns, m.BASE_LINK))


def sonar_message(ev: SonarReading, stamp_ns: int) -> m.SonarScan:
    return m.SonarScan(
        transducer_poses=np.asarray(ev.transducer_poses, float), ranges=np.asarray(ev.ranges, np.float32),
        beam_width_rad=float(ev.beam_width), min_range_m=float(ev.min_range), max_range_m=float(ev.max_range),
        header=m.header(0, stamp_ns, m.BASE_LINK))


def camera_messages(images: StereoImages, seq: int, stamp_ns: int, encoding: str = "rgb8",
                    depth: bool = False, quality: int = 90) -> dict[str, object]:
    """{'stereo/frame': ..., 'truth/pose': ..., ['truth/depth': ...]} for one rendered frame."""
    out = {"stereo/frame": make_frame(images.left, images.right, seq, stamp_ns, encoding, quality=quality),
           "truth/pose": m.pose_msg(images.T_map_base, seq=seq, stamp_ns=stamp_ns, source_seq=seq)}
    if depth:
        out["truth/depth"] = m.DepthImage(depth=images.depth, header=m.header(seq, stamp_ns, m.CAMERA_LEFT_OPTICAL))
    return out


def target_message(scenario, stamp_ns: int) -> m.Target | None:
    if scenario.target is None:
        return None
    return m.Target(x=float(scenario.target[0]), y=float(scenario.target[1]), radius_m=0.4,
                    header=m.header(0, stamp_ns, m.MAP))
