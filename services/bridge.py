"""Rerun bridge: logs the bus (images, flies, map, trajectories, field, commands, health) to Rerun, live and/or .rrd.

Thin on purpose: subscriptions here, the message → Rerun mapping in :mod:`common.viz`.

- Sensor-rate streams (stereo frames, fly populations, the harmonic field) are latest-value
  subscriptions polled at ``--image-hz``: the bridge never queues images it cannot afford to log.
- Poses, commands, heartbeats, calibration and targets arrive by callback into a bounded inbox that the
  main loop drains (Rerun's timelines are per thread, so all logging happens on the main thread).
- The latched calibration, the target and the localiser's map (a queryable, asked every ``--map-period-s``
  seconds) come through :meth:`common.bus.Node.latched`.
- Liveliness tokens (``health/*``) are watched so that a vanished service shows as 0 in "Alive".

Sinks: ``--rrd PATH`` (closed cleanly on SIGTERM/SIGINT so that ``rerun rrd verify`` passes) and a live
gRPC server (``--grpc-port``) with a web viewer (``--web-port``), both bound to ``--bind`` (loopback by
default). The in-process web viewer of rerun-sdk 0.41 always listens on all interfaces, so the web
viewer runs as a ``rerun --serve-web --bind ...`` child process, which honours the address.
"""
from __future__ import annotations

import collections
import logging
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

# Rerun's native allocator (mimalloc) by default keeps freed pages for a while before returning them; with
# images and thousands of small log calls a second the bridge's RSS crept up. Returning them at once
# (read when rerun's library loads, so before the import) slows that creep.
os.environ.setdefault("MIMALLOC_PURGE_DELAY", "0")
import rerun as rr  # noqa: E402

from common import streams as S
from common.bus import port_free
from common.recording import claim_segment
from common.viz import RerunLogger, blueprint
from common.viz.logger import PoseRate, finite_pose
from services.base import run_service, service_parser, survive

log = logging.getLogger("flyslam.bridge")

# Streams delivered by callback: every message matters (trajectories, commands, health).
CALLBACK_STREAMS = [S.SLAM_POSE, S.FUSION_POSE, S.FUSION_ODOM, S.TRUTH_POSE, S.PLANNER_CMD_VEL, S.PLANNER_TARGET,
                    S.STATUS]
POSE_STREAMS = {s.key for s in (S.SLAM_POSE, S.FUSION_POSE, S.FUSION_ODOM, S.TRUTH_POSE)}
# Streams where only the newest message is worth logging.
LATEST_STREAMS = [S.STEREO_FRAME, S.FLIES_POPULATION, S.PLANNER_FIELD, S.FUSION_SONAR_POINTS]
INBOX_MAX_BYTES = 8 * 1024 * 1024      # ~5,000 small messages: half a minute of a stalled main loop
MESSAGE_OVERHEAD_BYTES = 1536          # a decoded PoseEstimate holds ~1.5 kB beyond its arrays' data


def build_parser():
    p = service_parser("bridge", __doc__.splitlines()[0])
    p.add_argument("--rrd", help="write the recording to this .rrd file, or to the next free <stem>.<n>.rrd "
                                    "if it exists")
    p.add_argument("--grpc-port", type=int, default=9876, help="live gRPC server for viewers (0: none)")
    p.add_argument("--web-port", type=int, default=9090, help="web viewer over HTTP (0: none; needs --grpc-port)")
    p.add_argument("--bind", default="127.0.0.1",
                   help="address the live servers listen on; 0.0.0.0 exposes them to the network")
    p.add_argument("--server-memory-limit", default="48MiB",
                   help="newest data the live server keeps for late viewers (~30 s of the demo; the .rrd has it all)")
    p.add_argument("--image-hz", type=float, default=10.0, help="log images, flies and the field at most this often")
    p.add_argument("--pose-hz", type=float, default=30.0,
                   help="log each pose stream at most this often (sensor time): a flood of poses costs no memory")
    p.add_argument("--max-flies", type=int, default=20_000, help="subsample larger populations to this many")
    p.add_argument("--max-map-points", type=int, default=100_000, help="subsample the map to this many points")
    p.add_argument("--jpeg-quality", type=int, default=80, help="quality when raw images must be compressed")
    p.add_argument("--map-period-s", type=float, default=3.0, help="query the localiser's map this often")
    p.add_argument("--application-id", default="flyslam", help="Rerun application id")
    return p


