"""ROS 1 (``.bag``) and ROS 2 (folder with ``metadata.yaml``, sqlite3 or MCAP storage) bags → a
:class:`~common.importers.base.StereoDataset`, read with the pure-Python ``rosbags`` package.

Images: ``sensor_msgs/Image`` (mono8, mono16, rgb8, bgr8, rgba8, bgra8, bayer_*8 demosaiced to RGB) or
``sensor_msgs/CompressedImage`` (JPEG/PNG) on a left and a right topic. Each left image is paired with the right image nearest in
header stamp, within ``sync_tolerance_ms``; each right image serves at most one pair; the frame's
stamp is the left image's header stamp (the bag's receive time when the header stamp is zero).
16-bit images become 8-bit by one right shift for the whole import, chosen from the first image's
maximum, so left and right (and every frame) keep one brightness scale.

Calibration, in order of precedence:

- a Kalibr ``camchain.yaml`` (:mod:`common.importers.kalibr`: fisheye or radtan, rectified on import);
  its ``rostopic`` entries name the image topics when ``left``/``right`` are not given;
- the first ``sensor_msgs/CameraInfo`` on each camera's info topic (default: the image topic's sibling
  ``camera_info``). As ROS's image_proc does, K and D describe the raw image and R, P the rectification
  (``plumb_bob``/``rational_polynomial`` through OpenCV's pinhole model, ``equidistant`` through its
  fisheye model); the baseline is ``(P_left[0,3] − P_right[0,3]) / fx``. Images on ``image_rect``
  topics (or with ``rectified=True``) are taken as already rectified and only P is used.

Ground truth (optional): ``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped``,
``TransformStamped`` or ``nav_msgs/Odometry``, the pose of a frame B in a world frame. ``truth_frame``
says what B is: ``body`` (default) a REP-103 body frame at the cameras, taken as base_link;
``optical`` the raw left camera's optical frame; ``imu`` the IMU of a camchain with ``T_cam_imu``.
The map is B's pose nearest the first frame; poses from the first to the last frame are kept.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from common.camera import CalibrationError, StereoCalibration
from common.geometry import invert, make_transform
from common.importers.base import DatasetLayoutError, StereoDataset, T_BASE_CAMERA, map_poses_from_camera, require
from common.importers.euroc import poses_from_wxyz
from common.importers.kalibr import RectifiedRig, lens_maps, load_camchain, read_camchain
from common.stereo_rectify import StereoRectifier

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TRUTH_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped",
               "geometry_msgs/msg/TransformStamped", "nav_msgs/msg/Odometry")
TRUTH_FRAMES = ("body", "optical", "imu")
DEFAULT_SYNC_TOLERANCE_MS = 5.0
_CHANNELS = {"mono8": 1, "8uc1": 1, "rgb8": 3, "bgr8": 3, "8uc3": 3, "rgba8": 4, "bgra8": 4, "8uc4": 4,
             "mono16": 1, "16uc1": 1, "bayer_rggb8": 1, "bayer_bggr8": 1, "bayer_gbrg8": 1, "bayer_grbg8": 1}
# ROS names a Bayer mosaic by its first row pair, OpenCV by its second (as cv_bridge maps them).
_BAYER = {"bayer_rggb8": cv2.COLOR_BayerBG2RGB, "bayer_bggr8": cv2.COLOR_BayerRG2RGB,
          "bayer_gbrg8": cv2.COLOR_BayerGR2RGB, "bayer_grbg8": cv2.COLOR_BayerGB2RGB}
PINHOLE_MODELS = ("plumb_bob", "rational_polynomial", "radtan", "")


def _stamp_ns(msg) -> int:
    t = msg.header.stamp
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def info_topic(image_topic: str) -> str:
    """ROS convention: ``/ns/image_raw`` (or any image topic) → ``/ns/camera_info``."""
    return image_topic.rsplit("/", 1)[0] + "/camera_info" if "/" in image_topic.strip("/") else "/camera_info"


class ImageDecoder:
    """sensor_msgs Image / CompressedImage → uint8 mono (H×W) or RGB (H×W×3); one 16→8-bit shift per import."""

    def __init__(self, notes: list[str]):
        self.shift: int | None = None
        self.notes = notes

    def _to8(self, img: np.ndarray) -> np.ndarray:
        if img.dtype == np.uint8:
            return img
        if self.shift is None:
            self.shift = max(int(img.max()).bit_length() - 8, 0)
            self.notes.append(f"16-bit images scaled to 8 bits by >> {self.shift} (from the first image's maximum)")
        return np.clip(img >> self.shift, 0, 255).astype(np.uint8)

    def decode(self, msg, msgtype: str, topic: str) -> np.ndarray:
        data = np.asarray(msg.data, np.uint8)
        if msgtype == COMPRESSED:
            img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
            if img is None:
                raise DatasetLayoutError(f"ROS bag: {topic}: cannot decode a {msg.format!r} compressed image")
            img = self._to8(img)
            if img.ndim == 3:
                img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)
            return img
        enc = msg.encoding.lower()
        if enc not in _CHANNELS:
            raise DatasetLayoutError(f"ROS bag: {topic}: image encoding {msg.encoding!r} is not supported "
                                     "(mono8, mono16, rgb8, bgr8, rgba8, bgra8, bayer_*8)")
        h, w, c, step = int(msg.height), int(msg.width), _CHANNELS[enc], int(msg.step)
        wide = enc in ("mono16", "16uc1")
        if data.size < h * step or step < w * c * (2 if wide else 1):
            raise DatasetLayoutError(f"ROS bag: {topic}: a {w}×{h} {msg.encoding} image holds {data.size} bytes "
                                     f"(step {step})")
        rows = data[: h * step].reshape(h, step)
        if wide:
            img = rows[:, : 2 * w].copy().view(">u2" if msg.is_bigendian else "<u2").astype(np.uint16)
            return self._to8(img)
        img = rows[:, : w * c].reshape(h, w, c) if c > 1 else rows[:, :w]
        if enc in _BAYER:
            return cv2.cvtColor(np.ascontiguousarray(img), _BAYER[enc])
        if enc in ("bgr8", "8uc3"):
            return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        if c == 4:
            return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if enc.startswith("bgra") else cv2.COLOR_RGBA2RGB)
        return np.ascontiguousarray(img)


def pair_by_stamp(left: np.ndarray, right: np.ndarray, tolerance_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices (into ``left``, into ``right``) of pairs: each left stamp with the nearest right stamp within
    ``tolerance_ns``, each right used once (by its nearest left), ordered by left stamp."""
    left, right = np.asarray(left, np.int64), np.asarray(right, np.int64)
    if not len(left) or not len(right):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    order = np.argsort(right, kind="stable")
    rs = right[order]
    j = np.clip(np.searchsorted(rs, left), 1, len(rs) - 1) if len(rs) > 1 else np.zeros(len(left), np.int64)
    before = np.maximum(j - 1, 0)
    pick = np.where(np.abs(rs[before] - left) <= np.abs(rs[j] - left), before, j)
    dt = np.abs(rs[pick] - left)
    li = np.nonzero(dt <= tolerance_ns)[0]
    ri = pick[li]
    # One left per right image: the nearest (ties → the earlier left).
    by_quality = np.lexsort((li, dt[li], ri))
    _, first = np.unique(ri[by_quality], return_index=True)
    keep = np.sort(li[by_quality][first])
    ri = pick[keep]
    keep_order = np.argsort(left[keep], kind="stable")
    return keep[keep_order], order[ri[keep_order]]


