"""Pipeline benchmark: the whole flyslam pipeline on simulator frames at 30 frames/s, 640×480, on this machine.

The simulator's frames are rendered once (deterministic, cached in .cache/recordings/) and replayed in
real time at 30 frames/s, so that rendering — which alone would take most of one of the two cores at
this rate — does not compete with the pipeline it feeds. Then replay → fusion → evolver → localiser →
planner, with the Rerun bridge writing an .rrd, run as separate processes under the supervisor while
this process listens on the bus and samples every service's memory.

Prints, and with --json as one JSON object on the last line:
- pose_latency_p50_ms / pose_latency_p99_ms: from a frame's publication to the publication of the
  localiser's pose estimate for that frame (both taken as receive times here, one clock);
- frames_skipped_fraction: frames the evolver never worked on (its latest-value input dropped them);
- evolver_generations_per_s (median while frames flow), evolver_degraded_frames (frames evolved while the evolver ran degraded:
  it got less CPU than it asked for), evolver_cpu_share: from the evolver's last heartbeat;
- peak_rss_mb: peak of the sum of all services' resident memory; rss_growth_mb: second half of the run
  (up to the last frame) minus first half (≈ 0 when memory is flat; start-up falls in the first half),
  rss_growth_after_warmup_mb: last quarter minus second quarter. Figures only, no pass/fail.
- stages_ms: where a frame's latency goes (p50/p99 over the frames that got a pose), from the evolver's
  per-frame trace (``--trace``: monotonic times, the same clock as this process's receive times):
  frame→take (the frame waits in the evolver's latest-value slot while it finishes a generation or the
  previous frame), decode (JPEG), rescore (move the flies by odometry, prepare the images, re-score),
  settle (evolution until good enough), publish→localiser start (the population waits while the
  localiser finishes the previous one: inferred as max(published, previous pose)), localiser (the rest,
  up to the pose's arrival here);
- cpu_percent: each service's CPU time over the whole run (start-up included), in % of one core (the
  machine has two; the supervisor itself not counted);
- cpu_pct_of_one_core / cpu_ms_per_frame: each service's CPU (user + system, the supervisor included)
  while frames flow — from the first frame seen here to the last — in % of one core and in CPU-ms per
  frame published, plus "total": the budget figure, which depends on the machine far less than latency;
- ate_rmse_m: the localiser's poses against the replayed ground truth (a latency cut must not cost
  accuracy);
- reference_cpu_ms: the CPU time of a fixed piece of the evolver's work (:func:`machine_reference_ms`),
  measured before and after the run, and cpu_per_frame_in_references: the total CPU-ms per frame over
  their mean. A virtual machine's speed changes from day to day (the same code gave 34 and 58 CPU-ms
  per frame), so runs on different days compare by this ratio, not by CPU-ms.

``--hog`` runs the bench a second time with one busy process (``python -c 'while True: pass'``) beside
it and reports that run's figures under the key "hog" (its files in OUT/hog/).

OUT/latency_by_frame.json holds every posed frame's latency, its time in the run and its stage durations:
whether the tail is start-up, a stretch of the run where everything slows (CPU taken by other work) or
one stage.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
# The services get the environment a launch would give them, not what importing common.fly below sets
# in this process (OMP_WAIT_POLICY).
SERVICE_ENV = dict(os.environ, PYTHONPATH=str(ROOT))

from common import messages as m  # noqa: E402
from common.bus import BusOptions, Node  # noqa: E402
from common.fly.core import EvolverServiceConfig  # noqa: E402
from common.trajectory_metrics import TrajectoryMismatch, evaluate  # noqa: E402
from common.sim.offline import cached_recording  # noqa: E402

LAUNCH = """
[run]
duration_s = {duration}
latch = ["fusion/odom", "fusion/pose", "slam/map_to_odom"]

