"""flyslam eval uses a recording's wheel odometry even when the recording's first frame comes before its
first odometry message (as the simulator writes them), and runs visual-only when there are no wheels."""
from __future__ import annotations

from itertools import islice
from pathlib import Path

from common.fly import EvolverConfig
from common.lockstep import run_lockstep
from common.recording import RecordingReader

CORRIDOR = Path(__file__).resolve().parent.parent / "recordings" / "corridor.mcap"
SMALL = EvolverConfig(population=1500, parallel=False)


def _first(n):
    return islice(RecordingReader(CORRIDOR).messages(), n)


def test_first_frame_before_first_odometry_still_runs_on_wheels():
    keys = [r.key.split("/", 1)[1] for r in _first(8)]
    assert keys.index("stereo/frame") < keys.index("odom/wheels")      # the case this test is about
    res = run_lockstep(RecordingReader(CORRIDOR).messages(), generations_per_frame=5, evolver_config=SMALL,
                       max_frames=6)
    assert res.localiser.config.odometry == "wheels"
    assert len(res.odometry) == 6 and all(T is not None for T in res.odometry[1:])   # the first frame predates it


def test_recording_without_wheels_runs_visual_only():
    no_wheels = (r for r in RecordingReader(CORRIDOR).messages() if not r.key.endswith("/odom/wheels"))
    res = run_lockstep(no_wheels, generations_per_frame=5, evolver_config=SMALL, max_frames=6)
    assert res.localiser.config.odometry == "visual"
    assert res.frames == 6 and all(T is None for T in res.odometry)


def test_frames_decoded_ahead_keep_the_recordings_order_and_images():
    from common import messages as m
    from common.images import frame_images
    from common.lockstep import _decoded
    from common.recording import RecordedMessage

    recs = list(_first(40))
    corrupt = m.decode(next(r for r in recs if r.key.endswith("stereo/frame")).payload)
    corrupt.left = corrupt.left[:10].copy()          # JPEG bytes cut short: they do not decode
    recs.insert(5, RecordedMessage(recs[4].key.split("/", 1)[0] + "/stereo/frame", "", 0, 0, m.encode(corrupt)))
    recs.insert(7, RecordedMessage("robot/odom/wheels", "", 0, 0, b"\x93not msgpack"))
    wanted = [r for r in recs if r.key.split("/", 1)[1] in ("stereo/calibration", "odom/wheels", "truth/pose",
                                                              "stereo/frame")]
    got = list(_decoded(iter(recs)))
    assert [s for s, _ in got] == [r.key.split("/", 1)[1] for r in wanted]
    assert got[[i for i, r in enumerate(wanted) if r.payload == b"\x93not msgpack"][0]][1] is None
    for (stream, msg), rec in zip(got, wanted):
        if stream == "stereo/frame" and msg.encoding in ("rgb8", "mono8"):
            left, right = frame_images(m.decode(rec.payload))
            assert (msg.left == left).all() and (msg.right == right).all()
    assert sum(1 for s, msg in got if s == "stereo/frame" and msg.encoding == "jpeg") == 1   # the corrupt one
