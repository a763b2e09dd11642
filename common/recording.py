"""Recordings: flyslam messages in MCAP files.

Layout of a flyslam recording:
- one MCAP channel per Zenoh key (topic = the full key, e.g. ``rig/stereo/frame``), message encoding
  ``msgpack``, the channel's schema named after the flyslam schema (``flyslam.StereoFrame``);
- each message's payload is the exact bytes seen on the bus, ``log_time`` = receive time,
  ``publish_time`` = the envelope's ``stamp_ns``;
- chunked and zstd-compressed; metadata records ``flyslam.calibration`` (the calibration payload,
  base64) and ``flyslam.config`` (the effective configuration of the run, JSON).

:meth:`RecordingWriter.flush` closes the chunk in progress and pushes it to the OS, so
a recorder killed with SIGKILL leaves a file readable up to its last complete chunk. The reader streams
records in file order and, on a truncated or corrupt file, yields what it could read and then reports
the problem (:attr:`RecordingReader.error`) instead of raising half-way.

A run's recording may be several *segments*: a restarted recorder never overwrites, it opens the next
free name (``recording.mcap``, then ``recording.1.mcap``, ``recording.2.mcap``, …; :func:`open_segment`;
:func:`claim_segment` names the bridge's ``run.rrd`` segments the same way).
:class:`RecordingReader` given the base path (or the run's folder) reads every segment, in number
order, as one recording; given ``recording.1.mcap`` it reads that segment alone.

MCAP stores times as uint64: a payload whose ``stamp_ns`` cannot be stored (negative, ≥ 2⁶⁴, not an
integer) is still recorded, with ``publish_time`` = its receive time, and counted
(:attr:`RecordingWriter.bad_stamps`).
"""
from __future__ import annotations

import base64
import collections
import json
import re
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import zenoh
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from common import messages

MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "flyslam-msgpack"  # our schemas are Python dataclasses; the name identifies them
CALIBRATION_METADATA = "flyslam.calibration"
CONFIG_METADATA = "flyslam.config"
UINT64_LIMIT = 1 << 64
_SEGMENT_NAME = re.compile(r"^(?P<stem>.+)\.(?P<n>[0-9]+)(?P<suffix>\.mcap)$")


class RecorderBacklog:
    """Messages received on the bus's threads, waiting for the recorder's writer loop; bounded in bytes.

    A recorder must keep up, but a niced one on a loaded machine can fall behind for minutes.  Past
    ``max_bytes`` of queued payloads the OLDEST are dropped and counted per key (as rosbag's
    ``--buffsize``), so the recording loses a stretch, says so, and the machine's memory stays bounded;
    an unbounded queue would grow until the machine swapped and starved every other service too.
    ``max_bytes`` 0: unbounded."""

    def __init__(self, max_bytes: int):
        self.max_bytes = int(max_bytes)
        self._items: collections.deque = collections.deque()
        self._bytes = 0
        self._ready = threading.Condition()
        self._dropped: dict[str, int] = {}

    def put(self, key: str, payload: bytes, recv_ns: int) -> None:
        with self._ready:
            self._items.append((key, payload, recv_ns))
            self._bytes += len(payload)
            while self.max_bytes and self._bytes > self.max_bytes and len(self._items) > 1:
                old_key, old_payload, _ = self._items.popleft()
                self._bytes -= len(old_payload)
                self._dropped[old_key] = self._dropped.get(old_key, 0) + 1
            self._ready.notify()

    def get(self, timeout: float) -> tuple[str, bytes, int] | None:
        """The oldest message, or None if none came within ``timeout`` seconds."""
        with self._ready:
            if not self._items and not self._ready.wait_for(lambda: self._items, timeout):
                return None
            item = self._items.popleft()
            self._bytes -= len(item[1])
            return item

    @property
    def queued_bytes(self) -> int:
        with self._ready:
            return self._bytes

    def __len__(self) -> int:
        with self._ready:
            return len(self._items)

    def dropped_by_key(self) -> dict[str, int]:
        """Messages dropped so far, per key (a copy: the bus's threads keep adding)."""
        with self._ready:
            return dict(self._dropped)


