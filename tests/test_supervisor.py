"""Supervisor: restarts a killed child, stops everything on SIGTERM, fails when a required service gives up."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

from common.recording import RecordingReader
from tests.helpers import ROOT, hub, wait_until, write_source_recording

LAUNCH = """
[run]
duration_s = {duration}

[[service]]
name = "recorder"
module = "services.recorder"
args = ["--out", "{{out}}/recording.mcap", "--keys", "stereo/frame", "--flush-s", "0.2"]
restart = "on-failure"
start_delay_s = 1.0

[[service]]
name = "replay"
module = "services.replay"
args = ["{{source}}", "--loop", "--rate", "1"]
restart = "on-failure"
max_restarts = 2
backoff_s = 0.2

[vars]
source = "{source}"
"""


def children_of(pid: int) -> list[int]:
    kids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                kids.append(int(entry.name))
    return kids


def cmdline(pid: int) -> str:
    try:
        return (Path("/proc") / str(pid) / "cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def alive(pid: int) -> bool:
    try:
        state = (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def start_supervisor(tmp_path, port, launch_text, *extra):
    launch = tmp_path / "launch.toml"
    launch.write_text(launch_text)
    return subprocess.Popen([sys.executable, "-m", "deploy.cli", "run", str(launch), "--out", str(tmp_path / "run"),
                             "--hub", hub(port), *extra], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)))


def test_killed_child_is_restarted_and_sigterm_leaves_no_child(tmp_path, zenoh_port):
    source = tmp_path / "source.mcap"
    write_source_recording(source, frames=60)
    sup = start_supervisor(tmp_path, zenoh_port, LAUNCH.format(duration=0, source=source))
    try:
        # Count a child once it has exec'd its module (between fork and exec it still looks like the supervisor).
        assert wait_until(lambda: sum("services." in cmdline(p) for p in children_of(sup.pid)) == 2, 20), \
            "both services should start"
        (replay_pid,) = [p for p in children_of(sup.pid) if "services.replay" in cmdline(p)]
        recording = tmp_path / "run" / "recording.mcap"
        assert wait_until(lambda: recording.exists() and recording.stat().st_size > 20_000, 30)
        os.kill(replay_pid, signal.SIGKILL)
        assert wait_until(lambda: any("services.replay" in cmdline(p) and p != replay_pid
                                      for p in children_of(sup.pid)), 20), "replay was not restarted"
        size_after_restart = recording.stat().st_size
        assert wait_until(lambda: recording.stat().st_size > size_after_restart + 20_000, 30), \
            "the pipeline should carry on: the recorder keeps receiving frames from the restarted replay"
        kids = children_of(sup.pid)
        sup.send_signal(signal.SIGTERM)
        out, _ = sup.communicate(timeout=60)
    finally:
        if sup.poll() is None:
            sup.kill()
    assert sup.returncode == 0, out
    assert not [k for k in kids if alive(k)], "children must not outlive the supervisor"
    assert "replay" in out and "restarts" in out
    reader = RecordingReader(tmp_path / "run" / "recording.mcap")
    frames = sum(1 for _ in reader.messages())
    assert reader.error is None, f"the recorder must finalise its file on SIGTERM: {reader.error}"
    assert frames >= 2   # frames from before and after the restart (the file grew after it)


def test_required_service_giving_up_fails_the_run(tmp_path, zenoh_port):
    launch = """
[[service]]
name = "broken"
module = "services.replay"
args = ["/nonexistent/recording.mcap"]
restart = "on-failure"
max_restarts = 1
backoff_s = 0.1
"""
    sup = start_supervisor(tmp_path, zenoh_port, launch, "--duration", "60")
    out, _ = sup.communicate(timeout=60)
    assert sup.returncode == 1
    assert "FAILED" in out and "broken" in out and "gave up after 1 restarts" in out


def test_bad_launch_file_gives_a_clear_error(tmp_path, zenoh_port):
    sup = start_supervisor(tmp_path, zenoh_port, '[[service]]\nname = "x"\nmodule = "m"\nrestart = "sometimes"\n')
    out, _ = sup.communicate(timeout=30)
    assert sup.returncode == 2 and "restart must be one of" in out and "launch.toml" in out
