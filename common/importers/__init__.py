"""Public stereo datasets → flyslam recordings.

Each format module (kitti, euroc, middlebury, rosbag) parses its dataset layout into a
:class:`~common.importers.base.StereoDataset` (rectified calibration, timestamped frame loaders, ground
truth in flyslam's frames); kalibr turns a Kalibr camchain.yaml into a rectified rig;
:func:`~common.importers.base.write_recording` turns any of them into an MCAP recording.
"""
from __future__ import annotations

from common.importers.base import DatasetLayoutError, ImportSummary, StereoDataset, write_recording

FORMATS = ("kitti", "euroc", "middlebury", "rosbag")

__all__ = ["DatasetLayoutError", "ImportSummary", "StereoDataset", "write_recording", "FORMATS"]
