"""Sonar term on a synthetic wall, sonar scans in base_link and their echo points."""
from __future__ import annotations

import numpy as np
import pytest

from common.camera import StereoCalibration
from common.fusion.sonar import SonarScanError, echo_points, scan_in_base
from common.fusion.sonar_term import SonarTerm, SonarTermConfig, in_echo_beams, sonar_fitness
from common.geometry import R_BODY_OPTICAL, invert, make_transform, transform_points
from common.messages import SonarScan, header

WALL_X = 2.0                   # a wall across the robot's path, 2 m ahead of base_link
RING, HEIGHT, K = 0.2, 0.25, 12
T_BASE_CAMERA = make_transform(R_BODY_OPTICAL, [0.10, 0.0, 0.45])   # camera 45 cm up, looking forward


def ring_scan(frame: str = "base_link") -> SonarScan:
    """12 transducers around a ring; only the front one (yaw 0) faces the wall and hears it."""
    yaw = np.arange(K) * 2 * np.pi / K
    yaw = (yaw + np.pi) % (2 * np.pi) - np.pi
    poses = np.stack([RING * np.cos(yaw), RING * np.sin(yaw), yaw], 1)
    ranges = np.full(K, np.nan, np.float32)
    ranges[np.argmin(np.abs(yaw))] = WALL_X - RING
    return SonarScan(transducer_poses=poses, ranges=ranges, beam_width_rad=np.deg2rad(25.0), min_range_m=0.15,
                     max_range_m=5.0, header=header(7, 123, frame))


def in_camera(points_base) -> np.ndarray:
    return transform_points(invert(T_BASE_CAMERA), np.asarray(points_base, float)).astype(np.float32)


def test_sonar_term_on_a_synthetic_wall():
    rng = np.random.default_rng(0)
    n = 400
    # Inside the front beam (|bearing| < 10°, near the ring's height), in free space before the wall.
    before = np.c_[rng.uniform(0.5, 1.6, n), rng.uniform(-0.05, 0.05, n), rng.uniform(0.2, 0.3, n)]
    # On the wall, inside the beam.
    bearing = rng.uniform(-0.15, 0.15, n)
    on_wall = np.c_[np.full(n, WALL_X), np.tan(bearing) * (WALL_X - RING), rng.uniform(0.2, 0.3, n)]
    # Outside every beam with an echo: high above the ring, and off to the sides where nothing answered.
    above = np.c_[rng.uniform(0.5, 1.6, n), rng.uniform(-0.1, 0.1, n), rng.uniform(1.2, 2.0, n)]
    aside = np.c_[rng.uniform(-1.0, 1.0, n), rng.choice([-1.0, 1.0], n) * rng.uniform(0.8, 1.5, n),
                  np.full(n, HEIGHT)]
    pts = np.vstack([before, on_wall, above, aside])
    term = SonarTerm(SonarTermConfig(height_m=HEIGHT, reward_gain=1.0))
    assert np.all(term(in_camera(pts)) == 0.0), "no scan yet: no effect"
    term.update(ring_scan(), T_BASE_CAMERA)
    fit = term(in_camera(pts))
    assert fit.shape == (4 * n,) and fit.dtype == np.float32
    f_before, f_wall, f_above, f_aside = np.split(fit, 4)
    assert np.all(f_before <= -0.5), "free space nearer than the echo is penalised"
    nearer = np.argsort(np.linalg.norm(before - [RING, 0.0, HEIGHT], axis=1))
    assert np.all(np.diff(f_before[nearer]) >= -1e-6), "... the more, the nearer (a slope out of free space)"
    assert np.all(f_wall >= 0.95), "flies at the echo range are rewarded"
    assert np.all(f_above == 0.0) and np.all(f_aside == 0.0), "flies outside the beams are unaffected"
    # By default only the free-space penalty acts (see the module docstring for why).
    default = sonar_fitness(in_camera(pts), T_BASE_CAMERA, ring_scan(), SonarTermConfig(height_m=HEIGHT))
    np.testing.assert_allclose(default[:n], f_before, atol=1e-6)
    assert np.all(default[n:] == 0.0)
    # The floor inside the cone is not free space: it never echoes at grazing incidence.
    floor = in_camera([[1.0, 0.0, 0.02]])
    assert sonar_fitness(floor, T_BASE_CAMERA, ring_scan(), SonarTermConfig(height_m=HEIGHT,
                                                                            vertical_half_angle_rad=0.3))[0] == 0.0
    mask = in_echo_beams(in_camera(pts), T_BASE_CAMERA, ring_scan(), SonarTermConfig(height_m=HEIGHT))
    assert mask[:2 * n].all() and not mask[2 * n:].any()
    # Behind the wall (possibly occluded) nothing is said either.
    behind = in_camera([[WALL_X + 0.5, 0.0, HEIGHT]])
    assert term(behind)[0] == 0.0


