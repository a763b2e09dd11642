"""Recorder and replay as real processes: record -> replay -> record is lossless; damaged files."""
from __future__ import annotations

import signal
import time

import pytest

from common.recording import RecorderBacklog, RecordingError, RecordingReader, RecordingWriter, open_segment
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


def test_segments_of_a_restarted_recorder_read_as_one_recording(tmp_path, capsys):
    """open_segment never overwrites; the base path, the folder and info see every segment in number order."""
    base = tmp_path / "run" / "recording.mcap"
    names = []
    for seg in range(12):   # past 9, so number order and name order differ
        with open_segment(base) as w:
            w.write("rig/odom/wheels", b"not msgpack", 1000 + seg)
            names.append(w.path.name)
    assert names[:3] == ["recording.mcap", "recording.1.mcap", "recording.2.mcap"] and names[-1] == "recording.11.mcap"
    for path in (base, tmp_path / "run"):
        reader = RecordingReader(path)
        assert [m.log_time_ns for m in reader.messages()] == [1000 + i for i in range(12)]
        assert reader.error is None and reader.path == base
    assert [m.log_time_ns for m in RecordingReader(base, segments=False).messages()] == [1000]
    assert [m.log_time_ns for m in RecordingReader(tmp_path / "run" / "recording.10.mcap").messages()] == [1010]
    assert info.main([str(tmp_path / "run")]) == 0
    out = capsys.readouterr().out
    assert "segments   12" in out and "messages   12" in out
    with pytest.raises(RecordingError, match="is a directory"):
        open_segment(tmp_path / "run")
    (tmp_path / "run" / "other.mcap").write_bytes(base.read_bytes())
    with pytest.raises(RecordingError, match="several recordings"):
        RecordingReader(tmp_path / "run")


def test_a_damaged_first_segment_does_not_hide_the_next(tmp_path):
    base = tmp_path / "recording.mcap"
    write_source_recording(base, frames=60)
    base.write_bytes(base.read_bytes()[: int(base.stat().st_size * 0.6)])   # a recorder killed mid-chunk
    with open_segment(base) as w:
        w.write("rig/odom/wheels", b"after the restart", 5)
    reader = RecordingReader(base)
    got = list(reader.messages())
    assert got[-1].payload == b"after the restart" and len(got) > 2
    assert set(reader.errors) == {base} and reader.error.startswith("recording.mcap: truncated")


def test_stamps_mcap_cannot_store_are_recorded_with_the_receive_time_and_counted(tmp_path):
    import msgpack
    path = tmp_path / "stamps.mcap"
    envelope = {"schema": "flyslam.WheelOdometry", "major": 1, "seq": 1, "frame_id": "base_link"}
    with RecordingWriter(path) as w:
        for stamp in (-1, -(2**63), 2**64 - 1, 1.5, 7):
            w.write("rig/odom/wheels", msgpack.packb({**envelope, "stamp_ns": stamp}), 42)
    assert w.bad_stamps == 2 + 1   # the two negatives and the float; 2**64 - 1 fits uint64
    reader = RecordingReader(path)
    assert [m.publish_time_ns for m in reader.messages()] == [42, 42, 2**64 - 1, 42, 7]
    assert reader.error is None


def test_recorder_survives_bad_stamps_and_a_restart_appends_a_segment(tmp_path, zenoh_port):
    """Kill -9 the recorder mid-run and start it again on the same --out: both segments read back as one
    recording holding every message published while a recorder ran; negative stamps are counted in the
    heartbeat and crash nothing."""
    import msgpack
    from common import messages as m
    from common.bus import BusOptions, Node
    from tests.helpers import hub
    out = tmp_path / "recording.mcap"
    heartbeats = []
    with Node("feeder", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
        node.subscribe("status/recorder", m.Heartbeat, heartbeats.append)
        pub = node.publisher("odom/wheels", reliable=True)
        sent = []

        def publish(n, stamp=None):
            for _ in range(n):
                seq = len(sent) + 1
                stamp_ns = 10**9 + seq if stamp is None else stamp
                payload = msgpack.packb({"schema": "flyslam.WheelOdometry", "major": 1, "seq": seq,
                                         "stamp_ns": stamp_ns, "frame_id": "base_link", "wheel_speeds": [1.0]})
                pub.put_raw(payload)
                sent.append(payload)
                time.sleep(0.005)

        for attempt in range(2):
            heartbeats.clear()
            recorder = start_module("services.recorder", "--out", str(out), "--keys", "odom/*", "--flush-s", "0.1",
                                    port=zenoh_port, log_path=tmp_path / f"recorder{attempt}.log")
            assert wait_until(lambda: heartbeats, 20), (tmp_path / f"recorder{attempt}.log").read_text()
            time.sleep(1.0)   # its subscription reaches the hub
            publish(50)
            publish(3, stamp=-5)
            publish(50)
            assert wait_until(lambda: recorder.poll() is None and any(
                hb.counters.get("bad_stamps", 0) == 3 for hb in heartbeats), 10), "bad stamps not counted"
            time.sleep(0.3)   # one more flush
            if attempt == 0:
                recorder.send_signal(signal.SIGKILL)
                recorder.wait(10)
            else:
                assert stop(recorder) == 0
    assert sorted(p.name for p in tmp_path.glob("recording*.mcap")) == ["recording.1.mcap", "recording.mcap"]
    got = [msg.payload for msg in RecordingReader(out).messages()]
    assert got == sent, f"kept {len(set(got) & set(sent))} of {len(sent)}"
