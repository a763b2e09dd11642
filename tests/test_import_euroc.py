"""`flyslam import euroc` on a small synthetic sequence in the EuRoC MAV (ASL) layout.

The sensor.yaml files use the real MH_01 cameras' extrinsics and distortion with intrinsics scaled to
188×120 images; the ground truth moves the body so that the *rectified* left camera flies straight
along its optical axis, which must come out as pure +x motion of base_link in map.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.geometry import invert, make_transform, quat_from_matrix, rot_z
from common.images import frame_images
from common.messages import StereoCalibrationMsg, calibration_from_msg, decode, transform_of
from common.recording import RecordingReader
from common.stereo_rectify import RawStereoRig, StereoRectifier, rectify_rig
from deploy.commands import importer

W, H = 188, 120
T_BS0 = [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
         -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949, 0.0, 0.0, 0.0, 1.0]
T_BS1 = [0.0125552670891, -0.999755099723, 0.0182237714554, -0.0198435579556,
         0.999598781151, 0.0130119051815, 0.0251588363115, 0.0453689425024,
         -0.0253898008918, 0.0179005838253, 0.999517347078, 0.00786212447038, 0.0, 0.0, 0.0, 1.0]
CAMS = {
    "cam0": dict(T_BS=T_BS0, intr=[458.654 / 4, 457.296 / 4, 367.215 / 4, 248.375 / 4],
                 dist=[-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]),
    "cam1": dict(T_BS=T_BS1, intr=[457.587 / 4, 456.134 / 4, 379.999 / 4, 255.238 / 4],
                 dist=[-0.28368365, 0.07451284, -0.00010473, -3.55590700e-05]),
}
T0 = 1403636579763555584
FRAME_STAMPS = [T0, T0 + 50_000_000, T0 + 100_000_000]
SPEED = 2.0  # m/s along the rectified left camera's optical axis


def _sensor_yaml(cam: dict) -> str:
    f = ", ".join
    return f"""%YAML:1.0
# General sensor definitions.
sensor_type: camera
comment: VI-Sensor (synthetic test copy)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [{f(str(v) for v in cam["T_BS"][:8])},
         {f(str(v) for v in cam["T_BS"][8:])}]

