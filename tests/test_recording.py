"""Recorder and replay as real processes: record -> replay -> record is lossless; damaged files."""
from __future__ import annotations

import signal
import time

import pytest

from common.recording import RecorderBacklog, RecordingError, RecordingReader, RecordingWriter
from deploy.commands import info
from tests.helpers import start_module, stop, wait_until, write_source_recording


def _replay_and_record(src, dst, port, tmp_path, *replay_args):
    recorder = start_module("services.recorder", "--out", str(dst), "--keys", "stereo/*", "odom/*",
                            port=port, log_path=tmp_path / "recorder.log")
    try:
        time.sleep(1.5)  # let the recorder's subscriptions reach the hub before anything is published
        replay = start_module("services.replay", str(src), "--rate", "4", *replay_args, port=port,
                              log_path=tmp_path / "replay.log")
        rc = replay.wait(timeout=60)
        time.sleep(0.5)
    finally:
        assert stop(recorder) == 0, (tmp_path / "recorder.log").read_text()
    return rc


def test_record_replay_record_gives_the_same_messages(tmp_path, zenoh_port):
    src = tmp_path / "source.mcap"
    written = write_source_recording(src, frames=40)
    dst = tmp_path / "again.mcap"
    assert _replay_and_record(src, dst, zenoh_port, tmp_path) == 0, (tmp_path / "replay.log").read_text()
    reader = RecordingReader(dst)
    again = [(m.key, m.payload) for m in reader.messages()]
    assert reader.error is None
    assert again == written, f"{len(again)} messages recorded back, {len(written)} written"
    assert reader.calibration_payload() == written[0][1]


def test_truncated_recording_is_reported_and_its_readable_part_replays(tmp_path, zenoh_port, capsys):
    src = tmp_path / "source.mcap"
    written = write_source_recording(src, frames=60)
    data = src.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])

    assert info.main([str(cut)]) == 3
    out = capsys.readouterr().out
    assert "truncated" in out and "cut.mcap" in out

    readable = [(m.key, m.payload) for m in RecordingReader(cut).messages()]
    assert 0 < len(readable) < len(written) and readable == written[: len(readable)]

    dst = tmp_path / "again.mcap"
    rc = _replay_and_record(cut, dst, zenoh_port, tmp_path)
    assert rc == 3  # replayed what it could, then reported the damage
    log = (tmp_path / "replay.log").read_text()
    assert "cut.mcap" in log and "truncated" in log
    again = [(m.key, m.payload) for m in RecordingReader(dst).messages()]
    assert again == readable


def test_not_an_mcap_file_gives_a_clear_error(tmp_path, capsys):
    bad = tmp_path / "notes.mcap"
    bad.write_text("hello")
    with pytest.raises(RecordingError, match="notes.mcap.*not an MCAP"):
        RecordingReader(bad)
    assert info.main([str(bad), str(tmp_path / "missing.mcap")]) == 2
    err = capsys.readouterr().err
    assert "not an MCAP" in err and "missing.mcap" in err


def test_recorder_killed_with_sigkill_leaves_a_readable_file(tmp_path, zenoh_port):
    src = tmp_path / "source.mcap"
    write_source_recording(src, frames=120)
    dst = tmp_path / "killed.mcap"
    recorder = start_module("services.recorder", "--out", str(dst), "--flush-s", "0.3", port=zenoh_port,
                            log_path=tmp_path / "recorder.log")
    time.sleep(1.5)
    replay = start_module("services.replay", str(src), "--rate", "1", "--loop", port=zenoh_port,
                          log_path=tmp_path / "replay.log")
    try:
        assert wait_until(lambda: dst.exists() and dst.stat().st_size > 200_000, 30)
        recorder.send_signal(signal.SIGKILL)
        recorder.wait(10)
    finally:
        stop(replay)
    reader = RecordingReader(dst)
    got = list(reader.messages())
    assert reader.error is not None  # no footer: it was killed
    # Everything flushed before the kill (> 200 kB of ~19 kB frames) reads back, and every message is whole.
    assert len(got) >= 10
    assert {m.key for m in got} >= {"rig/stereo/frame", "rig/odom/wheels"}
    from common import messages
    assert all(messages.decode(m.payload) is not None for m in got)


def test_writer_survives_unknown_payloads(tmp_path):
    path = tmp_path / "raw.mcap"
    with RecordingWriter(path) as w:
        w.write("rig/x", b"not msgpack", 5)
    (msg,) = list(RecordingReader(path).messages())
    assert (msg.schema, msg.payload, msg.publish_time_ns) == ("unknown", b"not msgpack", 5)


def test_a_recorder_that_falls_behind_drops_its_oldest_messages_and_counts_them():
    """Bounded in bytes: the newest messages are kept in order, the oldest dropped and counted per key;
    unbounded with 0."""
    backlog = RecorderBacklog(max_bytes=1000)
    for i in range(30):
        backlog.put("rig/stereo/frame" if i % 3 == 0 else "rig/odom/wheels", bytes(100), i)
    kept = []
    while (item := backlog.get(timeout=0.01)) is not None:
        kept.append(item[2])
    assert kept == list(range(20, 30))                 # the 10 newest (1000 bytes), in arrival order
    assert backlog.dropped_by_key() == {"rig/stereo/frame": 7, "rig/odom/wheels": 13}
    assert backlog.get(timeout=0.01) is None and len(backlog) == 0 and backlog.queued_bytes == 0
    unbounded = RecorderBacklog(max_bytes=0)
    for i in range(50):
        unbounded.put("k", bytes(1000), i)
    assert len(unbounded) == 50 and unbounded.dropped_by_key() == {}
