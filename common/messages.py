"""The wire schemas of flyslam: every message type on the bus and in recordings, and their helpers.

Each schema is a dataclass registered with :func:`common.codec.schema`; top-level messages carry an
envelope (``header``: seq, stamp_ns, frame_id).  Minor, backward-compatible additions (a new optional
field) keep the major version; readers ignore unknown fields.  A breaking change bumps ``MAJOR``.

The codec's names are re-exported, so ``from common import messages as m`` gives ``m.encode``,
``m.decode``, ``m.header`` and the ``m.DecodeError`` family alongside the schemas.
"""
from __future__ import annotations

from dataclasses import field
from typing import Optional

import numpy as np

from common.codec import (  # noqa: F401  (re-exported: the codec's public names)
    ALLOWED_DTYPES, ENVELOPE_KEYS, MAX_ARRAY_BYTES, MAX_ARRAY_NDIM, MAX_COUNT, MAX_FLY_RANGE_M, MAX_LIST_LEN,
    MAX_PAYLOAD_BYTES, MAX_STAMP_NS, MAX_WORLD_M, SCHEMAS, Array, DecodeError, Envelope, InvalidValue,
    MalformedPayload, Message, MissingField, ShapeMismatch, TooLarge, UnknownSchema, UnsupportedVersion,
    WrongType, _header_field, array_field, check_finite, check_positive, check_range, decode, encode,
    encode_side, header, peek_envelope, peek_schema, required, schema)

# ------------------------------------------------------------------------------------- schemas
# Frame names (REP-105 tree): map -> odom -> base_link -> camera_left -> camera_left_optical, ...

MAP, ODOM, BASE_LINK = "map", "odom", "base_link"
CAMERA_LEFT_OPTICAL = "camera_left_optical"

IMAGE_SHAPES = ((None, None), (None, None, 3))
FRAME_ENCODINGS = {"rgb8": 3, "mono8": 2, "jpeg": 1, "png": 1}   # encoding -> ndim (as common.images)
MAX_RANGE_M = 1e4        # sonar limits, beyond any transducer
MAX_SPEED = 1e3          # |m/s| and |rad/s| of a command, beyond any robot


def _check_quaternion(where: str, q) -> None:
    check_finite(where, q)
    if not 0.5 < float(np.dot(q, q)) < 2.0:
        raise InvalidValue(f"{where} is not a unit quaternion (norm² {float(np.dot(q, q)):.3g})")


def _check_covariance(where: str, cov) -> None:
    check_finite(where, cov, MAX_WORLD_M ** 2)
    if np.any(np.diag(cov) < 0):
        raise InvalidValue(f"{where} has a negative variance")


@schema("StereoFrame")
class StereoFrame(Message):
    """A rectified stereo pair. ``encoding``: 'rgb8' or 'mono8' (raw arrays), or 'jpeg'/'png' (the
    images are then 1-D uint8 arrays holding the compressed bytes; see common.images)."""
    left: np.ndarray = array_field("uint8", shapes=IMAGE_SHAPES + ((None,),))
    right: np.ndarray = array_field("uint8", shapes=IMAGE_SHAPES + ((None,),))
    encoding: str = "rgb8"
    header: Envelope = _header_field()

    def validate(self) -> None:
        ndim = FRAME_ENCODINGS.get(self.encoding)
        if ndim is None:
            raise InvalidValue(f"unknown encoding {self.encoding!r} (expected {', '.join(FRAME_ENCODINGS)})")
        for side, img in (("left", self.left), ("right", self.right)):
            if img.ndim != ndim:
                raise InvalidValue(f"{side}: a {self.encoding} image must have {ndim} dimensions, got {img.shape}")
            if img.size == 0:
                raise InvalidValue(f"{side} image is empty {img.shape}")
        if ndim > 1 and self.left.shape != self.right.shape:
            raise InvalidValue(f"left {self.left.shape} and right {self.right.shape} images differ in size")