def open_sinks(args) -> tuple[list, str | None]:
    """(sinks, live gRPC URI or None). A busy live port is reported and skipped, never fatal: the file
    matters more than the live view (rerun would otherwise fail every flush)."""
    sinks, uri = [], None
    if args.rrd:
        path = Path(args.rrd)
        if not path.parent.is_dir():
            raise SystemExit(f"bridge: directory of --rrd {path} does not exist")
        path = claim_segment(path)   # a restarted bridge writes run.1.rrd, … and never overwrites
        log.info("writing %s", path)
        sinks.append(rr.FileSink(str(path)))
    if args.grpc_port:
        if port_free(args.bind, args.grpc_port):
            server = rr.GrpcServerSink(bind_ip=args.bind, port=args.grpc_port,
                                       server_memory_limit=args.server_memory_limit)
            sinks.append(server)
            uri = server.uri
        else:
            log.warning("port %s:%d is busy: no live gRPC server (the .rrd is still written)", args.bind,
                        args.grpc_port)
    if not sinks:
        raise SystemExit("bridge: nothing to do: give --rrd and/or a free --grpc-port")
    return sinks, uri


def rerun_binary() -> str:
    """The rerun executable itself (``.venv/bin/rerun`` is a Python wrapper whose child would outlive a
    terminate())."""
    import rerun_cli

    exe = Path(rerun_cli.__file__).parent / "rerun"
    if not exe.is_file():
        raise SystemExit(f"bridge: rerun executable not found at {exe}")
    return str(exe)


def start_web_viewer(args, grpc_uri: str) -> subprocess.Popen | None:
    if not args.web_port:
        return None
    if not port_free(args.bind, args.web_port):
        log.warning("port %s:%d is busy: no web viewer", args.bind, args.web_port)
        return None
    cmd = [rerun_binary(), "--serve-web", "--bind", args.bind,
           "--web-viewer-port", str(args.web_port), grpc_uri]
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    log.info("web viewer: http://%s:%d/?url=%s", args.bind, args.web_port, grpc_uri)
    return proc


class Inbox:
    """Queue of (stream, message) filled by Zenoh callbacks, bounded in bytes (estimated from the
    messages' arrays): past ``max_bytes`` the oldest are dropped and counted, the callbacks never block."""

    def __init__(self, node, max_bytes: int = INBOX_MAX_BYTES):
        self._q: collections.deque = collections.deque()
        self._lock = threading.Lock()
        self._bytes = 0
        self.max_bytes = max_bytes
        self._node = node

    @staticmethod
    def _cost(msg) -> int:
        """Rough resident size of a message: its numpy arrays plus a fixed overhead."""
        fields = vars(msg).values() if hasattr(msg, "__dict__") else ()
        return MESSAGE_OVERHEAD_BYTES + sum(a.nbytes for a in fields if isinstance(a, np.ndarray))

    def put(self, stream: str, msg) -> None:
        cost = self._cost(msg)
        with self._lock:
            self._q.append((stream, msg, cost))
            self._bytes += cost
            while self._bytes > self.max_bytes and len(self._q) > 1:
                _, _, dropped = self._q.popleft()
                self._bytes -= dropped
                self._node.counters.add("inbox_dropped")

    def size(self) -> int:
        return len(self._q)

    def bytes(self) -> int:
        return self._bytes

    def drain(self):
        while True:
            with self._lock:
                if not self._q:
                    return
                stream, msg, cost = self._q.popleft()
                self._bytes -= cost
            yield stream, msg


class PoseThinning:
    """Lets through the poses :meth:`common.viz.RerunLogger.pose` would log (its :class:`PoseRate` rule;
    a rejected or non-finite pose is not one and does not move the clock) and every status change,
    decided on arrival (Zenoh threads), so that a flood of poses never queues in the inbox faster than
    the main loop logs it."""

    def __init__(self, period_s: float):
        self._rate = PoseRate(int(period_s * 1e9))
        self._status: dict[str, str] = {}
        self._lock = threading.Lock()

    def keep(self, stream: str, msg) -> bool:
        status = msg.status
        loggable = not status.startswith("rejected") and finite_pose(msg)
        with self._lock:
            changed = status != self._status.get(stream)
            self._status[stream] = status
            return (loggable and self._rate.due(stream, msg.header.stamp_ns)) or changed


