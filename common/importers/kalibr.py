"""Kalibr ``camchain.yaml`` (pinhole cameras, ``equidistant`` fisheye or ``radtan`` lenses) → a rectified
stereo rig: the remap tables, built once, and the :class:`~common.camera.StereoCalibration` of the
rectified images.

camchain keys per camera (``cam0``, ``cam1``, ...): ``camera_model`` (only ``pinhole``),
``distortion_model`` (``equidistant`` = OpenCV's fisheye / Kannala-Brandt k1..k4, ``radtan`` = OpenCV's
k1 k2 p1 p2, ``none``), ``intrinsics`` [fu, fv, pu, pv], ``distortion_coeffs``, ``resolution`` [w, h],
``T_cn_cnm1`` (camera n−1 → camera n: ``x_n = T·x_{n−1}``), optional ``T_cam_imu`` and ``rostopic``.

Fisheye lenses are rectified with ``cv2.fisheye.stereoRectify`` (the rotations) and
``cv2.fisheye.initUndistortRectifyMap`` at the raw resolution, with the raw focal length and the
principal point at the image centre: the centre keeps its resolution, and as a pinhole radius f·tan θ
grows faster than the fisheye's f·θ, the output stays (up to the small rectifying rotation) inside the
raw image. Radtan lenses go through :func:`rectify_rig`, as in the EuRoC importer. OpenCV's pinhole
model would read four fisheye coefficients as k1 k2 p1 p2, so a fisheye rig's calibration describes
the rectified images (K = P, no distortion, R = I), which is what an importer writes; the
raw-to-rectified rotation of the left camera is kept in :attr:`RectifiedRig.rotation_left`.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from common.camera import CalibrationError, StereoCalibration
from common.geometry import invert
from common.importers.base import DatasetLayoutError, load_yaml, numbers
from common.stereo_rectify import DEFAULT_T_BASE_CAMERA, RawStereoRig, rectify_rig

LENS_MODELS = ("equidistant", "radtan")


@dataclass
class KalibrCamera:
    """One camera of a camchain: pinhole intrinsics K, lens model and coefficients D, size (w, h)."""
    name: str
    lens: str  # "equidistant" or "radtan"
    K: np.ndarray
    D: np.ndarray
    size: tuple[int, int]
    T_cn_cnm1: np.ndarray | None = None  # previous camera → this camera
    T_cam_imu: np.ndarray | None = None  # IMU → this camera
    rostopic: str | None = None


@dataclass
class RectifiedRig:
    """A stereo rig ready to rectify raw image pairs: :meth:`rectify` is two remaps."""
    calibration: StereoCalibration
    maps: tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
    rotation_left: np.ndarray  # raw left optical frame → rectified left optical frame
    raw_size: tuple[int, int]
    lens: str

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rectified (left, right) from raw images; CalibrationError if one is not the raw size."""
        for img, which in ((left, "left"), (right, "right")):
            if (img.shape[1], img.shape[0]) != self.raw_size:
                raise CalibrationError(f"{which} image is {img.shape[1]}×{img.shape[0]} but the camera is "
                                       f"calibrated for {self.raw_size[0]}×{self.raw_size[1]}")
        (m1l, m2l), (m1r, m2r) = self.maps
        return cv2.remap(left, m1l, m2l, cv2.INTER_LINEAR), cv2.remap(right, m1r, m2r, cv2.INTER_LINEAR)


