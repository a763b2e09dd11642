"""A run's files survive its services' restarts and kills: a restarted bridge writes a new .rrd segment
(the run's summary lists both and views both), a SIGKILLed simulator still leaves its ground truth."""
from __future__ import annotations

import signal
import subprocess

import numpy as np

from common.trajectory import read_tum
from deploy.report import format_pipeline_summary, pipeline_summary
from tests.helpers import ROOT, start_module, stop, wait_until

RERUN = ROOT / ".venv" / "bin" / "rerun"


def test_a_restarted_bridge_writes_the_next_rrd_segment_and_the_summary_views_them_all(zenoh_port, tmp_path):
    rrd = tmp_path / "run.rrd"
    args = ("--rrd", str(rrd), "--grpc-port", "0", "--web-port", "0")
    first = start_module("services.bridge", *args, port=zenoh_port, log_path=tmp_path / "bridge.log")
    try:
        assert wait_until(lambda: rrd.exists() and rrd.stat().st_size > 0, 60), "the first bridge wrote nothing"
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait(10)
    size_before = rrd.stat().st_size
    second = start_module("services.bridge", *args, port=zenoh_port, log_path=tmp_path / "bridge.1.log")
    try:
        assert wait_until(lambda: (tmp_path / "run.1.rrd").exists(), 60)
    finally:
        assert stop(second, timeout=30) == 0
    assert rrd.stat().st_size == size_before, "the restarted bridge touched the first segment"
    verify = subprocess.run([str(RERUN), "rrd", "verify", str(tmp_path / "run.1.rrd")], capture_output=True,
                            text=True, timeout=60)
    assert verify.returncode == 0, verify.stdout + verify.stderr
    summary = pipeline_summary(tmp_path)
    assert summary["files"]["rerun"] == [str(rrd), str(tmp_path / "run.1.rrd")]
    assert f"rerun {rrd} {tmp_path / 'run.1.rrd'}" in format_pipeline_summary(summary)


def test_a_simulator_killed_with_sigkill_leaves_its_ground_truth(zenoh_port, tmp_path):
    truth = tmp_path / "truth.tum"
    sim = start_module("services.sim", "--width", "96", "--height", "72", "--fps", "10", "--truth-tum", str(truth),
                       port=zenoh_port, log_path=tmp_path / "sim.log")
    try:
        # the file appears after a second of simulation; wait for a second rewrite too
        assert wait_until(lambda: truth.exists() and len(read_tum(truth)[0]) >= 15, 90), \
            (tmp_path / "sim.log").read_text()[-2000:]
    finally:
        sim.send_signal(signal.SIGKILL)
        sim.wait(10)
    stamps, poses = read_tum(truth)
    assert len(stamps) >= 15 and np.all(np.diff(stamps) > 0) and np.all(np.isfinite(poses))