@dataclass
class _Topic:
    name: str
    msgtype: str
    connections: list
    stamps: list
    unstamped: int = 0  # messages with a zero header stamp (the receive time stands in)


class _PairCursor:
    """Serves the image messages of the pairs in order with one sequential pass over the bag (rosbags'
    readers are not random-access: ROS 1 chunks are compressed), stashing only wanted messages."""

    def __init__(self, path: Path, typestore, left: _Topic, right: _Topic, li: np.ndarray, ri: np.ndarray):
        self.path, self.typestore, self.topics = path, typestore, (left, right)
        self.wanted = ({int(i): k for k, i in enumerate(li)}, {int(i): k for k, i in enumerate(ri)})
        self.stash: dict[tuple[int, int], tuple[object, str]] = {}
        self.reader = self.messages = None
        self.sides: dict[tuple[int, int], int] = {}
        self.counts = [0, 0]

    def _open(self):
        from rosbags.highlevel import AnyReader
        self.reader = AnyReader([self.path], default_typestore=self.typestore)
        self.reader.open()
        names = [t.name for t in self.topics]
        conns = [c for c in self.reader.connections if c.topic in names]
        self.sides = {(c.id, id(c.owner)): names.index(c.topic) for c in conns}
        self.counts = [0, 0]
        self.messages = self.reader.messages(connections=conns)

    def close(self):
        if self.reader is not None:
            self.reader.close()
        self.reader = self.messages = None

    def get(self, k: int):
        """The (left, right) deserialised messages (with their types) of pair k."""
        from rosbags.highlevel import AnyReaderError
        try:
            return self._get(k)
        except AnyReaderError as e:
            self.close()
            raise DatasetLayoutError(f"ROS bag: {self.path}: {e}") from None

    def _get(self, k: int):
        if self.reader is None:
            self._open()
        while (0, k) not in self.stash or (1, k) not in self.stash:
            item = next(self.messages, None)
            if item is None:
                self.close()
                raise DatasetLayoutError(f"ROS bag: {self.path}: pair {k} not found on a second read (bag changed?)")
            conn, _t, raw = item
            side = self.sides[conn.id, id(conn.owner)]
            index = self.counts[side]
            self.counts[side] += 1
            pair = self.wanted[side].get(index)
            if pair is not None:
                self.stash[side, pair] = (self.reader.deserialize(raw, conn.msgtype), conn.msgtype)
        return self.stash.pop((0, k)), self.stash.pop((1, k))


