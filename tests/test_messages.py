"""Codec: every schema round-trips; every malformed case is rejected with its typed error."""
from __future__ import annotations

import cv2
import msgpack
import numpy as np
import pytest

from common import messages as m
from common.camera import StereoCalibration
from common.images import frame_images, jpeg_components, make_frame

rng = np.random.default_rng(0)


def samples():
    img = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
    calib = StereoCalibration.ideal(64, 48)
    yield make_frame(img, img[:, ::-1].copy(), 7, 123, "rgb8")
    yield make_frame(img[..., 0].copy(), img[..., 1].copy(), 8, 124, "mono8")
    yield m.calibration_to_msg(calib, 1, 99)
    yield m.WheelOdometry(wheel_speeds=np.array([1.0, 1.1]), ticks=np.array([100, 120]), ticks_per_rev=1024.0,
                          wheel_radius_m=0.05, track_width_m=0.3, pose_xyyaw=np.array([1.0, 2.0, 0.3]),
                          covariance=np.eye(3) * 1e-3, header=m.header(3, 5, "odom"))
    yield m.SonarScan(transducer_poses=rng.random((8, 3)), ranges=rng.random(8).astype(np.float32),
                      beam_width_rad=0.4, min_range_m=0.1, max_range_m=5.0, header=m.header(1, 2, "base_link"))
    yield m.FlyPopulation(positions=rng.random((100, 3)).astype(np.float32), fitness=rng.random(100).astype(np.float32),
                          generation=42, source_seq=9, T_odom_camera=np.eye(4), header=m.header(1, 2, "camera_left_optical"))
    yield m.pose_msg(np.eye(4), np.eye(6), seq=4, stamp_ns=5, status="odometry only", source_seq=3)
    yield m.TransformMsg(child_frame_id="odom", translation=np.zeros(3), rotation=np.array([0, 0, 0, 1.0]),
                         header=m.header(1, 1, "map"))
    yield m.FlyMap(keyframes=[m.Keyframe(id=i, stamp_ns=i, position=np.zeros(3), orientation=np.array([0, 0, 0, 1.0]),
                                         points=rng.random((10, 3)).astype(np.float32),
                                         fitness=np.ones(10, np.float32)) for i in range(3)], header=m.header(1, 1, "map"))
    yield m.VelocityCommand(linear_mps=0.3, angular_radps=-0.1, stop=True, reason="target reached")
    yield m.Target(x=3.0, y=-1.0, radius_m=0.5, header=m.header(1, 1, "map"))
    yield m.HarmonicField(values=rng.random((20, 30)), origin_xy=np.zeros(2), resolution_m=0.1,
                          path_xy=rng.random((5, 2)))
    yield m.Heartbeat(service="evolver", pid=12, progress=1000, rates={"generations_per_s": 50.5},
                      counters={"rejected": 2})
    yield m.DepthImage(depth=rng.random((48, 64)).astype(np.float32))
    yield m.EvolverTrace(take_ns=10, decoded_ns=20, ready_ns=30, published_ns=45, generations=7,
                         reference=None, quality=0.25, header=m.header(3, 123))
    yield m.EvolverTrace(generations=2, reference=0.5, quality=0.5)


def _equal(a, b):
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True)
    if isinstance(a, list):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    if hasattr(a, "__dataclass_fields__"):
        return type(a) is type(b) and all(_equal(getattr(a, f), getattr(b, f)) for f in a.__dataclass_fields__)
    return a == b


@pytest.mark.parametrize("msg", list(samples()), ids=lambda x: type(x).__name__)
def test_round_trip(msg):
    back = m.decode(m.encode(msg))
    assert _equal(msg, back)


def test_every_registered_schema_is_covered():
    top_level = {name for name, cls in m.SCHEMAS.items() if "header" in cls.__dataclass_fields__}
    covered = {type(x).SCHEMA for x in samples()}
    assert top_level <= covered


def test_compressed_frames_decode_to_the_same_size():
    img = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
    for enc in ("png", "jpeg"):
        left, right = frame_images(m.decode(m.encode(make_frame(img, img, 1, 1, enc))))
        assert left.shape == img.shape
    left, _ = frame_images(m.decode(m.encode(make_frame(img, img, 1, 1, "png"))))
    assert np.array_equal(left, img)  # png is lossless