[[service]]
name = "recorder"
module = "services.recorder"
args = ["--out", "{{out}}/recording.mcap", "--keys", "stereo/calibration", "stereo/frame", "odom/*", "sonar/*",
        "truth/*", "fusion/*", "flies/*", "slam/*", "planner/*", "status/*"]
nice = {nice_recorder}

[[service]]
name = "bridge"
module = "services.bridge"
args = ["--rrd", "{{out}}/run.rrd", "--grpc-port", "0", "--web-port", "0", "--image-hz", "{image_hz}"]
required = false
nice = {nice_bridge}

[[service]]
name = "fusion"
module = "services.fusion"

[[service]]
name = "evolver"
module = "services.evolver"
args = ["--threads", "1", "--settle-ms", "{settle}", "--recovery", "{recovery}", "--duty", "{duty}",
        "--cpu-budget", "{cpu_budget}", "--trace"]

[[service]]
name = "localiser"
module = "services.localiser"

[[service]]
name = "planner"
module = "services.planner"
nice = {nice_planner}

[[service]]
name = "replay"
module = "services.replay"
args = ["{recording}", "--rate", "1", "--wait-subscribers", "2"]
ends_run = true
"""


CLOCK_TICK = os.sysconf("SC_CLK_TCK")
STAGES = ("frame_to_take", "decode", "rescore", "settle", "publish_to_localiser", "localiser", "total")


def rss_mb(pid: int) -> float:
    try:
        for line in (Path("/proc") / str(pid) / "status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of a process so far (None once it has gone)."""
    try:
        fields = (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICK


def service_name(pid: int) -> str:
    """'evolver' for `python -m services.evolver ...`, 'supervisor' for deploy.cli and for its watchdog
    (`python -c ...`), else the program."""
    try:
        argv = (Path("/proc") / str(pid) / "cmdline").read_bytes().split(b"\0")
    except OSError:
        return "?"
    argv = [a.decode(errors="replace") for a in argv if a]
    if "-m" in argv and argv.index("-m") + 1 < len(argv):
        module = argv[argv.index("-m") + 1]
        return "supervisor" if module == "deploy.cli" else module.rsplit(".", 1)[-1]
    if "-c" in argv:
        return "supervisor"
    return Path(argv[0]).name if argv else "?"


def descendants(pid: int) -> list[int]:
    kids, frontier = [], [pid]
    while frontier:
        parent = frontier.pop()
        for entry in Path("/proc").iterdir():
            if entry.name.isdigit():
                try:
                    ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
                except (OSError, IndexError, ValueError):
                    continue
                if ppid == parent:
                    kids.append(int(entry.name))
                    frontier.append(int(entry.name))
    return kids


def percentiles(values) -> dict | None:
    v = np.asarray(values, float)
    if not v.size:
        return None
    return {"p50": round(float(np.percentile(v, 50)), 1), "p99": round(float(np.percentile(v, 99)), 1)}


def stage_breakdown(frame_seen: dict, traces: dict, poses: dict, by_seq: dict | None = None) -> dict[str, list[float]]:
    """Per-stage durations (ms) of every frame that has a receive time, an evolver trace and a pose.

    ``frame_seen[seq]`` and ``poses[seq]`` are this process's receive times (monotonic s) of the frame and
    of the localiser's pose for it; ``traces[seq]`` the evolver's stage times (monotonic ns). The
    localiser handles one population at a time, so it starts on a population when it has been published
    *and* the previous pose is out: the difference is waiting, the rest is the localiser's own work
    (plus the bus hops, which are well under a millisecond here).
    """
    out: dict[str, list[float]] = {k: [] for k in STAGES}
    previous_pose = -np.inf
    for seq in sorted(poses):
        if seq in frame_seen and seq in traces:
            t, f = traces[seq], frame_seen[seq]
            published = t["published"] * 1e-9
            start = max(published, previous_pose)
            durations = {"frame_to_take": t["take"] * 1e-9 - f, "decode": (t["decoded"] - t["take"]) * 1e-9,
                         "rescore": (t["ready"] - t["decoded"]) * 1e-9,
                         "settle": (t["published"] - t["ready"]) * 1e-9,
                         "publish_to_localiser": start - published, "localiser": poses[seq] - start,
                         "total": poses[seq] - f}
            for k, v in durations.items():
                out[k].append(1000 * v)
            if by_seq is not None:
                by_seq[seq] = {k: round(1000 * v, 2) for k, v in durations.items()}
        previous_pose = poses[seq]
    return out


def cpu_while_flowing(snapshots: list[tuple[float, int, dict[int, float]]], names: dict[int, str]):
    """({service: % of one core}, {service: CPU-ms per frame}), each with "total", between the first
    snapshot that saw a frame and the first that saw the last one.  ``snapshots``: (monotonic s, frames
    seen so far, {pid: CPU s so far}); a service's processes are summed."""
    flowing = [k for k, (_, frames, _) in enumerate(snapshots) if frames > 0]
    if len(flowing) < 2:
        return None, None
    i0 = flowing[0]
    i1 = next(k for k in flowing if snapshots[k][1] == snapshots[flowing[-1]][1])
    (t0, f0, c0), (t1, f1, _) = snapshots[i0], snapshots[i1]
    if t1 <= t0 or f1 <= f0:
        return None, None
    first: dict[int, float] = {}
    last: dict[int, float] = {}
    for _, _, c in snapshots[i0:i1 + 1]:      # a process that ended (replay does) counts up to its last sample,
        last.update(c)                        # one started meanwhile (a restart) from its first
        for pid, v in c.items():
            first.setdefault(pid, v)
    cpu: dict[str, float] = {}
    for pid, v in first.items():
        cpu[names.get(pid, "?")] = cpu.get(names.get(pid, "?"), 0.0) + last[pid] - v
    cpu["total"] = sum(cpu.values())
    return ({k: round(100 * v / (t1 - t0), 1) for k, v in cpu.items()},
            {k: round(1000 * v / (f1 - f0), 2) for k, v in cpu.items()})


def format_breakdown(stages: dict[str, list[float]], cpu: dict[str, float]) -> str:
    labels = {"frame_to_take": "frame -> evolver takes it", "decode": "  decode (JPEG x2)",
              "rescore": "  move flies + prepare images + re-score", "settle": "  settle (evolve until good enough)",
              "publish_to_localiser": "published -> localiser starts", "localiser": "localiser (register + publish)",
              "total": "frame -> pose (total)"}
    lines = [f"[pipeline] latency breakdown over {len(stages['total'])} posed frames (ms):",
             f"[pipeline]   {'stage':<42} {'p50':>7} {'p99':>7}"]
    for k in STAGES:
        pc = percentiles(stages[k])
        if pc:
            lines.append(f"[pipeline]   {labels[k]:<42} {pc['p50']:7.1f} {pc['p99']:7.1f}")
    lines.append("[pipeline] CPU per service over the whole run (% of one core; 200 % = both cores): " +
                 ", ".join(f"{k} {v:.0f}" for k, v in sorted(cpu.items(), key=lambda kv: -kv[1])))
    return "\n".join(lines)


def format_budget(pct: dict[str, float] | None, ms: dict[str, float] | None) -> str:
    if not pct or not ms:
        return "[pipeline] CPU while frames flow: not measured (fewer than two samples with frames)"
    order = sorted((k for k in pct if k != "total"), key=lambda k: -pct[k]) + ["total"]
    lines = ["[pipeline] CPU while frames flow:",
             f"[pipeline]   {'service':<12} {'% of a core':>11} {'CPU-ms/frame':>13}"]
    lines += [f"[pipeline]   {k:<12} {pct[k]:11.1f} {ms[k]:13.2f}" for k in order]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    p.add_argument("--seconds", type=float, default=30.0, help="length of the replayed run")
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--settle-ms", type=float, default=25.0,
                   help="evolver's longest evolution per new frame before publishing")
    evolver = EvolverServiceConfig()
    p.add_argument("--recovery", type=float, default=evolver.recovery,
                   help="evolver publishes once the population's mean fitness is back to this fraction of the "
                        "recent frames' best (2 = never: always the whole --settle-ms, the old behaviour)")
    p.add_argument("--duty", type=float, default=evolver.duty, help="evolver's duty cycle between frames")
    p.add_argument("--cpu-budget", type=float, default=evolver.cpu_budget,
                   help="evolver evolves between frames only while under this fraction of a core")
    p.add_argument("--image-hz", type=float, default=5.0, help="bridge's image/flies logging rate")
    p.add_argument("--no-nice", action="store_true", help="run every service at normal priority")
    p.add_argument("--out", default=str(ROOT / "bench" / "out" / "pipeline"))
    p.add_argument("--hog", action="store_true",
                   help="run a second time beside one busy process; that run's figures go under \"hog\"")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    print(f"[pipeline] rendering (or reusing) {args.seconds:g} s of 640×480 corridor at {args.fps:g} frames/s ...",
          file=sys.stderr, flush=True)
    t0 = time.monotonic()
    recording = cached_recording("corridor", seed=0, seconds=args.seconds, fps=args.fps, width=640, height=480,
                                 encoding="jpeg", quality=90)
    print(f"[pipeline] recording {recording} ready in {time.monotonic() - t0:.0f} s", file=sys.stderr, flush=True)
    reference = [machine_reference_ms()]
    print(f"[pipeline] machine reference: {reference[0]} CPU-ms (20 generations of 5,000 flies, one thread)",
          file=sys.stderr, flush=True)
    result = run_once(args, out, recording)
    reference.append(machine_reference_ms())
    result["reference_cpu_ms"] = {"before": reference[0], "after": reference[1]}
    result["cpu_per_frame_in_references"] = in_references(result, reference)
    if args.hog:
        print("[pipeline] again, beside one busy process (--hog) ...", file=sys.stderr, flush=True)
        hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
        try:
            result["hog"] = run_once(args, out / "hog", recording)
        finally:
            hog.kill()
            hog.wait()
        result["hog"]["cpu_per_frame_in_references"] = in_references(result["hog"], reference)
    for label, r in [("", result)] + ([("hog: ", result["hog"])] if "hog" in result else []):
        print(f"{label}frames published {r['frames_published']}, evolved {r['frames_evolved']} "
              f"({100 * (r['frames_skipped_fraction'] or 0):.0f} % skipped), poses {r['poses']} "
              f"({100 * (r['posed_fraction'] or 0):.0f} % of frames), ATE {r['ate_rmse_m']} m, "
              f"load {r['loadavg_1min_at_start']} -> {r['loadavg_1min']}")
        print(f"{label}pose latency p50 {r['pose_latency_p50_ms']} ms, p99 {r['pose_latency_p99_ms']} ms "
              f"(frame published -> pose published for that frame)")
        print(f"{label}evolver {r['evolver_generations_per_s']} generations/s, degraded for "
              f"{r['evolver_degraded_frames']} frames (CPU share {r['evolver_cpu_share']}); services' memory peak "
              f"{r['peak_rss_mb']} MB, growth {r['rss_growth_mb']} MB (second half vs first)")
        total = (r["cpu_ms_per_frame"] or {}).get("total")
        print(f"{label}CPU while frames flow: {(r['cpu_pct_of_one_core'] or {}).get('total')} % of one core, "
              f"{total} CPU-ms per frame in all, {r['cpu_per_frame_in_references']} machine references "
              f"({reference[0]} -> {reference[1]} CPU-ms)")
    if args.json:
        print(json.dumps(result))
    return 0