def subscribe_all(node, inbox: Inbox, map_period_s: float, pose_period_s: float):
    """Callback streams and liveliness into the inbox (pose streams thinned to what the logger logs);
    (latest-value subscriptions, latched inputs)."""
    thinning = PoseThinning(pose_period_s)
    for stream in CALLBACK_STREAMS:
        name = "status" if stream is S.STATUS else stream.key
        if name in POSE_STREAMS:
            node.subscribe(stream, callback=lambda msg, name=name: thinning.keep(name, msg) and inbox.put(name, msg))
        else:
            node.subscribe(stream, callback=lambda msg, name=name: inbox.put(name, msg))
    node.watch_liveliness(S.HEALTH_PREFIX, lambda service, alive: inbox.put("health", (service, alive)))
    latest = {stream.key: node.subscribe_latest(stream, polled=True) for stream in LATEST_STREAMS}
    # The target comes by callback too; asked for as well, since a target published once before the
    # subscription matched its publisher (a bridge started with the planner) was otherwise never shown.
    latched = {S.STEREO_CALIBRATION.key: node.latched(S.STEREO_CALIBRATION),
               S.PLANNER_TARGET.key: node.latched(S.PLANNER_TARGET),
               S.SLAM_MAP.key: node.latched(S.SLAM_MAP, refresh_s=map_period_s)}
    return latest, latched


def log_batch(node, viz: RerunLogger, batch) -> None:
    """Log (stream, message) pairs; a message that cannot be viewed (cv2.error, a rerun error...) is
    counted as ``view_errors`` and logged, not fatal."""
    for stream, msg in batch:
        with survive(node, "view", log, on=stream):
            if stream == "health":
                viz.liveliness(*msg)
            else:
                viz.handle(stream, msg)
            node.progress += 1


def close_sinks(rec, viz: RerunLogger, web) -> None:
    try:
        viz.finish()
    finally:
        try:
            rec.flush(timeout_sec=10.0)
        except RuntimeError as e:  # a live sink that died must not keep the file from closing
            log.warning("flushing: %s", e)
        rec.disconnect()
        if web is not None:
            web.terminate()
            try:
                web.wait(5)
            except subprocess.TimeoutExpired:
                web.kill()


def body(node, args) -> int:
    if args.image_hz <= 0 or args.map_period_s <= 0 or args.pose_hz <= 0:
        raise SystemExit("bridge: --image-hz, --pose-hz and --map-period-s must be positive")
    sinks, grpc_uri = open_sinks(args)
    rec = rr.RecordingStream(args.application_id, send_properties=True)
    # the planner's views join the layout when the planner shows up (a replay or a camera has none)
    rec.set_sinks(*sinks, default_blueprint=blueprint(planner=False))
    viz = RerunLogger(rec, max_flies=args.max_flies, max_map_points=args.max_map_points,
                      jpeg_quality=args.jpeg_quality, pose_period_s=1.0 / args.pose_hz, planner_layout=False)
    web = start_web_viewer(args, grpc_uri) if grpc_uri else None
    log.info("live: rerun %s; recording to %s", grpc_uri, args.rrd)
    inbox = Inbox(node)
    latest, latched = subscribe_all(node, inbox, args.map_period_s, 1.0 / args.pose_hz)
    try:
        while True:
            t0 = time.monotonic()
            last_round = node.stopping  # one more round after the stop request drains what arrived
            node.rates["inbox_backlog"] = float(inbox.size())
            node.rates["inbox_mb"] = round(inbox.bytes() / 2**20, 2)
            batch = list(inbox.drain())
            batch += [(stream, msg) for stream, sub in latched.items() if (msg := sub.take()) is not None]
            batch += [(stream, msg) for stream, sub in latest.items() if (msg := sub.take()) is not None]
            log_batch(node, viz, batch)
            if last_round:
                break
            node.sleep(max(0.0, 1.0 / args.image_hz - (time.monotonic() - t0)))
    finally:
        close_sinks(rec, viz, web)
        log.info("bridge stopped after logging %d messages", node.progress)
    return 0


def main(argv=None) -> int:
    return run_service("bridge", build_parser(), body, argv)


if __name__ == "__main__":
    sys.exit(main())