def test_jpeg_frames_decode_straight_to_rgb_with_the_colours_in_place():
    # The decoder reads the JPEG header's component count and has libjpeg write RGB directly; the
    # image must be what OpenCV's BGR decode turned into RGB was, and a grey JPEG must stay grey.
    img = cv2.GaussianBlur(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8), (0, 0), 1.5)
    img[:, :20] = (230, 20, 20)                                            # a red stripe: channel order shows
    frame = m.decode(m.encode(make_frame(img, img, 1, 1, "jpeg", quality=95)))
    left, _ = frame_images(frame)
    bgr = cv2.imdecode(np.asarray(frame.left), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(left, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    assert left[24, 10, 0] > 200 and left[24, 10, 2] < 60
    assert jpeg_components(frame.left) == 3
    grey = m.decode(m.encode(make_frame(img[:, :, 1].copy(), img[:, :, 1].copy(), 1, 1, "jpeg")))
    assert jpeg_components(grey.left) == 1 and frame_images(grey)[0].shape == (48, 64)
    assert jpeg_components(np.frombuffer(b"\xff\xd8\xff\xe0\x00\x10", np.uint8)) is None   # ends early
    assert jpeg_components(cv2.imencode(".png", img)[1]) is None


def _payload(**changes):
    obj = msgpack.unpackb(m.encode(m.Target(x=1.0, y=2.0, header=m.header(1, 2, "map"))), raw=False)
    obj.update(changes)
    return msgpack.packb({k: v for k, v in obj.items() if v is not _DROP}, use_bin_type=True)


_DROP = object()


@pytest.mark.parametrize("payload,error", [
    (b"", m.MalformedPayload),
    (b"\xc1\xc1\xc1", m.MalformedPayload),
    (msgpack.packb([1, 2, 3]), m.MalformedPayload),
    (m.encode(m.Target())[:-3], m.MalformedPayload),                       # truncated
    (m.encode(m.Target()) + b"\x00", m.MalformedPayload),                  # trailing bytes
    (_payload(schema="flyslam.NoSuchThing"), m.UnknownSchema),
    (_payload(major=2), m.UnsupportedVersion),
    (_payload(x="three"), m.WrongType),
    (_payload(stamp_ns=1.5), m.WrongType),
    (_payload(seq=_DROP), m.MissingField),
])
def test_malformed_target_payloads_are_rejected(payload, error):
    with pytest.raises(error):
        m.decode(payload)


def _frame_obj():
    img = np.zeros((4, 5, 3), np.uint8)
    return msgpack.unpackb(m.encode(make_frame(img, img, 1, 1)), raw=False)


@pytest.mark.parametrize("mutate,error", [
    (lambda o: o["left"].update(shape=[4, 5, 4]), m.ShapeMismatch),         # shape not matching data
    (lambda o: o["left"].update(shape=[2, 2, 3, 5]), m.ShapeMismatch),      # right byte count, not an image shape
    (lambda o: o["left"].update(dtype="complex128"), m.WrongType),
    (lambda o: o["left"].update(dtype="float32", data=b"\x00" * 240, shape=[4, 5, 3]), m.WrongType),
    (lambda o: o["left"].update(shape=[1 << 20, 1 << 20]), m.TooLarge),     # absurd size
    (lambda o: o["left"].update(shape=[1, 1, 1, 1, 1, 60]), m.TooLarge),
    (lambda o: o.pop("right"), m.MissingField),
    (lambda o: o.update(left="not an array"), m.WrongType),
    (lambda o: o["left"].pop("data"), m.MissingField),
])
def test_malformed_arrays_are_rejected(mutate, error):
    obj = _frame_obj()
    mutate(obj)
    payload = msgpack.packb(obj, use_bin_type=True)
    with pytest.raises(error):
        m.decode(payload)


def test_decode_can_require_a_schema():
    with pytest.raises(m.UnknownSchema):
        m.decode(m.encode(m.Target()), m.StereoFrame)


def test_random_bytes_only_ever_raise_decode_errors():
    for i in range(2000):
        data = rng.integers(0, 256, rng.integers(0, 200), dtype=np.uint8).tobytes()
        try:
            m.decode(data)
        except m.DecodeError:
            pass


def test_mutated_payloads_only_ever_raise_decode_errors():
    base = bytearray(m.encode(m.FlyPopulation(positions=np.zeros((5, 3), np.float32), fitness=np.zeros(5, np.float32))))
    for i in range(2000):
        data = bytearray(base)
        for _ in range(rng.integers(1, 4)):
            data[rng.integers(0, len(data))] = rng.integers(0, 256)
        try:
            m.decode(bytes(data[: rng.integers(1, len(data) + 1)]))
        except m.DecodeError:
            pass


def test_every_schema_with_numbers_or_images_checks_their_meaning():
    """Shape alone let a 1e308 pose or an empty image through; every such schema has a validate()."""
    containers = {"flyslam.FlyMap"}            # its keyframes validate themselves
    missing = {name for name, cls in m.SCHEMAS.items() if not hasattr(cls, "validate")} - containers
    assert missing == set()


def test_validation_errors_are_decode_errors_naming_the_schema_and_field():
    bad = m.Target(x=float("nan"), y=0.0)
    with pytest.raises(m.DecodeError, match=r"flyslam\.Target: x = nan"):
        m.decode(m.encode(bad))
    kf = m.Keyframe(id=0, stamp_ns=0, position=np.array([1e9, 0, 0]), orientation=np.array([0, 0, 0, 1.0]),
                    points=np.zeros((1, 3), np.float32), fitness=np.zeros(1, np.float32))
    with pytest.raises(m.InvalidValue, match=r"keyframes\[0\]: position"):
        m.decode(m.encode(m.FlyMap(keyframes=[kf])))
