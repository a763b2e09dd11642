"""Relocalisation in a known fly map: a robot put down at an unknown pose finds it (and only then
tracks and maps), refuses a map that looks the same everywhere, and says so in its status."""
from __future__ import annotations

import numpy as np

from common import messages as m
from common.camera import StereoCalibration
from common.geometry import invert, planar_from_transform, planar_pose, transform_points, wrap_angle
from common.slam import Keyframe, LocaliserConfig
from common.slam.core import LocaliserCore
from common.slam.localiser import FlyLocaliser
from common.slam.mapfile import FlyMapData, MapKeyframe
from common.slam.relocalise import Relocaliser
from tests.test_slam import T_BASE_CAMERA

CALIB = StereoCalibration.ideal(320, 240, T_base_camera=T_BASE_CAMERA)


def corridor(rng, n=60000, length=24.0, boxes=((3.2, -0.7), (5.5, 0.7), (9.1, -0.7), (11.6, 0.7), (12.2, -0.7),
                                                 (16.0, 0.7), (18.3, 0.7), (20.3, -0.7))):
    """Two walls (y = ±1) and boxes (0.4 m cubes) at irregular places along the corridor (no two
    stretches of the default layout alike: a pair of boxes repeated 6 m on is rightly ambiguous)."""
    wall = rng.random(n) < 0.8
    side = rng.choice([-1.0, 1.0], n)
    pts = np.stack([rng.uniform(-1.0, length, n), side, rng.uniform(0.1, 2.2, n)], 1)
    which = rng.integers(0, len(boxes), n)
    centre = np.array(boxes)[which]
    face = rng.uniform(-0.2, 0.2, (n, 3))
    box_pts = np.stack([centre[:, 0] + face[:, 0], centre[:, 1] + face[:, 1], 0.2 + face[:, 2]], 1)
    axis = rng.integers(0, 3, n)
    box_pts[np.arange(n), axis] = np.where(axis == 2, 0.4, np.where(axis == 0, centre[:, 0], centre[:, 1])
                                           + 0.2 * rng.choice([-1, 1], n))
    return np.where(wall[:, None], pts, box_pts)


def view(T_map_base, world, rng, noise=0.01):
    """Points of the world a robot at T_map_base sees (left optical frame, in the image, 0.5–8 m)."""
    cam = transform_points(invert(T_map_base @ T_BASE_CAMERA), world)
    cam = cam[(cam[:, 2] > 0.5) & (cam[:, 2] < 8.0)]
    u = CALIB.fx * cam[:, 0] / cam[:, 2] + CALIB.cx_left
    v = CALIB.fy * cam[:, 1] / cam[:, 2] + CALIB.cy
    cam = cam[(u >= 0) & (u < CALIB.width) & (v >= 0) & (v < CALIB.height)]
    return cam + rng.normal(0, noise, cam.shape)


def saved_map(world, rng, xs=np.arange(0.0, 19.0, 1.5)) -> FlyMapData:
    """A map as the localiser saves it: keyframes along the corridor's centre line (base_link points)."""
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig(), calibration=CALIB)
    kfs = []
    for i, x in enumerate(xs):
        T = planar_pose(float(x), 0.0, 0.0)
        pts, fit = loc.select_flies(view(T, world, rng), np.ones(len(view(T, world, rng))))
        kfs.append(MapKeyframe(i, 10**9 * (i + 1), T, pts.astype(np.float32), fit.astype(np.float32)))
    return FlyMapData(kfs, [], {})


def population(T_map_base, world, rng, seq, stamp_ns, T_odom_base):
    cam = view(T_map_base, world, rng).astype(np.float32)
    return m.FlyPopulation(positions=cam, fitness=np.ones(len(cam), np.float32), generation=500, source_seq=seq,
                           T_odom_camera=T_odom_base @ T_BASE_CAMERA, header=m.header(0, stamp_ns, m.CAMERA_LEFT_OPTICAL))


def errors(T, T_true):
    x, y, yaw = planar_from_transform(T)
    tx, ty, tyaw = planar_from_transform(T_true)
    return float(np.hypot(x - tx, y - ty)), float(np.degrees(abs(wrap_angle(yaw - tyaw))))


