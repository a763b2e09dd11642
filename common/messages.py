"""Message schemas and their msgpack codec.

Every message on the bus (and in a recording) is a msgpack map: an *envelope* and the schema's fields.

    {"schema": "flyslam.StereoFrame", "major": 1, "seq": 12, "stamp_ns": 1700000000000, "frame_id": "camera_left_optical",
     ...fields...}

numpy arrays travel as ``{"dtype": "uint8", "shape": [480, 640, 3], "data": <bytes>}``: no per-element
encoding, so a 640×480 stereo pair costs one memcpy each way.

Decoding *validates* and raises a subclass of :class:`DecodeError` for anything wrong — truncated bytes,
wrong types, missing fields, unknown schema or major version, shape not matching the data, absurd sizes.
Services catch ``DecodeError``, count it and carry on; nothing malformed ever escapes as another exception.

A schema is a dataclass registered with :func:`schema`. Its fields are typed with the small vocabulary
below (``int``, ``float``, ``str``, ``bool``, ``dict``, ``Array(...)``, a nested schema, ``list[...]`` of a
nested schema, ``Optional``); the codec derives encoding and validation from those types.
Minor, backward-compatible additions (a new optional field) keep the major version; readers ignore
unknown fields.  A breaking change bumps ``MAJOR``.
"""
from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass, field
from typing import Any, ClassVar, Optional

import msgpack
import numpy as np

# ------------------------------------------------------------------------------------------ errors


class DecodeError(ValueError):
    """A payload that is not a valid flyslam message. Subclasses say why."""


class MalformedPayload(DecodeError):
    """Not msgpack, truncated, trailing bytes, or not a map."""


class UnknownSchema(DecodeError):
    """The envelope names a schema this build does not know (or not the one expected)."""


class UnsupportedVersion(DecodeError):
    """The schema's major version differs from this build's."""


class MissingField(DecodeError):
    """A required field (or envelope key) is absent."""


class WrongType(DecodeError):
    """A field holds a value of the wrong type."""


class ShapeMismatch(DecodeError):
    """An array's shape does not match its data length or the schema's constraint."""


class TooLarge(DecodeError):
    """A payload, array or list exceeds the configured sanity limits."""


# Sanity limits: far above any legitimate message, far below what would hurt a 24 GiB machine.
MAX_PAYLOAD_BYTES = 256 * 1024 * 1024
MAX_ARRAY_BYTES = 128 * 1024 * 1024
MAX_ARRAY_NDIM = 4
MAX_LIST_LEN = 100_000

ALLOWED_DTYPES = {"uint8", "uint16", "int16", "int32", "int64", "float32", "float64", "bool"}

# ------------------------------------------------------------------------------- field vocabulary


@dataclass(frozen=True)
class Array:
    """Type marker for a numpy array field. ``shape`` entries of ``None`` match any length.

    ``ndim`` alternatives (e.g. images H×W or H×W×C) are given with ``shapes``.
    """
    dtype: str | tuple[str, ...]
    shape: tuple | None = None
    shapes: tuple[tuple, ...] | None = None

    def dtypes(self) -> tuple[str, ...]:
        return (self.dtype,) if isinstance(self.dtype, str) else self.dtype

    def check(self, arr: np.ndarray, where: str) -> None:
        if arr.dtype.name not in self.dtypes():
            raise WrongType(f"{where}: dtype {arr.dtype.name}, expected {'/'.join(self.dtypes())}")
        options = self.shapes if self.shapes is not None else ((self.shape,) if self.shape else None)
        if options is None:
            return
        for shape in options:
            if len(shape) == arr.ndim and all(s is None or s == n for s, n in zip(shape, arr.shape)):
                return
        raise ShapeMismatch(f"{where}: shape {arr.shape} does not match {options}")


def array_field(dtype, shape=None, shapes=None, optional=False):
    """Declare an array field: ``positions: np.ndarray = array_field("float32", (None, 3))``."""
    meta = {"array": Array(dtype, shape, shapes)}
    if optional:
        return field(default=None, metadata=meta)
    return field(default=None, metadata=meta | {"required": True})


# ----------------------------------------------------------------------------- schema registry

SCHEMAS: dict[str, type] = {}
ENVELOPE_KEYS = ("schema", "major", "seq", "stamp_ns", "frame_id")


