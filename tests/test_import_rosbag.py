"""`flyslam import rosbag` on ROS 1 and ROS 2 bags written here with rosbags' own writers.

The images are the first frames of the real KITTI clip (synthetic texture when the shared data is
absent), published with CameraInfo topics carrying KITTI's P0/P1, and the KITTI poses as ground truth;
what comes out must match what `flyslam import kitti` makes of the same frames.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from common.geometry import invert, make_transform, quat_from_matrix
from common.images import frame_images
from common.importers.base import C_BODY_OPTICAL, DatasetLayoutError, map_poses_from_camera
from common.importers.rosbag import load_rosbag, pair_by_stamp
from common.messages import StereoCalibrationMsg, calibration_from_msg, decode, transform_of
from common.recording import RecordingReader
from common.trajectory import read_kitti
from deploy.commands import importer
from tests.conftest import SHARED_DATA
from tests import test_import_kalibr as fisheye

KITTI = SHARED_DATA / "kitti-00-frames-0-99"
N = 5
T0 = 1_700_000_000_123_456_789
PERIOD = 100_000_000
JITTER = [0, 1_200_000, -800_000, 300_000, 2_000_000]  # right header stamp − left, ns (< 5 ms)


def _clip():
    """(left images, right images, P0, P1, T_w_cam poses) of N frames."""
    seq = KITTI / "sequences" / "00"
    if seq.is_dir():
        rows = {l.split(":")[0]: np.array(l.split(":")[1].split(), float)
                for l in (seq / "calib.txt").read_text().splitlines() if ":" in l}
        read = lambda cam, i: cv2.imread(str(seq / cam / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)  # noqa: E731
        return ([read("image_0", i) for i in range(N)], [read("image_1", i) for i in range(N)],
                rows["P0"].reshape(3, 4), rows["P1"].reshape(3, 4), read_kitti(KITTI / "poses" / "00.txt")[:N])
    rng = np.random.default_rng(0)
    imgs = [cv2.GaussianBlur(rng.integers(0, 256, (120, 320), dtype=np.uint8), (0, 0), 1.0) for _ in range(2 * N)]
    P0 = np.array([[300.0, 0, 160, 0], [0, 300, 60, 0], [0, 0, 1, 0]])
    P1 = P0.copy()
    P1[0, 3] = -300.0 * 0.5
    poses = [make_transform(np.eye(3), [0.02 * i, 0, 0.9 * i]) for i in range(N)]
    return list(imgs[:N]), list(imgs[N:]), P0, P1, np.array(poses)


CLIP = _clip()


class Bag:
    """A ROS 1 or ROS 2 bag being written: typed message construction and serialisation."""

    def __init__(self, path: Path, ros: int, storage: str = "sqlite3"):
        self.ros = ros
        self.ts = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
        if ros == 1:
            from rosbags.rosbag1 import Writer
            self.writer = Writer(path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer
            self.writer = Writer(path, version=9, storage_plugin=StoragePlugin[storage.upper()])
        self.conns = {}

    def __enter__(self):
        self.writer.open()
        return self

    def __exit__(self, *exc):
        self.writer.close()

    def t(self, name):
        return self.ts.types[name]

    def header(self, stamp_ns: int, frame: str = "camera"):
        Time, Header = self.t("builtin_interfaces/msg/Time"), self.t("std_msgs/msg/Header")
        stamp = Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
        return Header(seq=0, stamp=stamp, frame_id=frame) if self.ros == 1 else Header(stamp=stamp, frame_id=frame)

    def write(self, topic: str, msgtype: str, msg, log_ns: int):
        if topic not in self.conns:
            self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts)
        raw = self.ts.serialize_ros1(msg, msgtype) if self.ros == 1 else self.ts.serialize_cdr(msg, msgtype)
        self.writer.write(self.conns[topic], log_ns, raw)

    def image(self, topic, img: np.ndarray, stamp_ns, encoding="mono8", compressed=False, log_ns=None):
        log_ns = stamp_ns + 5_000_000 if log_ns is None else log_ns
        if compressed:
            ok, data = cv2.imencode(".png", img)
            msg = self.t("sensor_msgs/msg/CompressedImage")(header=self.header(stamp_ns), format="png",
                                                           data=data.ravel())
            self.write(topic, "sensor_msgs/msg/CompressedImage", msg, log_ns)
            return
        h, w = img.shape[:2]
        data = np.ascontiguousarray(img).view(np.uint8).ravel()
        msg = self.t("sensor_msgs/msg/Image")(header=self.header(stamp_ns), height=h, width=w, encoding=encoding,
                                              is_bigendian=0, step=data.size // h, data=data)
        self.write(topic, "sensor_msgs/msg/Image", msg, log_ns)

    def camera_info(self, topic, P: np.ndarray, size, stamp_ns, K=None, D=(), R=None, model="plumb_bob"):
        RegionOfInterest = self.t("sensor_msgs/msg/RegionOfInterest")
        roi = RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        fields = dict(K=np.asarray(P[:, :3] if K is None else K, float).ravel(), D=np.asarray(D, float),
                      R=np.eye(3).ravel() if R is None else np.asarray(R, float).ravel(),
                      P=np.asarray(P, float).ravel())
        if self.ros == 2:
            fields = {k.lower(): v for k, v in fields.items()}
        msg = self.t("sensor_msgs/msg/CameraInfo")(header=self.header(stamp_ns), height=size[1], width=size[0],
                                                   distortion_model=model, binning_x=0, binning_y=0, roi=roi,
                                                   **fields)
        self.write(topic, "sensor_msgs/msg/CameraInfo", msg, stamp_ns)

    def pose(self, topic, msgtype, T: np.ndarray, stamp_ns):
        g = lambda n: self.t(f"geometry_msgs/msg/{n}")  # noqa: E731
        q = quat_from_matrix(T[:3, :3])
        position, orientation = g("Point")(x=T[0, 3], y=T[1, 3], z=T[2, 3]), g("Quaternion")(x=q[0], y=q[1], z=q[2], w=q[3])
        pose = g("Pose")(position=position, orientation=orientation)
        if msgtype == "geometry_msgs/msg/PoseStamped":
            msg = g("PoseStamped")(header=self.header(stamp_ns, "world"), pose=pose)
        else:
            cov = g("PoseWithCovariance")(pose=pose, covariance=np.zeros(36))
            zero = g("Vector3")(x=0.0, y=0.0, z=0.0)
            twist = g("TwistWithCovariance")(twist=g("Twist")(linear=zero, angular=zero), covariance=np.zeros(36))
            msg = self.t("nav_msgs/msg/Odometry")(header=self.header(stamp_ns, "world"), child_frame_id="base_link",
                                                  pose=cov, twist=twist)
        self.write(topic, msgtype, msg, stamp_ns)


def _write_clip(path: Path, ros: int, compressed=False, camera_info=True, truth=None, jitter=JITTER,
                storage="sqlite3"):
    """N KITTI frames on /kitti/left|right/image_raw (+ camera_info), truth on /truth in the given style."""
    lefts, rights, P0, P1, poses = CLIP
    size = lefts[0].shape[::-1]
    with Bag(path, ros, storage) as bag:
        for i in range(N):
            stamp = T0 + i * PERIOD
            if camera_info:
                bag.camera_info("/kitti/left/camera_info", P0, size, stamp)
                bag.camera_info("/kitti/right/camera_info", P1, size, stamp)
            bag.image("/kitti/left/image_raw", lefts[i], stamp, compressed=compressed)
            bag.image("/kitti/right/image_raw", rights[i], stamp + jitter[i], compressed=compressed)
            if truth == "optical":
                bag.pose("/truth", "geometry_msgs/msg/PoseStamped", poses[i], stamp)
            elif truth == "body":  # the same motion, as a REP-103 body frame at the camera
                bag.pose("/truth", "nav_msgs/msg/Odometry", C_BODY_OPTICAL @ poses[i] @ invert(C_BODY_OPTICAL), stamp)
        bag.image("/kitti/right/image_raw", rights[-1], T0 + N * PERIOD + 40_000_000, compressed=compressed)  # skipped
    return path


def _read(out: Path):
    reader = RecordingReader(out)
    msgs = {}
    for m in reader.messages():
        msgs.setdefault(m.key, []).append(decode(m.payload))
    return msgs, calibration_from_msg(decode(reader.calibration_payload(), StereoCalibrationMsg))


def _expected_truth():
    poses = CLIP[4]
    return map_poses_from_camera(poses, reference=poses[0])


@pytest.mark.parametrize("ros, storage, compressed, truth", [(2, "sqlite3", False, "optical"),
                                                             (2, "mcap", True, "body"), (1, None, True, "body")])
def test_bag_import_matches_the_kitti_clip(tmp_path, capsys, ros, storage, compressed, truth):
    bag = _write_clip(tmp_path / ("clip.bag" if ros == 1 else "clip"), ros, compressed=compressed, truth=truth,
                      storage=storage)
    if storage == "mcap":  # a user may point at the storage file inside the bag folder
        bag = next(bag.glob("*.mcap"))
    out = tmp_path / "clip.mcap"
    argv = ["rosbag", str(bag), "--left", "/kitti/left/image_raw", "--right", "/kitti/right/image_raw",
            "--truth", "/truth", "--truth-frame", truth, "--out", str(out)]
    assert importer.main(argv) == 0, capsys.readouterr().err
    text = capsys.readouterr().out
    assert f"frames     {N} over 0.40 s" in text and f"truth      {N} poses" in text
    assert "1 images without a partner" in text

    msgs, calib = _read(out)
    P0, P1 = CLIP[2], CLIP[3]
    assert calib.fx == pytest.approx(P0[0, 0]) and calib.cx_left == pytest.approx(P0[0, 2])
    assert calib.baseline == pytest.approx((P0[0, 3] - P1[0, 3]) / P0[0, 0])
    frames = msgs["rig/stereo/frame"]
    assert [f.header.stamp_ns for f in frames] == [T0 + i * PERIOD for i in range(N)]  # the left header stamps
    for i, f in enumerate(frames):  # already-rectified CameraInfo (D = 0, R = I, K = P): pixels untouched
        left, right = frame_images(f)
        np.testing.assert_array_equal(left, CLIP[0][i])
        np.testing.assert_array_equal(right, CLIP[1][i])
    got = np.array([transform_of(m) for m in msgs["rig/truth/pose"]])
    np.testing.assert_allclose(got, _expected_truth(), atol=1e-6)
    if KITTI.is_dir():  # the car drives forward: base_link along map +x
        assert got[-1, 0, 3] > 3.0 and abs(got[-1, 1, 3]) < 0.5


def test_distorted_camera_info_is_rectified_with_its_own_R_and_P(tmp_path):
    """A raw camera with plumb_bob distortion: frames come out through K, D, R, P (as image_proc does)."""
    lefts, rights, P0, P1, _ = CLIP
    size = lefts[0].shape[::-1]
    K = P0[:, :3].copy()
    D = [-0.05, 0.01, 0.0, 0.0, 0.0]
    path = tmp_path / "raw"
    with Bag(path, 2) as bag:
        for i in range(2):
            bag.camera_info("/cam/left/camera_info", P0, size, T0, K=K, D=D)
            bag.camera_info("/cam/right/camera_info", P1, size, T0, K=K, D=D)
            bag.image("/cam/left/image_raw", lefts[i], T0 + i * PERIOD)
            bag.image("/cam/right/image_raw", rights[i], T0 + i * PERIOD)
    ds = load_rosbag(path, "/cam/left/image_raw", "/cam/right/image_raw")
    left, _ = ds.load_pair(0)
    m1, m2 = cv2.initUndistortRectifyMap(K, np.array(D), np.eye(3), P0, size, cv2.CV_16SC2)
    np.testing.assert_array_equal(left, cv2.remap(lefts[0], m1, m2, cv2.INTER_LINEAR))
    assert not np.array_equal(left, lefts[0])
    np.testing.assert_allclose(ds.calibration.D_left, D)


def test_mono16_images_keep_one_scale(tmp_path):
    rng = np.random.default_rng(1)
    imgs = rng.integers(0, 4096, (4, 40, 60)).astype(np.uint16)  # 12-bit data
    imgs[0, 0, 0] = 4095
    P0 = np.array([[100.0, 0, 30, 0], [0, 100, 20, 0], [0, 0, 1, 0]])
    P1 = P0.copy()
    P1[0, 3] = -10.0
    path = tmp_path / "m16"
    with Bag(path, 2) as bag:
        bag.camera_info("/a/camera_info", P0, (60, 40), T0)
        bag.camera_info("/b/camera_info", P1, (60, 40), T0)
        for i in range(2):
            bag.image("/a/image", imgs[2 * i], T0 + i * PERIOD, encoding="mono16")
            bag.image("/b/image", imgs[2 * i + 1], T0 + i * PERIOD, encoding="mono16")
    ds = load_rosbag(path, "/a/image", "/b/image")
    assert ds.calibration.baseline == pytest.approx(0.1)
    for i in range(2):
        left, right = ds.load_pair(i)
        np.testing.assert_array_equal(left, (imgs[2 * i] >> 4).astype(np.uint8))
        np.testing.assert_array_equal(right, (imgs[2 * i + 1] >> 4).astype(np.uint8))
    assert any(">> 4" in n for n in ds.notes)


def test_fisheye_bag_with_a_kalibr_camchain(tmp_path):
    """TUM-VI style: raw fisheye images, no camera_info, topics and calibration from camchain.yaml."""
    X0, raw_left, raw_right = fisheye.render_rig()
    camchain = fisheye._camchain(tmp_path / "camchain.yaml")
    path = tmp_path / "room.bag"
    with Bag(path, 1) as bag:
        for i in range(3):
            bag.image("/cam0/image_raw", raw_left, T0 + i * PERIOD)
            bag.image("/cam1/image_raw", raw_right, T0 + i * PERIOD)
    out = tmp_path / "room.mcap"
    assert importer.main(["rosbag", str(path), "--camchain", str(camchain), "--out", str(out)]) == 0
    msgs, calib = _read(out)
    assert len(msgs["rig/stereo/frame"]) == 3
    assert calib.fx == pytest.approx(fisheye.K0[0, 0], rel=0.01)
    assert calib.baseline == pytest.approx(fisheye.BASELINE, rel=0.01)
    left, right = frame_images(msgs["rig/stereo/frame"][0])
    # Rectified: a blob's row is the same in both images (coarse check; the sub-pixel one is in test_import_kalibr).
    rows_l = np.sort(fisheye._centroids(left)[:, 1])
    rows_r = np.sort(fisheye._centroids(right)[:, 1])
    assert len(rows_l) == len(rows_r) and np.abs(rows_l - rows_r).max() < 0.5


def test_equidistant_camera_info_goes_through_the_fisheye_model(tmp_path):
    """A ROS driver's fisheye CameraInfo (distortion_model equidistant, R and P from a stereo calibration)."""
    X0, raw_left, raw_right = fisheye.render_rig()
    size = (fisheye.W, fisheye.H)
    R, T = fisheye.T_C1_C0[:3, :3].copy(), fisheye.T_C1_C0[:3, 3].reshape(3, 1).copy()
    R1, R2, _, P2cv, _ = cv2.fisheye.stereoRectify(fisheye.K0, fisheye.D0.reshape(4, 1), fisheye.K1,
                                                   fisheye.D1.reshape(4, 1), size, R, T,
                                                   flags=cv2.CALIB_ZERO_DISPARITY, newImageSize=size)
    f, c = 190.0, (fisheye.W - 1) / 2
    P1 = np.array([[f, 0, c, 0], [0, f, c, 0], [0, 0, 1, 0]])
    P2 = P1.copy()
    P2[0, 3] = f * P2cv[0, 3] / P2cv[0, 0]
    path = tmp_path / "t265"
    with Bag(path, 2) as bag:
        bag.camera_info("/t265/fisheye1/camera_info", P1, size, T0, K=fisheye.K0, D=fisheye.D0, R=R1, model="equidistant")
        bag.camera_info("/t265/fisheye2/camera_info", P2, size, T0, K=fisheye.K1, D=fisheye.D1, R=R2, model="equidistant")
        bag.image("/t265/fisheye1/image_raw", raw_left, T0)
        bag.image("/t265/fisheye2/image_raw", raw_right, T0)
    ds = load_rosbag(path, "/t265/fisheye1/image_raw", "/t265/fisheye2/image_raw")
    assert ds.calibration.fx == f and ds.calibration.baseline == pytest.approx(np.linalg.norm(T), rel=1e-6)
    np.testing.assert_array_equal(ds.calibration.D_left, 0)  # describes the rectified images (see kalibr)
    left, right = ds.load_pair(0)
    u_l, u_r, v = ds.calibration.project(X0 @ R1.T)  # where the rectified model puts the points
    found_l = fisheye._nearest(fisheye._centroids(left), np.stack([u_l, v], 1))
    found_r = fisheye._nearest(fisheye._centroids(right), np.stack([u_r, v], 1))
    assert np.isfinite(found_l).all() and np.isfinite(found_r).all()
    assert np.abs(found_l[:, 1] - found_r[:, 1]).max() < 0.5
    assert np.abs(found_l - np.stack([u_l, v], 1)).max() < 0.5


