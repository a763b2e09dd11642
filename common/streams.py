"""Every stream of the bus: its key (under ``<robot>/``), message type and delivery.

``latched``: the publisher keeps its last message and answers queries for it (late joiners get it
with :meth:`common.bus.Node.latched`); ``reliable``: the publisher blocks under congestion instead of
dropping. Services name streams through this module, never by a bare string. A key chunk starting with
``@`` is verbatim: no wildcard (``*``, ``**``) matches it, so only a subscriber that names the key gets it.
"""
from __future__ import annotations

from dataclasses import dataclass

from common import messages as m


@dataclass(frozen=True)
class Stream:
    key: str
    schema: type
    latched: bool = False
    reliable: bool = False

    def __str__(self) -> str:
        return self.key


# Sensors (simulator, camera, replay)
STEREO_FRAME = Stream("stereo/frame", m.StereoFrame)
STEREO_CALIBRATION = Stream("stereo/calibration", m.StereoCalibrationMsg, latched=True)
ODOM_WHEELS = Stream("odom/wheels", m.WheelOdometry)
SONAR_SCAN = Stream("sonar/scan", m.SonarScan)
# (reliable: every truth pose counts in the run's ATE; best-effort, one published right behind a frame's
# bytes can be dropped on a loaded machine)
TRUTH_POSE = Stream("truth/pose", m.PoseEstimate, reliable=True)
TRUTH_DEPTH = Stream("truth/depth", m.DepthImage)
# Fusion
FUSION_ODOM = Stream("fusion/odom", m.PoseEstimate, latched=True)
FUSION_POSE = Stream("fusion/pose", m.PoseEstimate, latched=True)
FUSION_SONAR = Stream("fusion/sonar", m.SonarScan)
FUSION_SONAR_POINTS = Stream("fusion/sonar_points", m.FlyPopulation)
# Evolver
FLIES_POPULATION = Stream("flies/population", m.FlyPopulation)
# Each frame's first population again, with the frame's grey left image as its side field: the localiser's
# input (photometric tracking). Verbatim (``@``), so that only the localiser receives the image (307 kB at
# 640×480), not every consumer of flies/population nor a recorder or viewer subscribed to ``**``.
FLIES_WITH_IMAGE = Stream("flies/population/@image", m.FlyPopulation)
TRACE_EVOLVER = Stream("trace/evolver", m.EvolverTrace)
# Localiser
SLAM_POSE = Stream("slam/pose", m.PoseEstimate)
SLAM_MAP_TO_ODOM = Stream("slam/map_to_odom", m.TransformMsg, latched=True)
SLAM_MAP = Stream("slam/map", m.FlyMap, latched=True)          # a queryable only, answered on demand
# Planner
PLANNER_TARGET = Stream("planner/target", m.Target, latched=True)
PLANNER_CMD_VEL = Stream("planner/cmd_vel", m.VelocityCommand, reliable=True)
PLANNER_FIELD = Stream("planner/field", m.HarmonicField)
# Health (every Node)
STATUS = Stream("status/*", m.Heartbeat)
HEALTH_PREFIX = "health/"
