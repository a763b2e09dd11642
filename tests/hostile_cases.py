"""Hostile messages on a valid schema, per stream a service reads: a well-formed message and named
hostile cases (messages or raw payloads). Shared by tests/test_hostile_messages.py and bench/faults.py."""
from __future__ import annotations

import dataclasses

import msgpack
import numpy as np

from common import messages as m
from common import streams as S
from common.camera import StereoCalibration
from common.images import make_frame

IMG = np.full((48, 64, 3), 100, np.uint8)
EYE_Q = np.array([0.0, 0.0, 0.0, 1.0])


def _calib(**changes):
    msg = m.calibration_to_msg(StereoCalibration.ideal(64, 48), 1, 5)
    return dataclasses.replace(msg, **changes) if changes else msg


def _camera(msg, side, **arrays):
    cam = dataclasses.replace(getattr(msg, side), **arrays)
    return dataclasses.replace(msg, **{side: cam})


def pose(position=(1.0, 2.0, 0.0), orientation=EYE_Q, cov=None, **kw):
    return m.PoseEstimate(position=np.array(position, float), orientation=np.array(orientation, float),
                          covariance=np.eye(6) * 0.01 if cov is None else cov, header=m.header(1, 5, "map"), **kw)


def population(positions=None, fitness=None, **kw):
    pos = np.ones((10, 3), np.float32) if positions is None else positions
    fit = np.zeros(len(pos), np.float32) if fitness is None else fitness
    return m.FlyPopulation(positions=pos, fitness=fit, header=m.header(1, 5, "camera_left_optical"), **kw)


def _sonar(**kw):
    base = dict(transducer_poses=np.zeros((2, 3)), ranges=np.array([1.0, np.nan], np.float32), beam_width_rad=0.4,
                min_range_m=0.1, max_range_m=5.0, header=m.header(1, 5, "base_link"))
    return m.SonarScan(**(base | kw))


def _transform(translation=(1.0, 0.0, 0.0), rotation=EYE_Q):
    return m.TransformMsg(child_frame_id="odom", translation=np.array(translation, float),
                          rotation=np.array(rotation, float), header=m.header(1, 5, "map"))


def _heartbeat(**kw):
    return m.Heartbeat(**(dict(service="evolver", pid=12, progress=3, rates={"frames_skipped": 2.0},
                                counters={"rejected": 1}) | kw))


def keyframe_map(**kw):
    base = dict(id=1, stamp_ns=5, position=np.zeros(3), orientation=EYE_Q, points=np.ones((4, 3), np.float32),
                fitness=np.ones(4, np.float32))
    return m.FlyMap(keyframes=[m.Keyframe(**(base | kw))], header=m.header(1, 5, "map"))


def _envelope_only(schema: type) -> bytes:
    return msgpack.packb({"schema": schema.SCHEMA, "major": schema.MAJOR, "seq": 1, "stamp_ns": 5, "frame_id": "map"})


def with_header(msg, **changes):
    return dataclasses.replace(msg, header=dataclasses.replace(msg.header, **changes))


NAN, HUGE = float("nan"), 1e308

