"""The simulator as a live source on the bus: calibration (latched), frames, odometry, sonar, truth and
target arrive from a separate process with consistent stamps; in closed loop it obeys velocity commands."""
from __future__ import annotations

import time

import numpy as np

from common import messages as m
from common.bus import BusOptions, Node
from common.images import frame_images
from tests.helpers import hub, start_module, stop, wait_until


def test_simulator_publishes_every_source_stream(tmp_path, zenoh_port):
    proc = start_module("services.sim", "--width", "160", "--height", "120", "--fps", "10", "--duration", "60",
                        port=zenoh_port, log_path=tmp_path / "sim.log")
    got: dict[str, list] = {k: [] for k in ("frame", "odom", "sonar", "truth")}
    try:
        with Node("listener", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
            node.subscribe("stereo/frame", m.StereoFrame, got["frame"].append)
            node.subscribe("odom/wheels", m.WheelOdometry, got["odom"].append)
            node.subscribe("sonar/scan", m.SonarScan, got["sonar"].append)
            node.subscribe("truth/pose", m.PoseEstimate, got["truth"].append)
            assert wait_until(lambda: len(got["frame"]) >= 8, 60), (tmp_path / "sim.log").read_text()[-2000:]
            calib = node.query_latest("stereo/calibration", m.StereoCalibrationMsg, timeout=2.0)
            target = node.query_latest("planner/target", m.Target, timeout=2.0)
    finally:
        assert stop(proc) == 0
    assert calib is not None and (calib.width, calib.height) == (160, 120)
    assert target is not None and target.header.frame_id == "map"
    left, right = frame_images(got["frame"][-1])
    assert left.shape == (120, 160, 3) and not np.array_equal(left, right)
    seqs = [f.header.seq for f in got["frame"]]
    assert seqs == sorted(seqs)
    # Odometry runs at 50 Hz, sonar at 10 Hz, frames at 10 Hz, all on one clock.
    assert len(got["odom"]) > 3 * len(got["frame"]) and len(got["sonar"]) >= len(got["frame"]) - 2
    assert {t.source_seq for t in got["truth"]} >= set(seqs[:5])
    stamps = np.array([f.header.stamp_ns for f in got["frame"]])
    assert np.allclose(np.diff(stamps), 1e8, rtol=0.01)


def test_closed_loop_simulator_follows_velocity_commands(tmp_path, zenoh_port):
    proc = start_module("services.sim", "--scenario", "obstacles_boxes", "--width", "96", "--height", "72",
                        "--fps", "5", "--closed-loop", port=zenoh_port, log_path=tmp_path / "sim.log")
    truth: list = []
    try:
        with Node("driver", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
            node.subscribe("truth/pose", m.PoseEstimate, truth.append)
            cmd = node.publisher("planner/cmd_vel", reliable=True)
            assert wait_until(lambda: truth, 60)
            start = truth[-1].position.copy()
            t_end = time.monotonic() + 3.0
            while time.monotonic() < t_end:
                cmd.publish(m.VelocityCommand(linear_mps=0.3, angular_radps=0.0))
                time.sleep(0.05)
            moved = truth[-1].position - start
            time.sleep(1.5)   # commands stop: the robot must stop too (command timeout)
            still = truth[-1].position.copy()
            time.sleep(1.0)
            after = truth[-1].position
    finally:
        assert stop(proc) == 0
    assert 0.4 < np.linalg.norm(moved[:2]) < 1.2, moved
    assert np.linalg.norm(after - still) < 0.02