@schema("CameraInfo")
class CameraInfo:
    """One camera of a stereo pair, OpenCV conventions: K intrinsics, D distortion (raw camera),
    R rectifying rotation, P 3×4 projection in the rectified frame."""
    K: np.ndarray = array_field("float64", (3, 3))
    D: np.ndarray = array_field("float64", (None,))
    R: np.ndarray = array_field("float64", (3, 3))
    P: np.ndarray = array_field("float64", (3, 4))

    def validate(self) -> None:
        for name in ("K", "D", "R", "P"):
            check_finite(name, getattr(self, name))
        for name, m in (("K", self.K), ("P", self.P)):
            if not (m[0, 0] > 0 and m[1, 1] > 0):
                raise InvalidValue(f"{name}: focal lengths ({m[0, 0]}, {m[1, 1]}) must be > 0")


@schema("StereoCalibration")
class StereoCalibrationMsg(Message):
    """Calibration of a rectified stereo rig; published latched (sources re-publish it periodically and
    answer queries) so that late joiners get it."""
    width: int = 0
    height: int = 0
    left: CameraInfo = required()
    right: CameraInfo = required()
    baseline_m: float = 0.0
    T_base_camera: np.ndarray = array_field("float64", (4, 4))  # left optical frame in base_link
    header: Envelope = _header_field()

    def validate(self) -> None:
        check_range("width", self.width, 1, 1 << 16)
        check_range("height", self.height, 1, 1 << 16)
        check_positive("baseline_m", self.baseline_m)
        check_finite("T_base_camera", self.T_base_camera, MAX_WORLD_M)


@schema("WheelOdometry")
class WheelOdometry(Message):
    """Raw differential-drive odometry: wheel speeds (rad/s, left/right) and/or encoder ticks, plus the
    source's own integrated planar pose (x, y, yaw in odom) and its 3×3 covariance when it has one."""
    wheel_speeds: Optional[np.ndarray] = array_field("float64", (2,), optional=True)
    ticks: Optional[np.ndarray] = array_field("int64", (2,), optional=True)
    ticks_per_rev: float = 0.0
    wheel_radius_m: float = 0.0
    track_width_m: float = 0.0
    pose_xyyaw: Optional[np.ndarray] = array_field("float64", (3,), optional=True)
    covariance: Optional[np.ndarray] = array_field("float64", (3, 3), optional=True)
    header: Envelope = _header_field()

    def validate(self) -> None:
        for name in ("ticks_per_rev", "wheel_radius_m", "track_width_m"):
            check_range(name, getattr(self, name), 0.0, MAX_WORLD_M)
        # A non-finite wheel speed is let through: the odometry model flags it and republishes the held
        # pose (fusion/odom says 'flagged'), so it cannot reach the fused state.
        if self.wheel_speeds is not None and np.any(np.abs(self.wheel_speeds) > MAX_WORLD_M):
            raise InvalidValue(f"wheel_speeds beyond ±{MAX_WORLD_M:g}")
        if self.pose_xyyaw is not None:
            check_finite("pose_xyyaw", self.pose_xyyaw, MAX_WORLD_M)
        if self.covariance is not None:
            _check_covariance("covariance", self.covariance)


@schema("SonarScan")
class SonarScan(Message):
    """One reading of a sonar ring: per transducer its planar pose in the frame named by frame_id
    (x, y, yaw), the range (NaN = no echo), and the ring's beam width and range limits."""
    transducer_poses: np.ndarray = array_field("float64", (None, 3))
    ranges: np.ndarray = array_field(("float32", "float64"), (None,))
    beam_width_rad: float = 0.0
    min_range_m: float = 0.0
    max_range_m: float = 0.0
    header: Envelope = _header_field()

    def validate(self) -> None:
        if len(self.ranges) != len(self.transducer_poses):
            raise InvalidValue(f"{len(self.transducer_poses)} transducer poses but {len(self.ranges)} ranges")
        check_finite("transducer_poses", self.transducer_poses, MAX_WORLD_M)
        echoes = self.ranges[~np.isnan(self.ranges)]
        if not np.all((echoes >= 0) & (echoes <= MAX_RANGE_M)):
            raise InvalidValue(f"ranges must be NaN (no echo) or in [0, {MAX_RANGE_M:g}] m")
        for name in ("beam_width_rad", "min_range_m", "max_range_m"):
            check_range(name, getattr(self, name), 0.0, MAX_RANGE_M)


