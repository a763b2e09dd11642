"""Break-it figures for files, flags and restarts (figures, not pass/fail).

- File and flag cases (:func:`file_and_flag_cases`): each a ``flyslam`` command given one bad launch
  file, scenario, calibration or bus option, run as its own process. ``tracebacks`` counts the cases
  that printed a Python traceback; ``one_line_errors`` those that exited 2 with a single stderr line
  naming what was wrong.
- Recorder restarts: a publisher sends odometry-sized messages at ``--rate`` Hz while the recorder,
  writing to one ``--out``, is killed with SIGKILL ``--kills`` times and started again.
  ``recording_kept_fraction``: messages read back from the whole recording (every segment) at the end
  over the messages each recorder had written when it died (each segment read alone right after);
  ``recording_coverage``: messages read back over messages published (restart gaps included).
- Supervisor kill: a supervised recorder and bridge (with its ``rerun --serve-web`` child); after
  ``kill -9`` of the supervisor, ``orphans_after_supervisor_kill`` counts its processes (children and
  grandchildren) alive 5 s later, and ``run_json_state`` is what its run.json says.
- Pipeline (bench/faults_pipeline.py): the demo's services but the simulator, fed a simulated clip:
  a ``--flood``× flood for ``--phase-s`` after as long at the nominal rate (``flood_rss_growth_mb`` and
  ``nominal_rss_growth_mb`` per service, the rate the publishers really reached), ``--hostile``
  hostile valid-schema messages (``hostile_crashes``), and a localiser SIGKILL
  (``pose_gap_after_restart_s``, ``trajectory_kept_fraction``). ``--phase-s 0`` skips it.
- Secured deployment (bench/faults_secured.py): the demo over mutual TLS with access control
  (``secured_poses``), attacked from another network namespace (``attacker_commands_delivered``;
  skipped with the reason where ``ip netns`` is not permitted). ``--secured-s 0`` skips it.

``--json``: one JSON object as the last stdout line.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from common import messages as m  # noqa: E402

from common.bus import BusOptions, Node  # noqa: E402
from common.recording import RecordingReader, segments_of  # noqa: E402

from bench.faults_pipeline import pipeline_faults  # noqa: E402
from bench.faults_secured import secured_run  # noqa: E402
from tests.hostile_cases import hostile_payloads  # noqa: E402

ENV = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
FLYSLAM = [sys.executable, "-m", "deploy.cli"]
GOOD_SERVICE = '[[service]]\nname = "r"\nmodule = "services.recorder"\nargs = ["--out", "{out}/x.mcap"]\n'
ZERO_BASELINE_YAML = """%YAML:1.0
---
image_width: 640
image_height: 480
units_m: 1.0
K1: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [500., 0., 320., 0., 500., 240., 0., 0., 1.]
D1: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [0., 0., 0., 0., 0.]
K2: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [500., 0., 320., 0., 500., 240., 0., 0., 1.]
D2: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [0., 0., 0., 0., 0.]
R: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [1., 0., 0., 0., 1., 0., 0., 0., 1.]
T: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [0., 0., 0.]
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def file_and_flag_cases(tmp: Path) -> list[tuple[str, list[str], str]]:
    """(case, flyslam argv, text the one-line error must contain); the files are written under ``tmp``."""
    def launch(name: str, text: str) -> str:
        path = tmp / f"{name}.toml"
        path.write_text(text)
        return str(path)

    def run(launch_path: str) -> list[str]:   # bounded: a launch file wrongly accepted ends its run soon
        return ["run", launch_path, "--duration", "2", "--out", str(tmp / "run")]

    (tmp / "latin1.toml").write_bytes('[run]\nduration_s = 1 # café\n'.encode("latin-1"))
    (tmp / "a_directory.toml").mkdir(exist_ok=True)
    (tmp / "empty_scenario.toml").write_text("")
    (tmp / "zero_baseline.yaml").write_text(ZERO_BASELINE_YAML)
    (tmp / "malformed.json5").write_text("{ mode: 'peer', ")
    record = ["record", "--out", str(tmp / "never.mcap")]
    return [
        ("launch duration_s = 'abc'", run(launch("duration", '[run]\nduration_s = "abc"\n' + GOOD_SERVICE)),
         "duration_s must be a number"),
        ("launch service = 5", run(launch("service", "service = 5\n")), "service must be an array of tables"),
        ("launch max_restarts = 'x'", run(launch("restarts", GOOD_SERVICE + 'max_restarts = "x"\n')),
         "max_restarts must be an integer"),
        ("launch name = 5", run(launch("name", GOOD_SERVICE.replace('name = "r"', "name = 5"))),
         "name must be a string"),
        ("launch not UTF-8", run(str(tmp / "latin1.toml")), "not UTF-8"),
        ("launch is a directory", run(str(tmp / "a_directory.toml")), "is a directory"),
        ("empty scenario", ["simulate", "--scenario", str(tmp / "empty_scenario.toml"), "--out",
                            str(tmp / "never.mcap")], "empty scenario"),
        ("calibration with zero baseline", ["camera", "--calibration", str(tmp / "zero_baseline.yaml"),
                                            "--left", "0", "--right", "1"], "baseline must be non-zero"),
        ("--config missing", [*record, "--config", str(tmp / "missing.json5")], "not found"),
        ("--config malformed", [*record, "--config", str(tmp / "malformed.json5")], "not a valid Zenoh"),
        ("--config is a directory", [*record, "--config", str(tmp)], "is a directory"),
        ("--connect garbage", [*record, "--connect", "garbage"], "--connect 'garbage'"),
        ("--cfg nocolon", [*record, "--cfg", "nocolon"], "--cfg expects KEY:JSON5"),
        ("--cfg unknown key", [*record, "--cfg", "no/such/key:true"], "unknown key"),
        ("--keys not a key expression", [*record, "--keys", "odom/"], "not a Zenoh key expression"),
        ("run --connect garbage", [*run(launch("good", GOOD_SERVICE)), "--connect", "garbage"], "--connect"),
        ("info on an empty folder", ["info", str(tmp / "a_directory.toml")], "no .mcap recording"),
    ]


