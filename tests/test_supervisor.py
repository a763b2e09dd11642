"""Supervisor: restarts a killed child, stops everything on SIGTERM, fails when a required service gives up,
keeps run.json readable and leaves no process behind even when it is SIGKILLed.

Run as a module (``python -m tests.test_supervisor``) this file is a stand-in service that starts one
grandchild (``sleep``), as the bridge starts its web viewer, and writes the grandchild's pid to the run
folder."""
from __future__ import annotations

import json
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
        (recorder_pid,) = [p for p in children_of(sup.pid) if "services.recorder" in cmdline(p)]
        frames_before_kill = sum(1 for _ in RecordingReader(recording, segments=False).messages())
        os.kill(recorder_pid, signal.SIGKILL)
        segment = tmp_path / "run" / "recording.1.mcap"
        assert wait_until(lambda: segment.exists() and segment.stat().st_size > 20_000, 30), \
            "a restarted recorder should write a new segment"
        kids = children_of(sup.pid)
        sup.send_signal(signal.SIGTERM)
        out, _ = sup.communicate(timeout=60)
    finally:
        if sup.poll() is None:
            sup.kill()
    assert sup.returncode == 0, out
    assert not [k for k in kids if alive(k)], "children must not outlive the supervisor"
    assert "replay" in out and "restarts" in out
    first = RecordingReader(recording, segments=False)
    assert sum(1 for _ in first.messages()) >= frames_before_kill, "the restart must not overwrite the first segment"
    last = RecordingReader(segment, segments=False)
    assert sum(1 for _ in last.messages()) >= 2 and last.error is None, \
        f"the recorder must finalise its file on SIGTERM: {last.error}"
    whole = RecordingReader(recording)
    assert sum(1 for _ in whole.messages()) == sum(1 for _ in first.messages()) + sum(1 for _ in last.messages())
    record = json.loads((tmp_path / "run" / "run.json").read_text())
    assert record["state"] == "finished" and record["services"]["recorder"]["restarts"] == 1
    assert record["services"]["replay"]["restarts"] == 1


def test_required_service_giving_up_fails_the_run(tmp_path, zenoh_port):
    launch = """
[[service]]
name = "broken"
module = "services.no_such_module"
restart = "on-failure"
max_restarts = 1
backoff_s = 0.1
"""
    sup = start_supervisor(tmp_path, zenoh_port, launch, "--duration", "60")
    out, _ = sup.communicate(timeout=60)
    assert sup.returncode == 1
    assert "FAILED" in out and "broken" in out and "gave up after 1 restarts" in out
    assert "No module named services.no_such_module" in out.split("FAILED")[-1]


def test_a_service_given_a_bad_file_is_not_restarted_and_says_why(tmp_path, zenoh_port):
    launch = """
[[service]]
name = "broken"
module = "services.replay"
args = ["/nonexistent/recording.mcap"]
restart = "on-failure"
max_restarts = 3
backoff_s = 0.1
"""
    sup = start_supervisor(tmp_path, zenoh_port, launch, "--duration", "60")
    out, _ = sup.communicate(timeout=60)
    assert sup.returncode == 1
    assert "not restarted" in out and "restarting broken" not in out
    assert "broken: " in out.split("FAILED")[-1] and "no such recording" in out.split("FAILED")[-1]
    record = json.loads((tmp_path / "run" / "run.json").read_text())
    assert record["services"]["broken"]["restarts"] == 0 and "no such recording" in record["services"]["broken"]["error"]


def test_bad_launch_file_gives_a_clear_error(tmp_path, zenoh_port):
    sup = start_supervisor(tmp_path, zenoh_port, '[[service]]\nname = "x"\nmodule = "m"\nrestart = "sometimes"\n')
    out, _ = sup.communicate(timeout=30)
    assert sup.returncode == 2 and "restart must be one of" in out and "launch.toml" in out


SLEEPERS = """
[[service]]
name = "{name}"
module = "tests.test_supervisor"
restart = "never"
required = false
liveliness_timeout_s = 0
"""