def test_a_kidnapped_robot_relocalises_then_tracks_and_maps_only_after(tmp_path):
    rng = np.random.default_rng(4)
    world = corridor(rng)
    fly_map = saved_map(world, rng)
    core = LocaliserCore(LocaliserConfig(), initial_map=fly_map)
    core.on_calibration(m.calibration_to_msg(CALIB, 1, 1))
    odom_offset = planar_pose(30.0, -12.0, 2.0)         # odometry's frame says nothing about the map
    start = np.array([8.3, 0.15, np.deg2rad(6.0)])
    outputs, truths = [], []
    for k in range(8):
        T_true = planar_pose(start[0] + 0.05 * k, start[1], start[2])
        T_odom = odom_offset @ planar_pose(0.05 * k, 0.0, 0.0)
        outputs.append(core.on_population(population(T_true, world, rng, k + 1, (k + 1) * 10**8, T_odom)))
        truths.append(T_true)
        if not core.relocalising:
            break
    assert not core.relocalising, [o.pose.status for o in outputs]
    searching, found = outputs[:-1], outputs[-1]
    assert len(searching) >= 2                          # one winning frame is not enough
    for o in searching:                                 # no pose fusion or the planner would take
        assert o.estimate is None and o.map_to_odom is None
        assert o.pose.status.startswith("relocalising: ")
        assert np.all(np.diag(o.pose.covariance) >= 1e3)
    assert len(core.keyframes) == len(fly_map.keyframes)        # nothing mapped while lost
    e_m, e_deg = errors(core.relocalisation.T_map_base, truths[-1])
    assert e_m < 0.1 and e_deg < 1.0, (e_m, e_deg, core.relocalisation.reason)
    # the same population is then localised as usual, from the found pose
    assert found.estimate is not None and found.map_to_odom is not None
    assert not found.pose.status.startswith("relocalising")
    stamps, traj = core.trajectory()
    assert len(stamps) == 1 and errors(traj[0], truths[-1])[0] < 0.15
    nxt = core.on_population(population(planar_pose(start[0] + 0.5, start[1], start[2]), world, rng, 20, 2 * 10**9,
                                        odom_offset @ planar_pose(0.5, 0.0, 0.0)))
    assert nxt.estimate is not None and errors(nxt.estimate.T_map_base, planar_pose(start[0] + 0.5, *start[1:]))[0] < 0.15


def test_a_map_that_repeats_itself_is_never_taken_for_a_place():
    """Boxes every 3 m on a corridor far longer than the view: every third keyframe sees the same."""
    rng = np.random.default_rng(5)
    boxes = tuple((x, 0.7 if i % 2 else -0.7) for i, x in enumerate(np.arange(0.0, 40.0, 1.5)))
    world = corridor(rng, length=40.0, boxes=boxes)
    fly_map = saved_map(world, rng, xs=np.arange(3.0, 31.0, 1.5))
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig(), calibration=CALIB)
    loc.load_map(fly_map)
    relo = Relocaliser(loc.map_keyframes(), stereo=loc.stereo)
    previous, streak = None, 0
    for k in range(4):
        T = planar_pose(15.2 + 0.05 * k, 0.1, 0.0)
        pts, fit = loc.select_flies(view(T, world, rng), np.ones(len(view(T, world, rng))))
        res = relo.search(pts, fit, previous=previous, streak=streak)
        assert res.T_map_base is None and res.reason.startswith("ambiguous"), res.reason
        previous, streak = res.best, res.streak
        if previous is not None:
            previous = previous @ planar_pose(0.05, 0.0, 0.0)


def test_a_restart_hint_relocalises_from_the_first_population():
    rng = np.random.default_rng(6)
    world = corridor(rng)
    fly_map = saved_map(world, rng)
    T_true = planar_pose(11.0, -0.1, np.deg2rad(-4.0))
    odom = planar_pose(3.0, 4.0, 1.0)
    hint = T_true @ planar_pose(0.08, 0.03, np.deg2rad(0.5)) @ invert(odom)      # map->odom, a little off
    core = LocaliserCore(LocaliserConfig(), initial_map=fly_map, hint_map_to_odom=hint)
    core.on_calibration(m.calibration_to_msg(CALIB, 1, 1))
    out = core.on_population(population(T_true, world, rng, 1, 10**8, odom))
    assert not core.relocalising and out.estimate is not None, core.relocalisation.reason
    assert errors(core.relocalisation.T_map_base, T_true)[0] < 0.1