def _info_arrays(msg) -> dict:
    """CameraInfo fields as arrays, for ROS 1 (D, K, R, P) and ROS 2 (d, k, r, p) naming alike."""
    def get(name: str) -> np.ndarray:
        return np.asarray(getattr(msg, name.lower()) if hasattr(msg, name.lower()) else getattr(msg, name), np.float64)

    return dict(K=get("K").reshape(3, 3), D=get("D").ravel(), R=get("R").reshape(3, 3), P=get("P").reshape(3, 4),
                size=(int(msg.width), int(msg.height)), model=str(msg.distortion_model).lower(),
                binning=(int(msg.binning_x), int(msg.binning_y)))


ROSBAG_REMEDIES = {"swap": "swap --left and --right", "pair": "use --camchain"}


def calibration_from_camera_info(left: dict, right: dict, left_topic: str, right_topic: str, rectified: bool,
                                 source: str = "ROS bag", remedies: dict[str, str] = ROSBAG_REMEDIES
                                 ) -> tuple[StereoCalibration, object, np.ndarray, str]:
    """(calibration, rectify(left, right) callable, raw-to-rectified rotation of the left camera, how the
    images are treated, in words).  ``source`` begins every error message (the topics, or files, follow);
    ``remedies`` says what to do about a swapped ("swap") or an unpaired ("pair") rig in the caller's terms."""
    for info, topic in ((left, left_topic), (right, right_topic)):
        if not np.any(info["P"]):
            raise DatasetLayoutError(f"{source}: {topic}: CameraInfo has no projection P (camera not calibrated)")
        if max(info["binning"]) > 1:
            raise DatasetLayoutError(f"{source}: {topic}: binned images (binning {info['binning']}) are not supported")
        if not rectified and info["model"] not in PINHOLE_MODELS + ("equidistant",):
            raise DatasetLayoutError(f"{source}: {topic}: distortion model {info['model']!r} is not supported "
                                     "(plumb_bob, rational_polynomial, equidistant)")
        if not np.any(info["R"]):
            info["R"] = np.eye(3)
        P, K, R = info["P"], info["K"], info["R"]
        if not (P[0, 0] > 0 and P[1, 1] > 0):
            raise DatasetLayoutError(f"{source}: {topic}: the projection P has no positive focal length "
                                     f"(fx {P[0, 0]:g}, fy {P[1, 1]:g})")
        if not rectified and not (K[0, 0] > 0 and K[1, 1] > 0):
            raise DatasetLayoutError(f"{source}: {topic}: the camera matrix K has no positive focal length "
                                     f"(fx {K[0, 0]:g}, fy {K[1, 1]:g})")
        if not rectified and not (np.allclose(R @ R.T, np.eye(3), atol=1e-4) and np.linalg.det(R) > 0):
            raise DatasetLayoutError(f"{source}: {topic}: the rectification matrix R is not a rotation")
        if not rectified and info["model"] == "equidistant" and np.size(info["D"]) != 4:
            raise DatasetLayoutError(f"{source}: {topic}: an equidistant lens has 4 coefficients k1..k4, "
                                     f"got {np.size(info['D'])}")
    Pl, Pr = left["P"], right["P"]
    if left["size"] != right["size"]:
        raise DatasetLayoutError(f"{source}: {left_topic} is {left['size']} but {right_topic} is {right['size']}")
    if not np.allclose([Pl[0, 0], Pl[1, 1], Pl[1, 2]], [Pr[0, 0], Pr[1, 1], Pr[1, 2]], rtol=1e-6, atol=1e-6):
        raise DatasetLayoutError(f"{source}: {left_topic} and {right_topic}: the CameraInfo projections P differ in "
                                 f"fx, fy or cy, so they are not a rectified stereo pair ({remedies['pair']})")
    fx = Pl[0, 0]
    baseline = (Pl[0, 3] - Pr[0, 3]) / fx
    if baseline == 0:
        raise DatasetLayoutError(f"{source}: {right_topic}: CameraInfo P has no baseline (P[0,3] = 0): the cameras "
                                 f"were not calibrated as a stereo pair ({remedies['pair']})")
    if baseline < 0:
        raise DatasetLayoutError(f"{source}: {right_topic} is to the LEFT of {left_topic} (baseline {baseline:.3f} m "
                                 f"from P); {remedies['swap']}")
    fisheye = not rectified and left["model"] == "equidistant"
    keep_raw = not rectified and not fisheye
    raw = lambda info, name, default: info[name] if keep_raw else default  # noqa: E731
    try:
        calib = StereoCalibration(
            width=left["size"][0], height=left["size"][1], fx=float(fx), fy=float(Pl[1, 1]),
            cx_left=float(Pl[0, 2]), cx_right=float(Pr[0, 2]), cy=float(Pl[1, 2]), baseline=float(baseline),
            K_left=raw(left, "K", Pl[:, :3].copy()), D_left=_opencv_distortion(raw(left, "D", np.zeros(5)), f"{source}: {left_topic}"),
            R_left=raw(left, "R", np.eye(3)), K_right=raw(right, "K", Pr[:, :3].copy()),
            D_right=_opencv_distortion(raw(right, "D", np.zeros(5)), f"{source}: {right_topic}"), R_right=raw(right, "R", np.eye(3)),
            T_base_camera=T_BASE_CAMERA.copy())
    except CalibrationError as e:
        raise DatasetLayoutError(f"{source}: {left_topic} and {right_topic} CameraInfo: {e}") from None
    if fisheye:
        maps = tuple(lens_maps("equidistant", i["K"], i["D"], i["R"], i["P"], i["size"]) for i in (left, right))
        rig = RectifiedRig(calib, maps, left["R"], left["size"], "equidistant")
        return calib, rig.rectify, left["R"], "equidistant lenses, rectified on import"
    rectifier = StereoRectifier(calib)
    how = ("images already rectified: P only" if rectified else
           "D = 0, R = I, K = P: images used as they are" if rectifier.passthrough else "rectified on import")
    return calib, rectifier.rectify, (left["R"] if keep_raw else np.eye(3)), how