def run_file_and_flag_cases(tmp: Path) -> tuple[int, int, list[dict]]:
    rows, tracebacks, one_line = [], 0, 0
    for name, argv, expected in file_and_flag_cases(tmp):
        proc = subprocess.Popen([*FLYSLAM, *argv], cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, start_new_session=True)
        try:
            out, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:   # accepted the bad input and kept running
            os.killpg(proc.pid, signal.SIGKILL)
            out, err = proc.communicate()
        lines = [ln for ln in err.splitlines() if ln.strip()]
        traceback = "Traceback (most recent call last)" in err + out
        good = proc.returncode == 2 and len(lines) == 1 and expected in lines[0] and not traceback
        tracebacks += traceback
        one_line += good
        rows.append({"case": name, "exit": proc.returncode, "traceback": traceback, "one_line": good,
                     "stderr": lines[-1] if lines else ""})
    return tracebacks, one_line, rows


def start_recorder(out: Path, port: int, log) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "services.recorder", "--out", str(out), "--keys", "odom/*",
                             "--flush-s", "0.2", "--hub", f"tcp/127.0.0.1:{port}"], cwd=ROOT, env=ENV,
                            stdout=log, stderr=subprocess.STDOUT)


def recorder_restarts(tmp: Path, kills: int, rate_hz: float, lifetime_s: float) -> dict:
    port, out = free_port(), tmp / "restarts" / "recording.mcap"
    out.parent.mkdir()
    written_per_life, published = [], 0
    with open(tmp / "recorder.log", "wb") as log, \
            Node("faults-feeder", BusOptions(hub=f"tcp/127.0.0.1:{port}"), handle_signals=False) as node:
        pub = node.publisher("odom/wheels", reliable=True)
        for life in range(kills + 1):
            before = set(segments_of(out))
            rec = start_recorder(out, port, log)
            time.sleep(1.5)   # session up and subscribed
            t_end = time.monotonic() + lifetime_s
            while time.monotonic() < t_end:
                published += 1
                pub.put_raw(m.encode(m.WheelOdometry(wheel_speeds=np.ones(2),
                                                     header=m.header(published, time.time_ns(), m.BASE_LINK))))
                time.sleep(1 / rate_hz)
            if life < kills:
                rec.send_signal(signal.SIGKILL)
            else:
                rec.send_signal(signal.SIGTERM)
            rec.wait(20)
            (segment,) = set(segments_of(out)) - before
            written_per_life.append(sum(1 for _ in RecordingReader(segment, segments=False).messages()))
    read_back = sum(1 for _ in RecordingReader(out).messages())
    return {"recorder_kills": kills, "segments": len(segments_of(out)), "messages_published": published,
            "messages_written_per_recorder": written_per_life, "messages_read_back": read_back,
            "recording_kept_fraction": round(read_back / max(sum(written_per_life), 1), 4),
            "recording_coverage": round(read_back / max(published, 1), 4)}