def test_sonar_term_matches_its_functional_form_and_rejects_bad_input():
    pts = in_camera([[1.0, 0.0, HEIGHT], [WALL_X, 0.0, HEIGHT]])
    scan = ring_scan()
    cfg = SonarTermConfig(height_m=HEIGHT, reward_gain=1.0)
    np.testing.assert_allclose(sonar_fitness(pts, T_BASE_CAMERA, scan, cfg), [-(0.5 + 0.5 * (1.8 - 0.8) / 1.8), 1.0],
                               rtol=1e-5)
    with pytest.raises(ValueError, match="positions must be"):
        sonar_fitness(pts[:, :2], T_BASE_CAMERA, scan)
    with pytest.raises(SonarScanError, match="base_link"):
        sonar_fitness(pts, T_BASE_CAMERA, ring_scan("sonar_ring"))
    # "No echo" is only read as free space when asked: a fly ahead-left in the 60° beam.
    left = in_camera([[0.8 * np.cos(np.pi / 3), 0.2 + 0.8 * np.sin(np.pi / 3), HEIGHT]])
    assert sonar_fitness(left, T_BASE_CAMERA, scan)[0] == 0.0
    assert sonar_fitness(left, T_BASE_CAMERA, scan, SonarTermConfig(no_echo_is_free=True))[0] < -0.5


def test_sonar_term_plugs_into_the_evolver():
    from common.fly.evolver import FlyEvolver
    from tests.fly_synthetic import textured_plane_pair

    calib, left, right, _ = textured_plane_pair()
    calib = StereoCalibration.ideal(calib.width, calib.height, baseline=calib.baseline, T_base_camera=T_BASE_CAMERA)
    ev = FlyEvolver(calib, seed=0)
    ev.set_images(left, right)
    term = SonarTerm(SonarTermConfig(height_m=HEIGHT, reward_gain=1.0))
    term.update(ring_scan(), T_BASE_CAMERA)
    pts = in_camera([[1.0, 0.0, 0.40], [WALL_X, 0.0, 0.40]])   # both in the camera's view, in the beam
    base = ev.evaluate(pts)
    ev.add_fitness_term("sonar", term, weight=0.5)
    with_sonar = ev.evaluate(pts)
    np.testing.assert_allclose(with_sonar - base, 0.5 * term(pts), atol=1e-6)
    assert with_sonar[0] < base[0] and with_sonar[1] > base[1]


def test_scan_in_base_and_echo_points():
    scan = ring_scan()
    scan.ranges[3] = 9.0                          # beyond max range: not an echo
    base = scan_in_base(scan)
    assert base.header.frame_id == "base_link" and base.header.stamp_ns == 123
    assert np.isnan(base.ranges[3])
    pts = echo_points(base, HEIGHT, arc_samples=3)
    assert pts.shape == (3, 3)
    np.testing.assert_allclose(pts[1], [WALL_X, 0.0, HEIGHT], atol=1e-6)   # the beam's axis hits the wall
    assert np.allclose(np.hypot(pts[:, 0] - RING, pts[:, 1]), WALL_X - RING, atol=1e-5)
    # A ring mounted 0.1 m ahead and turned 90° left: poses are re-expressed in base_link.
    mounted = scan_in_base(ring_scan("sonar_ring"), mount_xyyaw=(0.1, 0.0, np.pi / 2))
    front = np.argmin(np.abs(ring_scan().transducer_poses[:, 2]))
    np.testing.assert_allclose(mounted.transducer_poses[front], [0.1, RING, np.pi / 2], atol=1e-12)
    with pytest.raises(SonarScanError, match="mount"):
        scan_in_base(ring_scan("sonar_ring"))
    bad = ring_scan()
    bad.ranges = bad.ranges[:5]
    with pytest.raises(SonarScanError, match="ranges of shape"):
        scan_in_base(bad)