def _opencv_distortion(D: np.ndarray, where: str) -> np.ndarray:
    D = np.asarray(D, np.float64).ravel()
    if D.size == 0 or not np.any(D):
        return np.zeros(5)
    if D.size not in (4, 5, 8, 12, 14):
        raise DatasetLayoutError(f"{where}: CameraInfo D has {D.size} coefficients (4, 5, 8, 12 or 14)")
    return D


def _truth_poses(msgs: list, msgtype: str) -> np.ndarray:
    """(N, 4, 4) poses T_world_B from PoseStamped / PoseWithCovarianceStamped / TransformStamped / Odometry."""
    if msgtype == "geometry_msgs/msg/TransformStamped":
        parts = [(m.transform.translation, m.transform.rotation) for m in msgs]
    else:
        poses = [m.pose if msgtype == "geometry_msgs/msg/PoseStamped" else m.pose.pose for m in msgs]
        parts = [(p.position, p.orientation) for p in poses]
    pos = np.array([[t.x, t.y, t.z] for t, _ in parts], np.float64).reshape(-1, 3)
    q_wxyz = np.array([[q.w, q.x, q.y, q.z] for _, q in parts], np.float64).reshape(-1, 4)
    if len(q_wxyz) and not np.all(np.linalg.norm(q_wxyz, axis=1) > 0.5):
        raise DatasetLayoutError("ROS bag: ground-truth orientations include a zero quaternion")
    return poses_from_wxyz(pos, q_wxyz)


