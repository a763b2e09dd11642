"""Recorder service: writes bus keys to an MCAP recording until stopped.

Subscribes once (raw, unvalidated: a recorder keeps what was on the bus) to ``<robot>/**`` and keeps the
keys a ``--keys`` pattern includes (Zenoh key expressions, common.recording.KeyFilter; a verbatim ``@``
key such as the localiser's ``flies/population/@image`` is never among them) — one
subscription, because Zenoh may run the callbacks of separate subscriptions concurrently and the
recording must keep the order of arrival — queues payloads from Zenoh's threads and writes them from
the main loop, flushing the chunk in progress every ``--flush-s`` seconds so that a SIGKILL loses at
most that much. The first calibration seen is also stored as
metadata, with the run's configuration (``--run-config``).

A recorder never overwrites: when ``--out`` exists (a restart), it writes the next numbered segment
(``recording.1.mcap``, …), and readers take the segments together as one recording
(common.recording). A payload whose stamp MCAP cannot store (a negative ``stamp_ns``…) is recorded
with its receive time as publish time and counted (``bad_stamps`` in the heartbeat).

The queue holds at most ``--max-backlog-mb`` of payloads (default 16 MB: 12 s of the demo's frames,
so that a flood costs the process at most a few tens of MB): a recorder that falls that far behind
(niced on a loaded machine) drops the oldest queued messages, counts them per key in its heartbeat
(``dropped``; ``backlog``/``backlog_mb`` in its rates) and logs a warning, instead of growing without bound.
"""
from __future__ import annotations

import json
import logging
import sys
import time
from pathlib import Path

from common.recording import KeyFilter, RecorderBacklog, open_segment
from services.base import run_service, service_parser

log = logging.getLogger("flyslam.recorder")


def build_parser():
    p = service_parser("record", __doc__.splitlines()[0])
    p.add_argument("--out", "-o", required=True,
                   help="MCAP file to write; if it exists, the next free recording.<n>.mcap segment")
    p.add_argument("--keys", nargs="+", default=["**"],
                   help="stream patterns under the robot prefix, e.g. 'stereo/*' 'odom/wheels'")
    p.add_argument("--flush-s", type=float, default=1.0, help="close the chunk in progress this often")
    p.add_argument("--run-config", help="JSON file describing the run, stored as metadata")
    p.add_argument("--chunk-mb", type=float, default=4.0, help="chunk size before compression")
    p.add_argument("--compression", choices=("none", "lz4", "zstd"), default="none",
                   help="chunk compression; camera frames (JPEG) and fly populations (float32) hardly "
                        "compress, so the default spends no CPU on it")
    p.add_argument("--max-backlog-mb", type=float, default=16.0,
                   help="payloads queued for writing beyond this are dropped, oldest first, and counted "
                        "(0 = unbounded)")
    return p


def body(node, args) -> int:
    wanted = KeyFilter([node.key(k) for k in args.keys])   # a bad pattern fails before any file is made
    backlog = RecorderBacklog(int(args.max_backlog_mb * 1e6))
    run_config = json.loads(Path(args.run_config).read_text()) if args.run_config else None
    writer = open_segment(args.out, chunk_size=int(args.chunk_mb * 1e6), compression=args.compression)
    if run_config is not None:
        writer.add_config(run_config)

    def on_payload(key: str, payload: bytes) -> None:
        if wanted(key):
            backlog.put(key, payload, time.time_ns())

    node.subscribe("**", None, on_payload, raw=True)
    calibration_key = node.key("stereo/calibration")
    have_calibration = False
    last_flush = time.monotonic()
    reported_drops = reported_bad_stamps = 0
    log.info("recording %s to %s", " ".join(node.key(k) for k in args.keys), writer.path)
    try:
        while True:
            item = backlog.get(timeout=0.05)
            if item is None:
                if node.stopping:
                    break
            else:
                key, payload, recv_ns = item
                writer.write(key, payload, recv_ns)
                node.progress += 1
                if not have_calibration and key == calibration_key:
                    writer.add_calibration(payload)
                    have_calibration = True
            if time.monotonic() - last_flush >= args.flush_s:
                writer.flush()
                last_flush = time.monotonic()
                if writer.bad_stamps > reported_bad_stamps:
                    node.counters.add("bad_stamps", writer.bad_stamps - reported_bad_stamps)
                    log.warning("%d messages so far had a stamp_ns MCAP cannot store (negative or too large); "
                                "recorded with their receive time", writer.bad_stamps)
                    reported_bad_stamps = writer.bad_stamps
                by_key = backlog.dropped_by_key()
                dropped = sum(by_key.values())
                if dropped > reported_drops:
                    node.counters.add("dropped", dropped - reported_drops)
                    log.warning("writing fell %.0f MB behind: dropped %d oldest queued messages so far (%s)",
                                args.max_backlog_mb, dropped,
                                ", ".join(f"{k}: {n}" for k, n in sorted(by_key.items())))
                    reported_drops = dropped
            node.rates["backlog"] = float(len(backlog))
            node.rates["backlog_mb"] = backlog.queued_bytes / 1e6
    finally:
        writer.close()
        dropped = sum(backlog.dropped_by_key().values())
        log.info("wrote %d messages to %s%s", writer.count, writer.path,
                 f"; dropped {dropped} when writing fell behind" if dropped else "")
    return 0


def main(argv=None) -> int:
    return run_service("recorder", build_parser(), body, argv)


if __name__ == "__main__":
    sys.exit(main())
