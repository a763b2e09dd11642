"""The localiser's pose-graph back-end: a loop closes and pulls the drifted end back; a saved map
reloads and a new run registers against it from its first frame."""
from __future__ import annotations

import numpy as np

from common.geometry import invert, planar_from_transform, planar_pose, scaled_motion
from common.slam import FlyLocaliser, LocaliserConfig
from common.slam.mapfile import load_map, save_map
from tests.test_slam import T_BASE_CAMERA, seen_from

# A corridor ring 2 m wide around a 8 m x 2 m block; the robot drives its centre line (0,0)-(10,0)-(10,4)-(0,4).
WALLS = [((-1, -1), (11, -1)), ((11, -1), (11, 5)), ((11, 5), (-1, 5)), ((-1, 5), (-1, -1)),
         ((1, 1), (9, 1)), ((9, 1), (9, 3)), ((9, 3), (1, 3)), ((1, 3), (1, 1))]


def ring_points(rng, n):
    """Flies on the ring's walls (z 0.1-2 m) and on 40 boxes along them, so every place looks different."""
    a, b = np.array([w[0] for w in WALLS], float), np.array([w[1] for w in WALLS], float)
    length = np.linalg.norm(b - a, axis=1)
    wall = rng.choice(len(WALLS), n, p=length / length.sum())
    t = rng.random(n)[:, None]
    xy = a[wall] + t * (b[wall] - a[wall])
    pts = np.column_stack([xy, rng.uniform(0.1, 2.0, n)])
    centres = a[wall[:40]] + rng.random((40, 1)) * (b[wall[:40]] - a[wall[:40]])
    box = rng.random(n) < 0.25
    k = rng.integers(0, 40, box.sum())
    pts[box, :2] = centres[k] + rng.uniform(-0.25, 0.25, (box.sum(), 2))
    pts[box, 2] = rng.uniform(0.1, 0.6, box.sum())
    return pts


def lap():
    """True planar poses of one lap (0.2 m steps, 5° turns on the spot), ending 3 m past the start."""
    poses, x, y, yaw = [], 2.0, 0.0, 0.0
    for leg, turn in ((8.0, 1), (4.0, 1), (10.0, 1), (4.0, 1), (3.0, 0)):
        for _ in range(int(round(leg / 0.2))):
            x, y = x + 0.2 * np.cos(yaw), y + 0.2 * np.sin(yaw)
            poses.append((x, y, yaw))
        for _ in range(18 * turn):
            yaw += np.deg2rad(5.0)
            poses.append((x, y, yaw))
    return poses


def drive(loc, world, poses, rng, yaw_scale=1.0, dist_scale=1.0, yaw_per_m=0.0, estimates=None):
    """Feed one population per pose with odometry integrating the true steps with scale errors; returns
    (first estimate, final estimate, final odometry pose) — odometry starts at the first true pose.
    ``estimates``: a list every estimate is appended to."""
    T_odom = planar_pose(*poses[0])
    prev = poses[0]
    est = first = None
    for k, p in enumerate(poses):
        d = planar_from_transform(invert(planar_pose(*prev)) @ planar_pose(*p))
        T_odom = T_odom @ planar_pose(d[0] * dist_scale, d[1] * dist_scale,
                                      d[2] * yaw_scale + yaw_per_m * np.hypot(d[0], d[1]))
        prev = p
        cam = seen_from(planar_pose(*p), world)
        cam = cam[rng.random(len(cam)) < 0.5]
        cam = cam + rng.normal(0, 0.01, cam.shape)          # 1 cm of fly noise
        est = loc.update(k * 500_000_000, cam, np.ones(len(cam)), T_odom)
        first = first or est
        if estimates is not None:
            estimates.append(est)
    return first, est, T_odom


