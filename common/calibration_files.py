"""The stereo calibration a user already has → the rectified calibration and the rectifier of raw pairs.

``flyslam camera --calibration`` takes any of:

- OpenCV stereo YAML/XML, one file or several merged in order (``flyslam calibrate``, OpenCV's
  stereo_calib sample): :mod:`common.stereo_rectify`;
- a Kalibr ``camchain.yaml`` (cam0 the left camera, cam1 the right; radtan, or equidistant fisheye
  lenses): :mod:`common.importers.kalibr`;
- two ROS ``camera_info`` YAML files, left then right (what ROS's camera_calibration writes, and what
  a stereo camera's ROS driver publishes): read as a bag's CameraInfo is
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
from common.importers.base import DatasetLayoutError
from common.importers.kalibr import load_camchain
from common.importers.rosbag import calibration_from_camera_info
from common.stereo_rectify import StereoRectifier, load_calibration

FORMATS = ("opencv", "kalibr", "camera_info")
_KALIBR = re.compile(r"^cam\d+\s*:", re.MULTILINE)
_CAMERA_INFO_KEYS = ("camera_matrix", "projection_matrix")

# calibration_from_camera_info speaks to `flyslam import rosbag`'s flags; here the files are the flags
_CAMERA_INFO_REMEDIES = {"swap --left and --right": "give the left camera's file first",
                         "(use --camchain)": "(calibrate the two cameras as one stereo rig)"}

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
    if all(re.search(rf"^{key}\s*:", text, re.MULTILINE) for key in _CAMERA_INFO_KEYS):
        return "camera_info"
    if _KALIBR.search(text) and "intrinsics" in text:
        return "kalibr"
    return "opencv"


def load_rig(paths, units_m: float | None = None) -> CalibratedRig:
    """The rig the calibration file(s) ``paths`` describe (see the module doc for the formats)."""
    paths = [Path(p) for p in ([paths] if isinstance(paths, (str, Path)) else paths)]
    if not paths:
        raise CalibrationError("no calibration file given")
    kind = calibration_format(paths[0])
    if kind == "opencv":
        calib = load_calibration(paths, units_m)
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
                                                              rectified=False, source="camera_info")
        return CalibratedRig(calib, rectify, f"ROS camera_info ({how})")
    except DatasetLayoutError as e:
        text = str(e)
        for flag, remedy in _CAMERA_INFO_REMEDIES.items():
            text = text.replace(flag, remedy) if kind == "camera_info" else text
        raise CalibrationError(text) from None


def read_camera_info_yaml(path) -> dict:
    """A ROS camera_info YAML file as the arrays CameraInfo holds: K, D, R, P, size, model, binning."""
    from ruamel.yaml import YAML, YAMLError  # rosbags' own YAML reader

    path = Path(path)
    try:
        doc = YAML(typ="safe", pure=True).load(path.read_text())
    except OSError as e:
        raise CalibrationError(f"{path}: cannot read ({e.strerror or e})") from None
    except (YAMLError, UnicodeDecodeError) as e:
        raise CalibrationError(f"{path} is not readable YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(doc, dict):
        raise CalibrationError(f"{path}: not a camera_info map")

    def matrix(key: str, shape: tuple[int, ...], required: bool = True) -> np.ndarray:
        node = doc.get(key)
        data = node.get("data") if isinstance(node, dict) else node
        if data is None:
            if required:
                raise CalibrationError(f"{path}: no {key}")
            return np.zeros(shape)
        try:
            a = np.array(data, dtype=np.float64)
        except (TypeError, ValueError):
            raise CalibrationError(f"{path}: {key} is not numeric") from None
        if int(np.prod(shape)) and a.size != int(np.prod(shape)):
            raise CalibrationError(f"{path}: {key} has {a.size} numbers, expected {int(np.prod(shape))}")
        if not np.all(np.isfinite(a)):
            raise CalibrationError(f"{path}: {key} contains NaN or inf")
        return a.reshape(shape) if int(np.prod(shape)) else a.ravel()

    try:
        size = (int(doc["image_width"]), int(doc["image_height"]))
    except (KeyError, TypeError, ValueError):
        raise CalibrationError(f"{path}: no integer image_width and image_height") from None
    return dict(K=matrix("camera_matrix", (3, 3)), D=matrix("distortion_coefficients", (0,), required=False),
                R=matrix("rectification_matrix", (3, 3), required=False), P=matrix("projection_matrix", (3, 4)),
                size=size, model=str(doc.get("distortion_model", "plumb_bob")).lower(), binning=(0, 0))
