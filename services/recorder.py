"""Recorder service: writes bus keys to an MCAP recording until stopped.

Subscribes once (raw, unvalidated: a recorder keeps what was on the bus) to ``<robot>/**`` and keeps the
keys matching a ``--keys`` pattern — one subscription, because Zenoh may run the callbacks of separate
subscriptions concurrently and the recording must keep the order of arrival — queues payloads from Zenoh's threads and writes them from the main loop, flushing
the chunk in progress every ``--flush-s`` seconds so that a SIGKILL loses at most that much. The first
calibration seen is also stored as metadata, with the run's configuration (``--run-config``).
"""
from __future__ import annotations

import json
import logging
import queue
import sys
import time
from pathlib import Path

import zenoh

from common.recording import RecordingWriter
from services.base import run_service, service_parser

log = logging.getLogger("flyslam.recorder")


def build_parser():
    p = service_parser("record", __doc__.splitlines()[0])
    p.add_argument("--out", "-o", required=True, help="MCAP file to write")
    p.add_argument("--keys", nargs="+", default=["**"],
                   help="stream patterns under the robot prefix, e.g. 'stereo/*' 'odom/wheels'")
    p.add_argument("--flush-s", type=float, default=1.0, help="close the chunk in progress this often")
    p.add_argument("--run-config", help="JSON file describing the run, stored as metadata")
    p.add_argument("--chunk-mb", type=float, default=4.0, help="chunk size before compression")
    return p


def body(node, args) -> int:
    inbox: queue.SimpleQueue = queue.SimpleQueue()  # unbounded, drained by the loop below
    writer = RecordingWriter(args.out, chunk_size=int(args.chunk_mb * 1e6))
    if args.run_config:
        writer.add_config(json.loads(Path(args.run_config).read_text()))
    patterns = [zenoh.KeyExpr(node.key(k)) for k in args.keys]

    def on_payload(key: str, payload: bytes) -> None:
        if any(p.intersects(zenoh.KeyExpr(key)) for p in patterns):
            inbox.put((key, payload, time.time_ns()))

    node.subscribe("**", None, on_payload, raw=True)
    calibration_key = node.key("stereo/calibration")
    have_calibration = False
    last_flush = time.monotonic()
    log.info("recording %s to %s", " ".join(node.key(k) for k in args.keys), args.out)
    try:
        while True:
            try:
                key, payload, recv_ns = inbox.get(timeout=0.05)
            except queue.Empty:
                if node.stopping:
                    break
            else:
                writer.write(key, payload, recv_ns)
                node.progress += 1
                if not have_calibration and key == calibration_key:
                    writer.add_calibration(payload)
                    have_calibration = True
            if time.monotonic() - last_flush >= args.flush_s:
                writer.flush()
                last_flush = time.monotonic()
            node.rates["backlog"] = float(inbox.qsize())
    finally:
        writer.close()
        log.info("wrote %d messages to %s", writer.count, args.out)
    return 0


def main(argv=None) -> int:
    return run_service("recorder", build_parser(), body, argv)


if __name__ == "__main__":
    sys.exit(main())
