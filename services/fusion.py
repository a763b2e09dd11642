"""Fusion service: wheel odometry + localiser corrections → one best pose; sonar scans in base_link.

Subscribes (under the robot prefix):
  ``odom/wheels``       WheelOdometry (every message matters: callback subscription)
  ``slam/pose``         PoseEstimate, base_link in map with covariance (the localiser's fix)
  ``slam/map_to_odom``  TransformMsg map→odom (fused with ``--map-to-odom-sigma`` when it has no
                        matching slam/pose of the same stamp)
  ``sonar/scan``        SonarScan in base_link (or in ``--sonar-frame`` mounted at ``--sonar-mount``)
Publishes:
  ``fusion/odom``          PoseEstimate base_link in odom, frame_id 'odom', 6×6 covariance, per odometry
                           reading, latched; status 'ok' or 'flagged: <why>' (the reading was dropped)
  ``fusion/pose``          PoseEstimate base_link in map, frame_id 'map', per odometry reading, latched;
                           status 'ok' / 'odometry only' / 'flagged: <why>'
  ``fusion/sonar``         SonarScan in base_link (ranges outside [min, max] set to NaN)
  ``fusion/sonar_points``  FlyPopulation reused as a point cloud: echo points in base_link (frame_id
                           'base_link'), ``--arc-samples`` per echo spread across the beam at the echo
                           range and at ``--sonar-height``; fitness = 1 for every point; source_seq = the
                           scan's seq. For the planner: every point is an obstacle seen by sonar.

On start it asks the bus for the latched ``fusion/odom`` and ``fusion/pose`` (``--recover-timeout``) and
continues from them, so a restart does not send the odom pose back to zero.  Note: a latched stream is
answered by whoever still holds it; when this process was the only publisher, something else on the bus
(a recorder or a Zenoh storage) must keep it for the recovery to find anything.

The odometry/filter logic lives in ``common.fusion.core`` (pure); this file only wires it to the bus.
"""
from __future__ import annotations

import logging
import sys
import threading

import numpy as np

from common.fusion.core import FusionCore
from common.fusion.odometry import OdometryModel
from common.fusion.pose_filter import FilterConfig
from common.fusion.sonar import SonarScanError, echo_points, scan_in_base
from common.messages import (BASE_LINK, FlyPopulation, PoseEstimate, SonarScan, TransformMsg, WheelOdometry,
                             header)
from services.base import run_service, service_parser

log = logging.getLogger("flyslam.fusion")


def _floats(text: str, n: int, what: str) -> tuple[float, ...]:
    parts = text.split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != n or not all(np.isfinite(values)):
        raise SystemExit(f"{what}: expected {n} comma-separated numbers, got {text!r}")
    return values


def build_parser():
    p = service_parser("fusion", __doc__.splitlines()[0])
    p.add_argument("--wheel-radius", type=float, default=0.0, help="m, when readings carry 0")
    p.add_argument("--track-width", type=float, default=0.0, help="m, when readings carry 0")
    p.add_argument("--k-wheel", type=float, default=OdometryModel.k_wheel_m,
                   help="wheel travel variance per metre travelled (m²/m)")
    p.add_argument("--max-wheel-speed", type=float, default=OdometryModel.max_wheel_speed_radps,
                   help="rad/s; faster is a jump and the reading is flagged")
    p.add_argument("--max-gap", type=float, default=OdometryModel.max_gap_s,
                   help="s; longer speeds-only gaps are not integrated")
    p.add_argument("--map-to-odom-sigma", default="0.05,0.035",
                   help="σ_xy (m), σ_yaw (rad) assumed for slam/map_to_odom")
    p.add_argument("--stale-after", type=float, default=FilterConfig.stale_after_s,
                   help="s without a correction before fusion/pose says 'odometry only'")
    p.add_argument("--sonar-frame", default=BASE_LINK, help="frame the sonar scans may arrive in")
    p.add_argument("--sonar-mount", default="0,0,0", help="x,y,yaw of --sonar-frame in base_link")
    p.add_argument("--sonar-height", type=float, default=0.25, help="m, height of the sonar ring")
    p.add_argument("--arc-samples", type=int, default=5, help="obstacle points per sonar echo")
    p.add_argument("--recover-timeout", type=float, default=1.0,
                   help="s to wait for the latched fusion/odom and fusion/pose at start")
    return p


