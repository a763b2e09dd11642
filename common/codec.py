"""The msgpack codec of flyslam messages: envelope, field vocabulary, schema registry, encode/decode.

Every message on the bus (and in a recording) is a msgpack map: an *envelope* and the schema's fields.

    {"schema": "flyslam.StereoFrame", "major": 1, "seq": 12, "stamp_ns": 1700000000000, "frame_id": "camera_left_optical",
     ...fields...}

numpy arrays travel as ``{"dtype": "uint8", "shape": [480, 640, 3], "data": <bytes>}``: no per-element
encoding, so a 640×480 stereo pair costs one memcpy each way.

Decoding *validates* and raises a subclass of :class:`DecodeError` for anything wrong — truncated bytes,
wrong types, missing fields, unknown schema or major version, shape not matching the data, absurd sizes —
and for values that are well-typed but meaningless (:class:`InvalidValue`): seq outside [0, 2⁵³], a
negative stamp, any integer field outside int64, and whatever a schema's ``validate()`` method refuses
(non-finite numbers, positions beyond ``MAX_WORLD_M``, empty images, a non-positive focal length...).
A field declared with :func:`required` must be on the wire although it has a default.
Services catch ``DecodeError``, count it and carry on; nothing malformed ever escapes as another exception.

A schema is a dataclass registered with :func:`schema`. Its fields are typed with the small vocabulary
below (``int``, ``float``, ``str``, ``bool``, ``dict``, ``Array(...)``, a nested schema, ``list[...]`` of a
nested schema, ``Optional``); the codec derives encoding and validation from those types.
The schemas themselves are in :mod:`common.messages`, which re-exports this module's names.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import types
import typing
from dataclasses import dataclass, field
from typing import Any, ClassVar

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


class InvalidValue(DecodeError):
    """Well-typed but meaningless: a non-finite or absurd number, a negative stamp, an empty or
    mismatched image, a non-positive focal length... (a schema's ``validate`` says which)."""


# Sanity limits: far above any legitimate message, far below what would hurt a 24 GiB machine.
MAX_PAYLOAD_BYTES = 256 * 1024 * 1024
MAX_ARRAY_BYTES = 128 * 1024 * 1024
MAX_ARRAY_NDIM = 4
MAX_LIST_LEN = 100_000

# Meaning limits. MAX_WORLD_M bounds every position, translation and target in a world frame (map, odom,
# base_link); fly positions (camera frame, drawn out to ~10⁶ × the nearest depth when depth_max = inf)
# get MAX_FLY_RANGE_M, which still keeps a grid index of them far inside int64. MAX_COUNT bounds seq
# and the count fields schemas name (beyond 2⁵³ a float64 counter can no longer add 1); every integer
# field must fit in int64 (stamps are int64 ns, ~1.7e18 today).
MAX_WORLD_M = 1e6
MAX_FLY_RANGE_M = 1e9
MAX_COUNT = 2 ** 53
MAX_STAMP_NS = 2 ** 63 - 1

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

    def check(self, arr: np.ndarray, where: str, dtype_name: str | None = None) -> None:
        """Raise unless ``arr`` has an allowed dtype and shape (``dtype_name``: its dtype's name when known,
        which saves numpy the work of spelling it)."""
        name = dtype_name or arr.dtype.name
        if name not in self.dtypes():
            raise WrongType(f"{where}: dtype {name}, expected {'/'.join(self.dtypes())}")
        options = self.shapes if self.shapes is not None else ((self.shape,) if self.shape else None)
        if options is None:
            return
        for shape in options:
            if len(shape) == arr.ndim and all(s is None or s == n for s, n in zip(shape, arr.shape)):
                return
        raise ShapeMismatch(f"{where}: shape {arr.shape} does not match {options}")


def array_field(dtype, shape=None, shapes=None, optional=False, side=False):
    """Declare an array field: ``positions: np.ndarray = array_field("float32", (None, 3))``.

    ``side`` (optional fields only): the field is left out of :func:`encode`'s payload and travels
    beside it, encoded by :func:`encode_side` (the bus sends it as the sample's attachment): live
    subscribers get it, a recording of the payloads does not keep it."""
    if side and not optional:
        raise TypeError("a side field must be optional: a recording does not keep it")
    meta = {"array": Array(dtype, shape, shapes)} | ({"side": True} if side else {})
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


# ------------------------------------------------------------------------------------ encoding


_DTYPE_NAMES = {np.dtype(name): name for name in ALLOWED_DTYPES}


@functools.cache
def _field_names(cls) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls) if f.name != "header" and not f.metadata.get("side"))