def in_references(r: dict, reference: list[float]) -> float | None:
    """A run's total CPU-ms per frame over the mean machine reference."""
    total = (r.get("cpu_ms_per_frame") or {}).get("total")
    return round(total / float(np.mean(reference)), 3) if total else None


def machine_reference_ms(repeats: int = 5) -> float:
    """CPU-ms (this thread's) of a fixed piece of the evolver's work, the least of ``repeats``: 20
    generations of 5,000 flies on a synthetic 640×480 colour pair, one thread, seed 0."""
    from common.fly import EvolverConfig, FlyEvolver
    from common.fly.synthetic import textured_plane_pair
    calib, left, right, _ = textured_plane_pair(width=640, height=480)
    times = []
    for _ in range(repeats + 1):
        evolver = FlyEvolver(calib, EvolverConfig(parallel=False), seed=0)
        t0 = time.thread_time()
        evolver.set_images(left, right)
        evolver.step(20)
        times.append((time.thread_time() - t0) * 1e3)
    return round(min(times[1:]), 1)         # the first run loads the kernels


def run_once(args, out: Path, recording: Path) -> dict:
    """One run of the pipeline under the supervisor; returns the figures (the module docstring)."""
    out.mkdir(parents=True, exist_ok=True)
    load_start = os.getloadavg()[0]
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    hub = f"tcp/127.0.0.1:{port}"
    launch = out / "launch.toml"
    nice = {"nice_recorder": 0, "nice_bridge": 0, "nice_planner": 0} if args.no_nice else \
        {"nice_recorder": 10, "nice_bridge": 10, "nice_planner": 5}
    launch.write_text(LAUNCH.format(duration=args.seconds + 30, settle=args.settle_ms, recording=recording,
                                    recovery=args.recovery, duty=args.duty, cpu_budget=args.cpu_budget,
                                    image_hz=args.image_hz, **nice))

    frame_seen: dict[int, float] = {}
    pose_seen: dict[int, float] = {}
    traces: dict[int, dict] = {}
    slam_poses: list[tuple[int, np.ndarray]] = []
    truth_poses: list[tuple[int, np.ndarray]] = []
    frames_total = [0]
    heartbeats: dict[str, m.Heartbeat] = {}
    generation_rates: list[tuple[int, float]] = []    # (frames seen, evolver's generations/s) per heartbeat
    lock = threading.Lock()

    def on_frame(key, payload):
        # Only the envelope is needed: peek at seq without decoding the images.
        obj = msgpack.unpackb(payload, raw=False)
        with lock:
            frame_seen[int(obj["seq"])] = time.monotonic()
            frames_total[0] += 1

    def on_pose(msg: m.PoseEstimate):
        now = time.monotonic()
        with lock:
            pose_seen.setdefault(msg.source_seq, now)
            slam_poses.append((msg.header.stamp_ns, m.transform_of(msg)))

    def on_truth(msg: m.PoseEstimate):
        with lock:
            truth_poses.append((msg.header.stamp_ns, m.transform_of(msg)))

    def on_trace(msg: m.EvolverTrace):
        t = {"take": msg.take_ns, "decoded": msg.decoded_ns, "ready": msg.ready_ns,
             "published": msg.published_ns, "generations": msg.generations, "reference": msg.reference,
             "quality": msg.quality}
        with lock:
            traces[int(msg.header.seq)] = t

    def on_status(key, payload):
        try:
            hb = m.decode(payload, m.Heartbeat)
        except m.DecodeError:
            return
        heartbeats[hb.service] = hb
        if hb.service == "evolver" and "generations_per_s" in hb.rates:
            generation_rates.append((frames_total[0], hb.rates["generations_per_s"]))

    sup = subprocess.Popen([sys.executable, "-m", "deploy.cli", "run", str(launch), "--out", str(out / "run"),
                            "--hub", hub], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                           env=SERVICE_ENV)
    time.sleep(1.0)
    rss_samples: list[tuple[float, float]] = []
    rss_by_service: dict[str, list[float]] = {}
    cpu_first: dict[int, tuple[str, float]] = {}
    cpu_last: dict[int, float] = {}
    cpu_snapshots: list[tuple[float, int, dict[int, float]]] = []
    with Node("bench-pipeline", BusOptions(connect=[hub], listen=["tcp/127.0.0.1:0"]), handle_signals=False) as node:
        node.subscribe("stereo/frame", None, on_frame, raw=True)
        node.subscribe("slam/pose", m.PoseEstimate, on_pose)
        node.subscribe("truth/pose", m.PoseEstimate, on_truth)
        node.subscribe("trace/evolver", m.EvolverTrace, on_trace)
        node.subscribe("status/*", None, on_status, raw=True)
        t_start = time.monotonic()
        while sup.poll() is None:
            pids = descendants(sup.pid)
            per_pid = {pid: rss_mb(pid) for pid in pids}
            rss_samples.append((time.monotonic() - t_start, sum(per_pid.values())))
            for pid in pids:
                if pid in cpu_first:
                    rss_by_service.setdefault(cpu_first[pid][0], []).append(per_pid[pid])
                cpu = cpu_seconds(pid)
                if cpu is None:
                    continue
                if pid not in cpu_first:
                    cpu_first[pid] = (service_name(pid), cpu)
                cpu_last[pid] = cpu
            with lock:
                seen = frames_total[0]
            flowing = {pid: cpu_last[pid] for pid in pids if pid in cpu_last}
            sup_cpu = cpu_seconds(sup.pid)
            if sup_cpu is not None:
                flowing[sup.pid] = sup_cpu
            cpu_snapshots.append((time.monotonic(), seen, flowing))
            n = len(pose_seen)
            print(f"\r[pipeline] {time.monotonic() - t_start:5.0f} s  frames {frames_total[0]}  poses {n}  "
                  f"rss {rss_samples[-1][1]:.0f} MB", end="", file=sys.stderr, flush=True)
            time.sleep(0.5)
            if time.monotonic() - t_start > args.seconds + 90:
                sup.send_signal(signal.SIGTERM)
        print(file=sys.stderr)
        run_s = time.monotonic() - t_start
    sup_out = sup.communicate()[0]
    (out / "supervisor.txt").write_text(sup_out)
    (out / "rss_by_service.json").write_text(json.dumps(rss_by_service))   # 2 samples/s, for a closer look

    with lock:
        latencies = [1000 * (t - frame_seen[seq]) for seq, t in pose_seen.items() if seq in frame_seen]
        stage_by_seq: dict = {}
        stages = stage_breakdown(frame_seen, traces, pose_seen, stage_by_seq)
        per_frame = {int(seq): dict(latency_ms=round(1000 * (t - frame_seen[seq]), 2),
                                    frame_s=round(frame_seen[seq] - t_start, 3), stages_ms=stage_by_seq.get(seq))
                     for seq, t in pose_seen.items() if seq in frame_seen}
    (out / "latency_by_frame.json").write_text(json.dumps(per_frame))   # where in the run the tail sits
    cpu_percent: dict[str, float] = {}
    for pid, (name, first) in cpu_first.items():
        cpu_percent[name] = cpu_percent.get(name, 0.0) + 100 * (cpu_last[pid] - first) / run_s
    names = {pid: name for pid, (name, _) in cpu_first.items()}
    names[sup.pid] = "supervisor"
    cpu_pct, cpu_ms = cpu_while_flowing(cpu_snapshots, names)
    ate = None
    if slam_poses and truth_poses:
        try:
            es, ep = zip(*sorted(slam_poses, key=lambda x: x[0]))
            gs, gp = zip(*sorted(truth_poses, key=lambda x: x[0]))
            ate = round(evaluate(np.array(es), np.array(ep), np.array(gs), np.array(gp),
                                 tolerance_ns=int(0.5e9 / args.fps)).ate_rmse_m, 3)
        except TrajectoryMismatch as e:
            print(f"[pipeline] no ATE: {e}", file=sys.stderr)
    settle_generations = [t["generations"] for t in traces.values()]
    # Mean fitness of each published population, in frame order: a publication rule that publishes too
    # early would show as a quality that sinks over the run.
    quality = np.array([traces[k].get("quality", np.nan) for k in sorted(traces)], float)
    thirds = np.array_split(quality, 3) if quality.size >= 3 else []

    lat = np.array(latencies)
    evo = heartbeats.get("evolver")
    flowing_rates = [r for n, r in generation_rates if 0 < n < frames_total[0]]
    evolved = evo.progress if evo else 0
    frames = frames_total[0]
    # Up to the last frame: afterwards the services stop one by one and their memory leaves the sum.
    last_frame_s = max(frame_seen.values()) - t_start if frame_seen else np.inf
    rss = np.array([r for r in rss_samples if r[0] <= last_frame_s])
    half = len(rss) // 2
    result = {
        "pose_latency_p50_ms": round(float(np.percentile(lat, 50)), 1) if lat.size else None,
        "pose_latency_p99_ms": round(float(np.percentile(lat, 99)), 1) if lat.size else None,
        "frames_skipped_fraction": round(1 - evolved / frames, 3) if frames else None,
        # Median over the heartbeats while frames flowed (the last one comes after the run).
        "evolver_generations_per_s": round(float(np.median(flowing_rates)), 1) if flowing_rates else None,
        "evolver_degraded_frames": int(evo.counters.get("degraded_frames", 0)) if evo else None,
        "evolver_cpu_share": evo.rates.get("cpu_share") if evo else None,
        "peak_rss_mb": round(float(rss[:, 1].max()), 1) if len(rss) else None,
        "rss_growth_mb": round(float(np.median(rss[half:, 1]) - np.median(rss[:half, 1])), 1) if half > 2 else None,
        # The first half includes start-up (imports, numba compilation, the first keyframes), so also: last
        # quarter minus second quarter, both after the services have warmed up.
        "rss_growth_after_warmup_mb": round(float(np.median(rss[3 * half // 2:, 1]) - np.median(rss[half // 2:half, 1])), 1)
        if half > 4 else None,
        "frames_published": frames, "frames_evolved": evolved, "poses": int(lat.size),
        "posed_fraction": round(lat.size / frames, 3) if frames else None,
        "ate_rmse_m": ate,
        "settle_generations_p50": float(np.median(settle_generations)) if settle_generations else None,
        "published_quality_by_third": [round(float(np.nanmean(t)), 4) for t in thirds],
        "stages_ms": {k: percentiles(v) for k, v in stages.items()},
        "cpu_percent": {k: round(v, 1) for k, v in sorted(cpu_percent.items())},
        "cpu_pct_of_one_core": cpu_pct,
        "cpu_ms_per_frame": cpu_ms,
        "rss_growth_by_service_mb": {k: round(float(np.median(v[len(v) // 2:]) - np.median(v[:len(v) // 2])), 1)
                                     for k, v in sorted(rss_by_service.items()) if len(v) > 6},
        "settle_ms": args.settle_ms, "recovery": args.recovery, "duty": args.duty, "cpu_budget": args.cpu_budget,
        "image_hz": args.image_hz,
        "niced": not args.no_nice,
        "fps": args.fps, "resolution": "640x480", "cores": os.cpu_count(),
        "loadavg_1min": round(os.getloadavg()[0], 2),
        "loadavg_1min_at_start": round(load_start, 2),
    }
    print(format_breakdown(stages, cpu_percent), file=sys.stderr)
    print(format_budget(cpu_pct, cpu_ms), file=sys.stderr)
    return result


if __name__ == "__main__":
    sys.exit(main())