def test_colour_and_bayer_images_come_out_rgb(tmp_path):
    h, w = 48, 64
    yy, xx = np.mgrid[0:h, 0:w]
    rgb = np.stack([100 + 50 * np.sin(xx / 9), 120 + 40 * np.cos(yy / 7), 80 + 60 * np.sin((xx + yy) / 11)],
                   -1).astype(np.uint8)
    mosaic = {"bayer_rggb8": "rggb", "bayer_gbrg8": "gbrg"}
    P0 = np.array([[60.0, 0, 32, 0], [0, 60, 24, 0], [0, 0, 1, 0]])
    P1 = P0.copy()
    P1[0, 3] = -6.0
    path = tmp_path / "colour"
    with Bag(path, 2) as bag:
        bag.camera_info("/l/camera_info", P0, (w, h), T0)
        bag.camera_info("/r/camera_info", P1, (w, h), T0)
        for i, enc in enumerate(("rgb8", "bgr8", "bayer_rggb8", "bayer_gbrg8")):
            if enc in mosaic:  # the sensor's colour filter pattern, from the top-left 2×2 cell
                img = np.zeros((h, w), np.uint8)
                for (dy, dx), c in zip(((0, 0), (0, 1), (1, 0), (1, 1)), mosaic[enc]):
                    img[dy::2, dx::2] = rgb[dy::2, dx::2, "rgb".index(c)]
            else:
                img = rgb if enc == "rgb8" else rgb[..., ::-1]
            bag.image("/l/image", img, T0 + i * PERIOD, encoding=enc)
            bag.image("/r/image", img, T0 + i * PERIOD, encoding=enc)
    ds = load_rosbag(path, "/l/image", "/r/image")
    for i in range(4):
        left, _ = ds.load_pair(i)
        assert left.shape == (h, w, 3)
        error = np.abs(left.astype(int) - rgb)[4:-4, 4:-4].mean()  # demosaicing blurs the border
        assert error < (0.5 if i < 2 else 2.0), f"frame {i}: mean error {error:.1f}"


