"""The localiser: beats miscalibrated odometry on a simulated corridor; falls back to odometry and says
so when it cannot register; keeps a bounded map."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from common.fly import EvolverConfig, FlyEvolver
from common.geometry import R_BODY_OPTICAL, invert, make_transform, planar_from_transform, planar_pose, transform_points
from common.pose_buffer import PoseBuffer
from common.sim import Simulator, load_scenario
from common.sim.scenario import scenario_path
from common.sim.sensors import OdometryReading
from common.sim.simulator import CameraDue
from common.slam import FlyLocaliser, LocaliserConfig, LocaliserError


def corridor_points(rng, n, x0=0.0, length=10.0):
    """Flies on two corridor walls (y = ±1) with a few boxes, in base_link-like coordinates (z up)."""
    side = rng.choice([-1.0, 1.0], n)
    pts = np.stack([rng.uniform(x0, x0 + length, n), side, rng.uniform(0.1, 2.0, n)], 1)
    box = rng.random(n) < 0.2
    pts[box, 1] = side[box] * 0.7
    pts[box, 0] = np.round(pts[box, 0])
    return pts


def test_localiser_beats_miscalibrated_odometry_on_the_simulated_corridor():
    scn = load_scenario(scenario_path("corridor"))
    scn.odometry = replace(scn.odometry, radius_error_left=0.01, radius_error_right=0.03, track_error=0.04)
    sim = Simulator(scn, seed=3, width=320, height=240, camera_rate_hz=5)
    cal = sim.calibration
    evolver = FlyEvolver(cal, EvolverConfig(population=3000, depth_max=30.0), seed=0)
    loc = FlyLocaliser(cal.T_base_camera, LocaliserConfig(), calibration=cal)
    odom = PoseBuffer(maxlen=10_000)
    last = None
    odo_err, est_err, statuses = [], [], []
    while len(statuses) < 45:
        for ev in sim.advance(0.02):
            if isinstance(ev, OdometryReading):
                odom.add(ev.stamp_ns, planar_pose(*ev.pose_xyyaw_integrated))
            elif isinstance(ev, CameraDue):
                frame = sim.render(ev.stamp_ns)
                T_odom_base = odom.at(ev.stamp_ns)
                if T_odom_base is None:
                    continue
                T_cam = T_odom_base @ cal.T_base_camera
                if last is not None:
                    evolver.move_flies(invert(T_cam) @ last)
                last = T_cam
                evolver.set_images(frame.left, frame.right)
                evolver.step(30)
                est = loc.update(ev.stamp_ns, evolver.positions, evolver.fitness, T_odom_base)
                statuses.append(est.status)
                # odom starts at the robot's start pose = map origin here
                odo_err.append(np.hypot(*planar_from_transform(invert(frame.T_map_base) @ T_odom_base)[:2]))
                est_err.append(np.hypot(*planar_from_transform(invert(frame.T_map_base) @ est.T_map_base)[:2]))
    odo_rms, est_rms = np.sqrt(np.mean(np.square(odo_err))), np.sqrt(np.mean(np.square(est_err)))
    ok = np.mean([s == "ok" for s in statuses])
    print(f"\nposition RMS: odometry {odo_rms:.3f} m, localiser {est_rms:.3f} m; registered {100 * ok:.0f} % of frames")
    assert ok > 0.5
    assert est_rms < 0.6 * odo_rms


T_BASE_CAMERA = make_transform(R_BODY_OPTICAL, [0.0, 0.0, 0.4])


def seen_from(T_map_base, pts_map):
    """Map points as the camera of a robot at T_map_base sees them (left optical frame), in front only."""
    cam = transform_points(invert(T_map_base @ T_BASE_CAMERA), pts_map)
    return cam[cam[:, 2] > 0.5]


def test_unusable_population_lets_odometry_carry_on_and_says_why():
    rng = np.random.default_rng(0)
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig())
    cam = seen_from(planar_pose(0, 0, 0), corridor_points(rng, 4000))
    first = loc.update(0, cam, np.ones(len(cam)), planar_pose(0, 0, 0))
    assert first.status == "initialised" and len(loc.keyframes) == 1
    few = loc.update(10**8, cam[:20], np.ones(20), planar_pose(0.3, 0.0, 0.0))
    assert not few.registered and few.status.startswith("odometry only")
    assert np.allclose(few.T_map_base, planar_pose(0.3, 0, 0))
    with pytest.raises(LocaliserError):
        loc.update(2 * 10**8, cam, np.ones(len(cam)), np.full((4, 4), np.nan))


def test_map_memory_stays_bounded():
    rng = np.random.default_rng(1)
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig(max_keyframes=5, keyframe_distance_m=0.3))
    world = corridor_points(rng, 40000, length=25.0)
    for k in range(30):
        T = planar_pose(0.5 * k, 0.0, 0.0)
        cam = seen_from(T, world)
        loc.update(k * 10**8, cam, np.ones(len(cam)), T)
    assert len(loc.keyframes) == 5
    assert sum(len(kf.points) for kf in loc.keyframes) <= 5 * 40000


def room_points(rng, n):
    """Flies on the walls of a closed 11 m × 2 m corridor section (x in [-3, 8], y = ±1, end walls) with
    boxes, so that a robot turning on the spot at the origin sees a different wall at every heading."""
    side = rng.integers(0, 4, n)
    t = rng.random(n)
    x = np.where(side < 2, -3.0 + 11.0 * t, np.where(side == 2, -3.0, 8.0))
    y = np.where(side == 0, 1.0, np.where(side == 1, -1.0, -1.0 + 2.0 * t))
    pts = np.stack([x, y, rng.uniform(0.1, 2.0, n)], 1)
    box = rng.random(n) < 0.15
    pts[box, 1] *= 0.7
    pts[box, 0] = np.round(pts[box, 0])
    return pts


def _flies(world, T, rng):
    """(positions, fitness) of the flies a robot at T sees, every fly the same fitness."""
    v = _view(world, T, rng)
    return v, np.full(len(v), 0.5)


def _view(world, T, rng):
    cam = seen_from(T, world)
    cam = cam[(cam[:, 2] < 8.0) & (np.abs(cam[:, 0]) < 0.7 * cam[:, 2])][:3000]   # a 70° field of view
    return cam + rng.normal(0, 0.01, cam.shape)


def test_local_map_is_the_keyframes_that_look_the_same_way():
    """Two keyframes at the same spot, one looking down the corridor and one looking back: the local map
    for a robot looking back is the keyframe that looks back, not merely the nearest one."""
    rng = np.random.default_rng(3)
    world = room_points(rng, 60000)
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig(local_keyframes=1))
    ahead, back = planar_pose(0.0, 0.0, 0.0), planar_pose(0.05, 0.0, np.pi)
    loc.update(0, *_flies(world, ahead, rng), ahead, generation=500)
    # Looking back the map does not cover the view: a keyframe is added even without a registration.
    est = loc.update(20 * 10**9, *_flies(world, back, rng), back, generation=500)   # 9°/s
    assert est.keyframe_added and len(loc.keyframes) == 2
    chosen = loc.local_map(planar_pose(0.0, 0.0, np.pi))
    assert np.median(chosen[:, 0]) < 0     # the points behind the start (x < 0), not those ahead
    chosen = loc.local_map(planar_pose(0.1, 0.0, 0.0))       # nearer to the back-looking keyframe
    assert np.median(chosen[:, 0]) > 0


def test_no_registration_while_turning_fast():
    """Populations evolved while the view sweeps fast are not registered nor made keyframes; odometry
    carries the pose and the status says why."""
    rng = np.random.default_rng(4)
    world = room_points(rng, 60000)
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig())
    loc.update(0, *_flies(world, planar_pose(0, 0, 0), rng), planar_pose(0, 0, 0), generation=500)
    T = planar_pose(0.0, 0.0, np.deg2rad(9.0))          # 9° in 0.1 s: 90°/s
    est = loc.update(10**8, *_flies(world, T, rng), T, generation=500)
    assert not est.registered and est.status.startswith("odometry only: turning at 90°/s")
    assert not est.keyframe_added and np.allclose(est.T_map_base, T)
    T2 = planar_pose(0.0, 0.0, np.deg2rad(9.5))         # then slowly: registered again
    est = loc.update(2 * 10**8, *_flies(world, T2, rng), T2, generation=500)
    assert est.status == "ok"


def test_no_map_is_started_while_turning_fast():
    """The first keyframe is not made of a population evolved while the view swept fast: the map starts
    once the turn slows."""
    rng = np.random.default_rng(5)
    world = room_points(rng, 60000)
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig())
    T0 = planar_pose(0, 0, 0)
    v = _view(world, T0, rng)
    assert loc.update(0, v, np.full(len(v), 0.5), T0, generation=20).status.startswith("odometry only: waiting")
    T1 = planar_pose(0.0, 0.0, np.deg2rad(9.0))          # 90°/s, and the flies have converged meanwhile
    v = _view(world, T1, rng)
    est = loc.update(10**8, v, np.full(len(v), 0.5), T1, generation=500)
    assert est.status.startswith("odometry only: turning") and not loc.keyframes
    T2 = planar_pose(0.0, 0.0, np.deg2rad(9.5))
    v = _view(world, T2, rng)
    assert loc.update(2 * 10**8, v, np.full(len(v), 0.5), T2, generation=500).status == "initialised"


def test_missing_odometry_does_not_keep_a_stale_turn_rate():
    """Odometry that drops out right after a fast turn: the localiser registers on its constant-velocity
    prediction instead of refusing every population as 'turning' until odometry comes back."""
    rng = np.random.default_rng(6)
    world = room_points(rng, 60000)
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig())
    T0, T1 = planar_pose(0, 0, 0), planar_pose(0.0, 0.0, np.deg2rad(4.0))   # 40°/s
    v = _view(world, T0, rng)
    loc.update(0, v, np.full(len(v), 0.5), T0, generation=500)
    v = _view(world, T1, rng)
    assert loc.update(10**8, v, np.full(len(v), 0.5), T1, generation=500).status.startswith("odometry only: turning")
    v = _view(world, T1, rng)                                # stopped; no odometry for this population
    est = loc.update(2 * 10**8, v, np.full(len(v), 0.5), None, generation=500)
    assert est.registered and est.status == "ok"
    # nearer the truth than the constant-velocity prediction (4° on, to 8°)
    assert abs(planar_from_transform(invert(T1) @ est.T_map_base)[2]) < np.deg2rad(3.0)


def test_malformed_odometry_pose_is_refused_with_a_reason():
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig())
    with pytest.raises(LocaliserError, match="4×4"):
        loc.update(0, np.ones((200, 3)), np.ones(200), np.eye(3))



def test_tracking_right_after_a_fix_gives_the_global_search_answer(monkeypatch):
    """Within tracking_gap_s of a fix the localiser registers from one seed at the prediction instead of a
    lattice of candidates (the lattice was most of a registration's cost at 30 frames/s); driving down
    the corridor with an odometry that drifts sideways, it ends where the global search ends."""
    import common.slam.localiser as slam
    lattices = []
    real = slam.register_planar
    monkeypatch.setattr(slam, "register_planar", lambda *a, **k: lattices.append(k["lattice"]) or real(*a, **k))
    results = {}
    for gap in (0.0, 0.25):
        rng = np.random.default_rng(8)
        world = room_points(rng, 60000)
        loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig(tracking_gap_s=gap))
        lattices.clear()
        for k in range(8):
            truth = planar_pose(0.03 * k, 0.0, 0.0)
            odom = planar_pose(0.03 * k, 0.01 * k, np.deg2rad(0.2 * k))      # drifting left and turning
            est = loc.update(k * 10**8, *_flies(world, truth, rng), odom, generation=500)
            assert k == 0 or est.status == "ok"
        results[gap] = np.array(planar_from_transform(est.T_map_base))
        assert ((1, 1, 1) in lattices) == (gap > 0)      # tracking searched around the prediction only
    print(f"\nglobal {results[0.0]}, tracking {results[0.25]}")
    assert np.hypot(*(results[0.25][:2] - results[0.0][:2])) < 0.01
    assert abs(results[0.25][2] - results[0.0][2]) < np.deg2rad(0.2)


def test_tracking_pins_from_the_start_what_the_last_frame_found_on_the_window_edge(monkeypatch):
    """Along a corridor the registered position along the view often sits on the window's edge and is
    pinned and registered again (two registrations per frame).  While tracking, the next frames pin it
    from the start (one registration each), and every tracking_recheck_pinned frames the full window is
    tried again, so a position the view can pin again is not held at the prediction for ever."""
    import common.slam.localiser as slam
    from common.registration.register import RegistrationResult

    windows = []

    def edge_in_x(A, B, window, **kw):
        """A stand-in registration: its minimum along x is always beyond the window."""
        windows.append(np.array(window))
        p = np.array([window[0], 0.0, 0.0])
        edge = window[0] > 0
        return RegistrationResult(T=planar_pose(*p), params=p, covariance=np.eye(3) * 1e-4, delta=1.0,
                                  ok=not edge, reason="minimum on the search window boundary in parameter(s) [0]"
                                  if edge else "")
    monkeypatch.setattr(slam, "register_planar", edge_in_x)
    rng = np.random.default_rng(9)
    world = room_points(rng, 20000)
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig(tracking_recheck_pinned=3))
    for k in range(10):
        T = planar_pose(0.01 * k, 0.0, 0.0)
        est = loc.update(k * 33_000_000, *_flies(world, T, rng), T, generation=500)
        assert k == 0 or est.status == "ok"
    pinned_x = [w[0] == 0 for w in windows]
    # frame 1: full window, then pinned again; frames 2-4: pinned from the start; frame 5: full window
    # again (and pinned again), frames 6-8 pinned; frame 9 full window...
    assert pinned_x == [False, True, True, True, True, False, True, True, True, True, False, True]


def test_a_first_fix_long_after_the_maps_origin_restarts_the_map():
    """Visual-only, the motion unknown: a live start whose next population comes long after the map's
    origin (the evolver's first frame was slow) starts the map again from it rather than searching a
    motion beyond reach; the limit doubles at each restart, so a slow machine still gets its first fix."""
    rng = np.random.default_rng(7)
    world = corridor_points(rng, 6000, x0=-2.0, length=14.0)
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig(odometry="visual", first_fix_gap_s=0.3))

    def at(t_s, x):
        v = seen_from(planar_pose(x, 0, 0), world)
        return loc.update(int(t_s * 1e9), v, np.full(len(v), 0.5), generation=500)

    assert at(0.0, 0.0).status == "initialised"
    assert at(0.8, 6.0).status.startswith("initialised (the map restarted: 0.80 s")      # > 0.3 s
    assert at(1.5, 6.5).status.startswith("initialised (the map restarted: 0.70 s")      # > 0.6 s
    third = at(2.3, 7.0)                                                                 # ≤ 1.2 s
    assert not third.status.startswith("initialised") and loc.map_restarts == 2
    stamps, _ = loc.trajectory()
    assert stamps[0] == int(1.5e9) and len(stamps) == 2      # the trajectory starts with the last map
    wheels = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig(first_fix_gap_s=0.3))
    v = seen_from(planar_pose(0, 0, 0), world)
    wheels.update(0, v, np.full(len(v), 0.5), planar_pose(0, 0, 0), generation=500)
    v = seen_from(planar_pose(1.0, 0, 0), world)
    late = wheels.update(10**9, v, np.full(len(v), 0.5), planar_pose(1.0, 0, 0), generation=500)
    assert not late.status.startswith("initialised") and wheels.map_restarts == 0     # odometry knows the motion
    gappy = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig(first_fix_gap_s=0.3))
    v = seen_from(planar_pose(0, 0, 0), world)
    gappy.update(0, v, np.full(len(v), 0.5), planar_pose(0, 0, 0), generation=500)
    v = seen_from(planar_pose(1.0, 0, 0), world)
    gap = gappy.update(8 * 10**8, v, np.full(len(v), 0.5), None, generation=500)      # a gap in the odometry
    assert not gap.status.startswith("initialised") and gappy.map_restarts == 0


def test_a_slow_camera_s_next_frame_does_not_restart_the_map():
    """A camera slower than first_fix_gap_s (KITTI at every third frame, 0.3 s apart): its second
    frame comes late because no frame comes sooner, so the map keeps its origin and fixes from it."""
    rng = np.random.default_rng(7)
    world = room_points(rng, 20000)
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig(odometry="visual", first_fix_gap_s=0.3))
    for k, x in enumerate((0.0, 0.3, 0.6)):
        v = seen_from(planar_pose(x, 0, 0), world)
        est = loc.update(int(k * 0.5e9), v, np.full(len(v), 0.5), generation=500, next_frame=k > 0)
        assert est.status.startswith("initialised") == (k == 0), est.status
    stamps, _ = loc.trajectory()
    assert loc.map_restarts == 0 and stamps[0] == 0 and len(stamps) == 3   # it starts with the first frame


@pytest.mark.parametrize("second, restarts", [
    ((1, 0.5), 0),          # the next frame of a 2 frames/s camera: kept
    ((2, 0.5), 1),          # a frame skipped between: as late as it looks
    ((1, 5.0), 1),          # the next frame after a 5 s stall
    ((0, 0.5), 1),          # a restarted camera's seq 0 again (a new stamp: not a republication)
], ids=["next frame", "frame skipped", "stalled", "camera restarted"])
def test_the_core_tells_the_localiser_which_population_is_the_next_frame(second, restarts):
    from common import messages as m
    from common.slam.core import LocaliserCore
    from tests.test_relocalise import CALIB, corridor, population
    rng = np.random.default_rng(3)
    world = corridor(rng)
    core = LocaliserCore(LocaliserConfig(odometry="visual", first_fix_gap_s=0.3))
    core.on_calibration(m.calibration_to_msg(CALIB, 1, 1))
    T0, T1 = planar_pose(0.0, 0.0, 0.0), planar_pose(0.3, 0.0, 0.0)
    assert core.on_population(population(T0, world, rng, 0, 10**9, T0)).estimate.status == "initialised"
    seq, t_s = second
    out = core.on_population(population(T1, world, rng, seq, 10**9 + int(t_s * 1e9), T1))
    assert out.estimate.status.startswith("initialised") == bool(restarts), out.estimate.status
    assert core.localiser.map_restarts == restarts