@functools.cache
def _side_names(cls) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls) if f.metadata.get("side"))


def _encode_value(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        arr = np.ascontiguousarray(value)
        return {"dtype": _DTYPE_NAMES.get(arr.dtype) or arr.dtype.name, "shape": list(arr.shape),
                "data": arr.tobytes()}
    if dataclasses.is_dataclass(value):
        return {name: _encode_value(getattr(value, name)) for name in _field_names(type(value))}
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


def encode_side(msg) -> bytes | None:
    """The message's side fields that are set (see :func:`array_field`) as one msgpack map, or None."""
    side = {name: _encode_value(v) for name in _side_names(type(msg)) if (v := getattr(msg, name)) is not None}
    return msgpack.packb(side, use_bin_type=True) if side else None


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
    spec.check(arr, where, dtype)
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
        if not -MAX_STAMP_NS - 1 <= value <= MAX_STAMP_NS:
            raise InvalidValue(f"{where}: {value} does not fit in int64")
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


_ARRAY, _STRUCT, _LIST_OF_STRUCTS, _LIST_OF_SCALARS, _SCALAR = range(5)


@functools.cache
def _decode_plan(cls) -> tuple:
    """A schema's fields as (name, kind, what, required), resolved once per schema: resolving type
    hints and inspecting them cost more than decoding a small message."""
    hints = typing.get_type_hints(cls)
    plan = []
    for f in dataclasses.fields(cls):
        if f.name == "header":
            continue
        tp, optional = _unwrap_optional(hints[f.name])
        required = f.metadata.get("required", False) or (
            not optional and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING)
        if "array" in f.metadata:
            kind, what = _ARRAY, f.metadata["array"]
        elif typing.get_origin(tp) is list:
            (what,) = typing.get_args(tp)
            kind = _LIST_OF_STRUCTS if dataclasses.is_dataclass(what) else _LIST_OF_SCALARS
        elif dataclasses.is_dataclass(tp):
            kind, what = _STRUCT, tp
        else:
            kind, what = _SCALAR, tp
        plan.append((f.name, kind, what, required))
    return tuple(plan)


def _decode_struct(obj: Any, cls, where: str):
    if not isinstance(obj, dict):
        raise WrongType(f"{where}: expected a map, got {type(obj).__name__}")
    kwargs = {}
    for name, kind, what, required in _decode_plan(cls):
        value = obj.get(name)
        if value is None:
            if required:
                raise MissingField(f"{where}.{name} is missing")
            continue
        if kind == _ARRAY:
            kwargs[name] = _decode_array(value, what, f"{where}.{name}")
        elif kind == _SCALAR:
            kwargs[name] = _decode_scalar(value, what, f"{where}.{name}")
        elif kind == _STRUCT:
            kwargs[name] = _decode_struct(value, what, f"{where}.{name}")
        else:
            fwhere = f"{where}.{name}"
            if not isinstance(value, list):
                raise WrongType(f"{fwhere}: expected a list, got {type(value).__name__}")
            if len(value) > MAX_LIST_LEN:
                raise TooLarge(f"{fwhere}: {len(value)} items")
            item = _decode_struct if kind == _LIST_OF_STRUCTS else _decode_scalar
            kwargs[name] = [item(v, what, f"{fwhere}[{i}]") for i, v in enumerate(value)]
    missing = [name for name in getattr(cls, "REQUIRED_FIELDS", ()) if name not in kwargs]
    if missing:
        raise MissingField(f"{where}.{missing[0]} is missing")
    out = cls(**kwargs)
    validate = getattr(out, "validate", None)
    if validate is not None:
        try:
            validate()
        except InvalidValue as e:
            raise InvalidValue(f"{where}: {e}") from None
    return out


def peek_schema(payload: bytes) -> tuple[str, int]:
    """(schema, major) of a payload without validating the rest; raises DecodeError."""
    return peek_envelope(payload)[:2]


def peek_envelope(payload: bytes) -> tuple[str, int, Any]:
    """(schema, major, stamp_ns as sent: unchecked, None if absent) of a payload in one parse, without
    validating the rest (a recorder's per-message question); raises DecodeError."""
    obj = _unpack(payload)
    return (*_envelope_schema(obj), obj.get("stamp_ns"))


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


def decode(payload: bytes, expected: type | tuple[type, ...] | None = None, side: bytes | None = None):
    """Parse and validate a payload. ``expected`` restricts which schema(s) are acceptable; ``side`` is
    what :func:`encode_side` made of the same message (its fields are validated like the others)."""
    obj = _unpack(payload)
    name, major = _envelope_schema(obj)
    cls = SCHEMAS.get(name)
    if side is not None and cls is not None:
        extra = _unpack(side)
        obj.update((k, extra[k]) for k in _side_names(cls) if k in extra)
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
    if not 0 <= seq <= MAX_COUNT:
        raise InvalidValue(f"envelope.seq {seq} is outside [0, 2⁵³]")
    if not 0 <= stamp <= MAX_STAMP_NS:
        raise InvalidValue(f"envelope.stamp_ns {stamp} is negative or beyond int64")
    msg = _decode_struct(obj, cls, name)
    msg.header = Envelope(seq=seq, stamp_ns=stamp, frame_id=frame_id)
    return msg


# ------------------------------------------------------------------------- meaning checks (validate)


def check_finite(where: str, value, limit: float | None = None, allow_neg_inf: bool = False) -> None:
    """Raise InvalidValue unless every element of ``value`` is finite (−inf too with ``allow_neg_inf``)
    and, with ``limit``, within ±limit."""
    a = np.asarray(value, dtype=float)
    if not a.size:
        return
    if allow_neg_inf:
        a = np.where(a == -np.inf, 0.0, a)
    largest = float(np.abs(a).max())      # NaN and ±inf propagate: one reduction checks every element
    if not math.isfinite(largest):
        raise InvalidValue(f"{where} is not finite ({a[~np.isfinite(a)].flat[0]})")
    if limit is not None and largest > limit:
        raise InvalidValue(f"{where} is beyond ±{limit:g}")


def check_positive(where: str, value: float) -> None:
    """Raise InvalidValue unless ``value`` is a finite number > 0."""
    if not (math.isfinite(value) and value > 0):
        raise InvalidValue(f"{where} must be > 0, got {value}")


def check_range(where: str, value: float, lo: float, hi: float) -> None:
    """Raise InvalidValue unless lo <= value <= hi (NaN fails)."""
    if not lo <= value <= hi:
        raise InvalidValue(f"{where} = {value} is outside [{lo:g}, {hi:g}]")


def header(seq: int = 0, stamp_ns: int = 0, frame_id: str = "") -> Envelope:
    return Envelope(int(seq), int(stamp_ns), str(frame_id))


def _header_field():
    return field(default_factory=Envelope)


def required(default=None):
    """A field that must be present on the wire (a nested struct, or a value whose default must not stand
    in for a missing one: an empty VelocityCommand is not a command to stop)."""
    return field(default=default, metadata={"required": True})
