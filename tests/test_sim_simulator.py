"""Simulator stepping: scripted paths, trolley moves, velocity commands, event schedule, determinism."""
import numpy as np
import pytest

from common.geometry import R_BODY_OPTICAL, planar_from_transform
from common.sim import (CameraDue, OdometryReading, SimulationError, Simulator, SonarReading, load_scenario,
                        parse_scenario, scenario_path)
from common.trajectory import parse_tum, format_tum


def room(**extra):
    data = {"robot": {"start": [0.0, 0.0, 0.0]}, "camera": {"width": 48, "height": 36},
            "walls": [{"from": [5.0, -3.0], "to": [5.0, 3.0], "z": [0.0, 2.5]},
                      {"from": [-3.0, 3.0], "to": [5.0, 3.0], "z": [0.0, 2.5]},
                      {"from": [-3.0, -3.0], "to": [5.0, -3.0], "z": [0.0, 2.5]}]}
    data.update(extra)
    return parse_scenario(data, "room")


def run(sim, dt=0.05, limit_s=200.0):
    events = []
    while not sim.finished and sim.time_ns < limit_s * 1e9:
        events += sim.advance(dt)
    return events


def test_waypoint_path_visits_every_waypoint_and_finishes():
    pts = [[2.0, 0.0], [2.0, 1.5], [0.0, 1.5]]
    sim = Simulator(room(path={"mode": "waypoints", "waypoints": pts, "speed": 0.5}), seed=0)
    visited, k = [], 0
    while not sim.finished:
        sim.advance(0.02)
        if k < len(pts) and np.hypot(sim.pose[0] - pts[k][0], sim.pose[1] - pts[k][1]) < 0.01:
            visited.append(k)
            k += 1
    assert visited == [0, 1, 2]
    x, y, _ = planar_from_transform(sim.truth_pose())
    assert (x, y) == pytest.approx((0.0, 1.5), abs=0.01)
    # turn-then-drive at the configured speed: the path is 5.5 m long, plus three turns
    assert 5.5 / 0.5 < sim.time_ns * 1e-9 < 5.5 / 0.5 + 3 * np.pi / np.deg2rad(30) + 1


def test_trolley_moves_translate_sideways_and_rotate_to_the_exact_poses():
    path = {"mode": "poses", "poses": [[0.2, 0.0, 0.0], [0.2, 0.1, 0.0], [0.2, 0.1, 5.0]],
            "speed": 0.1, "turn_rate_deg": 5.0, "pause_s": 0.5}
    sim = Simulator(room(path=path), seed=0)
    events = run(sim)
    x, y, yaw = sim.pose
    assert (x, y, np.rad2deg(yaw)) == pytest.approx((0.2, 0.1, 5.0), abs=1e-9)
    assert sim.time_ns * 1e-9 == pytest.approx(2.0 + 1.0 + 1.0 + 1.5, abs=0.01)
    # Wheel odometry sees the forward move and the rotation but not the sideways step.
    odo = [e for e in events if isinstance(e, OdometryReading)][-1].pose_xyyaw_integrated
    assert odo[0] == pytest.approx(0.2, abs=0.01)
    assert abs(odo[1]) < 0.01
    assert np.rad2deg(odo[2]) == pytest.approx(5.0, abs=0.3)


def test_shipped_trolley_scenario_uses_only_x_sideways_and_yaw_moves():
    sim = Simulator(load_scenario(scenario_path("trolley")), seed=0, width=32, height=24)
    poses = []
    while not sim.finished:
        sim.advance(0.5)
        poses.append(sim.truth_pose())
    P = np.array(poses)
    assert np.allclose(P[:, 2, 3], 0.0) and np.allclose(P[:, 2, :3], [0, 0, 1])
    steps = np.linalg.norm(np.diff(P[:, :2, 3], axis=0), axis=1)
    assert steps.max() <= 0.1 * 0.5 + 1e-9  # short, slow moves


def test_velocity_commands_drive_the_robot_and_walls_stop_it():
    sim = Simulator(room(), seed=0)
    assert not sim.finished
    sim.set_command(0.5, 0.0)
    sim.advance(2.0)
    assert sim.pose[0] == pytest.approx(1.0, abs=1e-9)
    sim.set_command(0.5, 0.0)  # straight on into the wall at x = 5
    sim.advance(20.0)
    assert sim.collisions > 0
    assert sim.pose[0] == pytest.approx(5.0 - 0.22, abs=0.01)
    assert sim.clearance() > -0.005
    sim.set_command(0.0, 1.0)  # turning in place is always allowed
    sim.advance(np.pi / 2)
    assert sim.pose[2] == pytest.approx(np.pi / 2, abs=1e-6)
    with pytest.raises(SimulationError, match="finite"):
        sim.set_command(np.nan, 0.0)