# stream -> (a well-formed message, {hostile case: message or raw payload})
CASES = {
    S.STEREO_FRAME: (make_frame(IMG, IMG, 1, 5), {
        "empty rgb8 image": make_frame(np.zeros((0, 0, 3), np.uint8), np.zeros((0, 0, 3), np.uint8), 1, 5),
        "left/right size mismatch": m.StereoFrame(left=IMG, right=IMG[:24], encoding="rgb8"),
        "mono8 with colour images": m.StereoFrame(left=IMG, right=IMG, encoding="mono8"),
        "unknown encoding": m.StereoFrame(left=IMG, right=IMG, encoding="bgr16"),
        "empty jpeg bytes": m.StereoFrame(left=np.zeros(0, np.uint8), right=np.zeros(0, np.uint8), encoding="jpeg"),
        "seq 2^62": with_header(make_frame(IMG, IMG, 1, 5), seq=2 ** 62),
        "negative stamp": with_header(make_frame(IMG, IMG, 1, 5), stamp_ns=-1),
    }),
    S.STEREO_CALIBRATION: (_calib(), {
        "zero width": _calib(width=0),
        "zero baseline": _calib(baseline_m=0.0),
        "negative baseline": _calib(baseline_m=-0.1),
        "NaN baseline": _calib(baseline_m=NAN),
        "zero focal length": _camera(_calib(), "left", P=np.zeros((3, 4))),
        "negative focal length": _camera(_calib(), "right", K=np.diag([-500.0, 500.0, 1.0])),
        "NaN distortion": _camera(_calib(), "left", D=np.array([NAN, 0, 0, 0, 0])),
        "mount at 1e308": _calib(T_base_camera=np.diag([1.0, 1, 1, 1]) + np.pad([[HUGE]], ((0, 3), (3, 0)))),
    }),
    S.ODOM_WHEELS: (m.WheelOdometry(wheel_speeds=np.array([1.0, 1.0]), wheel_radius_m=0.05, track_width_m=0.3), {
        "negative wheel radius": m.WheelOdometry(wheel_radius_m=-0.05, track_width_m=0.3),
        "NaN track width": m.WheelOdometry(wheel_radius_m=0.05, track_width_m=NAN),
        "pose at 1e308": m.WheelOdometry(pose_xyyaw=np.array([HUGE, 0.0, 0.0])),
        "NaN covariance": m.WheelOdometry(covariance=np.full((3, 3), NAN)),
        "wheel speed 1e308": m.WheelOdometry(wheel_speeds=np.array([HUGE, 0.0])),
    }),
    S.SONAR_SCAN: (_sonar(), {
        "infinite range": _sonar(ranges=np.array([np.inf, 1.0], np.float32)),
        "negative range": _sonar(ranges=np.array([-1.0, 1.0], np.float32)),
        "ranges/poses mismatch": _sonar(ranges=np.ones(3, np.float32)),
        "transducer at 1e308": _sonar(transducer_poses=np.array([[HUGE, 0, 0], [0, 0, 0]])),
        "NaN beam width": _sonar(beam_width_rad=NAN),
    }),
    S.TRUTH_POSE: (pose(), {"position 1e308": pose((HUGE, 0, 0))}),
    S.TRUTH_DEPTH: (m.DepthImage(depth=np.full((4, 4), np.inf, np.float32)), {
        "empty depth": m.DepthImage(depth=np.zeros((0, 0), np.float32)),
        "NaN depth": m.DepthImage(depth=np.full((4, 4), NAN, np.float32)),
    }),
    S.FUSION_ODOM: (pose(), {
        "position 1e308": pose((HUGE, 0, 0)),
        "NaN position": pose((NAN, 0, 0)),
        "zero quaternion": pose(orientation=np.zeros(4)),
        "NaN covariance": pose(cov=np.full((6, 6), NAN)),
        "negative variance": pose(cov=-np.eye(6)),
        "source_seq 2^62": pose(source_seq=2 ** 62),
    }),
    S.FUSION_POSE: (pose(), {
        "position 1e308": pose((HUGE, 0, 0)),
        "beyond the world (1e7 m)": pose((1e7, 0, 0)),
        "NaN covariance": pose(cov=np.full((6, 6), NAN)),
    }),
    S.FUSION_SONAR: (_sonar(), {"infinite range": _sonar(ranges=np.array([np.inf, 1.0], np.float32))}),
    S.FUSION_SONAR_POINTS: (population(), {"NaN point": population(np.full((2, 3), NAN, np.float32))}),
    S.FLIES_POPULATION: (population(fitness=np.array([-np.inf] * 5 + [0.5] * 5, np.float32)), {
        "NaN positions": population(np.full((3, 3), NAN, np.float32)),
        "infinite position": population(np.full((3, 3), np.inf, np.float32)),
        "NaN fitness": population(fitness=np.full(10, NAN, np.float32)),
        "fitness/positions mismatch": population(fitness=np.zeros(3, np.float32)),
        "NaN odometry pose": population(T_odom_camera=np.full((4, 4), NAN)),
        "empty image": population(image=np.zeros((0, 0), np.uint8)),
        "source_seq 2^62": population(source_seq=2 ** 62),
    }),
    S.TRACE_EVOLVER: (m.EvolverTrace(take_ns=1, generations=3), {
        "negative generations": m.EvolverTrace(generations=-5),
    }),
    S.SLAM_POSE: (pose(), {
        "position 1e308": pose((HUGE, 0, 0)),
        "NaN orientation": pose(orientation=[NAN, 0, 0, 1]),
        "NaN covariance": pose(cov=np.full((6, 6), NAN)),
    }),
    S.SLAM_MAP_TO_ODOM: (_transform(), {
        "NaN translation": _transform((NAN, 0, 0)),
        "translation 1e308": _transform((HUGE, 0, 0)),
        "zero rotation": _transform(rotation=np.zeros(4)),
    }),
    S.SLAM_MAP: (keyframe_map(), {
        "keyframe at 1e308": keyframe_map(position=np.array([HUGE, 0, 0])),
        "NaN points": keyframe_map(points=np.full((4, 3), NAN, np.float32)),
        "negative keyframe stamp": keyframe_map(stamp_ns=-1),
    }),
    S.PLANNER_TARGET: (m.Target(x=3.0, y=-1.0, header=m.header(1, 5, "map")), {
        "envelope with no fields": _envelope_only(m.Target),
        "NaN x": m.Target(x=NAN, y=0.0),
        "y at 1e308": m.Target(x=0.0, y=HUGE),
        "negative radius": m.Target(x=1.0, y=1.0, radius_m=-1.0),
    }),
    S.PLANNER_CMD_VEL: (m.VelocityCommand(linear_mps=0.3, angular_radps=0.1), {
        "envelope with no fields": _envelope_only(m.VelocityCommand),
        "NaN speed": m.VelocityCommand(linear_mps=NAN),
        "speed 1e308": m.VelocityCommand(angular_radps=HUGE),
    }),
    S.PLANNER_FIELD: (m.HarmonicField(values=np.zeros((4, 4)), origin_xy=np.zeros(2)), {
        "zero resolution": m.HarmonicField(values=np.zeros((4, 4)), origin_xy=np.zeros(2), resolution_m=0.0),
        "NaN origin": m.HarmonicField(values=np.zeros((4, 4)), origin_xy=np.full(2, NAN)),
    }),
    S.STATUS: (_heartbeat(), {
        "frames_skipped = 'lots'": _heartbeat(rates={"frames_skipped": "lots"}),
        "NaN rate": _heartbeat(rates={"generations_per_s": NAN}),
        "counter 2^62": _heartbeat(counters={"rejected": 2 ** 62}),
        "negative counter": _heartbeat(counters={"rejected": -3}),
        "counter as a map": _heartbeat(counters={"rejected": {"a": 1}}),
        "progress 2^62": _heartbeat(progress=2 ** 62),
    }),
}

CASES[S.FLIES_WITH_IMAGE] = CASES[S.FLIES_POPULATION]     # the same population, with its image

HOSTILE = [(stream, label, msg) for stream, (_, cases) in CASES.items() for label, msg in cases.items()]


def hostile_payloads() -> list[tuple[str, bytes]]:
    """(stream key, payload) of every hostile case."""
    return [(stream.key, msg if isinstance(msg, bytes) else m.encode(msg)) for stream, _, msg in HOSTILE]
