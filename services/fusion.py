"""Fusion service: wheel odometry + localiser corrections → one best pose; sonar scans in base_link.

Subscribes ``odom/wheels`` (every message), ``slam/pose`` and ``slam/map_to_odom`` (corrections; a
map→odom without a matching pose is fused with ``--map-to-odom-sigma``) and ``sonar/scan`` (in base_link
or in ``--sonar-frame`` mounted at ``--sonar-mount``). Publishes ``fusion/odom`` (base_link in odom) and
``fusion/pose`` (base_link in map), both latched, at most ``--publish-hz`` a second (the newest reading's
state; a change of status kind at once: :mod:`common.fusion.output_rate`), with status 'ok', 'odometry only' or
'flagged: <why>'; ``fusion/sonar`` (the scan in base_link) and ``fusion/sonar_points`` (echo
points in base_link for the planner, ``--arc-samples`` per echo, fitness 1, source_seq = the scan's seq).

On start it continues from the latched ``fusion/odom``/``fusion/pose`` found on the bus (kept by a
recorder, a storage or the supervisor), so a restart does not send the odom pose back to zero. The
state machine is :class:`common.fusion.core.FusionCore`.
"""
from __future__ import annotations

import logging
import sys
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from common import messages as m
from common import streams as S
from common.config_args import add_config_arguments
from common.fusion.core import FusionCore
from common.fusion.odometry import OdometryModel
from common.fusion.output_rate import OutputRate
from common.fusion.pose_filter import FilterConfig
from common.fusion.sonar import SonarScanError, echo_points, scan_in_base
from services.base import config_or_exit, run_service, service_parser

log = logging.getLogger("flyslam.fusion")
ODOMETRY_RENAME = {"wheel_radius_m": "wheel-radius", "track_width_m": "track-width", "k_wheel_m": "k-wheel",
                   "max_wheel_speed_radps": "max-wheel-speed", "max_gap_s": "max-gap"}
FILTER_FLAGS = ["map_to_odom_sigma", "stale_after_s"]
FILTER_RENAME = {"stale_after_s": "stale-after"}


@dataclass
class FusionServiceConfig:
    """The fusion service's sonar geometry and start-up recovery."""
    sonar_frame: str = field(default=m.BASE_LINK, metadata={"help": "frame the sonar scans may arrive in"})
    sonar_mount: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0), metadata={
        "help": "x y yaw of --sonar-frame in base_link", "metavar": ("X", "Y", "YAW")})
    sonar_height: float = field(default=0.25, metadata={"help": "height of the sonar ring (m)"})
    arc_samples: int = field(default=5, metadata={"help": "obstacle points per sonar echo"})
    recover_timeout: float = field(default=1.0, metadata={
        "help": "seconds to wait for the latched fusion/odom and fusion/pose at start"})
    publish_hz: float = field(default=30.0, metadata={
        "help": "fusion/odom and fusion/pose at most this often (Hz of reading stamps; 0: every reading)"})

    def __post_init__(self):
        if not (self.publish_hz == 0 or 0.1 <= self.publish_hz < float("inf")):
            raise ValueError(f"publish_hz must be 0 (every reading) or a finite rate of at least 0.1 Hz, got "
                             f"{self.publish_hz}")


def build_parser():
    p = service_parser("fusion", __doc__.splitlines()[0])
    add_config_arguments(p, OdometryModel, rename=ODOMETRY_RENAME, helps={
        "wheel_radius_m": "wheel radius (m) when readings carry 0",
        "track_width_m": "track width (m) when readings carry 0",
        "k_wheel_m": "wheel travel variance per metre travelled (m²/m)",
        "max_wheel_speed_radps": "faster wheel speed (rad/s) is a jump: the reading is flagged",
        "max_gap_s": "longer speeds-only gaps (s) are not integrated"})
    add_config_arguments(p, FilterConfig, only=FILTER_FLAGS, rename=FILTER_RENAME, helps={
        "map_to_odom_sigma": "σ_xy (m) and σ_yaw (rad) assumed for slam/map_to_odom",
        "stale_after_s": "seconds without a correction before fusion/pose says 'odometry only'"})
    add_config_arguments(p, FusionServiceConfig)
    return p


def sonar_outputs(msg: m.SonarScan, run: FusionServiceConfig) -> tuple[m.SonarScan, m.FlyPopulation]:
    """(scan in base_link, its echo points as a FlyPopulation); raises SonarScanError."""
    scan = scan_in_base(msg, run.sonar_mount if msg.header.frame_id == run.sonar_frame else None)
    pts = echo_points(scan, run.sonar_height, run.arc_samples)
    return scan, m.FlyPopulation(positions=pts, fitness=np.ones(len(pts), np.float32), source_seq=msg.header.seq,
                                 header=m.header(0, msg.header.stamp_ns, m.BASE_LINK))


