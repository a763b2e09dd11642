"""The main job ends itself: in closed loop the simulator exits 0 once the planner has said 'target
reached' for --end-on-target seconds, and still writes its ground truth; any other command keeps it going."""
from __future__ import annotations

import time

from common import messages as m
from common.bus import BusOptions, Node
from common.trajectory import read_tum
from tests.helpers import hub, start_module, stop, wait_until


def test_simulator_ends_after_the_planner_reports_the_target_reached(tmp_path, zenoh_port):
    tum = tmp_path / "truth.tum"
    proc = start_module("services.sim", "--scenario", "obstacles_boxes", "--width", "96", "--height", "72",
                        "--fps", "5", "--closed-loop", "--end-on-target", "1.0", "--truth-tum", str(tum),
                        port=zenoh_port, log_path=tmp_path / "sim.log")
    truth: list = []
    try:
        with Node("planner-stand-in", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
            node.subscribe("truth/pose", m.PoseEstimate, truth.append)
            cmd = node.publisher("planner/cmd_vel", reliable=True)
            assert wait_until(lambda: truth, 60), (tmp_path / "sim.log").read_text()[-2000:]
            t_end = time.monotonic() + 2.0          # other stop reasons do not end the run
            while time.monotonic() < t_end:
                cmd.publish(m.VelocityCommand(stop=True, reason="no path"))
                time.sleep(0.05)
            assert proc.poll() is None
            t_end = time.monotonic() + 30.0
            while proc.poll() is None and time.monotonic() < t_end:
                cmd.publish(m.VelocityCommand(stop=True, reason="target reached"))
                time.sleep(0.05)
            rc = proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            stop(proc)
    assert rc == 0, (tmp_path / "sim.log").read_text()[-2000:]
    assert "target reached" in (tmp_path / "sim.log").read_text()
    stamps, poses = read_tum(tum)
    assert len(stamps) >= len(truth) - 1 > 0
