"""Wheel dead reckoning: covariance on known motions, and bad readings flagged instead of integrated."""
from __future__ import annotations

import numpy as np
import pytest

from common.fusion.odometry import OdometryConfigError, OdometryModel, WheelIntegrator
from common.messages import WheelOdometry, header

R, B, TPR = 0.05, 0.30, 4096.0
PERIOD_NS = 20_000_000          # 50 Hz


def ticks_for(distance_m: float) -> int:
    return int(np.floor(distance_m / (2 * np.pi * R) * TPR))


def reading(i: int, left_m: float, right_m: float, stamp_ns: int | None = None, speeds=None) -> WheelOdometry:
    return WheelOdometry(ticks=np.array([ticks_for(left_m), ticks_for(right_m)], np.int64), ticks_per_rev=TPR,
                         wheel_radius_m=R, track_width_m=B,
                         wheel_speeds=None if speeds is None else np.asarray(speeds, float),
                         header=header(i + 1, 10**9 + i * PERIOD_NS if stamp_ns is None else stamp_ns, "base_link"))


def straight(n: int, step_m: float = 0.01):
    return [reading(i, i * step_m, i * step_m) for i in range(n + 1)]


def run(readings, model=None):
    odo = WheelIntegrator(model)
    steps = [odo.update(r) for r in readings]
    return odo, steps


def test_straight_line_covariance_grows_along_x_first_then_laterally():
    odo = WheelIntegrator()
    snapshots = {}
    for i, r in enumerate(straight(200)):           # 2 m at 0.5 m/s
        assert odo.update(r).ok
        if i in (10, 100, 200):
            snapshots[i] = odo.cov.copy()
    assert odo.pose == pytest.approx([2.0, 0.0, 0.0], abs=2e-4)
    early, mid, end = snapshots[10], snapshots[100], snapshots[200]
    # Along the motion the variance grows linearly with distance ...
    assert end[0, 0] / mid[0, 0] == pytest.approx(2.0, rel=0.02)
    # ... heading uncertainty too, and lateral uncertainty grows ~cubically through it.
    assert end[2, 2] / mid[2, 2] == pytest.approx(2.0, rel=0.02)
    assert end[1, 1] / mid[1, 1] > 6.0
    # Early on the robot is less sure of how far it went than of its lateral offset; later the reverse.
    assert early[0, 0] > early[1, 1]
    assert end[1, 1] > end[0, 0]
    # Lateral error and heading error are positively correlated; along-track and lateral are not.
    assert end[1, 2] > 0.5 * np.sqrt(end[1, 1] * end[2, 2])
    assert abs(end[0, 1]) < 1e-12
    assert np.all(np.linalg.eigvalsh(end) >= 0)


def test_pure_rotation_grows_yaw_variance_and_keeps_the_position():
    quarter_m = (B / 2) * (np.pi / 2)             # wheel travel for a quarter turn
    odo = WheelIntegrator()
    yaw_var = {}
    for i in range(201):                           # a full turn on the spot in 200 readings
        wheel = i * 4 * quarter_m / 200
        r = WheelOdometry(ticks=np.array([-ticks_for(wheel), ticks_for(wheel)], np.int64), ticks_per_rev=TPR,
                          wheel_radius_m=R, track_width_m=B, header=header(i + 1, 10**9 + i * PERIOD_NS, "base_link"))
        assert odo.update(r).ok
        if i in (100, 200):
            yaw_var[i] = odo.cov[2, 2]
    assert odo.pose[:2] == pytest.approx([0.0, 0.0], abs=1e-12)
    tick_angle = 2 * np.pi * R / TPR / (B / 2)
    assert abs(odo.pose[2]) < 2 * tick_angle        # back to heading 0 after a full turn
    assert yaw_var[200] / yaw_var[100] == pytest.approx(2.0, rel=0.02)
    # Over a full turn the small position uncertainty is the same in every direction.
    assert odo.cov[0, 0] == pytest.approx(odo.cov[1, 1], rel=0.05)
    assert np.sqrt(yaw_var[200]) > 0.01