@schema("FlyPopulation")
class FlyPopulation(Message):
    """The evolver's current answer: fly positions (N×3, in frame_id, normally camera_left_optical),
    fitness, generation count and the seq of the stereo frame they were last evaluated on.
    ``T_odom_camera`` is the camera pose in odom at that frame, when odometry was available; ``image``
    the grey left image of that frame (the flies' neighbourhoods, for photometric tracking), sent with
    a frame's first publication on ``flies/population/@image`` only (the localiser's stream), as a side
    field (beside the payload: live subscribers get it, recordings do not keep it — the frame itself is
    recorded)."""
    positions: np.ndarray = array_field("float32", (None, 3))
    fitness: np.ndarray = array_field("float32", (None,))
    generation: int = 0
    source_seq: int = 0
    T_odom_camera: Optional[np.ndarray] = array_field("float64", (4, 4), optional=True)
    image: Optional[np.ndarray] = array_field("uint8", (None, None), optional=True, side=True)
    header: Envelope = _header_field()

    def validate(self) -> None:
        if len(self.fitness) != len(self.positions):
            raise InvalidValue(f"{len(self.positions)} positions but {len(self.fitness)} fitness values")
        check_finite("positions", self.positions, MAX_FLY_RANGE_M)
        if np.any(np.isnan(self.fitness)) or np.any(np.isposinf(self.fitness)):
            raise InvalidValue("fitness must be finite or -inf (outside the images)")
        check_range("generation", self.generation, 0, MAX_COUNT)
        check_range("source_seq", self.source_seq, 0, MAX_COUNT)
        if self.T_odom_camera is not None:
            check_finite("T_odom_camera", self.T_odom_camera, MAX_WORLD_M)
        if self.image is not None and self.image.size == 0:
            raise InvalidValue(f"image is empty {self.image.shape}")


@schema("PoseEstimate")
class PoseEstimate(Message):
    """Pose of child_frame_id in frame_id (REP-105: e.g. base_link in map) with a 6×6 covariance over
    (x, y, z, roll, pitch, yaw). ``status``: 'ok', or why not ('rejected: ...', 'odometry only', ...)."""
    child_frame_id: str = BASE_LINK
    position: np.ndarray = array_field("float64", (3,))
    orientation: np.ndarray = array_field("float64", (4,))  # quaternion xyzw
    covariance: np.ndarray = array_field("float64", (6, 6))
    status: str = "ok"
    source_seq: int = 0
    header: Envelope = _header_field()

    def validate(self) -> None:
        check_finite("position", self.position, MAX_WORLD_M)
        _check_quaternion("orientation", self.orientation)
        _check_covariance("covariance", self.covariance)
        check_range("source_seq", self.source_seq, 0, MAX_COUNT)


@schema("Transform")
class TransformMsg(Message):
    """A transform frame_id → child_frame_id (e.g. map → odom)."""
    child_frame_id: str = ""
    translation: np.ndarray = array_field("float64", (3,))
    rotation: np.ndarray = array_field("float64", (4,))  # quaternion xyzw
    header: Envelope = _header_field()

    def validate(self) -> None:
        check_finite("translation", self.translation, MAX_WORLD_M)
        _check_quaternion("rotation", self.rotation)