def recover(node, core: FusionCore, timeout: float) -> None:
    """Continue from the latched outputs of a previous run, before integrating anything."""
    last_odom = node.query_latest(S.FUSION_ODOM, timeout=timeout)
    last_pose = node.query_latest(S.FUSION_POSE, timeout=timeout) if last_odom else None
    if core.restore(last_odom, last_pose):
        node.counters.add("recovered")
        log.info("recovered odom pose %s (stamp %d) from the bus", np.round(last_odom.position, 3),
                 last_odom.header.stamp_ns)
    else:
        log.info("no previous fusion/odom on the bus: starting at the odom origin")


class FusionHandlers:
    """The subscriptions' callbacks: FusionCore under one lock, its outputs published (paced by
    ``--publish-hz``), problems counted."""

    def __init__(self, node, core: FusionCore, run: FusionServiceConfig):
        self.node, self.core, self.run = node, core, run
        self.lock = threading.Lock()
        self.pubs = {s: node.publisher(s) for s in (S.FUSION_ODOM, S.FUSION_POSE, S.FUSION_SONAR,
                                                     S.FUSION_SONAR_POINTS)}
        self._slam_correction = self.correction(core.on_slam_pose, "slam_pose")
        self.rate = OutputRate(run.publish_hz)
        self._held: tuple[m.PoseEstimate, m.PoseEstimate] | None = None

    def _publish(self, odom: m.PoseEstimate, pose: m.PoseEstimate) -> None:
        self.pubs[S.FUSION_ODOM].publish(odom)
        self.pubs[S.FUSION_POSE].publish(pose)

    def _output(self, odom: m.PoseEstimate, pose: m.PoseEstimate) -> None:
        """Publish the (fusion/odom, fusion/pose) pair now, or hold it as the newest until it is due."""
        if self.rate.due(odom.header.stamp_ns, (odom.status, pose.status), time.monotonic()):
            self._held = None
            self._publish(odom, pose)
        else:
            self._held = (odom, pose)

    def flush_overdue(self, stopping: bool = False) -> None:
        """Publish the held pair once it has waited a period (the readings stopped or slowed), or at once
        when the service stops (the latched outputs then hold the newest state)."""
        with self.lock:
            if self._held is not None and (self.rate.overdue(time.monotonic()) or stopping):
                self._publish(*self._held)
                self._held = None

    def on_wheels(self, msg: m.WheelOdometry) -> None:
        with self.lock:
            odom, pose = self.core.on_odometry(msg)
            step = self.core.last_step
            self._output(odom, pose)
        if step.ok:
            self.node.progress += 1
            if step.note.startswith("resynchronised"):
                self.node.counters.add("odometry_resynchronised")
                log.warning("odometry %s", step.note)
        else:
            self.node.counters.add("odometry_flagged")
            self.node.counters.add(f"odometry_flagged_{step.kind}")
            log.warning("odometry reading %d flagged: %s", msg.header.seq, step.flag)

    def correction(self, handler, what: str):
        def on_msg(msg) -> None:
            with self.lock:
                result = handler(msg)
            self.node.counters.add(f"{what}_{'fused' if result.accepted else 'refused'}")
            if not result.accepted:   # a map->odom of the pose just fused is a duplicate, not a problem
                log.log(logging.DEBUG if result.reason.startswith("duplicate") else logging.WARNING,
                        "%s not fused: %s", what, result.reason)
        return on_msg

    def on_slam_pose(self, msg: m.PoseEstimate) -> None:
        """Without wheels: the localiser's estimate is republished as odometry; else fused as a correction."""
        with self.lock:
            visual = self.core.visual_odometry(msg)
            if visual is not None:      # at the camera's rate already: not paced (camera stamps jitter)
                self._publish(*visual)
        if visual is not None:
            self.node.progress += 1
            return
        self._slam_correction(msg)

    def on_sonar(self, msg: m.SonarScan) -> None:
        try:
            scan, points = sonar_outputs(msg, self.run)
        except SonarScanError as e:
            self.node.counters.add("sonar_refused")
            log.warning("%s", e)
            return
        self.pubs[S.FUSION_SONAR].publish(scan)
        self.pubs[S.FUSION_SONAR_POINTS].publish(points)


def body(node, args) -> int:
    run = config_or_exit(FusionServiceConfig, args)
    core = FusionCore(config_or_exit(OdometryModel, args, rename=ODOMETRY_RENAME),
                      config_or_exit(FilterConfig, args, only=FILTER_FLAGS, rename=FILTER_RENAME))
    handlers = FusionHandlers(node, core, run)
    recover(node, core, run.recover_timeout)
    node.subscribe(S.ODOM_WHEELS, callback=handlers.on_wheels)
    node.subscribe(S.SLAM_POSE, callback=handlers.on_slam_pose)
    node.subscribe(S.SLAM_MAP_TO_ODOM, callback=handlers.correction(core.on_map_to_odom, "map_to_odom"))
    node.subscribe(S.SONAR_SCAN, callback=handlers.on_sonar)
    while node.sleep(min(max(1.0 / run.publish_hz, 0.01), 0.5) if run.publish_hz > 0 else 0.5):
        handlers.flush_overdue()
    handlers.flush_overdue(stopping=True)
    return 0


def main(argv=None) -> int:
    return run_service("fusion", build_parser(), body, argv)


if __name__ == "__main__":
    sys.exit(main())