def process_tree(pid: int) -> set[int]:
    """``pid``'s descendants, by parent links in /proc (processes in other sessions included)."""
    parents = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parents[int(entry.name)] = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                pass
    tree, frontier = set(), {pid}
    while frontier:
        frontier = {p for p, pp in parents.items() if pp in frontier} - tree
        tree |= frontier
    return tree


def alive(pid: int) -> bool:
    try:
        return (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def supervisor_kill(tmp: Path) -> dict:
    run = tmp / "supervised"
    launch = tmp / "kill.toml"
    launch.write_text(f"""
[[service]]
name = "recorder"
module = "services.recorder"
args = ["--out", "{{out}}/recording.mcap"]
[[service]]
name = "bridge"
module = "services.bridge"
args = ["--rrd", "{{out}}/run.rrd", "--grpc-port", "{free_port()}", "--web-port", "{free_port()}"]
required = false
""")
    sup = subprocess.Popen([*FLYSLAM, "run", str(launch), "--out", str(run), "--hub", f"tcp/127.0.0.1:{free_port()}"],
                           cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline, tree = time.monotonic() + 60, set()
    while time.monotonic() < deadline:   # supervisor's children, the bridge's viewer, the watchdog
        tree = process_tree(sup.pid)
        if any("rerun" in _cmdline(p) and "--serve-web" in _cmdline(p) for p in tree):
            break
        time.sleep(0.2)
    viewer_started = any("--serve-web" in _cmdline(p) for p in tree)
    time.sleep(1.0)
    tree = process_tree(sup.pid)
    os.kill(sup.pid, signal.SIGKILL)
    sup.wait()
    time.sleep(5.0)
    survivors = [p for p in tree if alive(p)]
    for p in survivors:
        os.kill(p, signal.SIGKILL)
    try:
        state = json.loads((run / "run.json").read_text()).get("state")
    except (OSError, ValueError) as e:
        state = f"unreadable ({e})"
    return {"supervised_processes": len(tree), "viewer_started": viewer_started,
            "orphans_after_supervisor_kill": len(survivors), "run_json_state": state}


def _cmdline(pid: int) -> str:
    try:
        return (Path("/proc") / str(pid) / "cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--kills", type=int, default=2, help="recorder SIGKILLs (then restarts)")
    p.add_argument("--rate", type=float, default=200.0, help="messages per second published")
    p.add_argument("--lifetime", type=float, default=3.0, help="seconds each recorder records before it is killed")
    p.add_argument("--phase-s", type=float, default=60.0,
                   help="seconds at the nominal rate, then as long flooded (0: no pipeline faults)")
    p.add_argument("--warmup-s", type=float, default=20.0, help="seconds at the nominal rate before measuring")
    p.add_argument("--flood", type=float, default=10.0, help="flood rate as a multiple of the nominal rate")
    p.add_argument("--flood-publishers", type=int, default=2, help="publisher processes for the flood")
    p.add_argument("--hostile", type=int, default=10_000, help="hostile valid-schema messages sent to the pipeline")
    p.add_argument("--secured-s", type=float, default=60.0, help="seconds of the secured demo run (0: skip it)")
    p.add_argument("--json", action="store_true", help="one JSON object as the last stdout line")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="flyslam-faults-") as d:
        tmp = Path(d)
        t0 = time.monotonic()
        tracebacks, one_line, rows = run_file_and_flag_cases(tmp)
        for r in rows:
            print(f"  {r['case']:<32} exit {r['exit']}  {'TRACEBACK' if r['traceback'] else 'one line' if r['one_line'] else 'UNCLEAR'}"
                  f"  {r['stderr'][:110]}")
        result = {"file_and_flag_cases": len(rows), "tracebacks": tracebacks, "one_line_errors": one_line}
        result.update(recorder_restarts(tmp, args.kills, args.rate, args.lifetime))
        result.update(supervisor_kill(tmp))
        if args.phase_s > 0:
            result.update(pipeline_faults(tmp, FLYSLAM, ENV, f"tcp/127.0.0.1:{free_port()}", args.phase_s,
                                          args.warmup_s, hostile_payloads(), args.hostile, args.flood,
                                          args.flood_publishers))
        if args.secured_s > 0:
            result.update(secured_run(tmp, FLYSLAM, ENV, free_port(), args.secured_s))
        result["seconds"] = round(time.monotonic() - t0, 1)
        result["load_average"] = os.getloadavg()[0]
    for k, v in result.items():
        print(f"{k:<32} {v}")
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
