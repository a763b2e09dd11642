"""The Zenoh bus layer every flyslam process stands on.

- :func:`add_bus_arguments` gives every command the zenoh-python examples' flags (``--config``,
  ``--connect``, ``--listen``, ``--cfg KEY:JSON5``) plus ``--hub`` (one endpoint to both listen on and
  connect to, handy for tests on unique ports) and ``--robot`` (the key prefix).
- :class:`Node` is one service's presence on the bus: its session, key prefix, a liveliness token
  (``<robot>/health/<service>``), a heartbeat (``<robot>/status/<service>``) carrying a progress counter,
  rates and counters, typed publishers and validating subscriptions.
- Sensor streams use :meth:`Node.subscribe_latest` (a slot of depth 1): a slow consumer gets the
  newest message and the skipped ones are counted from sequence gaps, never queued.
- Streams where every message matters (odometry) use :meth:`Node.subscribe` with a callback.
- Latched inputs (calibration, target, the map) use :meth:`Node.latched`; a service answers queries with
  :meth:`Node.queryable` and watches other services' liveliness with :meth:`Node.watch_liveliness`.
- Every method taking a stream accepts a :class:`common.streams.Stream` (key, schema, latched, reliable).

A malformed payload or an unknown major version is logged (rate-limited) and counted as ``rejected``;
it never raises out of a subscription.
"""
from __future__ import annotations

import argparse
import errno
import importlib.resources
import json
import logging
import os
import re
import signal
import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import zenoh

from common import messages
from common.messages import DecodeError, Heartbeat, header
from common.streams import Stream

log = logging.getLogger("flyslam.bus")

DEFAULT_CONFIG = importlib.resources.files("common") / "zenoh_local.json5"   # package data: loopback only
DEFAULT_ROBOT = "rig"


# ------------------------------------------------------------------------------ configuration


@dataclass
class BusOptions:
    """Everything needed to open a session the same way in every process of a run."""
    config: str | None = None
    connect: list[str] = field(default_factory=list)
    listen: list[str] = field(default_factory=list)
    cfg: list[str] = field(default_factory=list)
    hub: str | None = None
    robot: str = DEFAULT_ROBOT

    def to_argv(self) -> list[str]:
        """Command-line flags that reproduce these options in a child process."""
        argv = []
        if self.config:
            argv += ["--config", self.config]
        for e in self.connect:
            argv += ["--connect", e]
        for e in self.listen:
            argv += ["--listen", e]
        for c in self.cfg:
            argv += ["--cfg", c]
        if self.hub:
            argv += ["--hub", self.hub]
        argv += ["--robot", self.robot]
        return argv