def test_a_loop_closure_pulls_the_drifted_end_of_a_lap_back():
    # Registrations all refused (gate below 0): only odometry moves the pose, 2 % over-turning and 3 %
    # over-counted distance drift it by about a metre over the lap; keyframes still come.
    world = ring_points(np.random.default_rng(0), 30000)
    poses = lap()
    errors = {}
    for closure in (False, True):
        cfg = LocaliserConfig(gate_chi2=-1.0, min_view_coverage=1.01, loop_closure=closure)
        loc = FlyLocaliser(T_BASE_CAMERA, cfg)
        _, est, T_odom = drive(loc, world, poses, np.random.default_rng(1), yaw_scale=1.02, dist_scale=1.03)
        truth = planar_pose(*poses[-1])
        errors[closure] = float(np.linalg.norm(est.T_map_base[:2, 3] - truth[:2, 3]))
        stamps, traj = loc.trajectory()
        assert len(stamps) == len(poses)
        if closure:
            assert any(lc.accepted for lc in loc.loop_closures)
            assert np.allclose(traj[-1], est.T_map_base, atol=1e-6)    # the published end is the graph's
        odometry_error = float(np.linalg.norm(T_odom[:2, 3] - truth[:2, 3]))
    print(f"\nend error: odometry {odometry_error:.2f} m, no closure {errors[False]:.2f} m, "
          f"closure {errors[True]:.2f} m")
    assert errors[False] > 0.3
    assert errors[True] < 0.4 * errors[False]


def test_a_saved_map_reloads_and_a_new_run_registers_against_it(tmp_path):
    rng = np.random.default_rng(2)
    world = ring_points(rng, 20000)
    poses = lap()[:70]          # the first leg, the corner and 2 m of the second
    first = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig())
    drive(first, world, poses, rng)
    path = save_map(tmp_path / "map.mcap", first.map_keyframes(), first.map_edges())
    saved = load_map(path)
    assert len(saved.keyframes) == len(first.map_keyframes()) and saved.edges

    second = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig())
    second.load_map(saved)
    # the same stretch again on wheels that curve the path 2°/m: the saved map holds it where it was
    first_est, est, T_odom = drive(second, world, poses, rng, yaw_per_m=np.deg2rad(2.0))
    assert first_est.status != "initialised"      # the first population met the saved map, no new map started
    truth = planar_pose(*poses[-1])
    err = float(np.linalg.norm(est.T_map_base[:2, 3] - truth[:2, 3]))
    odo = float(np.linalg.norm(T_odom[:2, 3] - truth[:2, 3]))
    print(f"\nsecond run on the saved map: end error {err:.3f} m, odometry {odo:.2f} m")
    assert odo > 0.5
    assert err < 0.2
    ids = [kf.id for kf in second.map_keyframes()]
    assert ids[: len(saved.keyframes)] == [kf.id for kf in saved.keyframes] and len(set(ids)) == len(ids)
    assert len(ids) - len(saved.keyframes) <= 3                  # the saved map covers the stretch
    assert second.trajectory()[0].size == len(poses)


