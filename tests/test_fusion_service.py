"""The fusion service as a real process on a unique port: flags, corrections, sonar, restart recovery."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from common.bus import BusOptions, Node
from common.fusion.planar import compose, from_transform, to_transform
from common.geometry import pose_from_transform
from common.messages import (FlyPopulation, Heartbeat, PoseEstimate, SonarScan, TransformMsg, WheelOdometry, header,
                             transform_of)
from tests.helpers import hub, start_module, stop, wait_until
from tests.test_fusion_odometry import B, R, TPR, ticks_for

PERIOD_NS = 20_000_000


class Inbox:
    """Messages of one stream, collected on Zenoh's thread."""

    def __init__(self, node: Node, stream: str, schema):
        self.items: list = []
        self._lock = threading.Lock()
        node.subscribe(stream, schema, self._put)

    def _put(self, msg) -> None:
        with self._lock:
            self.items.append(msg)

    def last(self):
        with self._lock:
            return self.items[-1] if self.items else None

    def find(self, predicate):
        with self._lock:
            return next((m for m in reversed(self.items) if predicate(m)), None)


class LatchKeeper:
    """Stands in for the bus's memory of latched streams (a recorder or a Zenoh storage in a deployment):
    keeps the last payload of each stream and answers queries with it, after its publisher has died."""

    def __init__(self, node: Node, streams):
        self._last: dict[str, bytes] = {}
        for s in streams:
            key = node.key(s)
            node.subscribe(s, None, lambda k, p, key=key: self._last.__setitem__(key, p), raw=True)
            node.session.declare_queryable(key, lambda q, key=key: self._answer(q, key), complete=True)

    def _answer(self, query, key) -> None:
        if key in self._last:
            query.reply(key, self._last[key])


