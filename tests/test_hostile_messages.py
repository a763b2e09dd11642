"""Hostile messages on a valid schema, on every stream a service reads, are rejected at decode with a
one-line reason (an InvalidValue or MissingField, so every service's DecodeError counting applies),
while the same stream's well-formed message still decodes."""
from __future__ import annotations

import dataclasses
import math
import time

import msgpack
import numpy as np
import pytest

from common import messages as m
from common import streams as S
from common.bus import BusOptions, Node
from common.camera import StereoCalibration
from common.images import make_frame
from tests.helpers import hub, start_module, stop, wait_until

IMG = np.full((48, 64, 3), 100, np.uint8)
EYE_Q = np.array([0.0, 0.0, 0.0, 1.0])


def _calib(**changes):
    msg = m.calibration_to_msg(StereoCalibration.ideal(64, 48), 1, 5)
    return dataclasses.replace(msg, **changes) if changes else msg


def _camera(msg, side, **arrays):
    cam = dataclasses.replace(getattr(msg, side), **arrays)
    return dataclasses.replace(msg, **{side: cam})


def _pose(position=(1.0, 2.0, 0.0), orientation=EYE_Q, cov=None, **kw):
    return m.PoseEstimate(position=np.array(position, float), orientation=np.array(orientation, float),
                          covariance=np.eye(6) * 0.01 if cov is None else cov, header=m.header(1, 5, "map"), **kw)


def _population(positions=None, fitness=None, **kw):
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


def _keyframe(**kw):
    base = dict(id=1, stamp_ns=5, position=np.zeros(3), orientation=EYE_Q, points=np.ones((4, 3), np.float32),
                fitness=np.ones(4, np.float32))
    return m.FlyMap(keyframes=[m.Keyframe(**(base | kw))], header=m.header(1, 5, "map"))


def _envelope_only(schema: type) -> bytes:
    return msgpack.packb({"schema": schema.SCHEMA, "major": schema.MAJOR, "seq": 1, "stamp_ns": 5, "frame_id": "map"})


