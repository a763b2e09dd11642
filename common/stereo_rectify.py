"""Raw stereo rig calibration → rectified :class:`~common.camera.StereoCalibration`, its YAML file, and
the per-pixel rectification maps.

A *raw* rig is what a chessboard calibration gives: per camera the intrinsics K and distortion D, and
the rigid motion from the left to the right camera, OpenCV's convention ``x_right = R·x_left + T``.
:func:`rectify_rig` runs ``cv2.stereoRectify`` (alpha=0: every output pixel is valid,
``CALIB_ZERO_DISPARITY``: both rectified cameras share cx) and returns the rectified model the rest of
flyslam works with, carrying K, D and the rectifying rotations so :class:`StereoRectifier` can rebuild
the remap tables from the calibration alone (on the camera side, on import, anywhere).

Calibration YAML (``cv2.FileStorage``, what ``flyslam calibrate`` writes) — node names:

=====================  ================================================================================
``image_width``,       raw image size in pixels (or one node ``image_size``/``size`` = ``[w, h]``)
``image_height``
``M1`` (or ``K1``)     left camera matrix 3×3     — the names of OpenCV's ``stereo_calib`` sample,
``D1``                 left distortion (4, 5, 8, 12 or 14 coefficients, OpenCV order)
``M2`` (or ``K2``)     right camera matrix 3×3
``D2``                 right distortion
``R``, ``T``           rotation 3×3 and translation 3×1 from the left to the right camera
``units_m``            metres per unit of ``T`` (1.0 when T is in metres). OpenCV's sample writes T in
                       chessboard squares and no ``units_m``: pass ``units_m`` (``--units-m`` on the
                       command line, e.g. the square size 0.025) — without either, loading fails rather
                       than guessing a baseline.
``T_base_camera``      optional 4×4 pose of the left optical frame in base_link; default: camera
                       looking along base_link +x, no offset (``R_BODY_OPTICAL``)
=====================  ================================================================================

Several files may be given and are merged in order (OpenCV's sample writes ``intrinsics.yml`` and
``extrinsics.yml`` separately). Rectification products stored in the file (R1, P1, ...) are ignored:
they are recomputed, so the file cannot disagree with itself.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from common.camera import CalibrationError, StereoCalibration
from common.geometry import R_BODY_OPTICAL, make_transform

DEFAULT_T_BASE_CAMERA = make_transform(R_BODY_OPTICAL)

_ALIASES = {"K1": ("M1", "K1"), "D1": ("D1",), "K2": ("M2", "K2"), "D2": ("D2",), "R": ("R",), "T": ("T",)}


@dataclass
class RawStereoRig:
    """An unrectified stereo rig: ``x_right = R·x_left + T``, T in metres."""
    width: int
    height: int
    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    R: np.ndarray
    T: np.ndarray
    T_base_camera: np.ndarray = None  # pose of the left optical frame in base_link

    def __post_init__(self):
        self.K1, self.K2 = _matrix(self.K1, (3, 3), "K1"), _matrix(self.K2, (3, 3), "K2")
        self.D1, self.D2 = _distortion(self.D1, "D1"), _distortion(self.D2, "D2")
        self.R, self.T = _matrix(self.R, (3, 3), "R"), _matrix(self.T, (3,), "T")
        if self.T_base_camera is None:
            self.T_base_camera = DEFAULT_T_BASE_CAMERA.copy()
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise CalibrationError(f"image size must be positive, got {self.width}×{self.height}")
        self.width, self.height = int(self.width), int(self.height)
        if not np.allclose(self.R @ self.R.T, np.eye(3), atol=1e-4) or np.linalg.det(self.R) < 0:
            raise CalibrationError("R is not a rotation matrix")
        for name, K in (("K1", self.K1), ("K2", self.K2)):
            if K[0, 0] <= 0 or K[1, 1] <= 0:
                raise CalibrationError(f"{name}: focal lengths fx, fy must be positive, got {K[0, 0]:g}, {K[1, 1]:g}")
        if np.linalg.norm(self.T) < 1e-9:
            raise CalibrationError(f"T: the baseline must be non-zero (two cameras at one place cannot give "
                                   f"depth), got {self.T.tolist()}")

    @property
    def size(self) -> tuple[int, int]:
        return self.width, self.height


def _matrix(value, shape, name) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    if a.size != int(np.prod(shape)):
        raise CalibrationError(f"{name} must have {int(np.prod(shape))} elements {shape}, got {a.size}")
    a = a.reshape(shape)
    if not np.all(np.isfinite(a)):
        raise CalibrationError(f"{name} contains NaN or inf")
    return a


def _distortion(value, name) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64).ravel()
    if a.size not in (4, 5, 8, 12, 14):
        raise CalibrationError(f"{name} must have 4, 5, 8, 12 or 14 coefficients, got {a.size}")
    if not np.all(np.isfinite(a)):
        raise CalibrationError(f"{name} contains NaN or inf")
    return a


# ---------------------------------------------------------------------------------- rectification


def rectify_rig(rig: RawStereoRig, alpha: float = 0.0) -> StereoCalibration:
    """The rectified model of a raw rig (``cv2.stereoRectify``, zero disparity at infinity).

    Raises CalibrationError for a vertical rig or one whose right camera is on the left.
    """
    try:
        R1, R2, P1, P2, _Q, _roi1, _roi2 = cv2.stereoRectify(
            rig.K1, rig.D1, rig.K2, rig.D2, rig.size, rig.R, rig.T.reshape(3, 1),
            flags=cv2.CALIB_ZERO_DISPARITY, alpha=alpha)
    except cv2.error as e:
        raise CalibrationError(f"stereo rectification failed: {str(e).strip().splitlines()[-1]}") from None
    if not (np.all(np.isfinite(P1)) and np.all(np.isfinite(P2))):
        raise CalibrationError("stereo rectification gave non-finite projections (degenerate K, R or T)")
    if abs(P2[1, 3]) > abs(P2[0, 3]):
        raise CalibrationError("the cameras are stacked vertically (T mostly along y); flyslam needs a "
                               "horizontal rig")
    baseline = -P2[0, 3] / P2[0, 0]
    if baseline <= 0:
        raise CalibrationError(f"the right camera is to the LEFT of the left one (T = {rig.T.round(4).tolist()}); "
                               "swap the left and right inputs")
    return StereoCalibration(
        width=rig.width, height=rig.height, fx=float(P1[0, 0]), fy=float(P1[1, 1]),
        cx_left=float(P1[0, 2]), cx_right=float(P2[0, 2]), cy=float(P1[1, 2]), baseline=float(baseline),
        K_left=rig.K1.copy(), D_left=rig.D1.copy(), R_left=R1, K_right=rig.K2.copy(), D_right=rig.D2.copy(),
        R_right=R2, T_base_camera=np.asarray(rig.T_base_camera, float).copy())


class StereoRectifier:
    """Remap tables for a :class:`StereoCalibration`, computed once; :meth:`rectify` is two remaps.

    An already-rectified calibration (no distortion, identity R, K equal to the rectified projection)
    passes images through untouched.
    """

    def __init__(self, calib: StereoCalibration, interpolation: int = cv2.INTER_LINEAR):
        self.calib = calib
        self.interpolation = interpolation
        size = (calib.width, calib.height)
        self.passthrough = all(
            not np.any(np.asarray(D)) and np.allclose(R, np.eye(3)) and np.allclose(K, P[:, :3])
            for K, D, R, P in ((calib.K_left, calib.D_left, calib.R_left, calib.P_left),
                               (calib.K_right, calib.D_right, calib.R_right, calib.P_right)))
        self.maps = None
        if not self.passthrough:
            self.maps = [cv2.initUndistortRectifyMap(np.asarray(K, float), np.asarray(D, float).ravel(),
                                                     np.asarray(R, float), P, size, cv2.CV_16SC2)
                         for K, D, R, P in ((calib.K_left, calib.D_left, calib.R_left, calib.P_left),
                                            (calib.K_right, calib.D_right, calib.R_right, calib.P_right))]

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rectified (left, right); CalibrationError if an image is not the calibrated size."""
        self.calib.check_image(left, "left image")
        self.calib.check_image(right, "right image")
        if self.passthrough:
            return left, right
        (m1l, m2l), (m1r, m2r) = self.maps
        return (cv2.remap(left, m1l, m2l, self.interpolation),
                cv2.remap(right, m1r, m2r, self.interpolation))

    def rectify_points(self, points: np.ndarray, which: str) -> np.ndarray:
        """Raw pixel coordinates (N, 2) of the ``which`` ('left'/'right') camera → rectified pixels."""
        c = self.calib
        K, D, R, P = ((c.K_left, c.D_left, c.R_left, c.P_left) if which == "left"
                      else (c.K_right, c.D_right, c.R_right, c.P_right))
        pts = np.asarray(points, np.float64).reshape(-1, 1, 2)
        return cv2.undistortPoints(pts, np.asarray(K, float), np.asarray(D, float).ravel(),
                                   R=np.asarray(R, float), P=P).reshape(-1, 2)