@schema("Keyframe")
class Keyframe:
    """One keyframe of the fly map: its camera pose in the map frame and its population (camera frame)."""
    id: int = 0
    stamp_ns: int = 0
    position: np.ndarray = array_field("float64", (3,))
    orientation: np.ndarray = array_field("float64", (4,))
    points: np.ndarray = array_field("float32", (None, 3))
    fitness: np.ndarray = array_field("float32", (None,))
    # the grey left image at half resolution, in a saved map only (photometric loops); not on the bus
    image: Optional[np.ndarray] = array_field("uint8", (None, None), optional=True)

    def validate(self) -> None:
        check_range("stamp_ns", self.stamp_ns, 0, MAX_STAMP_NS)
        check_finite("position", self.position, MAX_WORLD_M)
        _check_quaternion("orientation", self.orientation)
        if len(self.fitness) != len(self.points):
            raise InvalidValue(f"{len(self.points)} points but {len(self.fitness)} fitness values")
        if self.image is not None and self.image.size == 0:
            raise InvalidValue(f"keyframe image is empty {self.image.shape}")
        check_finite("points", self.points, MAX_FLY_RANGE_M)
        if np.any(np.isnan(self.fitness)) or np.any(np.isposinf(self.fitness)):
            raise InvalidValue("fitness must be finite or -inf")


@schema("FlyMap")
class FlyMap(Message):
    """The localiser's map: keyframe fly populations (frame_id = map)."""
    keyframes: list[Keyframe] = field(default_factory=list)
    header: Envelope = _header_field()


@schema("VelocityCommand")
class VelocityCommand(Message):
    """Differential-drive command in base_link: forward speed (m/s), turn rate (rad/s). ``stop`` with a
    ``reason`` when the planner halts ('target reached', 'no path', ...)."""
    linear_mps: float = required(0.0)
    angular_radps: float = required(0.0)
    stop: bool = False
    reason: str = ""
    header: Envelope = _header_field()

    def validate(self) -> None:
        check_range("linear_mps", self.linear_mps, -MAX_SPEED, MAX_SPEED)
        check_range("angular_radps", self.angular_radps, -MAX_SPEED, MAX_SPEED)


@schema("Target")
class Target(Message):
    """A navigation goal in frame_id (normally map)."""
    x: float = required(0.0)
    y: float = required(0.0)
    radius_m: float = 0.3
    header: Envelope = _header_field()

    def validate(self) -> None:
        check_range("x", self.x, -MAX_WORLD_M, MAX_WORLD_M)
        check_range("y", self.y, -MAX_WORLD_M, MAX_WORLD_M)
        check_range("radius_m", self.radius_m, 0.0, MAX_WORLD_M)


@schema("HarmonicField")
class HarmonicField(Message):
    """The planner's harmonic potential on a grid in the map frame, with the current descent path."""
    values: np.ndarray = array_field(("float32", "float64"), (None, None))
    origin_xy: np.ndarray = array_field("float64", (2,))
    resolution_m: float = 0.05
    path_xy: Optional[np.ndarray] = array_field("float64", (None, 2), optional=True)
    header: Envelope = _header_field()

    def validate(self) -> None:
        check_finite("origin_xy", self.origin_xy, MAX_WORLD_M)
        check_positive("resolution_m", self.resolution_m)
        if self.path_xy is not None:
            check_finite("path_xy", self.path_xy, MAX_WORLD_M)


@schema("Heartbeat")
class Heartbeat(Message):
    """Periodic liveness and health of a service. ``progress`` grows while the service does useful
    work (frames handled, generations...), so a stuck-but-alive process is visible."""
    service: str = ""
    pid: int = 0
    state: str = "running"
    progress: int = 0
    rates: dict = field(default_factory=dict)      # name -> per-second rate
    counters: dict = field(default_factory=dict)   # name -> count (dropped, rejected, ...)
    header: Envelope = _header_field()

    def validate(self) -> None:
        check_range("pid", self.pid, 0, 1 << 31)
        check_range("progress", self.progress, 0, MAX_COUNT)
        for name, table in (("rates", self.rates), ("counters", self.counters)):
            for key, value in table.items():
                if not isinstance(value, (int, float)) or isinstance(value, bool):
                    raise InvalidValue(f"{name}[{key!r}] = {value!r} is not a number")
                check_range(f"{name}[{key!r}]", value, -MAX_COUNT if name == "rates" else 0, MAX_COUNT)