class KeyFilter:
    """Which bus keys a recorder keeps: those one of ``patterns`` includes, by Zenoh's own key-expression
    rules (``*`` one chunk, ``**`` any number, ``$*`` within a chunk). Each key is decided once and
    remembered, up to ``cache_size`` keys (then forgotten and decided again: a bus may carry any number
    of keys). Called from Zenoh's threads: a dict read or write is atomic."""

    def __init__(self, patterns: list[str], cache_size: int = 4096):
        self._patterns = []
        for p in patterns:
            try:
                self._patterns.append(zenoh.KeyExpr.autocanonize(p))
            except zenoh.ZError as e:
                reason = str(e).split(" at ")[0]
                raise ValueError(f"--keys {p!r} is not a Zenoh key expression ({reason})") from None
        self.cache_size = cache_size
        self._decided: dict[str, bool] = {}

    @property
    def remembered_keys(self) -> int:
        return len(self._decided)

    def __call__(self, key: str) -> bool:
        keep = self._decided.get(key)
        if keep is None:
            try:
                concrete = zenoh.KeyExpr(key)
            except zenoh.ZError:
                return False
            keep = any(p.includes(concrete) for p in self._patterns)
            if len(self._decided) >= self.cache_size:
                self._decided.clear()
            self._decided[key] = keep
        return keep


class RecordingError(Exception):
    """A recording that cannot be opened or read; the message names the file and the problem."""


@dataclass
class RecordedMessage:
    key: str
    schema: str
    log_time_ns: int
    publish_time_ns: int
    payload: bytes


# ------------------------------------------------------------------------------------- writing


def segment_path(base: str | Path, n: int) -> Path:
    """Name of segment ``n`` of the recording ``base``: 0 is ``base`` itself, then ``<stem>.<n><suffix>``."""
    base = Path(base)
    return base if n == 0 else base.with_name(f"{base.stem}.{n}{base.suffix}")


def _numbered_segments(base: Path) -> list[tuple[int, Path]]:
    """(n, path) of the existing segments of ``base``, n = 0 for ``base`` itself, in number order."""
    found = [(0, base)] if base.is_file() else []
    if base.parent.is_dir():
        prefix, suffix = f"{base.stem}.", base.suffix
        for p in base.parent.iterdir():
            middle = p.name[len(prefix):len(p.name) - len(suffix)]
            if p.name.startswith(prefix) and p.name.endswith(suffix) and middle.isdigit() and p.is_file():
                found.append((int(middle), p))
    return sorted(found)


def segments_of(base: str | Path) -> list[Path]:
    """The existing segments of ``base`` (itself, then ``<stem>.<n><suffix>``), in number order."""
    return [p for _, p in _numbered_segments(Path(base))]


def find_recording(path: str | Path) -> list[Path]:
    """The segment files a path names: a base file and its numbered segments, or the one recording
    (base plus segments) in a folder. Raises RecordingError when there is none, or several in a folder."""
    path = Path(path)
    if path.is_dir():
        bases = set()
        for p in path.iterdir():
            if p.suffix == ".mcap" and p.is_file():
                m = _SEGMENT_NAME.match(p.name)
                bases.add(f"{m['stem']}{m['suffix']}" if m else p.name)
        if not bases:
            raise RecordingError(f"{path}: folder holds no .mcap recording")
        if len(bases) > 1:
            raise RecordingError(f"{path}: folder holds several recordings ({', '.join(sorted(bases))}); name one")
        path = path / bases.pop()
    found = segments_of(path)
    if not found:
        raise RecordingError(f"{path}: no such recording")
    return found


