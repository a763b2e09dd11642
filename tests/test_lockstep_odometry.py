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
    got = list(_decoded(iter(recs), SMALL))
    assert [s for s, _, _ in got] == [r.key.split("/", 1)[1] for r in wanted]
    assert got[[i for i, r in enumerate(wanted) if r.payload == b"\x93not msgpack"][0]][1] is None
    for (stream, msg, _), rec in zip(got, wanted):
        if stream == "stereo/frame" and msg.encoding in ("rgb8", "mono8"):
            left, right = frame_images(m.decode(rec.payload))
            assert (msg.left == left).all() and (msg.right == right).all()
    assert sum(1 for s, msg, _ in got if s == "stereo/frame" and msg.encoding == "jpeg") == 1   # the corrupt one


def test_frames_prepared_ahead_give_the_same_populations_to_the_bit(monkeypatch):
    """The decode worker also prepares each frame's fitness images (with the calibration recorded before
    the frame); the evolver fed them uses them, and evolves exactly as one that prepares its own."""
    from common.fly import fitness
    from common.fly.core import EvolverCore
    from common.lockstep import _decoded

    got = list(_decoded(_first(40), SMALL))
    frames = [(msg, images) for stream, msg, images in got if stream == "stereo/frame"]
    first_calibration = next(i for i, (s, _, _) in enumerate(got) if s == "stereo/calibration")
    assert all(images is None for s, _, images in got[:first_calibration] if s == "stereo/frame")
    assert len(frames) >= 4 and all(images is not None for _, images in frames[-3:])
    calibration = got[first_calibration][1]
    runs, prepared_here = [], []
    counting = fitness.prepare_images
    monkeypatch.setattr(fitness, "prepare_images", lambda *a, **k: prepared_here.append(1) or counting(*a, **k))
    for use_images in (True, False):
        core = EvolverCore(SMALL, settle=3, seed=1)
        core.on_calibration(calibration)
        runs.append([core.on_frame(msg, images=images if use_images else None).population
                     for msg, images in frames[-3:]])
        if use_images:
            assert not prepared_here          # every frame's images came from the worker
    for ahead, here in zip(*runs):
        assert (ahead.positions == here.positions).all() and (ahead.fitness == here.fitness).all()
    # images prepared from other arrays are not used: the evolver prepares its own
    core = EvolverCore(SMALL, settle=3, seed=1)
    core.on_calibration(calibration)
    wrong = [core.on_frame(msg, images=frames[-1][1]).population for msg, _ in frames[-3:]]
    assert all((w.fitness == h.fitness).all() for w, h in zip(wrong, runs[1]))
