"""EvolverCore, the per-frame step shared by the evolver service and flyslam eval: calibration changes,
refused inputs with a reason, motion compensation by odometry, and a latched input on the bus."""
from __future__ import annotations

import time

import numpy as np

from common import messages as m
from common.bus import BusOptions, Node
from common.camera import StereoCalibration
from common.fly import EvolverConfig
from common.fly.core import EvolverCore
from common.geometry import planar_pose
from common.images import make_frame
from tests.helpers import hub, wait_until

# Camera looking along base_link x (optical z forward, x right, y down).
T_BASE_CAMERA = np.array([[0, 0, 1, 0.0], [-1, 0, 0, 0.0], [0, -1, 0, 0.3], [0, 0, 0, 1.0]])


def _frame(width: int, height: int, seq: int, stamp_ns: int) -> m.StereoFrame:
    img = np.random.default_rng(seq).integers(0, 255, (height, width, 3), dtype=np.uint8)
    return make_frame(img, np.roll(img, -4, axis=1), seq, stamp_ns)


def _core(**kw) -> EvolverCore:
    return EvolverCore(EvolverConfig(population=300, depth_min=0.5, depth_max=20.0), settle=2, **kw)


def test_frames_are_refused_with_a_reason_until_a_usable_calibration_and_matching_size():
    core = _core()
    assert _core().on_frame(_frame(96, 72, 1, 1)).reason == "no calibration"
    bad = m.calibration_to_msg(StereoCalibration.ideal(96, 72), 1, 1)
    bad.width = 0
    core.on_calibration(bad)
    assert core.on_frame(_frame(96, 72, 1, 1)).reason.startswith("bad calibration")
    core.on_calibration(m.calibration_to_msg(StereoCalibration.ideal(96, 72), 2, 2))
    assert core.on_frame(_frame(64, 48, 2, 2)).reason.startswith("bad frame")
    result = core.on_frame(_frame(96, 72, 3, 3))
    assert result.reason is None and result.population.source_seq == 3 and result.generations == 2
    assert result.trace.reference is None and result.trace.take_ns <= result.trace.published_ns


def test_a_new_image_size_recreates_the_evolver_and_an_identical_calibration_does_not():
    core = _core()
    core.on_calibration(m.calibration_to_msg(StereoCalibration.ideal(96, 72), 1, 1))
    core.on_frame(_frame(96, 72, 1, 1))
    first = core.evolver
    core.on_calibration(m.calibration_to_msg(StereoCalibration.ideal(96, 72), 2, 2))   # republished
    second = core.on_frame(_frame(96, 72, 2, 2))
    assert core.evolver is first and second.trace.reference is not None
    core.on_calibration(m.calibration_to_msg(StereoCalibration.ideal(128, 96), 3, 3))
    third = core.on_frame(_frame(128, 96, 3, 3))
    assert core.evolver is not first and third.trace.reference is None


def test_flies_follow_the_odometry_motion_between_frames():
    core = EvolverCore(EvolverConfig(population=300, depth_min=1.0, depth_max=20.0), settle=0)
    core.on_calibration(m.calibration_to_msg(StereoCalibration.ideal(96, 72, T_base_camera=T_BASE_CAMERA), 1, 1))
    core.on_odometry(10**8, planar_pose(0.0, 0.0, 0.0))
    core.on_odometry(2 * 10**8, planar_pose(0.25, 0.0, 0.0))
    before = core.on_frame(_frame(96, 72, 1, 10**8)).population.positions.copy()
    after = core.on_frame(_frame(96, 72, 2, 2 * 10**8))
    assert not after.without_odometry
    assert np.allclose(after.population.positions[:, 2], before[:, 2] - 0.25, atol=1e-5)   # 0.25 m closer
    assert np.allclose(after.population.positions[:, :2], before[:, :2], atol=1e-5)
    assert np.allclose(after.population.T_odom_camera, planar_pose(0.25, 0.0, 0.0) @ T_BASE_CAMERA)


def test_latched_input_is_seeded_by_query_and_follows_new_messages(zenoh_port):
    opts = BusOptions(hub=hub(zenoh_port))
    with Node("source", opts, handle_signals=False) as source, Node("sink", opts, handle_signals=False) as sink:
        pub = source.publisher("stereo/calibration", latched=True)
        pub.publish(m.calibration_to_msg(StereoCalibration.ideal(96, 72), 1, 1))
        time.sleep(0.3)
        calib = sink.latched("stereo/calibration", m.StereoCalibrationMsg, timeout=2.0)
        assert calib.get() is not None and calib.get().width == 96        # published before we listened
        assert calib.take() is calib.get() and calib.take() is None       # take: once per new value
        pub.publish(m.calibration_to_msg(StereoCalibration.ideal(128, 96), 2, 2))
        assert wait_until(lambda: calib.get().width == 128, 10)
        missing = sink.latched("planner/target", m.Target, timeout=0.2, retry_s=0.2)
        assert missing.get() is None
        source.queryable("planner/target", lambda: m.Target(x=1.0, y=2.0, radius_m=0.3))   # answers queries only
        assert wait_until(lambda: missing.get() is not None, 10)          # found by the background retry
        assert missing.get().y == 2.0


def test_a_settle_scale_below_one_shortens_a_live_settle():
    from common.fly.scheduling import SettlePolicy
    core = EvolverCore(EvolverConfig(population=300, depth_min=0.5, depth_max=20.0),
                       settle=SettlePolicy(budget_s=0.15, recovery=2.0))   # never 'good enough': the whole budget
    core.on_calibration(m.calibration_to_msg(StereoCalibration.ideal(96, 72), 1, 1))
    for k in range(4):   # odometry at every frame: the normal budget (no 4x re-convergence budget)
        core.on_odometry(k * 33_000_000 + 1, planar_pose(0.0, 0.0, 0.0))
    core.on_frame(_frame(96, 72, 1, 1))
    full = core.on_frame(_frame(96, 72, 2, 33_000_001))
    scaled = core.on_frame(_frame(96, 72, 3, 66_000_001), settle_scale=0.25)
    assert not full.without_odometry and scaled.population is not None and scaled.generations >= 1
    assert scaled.generations < 0.6 * full.generations