def schema(name: str, major: int = 1):
    """Class decorator: make a dataclass a wire schema named ``flyslam.<name>`` at major ``major``."""
    def wrap(cls):
        cls = dataclass(cls)
        cls.SCHEMA = f"flyslam.{name}"
        cls.MAJOR = major
        SCHEMAS[cls.SCHEMA] = cls
        return cls
    return wrap


@dataclass
class Envelope:
    """Per-message header carried by every top-level message."""
    seq: int = 0
    stamp_ns: int = 0
    frame_id: str = ""


class Message:
    """Base of top-level schemas: carries the envelope as ``header``."""
    SCHEMA: ClassVar[str]
    MAJOR: ClassVar[int]


def _is_top_level(cls) -> bool:
    return any(f.name == "header" for f in dataclasses.fields(cls))


# ------------------------------------------------------------------------------------ encoding


def _encode_value(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        arr = np.ascontiguousarray(value)
        return {"dtype": arr.dtype.name, "shape": list(arr.shape), "data": arr.tobytes()}
    if dataclasses.is_dataclass(value):
        return {f.name: _encode_value(getattr(value, f.name)) for f in dataclasses.fields(value)
                if f.name != "header"}
    if isinstance(value, (list, tuple)):
        return [_encode_value(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _encode_value(v) for k, v in value.items()}
    if isinstance(value, np.generic):
        return value.item()
    return value


def encode(msg) -> bytes:
    """Serialise a top-level message (a registered schema instance with a ``header``) to bytes."""
    cls = type(msg)
    if getattr(cls, "SCHEMA", None) not in SCHEMAS:
        raise TypeError(f"{cls.__name__} is not a registered message schema")
    body = _encode_value(msg)
    h = msg.header
    body.update(schema=cls.SCHEMA, major=cls.MAJOR, seq=int(h.seq), stamp_ns=int(h.stamp_ns),
                frame_id=str(h.frame_id))
    return msgpack.packb(body, use_bin_type=True)


# ------------------------------------------------------------------------------------ decoding


def _decode_array(obj: Any, spec: Array, where: str) -> np.ndarray:
    if not isinstance(obj, dict):
        raise WrongType(f"{where}: expected an array map, got {type(obj).__name__}")
    for key in ("dtype", "shape", "data"):
        if key not in obj:
            raise MissingField(f"{where}: array without '{key}'")
    dtype, shape, data = obj["dtype"], obj["shape"], obj["data"]
    if not isinstance(dtype, str) or dtype not in ALLOWED_DTYPES:
        raise WrongType(f"{where}: dtype {dtype!r} is not allowed")
    if not isinstance(shape, list) or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0
                                               for n in shape):
        raise WrongType(f"{where}: shape must be a list of non-negative integers")
    if len(shape) > MAX_ARRAY_NDIM:
        raise TooLarge(f"{where}: {len(shape)} dimensions")
    if not isinstance(data, (bytes, bytearray)):
        raise WrongType(f"{where}: data must be bytes")
    itemsize = np.dtype(dtype).itemsize
    count = math.prod(shape)
    if count * itemsize > MAX_ARRAY_BYTES:
        raise TooLarge(f"{where}: {count * itemsize} bytes exceeds {MAX_ARRAY_BYTES}")
    if count * itemsize != len(data):
        raise ShapeMismatch(f"{where}: shape {shape} × {dtype} needs {count * itemsize} bytes, got {len(data)}")
    arr = np.frombuffer(data, dtype=dtype).reshape(shape)
    spec.check(arr, where)
    return arr


def _unwrap_optional(tp):
    """(inner type, is_optional) for ``Optional[X]`` / ``X | None``."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(tp)) == 2:
            return args[0], True
    return tp, False


def _decode_scalar(value: Any, tp, where: str):
    if tp is bool:
        if not isinstance(value, bool):
            raise WrongType(f"{where}: expected bool, got {type(value).__name__}")
        return value
    if tp is int:
        if not isinstance(value, int) or isinstance(value, bool):
            raise WrongType(f"{where}: expected int, got {type(value).__name__}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise WrongType(f"{where}: expected float, got {type(value).__name__}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise WrongType(f"{where}: expected str, got {type(value).__name__}")
        return value
    if tp is dict or typing.get_origin(tp) is dict:
        if not isinstance(value, dict):
            raise WrongType(f"{where}: expected a map, got {type(value).__name__}")
        return value
    raise TypeError(f"unsupported field type {tp!r} at {where}")  # a bug in a schema, not in a payload


def _decode_struct(obj: Any, cls, where: str):
    if not isinstance(obj, dict):
        raise WrongType(f"{where}: expected a map, got {type(obj).__name__}")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name == "header":
            continue
        fwhere = f"{where}.{f.name}"
        tp, optional = _unwrap_optional(hints[f.name])
        required = f.metadata.get("required", False) or (
            not optional and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING)
        if f.name not in obj or obj[f.name] is None:
            if required:
                raise MissingField(f"{fwhere} is missing")
            continue
        value = obj[f.name]
        if "array" in f.metadata:
            kwargs[f.name] = _decode_array(value, f.metadata["array"], fwhere)
        elif typing.get_origin(tp) is list:
            (item_tp,) = typing.get_args(tp)
            if not isinstance(value, list):
                raise WrongType(f"{fwhere}: expected a list, got {type(value).__name__}")
            if len(value) > MAX_LIST_LEN:
                raise TooLarge(f"{fwhere}: {len(value)} items")
            if dataclasses.is_dataclass(item_tp):
                kwargs[f.name] = [_decode_struct(v, item_tp, f"{fwhere}[{i}]") for i, v in enumerate(value)]
            else:
                kwargs[f.name] = [_decode_scalar(v, item_tp, f"{fwhere}[{i}]") for i, v in enumerate(value)]
        elif dataclasses.is_dataclass(tp):
            kwargs[f.name] = _decode_struct(value, tp, fwhere)
        else:
            kwargs[f.name] = _decode_scalar(value, tp, fwhere)
    return cls(**kwargs)


def peek_schema(payload: bytes) -> tuple[str, int]:
    """(schema, major) of a payload without validating the rest; raises DecodeError."""
    obj = _unpack(payload)
    return _envelope_schema(obj)


def _unpack(payload: bytes) -> dict:
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise MalformedPayload(f"payload must be bytes, got {type(payload).__name__}")
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise TooLarge(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD_BYTES}")
    try:
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=True, max_bin_len=MAX_ARRAY_BYTES,
                              max_str_len=1 << 20, max_array_len=MAX_LIST_LEN, max_map_len=1 << 16)
    except msgpack.ExtraData as e:
        raise MalformedPayload("trailing bytes after the message") from e
    except (ValueError, msgpack.UnpackException, TypeError, RecursionError) as e:
        raise MalformedPayload(f"not a valid msgpack message ({type(e).__name__}: {e})") from e
    if not isinstance(obj, dict):
        raise MalformedPayload(f"top level must be a map, got {type(obj).__name__}")
    return obj


def _envelope_schema(obj: dict) -> tuple[str, int]:
    for key in ENVELOPE_KEYS:
        if key not in obj:
            raise MissingField(f"envelope is missing '{key}'")
    name, major = obj["schema"], obj["major"]
    if not isinstance(name, str):
        raise WrongType("envelope.schema must be a string")
    if not isinstance(major, int) or isinstance(major, bool):
        raise WrongType("envelope.major must be an integer")
    return name, major


def decode(payload: bytes, expected: type | tuple[type, ...] | None = None):
    """Parse and validate a payload. ``expected`` restricts which schema(s) are acceptable."""
    obj = _unpack(payload)
    name, major = _envelope_schema(obj)
    cls = SCHEMAS.get(name)
    if cls is None:
        raise UnknownSchema(f"unknown schema {name!r}")
    if expected is not None:
        allowed = expected if isinstance(expected, tuple) else (expected,)
        if cls not in allowed:
            raise UnknownSchema(f"got {name}, expected {', '.join(c.SCHEMA for c in allowed)}")
    if major != cls.MAJOR:
        raise UnsupportedVersion(f"{name} major version {major}, this build reads {cls.MAJOR}")
    seq, stamp, frame_id = obj["seq"], obj["stamp_ns"], obj["frame_id"]
    if not isinstance(seq, int) or isinstance(seq, bool) or not isinstance(stamp, int) or isinstance(stamp, bool):
        raise WrongType("envelope.seq and envelope.stamp_ns must be integers")
    if not isinstance(frame_id, str):
        raise WrongType("envelope.frame_id must be a string")
    msg = _decode_struct(obj, cls, name)
    msg.header = Envelope(seq=seq, stamp_ns=stamp, frame_id=frame_id)
    return msg


def header(seq: int = 0, stamp_ns: int = 0, frame_id: str = "") -> Envelope:
    return Envelope(int(seq), int(stamp_ns), str(frame_id))


def _header_field():
    return field(default_factory=Envelope)


def required(default=None):
    """A nested-struct field that must be present on the wire."""
    return field(default=default, metadata={"required": True})


# ------------------------------------------------------------------------------------- schemas
# Frame names (REP-105 tree): map -> odom -> base_link -> camera_left -> camera_left_optical, ...

MAP, ODOM, BASE_LINK = "map", "odom", "base_link"
CAMERA_LEFT_OPTICAL = "camera_left_optical"

IMAGE_SHAPES = ((None, None), (None, None, 3))


@schema("StereoFrame")
class StereoFrame(Message):
    """A rectified stereo pair. ``encoding``: 'rgb8' or 'mono8' (raw arrays), or 'jpeg'/'png' (the
    images are then 1-D uint8 arrays holding the compressed bytes; see common.images)."""
    left: np.ndarray = array_field("uint8", shapes=IMAGE_SHAPES + ((None,),))
    right: np.ndarray = array_field("uint8", shapes=IMAGE_SHAPES + ((None,),))
    encoding: str = "rgb8"
    header: Envelope = _header_field()


@schema("CameraInfo")
class CameraInfo:
    """One camera of a stereo pair, OpenCV conventions: K intrinsics, D distortion (raw camera),
    R rectifying rotation, P 3×4 projection in the rectified frame."""
    K: np.ndarray = array_field("float64", (3, 3))
    D: np.ndarray = array_field("float64", (None,))
    R: np.ndarray = array_field("float64", (3, 3))
    P: np.ndarray = array_field("float64", (3, 4))


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


@schema("FlyPopulation")
class FlyPopulation(Message):
    """The evolver's current answer: fly positions (N×3, in frame_id, normally camera_left_optical),
    fitness, generation count and the seq of the stereo frame they were last evaluated on.
    ``T_odom_camera`` is the camera pose in odom at that frame, when odometry was available."""
    positions: np.ndarray = array_field("float32", (None, 3))
    fitness: np.ndarray = array_field("float32", (None,))
    generation: int = 0
    source_seq: int = 0
    T_odom_camera: Optional[np.ndarray] = array_field("float64", (4, 4), optional=True)
    header: Envelope = _header_field()


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


@schema("Transform")
class TransformMsg(Message):
    """A transform frame_id → child_frame_id (e.g. map → odom)."""
    child_frame_id: str = ""
    translation: np.ndarray = array_field("float64", (3,))
    rotation: np.ndarray = array_field("float64", (4,))  # quaternion xyzw
    header: Envelope = _header_field()


@schema("Keyframe")
class Keyframe:
    """One keyframe of the fly map: its camera pose in the map frame and its population (camera frame)."""
    id: int = 0
    stamp_ns: int = 0
    position: np.ndarray = array_field("float64", (3,))
    orientation: np.ndarray = array_field("float64", (4,))
    points: np.ndarray = array_field("float32", (None, 3))
    fitness: np.ndarray = array_field("float32", (None,))


@schema("FlyMap")
class FlyMap(Message):
    """The localiser's map: keyframe fly populations (frame_id = map)."""
    keyframes: list[Keyframe] = field(default_factory=list)
    header: Envelope = _header_field()


@schema("VelocityCommand")
class VelocityCommand(Message):
    """Differential-drive command in base_link: forward speed (m/s), turn rate (rad/s). ``stop`` with a
    ``reason`` when the planner halts ('target reached', 'no path', ...)."""
    linear_mps: float = 0.0
    angular_radps: float = 0.0
    stop: bool = False
    reason: str = ""
    header: Envelope = _header_field()


@schema("Target")
class Target(Message):
    """A navigation goal in frame_id (normally map)."""
    x: float = 0.0
    y: float = 0.0
    radius_m: float = 0.3
    header: Envelope = _header_field()


@schema("HarmonicField")
class HarmonicField(Message):
    """The planner's harmonic potential on a grid in the map frame, with the current descent path."""
    values: np.ndarray = array_field(("float32", "float64"), (None, None))
    origin_xy: np.ndarray = array_field("float64", (2,))
    resolution_m: float = 0.05
    path_xy: Optional[np.ndarray] = array_field("float64", (None, 2), optional=True)
    header: Envelope = _header_field()


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


@schema("DepthImage")
class DepthImage(Message):
    """Ground-truth depth (metres, Z in the left optical frame; inf = nothing) from a simulator."""
    depth: np.ndarray = array_field("float32", (None, None))
    header: Envelope = _header_field()


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
