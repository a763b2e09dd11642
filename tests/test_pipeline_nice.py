"""Launch files can lower a service's priority (``nice``) so it yields the CPU to the pose pipeline."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from deploy.supervisor import LaunchError, load_launch, renice
from tests.helpers import ROOT, hub, wait_until, write_source_recording
from tests.test_supervisor import children_of, cmdline


def niceness(tid: int) -> int:
    return int((Path("/proc") / str(tid) / "stat").read_text().rsplit(")", 1)[1].split()[16])


def thread_niceness(pid: int) -> list[int]:
    return [niceness(int(t.name)) for t in (Path("/proc") / str(pid) / "task").iterdir()]


THREADED_CHILD = """
import threading, time
for _ in range(3):
    threading.Thread(target=time.sleep, args=(30,), daemon=True).start()
time.sleep(30)
"""


def test_renice_lowers_every_thread_of_a_running_service(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", THREADED_CHILD])
    try:
        assert wait_until(lambda: len(thread_niceness(proc.pid)) == 4, 10)
        assert renice(proc.pid, 7) == 4
        assert thread_niceness(proc.pid) == [7, 7, 7, 7]
    finally:
        proc.kill()
        proc.wait()


def test_supervisor_nices_a_service_once_it_is_up(tmp_path, zenoh_port):
    source = tmp_path / "source.mcap"
    write_source_recording(source, frames=30)
    launch = tmp_path / "launch.toml"
    launch.write_text(f"""
[[service]]
name = "replay"
module = "services.replay"
args = ["{source}", "--loop"]
nice = 9
""")
    sup = subprocess.Popen([sys.executable, "-m", "deploy.cli", "run", str(launch), "--out", str(tmp_path / "run"),
                            "--hub", hub(zenoh_port), "--duration", "60"], cwd=ROOT, stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    try:
        def replay_threads():
            kids = [p for p in children_of(sup.pid) if "services.replay" in cmdline(p)]
            return thread_niceness(kids[0]) if kids else []
        assert wait_until(lambda: replay_threads() and set(replay_threads()) == {9}, 30), replay_threads()
    finally:
        sup.send_signal(signal.SIGTERM)
        sup.communicate(timeout=60)


def test_launch_file_nice_is_read_and_checked(tmp_path):
    launch = tmp_path / "launch.toml"
    launch.write_text('[[service]]\nname = "bridge"\nmodule = "services.bridge"\nnice = 15\n')
    assert load_launch(launch).services[0].nice == 15
    launch.write_text('[[service]]\nname = "bridge"\nmodule = "services.bridge"\nnice = -5\n')
    with pytest.raises(LaunchError, match="nice must be an integer in 0..19"):
        load_launch(launch)


def test_demo_launch_nices_only_services_off_the_pose_path():
    demo = load_launch(Path(__file__).resolve().parent.parent / "deploy" / "launch" / "demo.toml")
    nice = {s.name: s.nice for s in demo.services}
    assert nice["bridge"] > 0 and nice["recorder"] > 0
    assert nice["evolver"] == nice["localiser"] == nice["fusion"] == nice["sim"] == 0