def test_a_correction_of_the_keyframes_bends_the_trajectory_without_a_step_at_a_keyframe():
    """The corrected trajectory follows the keyframes smoothly: when the later keyframes are turned 5°
    about the first of them (as a graph correction does), the estimates made before it lean over
    towards it, by the share of the way between the two keyframes they had come (metres over
    keyframe_distance_m plus angle over keyframe_angle_rad, step by step), instead of the whole
    correction landing between two consecutive poses where one keyframe hands over to the next.
    Without the pose graph nothing else moves the keyframes, so the trajectory starts as published."""
    rng = np.random.default_rng(4)
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig(min_generations=0, pose_graph=False))
    published = []
    drive(loc, ring_points(rng, 20000), lap()[:40], rng, estimates=published)   # 8 m straight
    stamps, before = loc.trajectory()
    assert np.allclose(before, [e.T_map_base for e in published], atol=1e-9)
    kfs = loc.map_keyframes()
    assert len(kfs) >= 4
    prev, moved = kfs[len(kfs) // 2 - 1], kfs[len(kfs) // 2]
    pivot = planar_pose(*moved.T_map_base[:2, 3], 0.0)
    D = pivot @ planar_pose(0.0, 0.0, np.deg2rad(5.0)) @ invert(pivot)
    for kf in kfs:
        if kf.id >= moved.id:
            kf.T_map_base = D @ kf.T_map_base
    _, after = loc.trajectory()
    assert np.allclose(after[stamps <= prev.stamp_ns], before[stamps <= prev.stamp_ns], atol=1e-12)
    assert np.allclose(after[stamps >= moved.stamp_ns], D @ before[stamps >= moved.stamp_ns], atol=1e-9)
    between = np.flatnonzero((stamps > prev.stamp_ns) & (stamps < moved.stamp_ns))
    assert len(between) >= 3

    def way(k):          # from estimate k - 1 to estimate k, in keyframe spacings
        x, y, yaw = planar_from_transform(invert(before[k - 1]) @ before[k])
        return np.hypot(x, y) / loc.config.keyframe_distance_m + abs(yaw) / loc.config.keyframe_angle_rad

    whole = sum(way(k) for k in range(between[0], between[-1] + 2))     # to the moved keyframe's estimate
    for i in between:
        share = sum(way(k) for k in range(between[0], i + 1)) / whole
        expected = before[i] @ scaled_motion(invert(before[i]) @ D @ before[i], share)
        assert np.allclose(after[i], expected, atol=1e-9)
    turned = np.rad2deg([planar_from_transform(T)[2] for T in after]) - np.rad2deg(
        [planar_from_transform(T)[2] for T in before])
    assert np.all(np.diff(turned) >= -1e-9) and np.max(np.diff(turned)) < 2.0     # 5° over several poses


def test_a_robot_that_waits_between_keyframes_hardly_slides_when_they_are_corrected():
    """The blend goes by the way come, not the time: while the robot waits for 20 frames between two
    keyframes its poses keep nearly the same share of the correction (the estimates' jitter is all
    that moves them); by time they would slide 7 cm of a 10 cm correction while it stood still."""
    rng = np.random.default_rng(6)
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig(min_generations=0, pose_graph=False))
    straight = lap()[:40]
    poses = straight[:13] + [straight[12]] * 20 + straight[13:]      # 20 frames waiting at 2.6 m
    drive(loc, ring_points(rng, 20000), poses, rng)
    stamps, before = loc.trajectory()
    waiting = (stamps >= 12 * 500_000_000) & (stamps < 33 * 500_000_000)
    anchors = {kf.id for (_, kf, _), w in zip(loc._history, waiting) if w}
    assert len(anchors) == 1, "the robot waits between two keyframes"
    for kf in loc.map_keyframes():
        if kf.id > min(anchors):
            kf.T_map_base = planar_pose(0.0, 0.1, 0.0) @ kf.T_map_base
    _, after = loc.trajectory()
    shift = after[:, 1, 3] - before[:, 1, 3]
    assert 0.0 < shift[waiting][0] < 0.1
    assert np.ptp(shift[waiting]) < 0.02
    assert np.all(np.diff(shift[:np.flatnonzero(waiting)[-1] + 1]) > -1e-9)


def test_estimates_before_a_relocalisation_do_not_follow_the_keyframes_made_after_it():
    """A relocalisation starts a new run of estimates: keyframes made after it, corrected by the graph,
    move the estimates made since the relocalisation (those before the first new keyframe by their share
    of the way to it) and none made before it."""
    rng = np.random.default_rng(5)
    world = ring_points(rng, 20000)
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig(min_generations=0, loop_closure=False))
    poses = lap()[:40]
    for k, p in enumerate(poses):
        if k == 20:
            loc.relocalised(k * 500_000_000, planar_pose(*p), planar_pose(*p))
        cam = seen_from(planar_pose(*p), world)
        cam = cam[rng.random(len(cam)) < 0.5]
        loc.update(k * 500_000_000, cam, np.ones(len(cam)), planar_pose(*p))
    stamps, before = loc.trajectory()
    after_reloc = [kf for kf in loc.map_keyframes() if kf.stamp_ns > 20 * 500_000_000]
    assert after_reloc
    for kf in after_reloc:
        kf.T_map_base = planar_pose(0.0, 0.1, 0.0) @ kf.T_map_base
    _, after = loc.trajectory()
    shift = after[:, 1, 3] - before[:, 1, 3]
    assert np.all(np.abs(shift[stamps <= 20 * 500_000_000]) < 1e-12)
    assert np.allclose(shift[stamps >= after_reloc[0].stamp_ns], 0.1)
    leaning = shift[(stamps > 20 * 500_000_000) & (stamps < after_reloc[0].stamp_ns)]
    assert len(leaning) >= 2 and np.all((leaning > 0) & (leaning < 0.1)) and np.all(np.diff(leaning) > 0)