class RecordingWriter:
    """Append flyslam payloads to an MCAP file, one channel per key.

    ``exclusive``: fail (FileExistsError) rather than overwrite an existing file."""

    def __init__(self, path: str | Path, chunk_size: int = 1 << 20, compression: str = "zstd",
                 exclusive: bool = False):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "xb" if exclusive else "wb")  # noqa: SIM115 - closed in close()
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[compression]
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=comp)
        self._writer.start(profile="flyslam", library="flyslam")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.count = 0
        self.bad_stamps = 0
        self._closed = False

    def _channel(self, key: str, schema: str) -> int:
        ch = self._channels.get(key)
        if ch is None:
            sid = self._schemas.get(schema)
            if sid is None:
                sid = self._schemas[schema] = self._writer.register_schema(schema, SCHEMA_ENCODING, schema.encode())
            ch = self._channels[key] = self._writer.register_channel(key, MESSAGE_ENCODING, sid)
        return ch

    def write(self, key: str, payload: bytes, log_time_ns: int, publish_time_ns: int | None = None,
              schema: str | None = None) -> None:
        """Write one payload. ``schema``/``publish_time_ns`` default to what the envelope says; a payload
        whose envelope cannot be read is still recorded (schema 'unknown') so nothing is lost."""
        if schema is None or publish_time_ns is None:
            try:
                obj_schema, _, stamp = messages.peek_envelope(payload)
            except messages.DecodeError:
                obj_schema, stamp = "unknown", log_time_ns
            schema = schema or obj_schema
            publish_time_ns = stamp if publish_time_ns is None else publish_time_ns
        if not _storable(publish_time_ns):
            publish_time_ns = log_time_ns
            self.bad_stamps += 1
        self._writer.add_message(self._channel(key, schema), log_time=int(log_time_ns), data=bytes(payload),
                                 publish_time=int(publish_time_ns), sequence=self.count)
        self.count += 1

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._writer.add_metadata(name, {k: str(v) for k, v in data.items()})

    def add_calibration(self, payload: bytes) -> None:
        self.add_metadata(CALIBRATION_METADATA, {"payload_b64": base64.b64encode(payload).decode()})

    def add_config(self, config: dict) -> None:
        self.add_metadata(CONFIG_METADATA, {"json": json.dumps(config, sort_keys=True, default=str)})

    def flush(self) -> None:
        """Close the chunk in progress and push it to the OS (bounds what a SIGKILL can lose)."""
        if not self._closed:
            self._writer.flush()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._writer.finish()
        self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def claim_segment(base: str | Path) -> Path:
    """Create (empty) and return the first free segment name of ``base`` after the last existing one
    (``base``, ``<stem>.1<suffix>``, …); never an existing file, even if another process creates one
    meanwhile. Any writer can then open it (MCAP here, Rerun's .rrd in the bridge)."""
    base = Path(base)
    if base.is_dir():
        raise RecordingError(f"{base}: is a directory; give a file name in it")
    base.parent.mkdir(parents=True, exist_ok=True)
    existing = _numbered_segments(base)
    n = existing[-1][0] + 1 if existing else 0
    while True:
        path = segment_path(base, n)
        try:
            with open(path, "xb"):
                return path
        except FileExistsError:
            n += 1


def open_segment(base: str | Path, **kwargs) -> RecordingWriter:
    """A writer on a new segment of the recording ``base`` (:func:`claim_segment`)."""
    return RecordingWriter(claim_segment(base), **kwargs)


def _storable(stamp) -> bool:
    """True when MCAP can store ``stamp`` (an unsigned 64-bit integer of nanoseconds)."""
    return isinstance(stamp, int) and not isinstance(stamp, bool) and 0 <= stamp < UINT64_LIMIT


# ------------------------------------------------------------------------------------- reading


@dataclass
class ChannelInfo:
    key: str
    schema: str
    count: int = 0
    first_ns: int | None = None
    last_ns: int | None = None

    @property
    def rate_hz(self) -> float:
        if self.count < 2 or self.first_ns is None or self.last_ns == self.first_ns:
            return 0.0
        return (self.count - 1) / ((self.last_ns - self.first_ns) * 1e-9)


@dataclass
class RecordingInfo:
    path: Path
    size_bytes: int
    channels: dict[str, ChannelInfo] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    start_ns: int | None = None
    end_ns: int | None = None
    error: str | None = None
    segments: list[Path] = field(default_factory=list)

    @property
    def message_count(self) -> int:
        return sum(c.count for c in self.channels.values())

    @property
    def duration_s(self) -> float:
        return 0.0 if self.start_ns is None else (self.end_ns - self.start_ns) * 1e-9

    def format(self) -> str:
        lines = [f"recording  {self.path}"]
        if len(self.segments) > 1:
            lines.append(f"segments   {len(self.segments)}: {', '.join(p.name for p in self.segments)}")
        lines += [f"size       {self.size_bytes / 1e6:.1f} MB",
                  f"duration   {self.duration_s:.2f} s", f"messages   {self.message_count}"]
        if self.error:
            lines.append(f"PROBLEM    {self.error} (everything before it is readable)")
        lines.append("channels:")
        width = max([len(k) for k in self.channels] + [10])
        for key in sorted(self.channels):
            c = self.channels[key]
            lines.append(f"  {key:<{width}}  {c.schema:<28} {c.count:>7} msgs  {c.rate_hz:8.2f} Hz")
        if self.metadata:
            lines.append("metadata: " + ", ".join(sorted(self.metadata)))
        return "\n".join(lines)