# Camera specific definitions.
rate_hz: 20
resolution: [{W}, {H}]
camera_model: pinhole
intrinsics: [{f(str(v) for v in cam["intr"])}] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [{f(str(v) for v in cam["dist"])}]
"""


def _rig() -> RawStereoRig:
    K = {}
    for name, c in CAMS.items():
        fu, fv, cu, cv = c["intr"]
        K[name] = np.array([[fu, 0, cu], [0, fv, cv], [0, 0, 1]])
    T_c1_c0 = invert(np.reshape(T_BS1, (4, 4))) @ np.reshape(T_BS0, (4, 4))
    return RawStereoRig(W, H, K["cam0"], CAMS["cam0"]["dist"], K["cam1"], CAMS["cam1"]["dist"],
                        T_c1_c0[:3, :3], T_c1_c0[:3, 3])


def _euroc(root, with_truth=True):
    mav = root / "mav0"
    rng = np.random.default_rng(7)
    raw = {}
    for name, cam in CAMS.items():
        (mav / name / "data").mkdir(parents=True)
        (mav / name / "sensor.yaml").write_text(_sensor_yaml(cam))
        stamps = FRAME_STAMPS + ([T0 + 25_000_000] if name == "cam1" else [])  # one unpaired image
        rows = ["#timestamp [ns],filename"]
        for t in stamps:
            img = cv2.GaussianBlur(rng.integers(0, 256, (H, W), dtype=np.uint8), (0, 0), 1.0)
            cv2.imwrite(str(mav / name / "data" / f"{t}.png"), img)
            raw[(name, t)] = img
            rows.append(f"{t},{t}.png")
        (mav / name / "data.csv").write_text("\n".join(rows) + "\n")
    if with_truth:
        # Rectified left camera pose in the world: a start pose, then straight along its optical z.
        R1 = rectify_rig(_rig()).R_left
        T_BS0_m, T_cam0_rect = np.reshape(T_BS0, (4, 4)), make_transform(np.asarray(R1).T)
        start = make_transform(rot_z(0.7), [1.0, 2.0, 0.5])
        rows = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
                "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], "
                "b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], "
                "b_a_RS_S_z [m s^-2]"]
        (mav / "state_groundtruth_estimate0").mkdir()
        for k in range(-4, 25):  # 200 Hz from 20 ms before the first frame to 20 ms after the last
            t = T0 + k * 5_000_000
            T_R_rect = start @ make_transform(translation=[0, 0, SPEED * (t - T0) * 1e-9])
            T_R_S = T_R_rect @ invert(T_BS0_m @ T_cam0_rect)
            qx, qy, qz, qw = quat_from_matrix(T_R_S[:3, :3])
            p = T_R_S[:3, 3]
            rows.append(f"{t}," + ",".join(f"{v:.12f}" for v in (*p, qw, qx, qy, qz)) + ",0" * 9)
        (mav / "state_groundtruth_estimate0" / "data.csv").write_text("\n".join(rows) + "\n")
    return raw


def test_euroc_round_trip_rectifies_and_converts_truth(tmp_path, capsys):
    raw = _euroc(tmp_path / "MH_test")
    out = tmp_path / "euroc.mcap"
    assert importer.main(["euroc", str(tmp_path / "MH_test"), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "frames     3 over 0.10 s" in text and "1 images without a partner" in text

    reader = RecordingReader(out)
    msgs = {}
    for m in reader.messages():
        msgs.setdefault(m.key, []).append(decode(m.payload))
    calib = calibration_from_msg(decode(reader.calibration_payload(), StereoCalibrationMsg))
    expected = rectify_rig(_rig())
    assert calib.fx == pytest.approx(expected.fx) and calib.cx_left == pytest.approx(calib.cx_right)
    assert calib.baseline == pytest.approx(0.110, abs=0.002)  # EuRoC's ~11 cm baseline
    assert np.allclose(calib.D_left, CAMS["cam0"]["dist"])

    frames = msgs["rig/stereo/frame"]
    assert [f.header.stamp_ns for f in frames] == FRAME_STAMPS
    rectifier = StereoRectifier(calib)
    for f, t in zip(frames, FRAME_STAMPS):
        left, right = frame_images(f)
        want_l, want_r = rectifier.rectify(raw[("cam0", t)], raw[("cam1", t)])
        assert np.array_equal(left, want_l) and np.array_equal(right, want_r)
        assert np.abs(left.astype(int) - raw[("cam0", t)]).mean() > 5  # rectification changed the image

    poses = msgs["rig/truth/pose"]
    stamps = [p.header.stamp_ns for p in poses]
    assert stamps[0] == FRAME_STAMPS[0] and stamps[-1] == FRAME_STAMPS[-1] and len(stamps) == 21
    for p in poses:
        T = transform_of(p)
        dist = SPEED * (p.header.stamp_ns - T0) * 1e-9
        assert T[:3, 3] == pytest.approx([dist, 0, 0], abs=1e-6)  # optical forward = map +x
        assert np.allclose(T[:3, :3], np.eye(3), atol=1e-6)


def test_euroc_missing_sensor_yaml_is_named(tmp_path, capsys):
    _euroc(tmp_path / "seq", with_truth=False)
    (tmp_path / "seq" / "mav0" / "cam1" / "sensor.yaml").unlink()
    assert importer.main(["euroc", str(tmp_path / "seq"), "--out", str(tmp_path / "x.mcap")]) == 2
    err = capsys.readouterr().err
    assert f"EuRoC: {tmp_path / 'seq' / 'mav0' / 'cam1' / 'sensor.yaml'} not found" in err


def test_euroc_without_truth_and_max_frames(tmp_path, capsys):
    _euroc(tmp_path / "seq", with_truth=False)
    out = tmp_path / "x.mcap"
    assert importer.main(["euroc", str(tmp_path / "seq" / "mav0"), "--max-frames", "2", "--out", str(out)]) == 0
    assert "no ground truth" in capsys.readouterr().out
    keys = [m.key for m in RecordingReader(out).messages()]
    assert keys.count("rig/stereo/frame") == 2 and "rig/truth/pose" not in keys
