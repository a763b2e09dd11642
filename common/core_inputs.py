"""What every service core latches between its inputs: the newest calibration message and an odometry
history (``FusionCore`` aside, the cores derive from :class:`LatchedInputs`)."""
from __future__ import annotations

import numpy as np

from common import messages as m
from common.geometry import invert
from common.pose_buffer import PoseBuffer


class LatchedInputs:
    """The newest ``stereo/calibration`` (applied by the core when it next needs it) and the odometry
    poses received so far (interpolated, or extrapolated, at a frame's stamp)."""

    def __init__(self, odometry: PoseBuffer):
        self.odometry = odometry
        self._calibration_msg: m.StereoCalibrationMsg | None = None

    def on_calibration(self, msg: m.StereoCalibrationMsg) -> None:
        self._calibration_msg = msg

    @property
    def has_calibration(self) -> bool:
        return self._calibration_msg is not None

    def on_odometry(self, stamp_ns: int, T_odom_base: np.ndarray) -> None:
        self.odometry.add(stamp_ns, T_odom_base)

    def odom_base_of(self, pop: m.FlyPopulation, T_base_camera: np.ndarray | None) -> np.ndarray | None:
        """base_link in odom at a population: the camera pose it carries (None without ``T_base_camera``),
        else the odometry history at its stamp (None when that is too far off)."""
        if pop.T_odom_camera is not None:
            return None if T_base_camera is None else pop.T_odom_camera @ invert(T_base_camera)
        return self.odometry.at(pop.header.stamp_ns)