def body(node, args) -> int:
    model = OdometryModel(wheel_radius_m=args.wheel_radius, track_width_m=args.track_width,
                          k_wheel_m=args.k_wheel, max_wheel_speed_radps=args.max_wheel_speed,
                          max_gap_s=args.max_gap)
    config = FilterConfig(map_to_odom_sigma=_floats(args.map_to_odom_sigma, 2, "--map-to-odom-sigma"),
                          stale_after_s=args.stale_after)
    mount = _floats(args.sonar_mount, 3, "--sonar-mount")
    core = FusionCore(model, config)
    lock = threading.Lock()
    odom_pub = node.publisher("fusion/odom", latched=True)
    pose_pub = node.publisher("fusion/pose", latched=True)
    sonar_pub = node.publisher("fusion/sonar")
    points_pub = node.publisher("fusion/sonar_points")

    # Recover before integrating anything, so the odom pose continues instead of restarting at zero.
    last_odom = node.query_latest("fusion/odom", PoseEstimate, timeout=args.recover_timeout)
    last_pose = node.query_latest("fusion/pose", PoseEstimate, timeout=args.recover_timeout) if last_odom else None
    if core.restore(last_odom, last_pose):
        node.counters.add("recovered")
        log.info("recovered odom pose %s (stamp %d) from the bus", np.round(last_odom.position, 3),
                 last_odom.header.stamp_ns)
    else:
        log.info("no previous fusion/odom on the bus: starting at the odom origin")

    def on_wheels(msg: WheelOdometry) -> None:
        with lock:
            odom, pose = core.on_odometry(msg)
            step = core.last_step
            odom_pub.publish(odom)
            pose_pub.publish(pose)
        if step.ok:
            node.progress += 1
            if step.note.startswith("resynchronised"):
                node.counters.add("odometry_resynchronised")
                log.warning("odometry %s", step.note)
        else:
            node.counters.add("odometry_flagged")
            node.counters.add(f"odometry_flagged_{step.kind}")
            log.warning("odometry reading %d flagged: %s", msg.header.seq, step.flag)

    def on_correction(result, what: str) -> None:
        node.counters.add(f"{what}_{'fused' if result.accepted else 'refused'}")
        if not result.accepted:
            log.warning("%s not fused: %s", what, result.reason)

    def on_slam_pose(msg: PoseEstimate) -> None:
        with lock:
            result = core.on_slam_pose(msg)
        on_correction(result, "slam_pose")

    def on_map_to_odom(msg: TransformMsg) -> None:
        with lock:
            result = core.on_map_to_odom(msg)
        on_correction(result, "map_to_odom")

    def on_sonar(msg: SonarScan) -> None:
        try:
            scan = scan_in_base(msg, mount if msg.header.frame_id == args.sonar_frame else None)
        except SonarScanError as e:
            node.counters.add("sonar_refused")
            log.warning("%s", e)
            return
        sonar_pub.publish(scan)
        pts = echo_points(scan, args.sonar_height, args.arc_samples)
        points_pub.publish(FlyPopulation(positions=pts, fitness=np.ones(len(pts), np.float32),
                                         source_seq=msg.header.seq,
                                         header=header(0, msg.header.stamp_ns, BASE_LINK)))

    node.subscribe("odom/wheels", WheelOdometry, on_wheels)
    node.subscribe("slam/pose", PoseEstimate, on_slam_pose)
    node.subscribe("slam/map_to_odom", TransformMsg, on_map_to_odom)
    node.subscribe("sonar/scan", SonarScan, on_sonar)
    while node.sleep(0.5):
        pass
    return 0


def main(argv=None) -> int:
    return run_service("fusion", build_parser(), body, argv)


if __name__ == "__main__":
    sys.exit(main())