def add_bus_arguments(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("Zenoh bus")
    g.add_argument("--config", help="Zenoh JSON5 configuration file (default: the packaged common/zenoh_local.json5)")
    g.add_argument("--connect", "-e", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable; replaces the file's list)")
    g.add_argument("--listen", "-l", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to listen on (repeatable; replaces the file's list)")
    g.add_argument("--cfg", action="append", default=[], metavar="KEY:JSON5",
                   help="set one configuration key, e.g. --cfg 'scouting/multicast/enabled:true'")
    g.add_argument("--hub", metavar="ENDPOINT",
                   help="shorthand: listen on ENDPOINT (if free) and on an ephemeral port, and connect to ENDPOINT")
    g.add_argument("--robot", default=os.environ.get("FLYSLAM_ROBOT", DEFAULT_ROBOT),
                   help="robot name, the prefix of every key (default: %(default)s)")


def bus_options(ns: argparse.Namespace) -> BusOptions:
    return BusOptions(config=ns.config, connect=list(ns.connect), listen=list(ns.listen), cfg=list(ns.cfg),
                      hub=ns.hub, robot=ns.robot)


class BusConfigError(ValueError):
    """A bus option (--config, --connect, --listen, --cfg, --hub) that cannot be used; the message names
    the option and what it expects."""


def _zenoh_reason(e: Exception) -> str:
    """Zenoh's error text without its Rust source locations and debug wrapping, on one line."""
    text = str(e)
    m = re.search(r'msg: "(.*?)"(?:, location|\s*\}|$)', text, re.S)
    if m:
        text = m.group(1).encode().decode("unicode_escape", errors="replace")
    text = re.sub(r"\s+at /\S+?:\d+\.?", "", text)
    text = re.sub(r'^Str\("(.*)"\)$', r"\1", text)
    return " ".join(text.split()) or type(e).__name__


def make_config(opts: BusOptions) -> zenoh.Config:
    """The session's configuration; a bad option raises BusConfigError naming it."""
    if opts.config:
        path = Path(opts.config)
        if path.is_dir():
            raise BusConfigError(f"--config {path}: is a directory, not a Zenoh JSON5 configuration file")
        if not path.is_file():
            raise BusConfigError(f"--config {path}: Zenoh configuration file not found")
        try:
            conf = zenoh.Config.from_file(str(path))
        except zenoh.ZError as e:
            raise BusConfigError(f"--config {path}: not a valid Zenoh JSON5 configuration ({_zenoh_reason(e)})") from None
    else:
        conf = zenoh.Config.from_json5(DEFAULT_CONFIG.read_text())

    def insert(flag: str, value: str, key: str, json5: str) -> None:
        try:
            conf.insert_json5(key, json5)
        except zenoh.ZError as e:
            expected = " (expected KEY:JSON5 with a Zenoh configuration key)" if flag == "--cfg" else \
                " (expected an endpoint such as tcp/192.168.1.10:7447)"
            raise BusConfigError(f"{flag} {value!r}: {_zenoh_reason(e)}{expected}") from None

    if opts.hub:
        host = opts.hub.rsplit(":", 1)[0]
        insert("--hub", opts.hub, "listen/endpoints", json.dumps([opts.hub, f"{host}:0"]))
        insert("--hub", opts.hub, "connect/endpoints", json.dumps([opts.hub]))
        conf.insert_json5("listen/exit_on_failure", "false")
    if opts.connect:
        insert("--connect", " ".join(opts.connect), "connect/endpoints", json.dumps(opts.connect))
    if opts.listen:
        insert("--listen", " ".join(opts.listen), "listen/endpoints", json.dumps(opts.listen))
    for item in opts.cfg:
        key, sep, value = item.partition(":")
        if not sep or not key:
            raise BusConfigError(f"--cfg expects KEY:JSON5 (e.g. 'scouting/multicast/enabled:true'), got {item!r}")
        insert("--cfg", item, key, value)
    _check_secured(conf, opts.config)
    return conf


TLS_FILES = ("root_ca_certificate", "listen_private_key", "listen_certificate", "connect_private_key",
             "connect_certificate")


def _check_secured(conf: zenoh.Config, source) -> None:
    """A TLS configuration must name a real host and existing certificate files (Zenoh itself would
    start with a placeholder host and no certificates, silently alone)."""
    where = f"--config {source}" if source else "the Zenoh configuration"
    endpoints = []
    for key in ("connect/endpoints", "listen/endpoints"):
        value = json.loads(conf.get_json(key) or "[]")   # a list, or Zenoh's default {mode: [endpoints]}
        endpoints += [e for v in value.values() for e in v] if isinstance(value, dict) else value
    placeholder = [e for e in endpoints if isinstance(e, str) and "ROBOT_HOST" in e]
    if placeholder:
        raise BusConfigError(f"{where}: endpoint {placeholder[0]!r} still has the ROBOT_HOST placeholder "
                             "(put the robot's DNS name or IP there, or pass --connect)")
    for name in TLS_FILES:
        value = json.loads(conf.get_json(f"transport/link/tls/{name}") or "null")
        if isinstance(value, str) and not Path(value).is_file():
            raise BusConfigError(f"{where}: transport/link/tls/{name} {value!r} not found "
                                 "(make certificates with `flyslam certs --out DIR`)")


# Zenoh's async runtimes (the ZENOH_RUNTIME variable, in RON), unless the environment sets them: one
# worker thread that also receives and connects, where Zenoh's default hands each sample from a pool of
# reception threads to a pool of application threads. A sample then costs one thread wake-up fewer:
# ~1.3 CPU-ms a frame across the pipeline's ~32 deliveries a frame (bench/pipeline.py, 4 % of its CPU).
ZENOH_RUNTIME_DEFAULT = ("(rx: (handover: app), net: (handover: app), acc: (handover: app), "
                         "app: (worker_threads: 1), tx: (worker_threads: 1))")


def open_session(opts: BusOptions) -> zenoh.Session:
    """A session of ``opts``; ZENOH_RUNTIME_DEFAULT unless ZENOH_RUNTIME is set (it is read once a
    process, at its first session)."""
    conf = make_config(opts)
    if not os.environ.get("ZENOH_RUNTIME", "").strip():
        os.environ["ZENOH_RUNTIME"] = ZENOH_RUNTIME_DEFAULT
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        raise BusConfigError(f"cannot open the Zenoh session: {_zenoh_reason(e)}") from None
    except BaseException as e:   # a Rust panic reaches Python as pyo3's PanicException, a BaseException
        if type(e).__name__ != "PanicException":
            raise
        reason = (str(e).splitlines() or [""])[0][:160]
        raise BusConfigError(f"cannot open the Zenoh session: ZENOH_RUNTIME={os.environ['ZENOH_RUNTIME']!r} is "
                             f"not a valid Zenoh runtime configuration (RON, e.g. '(app: (worker_threads: 1))'): "
                             f"{reason}") from None


def _hub_endpoint(conf: zenoh.Config) -> tuple[str, int] | None:
    """(host, port) of the first fixed-port TCP-based endpoint (tcp, tls, ws) the configuration listens
    on: the local hub."""
    try:
        endpoints = json.loads(conf.get_json("listen/endpoints"))
    except (zenoh.ZError, ValueError, TypeError):
        return None
    for e in endpoints if isinstance(endpoints, list) else []:
        m = re.fullmatch(r"(?:tcp|tls|ws)/\[?([^\]]+?)\]?:(\d+)", re.split(r"[?#]", str(e))[0])
        if m and int(m.group(2)) > 0:
            return m.group(1), int(m.group(2))
    return None


def port_free(host: str, port: int) -> bool:
    """Whether a TCP listener could bind ``host:port`` now (IPv6 when the host has a colon); an address
    this machine does not have counts as free (nobody here holds it)."""
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as e:
            return e.errno != errno.EADDRINUSE
    return True


def services_alive(opts: BusOptions, wait_s: float = 2.0) -> list[str]:
    """The services of ``opts.robot`` alive on the bus these options join (their liveliness tokens), or
    [] at once when nobody holds the hub's port: a second run on a machine would otherwise join the first
    one's bus and each would take the other's frames.  A peer sees the tokens of the sessions it has
    linked to, and gossip links them one by one: asked until two answers agree, within ``wait_s``.
    Raises BusConfigError when the session cannot open."""
    hub = _hub_endpoint(make_config(opts))
    if hub is None or port_free(*hub):
        return []
    with open_session(opts) as session:
        deadline = time.monotonic() + wait_s
        while (not list(session.info.peers_zid()) and not list(session.info.routers_zid())
               and time.monotonic() < deadline):
            time.sleep(0.05)
        names: list[str] = []
        while time.monotonic() < deadline:
            replies = session.liveliness().get(f"{opts.robot}/health/*", timeout=0.5)
            answer = sorted({str(r.ok.key_expr).rsplit("/", 1)[-1] for r in replies if r.ok is not None})
            if answer and answer == names:
                break
            names = answer
            time.sleep(0.2)
        return names


# ----------------------------------------------------------------------------------- counters


class Counters:
    """Thread-safe named counters (Zenoh callbacks run on Zenoh's threads)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._values: dict[str, int] = {}

    def add(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._values[name] = self._values.get(name, 0) + n

    def get(self, name: str) -> int:
        with self._lock:
            return self._values.get(name, 0)

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self._values)


class _RateLimitedLog:
    """Log the first few occurrences of a problem, then every 100th, so a flood cannot drown the log."""

    def __init__(self):
        self._n: dict[str, int] = {}

    def warn(self, kind: str, text: str) -> None:
        n = self._n[kind] = self._n.get(kind, 0) + 1
        if n <= 5 or n % 100 == 0:
            log.warning("%s (%d so far)", text, n)


# ------------------------------------------------------------------------------ subscriptions


class LatestSubscription:
    """Latest-value subscription: a one-message slot, plus validation.

    :meth:`take` returns the newest valid message not yet taken (or None); :meth:`wait` blocks on the
    slot (no polling: an idle consumer costs nothing). Only the message taken is decoded. Messages
    overwritten before being taken are counted as ``skipped`` from gaps in the envelope's seq (a restart
    of the publisher, i.e. seq going backwards, is not counted as a gap).

    ``polled`` (for a consumer that only calls :meth:`take`, on its own period): the slot is Zenoh's
    one-sample ring channel, so a sample overwritten before it is taken never reaches Python (Zenoh's
    own threads still receive it; no Python thread runs and no GIL is taken for it). Without it a
    Zenoh callback fills the slot, which :meth:`wait` needs.
    """

    def __init__(self, node: "Node", key: str, expected, name: str, polled: bool = False):
        self._node, self._expected, self.name = node, expected, name
        self._ready = threading.Condition()
        self._payload = None          # the newest zenoh payload not yet taken
        self.polled = bool(polled)
        self._sub = node.session.declare_subscriber(
            key, zenoh.handlers.RingChannel(1) if self.polled else self._on_sample)
        self.received = 0
        self.skipped = 0
        self._last_seq: int | None = None
        self._closed = False

    def _on_sample(self, sample: zenoh.Sample) -> None:
        with self._ready:
            self._payload = (sample.payload, sample.attachment)
            self._ready.notify()

    def take(self):
        if self.polled:
            if self._closed:
                return None
            sample = self._sub.try_recv()
            payload = None if sample is None else (sample.payload, sample.attachment)
        else:
            with self._ready:
                payload, self._payload = self._payload, None
        if payload is None:
            return None
        data, side = payload
        msg = self._node.decode(data.to_bytes(), self._expected, self.name,
                                side.to_bytes() if side is not None else None)
        if msg is None:
            return None
        self.received += 1
        seq = msg.header.seq
        if self._last_seq is not None and seq > self._last_seq + 1:
            gap = seq - self._last_seq - 1
            self.skipped += gap
            self._node.counters.add(f"{self.name}_skipped", gap)
        self._last_seq = seq
        return msg

    def wait(self, timeout: float, poll: float = 0.1):
        """Block up to ``timeout`` seconds (or until the node stops: checked every ``poll`` s) for the
        next message."""
        if self.polled:
            raise RuntimeError(f"{self.name}: a polled subscription has take() only, not wait()")
        deadline = time.monotonic() + timeout
        while not self._node.stopping:
            msg = self.take()
            left = deadline - time.monotonic()
            if msg is not None or left <= 0:
                return msg
            with self._ready:
                if self._payload is None:
                    self._ready.wait(min(left, poll))
        return None

    def close(self):
        self._closed = True
        self._sub.undeclare()


class Publisher:
    """Typed publisher: encodes messages and stamps the envelope's seq when left at 0; a message's side
    fields (``common.codec.array_field(side=True)``) go as the sample's attachment."""

    def __init__(self, node: "Node", key: str, latched: bool = False, reliable: bool = False):
        self._node, self.key = node, key
        # Live sensor data may be dropped under congestion (the newest frame matters); a replay or a
        # command stream blocks instead so that nothing is lost.
        congestion = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
        self._pub = node.session.declare_publisher(key, congestion_control=congestion)
        self.seq = 0
        self._last: bytes | None = None
        self._queryable = None
        if latched:
            # Late joiners query the key and get the last message (calibration, map, targets...).
            self._queryable = node.session.declare_queryable(key, self._answer, complete=True)

    def _answer(self, query: zenoh.Query) -> None:
        last = self._last
        if last is not None:
            query.reply(self.key, last)

    def publish(self, msg) -> bytes:
        self.seq += 1
        if msg.header.seq == 0:
            msg.header.seq = self.seq
        payload = messages.encode(msg)
        side = messages.encode_side(msg)
        if side is None:
            self._pub.put(payload)
        else:
            self._pub.put(payload, attachment=side)
        if self._queryable is not None:
            self._last = payload
        self._node.counters.add("published")
        return payload

    def has_subscribers(self) -> bool:
        """Whether a subscriber somewhere on the bus matches this key now."""
        return bool(self._pub.matching_status.matching)

    def put_raw(self, payload: bytes) -> None:
        """Publish already-encoded bytes unchanged (replay)."""
        self._pub.put(payload)
        if self._queryable is not None:
            self._last = payload


def _resolve(stream, expected) -> tuple[str, object]:
    """(key under the robot prefix, schema) of a Stream or of a key string with its schema."""
    if isinstance(stream, Stream):
        return stream.key, expected if expected is not None else stream.schema
    return stream, expected


class Latched:
    """The newest value of a latched stream: a callback subscription, seeded by asking the latched
    publishers (:meth:`Node.query_latest`) and asked again every ``retry_s`` while still missing (a
    replay publishes its calibration once), or every ``refresh_s`` in any case (a queryable such as the
    map). :meth:`get` never blocks; :meth:`take` returns a value once, when it is new."""

    def __init__(self, node: "Node", stream: str, expected, retry_s: float, refresh_s: float | None,
                 timeout: float = 1.0):
        self._node, self.stream, self._expected = node, stream, expected
        self.retry_s, self.refresh_s, self.timeout = retry_s, refresh_s, timeout
        self._lock = threading.Lock()
        self._value = None
        self._taken = None
        self._last_query = 0.0
        node.subscribe(stream, expected, callback=self.set)

    def set(self, value) -> None:
        if value is None:
            return
        with self._lock:
            self._value = value

    def get(self):
        with self._lock:
            return self._value

    def take(self):
        """The value if it changed since the last take, else None."""
        with self._lock:
            if self._value is None or self._value is self._taken:
                return None
            self._taken = self._value
            return self._value

    def due(self) -> bool:
        period = self.refresh_s if self.refresh_s is not None else (self.retry_s if self.get() is None else None)
        return period is not None and time.monotonic() - self._last_query >= period

    def query(self, timeout: float) -> None:
        self._last_query = time.monotonic()
        self.set(self._node.query_latest(self.stream, self._expected, timeout=timeout))


# --------------------------------------------------------------------------------------- node


class Node:
    """One service's presence on the bus. Use as a context manager::

        with Node("evolver", opts) as node:
            frames = node.subscribe_latest("stereo/frame", StereoFrame)
            out = node.publisher("flies/population")
            while not node.stopping:
                ...
                node.progress += 1
    """

    def __init__(self, service: str, opts: BusOptions | None = None, heartbeat_period: float = 1.0,
                 handle_signals: bool = True):
        self.service = service
        self.opts = opts or BusOptions()
        self.robot = self.opts.robot
        self.counters = Counters()
        self.progress = 0
        self.state = "starting"
        self.rates: dict[str, float] = {}
        self._stop = threading.Event()
        self._heartbeat_period = heartbeat_period
        self._bad = _RateLimitedLog()
        self.session = open_session(self.opts)
        self._token = self.session.liveliness().declare_token(self.key(f"health/{service}"))
        self._status_pub = Publisher(self, self.key(f"status/{service}"))
        self._subscriptions: list = []
        self._latched: list[Latched] = []
        self._latched_lock = threading.Lock()
        self._latched_thread: threading.Thread | None = None
        if handle_signals and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, self._on_signal)
            signal.signal(signal.SIGINT, self._on_signal)
        self._hb_thread = threading.Thread(target=self._heartbeat_loop, name=f"{service}-heartbeat", daemon=True)
        self._hb_thread.start()

    # -------------------------------------------------------------------------------- lifecycle
    def __enter__(self):
        self.state = "running"
        return self

    def __exit__(self, *exc):
        self.close()

    def _on_signal(self, signum, _frame):
        log.info("%s: signal %d, stopping", self.service, signum)
        self._stop.set()

    def stop(self) -> None:
        self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def sleep(self, seconds: float) -> bool:
        """Sleep unless asked to stop; returns False when stopping."""
        return not self._stop.wait(seconds)

    def close(self) -> None:
        self._stop.set()
        self.state = "stopped"
        self._hb_thread.join(timeout=2)
        try:
            self._publish_heartbeat()
            self._token.undeclare()
            self.session.close()
        except Exception as e:  # closing a session whose peers vanished must not mask the real exit
            log.debug("closing session: %s", e)

    # ------------------------------------------------------------------------------------- keys
    def key(self, stream: str) -> str:
        """Full key expression ``<robot>/<stream>``."""
        return f"{self.robot}/{stream}"

    # ---------------------------------------------------------------------------------- decoding
    def decode(self, payload: bytes, expected, name: str, side: bytes | None = None):
        """Decode and validate (``side``: the sample's attachment); count and log a rejected payload and
        return None."""
        try:
            msg = messages.decode(payload, expected, side)
        except DecodeError as e:
            self.counters.add("rejected")
            self.counters.add(f"{name}_rejected")
            self._bad.warn(name, f"{self.service}: rejected a message on {name}: {type(e).__name__}: {e}")
            return None
        self.counters.add(f"{name}_received")
        return msg

    # ----------------------------------------------------------------------------- pub / sub
    def publisher(self, stream: "str | Stream", latched: bool = False, reliable: bool = False) -> Publisher:
        """Typed publisher; a :class:`common.streams.Stream` brings its own latched/reliable flags."""
        if isinstance(stream, Stream):
            latched, reliable, stream = latched or stream.latched, reliable or stream.reliable, stream.key
        return Publisher(self, self.key(stream), latched=latched, reliable=reliable)

    def subscribe_latest(self, stream: "str | Stream", expected=None, polled: bool = False) -> LatestSubscription:
        """Latest-value subscription (see :class:`LatestSubscription`; ``polled`` for take()-only consumers)."""
        stream, expected = _resolve(stream, expected)
        sub = LatestSubscription(self, self.key(stream), expected, stream.replace("/", "_"), polled)
        self._subscriptions.append(sub)
        return sub

    def subscribe(self, stream: "str | Stream", expected=None, callback: Callable | None = None, raw: bool = False):
        """Callback subscription (runs on a Zenoh thread). Invalid payloads are counted, not passed on.

        Exceptions raised by the callback are logged and counted as ``callback_errors`` so that one bad
        message cannot kill the subscription. With ``raw=True`` the callback gets (key, bytes) unvalidated:
        the payload only, not the side fields that travel as its attachment (so a recording lacks them).
        """
        stream, expected = _resolve(stream, expected)
        name = stream.replace("/", "_").replace("*", "any")

        def on_sample(sample: zenoh.Sample):
            try:
                payload = sample.payload.to_bytes()
                if raw:
                    callback(str(sample.key_expr), payload)
                    return
                side = sample.attachment
                msg = self.decode(payload, expected, name, side.to_bytes() if side is not None else None)
                if msg is not None:
                    callback(msg)
            except Exception as e:  # noqa: BLE001 - a service must survive any single message
                self.counters.add("callback_errors")
                self._bad.warn(f"cb-{name}", f"{self.service}: error handling {name}: {type(e).__name__}: {e}")

        sub = self.session.declare_subscriber(self.key(stream), on_sample)
        self._subscriptions.append(sub)
        return sub

    def query_latest(self, stream: "str | Stream", expected=None, timeout: float = 1.0):
        """Ask latched publishers of ``stream`` for their last message (None if nobody answers)."""
        stream, expected = _resolve(stream, expected)
        replies = self.session.get(self.key(stream), timeout=timeout)
        for reply in replies:
            if reply.ok is not None:
                msg = self.decode(reply.ok.payload.to_bytes(), expected, stream.replace("/", "_"))
                if msg is not None:
                    return msg
        return None

    def latched(self, stream: "str | Stream", expected=None, timeout: float = 1.0, retry_s: float = 1.0,
                refresh_s: float | None = None) -> "Latched":
        """The newest value of a latched stream (calibration, target...): see :class:`Latched`."""
        stream, expected = _resolve(stream, expected)
        value = Latched(self, stream, expected, retry_s, refresh_s, timeout)
        with self._latched_lock:
            self._latched.append(value)
            if self._latched_thread is None:
                self._latched_thread = threading.Thread(target=self._latched_loop, name=f"{self.service}-latched",
                                                        daemon=True)
                self._latched_thread.start()
        value.query(timeout)
        return value

    def _latched_loop(self) -> None:
        while not self._stop.wait(0.1):
            with self._latched_lock:
                due = [v for v in self._latched if v.due()]
            for v in due:
                try:
                    v.query(v.timeout)
                except Exception as e:  # the session may be closing
                    log.debug("latched query: %s", e)

    def queryable(self, stream: "str | Stream", handler: Callable[[], object]):
        """Answer queries on ``stream`` with ``handler()`` (a message, encoded here; None: no answer).
        The handler runs on a Zenoh thread; its errors are counted as ``query_errors``."""
        stream, _ = _resolve(stream, None)

        def answer(query: zenoh.Query) -> None:
            try:
                msg = handler()
                if msg is not None:
                    query.reply(query.key_expr, messages.encode(msg))
            except Exception as e:  # noqa: BLE001 - one failed answer must not kill the queryable
                self.counters.add("query_errors")
                self._bad.warn(f"q-{stream}", f"{self.service}: answering {stream}: {type(e).__name__}: {e}")

        q = self.session.declare_queryable(self.key(stream), answer)
        self._subscriptions.append(q)
        return q

    def hold_latched(self, stream: "str | Stream") -> None:
        """Keep the newest payload of ``stream``, whoever publishes it, and answer queries with it: a
        restarted service recovers its state from the bus even when the process that published it is
        the one that died (the supervisor does this for its launch file's ``latch`` streams).

        The newest sample waits in Zenoh's one-sample ring channel: a 30 Hz stream never reaches
        Python here (no GIL taken per sample); a query reads the ring, and the last payload read is
        kept for when the ring is empty.  A failed answer is counted as ``query_errors``."""
        stream, _ = _resolve(stream, None)
        key = self.key(stream)
        newest = self.session.declare_subscriber(key, zenoh.handlers.RingChannel(1))
        last: list[bytes | None] = [None]
        lock = threading.Lock()

        def answer(query: zenoh.Query) -> None:
            try:
                with lock:
                    sample = newest.try_recv()
                    if sample is not None:
                        last[0] = sample.payload.to_bytes()
                    payload = last[0]
                if payload is not None:
                    query.reply(key, payload)
            except Exception as e:  # noqa: BLE001 - e.g. the session closing; one answer must not kill it
                self.counters.add("query_errors")
                self._bad.warn(f"hold-{stream}", f"{self.service}: answering {stream}: {type(e).__name__}: {e}")

        self._subscriptions += [newest, self.session.declare_queryable(key, answer)]

    def watch_liveliness(self, prefix: str, callback: Callable[[str, bool], None]):
        """Call ``callback(name, alive)`` for every liveliness token under ``<robot>/<prefix>`` (e.g.
        ``health/``), for those already alive too; ``name`` is the key after the prefix."""
        full = self.key(prefix)

        def on_sample(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            if key.startswith(full):
                callback(key[len(full):], sample.kind == zenoh.SampleKind.PUT)

        sub = self.session.liveliness().declare_subscriber(full + "*", on_sample, history=True)
        self._subscriptions.append(sub)
        return sub

    # --------------------------------------------------------------------------------- heartbeat
    def _publish_heartbeat(self) -> None:
        hb = Heartbeat(service=self.service, pid=os.getpid(), state=self.state, progress=int(self.progress),
                       rates={k: float(v) for k, v in self.rates.items()},
                       counters=self.counters.snapshot(), header=header(0, time.time_ns(), ""))
        self._status_pub.publish(hb)

    def _heartbeat_loop(self) -> None:
        last_progress, last_t = self.progress, time.monotonic()
        while not self._stop.wait(self._heartbeat_period):
            now = time.monotonic()
            self.rates["progress_per_s"] = (self.progress - last_progress) / max(now - last_t, 1e-9)
            last_progress, last_t = self.progress, now
            try:
                self._publish_heartbeat()
            except Exception as e:  # the session may be closing
                log.debug("heartbeat: %s", e)


def setup_logging(service: str, level: str | None = None) -> None:
    logging.basicConfig(level=(level or os.environ.get("FLYSLAM_LOG", "INFO")).upper(),
                        format=f"%(asctime)s {service} %(levelname)s %(message)s", datefmt="%H:%M:%S")
