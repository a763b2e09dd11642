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

    recs = list(_first(40))
    first_frame = next(r for r in recs if r.key.endswith("stereo/frame"))
    assert recs[0].key.endswith("stereo/calibration")
    got = list(_decoded(iter([first_frame] + recs), SMALL))      # a frame before any calibration
    assert got[0][0] == "stereo/frame" and got[0][2] is None
    frames = [(msg, images) for stream, msg, images in got[1:] if stream == "stereo/frame"]
    assert len(frames) >= 4 and all(images is not None for _, images in frames)
    calibration = got[1][1]
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


def test_eval_prepares_every_frame_off_the_main_thread(monkeypatch):
    """run_lockstep hands the worker's images to the evolver: the main thread prepares none itself."""
    import threading

    from common.fly import evolver, fitness

    threads = []

    def recording(original):
        return lambda *a, **k: threads.append(threading.current_thread() is threading.main_thread()) or original(*a, **k)

    monkeypatch.setattr(fitness, "prepare_images", recording(fitness.prepare_images))     # prepare_frame's own
    monkeypatch.setattr(evolver, "prepare_images", recording(evolver.prepare_images))     # images_ahead's
    res = run_lockstep(RecordingReader(CORRIDOR).messages(), generations_per_frame=2, evolver_config=SMALL,
                       max_frames=4)
    assert res.frames == 4
    assert len(threads) >= 4 and not any(threads)