def test_a_pose_graph_that_cannot_be_solved_does_not_stop_the_localiser(monkeypatch):
    """GTSAM refusing a system (an indeterminate one, from a front end that diverged) costs the back-end's
    correction, never the localiser: every population still gets a pose and the failures are counted."""
    from common.slam import backend
    from common.slam.posegraph import PoseGraphError

    def unsolvable(self, newest_id, batch=False):
        raise PoseGraphError("pose graph cannot be solved: Indeterminate linear system")

    rng = np.random.default_rng(3)
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig(min_generations=0))
    monkeypatch.setattr(backend.KeyframeGraph, "optimise", unsolvable)
    poses = lap()[:60]
    _, last, _ = drive(loc, ring_points(rng, 20000), poses, rng)
    assert loc.graph_failures >= 2 and len(loc.keyframes) >= 3
    assert len(loc.trajectory()[0]) == len(poses)
    assert np.hypot(*(last.T_map_base[:2, 3] - np.array(poses[-1][:2]))) < 0.5



# A wheeled robot's keyframes as a demo run's front end placed them (x, y, z m; roll, pitch, yaw °): the
# photometric fixes are 6-DoF, and the last one is 3.7 cm below the floor and pitched 0.4°.
DEMO_KEYFRAMES = [
    [2.027, 0.059, 0.0, 0.0, 0.0, 7.24], [3.535, 0.216, 0.0008, -0.016, 0.018, 0.27],
    [4.607, 0.274, -0.0007, -0.029, -0.003, 16.23], [5.568, 0.561, 0.0004, -0.018, 0.016, 0.11],
    [6.343, 0.475, -0.0025, 0.015, -0.027, 15.76], [6.448, 0.522, 0.0015, -0.035, 0.040, 31.21],
    [7.092, 0.662, 0.0001, -0.001, 0.017, -10.83], [7.407, 0.554, 0.0001, -0.010, 0.004, -26.22],
    [8.546, 0.219, -0.0026, -0.051, -0.026, -5.33], [8.928, 0.244, -0.0011, -0.028, -0.004, 9.68],
    [10.421, 0.425, -0.0019, -0.018, -0.037, 13.74], [11.913, 0.692, 0.0003, 0.018, 0.002, 4.81],
    [13.400, 0.963, 0.0004, -0.019, 0.025, 18.84], [14.212, 1.162, 0.0001, 0.004, -0.001, 2.85],
    [14.545, 1.132, -0.0004, 0.005, -0.005, -12.62], [16.038, 0.767, 0.0007, -0.065, 0.004, 1.36],
    [17.564, 0.756, -0.0367, -0.099, -0.399, -2.64]]


def test_a_keyframe_a_little_off_the_floor_does_not_swing_the_planar_graph():
    """Factors built from 6-DoF poses contradicted the planar graph's z/roll/pitch priors by tens of
    sigmas; the robust kernel then discounted the newest odometry factor whole and the chain swung
    3 m and 16° (a demo run's jump). The graph keeps every keyframe's x, y and yaw."""
    from common.geometry import make_transform
    from common.slam.backend import KeyframeGraph
    from common.slam.localiser import Keyframe

    def pose(x, y, z, roll, pitch, yaw):
        r, p, w = np.deg2rad([roll, pitch, yaw])
        Rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
        Ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
        Rz = np.array([[np.cos(w), -np.sin(w), 0], [np.sin(w), np.cos(w), 0], [0, 0, 1]])
        return make_transform(Rz @ Ry @ Rx, [x, y, z])

    graph = KeyframeGraph(LocaliserConfig(), planar=True)
    fix_cov = np.diag([1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5]) ** 2
    for i, row in enumerate(DEMO_KEYFRAMES):
        kf = Keyframe(i, i * 10**9, pose(*row), np.zeros((0, 3), np.float32), np.zeros(0, np.float32))
        graph.add(kf, [], fix_cov if i else None)
        graph.optimise(i)
    for i, (x0, y0, _, _, _, yaw0) in enumerate(DEMO_KEYFRAMES):
        x, y, yaw = planar_from_transform(graph.archive[i].T_map_base)
        assert np.hypot(x - x0, y - y0) < 0.01 and abs(np.rad2deg(yaw) - yaw0) < 0.1, (i, x, y, np.rad2deg(yaw))


