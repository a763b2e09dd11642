"""Bus benchmark: 640×480 RGB stereo frames between two processes on loopback.

Measures, for the plain network transport and for Zenoh shared memory (``shm``):
- latency (envelope stamp at the publisher → decoded at the subscriber) at a paced 30 frames/s,
- throughput (frames/s decoded by the subscriber) with the publisher going as fast as it can;
- CPU per paced frame (ms, all threads) of the publishing and of the subscribing process.

Figures only, no pass/fail. With --json the last stdout line is one JSON object.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from common import messages  # noqa: E402
from common.bus import BusOptions, make_config  # noqa: E402
from common.images import make_frame  # noqa: E402

KEY = "benchbus/stereo/frame"


def config(port: int, shm: bool, listen: bool) -> zenoh.Config:
    ep = f"tcp/127.0.0.1:{port}"
    conf = make_config(BusOptions(listen=[ep] if listen else ["tcp/127.0.0.1:0"], connect=[] if listen else [ep]))
    conf.insert_json5("transport/shared_memory/enabled", "true" if shm else "false")
    return conf


def publisher(port: int, shm: bool, paced_frames: int, burst_s: float) -> None:
    """Child process: publish paced frames, then a burst as fast as possible, then a stop marker."""
    rng = np.random.default_rng(0)
    left = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
    right = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
    with zenoh.open(config(port, shm, listen=False)) as session:
        pub = session.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.BLOCK)
        provider = zenoh.shm.ShmProvider.default_backend(64 * 1024 * 1024) if shm else None
        time.sleep(1.0)  # let the subscriber's interest arrive

        def put(seq: int) -> None:
            payload = messages.encode(make_frame(left, right, seq, time.time_ns()))
            if provider is None:
                pub.put(payload)
            else:
                buf = provider.alloc(len(payload), policy=zenoh.shm.BlockOn(zenoh.shm.GarbageCollect()))
                buf[:] = payload
                pub.put(buf)

        seq = 0
        next_t = time.monotonic()
        cpu0 = time.process_time()
        for _ in range(paced_frames):
            seq += 1
            put(seq)
            next_t += 1 / 30
            time.sleep(max(0.0, next_t - time.monotonic()))
        cpu_ms = 1000 * (time.process_time() - cpu0) / max(paced_frames, 1)
        time.sleep(0.3)
        session.put(KEY + "/phase", f"burst {cpu_ms:.3f}".encode())
        time.sleep(0.2)
        t_end = time.monotonic() + burst_s
        while time.monotonic() < t_end:
            seq += 1
            put(seq)
        time.sleep(0.5)
        session.put(KEY + "/phase", b"done")
        time.sleep(0.5)


def measure(port: int, shm: bool, paced_frames: int, burst_s: float) -> dict:
    latencies: list[float] = []
    burst_times: list[float] = []
    phase = {"name": "paced", "pub_cpu_ms": None, "sub_cpu": []}
    via_shm = [0, 0]  # [payloads that arrived as shared memory, all payloads]
    done = threading.Event()
    lock = threading.Lock()

    def on_frame(sample: zenoh.Sample) -> None:
        via_shm[0] += sample.payload.as_shm() is not None
        via_shm[1] += 1
        msg = messages.decode(sample.payload.to_bytes(), messages.StereoFrame)
        now = time.time_ns()
        with lock:
            if phase["name"] == "paced":
                latencies.append((now - msg.header.stamp_ns) / 1e6)
                phase["sub_cpu"].append(time.process_time())
            else:
                burst_times.append(time.monotonic())

    def on_phase(sample: zenoh.Sample) -> None:
        text, _, cpu = sample.payload.to_string().partition(" ")
        with lock:
            phase["name"] = text
            if cpu:
                phase["pub_cpu_ms"] = float(cpu)
        if text == "done":
            done.set()

    with zenoh.open(config(port, shm, listen=True)) as session:
        session.declare_subscriber(KEY, on_frame)
        session.declare_subscriber(KEY + "/phase", on_phase)
        child = subprocess.Popen([sys.executable, __file__, "--role", "pub", "--port", str(port),
                                  "--paced", str(paced_frames), "--burst-s", str(burst_s)] + (["--shm"] if shm else []),
                                 cwd=ROOT)
        done.wait(timeout=paced_frames / 30 + burst_s + 30)
        child.wait(timeout=30)
    lat = np.array(latencies)
    fps = (len(burst_times) - 1) / (burst_times[-1] - burst_times[0]) if len(burst_times) > 1 else 0.0
    return {"latency_p50_ms": round(float(np.percentile(lat, 50)), 3) if lat.size else None,
            "latency_p99_ms": round(float(np.percentile(lat, 99)), 3) if lat.size else None,
            "frames_per_s": round(fps, 1), "frames_received_paced": int(lat.size),
            "publisher_cpu_ms_per_frame": phase["pub_cpu_ms"],
            # The subscribing process between its first and last paced frame (this process: Zenoh's threads,
            # the callback and the decode).
            "subscriber_cpu_ms_per_frame": round(1000 * (cpu[-1] - cpu[0]) / (len(cpu) - 1), 3)
            if len(cpu := phase["sub_cpu"]) > 1 else None,
            "shm_payload_fraction": round(via_shm[0] / max(via_shm[1], 1), 3)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    p.add_argument("--paced", type=int, default=150, help="frames sent at 30 frames/s for latency")
    p.add_argument("--burst-s", type=float, default=3.0, help="seconds of as-fast-as-possible publishing")
    p.add_argument("--port", type=int, default=0)
    p.add_argument("--role", choices=["bench", "pub"], default="bench", help=argparse.SUPPRESS)
    p.add_argument("--shm", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.role == "pub":
        publisher(args.port, args.shm, args.paced, args.burst_s)
        return 0
    import socket
    results = {}
    for shm in (False, True):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        label = "shm" if shm else "network"
        print(f"[bus] {label}: {args.paced} paced frames, then {args.burst_s:g} s burst ...", file=sys.stderr, flush=True)
        results[label] = measure(port, shm, args.paced, args.burst_s)
        r = results[label]
        print(f"  {label:8s} latency p50 {r['latency_p50_ms']} ms  p99 {r['latency_p99_ms']} ms  "
              f"throughput {r['frames_per_s']} frames/s (640×480 RGB pairs, decoded); CPU per frame: publisher "
              f"{r['publisher_cpu_ms_per_frame']} ms, subscriber {r['subscriber_cpu_ms_per_frame']} ms", flush=True)
    out = dict(results["network"])
    out["shm"] = results["shm"]
    if args.json:
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