def _grandchild(run: Path, pid: int) -> int | None:
    f = run / f"grandchild-{pid}"
    return int(f.read_text()) if f.exists() and f.read_text() else None


def test_sigkilled_supervisor_leaves_a_record_and_no_process(tmp_path, zenoh_port):
    """Children and grandchildren die within seconds of a kill -9 of the supervisor; run.json, written as
    the run started, says what happened. A service that dies takes its grandchildren with it."""
    run = tmp_path / "run"
    sup = start_supervisor(tmp_path, zenoh_port, '[run]\nreport = "pipeline"\n' +
                           "".join(SLEEPERS.format(name=n) for n in ("a", "b", "c")))
    try:
        def started() -> dict | None:
            try:
                record = json.loads((run / "run.json").read_text())
            except (OSError, ValueError):
                return None
            pids = {n: s["pid"] for n, s in record["services"].items() if s["state"] == "running"}
            return pids if len(pids) == 3 and all(_grandchild(run, p) for p in pids.values()) else None
        assert wait_until(started, 30), sup.stdout.read() if sup.poll() is not None else "services did not start"
        pids = started()
        watchdogs = [p for p in children_of(sup.pid) if "-I -c" in cmdline(p)]
        assert len(watchdogs) == 1
        grandchildren = {n: _grandchild(run, p) for n, p in pids.items()}
        assert all(alive(g) for g in grandchildren.values())

        os.kill(pids["a"], signal.SIGKILL)   # as a SIGKILLed bridge: its viewer must not live on
        assert wait_until(lambda: not alive(grandchildren["a"]), 5), "a dead service's grandchild survived"
        assert wait_until(lambda: json.loads((run / "run.json").read_text())["services"]["a"]["state"] == "failed", 5)

        os.kill(sup.pid, signal.SIGKILL)
        sup.wait(10)
        everyone = [pids["b"], pids["c"], grandchildren["b"], grandchildren["c"]]
        assert wait_until(lambda: not any(alive(p) for p in everyone), 6), \
            f"survivors of the supervisor: {[cmdline(p) for p in everyone if alive(p)]}"
        assert wait_until(lambda: not alive(watchdogs[0]), 30), "the watchdog should end after the report"
    finally:
        if sup.poll() is None:
            sup.kill()
        for f in run.glob("grandchild-*"):
            if (g := _grandchild(run, int(f.name.split("-")[1]))) and alive(g):
                os.kill(g, signal.SIGKILL)
    record = json.loads((run / "run.json").read_text())
    assert record["state"] == "supervisor-died" and "SIGKILL" in record["stop_reason"]
    assert record["services"]["a"]["state"] == "failed" and record["services"]["b"]["state"] == "killed"
    assert (run / "summary.json").exists(), "the watchdog should write the run's summary"
    assert json.loads((run / "summary.json").read_text())["out"] == str(run)


LATE = """
[[service]]
name = "{name}"
module = "tests.late_service"
args = ["--name", "{name}", "--delay", "{delay}"]
restart = "never"
wait_for_ready = {wait}
"""


def test_a_service_waiting_for_ready_starts_once_the_others_have_joined_the_bus(tmp_path, zenoh_port):
    """A replay or a video started before the evolver has loaded its kernels plays its first seconds to
    nobody; with wait_for_ready the source starts only once every service before it is up."""
    run = tmp_path / "run"
    launch = '[run]\nduration_s = 12\n' + LATE.format(name="slow", delay=2.5, wait="false") + \
        LATE.format(name="quick", delay=0.0, wait="false") + LATE.format(name="source", delay=0.0, wait="true")
    sup = start_supervisor(tmp_path, zenoh_port, launch)
    try:
        assert wait_until(lambda: (run / "source.up").exists(), 30), sup.stdout.read() if sup.poll() is not None else ""
    finally:
        sup.send_signal(signal.SIGTERM)
        out, _ = sup.communicate(timeout=30)
    times = {f.name: float(f.read_text()) for f in run.glob("*.started")} | \
        {f.name: float(f.read_text()) for f in run.glob("*.up")}
    assert times["quick.started"] - times["slow.started"] < 1.0        # no wait: started one after the other
    assert times["source.started"] >= times["slow.up"], out             # the source waited for the slow one
    assert "starting source: the services before it are up" in out


