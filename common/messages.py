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
    ALLOWED_DTYPES, ENVELOPE_KEYS, MAX_ARRAY_BYTES, MAX_ARRAY_NDIM, MAX_LIST_LEN, MAX_PAYLOAD_BYTES, SCHEMAS,
    Array, DecodeError, Envelope, MalformedPayload, Message, MissingField, ShapeMismatch, TooLarge,
    UnknownSchema, UnsupportedVersion, WrongType, _header_field, array_field, decode, encode, header,
    peek_schema, required, schema)

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
    ``T_odom_camera`` is the camera pose in odom at that frame, when odometry was available; ``image``
    the grey left image of that frame (the flies' neighbourhoods, for photometric tracking), sent with
    a frame's first publication only."""
    positions: np.ndarray = array_field("float32", (None, 3))
    fitness: np.ndarray = array_field("float32", (None,))
    generation: int = 0
    source_seq: int = 0
    T_odom_camera: Optional[np.ndarray] = array_field("float64", (4, 4), optional=True)
    image: Optional[np.ndarray] = array_field("uint8", (None, None), optional=True)
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