def test_zero_header_stamps_fall_back_to_the_receive_time(tmp_path):
    lefts, rights, P0, P1, _ = CLIP
    path = tmp_path / "unstamped"
    with Bag(path, 2) as bag:
        bag.camera_info("/l/camera_info", P0, lefts[0].shape[::-1], T0)
        bag.camera_info("/r/camera_info", P1, lefts[0].shape[::-1], T0)
        for i in range(2):
            bag.image("/l/image", lefts[i], 0, log_ns=T0 + i * PERIOD)
            bag.image("/r/image", rights[i], 0, log_ns=T0 + i * PERIOD + 1_000_000)
    ds = load_rosbag(path, "/l/image", "/r/image")
    assert ds.stamps_ns.tolist() == [T0, T0 + PERIOD]
    assert any("2 /l/image images have a zero header stamp" in n for n in ds.notes)


def test_pairing_takes_the_nearest_partner_once():
    li, ri = pair_by_stamp(np.array([0, 100, 200, 300]), np.array([2, 98, 104, 260, 299]), tolerance_ns=5)
    assert li.tolist() == [0, 1, 3] and ri.tolist() == [0, 1, 4]  # 100↔98 (not 104), 200 has none within 5
    li, ri = pair_by_stamp(np.array([100, 101]), np.array([100]), tolerance_ns=5)
    assert li.tolist() == [0] and ri.tolist() == [0]  # one right image serves one pair