def lens_maps(lens: str, K, D, R, P, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Remap tables (CV_16SC2) from raw ``lens`` images to the rectified projection P (3×3 or 3×4)."""
    K, D, R = np.asarray(K, float), np.asarray(D, float).ravel(), np.asarray(R, float)
    P = np.asarray(P, float)
    if lens == "equidistant":
        return cv2.fisheye.initUndistortRectifyMap(K, D.reshape(4, 1), R, P[:3, :3], size, cv2.CV_16SC2)
    return cv2.initUndistortRectifyMap(K, D, R, P, size, cv2.CV_16SC2)


def rectify_pair(lens: str, K1, D1, K2, D2, size: tuple[int, int], R, T,
                 T_base_camera: np.ndarray | None = None) -> RectifiedRig:
    """Rectify a raw rig (OpenCV convention ``x_right = R·x_left + T``, T in metres) once.

    Raises CalibrationError for a vertical rig or one whose right camera is on the left.
    """
    if lens not in LENS_MODELS:
        raise CalibrationError(f"lens model {lens!r} is not supported (one of {', '.join(LENS_MODELS)})")
    T_base = DEFAULT_T_BASE_CAMERA.copy() if T_base_camera is None else np.asarray(T_base_camera, float)
    if lens == "radtan":
        calib = rectify_rig(RawStereoRig(size[0], size[1], K1, D1, K2, D2, R, T, T_base))
        maps = tuple(lens_maps(lens, K, D, Rr, P, size) for K, D, Rr, P in
                     ((calib.K_left, calib.D_left, calib.R_left, calib.P_left),
                      (calib.K_right, calib.D_right, calib.R_right, calib.P_right)))
        return RectifiedRig(calib, maps, np.asarray(calib.R_left, float), tuple(size), lens)
    raw = RawStereoRig(size[0], size[1], K1, D1, K2, D2, R, T, T_base)  # validates K, D, R, T
    if raw.D1.size != 4 or raw.D2.size != 4:
        raise CalibrationError("an equidistant lens has 4 coefficients k1..k4")
    if abs(raw.T.ravel()[1]) > abs(raw.T.ravel()[0]):      # (fisheye stereoRectify makes any rig horizontal)
        raise CalibrationError("the cameras are stacked vertically (T mostly along y); flyslam needs a horizontal rig")
    K1, K2, D1, D2 = raw.K1, raw.K2, raw.D1.reshape(4, 1), raw.D2.reshape(4, 1)
    R, T = raw.R.copy(), raw.T.reshape(3, 1).copy()  # contiguous for OpenCV
    try:
        R1, R2, P1, P2, _Q = cv2.fisheye.stereoRectify(K1, D1, K2, D2, size, R, T, flags=cv2.CALIB_ZERO_DISPARITY,
                                                       newImageSize=size)
    except cv2.error as e:
        raise CalibrationError(f"fisheye stereo rectification failed: {str(e).strip().splitlines()[-1]}") from None
    # OpenCV's choice of focal length and centre follows the undistorted image edges, which at 75°+ off
    # axis swing with the slightest rotation; the raw focal length at the image centre does not.
    f, (cx, cy) = float(np.mean([K1[0, 0], K1[1, 1], K2[0, 0], K2[1, 1]])), ((size[0] - 1) / 2, (size[1] - 1) / 2)
    tx = P2[0, 3] / P2[0, 0]  # −baseline
    P1 = np.array([[f, 0, cx, 0], [0, f, cy, 0], [0, 0, 1, 0]])
    P2 = np.array([[f, 0, cx, f * tx], [0, f, cy, P2[1, 3] / P2[1, 1] * f], [0, 0, 1, 0]])
    if abs(P2[1, 3]) > abs(P2[0, 3]):
        raise CalibrationError("the cameras are stacked vertically (T mostly along y); flyslam needs a horizontal rig")
    baseline = -P2[0, 3] / P2[0, 0]
    if baseline <= 0:
        raise CalibrationError(f"the right camera is to the LEFT of the left one (T = {T.ravel().round(4).tolist()}); "
                               "swap the left and right cameras")
    calib = StereoCalibration(width=size[0], height=size[1], fx=float(P1[0, 0]), fy=float(P1[1, 1]),
                              cx_left=float(P1[0, 2]), cx_right=float(P2[0, 2]), cy=float(P1[1, 2]),
                              baseline=float(baseline), K_left=P1[:, :3].copy(), K_right=P2[:, :3].copy(),
                              T_base_camera=T_base)
    maps = (lens_maps(lens, K1, D1, R1, P1, size), lens_maps(lens, K2, D2, R2, P2, size))
    return RectifiedRig(calib, maps, R1, tuple(size), lens)


# ------------------------------------------------------------------------------------------ camchain


def read_camchain(path) -> dict[str, KalibrCamera]:
    """Every ``camN`` entry of a Kalibr camchain.yaml, by name; DatasetLayoutError naming the bad key."""
    path = Path(path)
    doc = load_yaml(path, "Kalibr camchain")
    cams = {k: v for k, v in doc.items() if re.fullmatch(r"cam\d+", str(k))} if isinstance(doc, dict) else {}
    if not cams:
        raise DatasetLayoutError(f"Kalibr: {path} has no cam0/cam1 entries")
    out = {}
    for name, entry in cams.items():
        where = f"{path}: {name}"
        if not isinstance(entry, dict):
            raise DatasetLayoutError(f"Kalibr: {where} is not a map")
        for key in ("intrinsics", "distortion_coeffs", "resolution"):
            if key not in entry:
                raise DatasetLayoutError(f"Kalibr: {where} has no {key}")
        model = entry.get("camera_model", "pinhole")
        if model != "pinhole":
            raise DatasetLayoutError(f"Kalibr: {where}: camera_model {model!r} is not supported (pinhole)")
        lens = entry.get("distortion_model", "radtan")
        fu, fv, pu, pv = numbers(entry["intrinsics"], 4, f"Kalibr: {where}: intrinsics")
        coeffs = numbers(entry["distortion_coeffs"], None, f"Kalibr: {where}: distortion_coeffs").ravel()
        if lens == "none":
            lens, coeffs = "radtan", np.zeros(4)
        if lens not in LENS_MODELS:
            raise DatasetLayoutError(f"Kalibr: {where}: distortion_model {lens!r} is not supported "
                                     f"({', '.join(LENS_MODELS)})")
        if coeffs.size != 4:
            raise DatasetLayoutError(f"Kalibr: {where}: distortion_coeffs has {coeffs.size} numbers, expected 4")
        w, h = (int(v) for v in numbers(entry["resolution"], 2, f"Kalibr: {where}: resolution"))
        transforms = {key: numbers(entry[key], 16, f"Kalibr: {where}: {key}").reshape(4, 4)
                      for key in ("T_cn_cnm1", "T_cam_imu") if key in entry}
        out[name] = KalibrCamera(name, lens, np.array([[fu, 0, pu], [0, fv, pv], [0, 0, 1]]), coeffs, (w, h),
                                 transforms.get("T_cn_cnm1"), transforms.get("T_cam_imu"), entry.get("rostopic"))
    return out


def transform_between(cams: dict[str, KalibrCamera], source: str, target: str) -> np.ndarray:
    """``T_target_source`` (x_target = T·x_source) by chaining the cameras' T_cn_cnm1 from cam0."""
    def from_cam0(name: str) -> np.ndarray:
        index = int(name[3:])
        T = np.eye(4)
        for n in range(1, index + 1):
            cam = cams.get(f"cam{n}")
            if cam is None or cam.T_cn_cnm1 is None:
                raise DatasetLayoutError(f"Kalibr: cam{n} has no T_cn_cnm1, so {name} is not placed relative to cam0")
            T = cam.T_cn_cnm1 @ T
        return T
    return from_cam0(target) @ invert(from_cam0(source))


def load_camchain(path, left: str = "cam0", right: str = "cam1") -> tuple[RectifiedRig, dict[str, KalibrCamera]]:
    """The rectified rig of cameras ``left`` and ``right`` of a camchain.yaml, and all its cameras."""
    cams = read_camchain(path)
    for name in (left, right):
        if name not in cams:
            raise DatasetLayoutError(f"Kalibr: {path} has no {name} (cameras: {', '.join(sorted(cams))})")
    a, b = cams[left], cams[right]
    if a.size != b.size or a.lens != b.lens:
        raise DatasetLayoutError(f"Kalibr: {path}: {left} ({a.lens}, {a.size}) and {right} ({b.lens}, {b.size}) "
                                 "differ in lens model or resolution")
    try:
        T_rl = transform_between(cams, left, right)
    except DatasetLayoutError as e:
        raise DatasetLayoutError(f"{e} ({path})") from None
    try:
        rig = rectify_pair(a.lens, a.K, a.D, b.K, b.D, a.size, T_rl[:3, :3], T_rl[:3, 3])
    except CalibrationError as e:
        raise DatasetLayoutError(f"Kalibr: {path}: {e}") from None
    return rig, cams
