"""Middlebury 2014 stereo: ``im0.png``, ``im1.png``, ``calib.txt`` and ``disp0.pfm`` in one folder.

``calib.txt`` gives ``cam0``/``cam1`` = [f 0 cx; 0 f cy; 0 0 1], ``doffs`` (= cx1 − cx0), ``baseline``
in millimetres, ``width``, ``height``. The pair is already rectified. ``disp0.pfm`` (left-view disparity,
inf = unknown) becomes ground-truth depth Z = baseline·f / (d + doffs) on ``truth/depth``.
A single pair has no time: it is written ``repeat`` times, ``period_ns`` apart from t = 0, each with the
identity truth pose (the camera does not move and defines the map).
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from common.camera import CalibrationError, StereoCalibration
from common.importers.base import DatasetLayoutError, StereoDataset, T_BASE_CAMERA, require

REQUIRED_KEYS = ("cam0", "cam1", "doffs", "baseline", "width", "height")


def parse_calib(path: Path) -> dict:
    """calib.txt → {key: float or 3×3 array}."""
    out = {}
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        key, sep, value = line.partition("=")
        if not sep:
            raise DatasetLayoutError(f"Middlebury: {path}:{lineno}: expected key=value, got {line[:40]!r}")
        value = value.strip()
        try:
            if value.startswith("["):
                rows = [r.split() for r in value.strip("[]").split(";")]
                out[key.strip()] = np.array(rows, dtype=np.float64)
            else:
                out[key.strip()] = float(value)
        except ValueError:
            raise DatasetLayoutError(f"Middlebury: {path}:{lineno}: {key.strip()} is not numeric") from None
    missing = [k for k in REQUIRED_KEYS if k not in out]
    if missing:
        raise DatasetLayoutError(f"Middlebury: {path} has no {', '.join(missing)}")
    for cam in ("cam0", "cam1"):
        if out[cam].shape != (3, 3):
            raise DatasetLayoutError(f"Middlebury: {path}: {cam} must be a 3×3 matrix")
    return out


def read_pfm(path: Path) -> np.ndarray:
    """A PFM image as float32 (H×W, or H×W×3 for 'PF'), top row first."""
    with open(path, "rb") as f:
        data = f.read()
    tokens, pos = [], 0
    while len(tokens) < 4:  # magic, width, height, scale: whitespace-separated, then one whitespace byte
        while pos < len(data) and data[pos:pos + 1].isspace():
            pos += 1
        start = pos
        while pos < len(data) and not data[pos:pos + 1].isspace():
            pos += 1
        if start == pos:
            raise DatasetLayoutError(f"Middlebury: {path}: truncated PFM header")
        tokens.append(data[start:pos].decode("ascii", "replace"))
    pos += 1
    magic = tokens[0]
    if magic not in ("Pf", "PF"):
        raise DatasetLayoutError(f"Middlebury: {path} is not a PFM file (magic {magic!r})")
    try:
        width, height, scale = int(tokens[1]), int(tokens[2]), float(tokens[3])
    except ValueError:
        raise DatasetLayoutError(f"Middlebury: {path}: bad PFM header {' '.join(tokens)!r}") from None
    channels = 3 if magic == "PF" else 1
    count = width * height * channels
    body = data[pos:]
    if len(body) < 4 * count:
        raise DatasetLayoutError(f"Middlebury: {path}: {len(body)} bytes of pixels, {4 * count} expected "
                                 f"for {width}×{height}×{channels}")
    img = np.frombuffer(body[: 4 * count], dtype="<f4" if scale < 0 else ">f4").astype(np.float32)
    img = img.reshape(height, width, channels)[::-1]  # PFM rows go bottom to top
    return np.ascontiguousarray(img[..., 0] if channels == 1 else img)


def depth_from_disparity(disp: np.ndarray, calib: StereoCalibration) -> np.ndarray:
    """Z (metres, float32) from Middlebury disparity; inf where the disparity is unknown."""
    d = disp.astype(np.float64) + calib.doffs
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(np.isfinite(d) & (d > 0), calib.fx * calib.baseline / d, np.inf)
    return z.astype(np.float32)


def _read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise DatasetLayoutError(f"Middlebury: cannot read image {path}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def load_middlebury(path, scale: float = 1.0, repeat: int = 1, period_ns: int = 100_000_000) -> StereoDataset:
    """A Middlebury 2014 scene folder; ``scale`` resizes images (and the calibration) on import."""
    folder = Path(path)
    require(folder, "Middlebury")
    im0, im1 = require(folder / "im0.png", "Middlebury"), require(folder / "im1.png", "Middlebury")
    cal = parse_calib(require(folder / "calib.txt", "Middlebury"))
    if not 0 < scale <= 1:
        raise DatasetLayoutError(f"Middlebury: --scale must be in (0, 1], got {scale}")
    if repeat < 1:
        raise DatasetLayoutError(f"Middlebury: repeat must be at least 1, got {repeat}")
    K0, K1 = cal["cam0"], cal["cam1"]
    if abs((K1[0, 2] - K0[0, 2]) - cal["doffs"]) > 0.5 or abs(K1[0, 0] - K0[0, 0]) > 1e-3 * K0[0, 0]:
        raise DatasetLayoutError(f"Middlebury: {folder / 'calib.txt'}: cam1 does not match cam0 and doffs "
                                 "(expected the same f and cx1 − cx0 = doffs)")
    try:
        calib = StereoCalibration.from_middlebury(f=K0[0, 0], cx_left=K0[0, 2], cy=K0[1, 2], doffs=cal["doffs"],
                                                  baseline_m=cal["baseline"] / 1000.0, width=int(cal["width"]),
                                                  height=int(cal["height"]))
    except CalibrationError as e:
        raise DatasetLayoutError(f"Middlebury: {folder / 'calib.txt'}: {e}") from None
    calib.T_base_camera = T_BASE_CAMERA.copy()
    left, right = _read_rgb(im0), _read_rgb(im1)
    for name, img in (("im0.png", left), ("im1.png", right)):
        if (img.shape[1], img.shape[0]) != (calib.width, calib.height):
            raise DatasetLayoutError(f"Middlebury: {folder / name} is {img.shape[1]}×{img.shape[0]} but calib.txt "
                                     f"says {calib.width}×{calib.height}")
    depth = None
    disp_file = folder / "disp0.pfm"
    notes = [] if disp_file.is_file() else [f"no ground-truth depth ({disp_file} not found)"]
    if disp_file.is_file():
        disp = read_pfm(disp_file)
        if disp.shape != left.shape[:2]:
            raise DatasetLayoutError(f"Middlebury: {disp_file} is {disp.shape[1]}×{disp.shape[0]}, "
                                     f"images are {calib.width}×{calib.height}")
        depth = depth_from_disparity(disp, calib)
    if scale != 1:
        calib = calib.scaled(scale)
        size = (calib.width, calib.height)
        left, right = (cv2.resize(img, size, interpolation=cv2.INTER_AREA) for img in (left, right))
        if depth is not None:
            depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)  # never blend across edges
    stamps = np.arange(repeat, dtype=np.int64) * int(period_ns)
    return StereoDataset(f"Middlebury 2014 {folder.resolve().name} ({calib.width}×{calib.height})", calib, stamps,
                         lambda i: (left, right), stamps.copy(), np.repeat(np.eye(4)[None], repeat, axis=0),
                         load_depth=None if depth is None else (lambda i: depth), notes=notes)
