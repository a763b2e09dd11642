"""Wheel odometry and sonar: their errors must be the ones configured."""
import numpy as np
import pytest

from common.sim import OdometryReading, Simulator, SonarReading, parse_scenario

QUIET_ODOMETRY = {"slip_sigma": 0.0, "burst_rate_hz": 0.0, "speed_noise": 0.0}


def drive(segments, odometry=None, sonar=None, walls=None, start=(0.0, 0.0, 0.0), seed=0):
    data = {"robot": {"start": list(start)}, "path": {"mode": "velocity", "segments": segments},
            "odometry": {**QUIET_ODOMETRY, **(odometry or {})}, "sonar": sonar or {},
            "camera": {"width": 32, "height": 24}}
    if walls:
        data["walls"] = walls
    sim = Simulator(parse_scenario(data, "sensor-test"), seed=seed)
    events = []
    while not sim.finished:
        events += sim.advance(0.1)
    odo = [e for e in events if isinstance(e, OdometryReading)]
    son = [e for e in events if isinstance(e, SonarReading)]
    return sim, odo, son


def test_wheel_radius_error_of_two_percent_makes_straight_runs_two_percent_long():
    sim, odo, _ = drive([[20.0, 0.5, 0.0]], {"radius_error_left": 0.02, "radius_error_right": 0.02})
    true_dist = sim.pose[0]
    assert true_dist == pytest.approx(10.0, abs=1e-6)
    x, y, yaw = odo[-1].pose_xyyaw_integrated
    assert np.hypot(x, y) / true_dist == pytest.approx(1.02, abs=0.001)
    assert abs(yaw) < 1e-3


def test_unequal_wheel_radii_make_a_straight_run_curve():
    _, odo, _ = drive([[10.0, 0.5, 0.0]], {"radius_error_left": -0.01, "radius_error_right": 0.01})
    # The right wheel reads long, so odometry turns left: Δθ ≈ (0.02 · s) / b.
    assert odo[-1].pose_xyyaw_integrated[2] == pytest.approx(0.02 * 5.0 / 0.30, rel=0.05)


def test_track_width_error_scales_turns():
    _, odo, _ = drive([[np.pi / 0.5, 0.0, 0.5]], {"track_error": 0.05})  # one true half turn
    est = odo[-1].pose_xyyaw_integrated[2]
    assert abs(est) == pytest.approx(np.pi / 1.05, abs=0.01)


def test_ticks_and_wheel_speeds_are_consistent_and_sampled_at_the_configured_rate():
    _, odo, _ = drive([[2.0, 0.4, 0.2]], {"rate_hz": 50.0})
    stamps = np.array([o.stamp_ns for o in odo])
    assert np.all(np.diff(stamps) == 20_000_000)
    assert len(odo) == 100
    ticks = np.array([o.ticks for o in odo])
    assert ticks.dtype == np.int64 and np.all(np.diff(ticks, axis=0) >= 0)
    o = odo[-1]
    wheel_angle = ticks[-1] * 2 * np.pi / o.ticks_per_rev
    speeds = np.array([x.wheel_speeds for x in odo])
    np.testing.assert_allclose(speeds.sum(0) * 0.02, wheel_angle, rtol=2e-3)
    # Ground truth: v ∓ ω b/2 over r.
    np.testing.assert_allclose(speeds[-1], [(0.4 - 0.2 * 0.15) / 0.05, (0.4 + 0.2 * 0.15) / 0.05], rtol=1e-6)


def test_random_slip_has_the_configured_spread():
    _, odo, _ = drive([[20.0, 0.5, 0.0]], {"slip_sigma": 0.03})
    speeds = np.array([o.wheel_speeds for o in odo[1:]])  # the first period has no slip drawn yet
    rel = speeds / (0.5 / 0.05) - 1
    assert rel.std() == pytest.approx(0.03, rel=0.15)
    assert abs(rel.mean()) < 0.005


def test_slip_bursts_hit_one_wheel_by_the_configured_amount():
    _, odo, _ = drive([[60.0, 0.5, 0.0]], {"burst_rate_hz": 0.2, "burst_duration_s": 0.5, "burst_slip": 0.4})
    rel = np.array([o.wheel_speeds for o in odo[1:]]) / 10.0 - 1
    bursting = rel > 0.2
    assert bursting.any()
    np.testing.assert_allclose(rel[bursting], 0.4, atol=1e-9)
    assert not np.any(bursting[:, 0] & bursting[:, 1])


def corridor_walls(half_width=1.0):
    return [{"from": [-50.0, half_width], "to": [50.0, half_width], "z": [0.0, 2.5]},
            {"from": [-50.0, -half_width], "to": [50.0, -half_width], "z": [0.0, 2.5]}]


def test_sonar_ranges_match_the_analytic_wall_distance_and_glancing_beams_miss():
    sonar = {"count": 8, "noise_sigma": 0.005, "noise_rel": 0.0, "dropout": 0.0, "max_range": 5.0}
    _, _, son = drive([[1.0, 0.0, 0.0]], sonar=sonar, walls=corridor_walls(1.0), start=(0.0, 0.3, 0.0))
    assert len(son) == 11  # 10 Hz for 1 s, plus t = 0
    ranges = np.array([s.ranges for s in son])
    yaw = son[0].transducer_poses[:, 2]
    left = np.argmin(np.abs(yaw - np.pi / 2))
    right = np.argmin(np.abs(yaw + np.pi / 2))
    assert np.mean(ranges[:, left]) == pytest.approx(1.0 - 0.3 - 0.2, abs=0.005)
    assert np.mean(ranges[:, right]) == pytest.approx(1.3 - 0.2, abs=0.005)
    assert np.std(ranges[:, left]) == pytest.approx(0.005, rel=0.6)
    ahead, behind = np.argmin(np.abs(yaw)), np.argmin(np.abs(np.abs(yaw) - np.pi))
    # Looking along the corridor the beam meets the walls at > 75° incidence: specular, no echo.
    assert np.isnan(ranges[:, ahead]).all() and np.isnan(ranges[:, behind]).all()
    # At 45° the near edge of the beam (32.5° incidence) echoes: range to that ray's hit.
    diag = np.argmin(np.abs(yaw - np.pi / 4))
    tx, ty = son[0].transducer_poses[diag, :2]
    half = np.deg2rad(12.5)
    expected = (1.0 - 0.3 - ty) / np.sin(np.pi / 4 + half)
    assert np.mean(ranges[:, diag]) == pytest.approx(expected, abs=0.01)


def test_sonar_dropout_and_max_range():
    sonar = {"count": 8, "dropout": 0.3, "max_range": 5.0}
    _, _, son = drive([[20.0, 0.0, 0.0]], sonar=sonar, walls=corridor_walls(1.0))
    ranges = np.array([s.ranges for s in son])
    yaw = son[0].transducer_poses[:, 2]
    side = np.abs(np.abs(yaw) - np.pi / 2) < 1e-6
    assert np.isnan(ranges[:, side]).mean() == pytest.approx(0.3, abs=0.08)
    far = {"count": 8, "dropout": 0.0, "max_range": 0.5}
    _, _, son = drive([[1.0, 0.0, 0.0]], sonar=far, walls=corridor_walls(1.0))
    assert np.isnan(np.array([s.ranges for s in son])).all()  # walls at 0.8 m are beyond 0.5 m
