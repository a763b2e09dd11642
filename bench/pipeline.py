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
- evolver_generations_per_s: from the evolver's heartbeat;
- peak_rss_mb: peak of the sum of all services' resident memory; rss_growth_mb: second half of the run
  minus first half (≈ 0 when memory is flat). Figures only, no pass/fail.
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

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from common import messages as m  # noqa: E402
from common.bus import BusOptions, Node  # noqa: E402
from common.sim.offline import cached_recording  # noqa: E402

LAUNCH = """
[run]
duration_s = {duration}
latch = ["fusion/odom", "fusion/pose", "slam/map_to_odom"]

[[service]]
name = "bridge"
module = "services.bridge"
args = ["--rrd", "{{out}}/run.rrd", "--grpc-port", "0", "--web-port", "0"]
required = false

[[service]]
name = "fusion"
module = "services.fusion"

[[service]]
name = "evolver"
module = "services.evolver"
args = ["--threads", "1", "--settle-ms", "{settle}"]

[[service]]
name = "localiser"
module = "services.localiser"

[[service]]
name = "planner"
module = "services.planner"

[[service]]
name = "replay"
module = "services.replay"
args = ["{recording}", "--rate", "1", "--wait-subscribers", "2"]
ends_run = true
"""


def rss_mb(pid: int) -> float:
    try:
        for line in (Path("/proc") / str(pid) / "status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


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


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    p.add_argument("--seconds", type=float, default=30.0, help="length of the replayed run")
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--settle-ms", type=float, default=25.0, help="evolver time per new frame before publishing")
    p.add_argument("--out", default=str(ROOT / "bench" / "out" / "pipeline"))
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    print(f"[pipeline] rendering (or reusing) {args.seconds:g} s of 640×480 corridor at {args.fps:g} frames/s ...",
          file=sys.stderr, flush=True)
    t0 = time.monotonic()
    recording = cached_recording("corridor", seed=0, seconds=args.seconds, fps=args.fps, width=640, height=480,
                                 encoding="jpeg", quality=90)
    print(f"[pipeline] recording {recording} ready in {time.monotonic() - t0:.0f} s", file=sys.stderr, flush=True)

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    hub = f"tcp/127.0.0.1:{port}"
    launch = out / "launch.toml"
    launch.write_text(LAUNCH.format(duration=args.seconds + 30, settle=args.settle_ms, recording=recording))

    frame_seen: dict[int, float] = {}
    latencies: list[float] = []
    frames_total = [0]
    heartbeats: dict[str, m.Heartbeat] = {}
    lock = threading.Lock()

    def on_frame(key, payload):
        # Only the envelope is needed: peek at seq without decoding the images.
        import msgpack
        obj = msgpack.unpackb(payload, raw=False)
        with lock:
            frame_seen[int(obj["seq"])] = time.monotonic()
            frames_total[0] += 1

    def on_pose(msg: m.PoseEstimate):
        now = time.monotonic()
        with lock:
            t = frame_seen.get(msg.source_seq)
        if t is not None:
            latencies.append((now - t) * 1000)

    def on_status(key, payload):
        try:
            hb = m.decode(payload, m.Heartbeat)
        except m.DecodeError:
            return
        heartbeats[hb.service] = hb

    sup = subprocess.Popen([sys.executable, "-m", "deploy.cli", "run", str(launch), "--out", str(out / "run"),
                            "--hub", hub], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                           env=dict(os.environ, PYTHONPATH=str(ROOT)))
    time.sleep(1.0)
    rss_samples: list[tuple[float, float]] = []
    with Node("bench-pipeline", BusOptions(connect=[hub], listen=["tcp/127.0.0.1:0"]), handle_signals=False) as node:
        node.subscribe("stereo/frame", None, on_frame, raw=True)
        node.subscribe("slam/pose", m.PoseEstimate, on_pose)
        node.subscribe("status/*", None, on_status, raw=True)
        t_start = time.monotonic()
        while sup.poll() is None:
            pids = descendants(sup.pid)
            rss_samples.append((time.monotonic() - t_start, sum(rss_mb(pid) for pid in pids)))
            n = len(latencies)
            print(f"\r[pipeline] {time.monotonic() - t_start:5.0f} s  frames {frames_total[0]}  poses {n}  "
                  f"rss {rss_samples[-1][1]:.0f} MB", end="", file=sys.stderr, flush=True)
            time.sleep(0.5)
            if time.monotonic() - t_start > args.seconds + 90:
                sup.send_signal(signal.SIGTERM)
        print(file=sys.stderr)
    sup_out = sup.communicate()[0]
    (out / "supervisor.txt").write_text(sup_out)

    lat = np.array(latencies)
    evo = heartbeats.get("evolver")
    evolved = evo.progress if evo else 0
    frames = frames_total[0]
    rss = np.array(rss_samples)
    half = len(rss) // 2
    result = {
        "pose_latency_p50_ms": round(float(np.percentile(lat, 50)), 1) if lat.size else None,
        "pose_latency_p99_ms": round(float(np.percentile(lat, 99)), 1) if lat.size else None,
        "frames_skipped_fraction": round(1 - evolved / frames, 3) if frames else None,
        "evolver_generations_per_s": round(float(evo.rates.get("generations_per_s", 0)), 1) if evo else None,
        "peak_rss_mb": round(float(rss[:, 1].max()), 1) if len(rss) else None,
        "rss_growth_mb": round(float(np.median(rss[half:, 1]) - np.median(rss[:half, 1])), 1) if half > 2 else None,
        "frames_published": frames, "frames_evolved": evolved, "poses": int(lat.size),
        "fps": args.fps, "resolution": "640x480", "cores": os.cpu_count(),
        "loadavg_1min": round(os.getloadavg()[0], 2),
    }
    print(f"frames published {frames}, evolved {evolved} ({100 * (result['frames_skipped_fraction'] or 0):.0f} % skipped), "
          f"poses {lat.size}")
    print(f"pose latency p50 {result['pose_latency_p50_ms']} ms, p99 {result['pose_latency_p99_ms']} ms "
          f"(frame published -> pose published for that frame)")
    print(f"evolver {result['evolver_generations_per_s']} generations/s; services' memory peak {result['peak_rss_mb']} MB, "
          f"growth {result['rss_growth_mb']} MB (second half vs first)")
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