if __name__ == "__main__":
    import time
    grandchild = subprocess.Popen(["sleep", "600"])
    (Path(os.environ["FLYSLAM_RUN_DIR"]) / f"grandchild-{os.getpid()}").write_text(str(grandchild.pid))
    time.sleep(600)


def test_paths_given_to_a_launch_are_relative_to_where_flyslam_run_was_started(tmp_path, zenoh_port):
    """`flyslam run deploy/launch/kitti.toml --var recording=k00.mcap`, typed in the folder that holds
    k00.mcap: the services resolve it there, not in the repository, and the run's folder (runs/<date>)
    is made there.  A package of the user's folder named like one of flyslam's (common/) does not shadow it."""
    work = tmp_path / "work"
    (work / "common").mkdir(parents=True)
    (work / "common" / "__init__.py").write_text("raise ImportError('the user folder shadowed flyslam')\n")
    write_source_recording(work / "source.mcap", frames=20)
    launch = """
[[service]]
name = "recorder"
module = "services.recorder"
args = ["--out", "{out}/recording.mcap", "--keys", "stereo/frame", "--flush-s", "0.2"]
start_delay_s = 1.0

[[service]]
name = "replay"
module = "services.replay"
args = ["{source}", "--rate", "4"]
ends_run = true

[vars]
source = "nowhere.mcap"
"""
    (work / "launch.toml").write_text(launch)
    # -P: as the installed `flyslam` script, which does not put the current folder on sys.path either
    done = subprocess.run([sys.executable, "-P", "-m", "deploy.cli", "run", "launch.toml", "--var",
                           "source=source.mcap", "--hub", hub(zenoh_port), "--duration", "60"], cwd=work,
                          capture_output=True, text=True, timeout=120, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert done.returncode == 0, done.stdout + done.stderr
    (run,) = (work / "runs").iterdir()          # the default run folder is in the user's folder too
    frames = sum(1 for _ in RecordingReader(run / "recording.mcap").messages())
    assert frames >= 15, done.stdout


def test_a_second_run_on_a_bus_in_use_refuses_instead_of_mixing_the_two(tmp_path, zenoh_port):
    """Two `flyslam run` at once on one machine shared the bus: each evolver took the other's frames and
    both runs' results were garbage, silently.  The second now refuses in one line and starts nothing;
    with its own --robot it may share the bus (several robots on one network)."""
    source = tmp_path / "source.mcap"
    write_source_recording(source, frames=60)
    first = start_supervisor(tmp_path, zenoh_port, LAUNCH.format(duration=0, source=source))
    try:
        recording = tmp_path / "run" / "recording.mcap"     # the recorder is on the bus, recording the replay
        assert wait_until(lambda: recording.exists() and recording.stat().st_size > 20_000, 30)
        second_out = tmp_path / "second"
        argv = [sys.executable, "-m", "deploy.cli", "run", str(tmp_path / "launch.toml"), "--out", str(second_out),
                "--hub", hub(zenoh_port), "--duration", "5"]
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        second = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=60, env=env)
        assert second.returncode == 2, second.stdout + second.stderr
        err = second.stderr.strip()
        assert err.count("\n") == 0 and "rig" in err and "--robot" in err and "supervisor" in err, err
        assert not (second_out / "run.json").exists()
        other = subprocess.run(argv + ["--robot", "other"], cwd=ROOT, capture_output=True, text=True, timeout=60,
                               env=env)
        assert other.returncode == 0, other.stdout + other.stderr
        first.send_signal(signal.SIGTERM)
        first.communicate(timeout=60)
    finally:
        if first.poll() is None:
            first.kill()
    assert first.returncode == 0
