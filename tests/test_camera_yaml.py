"""Calibration YAML loading: OpenCV stereo_calib's two files, node aliases, unit handling, clear errors."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.camera import CalibrationError
from common.geometry import R_BODY_OPTICAL, make_transform, rot_z
from common.stereo_rectify import RawStereoRig, load_calibration, load_stereo_yaml, save_stereo_yaml

K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])


def _write(path, **nodes):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for name, value in nodes.items():
        fs.write(name, value)
    fs.release()
    return path


def test_opencv_sample_intrinsics_and_extrinsics_files_merge(tmp_path):
    # what samples/cpp/stereo_calib.cpp writes (8 rational-model coefficients, T in squares), plus a size
    intr = _write(tmp_path / "intrinsics.yml", M1=K, D1=np.zeros((1, 8)), M2=K, D2=np.zeros((1, 8)),
                  image_size=np.array([[640.0, 480.0]]))
    extr = _write(tmp_path / "extrinsics.yml", R=np.eye(3), T=np.array([[-4.0], [0.0], [0.0]]),
                  R1=np.eye(3) * 7, P1=np.ones((3, 4)))  # stale rectification products are ignored
    calib = load_calibration([intr, extr], units_m=0.025)
    assert (calib.width, calib.height) == (640, 480)
    assert calib.baseline == pytest.approx(0.1)
    assert np.allclose(calib.R_left, np.eye(3)) and calib.fx == pytest.approx(500)
    assert np.allclose(calib.T_base_camera[:3, :3], R_BODY_OPTICAL)  # camera looks along base_link +x


def test_missing_nodes_and_units_are_named(tmp_path):
    path = _write(tmp_path / "a.yml", image_width=640, image_height=480, K1=K, D1=np.zeros(5), D2=np.zeros(5),
                  R=np.eye(3), T=np.array([-0.1, 0, 0]), units_m=1.0)
    with pytest.raises(CalibrationError, match="no M2 or K2 node"):
        load_stereo_yaml(path)
    path = _write(tmp_path / "b.yml", M1=K, D1=np.zeros(5), M2=K, D2=np.zeros(5), R=np.eye(3),
                  T=np.array([-0.1, 0, 0]), units_m=1.0)
    with pytest.raises(CalibrationError, match="no image size"):
        load_stereo_yaml(path)
    with pytest.raises(CalibrationError, match="not found"):
        load_stereo_yaml(tmp_path / "missing.yml")
    path = _write(tmp_path / "c.yml", image_width=640, image_height=480, M1=K, D1=np.zeros(3), M2=K,
                  D2=np.zeros(5), R=np.eye(3), T=np.array([-0.1, 0, 0]), units_m=1.0)
    with pytest.raises(CalibrationError, match="D1 must have 4, 5, 8, 12 or 14 coefficients"):
        load_stereo_yaml(path)


def test_metres_in_a_square_unit_file_give_an_implausible_baseline_error(tmp_path):
    # T in millimetres declared as metres: 100 m baseline is refused, not silently used
    path = _write(tmp_path / "mm.yml", image_width=640, image_height=480, M1=K, D1=np.zeros(5), M2=K,
                  D2=np.zeros(5), R=np.eye(3), T=np.array([-100.0, 0, 0]), units_m=1.0)
    with pytest.raises(CalibrationError, match="implausible"):
        load_calibration(path)
    assert load_calibration(path, units_m=0.001).baseline == pytest.approx(0.1)


def test_save_then_load_round_trip_keeps_the_mounting(tmp_path):
    mount = make_transform(rot_z(0.3) @ R_BODY_OPTICAL, [0.2, 0.0, 0.5])
    rig = RawStereoRig(320, 240, K * [[0.5], [0.5], [1]], [-0.1, 0.01, 0, 0, 0], K * [[0.5], [0.5], [1]],
                       np.zeros(5), np.eye(3), [-0.06, 0.0, 0.0], T_base_camera=mount)
    save_stereo_yaml(tmp_path / "s.yaml", rig, info={"rms_stereo_px": 0.3})
    back = load_stereo_yaml(tmp_path / "s.yaml")
    assert np.allclose(back.K1, rig.K1) and np.allclose(back.D1, rig.D1) and np.allclose(back.T, rig.T)
    assert np.allclose(load_calibration(tmp_path / "s.yaml").T_base_camera, mount)