def _keyframe_seeing(kf_id, T_true, T_est, world, rng):
    """A keyframe made at the (drifted) estimate T_est of a robot truly at T_true: its flies are what the
    camera (a 35° half-angle cone) saw there, in base_link."""
    from common.slam.localiser import Keyframe
    cam = seen_from(T_true, world)
    cam = cam[np.abs(cam[:, 0] / cam[:, 2]) < np.tan(np.deg2rad(35.0))]
    cam = cam[rng.random(len(cam)) < 0.3]
    cam = cam + rng.normal(0, 0.01, cam.shape)          # 1 cm of fly noise
    base = (T_BASE_CAMERA[:3, :3] @ cam.T).T + T_BASE_CAMERA[:3, 3]
    return Keyframe(kf_id, kf_id * 10**9, T_est, base.astype(np.float32), np.ones(len(base), np.float32))


def straight_corridor(rng, n):
    """Flies on the walls (y = ±1, z 0.1-2 m) of a straight corridor from x = -4 to 14, a quarter of them
    on 30 boxes at random places along it (so that no stretch repeats another)."""
    side = rng.choice([-1.0, 1.0], n)
    pts = np.stack([rng.uniform(-4, 14, n), side, rng.uniform(0.1, 2.0, n)], 1)
    centres = rng.uniform(-4, 14, 30)
    box = rng.random(n) < 0.25
    k = rng.integers(0, 30, box.sum())
    pts[box, 0] = centres[k] + rng.uniform(-0.2, 0.2, box.sum())
    pts[box, 1] = np.where(k % 2 == 0, 0.7, -0.7) + rng.uniform(-0.15, 0.15, box.sum())
    return pts


def test_a_loop_registers_the_overlap_of_two_views_far_apart_along_a_corridor():
    """Back 2.4 m behind the first keyframe, drifted 0.3 m along, 0.4 m across and 4°: most of the new
    keyframe's flies lie between the two cameras, where the old one never looked.  Registered whole,
    they pull it forward to the window's edge, a metre along the corridor; on the two views' overlap
    the loop factor stays within the drift it corrects."""
    rng = np.random.default_rng(3)
    world = straight_corridor(rng, 40000)
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig(loop_closure=True))
    old = _keyframe_seeing(0, planar_pose(0, 0, 0), planar_pose(0, 0, 0), world, rng)
    T_true = planar_pose(-2.4, 0.0, 0.0)
    new = _keyframe_seeing(1, T_true, T_true @ planar_pose(0.3, 0.4, np.deg2rad(4.0)), world, rng)
    loc.backend.add(old)
    loc.backend.add(new)
    assert loc._close_loop(old, new) is not None, loc.loop_closures
    loop = [e for e in loc.backend.graph.edges().values() if e.kind not in ("prior", "odometry")][-1]
    x, y, yaw = planar_from_transform(loop.T_i_j)       # the new keyframe in the old one's frame
    assert abs(x + 2.4) < 0.7 and abs(y) < 0.2 and abs(np.rad2deg(yaw)) < 1.5, (x, y, np.rad2deg(yaw))


def test_a_place_mapped_long_ago_comes_back_through_loop_closure_not_tracking():
    """Until a loop closure ties the drifted lap to its start, the start's keyframes are not tracked
    against (a window sized for one update's drift met the whole lap's); after it, they are."""
    world = ring_points(np.random.default_rng(0), 30000)
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig(gate_chi2=-1.0, min_view_coverage=1.01, loop_closure=True))
    chosen_before, chosen_after = [], []
    choose = loc._local_keyframes

    def spy(T):
        idx, cover = choose(T)
        closed = any(lc.accepted for lc in loc.loop_closures)
        newest = max(kf.id for kf in loc._pool)
        (chosen_after if closed else chosen_before).append(min((loc._pool[i].id for i in idx), default=newest) - newest)
        return idx, cover

    loc._local_keyframes = spy
    drive(loc, world, lap(), np.random.default_rng(1), yaw_scale=1.02, dist_scale=1.03)
    sep = loc.config.loop_min_separation
    assert any(lc.accepted for lc in loc.loop_closures)
    assert min(chosen_before) >= -sep
    assert min(chosen_after) < -sep