def _with_header(msg, **changes):
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
        "seq 2^62": _with_header(make_frame(IMG, IMG, 1, 5), seq=2 ** 62),
        "negative stamp": _with_header(make_frame(IMG, IMG, 1, 5), stamp_ns=-1),
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
    S.TRUTH_POSE: (_pose(), {"position 1e308": _pose((HUGE, 0, 0))}),
    S.TRUTH_DEPTH: (m.DepthImage(depth=np.full((4, 4), np.inf, np.float32)), {
        "empty depth": m.DepthImage(depth=np.zeros((0, 0), np.float32)),
        "NaN depth": m.DepthImage(depth=np.full((4, 4), NAN, np.float32)),
    }),
    S.FUSION_ODOM: (_pose(), {
        "position 1e308": _pose((HUGE, 0, 0)),
        "NaN position": _pose((NAN, 0, 0)),
        "zero quaternion": _pose(orientation=np.zeros(4)),
        "NaN covariance": _pose(cov=np.full((6, 6), NAN)),
        "negative variance": _pose(cov=-np.eye(6)),
        "source_seq 2^62": _pose(source_seq=2 ** 62),
    }),
    S.FUSION_POSE: (_pose(), {
        "position 1e308": _pose((HUGE, 0, 0)),
        "beyond the world (1e7 m)": _pose((1e7, 0, 0)),
        "NaN covariance": _pose(cov=np.full((6, 6), NAN)),
    }),
    S.FUSION_SONAR: (_sonar(), {"infinite range": _sonar(ranges=np.array([np.inf, 1.0], np.float32))}),
    S.FUSION_SONAR_POINTS: (_population(), {"NaN point": _population(np.full((2, 3), NAN, np.float32))}),
    S.FLIES_POPULATION: (_population(fitness=np.array([-np.inf] * 5 + [0.5] * 5, np.float32)), {
        "NaN positions": _population(np.full((3, 3), NAN, np.float32)),
        "infinite position": _population(np.full((3, 3), np.inf, np.float32)),
        "NaN fitness": _population(fitness=np.full(10, NAN, np.float32)),
        "fitness/positions mismatch": _population(fitness=np.zeros(3, np.float32)),
        "NaN odometry pose": _population(T_odom_camera=np.full((4, 4), NAN)),
        "empty image": _population(image=np.zeros((0, 0), np.uint8)),
        "source_seq 2^62": _population(source_seq=2 ** 62),
    }),
    S.TRACE_EVOLVER: (m.EvolverTrace(take_ns=1, generations=3), {
        "negative generations": m.EvolverTrace(generations=-5),
    }),
    S.SLAM_POSE: (_pose(), {
        "position 1e308": _pose((HUGE, 0, 0)),
        "NaN orientation": _pose(orientation=[NAN, 0, 0, 1]),
        "NaN covariance": _pose(cov=np.full((6, 6), NAN)),
    }),
    S.SLAM_MAP_TO_ODOM: (_transform(), {
        "NaN translation": _transform((NAN, 0, 0)),
        "translation 1e308": _transform((HUGE, 0, 0)),
        "zero rotation": _transform(rotation=np.zeros(4)),
    }),
    S.SLAM_MAP: (_keyframe(), {
        "keyframe at 1e308": _keyframe(position=np.array([HUGE, 0, 0])),
        "NaN points": _keyframe(points=np.full((4, 3), NAN, np.float32)),
        "negative keyframe stamp": _keyframe(stamp_ns=-1),
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

HOSTILE = [(stream, label, msg) for stream, (_, cases) in CASES.items() for label, msg in cases.items()]


def test_every_stream_has_hostile_cases():
    streams = {v for v in vars(S).values() if isinstance(v, S.Stream)}
    assert streams - set(CASES) == set()


@pytest.mark.parametrize("stream", list(CASES), ids=str)
def test_the_well_formed_message_of_each_stream_decodes(stream):
    good = CASES[stream][0]
    assert isinstance(m.decode(m.encode(good), stream.schema), stream.schema)


@pytest.mark.parametrize("stream,label,msg", HOSTILE, ids=[f"{s}:{label}" for s, label, _ in HOSTILE])
def test_hostile_message_is_rejected_with_a_one_line_reason(stream, label, msg):
    payload = msg if isinstance(msg, bytes) else m.encode(msg)
    with pytest.raises((m.InvalidValue, m.MissingField)) as err:
        m.decode(payload, stream.schema)
    reason = str(err.value)
    assert reason and "\n" not in reason and len(reason) < 200, reason


def test_a_restarted_publishers_seq_going_back_to_zero_is_accepted():
    for seq in (5, 0, 1):
        assert m.decode(m.encode(_with_header(_pose(), seq=seq)), m.PoseEstimate).header.seq == seq


def test_flies_far_out_in_the_camera_frame_are_kept():
    """depth_max = inf draws flies out to ~10⁶ × the nearest depth: farther than MAX_WORLD_M, still valid."""
    far = _population(np.full((3, 3), 5e6, np.float32))
    assert m.decode(m.encode(far)).positions[0, 0] == pytest.approx(5e6)
    assert m.MAX_WORLD_M < 5e6 < m.MAX_FLY_RANGE_M and math.isfinite(m.MAX_WORLD_M)


def test_fusion_rejects_and_counts_a_hostile_slam_pose_and_keeps_running(zenoh_port, tmp_path):
    """One slam/pose at 1e308 once poisoned fusion/pose for the rest of a run; now it never reaches it."""
    proc = start_module("services.fusion", port=zenoh_port, log_path=tmp_path / "fusion.log")
    try:
        with Node("tester", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
            heartbeats, poses = [], []
            node.subscribe("status/fusion", m.Heartbeat, heartbeats.append)
            node.subscribe("fusion/pose", m.PoseEstimate, poses.append)
            assert wait_until(lambda: heartbeats, 30), "fusion did not come up"
            raw = node.session.declare_publisher(node.key("slam/pose"))
            for label, msg in CASES[S.SLAM_POSE][1].items():
                raw.put(m.encode(msg))
            assert wait_until(lambda: heartbeats[-1].counters.get("slam_pose_rejected", 0) >= 3, 10), \
                heartbeats[-1].counters
            assert proc.poll() is None, "fusion exited on a hostile slam/pose"
            raw.put(m.encode(CASES[S.SLAM_POSE][0]))     # then a good one: fusion/pose comes, and stays sane
            assert wait_until(lambda: poses, 10), "fusion published no pose after a good slam/pose"
            assert all(np.all(np.abs(p.position) < 1e3) for p in poses)
    finally:
        assert stop(proc) == 0


def test_int64_nanosecond_stamps_inside_messages_are_accepted():
    now = time.time_ns()
    assert m.decode(m.encode(_keyframe(stamp_ns=now))).keyframes[0].stamp_ns == now
    assert m.decode(m.encode(_with_header(_pose(), stamp_ns=now))).header.stamp_ns == now


def test_a_step_that_raises_is_counted_and_logged_and_the_loop_carries_on(caplog):
    from types import SimpleNamespace
    import logging
    from common.bus import Counters
    from services.base import survive
    node, log = SimpleNamespace(counters=Counters()), logging.getLogger("flyslam.test")
    done = []
    for i in range(150):
        with survive(node, "frame", log):
            if i % 2:
                raise OverflowError("cannot convert float infinity to integer")
            done.append(i)
    assert len(done) == 75 and node.counters.get("frame_errors") == 75 and node.counters.get("step_errors") == 75
    warnings = [r for r in caplog.records if "frame failed" in r.getMessage()]
    assert len(warnings) == 5 and "OverflowError" in warnings[0].getMessage()
    with pytest.raises(SystemExit):
        with survive(node, "frame", log):
            raise SystemExit("flyslam: bad flag")


def test_the_planner_survives_and_counts_the_messages_that_once_crashed_it(zenoh_port, tmp_path):
    """A fusion/pose at 1e308, a NaN target, a NaN map->odom and a calibration of width 0 each ended
    the planner; now each is counted as rejected on its key and commands keep coming."""
    proc = start_module("services.planner", port=zenoh_port, log_path=tmp_path / "planner.log")
    try:
        with Node("tester", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
            heartbeats, commands = [], []
            node.subscribe("status/planner", m.Heartbeat, heartbeats.append)
            node.subscribe("planner/cmd_vel", m.VelocityCommand, commands.append)
            assert wait_until(lambda: heartbeats and commands, 30), "planner did not come up"
            hostile = {"fusion/pose": CASES[S.FUSION_POSE][1]["position 1e308"],
                       "planner/target": CASES[S.PLANNER_TARGET][1]["NaN x"],
                       "slam/map_to_odom": CASES[S.SLAM_MAP_TO_ODOM][1]["NaN translation"],
                       "stereo/calibration": CASES[S.STEREO_CALIBRATION][1]["zero width"]}
            for key, msg in hostile.items():
                node.session.put(node.key(key), m.encode(msg))
            names = [k.replace("/", "_") + "_rejected" for k in hostile]
            assert wait_until(lambda: all(heartbeats[-1].counters.get(n, 0) >= 1 for n in names), 10), \
                heartbeats[-1].counters
            n = len(commands)
            assert wait_until(lambda: len(commands) > n + 5, 10), "the planner stopped commanding"
            assert proc.poll() is None
    finally:
        assert stop(proc) == 0