def split_side_by_side(frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(left half, right half) of a side-by-side stereo frame (even width required)."""
    w = frame.shape[1]
    if w % 2:
        raise CalibrationError(f"a side-by-side frame must have an even width, got {w}")
    return frame[:, : w // 2], frame[:, w // 2:]


# ----------------------------------------------------------------------------------------- YAML


def _open(path: Path) -> cv2.FileStorage:
    if not path.is_file():
        raise CalibrationError(f"calibration file {path} not found")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:
        cause = e.__cause__ or e
        raise CalibrationError(f"{path}: not a readable OpenCV YAML/XML file ({str(cause).strip().splitlines()[-1]})") from None
    if not fs.isOpened():
        raise CalibrationError(f"{path}: not a readable OpenCV YAML/XML file")
    return fs


def read_node(node: cv2.FileNode, where: str) -> np.ndarray:
    """A numeric node (opencv-matrix, sequence of numbers, or scalar) as a float64 array."""
    if node.isMap():
        try:
            m = node.mat()
        except (cv2.error, SystemError):
            m = None
        if m is None:
            raise CalibrationError(f"{where} is a map, not a matrix")
        return np.asarray(m, np.float64)
    if node.isSeq():
        vals = [node.at(i) for i in range(node.size())]
        if not all(v.isReal() or v.isInt() for v in vals):
            raise CalibrationError(f"{where} must be a sequence of numbers")
        return np.array([v.real() for v in vals], np.float64)
    if node.isReal() or node.isInt():
        return np.array(node.real(), np.float64)
    raise CalibrationError(f"{where} is not numeric")


def _check_principal_points(nodes: dict, width: float, height: float, where: str) -> None:
    """A size taken from the frames must fit the intrinsics: each principal point within 20 % of the
    image's size from its centre (a calibration made at half or twice the resolution has it a quarter of
    the image away or beyond, and every depth would be wrong)."""
    for name in ("M1", "K1", "M2", "K2"):
        if name in nodes and nodes[name][0].size == 9:
            K = nodes[name][0].reshape(3, 3)
            cx, cy = float(K[0, 2]), float(K[1, 2])
            if not (abs(cx - width / 2) < 0.2 * width and abs(cy - height / 2) < 0.2 * height):
                raise CalibrationError(f"{where}: {name}'s principal point ({cx:.0f}, {cy:.0f}) does not fit the "
                                       f"camera's {width:.0f}×{height:.0f} frames: the calibration is for another "
                                       "resolution (or add image_width and image_height nodes)")


def load_stereo_yaml(paths, units_m: float | None = None,
                     image_size: Callable[[], tuple[int, int]] | None = None) -> RawStereoRig:
    """Read a raw rig from one or more OpenCV YAML/XML files (merged in order; see module doc).
    ``image_size``: asked for the raw (width, height) when the files hold none (OpenCV's ``stereo_calib``
    sample writes none): a camera knows the size of its own frames."""
    paths = [Path(p) for p in ([paths] if isinstance(paths, (str, Path)) else paths)]
    nodes: dict[str, tuple[np.ndarray, Path]] = {}
    for path in paths:
        fs = _open(path)
        root = fs.root()
        for name in root.keys():
            node = root.getNode(name)
            if node.isString():
                continue
            try:
                nodes[name] = (read_node(node, f"{path}: {name}"), path)
            except CalibrationError:
                continue  # a non-numeric node we do not use (comments, nested info)
        fs.release()
    where = ", ".join(str(p) for p in paths)

    def get(key):
        for alias in _ALIASES[key]:
            if alias in nodes:
                return nodes[alias][0]
        raise CalibrationError(f"{where}: no {' or '.join(_ALIASES[key])} node")

    if "image_width" in nodes and "image_height" in nodes:
        width, height = float(nodes["image_width"][0]), float(nodes["image_height"][0])
    else:
        size = next((nodes[k][0] for k in ("image_size", "size", "imageSize") if k in nodes), None)
        if size is not None and size.size == 2:
            width, height = size.ravel()
        elif image_size is not None:
            width, height = image_size()
            _check_principal_points(nodes, width, height, where)
        else:
            raise CalibrationError(f"{where}: no image size (add image_width and image_height nodes)")
    if units_m is None:
        if "units_m" not in nodes:
            raise CalibrationError(f"{where}: the unit of T is unknown — no units_m node; pass --units-m "
                                   "(metres per unit of T: the square size if T is in squares, 1 if in metres; "
                                   "--var units_m=... with a launch file)")
        units_m = float(nodes["units_m"][0])
    if not np.isfinite(units_m) or units_m <= 0:
        raise CalibrationError(f"units_m must be a positive number, got {units_m}")
    T_base = nodes["T_base_camera"][0] if "T_base_camera" in nodes else None
    try:
        rig = RawStereoRig(width=int(round(width)), height=int(round(height)), K1=get("K1"), D1=get("D1"),
                           K2=get("K2"), D2=get("D2"), R=get("R"), T=get("T").ravel() * units_m,
                           T_base_camera=None if T_base is None else _matrix(T_base, (4, 4), "T_base_camera"))
    except (CalibrationError, ValueError, OverflowError) as e:   # int() of a NaN or inf size, too
        raise CalibrationError(f"{where}: {e}") from None
    return rig


def save_stereo_yaml(path, rig: RawStereoRig, info: dict | None = None) -> None:
    """Write ``rig`` in the format :func:`load_stereo_yaml` reads (T in metres, ``units_m: 1``).

    ``info`` adds scalar nodes for the record (RMS errors, square size...); rectified R1/R2/P1/P2 are
    written too, for other tools, and ignored on reading.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    calib = rectify_rig(rig)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.writeComment("flyslam stereo calibration: x_right = R x_left + T, T in metres (units_m)")
    fs.write("image_width", rig.width)
    fs.write("image_height", rig.height)
    fs.write("M1", rig.K1)
    fs.write("D1", rig.D1.reshape(1, -1))
    fs.write("M2", rig.K2)
    fs.write("D2", rig.D2.reshape(1, -1))
    fs.write("R", rig.R)
    fs.write("T", rig.T.reshape(3, 1))
    fs.write("units_m", 1.0)
    fs.write("T_base_camera", np.asarray(rig.T_base_camera, float))
    for key, value in (info or {}).items():
        fs.write(key, value)
    fs.writeComment("rectification (alpha=0), informative only: recomputed on load")
    fs.write("R1", calib.R_left)
    fs.write("R2", calib.R_right)
    fs.write("P1", calib.P_left)
    fs.write("P2", calib.P_right)
    fs.write("baseline_m", calib.baseline)
    fs.release()


def load_calibration(paths, units_m: float | None = None,
                     image_size: Callable[[], tuple[int, int]] | None = None) -> StereoCalibration:
    """Rectified calibration from YAML file(s): :func:`load_stereo_yaml` then :func:`rectify_rig`;
    a CalibrationError names the file(s)."""
    rig = load_stereo_yaml(paths, units_m, image_size)
    try:
        return rectify_rig(rig)
    except CalibrationError as e:
        names = ", ".join(str(p) for p in ([paths] if isinstance(paths, (str, Path)) else paths))
        raise CalibrationError(f"{names}: {e}") from None