def _bag_path(path: Path) -> Path:
    """A ROS 1 .bag file or a ROS 2 bag folder; a ROS 2 storage file inside its folder → the folder."""
    require(path, "ROS bag")
    if path.is_file() and path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
        return path.parent
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        raise DatasetLayoutError(f"ROS bag: {path} is a folder without metadata.yaml (not a ROS 2 bag)")
    if path.is_file() and path.suffix != ".bag":
        raise DatasetLayoutError(f"ROS bag: {path} is neither a ROS 1 .bag file nor a ROS 2 bag folder")
    return path


def truth_in_map(stamps_ns: np.ndarray, T_world_b: np.ndarray, frame_stamps: np.ndarray, truth_frame: str,
                 rotation_left: np.ndarray, T_cam_imu: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Truth poses of frame B (``truth_frame``: see the module doc) → (stamps, T_map_base) over the frames."""
    order = np.argsort(stamps_ns, kind="stable")
    ts, T_w_b = np.asarray(stamps_ns, np.int64)[order], np.asarray(T_world_b, np.float64)[order]
    keep = (ts >= frame_stamps[0]) & (ts <= frame_stamps[-1])
    if not keep.any():
        return np.zeros(0, np.int64), np.zeros((0, 4, 4))
    ref = int(np.argmin(np.abs(ts - frame_stamps[0])))
    if truth_frame == "body":
        poses = invert(T_w_b[ref]) @ T_w_b
    else:
        T_w_cam = T_w_b if truth_frame == "optical" else T_w_b @ invert(T_cam_imu)
        T_w_rect = T_w_cam @ make_transform(np.asarray(rotation_left, float).T)
        poses = map_poses_from_camera(T_w_rect, reference=T_w_rect[ref])
    return ts[keep], poses[keep]


def _scan(path: Path, typestore, images: tuple[str, str], infos: tuple[str, ...], truth: str | None):
    """One pass over the bag: header stamps of the image (and truth) topics, truth messages, the first
    CameraInfo of each info topic. Returns (left _Topic, right _Topic, {info topic: msg}, truth _Topic, msgs)."""
    from rosbags.highlevel import AnyReader, AnyReaderError

    try:
        reader = AnyReader([path], default_typestore=typestore)
        reader.open()
    except (AnyReaderError, FileNotFoundError, OSError, ValueError) as e:
        raise DatasetLayoutError(f"ROS bag: {path}: {str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
    try:
        topics = reader.topics

        def topic(name: str, types: tuple[str, ...], what: str) -> _Topic:
            info = topics.get(name)
            if info is None:
                listed = sorted(t for t, i in topics.items() if i.msgtype in types)
                raise DatasetLayoutError(f"ROS bag: {path} has no topic {name} ({what}; "
                                         f"{'topics of that type: ' + ', '.join(listed) if listed else 'none of that type'})")
            if info.msgtype not in types:
                raise DatasetLayoutError(f"ROS bag: {name} is {info.msgtype}, expected {' or '.join(types)}")
            return _Topic(name, info.msgtype, list(info.connections), [])

        cams = [topic(name, (IMAGE, COMPRESSED), f"{side} images") for name, side in zip(images, ("left", "right"))]
        info_topics = [topic(name, (CAMERA_INFO,), f"{side} camera_info; or give --camchain")
                       for name, side in zip(infos, ("left", "right"))]
        truth_topic = topic(truth, TRUTH_TYPES, "ground truth") if truth else None
        wanted = cams + info_topics + ([truth_topic] if truth_topic else [])
        by_conn = {(c.id, id(c.owner)): t for t in wanted for c in t.connections}
        first_info: dict[str, object] = {}
        truth_msgs = []
        for conn, log_time, raw in reader.messages(connections=[c for t in wanted for c in t.connections]):
            t = by_conn[conn.id, id(conn.owner)]
            if t in info_topics:
                if t.name not in first_info:
                    first_info[t.name] = reader.deserialize(raw, conn.msgtype)
                continue
            msg = reader.deserialize(raw, conn.msgtype)
            stamp = _stamp_ns(msg)
            t.stamps.append(stamp or log_time)
            t.unstamped += not stamp
            if t is truth_topic:
                truth_msgs.append(msg)
    except AnyReaderError as e:
        raise DatasetLayoutError(f"ROS bag: {path}: {e}") from None
    finally:
        reader.close()
    for t in cams + info_topics:
        if not t.stamps and t.name not in first_info:
            raise DatasetLayoutError(f"ROS bag: {t.name} has no messages")
    return cams[0], cams[1], first_info, truth_topic, truth_msgs


def load_rosbag(path, left: str | None = None, right: str | None = None, left_info: str | None = None,
                right_info: str | None = None, camchain=None, truth: str | None = None, truth_frame: str = "body",
                sync_tolerance_ms: float = DEFAULT_SYNC_TOLERANCE_MS, rectified: bool = False,
                max_frames: int | None = None) -> StereoDataset:
    """A stereo sequence from a ROS 1 or ROS 2 bag (see the module doc for topics, calibration and truth)."""
    from rosbags.typesys import Stores, get_typestore

    path = _bag_path(Path(path))
    ros1 = path.suffix == ".bag"
    typestore = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if truth_frame not in TRUTH_FRAMES:
        raise DatasetLayoutError(f"ROS bag: truth frame {truth_frame!r} is not one of {', '.join(TRUTH_FRAMES)}")
    if not np.isfinite(sync_tolerance_ms) or sync_tolerance_ms < 0:
        raise DatasetLayoutError(f"ROS bag: the sync tolerance must be ≥ 0 ms, got {sync_tolerance_ms}")
    notes: list[str] = []
    rig = cams = None
    left_cam = "cam0"
    if camchain is not None:
        by_topic = {c.rostopic: name for name, c in read_camchain(camchain).items() if c.rostopic}
        left_cam, right_cam = by_topic.get(left, "cam0"), by_topic.get(right, "cam1")
        rig, cams = load_camchain(camchain, left_cam, right_cam)
        left, right = left or cams[left_cam].rostopic, right or cams[right_cam].rostopic
    if not left or not right:
        raise DatasetLayoutError("ROS bag: say which image topics to read (--left TOPIC --right TOPIC)")
    if left == right:
        raise DatasetLayoutError(f"ROS bag: the left and right image topics are both {left}")
    if truth_frame == "imu" and (cams is None or cams[left_cam].T_cam_imu is None):
        raise DatasetLayoutError("ROS bag: --truth-frame imu needs a camchain with T_cam_imu for the left camera")
    left_info, right_info = left_info or info_topic(left), right_info or info_topic(right)
    cam_l, cam_r, first_info, truth_topic, truth_msgs = _scan(
        path, typestore, (left, right), () if rig is not None else (left_info, right_info), truth)
    for t in (cam_l, cam_r):
        if t.unstamped:
            notes.append(f"{t.unstamped} {t.name} images have a zero header stamp: the bag's receive time is used")

    if rig is not None:
        calib, rectify, rotation_left = rig.calibration, rig.rectify, rig.rotation_left
        notes.append(f"calibration from {camchain} ({rig.lens} lenses, rectified on import)")
    else:
        rectified = rectified or ("image_rect" in left and "image_rect" in right)
        calib, rectify, rotation_left, how = calibration_from_camera_info(
            _info_arrays(first_info[left_info]), _info_arrays(first_info[right_info]), left_info, right_info, rectified)
        notes.append(f"calibration from {left_info} and {right_info} ({how})")

    stamps_l, stamps_r = np.array(cam_l.stamps, np.int64), np.array(cam_r.stamps, np.int64)
    li, ri = pair_by_stamp(stamps_l, stamps_r, int(round(sync_tolerance_ms * 1e6)))
    if not len(li):
        raise DatasetLayoutError(f"ROS bag: no {left} image has a {right} image within {sync_tolerance_ms:g} ms "
                                 "(raise --sync-tolerance-ms)")
    _, unique = np.unique(stamps_l[li], return_index=True)  # repeated left stamps: keep the first
    li, ri = li[np.sort(unique)], ri[np.sort(unique)]
    unpaired = len(stamps_l) + len(stamps_r) - 2 * len(li)
    skew = np.abs(stamps_l[li] - stamps_r[ri])
    notes.append(f"{len(li)} pairs, left-right stamp skew max {skew.max() / 1e6:.3f} ms"
                 + (f"; {unpaired} images without a partner within {sync_tolerance_ms:g} ms skipped" if unpaired else ""))
    n = len(li) if max_frames is None else min(len(li), int(max_frames))
    li, ri = li[:n], ri[:n]
    stamps = stamps_l[li]

    decoder = ImageDecoder(notes)
    cursor = _PairCursor(path, typestore, cam_l, cam_r, li, ri)

    def load_pair(i: int):
        (ml, tl), (mr, tr) = cursor.get(i)
        if i == n - 1:
            cursor.close()
        try:
            return rectify(decoder.decode(ml, tl, left), decoder.decode(mr, tr, right))
        except CalibrationError as e:
            raise DatasetLayoutError(f"ROS bag: {left}/{right} frame {i}: {e}") from None

    truth_stamps, truth_poses = np.zeros(0, np.int64), np.zeros((0, 4, 4))
    if truth_topic is not None:
        T_cam_imu = cams[left_cam].T_cam_imu if cams is not None else None
        truth_stamps, truth_poses = truth_in_map(np.array(truth_topic.stamps, np.int64),
                                                 _truth_poses(truth_msgs, truth_topic.msgtype), stamps, truth_frame,
                                                 rotation_left, T_cam_imu)
        notes.append(f"ground truth from {truth} ({truth_topic.msgtype.split('/')[-1]}, {truth_frame} frame)"
                     if len(truth_stamps) else f"ground truth on {truth} does not cover the imported frames")
    else:
        notes.append("no ground truth (give --truth TOPIC)")
    kind = "ROS 1" if ros1 else "ROS 2"
    return StereoDataset(f"{kind} bag {path.name} ({n} of {len(stamps_l)} {left} images paired)", calib, stamps,
                         load_pair, truth_stamps, truth_poses, notes=notes)