@pytest.mark.parametrize("argv_extra, kwargs, message", [
    (["--left", "/nope/image_raw"], {}, "has no topic /nope/image_raw"),
    ([], dict(camera_info=False), "has no topic /kitti/left/camera_info"),
    ([], dict(jitter=[20_000_000] * N), "no /kitti/left/image_raw image has a /kitti/right/image_raw image within 5 ms"),
    (["--truth", "/kitti/left/image_raw"], {}, "/kitti/left/image_raw is sensor_msgs/msg/Image, expected"),
])
def test_bad_bag_gives_one_line_naming_the_topic(tmp_path, capsys, argv_extra, kwargs, message):
    bag = _write_clip(tmp_path / "clip", 2, **kwargs)
    argv = ["rosbag", str(bag), "--left", "/kitti/left/image_raw", "--right", "/kitti/right/image_raw",
            "--out", str(tmp_path / "x.mcap")]
    assert importer.main(argv + argv_extra) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "x.mcap").exists()


def test_missing_bag_names_the_path(tmp_path):
    with pytest.raises(DatasetLayoutError, match="nothing.bag not found"):
        load_rosbag(tmp_path / "nothing.bag", "/a", "/b")


def test_empty_camera_info_topic_and_one_topic_twice_are_refused(tmp_path):
    lefts, rights, P0, P1, _ = CLIP
    path = tmp_path / "noinfo"
    with Bag(path, 2) as bag:
        bag.writer.add_connection("/l/camera_info", "sensor_msgs/msg/CameraInfo", typestore=bag.ts)  # no messages
        bag.camera_info("/r/camera_info", P1, lefts[0].shape[::-1], T0)
        bag.image("/l/image", lefts[0], T0)
        bag.image("/r/image", rights[0], T0)
    with pytest.raises(DatasetLayoutError, match="/l/camera_info has no messages"):
        load_rosbag(path, "/l/image", "/r/image")
    with pytest.raises(DatasetLayoutError, match="left and right image topics are both /l/image"):
        load_rosbag(path, "/l/image", "/l/image")