def test_a_loop_on_the_loop_scenario_registers_against_the_old_keyframes_neighbourhood():
    """The keyframes of the simulated loop (recordings/scenarios/loop.toml, seed 0; tests/data) as the
    localiser held them when it closed the loop: the new keyframe 2.5 m behind the first one shares few of
    its flies with it.  Registered against that one keyframe the loop factor was 2.8° and 0.23 m off, and
    the closure bent the whole lap (final error 0.12 -> 0.12 m, ATE 0.063 -> 0.086 % of the path); the
    old keyframe with its neighbours pins it to the truth."""
    from pathlib import Path

    from common.camera import StereoCalibration
    from common.slam.localiser import Keyframe
    d = np.load(Path(__file__).parent / "data" / "loop_closure_keyframes.npz")
    w, h, fx, fy, cxl, cxr, cy, b = d["calibration"]
    K = np.array([[fx, 0, cxl], [0, fy, cy], [0, 0, 1]])
    calib = StereoCalibration(int(w), int(h), fx, fy, cxl, cxr, cy, b, K_left=K, K_right=K.copy(),
                              T_base_camera=d["T_base_camera"])
    loc = FlyLocaliser(d["T_base_camera"], LocaliserConfig(loop_closure=True), calibration=calib)
    kfs = {int(i): Keyframe(int(i), int(i) * 10**9, d[f"T_{i}"], d[f"points_{i}"], d[f"fitness_{i}"])
           for i in d["ids"]}
    for kf in kfs.values():
        loc.backend.add(kf)
    old, new = kfs[int(d["old_id"])], kfs[int(d["new_id"])]
    handle = loc._close_loop(old, new)
    assert handle is not None, loc.loop_closures
    measured = loc.backend.graph.edge(handle).T_i_j                  # the new keyframe in the old one's frame
    truth = invert(d[f"truth_{old.id}"]) @ d[f"truth_{new.id}"]
    x, y, yaw = planar_from_transform(invert(truth) @ measured)
    assert np.hypot(x, y) < 0.08 and abs(np.rad2deg(yaw)) < 1.0, (x, y, np.rad2deg(yaw))


def test_a_loop_waits_for_a_keyframe_near_the_old_one():
    """On the simulated loop the keyframe made 2.5 m behind the first one is no loop candidate: views
    that far apart change scale, and a closure measured there was 115 mm off on one seed and left the
    lap worse than none.  The next keyframe, within a keyframe spacing of the old one, closes it."""
    from pathlib import Path

    from common.slam.localiser import Keyframe
    d = np.load(Path(__file__).parent / "data" / "loop_closure_keyframes.npz")
    loc = FlyLocaliser(d["T_base_camera"], LocaliserConfig(loop_closure=True))
    kfs = {int(i): Keyframe(int(i), int(i) * 10**9, d[f"T_{i}"], d[f"points_{i}"], d[f"fitness_{i}"])
           for i in d["ids"]}
    for kf in kfs.values():
        loc.backend.add(kf)
    old, far = kfs[int(d["old_id"])], kfs[int(d["new_id"])]
    assert np.hypot(*(invert(old.T_map_base) @ far.T_map_base)[:2, 3]) > 2.0
    assert loc.backend.loop_candidate(far, exclude=set()) is None
    near = Keyframe(far.id + 1, far.stamp_ns + 10**9, old.T_map_base @ planar_pose(-1.0, 0.05, 0.01),
                    far.points, far.fitness)
    loc.backend.add(near)
    assert loc.backend.loop_candidate(near, exclude=set()) is old
    wide = FlyLocaliser(d["T_base_camera"], LocaliserConfig(loop_closure=True, loop_radius_m=3.0))
    wide.backend.archive.update(kfs)
    assert wide.backend.loop_candidate(far, exclude=set()) is old, "a radius set by the user still holds"
