"""Hostile messages on a valid schema, on every stream a service reads, are rejected at decode with a
one-line reason (an InvalidValue or MissingField, so every service's DecodeError counting applies),
while the same stream's well-formed message still decodes."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest

from common import messages as m
from common import streams as S
from common.bus import BusOptions, Node
from tests.helpers import hub, start_module, stop, wait_until
from tests.hostile_cases import CASES, HOSTILE, keyframe_map, pose, population, with_header


def test_every_stream_has_hostile_cases():
    streams = {v for v in vars(S).values() if isinstance(v, S.Stream)}
    assert streams - set(CASES) == set()


@pytest.mark.parametrize("stream", list(CASES), ids=str)
def test_the_well_formed_message_of_each_stream_decodes(stream):
    good = CASES[stream][0]
    assert isinstance(m.decode(m.encode(good), stream.schema), stream.schema)


@pytest.mark.parametrize("stream,label,msg", HOSTILE, ids=[f"{s}:{label}" for s, label, _ in HOSTILE])
def test_hostile_message_is_rejected_with_a_one_line_reason(stream, label, msg):
    payload, side = (msg, None) if isinstance(msg, bytes) else (m.encode(msg), m.encode_side(msg))
    with pytest.raises((m.InvalidValue, m.MissingField)) as err:
        m.decode(payload, stream.schema, side)     # side: the fields the bus sends as the attachment
    reason = str(err.value)
    assert reason and "\n" not in reason and len(reason) < 200, reason


def test_a_restarted_publishers_seq_going_back_to_zero_is_accepted():
    for seq in (5, 0, 1):
        assert m.decode(m.encode(with_header(pose(), seq=seq)), m.PoseEstimate).header.seq == seq


def test_flies_far_out_in_the_camera_frame_are_kept():
    """depth_max = inf draws flies out to ~10⁶ × the nearest depth: farther than MAX_WORLD_M, still valid."""
    far = population(np.full((3, 3), 5e6, np.float32))
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
    assert m.decode(m.encode(keyframe_map(stamp_ns=now))).keyframes[0].stamp_ns == now
    assert m.decode(m.encode(with_header(pose(), stamp_ns=now))).header.stamp_ns == now


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


def test_the_bridge_counts_a_message_it_cannot_view_and_views_the_rest(caplog):
    """A message the viewer mapping chokes on (a cv2.error once ended the bridge) costs that message only."""
    from types import SimpleNamespace

    import cv2

    from common.bus import Counters
    from services.bridge import log_batch

    class Viz:
        def __init__(self):
            self.viewed = []

        def handle(self, stream, msg):
            if stream == "stereo/frame":
                raise cv2.error("OpenCV(4) resize: !ssize.empty()")
            self.viewed.append(msg)

    node, viz = SimpleNamespace(counters=Counters(), progress=0), Viz()
    log_batch(node, viz, [("slam/pose", 1), ("stereo/frame", 2), ("fusion/pose", 3)])
    assert viz.viewed == [1, 3] and node.progress == 2 and node.counters.get("view_errors") == 1
    assert any("view failed on stereo/frame" in r.getMessage() for r in caplog.records)