@schema("EvolverTrace")
class EvolverTrace(Message):
    """Where one frame's time went in the evolver (``--trace``; bench/pipeline.py's latency breakdown):
    the evolver process's monotonic clock (ns) when the frame was taken from its channel, decoded, ready
    (images set, flies re-scored) and its population published; the settle's generations; the mean
    fitness the settle waited to recover (``reference``, None for the first frame) and reached
    (``quality``).  ``header.seq`` is the frame's seq."""
    take_ns: int = 0
    decoded_ns: int = 0
    ready_ns: int = 0
    published_ns: int = 0
    generations: int = 0
    reference: Optional[float] = None
    quality: float = 0.0
    header: Envelope = _header_field()

    def validate(self) -> None:
        for name in ("take_ns", "decoded_ns", "ready_ns", "published_ns"):
            check_range(name, getattr(self, name), 0, MAX_STAMP_NS)
        check_range("generations", self.generations, 0, MAX_COUNT)


@schema("DepthImage")
class DepthImage(Message):
    """Ground-truth depth (metres, Z in the left optical frame; inf = nothing) from a simulator."""
    depth: np.ndarray = array_field("float32", (None, None))
    header: Envelope = _header_field()

    def validate(self) -> None:
        if self.depth.size == 0:
            raise InvalidValue(f"depth image is empty {self.depth.shape}")
        if np.any(np.isnan(self.depth)) or np.any(self.depth < 0):
            raise InvalidValue("depth must be >= 0 or inf (nothing)")


# ----------------------------------------------------------------------------- calibration glue


def calibration_to_msg(calib, seq: int = 0, stamp_ns: int = 0) -> StereoCalibrationMsg:
    """common.camera.StereoCalibration → wire message."""
    return StereoCalibrationMsg(
        width=int(calib.width), height=int(calib.height),
        left=CameraInfo(K=np.asarray(calib.K_left, float), D=np.asarray(calib.D_left, float).ravel(),
                        R=np.asarray(calib.R_left, float), P=calib.P_left),
        right=CameraInfo(K=np.asarray(calib.K_right, float), D=np.asarray(calib.D_right, float).ravel(),
                         R=np.asarray(calib.R_right, float), P=calib.P_right),
        baseline_m=float(calib.baseline), T_base_camera=np.asarray(calib.T_base_camera, float),
        header=header(seq, stamp_ns, CAMERA_LEFT_OPTICAL))


def calibration_from_msg(msg: StereoCalibrationMsg):
    """Wire message → common.camera.StereoCalibration (raises CalibrationError when inconsistent)."""
    from common.camera import StereoCalibration
    Pl, Pr = msg.left.P, msg.right.P
    return StereoCalibration(
        width=msg.width, height=msg.height, fx=float(Pl[0, 0]), fy=float(Pl[1, 1]),
        cx_left=float(Pl[0, 2]), cx_right=float(Pr[0, 2]), cy=float(Pl[1, 2]), baseline=msg.baseline_m,
        K_left=msg.left.K.copy(), D_left=msg.left.D.copy(), R_left=msg.left.R.copy(),
        K_right=msg.right.K.copy(), D_right=msg.right.D.copy(), R_right=msg.right.R.copy(),
        T_base_camera=msg.T_base_camera.copy())


def pose_msg(T, covariance=None, seq=0, stamp_ns=0, frame_id=MAP, child=BASE_LINK, status="ok",
             source_seq=0) -> PoseEstimate:
    """PoseEstimate from a 4×4 transform."""
    from common.geometry import pose_from_transform
    p, q = pose_from_transform(np.asarray(T, float))
    cov = np.zeros((6, 6)) if covariance is None else np.asarray(covariance, float)
    return PoseEstimate(child_frame_id=child, position=p, orientation=q, covariance=cov, status=status,
                        source_seq=int(source_seq), header=header(seq, stamp_ns, frame_id))


def transform_of(msg) -> np.ndarray:
    """4×4 transform of a PoseEstimate or TransformMsg."""
    from common.geometry import transform_from_pose
    if isinstance(msg, PoseEstimate):
        return transform_from_pose(msg.position, msg.orientation)
    return transform_from_pose(msg.translation, msg.rotation)