class Wheels:
    """A differential-drive robot's encoder stream with synthetic 50 Hz stamps."""

    def __init__(self, node: Node):
        self.pub = node.publisher("odom/wheels", reliable=True)
        self.i, self.left, self.right = 0, 0.0, 0.0

    def msg(self, **overrides) -> WheelOdometry:
        m = WheelOdometry(ticks=np.array([ticks_for(self.left), ticks_for(self.right)], np.int64), ticks_per_rev=TPR,
                          wheel_radius_m=R, track_width_m=B, header=header(self.i + 1, 10**9 + self.i * PERIOD_NS,
                                                                           "base_link"))
        for k, v in overrides.items():
            setattr(m, k, v)
        return m

    def send(self, dl: float = 0.0, dr: float = 0.0, **overrides) -> WheelOdometry:
        self.i += 1
        self.left += dl
        self.right += dr
        m = self.msg(**overrides)
        self.pub.publish(m)
        return m

    def until_answered(self, inbox: Inbox, timeout: float = 30.0) -> None:
        """Send stationary readings until the service answers one (it is up and subscribed)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            seq = self.send().header.seq
            if wait_until(lambda: inbox.find(lambda m: m.source_seq == seq) is not None, 0.3, 0.02):
                return
        raise AssertionError("the fusion service never answered")

    def drive(self, n: int, step_m: float = 0.01) -> int:
        for _ in range(n):
            last = self.send(step_m, step_m)
        return last.header.seq


def answered(inbox: Inbox, seq: int, timeout: float = 10.0):
    assert wait_until(lambda: inbox.find(lambda m: m.source_seq == seq) is not None, timeout), f"no answer to {seq}"
    return inbox.find(lambda m: m.source_seq == seq)


def test_flags_corrections_and_sonar_through_the_service(zenoh_port, tmp_path):
    with Node("fusion_test", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
        odom, pose = Inbox(node, "fusion/odom", PoseEstimate), Inbox(node, "fusion/pose", PoseEstimate)
        status = Inbox(node, "status/fusion", Heartbeat)
        sonar, points = Inbox(node, "fusion/sonar", SonarScan), Inbox(node, "fusion/sonar_points", FlyPopulation)
        wheels = Wheels(node)
        proc = start_module("services.fusion", port=zenoh_port, log_path=tmp_path / "fusion.log")
        try:
            wheels.until_answered(odom)
            first = wheels.i + 1
            good = answered(odom, wheels.drive(50))
            assert good.status == "ok" and good.position[0] == pytest.approx(0.5, abs=1e-3)
            # One second of 50 Hz readings comes out at --publish-hz (30), the newest one included (a few
            # more when a loaded machine pauses the burst long enough for a held output to be flushed).
            assert 28 <= len([o for o in odom.items if o.source_seq >= first]) <= 40
            assert answered(pose, good.source_seq).status == "odometry only"

            # A NaN, an out-of-order reading and an encoder jump: flagged, the pose does not move.
            nan = answered(odom, wheels.send(0.01, 0.01, wheel_speeds=np.array([np.nan, 1.0])).header.seq)
            old = answered(odom, wheels.send(header=header(900, 10**9, "base_link")).header.seq)
            jump = answered(odom, wheels.send(ticks=np.array([10**7, 10**7], np.int64)).header.seq)
            assert nan.status.startswith("flagged: non-finite")
            assert old.status.startswith("flagged: time went backwards")
            assert jump.status.startswith("flagged: impossible wheel speed")
            for flagged in (nan, old, jump):
                np.testing.assert_allclose(flagged.position, good.position)
            assert wait_until(lambda: (status.last() is not None and
                                       status.last().counters.get("odometry_flagged") == 3 and
                                       status.last().counters.get("odometry_flagged_jump") == 1), 10), \
                status.last() and status.last().counters
            after = answered(odom, wheels.drive(1))
            assert after.status == "ok" and after.position[0] == pytest.approx(0.52, abs=1e-3)

            # The localiser says map→odom is (1, 2, 90°): fusion/pose follows, fusion/odom does not.
            m2o = np.array([1.0, 2.0, np.pi / 2])
            t, q = pose_from_transform(to_transform(m2o))
            node.publisher("slam/map_to_odom").publish(TransformMsg(
                child_frame_id="odom", translation=t, rotation=q, header=header(0, after.header.stamp_ns, "map")))
            assert wait_until(lambda: status.last().counters.get("map_to_odom_fused") == 1, 10)
            seq = wheels.drive(10)
            o, p = answered(odom, seq), answered(pose, seq)
            assert p.status == "ok" and p.header.frame_id == "map" and o.header.frame_id == "odom"
            np.testing.assert_allclose(from_transform(transform_of(p)), compose(m2o, from_transform(transform_of(o))),
                                       atol=1e-6)
            assert o.position[0] == pytest.approx(0.62, abs=1e-3)

            # Sonar: republished in base_link, echoes as obstacle points.
            scan = SonarScan(transducer_poses=np.array([[0.2, 0.0, 0.0], [0.0, 0.2, np.pi / 2]]),
                             ranges=np.array([1.0, np.nan], np.float32), beam_width_rad=0.4, min_range_m=0.1,
                             max_range_m=5.0, header=header(0, 5, "base_link"))
            node.publisher("sonar/scan").publish(scan)
            assert wait_until(lambda: points.last() is not None and sonar.last() is not None, 10)
            assert sonar.last().header.frame_id == "base_link"
            pts = points.last()
            assert pts.header.frame_id == "base_link" and len(pts.positions) == 5
            np.testing.assert_allclose(pts.positions[2], [1.2, 0.0, 0.25], atol=1e-5)
        finally:
            assert stop(proc) == 0


def test_restarted_service_recovers_its_pose_from_the_bus(zenoh_port, tmp_path):
    with Node("fusion_test", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
        LatchKeeper(node, ["fusion/odom", "fusion/pose"])
        odom = Inbox(node, "fusion/odom", PoseEstimate)
        wheels = Wheels(node)
        proc = start_module("services.fusion", port=zenoh_port, log_path=tmp_path / "fusion1.log")
        try:
            wheels.until_answered(odom)
            wheels.send(0.0, 0.1)                              # turn a little: yaw must survive too
            first = answered(odom, wheels.drive(100))
        finally:
            assert stop(proc) == 0
        assert first.position[0] > 0.9
        before = from_transform(transform_of(first))
        proc = start_module("services.fusion", port=zenoh_port, log_path=tmp_path / "fusion2.log")
        try:
            wheels.until_answered(odom)
            resumed = odom.last()
            np.testing.assert_allclose(from_transform(transform_of(resumed)), before, atol=1e-9)
            assert resumed.covariance[0, 0] >= first.covariance[0, 0] > 0
            final = answered(odom, wheels.drive(50))
        finally:
            assert stop(proc) == 0
        expected = compose(before, [0.5, 0.0, 0.0])
        np.testing.assert_allclose(from_transform(transform_of(final)), expected, atol=2e-3)