def test_nan_and_out_of_order_readings_are_flagged_and_do_not_corrupt_the_pose():
    clean, _ = run(straight(100))
    readings = straight(100)
    bad_nan = reading(50, 0.5, 0.5, speeds=[np.nan, 1.0])
    bad_nan.header.stamp_ns += PERIOD_NS // 2
    old = reading(30, 0.3, 0.3)                     # a late duplicate of an earlier reading
    readings = readings[:51] + [bad_nan] + readings[51:70] + [old] + readings[70:]
    odo, steps = run(readings)
    flags = [s.kind for s in steps if not s.ok]
    assert flags == ["non_finite", "time_backwards"]
    np.testing.assert_allclose(odo.pose, clean.pose, atol=1e-12)
    np.testing.assert_allclose(odo.cov, clean.cov, atol=1e-15)


def test_speeds_only_nan_and_backwards_time_are_flagged():
    def sp(i, v, stamp=None):
        return WheelOdometry(wheel_speeds=np.array([v, v]), wheel_radius_m=R, track_width_m=B,
                             header=header(i, stamp if stamp is not None else 10**9 + i * PERIOD_NS, "base_link"))
    readings = [sp(i, 10.0) for i in range(51)]
    odo_clean, _ = run(readings)
    assert odo_clean.pose[0] == pytest.approx(50 * 10.0 * R * 0.02)
    odo, steps = run(readings[:20] + [sp(99, np.inf), sp(98, 10.0, stamp=10**9)] + readings[20:])
    assert [s.kind for s in steps if not s.ok] == ["non_finite", "time_backwards"]
    np.testing.assert_allclose(odo.pose, odo_clean.pose, atol=1e-12)


def test_impossible_wheel_speed_is_flagged_as_a_jump():
    clean, _ = run(straight(60))
    spike = reading(30, 0.0, 0.0)
    spike.ticks = spike.ticks + 10**6              # encoder glitch: a million ticks in 20 ms
    spike.header.stamp_ns += PERIOD_NS // 2
    readings = straight(60)
    odo, steps = run(readings[:31] + [spike] + readings[31:])
    bad = [s for s in steps if not s.ok]
    assert len(bad) == 1 and bad[0].kind == "jump" and "impossible wheel speed" in bad[0].flag
    np.testing.assert_allclose(odo.pose, clean.pose, atol=1e-12)
    # The same with a reported speed far beyond what the wheels can do.
    fast = WheelOdometry(wheel_speeds=np.array([500.0, 500.0]), wheel_radius_m=R, track_width_m=B,
                         header=header(1, 2 * 10**9, "base_link"))
    slow = WheelOdometry(wheel_speeds=np.array([5.0, 5.0]), wheel_radius_m=R, track_width_m=B,
                         header=header(0, 2 * 10**9 - PERIOD_NS, "base_link"))
    _, steps = run([slow, fast])
    assert steps[1].kind == "jump"


def test_encoder_counter_reset_resynchronises_instead_of_flagging_forever():
    readings = straight(100)
    shifted = readings[:50] + [reading(i, (i - 50) * 0.01, (i - 50) * 0.01, stamp_ns=readings[i].header.stamp_ns)
                               for i in range(50, 101)]
    shifted[50].ticks = np.array([0, 0], np.int64)  # the counter restarted at 0
    odo, steps = run(shifted)
    assert [s.kind for s in steps if not s.ok] == ["jump"]
    assert any(s.note.startswith("resynchronised") for s in steps)
    assert odo.pose[0] == pytest.approx(1.0 - 0.01, abs=3e-4)  # one interval is lost, not the rest


def test_restore_continues_from_the_recovered_pose():
    odo = WheelIntegrator()
    odo.restore([1.0, 2.0, np.pi / 2], np.eye(3) * 1e-3, stamp_ns=10**9 - 1)
    for r in straight(100):
        assert odo.update(r).ok
    assert odo.pose == pytest.approx([1.0, 3.0, np.pi / 2], abs=3e-4)
    assert odo.cov[0, 0] > 1e-3                      # grew from the recovered covariance
    stale = reading(0, 0, 0, stamp_ns=10)
    assert odo.update(stale).kind == "time_backwards"


def test_missing_geometry_and_bad_model_are_clear_errors():
    r = WheelOdometry(wheel_speeds=np.array([1.0, 1.0]), header=header(1, 1, "base_link"))
    odo = WheelIntegrator()
    assert odo.update(r).kind == "no_geometry"
    assert WheelIntegrator(OdometryModel(wheel_radius_m=R, track_width_m=B)).update(r).ok
    with pytest.raises(OdometryConfigError, match="k_wheel_m"):
        OdometryModel(k_wheel_m=-1.0)