class RecordingReader:
    """Sequential reader of a recording's segments that survives truncation and corruption.

    ``path``: a base file (its numbered segments follow it, see :func:`find_recording`), a folder
    holding one recording, or with ``segments=False`` exactly one file. Iterating :meth:`messages`
    yields every readable message, segment after segment, in file order; where a segment ends early or
    a record is corrupt, that segment stops there, the next one is read, and :attr:`error` says what
    happened (``"<segment>: <problem>"`` per damaged segment when there are several).
    """

    def __init__(self, path: str | Path, segments: bool = True):
        self.path = Path(path)
        if segments:
            self.segments = find_recording(self.path)
        elif self.path.is_file():
            self.segments = [self.path]
        else:
            raise RecordingError(f"{self.path}: no such recording")
        if self.path.is_dir() or not self.path.is_file():
            self.path = _base_of(self.segments[0])
        for seg in self.segments:
            with open(seg, "rb") as f:
                magic = f.read(8)
            if magic != b"\x89MCAP0\r\n":
                raise RecordingError(f"{seg}: not an MCAP file (bad magic bytes)")
        self.error: str | None = None
        self.errors: dict[Path, str] = {}
        self.metadata: dict[str, dict[str, str]] = {}

    def messages(self, keys: set[str] | None = None, start_ns: int | None = None,
                 end_ns: int | None = None) -> Iterator[RecordedMessage]:
        self.error = None
        self.errors = {}
        for seg in self.segments:
            yield from self._segment_messages(seg, keys, start_ns, end_ns)
        if len(self.segments) == 1:
            self.error = self.errors.get(self.segments[0])
        elif self.errors:
            self.error = "; ".join(f"{p.name}: {e}" for p, e in self.errors.items())

    def _segment_messages(self, path: Path, keys, start_ns, end_ns) -> Iterator[RecordedMessage]:
        channels: dict[int, Channel] = {}
        schemas: dict[int, Schema] = {0: None}
        ended_cleanly = False
        with open(path, "rb") as f:
            reader = StreamReader(f, skip_magic=False, validate_crcs=True)
            records = reader.records
            while True:
                try:
                    rec = next(records)
                except StopIteration:
                    break
                except Exception as e:  # noqa: BLE001 - any parse failure means "the file ends here"
                    self.errors[path] = _describe(e)
                    return
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Metadata):
                    self.metadata.setdefault(rec.name, dict(rec.metadata))
                elif isinstance(rec, Message):
                    ch = channels.get(rec.channel_id)
                    if ch is None:
                        continue
                    if keys is not None and ch.topic not in keys:
                        continue
                    if start_ns is not None and rec.log_time < start_ns:
                        continue
                    if end_ns is not None and rec.log_time > end_ns:
                        continue
                    sc = schemas.get(ch.schema_id)
                    yield RecordedMessage(ch.topic, sc.name if sc else "unknown", rec.log_time,
                                          rec.publish_time, rec.data)
                elif type(rec).__name__ == "Footer":
                    ended_cleanly = True
        if not ended_cleanly:
            self.errors[path] = "file ends without a footer (recorder stopped abruptly?)"

    def info(self) -> RecordingInfo:
        info = RecordingInfo(self.path, sum(p.stat().st_size for p in self.segments), segments=list(self.segments))
        for m in self.messages():
            c = info.channels.get(m.key)
            if c is None:
                c = info.channels[m.key] = ChannelInfo(m.key, m.schema)
            c.count += 1
            c.first_ns = m.log_time_ns if c.first_ns is None else min(c.first_ns, m.log_time_ns)
            c.last_ns = m.log_time_ns if c.last_ns is None else max(c.last_ns, m.log_time_ns)
            info.start_ns = m.log_time_ns if info.start_ns is None else min(info.start_ns, m.log_time_ns)
            info.end_ns = m.log_time_ns if info.end_ns is None else max(info.end_ns, m.log_time_ns)
        info.metadata = dict(self.metadata)
        info.error = self.error
        return info

    def calibration_payload(self) -> bytes | None:
        """The calibration stored as metadata (read the messages first, or this reads the file)."""
        if not self.metadata:
            for _ in self.messages():
                pass
        meta = self.metadata.get(CALIBRATION_METADATA)
        return base64.b64decode(meta["payload_b64"]) if meta else None


def _base_of(segment: Path) -> Path:
    m = _SEGMENT_NAME.match(segment.name)
    return segment.with_name(f"{m['stem']}{m['suffix']}") if m else segment


def _describe(e: Exception) -> str:
    name = type(e).__name__
    text = str(e) or "unexpected end of data"
    if "EndOfFile" in name or "struct" in name.lower() or "unpack requires" in text:
        return f"truncated: {text}"
    return f"corrupt record ({name}: {text})"
