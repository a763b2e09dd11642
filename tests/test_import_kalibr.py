"""Kalibr camchain.yaml with fisheye (equidistant) lenses → rectified rig, on a synthetic TUM-VI-like rig.

Known 3-D points are drawn as small blobs into the two raw fisheye images (cv2.fisheye.projectPoints);
after rectification the blobs of one point must sit on the same row in both images and where the
rectified calibration (focal length, baseline) says they should. The same rig as a TUM-VI EuRoC-format
folder (`flyslam import euroc --camchain`) must give rectified frames and the IMU's mocap truth as
base_link motion.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.camera import CalibrationError
from common.geometry import invert, make_transform, quat_from_matrix, rot_x, rot_y, rot_z
from common.images import frame_images
from common.importers.base import DatasetLayoutError
from common.importers.euroc import load_euroc
from common.importers.kalibr import load_camchain, read_camchain, rectify_pair
from common.messages import StereoCalibrationMsg, calibration_from_msg, decode, transform_of
from common.recording import RecordingReader
from deploy.commands import importer

W = H = 512
K0 = np.array([[190.98, 0, 254.93], [0, 190.97, 256.90], [0, 0, 1]])
K1 = np.array([[190.44, 0, 252.60], [0, 190.43, 254.92], [0, 0, 1]])
D0 = np.array([0.00348, 0.00072, -0.00205, 0.00020])
D1 = np.array([0.00340, 0.00177, -0.00266, 0.00033])
BASELINE = 0.101
# cam0 → cam1 (x_cam1 = T·x_cam0): cam1 sits 0.101 m along cam0's +x, slightly rotated and offset.
T_C1_C0 = make_transform(rot_x(0.004) @ rot_y(-0.006) @ rot_z(0.003), [-BASELINE, -0.002, -0.001])


def _rows(T: np.ndarray) -> str:
    return "\n".join(f"  - [{', '.join(repr(float(v)) for v in row)}]" for row in T)


def _camchain(path, lens="equidistant", model="pinhole", drop=None) -> str:
    cams = []
    for name, K, D in (("cam0", K0, D0), ("cam1", K1, D1)):
        entry = {"camera_model": f"  camera_model: {model}",
                 "distortion_coeffs": f"  distortion_coeffs: [{', '.join(repr(float(v)) for v in D)}]",
                 "distortion_model": f"  distortion_model: {lens}",
                 "intrinsics": f"  intrinsics: [{K[0, 0]}, {K[1, 1]}, {K[0, 2]}, {K[1, 2]}]",
                 "resolution": f"  resolution: [{W}, {H}]", "rostopic": f"  rostopic: /{name}/image_raw"}
        if drop:
            entry.pop(drop, None)
        extra = f"  T_cn_cnm1:\n{_rows(T_C1_C0)}\n" if name == "cam1" else ""
        cams.append(f"{name}:\n  T_cam_imu:\n{_rows(np.eye(4))}\n{extra}" + "\n".join(entry.values()))
    path.write_text("\n".join(cams) + "\n")
    return path


def _points(rng) -> np.ndarray:
    """A 7×7 fan of directions out to ±45° off axis, each at a random depth of 1.5–6 m (cam0 frame)."""
    a = np.deg2rad(np.linspace(-45, 45, 7))
    ax, ay = np.meshgrid(a, a)
    dirs = np.stack([np.tan(ax), np.tan(ay), np.ones_like(ax)], -1).reshape(-1, 3)
    return dirs * rng.uniform(1.5, 6.0, (len(dirs), 1))


def _render(points_cam: np.ndarray, K, D) -> np.ndarray:
    """Gaussian blobs (σ 1.2 px) at the fisheye projections of ``points_cam``."""
    uv, _ = cv2.fisheye.projectPoints(points_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D.reshape(4, 1))
    img = np.zeros((H, W), np.float64)
    yy, xx = np.mgrid[0:H, 0:W]
    for u, v in uv.reshape(-1, 2):
        x0, y0 = int(round(u)), int(round(v))
        sl = np.s_[max(y0 - 5, 0):y0 + 6, max(x0 - 5, 0):x0 + 6]
        img[sl] += np.exp(-((xx[sl] - u) ** 2 + (yy[sl] - v) ** 2) / (2 * 1.2 ** 2))
    return np.clip(img * 250, 0, 255).astype(np.uint8)


def _centroids(img: np.ndarray) -> np.ndarray:
    """Intensity-weighted centroids (N, 2) of the blobs of a rectified image."""
    n, labels = cv2.connectedComponents((img > 20).astype(np.uint8))
    w = img.astype(np.float64).ravel()
    yy, xx = np.indices(img.shape)
    mass = np.bincount(labels.ravel(), w, n)
    cu = np.bincount(labels.ravel(), w * xx.ravel(), n) / np.maximum(mass, 1e-9)
    cv = np.bincount(labels.ravel(), w * yy.ravel(), n) / np.maximum(mass, 1e-9)
    return np.stack([cu, cv], 1)[1:]


def _nearest(found: np.ndarray, expected: np.ndarray) -> np.ndarray:
    """For each expected point, the nearest found centroid (NaN where none is within 3 px)."""
    d = np.linalg.norm(expected[:, None] - found[None], axis=2)
    j = d.argmin(1)
    out = found[j].copy()
    out[d[np.arange(len(expected)), j] > 3.0] = np.nan
    return out


def render_rig():
    """(points in cam0, raw left image, raw right image) of the synthetic fisheye rig."""
    X0 = _points(np.random.default_rng(4))
    X1 = X0 @ T_C1_C0[:3, :3].T + T_C1_C0[:3, 3]
    return X0, _render(X0, K0, D0), _render(X1, K1, D1)


@pytest.fixture(scope="module")
def rendered():
    return render_rig()


def test_fisheye_camchain_rectifies_rows_and_recovers_baseline(tmp_path, rendered):
    X0, raw_left, raw_right = rendered
    rig, cams = load_camchain(_camchain(tmp_path / "camchain.yaml"))
    calib = rig.calibration
    assert cams["cam1"].rostopic == "/cam1/image_raw" and rig.lens == "equidistant"
    assert calib.baseline == pytest.approx(np.linalg.norm(T_C1_C0[:3, 3]), rel=1e-6)
    assert (calib.width, calib.height) == (W, H)
    left, right = rig.rectify(raw_left, raw_right)
    # Where the rectified model puts each point, in the rectified left frame.
    u_l, u_r, v = calib.project(X0 @ np.asarray(rig.rotation_left).T)
    found_l = _nearest(_centroids(left), np.stack([u_l, v], 1))
    found_r = _nearest(_centroids(right), np.stack([u_r, v], 1))
    both = np.isfinite(found_l[:, 0]) & np.isfinite(found_r[:, 0])
    assert both.sum() >= 0.9 * len(X0), f"only {both.sum()} of {len(X0)} points found in both rectified images"
    epipolar = np.abs(found_l[both, 1] - found_r[both, 1])
    assert epipolar.max() < 0.5, f"rows differ by up to {epipolar.max():.2f} px after rectification"
    # Baseline from the measured disparities and the true depths (rectified frame), as a user would check it.
    z = (X0 @ np.asarray(rig.rotation_left).T)[both, 2]
    measured = np.median((found_l[both, 0] - found_r[both, 0]) * z / calib.fx)
    assert measured == pytest.approx(BASELINE, rel=0.02)
    # The rectified calibration itself places the blobs to within half a pixel.
    assert np.abs(found_l[both] - np.stack([u_l, v], 1)[both]).max() < 0.5


def test_fisheye_rectified_image_keeps_the_centre_resolution_and_has_no_empty_border(tmp_path):
    rig, _ = load_camchain(_camchain(tmp_path / "camchain.yaml"))
    assert rig.calibration.fx == pytest.approx(K0[0, 0], rel=0.01)
    left, _ = rig.rectify(np.full((H, W), 200, np.uint8), np.full((H, W), 200, np.uint8))
    assert (left == 0).mean() < 0.01  # the output does not reach outside the raw image


def test_radtan_camchain_goes_through_the_pinhole_model(tmp_path):
    rig, _ = load_camchain(_camchain(tmp_path / "camchain.yaml", lens="radtan"))
    assert rig.lens == "radtan"
    assert rig.calibration.baseline == pytest.approx(np.linalg.norm(T_C1_C0[:3, 3]), rel=1e-6)
    np.testing.assert_allclose(rig.calibration.D_left, D0)  # raw model carried, as for EuRoC


def test_rig_with_the_cameras_swapped_is_refused():
    R, T = T_C1_C0[:3, :3], T_C1_C0[:3, 3]
    with pytest.raises(CalibrationError, match="right camera is to the LEFT"):
        rectify_pair("equidistant", K1, D1, K0, D0, (W, H), R.T, -R.T @ T)  # cam1 given as the left camera


@pytest.mark.parametrize("kwargs, message", [
    (dict(drop="intrinsics"), "cam0 has no intrinsics"),
    (dict(model="omni"), "camera_model 'omni' is not supported"),
    (dict(lens="fov"), "distortion_model 'fov' is not supported"),
])
def test_bad_camchain_names_the_key(tmp_path, kwargs, message):
    with pytest.raises(DatasetLayoutError, match=message):
        read_camchain(_camchain(tmp_path / "camchain.yaml", **kwargs))


def test_missing_camchain_names_the_file(tmp_path):
    with pytest.raises(DatasetLayoutError, match="camchain.yaml not found"):
        read_camchain(tmp_path / "camchain.yaml")


T_CAM_IMU = make_transform(np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]), [0.047, -0.047, -0.068])


def _tumvi_folder(root, rig_rotation_left, stamps, speed):
    """A TUM-VI-like EuRoC-format folder: fisheye cam0/cam1 images and mocap0 (the IMU's pose), no sensor.yaml."""
    _, raw_left, raw_right = render_rig()
    for cam, img in (("cam0", raw_left), ("cam1", raw_right)):
        (root / "mav0" / cam / "data").mkdir(parents=True)
        rows = ["#timestamp [ns],filename"]
        for t in stamps:
            cv2.imwrite(str(root / "mav0" / cam / "data" / f"{t}.png"), img)
            rows.append(f"{t},{t}.png")
        (root / "mav0" / cam / "data.csv").write_text("\n".join(rows) + "\n")
    # The rectified left camera moves along its optical axis at `speed`: T_R_rect(t) = Tz(speed·t).
    T_imu_rect = invert(T_CAM_IMU) @ make_transform(np.asarray(rig_rotation_left).T)
    rows = ["#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"]
    for t in range(stamps[0], stamps[-1] + 1, 5_000_000):
        T_R_S = make_transform(np.eye(3), [0, 0, speed * (t - stamps[0]) * 1e-9]) @ invert(T_imu_rect)
        x, y, z, w = quat_from_matrix(T_R_S[:3, :3])
        rows.append(",".join(str(v) for v in (t, *T_R_S[:3, 3], w, x, y, z)))
    (root / "mav0" / "mocap0").mkdir()
    (root / "mav0" / "mocap0" / "data.csv").write_text("\n".join(rows) + "\n")


def test_euroc_folder_with_a_fisheye_camchain(tmp_path, capsys):
    camchain = _camchain(tmp_path / "camchain.yaml")
    text = camchain.read_text().replace(_rows(np.eye(4)), _rows(T_CAM_IMU), 1)  # cam0's T_cam_imu
    camchain.write_text(text)
    rig, _ = load_camchain(camchain)
    stamps = [1520530308199447626 + k * 50_000_000 for k in range(3)]
    _tumvi_folder(tmp_path / "room1", rig.rotation_left, stamps, speed=1.5)
    out = tmp_path / "room1.mcap"
    assert importer.main(["euroc", str(tmp_path / "room1"), "--camchain", str(camchain), "--out", str(out)]) == 0, \
        capsys.readouterr().err
    reader = RecordingReader(out)
    msgs = {}
    for m in reader.messages():
        msgs.setdefault(m.key, []).append(decode(m.payload))
    calib = calibration_from_msg(decode(reader.calibration_payload(), StereoCalibrationMsg))
    assert calib.fx == pytest.approx(K0[0, 0], rel=0.01) and calib.baseline == pytest.approx(BASELINE, rel=0.01)
    frames = msgs["rig/stereo/frame"]
    assert [f.header.stamp_ns for f in frames] == stamps
    left, right = frame_images(frames[0])
    rows_l, rows_r = np.sort(_centroids(left)[:, 1]), np.sort(_centroids(right)[:, 1])
    assert len(rows_l) == len(rows_r) == 49 and np.abs(rows_l - rows_r).max() < 0.5
    poses = np.array([transform_of(p) for p in msgs["rig/truth/pose"]])
    assert len(poses) == 21  # 200 Hz over the 0.1 s of frames
    np.testing.assert_allclose(poses[-1][:3, 3], [1.5 * 0.1, 0, 0], atol=1e-6)  # base_link forward = map +x
    np.testing.assert_allclose(poses[-1][:3, :3], np.eye(3), atol=1e-6)


def test_euroc_camchain_without_imu_extrinsics_skips_the_truth(tmp_path):
    camchain = _camchain(tmp_path / "camchain.yaml")
    camchain.write_text(camchain.read_text().replace("  T_cam_imu:\n" + _rows(np.eye(4)) + "\n", ""))
    rig, _ = load_camchain(camchain)
    _tumvi_folder(tmp_path / "room1", rig.rotation_left, [10**18, 10**18 + 50_000_000], speed=1.0)
    ds = load_euroc(tmp_path / "room1", camchain=camchain)
    assert len(ds.truth_poses) == 0 and any("no T_cam_imu" in n for n in ds.notes)
