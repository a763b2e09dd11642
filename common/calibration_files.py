"""The stereo calibration a user already has → the rectified calibration and the rectifier of raw pairs.

``flyslam camera --calibration`` takes any of:

- OpenCV stereo YAML/XML, one file or several merged in order (``flyslam calibrate``, OpenCV's
  stereo_calib sample): :mod:`common.stereo_rectify`;
- a Kalibr ``camchain.yaml`` (cam0 the left camera, cam1 the right; radtan, or equidistant fisheye
  lenses): :mod:`common.importers.kalibr`;
- two ROS ``camera_info`` YAML files, left then right: what ROS's camera_calibration writes, or one
  echoed CameraInfo message each (``ros2 topic echo --once /left/camera_info > left.yaml``: what a
  stereo camera's driver publishes), read as a bag's CameraInfo is
  (:func:`common.importers.rosbag.calibration_from_camera_info`).

The format is told from the first file's content, never from its name. With a camchain or camera_info
files the camera sits at base_link, looking along +x (an OpenCV YAML may hold a ``T_base_camera``).
Every failure is one :class:`~common.camera.CalibrationError` line that names the file.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from common.camera import CalibrationError, StereoCalibration
from common.importers.base import DatasetLayoutError, load_yaml, numbers
from common.importers.kalibr import load_camchain
from common.importers.rosbag import calibration_from_camera_info
from common.stereo_rectify import StereoRectifier, load_calibration

_KALIBR = re.compile(r"^cam\d+\s*:", re.MULTILINE)
# top-level keys of camera_calibration's file (camera_matrix, ...) or of an echoed CameraInfo message
_CAMERA_INFO = re.compile(r"^(camera_matrix|projection_matrix|distortion_model)\s*:", re.MULTILINE)

# what to do about a swapped or unpaired rig, said in terms of this command's inputs (the files)
_CAMERA_INFO_REMEDIES = {"swap": "give the left camera's file first",
                         "pair": "calibrate the two cameras as one stereo rig"}

Rectify = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass
class CalibratedRig:
    """A rig's rectified calibration, the rectification of its raw (left, right) pairs, and what it was
    read from, in words."""
    calibration: StereoCalibration
    rectify: Rectify
    source: str


def calibration_format(path) -> str:
    """'kalibr', 'camera_info' or 'opencv' (also for a file this cannot read: OpenCV's reader says why)."""
    try:
        text = Path(path).read_text(errors="replace")
    except OSError:
        return "opencv"
    if _CAMERA_INFO.search(text):
        return "camera_info"
    if _KALIBR.search(text) and "intrinsics" in text:
        return "kalibr"
    return "opencv"


def load_rig(paths, units_m: float | None = None,
             image_size: Callable[[], tuple[int, int]] | None = None) -> CalibratedRig:
    """The rig the calibration file(s) ``paths`` describe (see the module doc for the formats).
    ``image_size``: the raw frames' (width, height), asked for only when an OpenCV YAML holds no size."""
    paths = [Path(p) for p in ([paths] if isinstance(paths, (str, Path)) else paths)]
    if not paths:
        raise CalibrationError("no calibration file given")
    kind = calibration_format(paths[0])
    if kind == "opencv":
        calib = load_calibration(paths, units_m, image_size)
        return CalibratedRig(calib, StereoRectifier(calib).rectify, "OpenCV stereo YAML")
    names = ", ".join(str(p) for p in paths)
    if units_m is not None:
        raise CalibrationError(f"{names}: --units-m applies to OpenCV stereo YAML only (a {kind} file is in metres)")
    try:
        if kind == "kalibr":
            if len(paths) != 1:
                raise CalibrationError(f"{names}: give one Kalibr camchain, not {len(paths)} files")
            rig, _ = load_camchain(paths[0])
            return CalibratedRig(rig.calibration, rig.rectify, f"Kalibr camchain ({rig.lens} lenses)")
        if len(paths) != 2:
            raise CalibrationError(f"{names}: camera_info YAML comes as two files, the left camera's then the "
                                   "right's (repeat --calibration)")
        left, right = (read_camera_info_yaml(p) for p in paths)
        calib, rectify, _, how = calibration_from_camera_info(left, right, str(paths[0]), str(paths[1]),
                                                              rectified=False, source="camera_info",
                                                              remedies=_CAMERA_INFO_REMEDIES)
        return CalibratedRig(calib, rectify, f"ROS camera_info ({how})")
    except DatasetLayoutError as e:
        raise CalibrationError(str(e)) from None


def read_camera_info_yaml(path) -> dict:
    """A camera_info YAML file as the arrays CameraInfo holds (K, D, R, P, size, model, binning): the
    file camera_calibration writes (camera_matrix: {rows, cols, data}, ...) or a ``ros2 topic echo`` /
    ``rostopic echo`` dump of one message (k / K, d / D, r / R, p / P, width, height)."""
    path = Path(path)
    doc = load_yaml(path, "camera_info")
    if not isinstance(doc, dict):
        raise DatasetLayoutError(f"camera_info: {path} is not a map of camera_info fields")

    def field(*names: str):
        return next((doc[n] for n in names if n in doc), None)

    def matrix(shape: tuple[int, ...] | None, *names: str, default=None) -> np.ndarray:
        node = field(*names)
        data = node.get("data") if isinstance(node, dict) else node
        if data is None:
            if default is None:
                raise DatasetLayoutError(f"camera_info: {path} has no {names[0]}")
            return default
        a = numbers(data, None if shape is None else int(np.prod(shape)), f"camera_info: {path}: {names[0]}")
        return a.ravel() if shape is None else a.reshape(shape)

    width, height = field("image_width", "width"), field("image_height", "height")
    if width is None or height is None:
        raise DatasetLayoutError(f"camera_info: {path} has no image_width and image_height")
    size = numbers([width, height], 2, f"camera_info: {path}: image_width and image_height")
    binning = [field("binning_x") or 0, field("binning_y") or 0]
    return dict(K=matrix((3, 3), "camera_matrix", "K", "k"), D=matrix(None, "distortion_coefficients", "D", "d",
                                                                       default=np.zeros(0)),
                R=matrix((3, 3), "rectification_matrix", "R", "r", default=np.zeros((3, 3))),
                P=matrix((3, 4), "projection_matrix", "P", "p"), size=(int(size[0]), int(size[1])),
                model=str(field("distortion_model") or "plumb_bob").lower(),
                binning=tuple(int(b) for b in numbers(binning, 2, f"camera_info: {path}: binning")))
