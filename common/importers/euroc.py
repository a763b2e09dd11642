"""EuRoC MAV (ASL folder format): ``mav0/cam0``, ``mav0/cam1`` and the optional ground truth.

Each camera folder holds ``data.csv`` (``#timestamp [ns],filename``), ``data/<file>.png`` and
``sensor.yaml`` (pinhole ``intrinsics: [fu, fv, cu, cv]``, radial-tangential
``distortion_coefficients: [k1, k2, p1, p2]``, ``resolution: [w, h]`` and ``T_BS``, the camera's pose in
the body/IMU frame). The images are rectified on import (cv2.stereoRectify, alpha=0) with the rig
``T_cam1_cam0 = T_BS1⁻¹ · T_BS0``. Frames are paired by equal timestamps (the cameras are hardware
synchronised); unpaired images are skipped and reported.

Ground truth ``mav0/state_groundtruth_estimate0/data.csv`` (timestamp, p_RS_R xyz, q_RS_R wxyz, ...) is
the body pose in the world R; the rectified left camera's pose is ``T_R_S · T_BS0 · R_left⁻¹``, converted
to base_link in map with the map at the camera's pose nearest the first imported frame. Truth poses
are kept from the first to the last imported frame (at the ground truth's own rate, 200 Hz).
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from common.camera import CalibrationError
from common.geometry import invert, make_transform
from common.importers.base import DatasetLayoutError, StereoDataset, map_poses_from_camera, require
from common.stereo_rectify import RawStereoRig, StereoRectifier, read_node, rectify_rig


def read_sensor_yaml(path: Path) -> dict:
    """Intrinsics K, distortion D, resolution (w, h) and T_BS of one EuRoC camera."""
    require(path, "EuRoC")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):
        raise DatasetLayoutError(f"EuRoC: {path} is not readable YAML") from None

    def numbers(name, count):
        node = fs.getNode(name)
        if node.empty():
            raise DatasetLayoutError(f"EuRoC: {path} has no {name}")
        try:
            vals = read_node(node.getNode("data") if node.isMap() and not node.getNode("data").empty() else node,
                             f"{path}: {name}").ravel()
        except CalibrationError as e:
            raise DatasetLayoutError(f"EuRoC: {e}") from None
        if vals.size != count:
            raise DatasetLayoutError(f"EuRoC: {path}: {name} has {vals.size} numbers, expected {count}")
        return vals

    model = fs.getNode("distortion_model").string() if not fs.getNode("distortion_model").empty() else ""
    if model and model not in ("radial-tangential", "radtan", "plumb_bob"):
        raise DatasetLayoutError(f"EuRoC: {path}: distortion model {model!r} is not supported (radial-tangential)")
    fu, fv, cu, cv = numbers("intrinsics", 4)
    out = dict(K=np.array([[fu, 0, cu], [0, fv, cv], [0, 0, 1]]), D=numbers("distortion_coefficients", 4),
               size=tuple(int(v) for v in numbers("resolution", 2)), T_BS=numbers("T_BS", 16).reshape(4, 4))
    fs.release()
    return out


def read_camera_csv(path: Path) -> dict[int, str]:
    """data.csv → {timestamp ns: file name}."""
    require(path, "EuRoC")
    out = {}
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip() or line.startswith("#"):
            continue
        parts = [p.strip() for p in line.split(",")]
        try:
            out[int(parts[0])] = parts[1]
        except (ValueError, IndexError):
            raise DatasetLayoutError(f"EuRoC: {path}:{lineno}: expected 'timestamp_ns,filename'") from None
    return out


def read_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """state_groundtruth_estimate0/data.csv → (stamps ns, T_R_S poses (N, 4, 4))."""
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip() or line.startswith("#"):
            continue
        parts = line.split(",")
        try:
            rows.append((int(parts[0]), *(float(v) for v in parts[1:8])))
        except (ValueError, IndexError):
            raise DatasetLayoutError(f"EuRoC: {path}:{lineno}: expected timestamp, p xyz, q wxyz, ...") from None
    if not rows:
        return np.zeros(0, np.int64), np.zeros((0, 4, 4))
    stamps = np.array([r[0] for r in rows], np.int64)
    vals = np.array([r[1:] for r in rows])
    return stamps, poses_from_wxyz(vals[:, :3], vals[:, 3:7])


def poses_from_wxyz(positions: np.ndarray, q_wxyz: np.ndarray) -> np.ndarray:
    """(N, 4, 4) transforms from positions and (w, x, y, z) quaternions (normalised here), vectorised."""
    q = q_wxyz / np.linalg.norm(q_wxyz, axis=1, keepdims=True)
    w, x, y, z = q.T
    T = np.zeros((len(q), 4, 4))
    T[:, 0, :3] = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], 1)
    T[:, 1, :3] = np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], 1)
    T[:, 2, :3] = np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], 1)
    T[:, :3, 3] = positions
    T[:, 3, 3] = 1.0
    return T


def load_euroc(path, max_frames: int | None = None, camchain=None) -> StereoDataset:
    """An EuRoC MAV sequence; ``path`` is the folder holding ``mav0`` (or ``mav0`` itself).

    ``camchain``: a Kalibr camchain.yaml used instead of the sensor.yaml files (fisheye lenses, as in
    TUM-VI's EuRoC-format export; see common.importers.kalibr), T_BS = T_cam_imu⁻¹."""
    path = Path(path)
    require(path, "EuRoC")
    mav = path if path.name == "mav0" and not (path / "mav0").is_dir() else path / "mav0"
    cam0, cam1 = require(mav / "cam0", "EuRoC"), require(mav / "cam1", "EuRoC")
    if camchain is not None:
        from common.importers.kalibr import load_camchain
        rig, cams = load_camchain(camchain)
        calib, rectifier, R_left = rig.calibration, rig, rig.rotation_left
        T_BS0 = None if cams["cam0"].T_cam_imu is None else invert(cams["cam0"].T_cam_imu)
    else:
        s0, s1 = read_sensor_yaml(cam0 / "sensor.yaml"), read_sensor_yaml(cam1 / "sensor.yaml")
        if s0["size"] != s1["size"]:
            raise DatasetLayoutError(f"EuRoC: cam0 is {s0['size']} but cam1 is {s1['size']}")
        T_c1_c0 = invert(s1["T_BS"]) @ s0["T_BS"]
        try:
            calib = rectify_rig(RawStereoRig(*s0["size"], s0["K"], s0["D"], s1["K"], s1["D"],
                                             T_c1_c0[:3, :3], T_c1_c0[:3, 3]))
        except CalibrationError as e:
            raise DatasetLayoutError(f"EuRoC: {mav}: {e}") from None
        rectifier, R_left, T_BS0 = StereoRectifier(calib), calib.R_left, s0["T_BS"]
    rows0, rows1 = read_camera_csv(cam0 / "data.csv"), read_camera_csv(cam1 / "data.csv")
    paired = sorted(set(rows0) & set(rows1))
    if not paired:
        raise DatasetLayoutError(f"EuRoC: {cam0 / 'data.csv'} and {cam1 / 'data.csv'} share no timestamp")
    notes = []
    unpaired = len(rows0) + len(rows1) - 2 * len(paired)
    if unpaired:
        notes.append(f"{unpaired} images without a partner of the same timestamp skipped")
    n = len(paired) if max_frames is None else min(len(paired), int(max_frames))
    stamps = np.array(paired[:n], np.int64)

    def read(folder: Path, name: str) -> np.ndarray:
        p = folder / "data" / name
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise DatasetLayoutError(f"EuRoC: cannot read image {p}")
        return img

    def load_pair(i: int):
        t = int(stamps[i])
        return rectifier.rectify(read(cam0, rows0[t]), read(cam1, rows1[t]))

    truth_stamps, truth = np.zeros(0, np.int64), np.zeros((0, 4, 4))
    gt_file = mav / "state_groundtruth_estimate0" / "data.csv"
    if not gt_file.is_file() and (mav / "mocap0" / "data.csv").is_file():  # TUM-VI: the IMU's pose, same columns
        gt_file = mav / "mocap0" / "data.csv"
    if gt_file.is_file() and T_BS0 is None:
        notes.append(f"ground truth {gt_file} skipped: the camchain has no T_cam_imu for cam0")
    elif gt_file.is_file():
        gt_stamps, T_R_S = read_groundtruth(gt_file)
        keep = (gt_stamps >= stamps[0]) & (gt_stamps <= stamps[-1])
        if len(gt_stamps) and keep.any():
            T_cam0_rect = make_transform(np.asarray(R_left).T)
            T_R_rect = T_R_S @ T_BS0 @ T_cam0_rect
            ref = T_R_rect[int(np.argmin(np.abs(gt_stamps - stamps[0])))]
            truth_stamps, truth = gt_stamps[keep], map_poses_from_camera(T_R_rect[keep], reference=ref)
        else:
            notes.append(f"ground truth {gt_file} does not cover the imported frames")
    else:
        notes.append(f"no ground truth ({gt_file} not found)")
    return StereoDataset(f"EuRoC {path.resolve().name} ({n} of {len(paired)} stereo pairs)", calib, stamps,
                         load_pair, truth_stamps, truth, notes=notes)