def test_set_command_overrides_a_scripted_path():
    sim = Simulator(room(path={"mode": "waypoints", "waypoints": [[4.0, 0.0]]}), seed=0)
    sim.advance(1.0)
    sim.set_command(0.0, 0.0)
    x = sim.pose[0]
    sim.advance(5.0)
    assert sim.pose[0] == x and not sim.finished


def test_events_come_at_their_rates_in_time_order_and_frames_match_truth():
    sim = Simulator(room(path={"mode": "velocity", "segments": [[3.0, 0.3, 0.2]]}), seed=0, camera_rate_hz=15)
    events = []
    for _ in range(37):  # uneven steps
        events += sim.advance(0.081)
    stamps = [e.stamp_ns for e in events]
    assert stamps == sorted(stamps) and all(s <= sim.time_ns for s in stamps)
    by = lambda cls: np.array([e.stamp_ns for e in events if isinstance(e, cls)])
    assert np.all(np.diff(by(OdometryReading)) == 20_000_000)
    assert np.all(np.diff(by(SonarReading)) == 100_000_000)
    cams = by(CameraDue)
    assert np.all(np.diff(cams) == round(1e9 / 15)) and cams[0] == 0
    late = int(cams[-2])
    frame = sim.render(late)
    assert frame.stamp_ns == late
    np.testing.assert_allclose(frame.T_map_base, sim.truth_at(late))
    # The truth at a camera stamp is the exact arc of the velocity profile.
    t = late * 1e-9
    yaw = 0.2 * t
    np.testing.assert_allclose(planar_from_transform(frame.T_map_base),
                               (0.3 / 0.2 * np.sin(yaw), 0.3 / 0.2 * (1 - np.cos(yaw)), yaw), atol=1e-9)
    with pytest.raises(SimulationError, match="outside the kept history"):
        sim.render(sim.time_ns + 10**9)
    with pytest.raises(SimulationError, match="dt_s"):
        sim.advance(-1.0)


def test_the_same_seed_gives_the_same_run():
    def record(seed):
        sim = Simulator(load_scenario(scenario_path("corridor")), seed=seed, width=32, height=24)
        out = []
        for _ in range(20):
            for e in sim.advance(0.1):
                if isinstance(e, OdometryReading):
                    out.append(("o", e.stamp_ns, tuple(e.ticks), tuple(e.wheel_speeds)))
                elif isinstance(e, SonarReading):
                    out.append(("s", e.stamp_ns, tuple(np.nan_to_num(e.ranges, nan=-1))))
        return out, sim.render().left
    a, b, c = record(3), record(3), record(4)
    assert a[0] == b[0] and np.array_equal(a[1], b[1])
    assert a[0] != c[0]


def test_calibration_describes_the_rig_on_the_robot():
    sim = Simulator(load_scenario(scenario_path("corridor")), seed=0, width=320, height=240, baseline=0.2)
    cal = sim.calibration
    assert (cal.width, cal.height, cal.baseline) == (320, 240, 0.2)
    T = cal.T_base_camera
    np.testing.assert_allclose(T[:3, :3], R_BODY_OPTICAL)
    assert 0.4 <= T[2, 3] <= 0.5
    assert T[1, 3] == pytest.approx(0.1)  # left camera half a baseline to the left
    with pytest.raises(SimulationError, match="width"):
        Simulator(load_scenario(scenario_path("corridor")), width=0)


def test_truth_trajectory_exports_as_tum():
    sim = Simulator(room(path={"mode": "velocity", "segments": [[1.0, 0.5, 0.3]]}), seed=0)
    stamps, poses = [], []
    for e in run(sim):
        if isinstance(e, CameraDue):
            stamps.append(e.stamp_ns)
            poses.append(sim.truth_at(e.stamp_ns))
    s2, p2 = parse_tum(format_tum(np.array(stamps), np.array(poses)))
    np.testing.assert_array_equal(s2, stamps)
    np.testing.assert_allclose(p2, poses, atol=1e-8)
