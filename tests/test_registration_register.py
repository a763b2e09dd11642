"""Registration of fly populations: recovery of known displacements, failures, covariance shape."""
import numpy as np
import pytest

from common.geometry import (R_BODY_OPTICAL, invert, make_transform, planar_pose, rot_y, so3_exp,
                             transform_points)
from common.registration import PopulationError, register_6dof, register_planar
from common.registration import scenes


def noisy_replica(A, T_f, rng, noise=0.02, keep=0.9):
    """B such that f(B) ≈ A: A moved by f⁻¹, jittered, shuffled, with some flies missing."""
    B = transform_points(invert(T_f), A) + rng.normal(0, noise, A.shape)
    idx = rng.permutation(len(A))[: int(keep * len(A))]
    return B[idx]


@pytest.fixture(scope="module")
def street_flies():
    rng = np.random.default_rng(10)
    scene = scenes.street_scene(rng)
    A, _, _ = scenes.observe(scene, np.eye(4), scenes.deep_rig(), 3000, rng, max_depth=25.0)
    return A


def test_planar_optical_recovers_known_motion_of_a_noisy_replica(street_flies):
    rng = np.random.default_rng(11)
    x, z, th = 0.3, 0.7, np.deg2rad(4.0)
    T_f = make_transform(rot_y(th), [x, 0, z])
    B = noisy_replica(street_flies, T_f, rng)
    res = register_planar(street_flies, B, plane="optical")
    assert res.ok, res.reason
    assert res.params[0] == pytest.approx(x, abs=0.03)
    assert res.params[1] == pytest.approx(z, abs=0.03)
    assert res.params[2] == pytest.approx(th, abs=np.deg2rad(0.3))
    np.testing.assert_allclose(res.T, make_transform(rot_y(res.params[2]), [res.params[0], 0, res.params[1]]))
    # The covariance is a proper covariance, and the truth is within a plausible distance of it.
    assert np.all(np.linalg.eigvalsh(res.covariance) > 0)
    assert res.delta > 0


def test_planar_body_frame_recovers_known_motion(street_flies):
    rng = np.random.default_rng(12)
    A_body = street_flies @ R_BODY_OPTICAL.T          # same flies, REP-103 body axes (z up)
    T_f = planar_pose(0.6, -0.25, np.deg2rad(-6.0))
    B = noisy_replica(A_body, T_f, rng)
    res = register_planar(A_body, B, plane="body")
    assert res.ok, res.reason
    np.testing.assert_allclose(res.params, [0.6, -0.25, np.deg2rad(-6.0)], atol=0.03)


def test_6dof_recovers_known_motion(street_flies):
    rng = np.random.default_rng(13)
    w = np.array([0.03, -0.06, 0.02])
    t = np.array([0.2, -0.1, 0.5])
    T_f = make_transform(so3_exp(w), t)
    B = noisy_replica(street_flies, T_f, rng)
    res = register_6dof(street_flies, B)
    assert res.ok, res.reason
    np.testing.assert_allclose(res.params[:3], t, atol=0.04)
    np.testing.assert_allclose(res.params[3:], w, atol=np.deg2rad(0.4))
    assert res.covariance.shape == (6, 6)


def test_prior_and_window_from_odometry(street_flies):
    rng = np.random.default_rng(14)
    T_f = make_transform(rot_y(np.deg2rad(25.0)), [1.5, 0, 2.0])   # outside the default window
    B = noisy_replica(street_flies, T_f, rng)
    prior = make_transform(rot_y(np.deg2rad(23.0)), [1.4, 0, 2.2])
    res = register_planar(street_flies, B, prior=prior, window=(0.5, 0.5, np.deg2rad(5)))
    assert res.ok, res.reason
    np.testing.assert_allclose(res.params, [1.5, 2.0, np.deg2rad(25.0)], atol=0.03)
    # Without the prior the truth is outside the window: reported, not silently wrong.
    bad = register_planar(street_flies, B)
    assert not bad.ok and "boundary" in bad.reason


def test_plane_sliding_along_itself_is_reported_flat():
    rng = np.random.default_rng(15)

    def ground(n):  # flies on the ground plane (y = 1.5 m below an optical camera), 2–30 m ahead
        return np.column_stack([rng.uniform(-10, 10, n), 1.5 + rng.normal(0, 0.02, n), rng.uniform(2, 30, n)])
    # Planar motion slides the ground along itself: x, z and θ about the plane's normal are all free.
    # Two independent populations (a replica would carry its random texture, which does register).
    A = ground(3000)
    B = transform_points(invert(make_transform(rot_y(0.03), [0.3, 0, 0.5])), ground(3000))
    res = register_planar(A, B, plane="optical")
    assert not res.ok
    assert "flat" in res.reason or "boundary" in res.reason
    assert res.flatness < 1.0          # σ along the ground wider than the search window


@pytest.mark.parametrize("A,B,word", [
    (np.zeros((0, 3)), np.ones((100, 3)), "too few"),
    (np.random.default_rng(0).normal(size=(100, 3)), np.zeros((5, 3)), "too few"),
    (np.random.default_rng(0).normal(size=(100, 3)), np.zeros((100, 3)), "degenerate"),
])
def test_empty_or_degenerate_input_is_reported_not_raised(A, B, word):
    for res in (register_planar(A, B), register_6dof(A, B)):
        assert not res.ok
        assert word in res.reason
        assert np.all(np.isnan(res.covariance))


def test_corridor_constrains_lateral_motion_better_than_longitudinal():
    rng = np.random.default_rng(16)

    def corridor(n):  # the paper's corridor: two parallel walls x = ±1 m, 2–30 m ahead
        side = rng.choice([-1.0, 1.0], n)
        return np.column_stack([side + rng.normal(0, 0.01, n), rng.uniform(-1.2, 1.2, n), rng.uniform(2, 30, n)])
    A = corridor(3000)
    B = transform_points(invert(make_transform(rot_y(0.02), [0.1, 0, 0.4])), corridor(3000))
    res = register_planar(A, B, plane="optical", flat_ratio=0.0)
    assert res.ok, res.reason
    assert res.params[0] == pytest.approx(0.1, abs=0.02)
    sx, sz, _ = res.std
    assert sz > 5 * sx
    # Soft is not flat: the default threshold lets it through, its σ_z saying how soft (and the error is
    # within it); test_registration_covariance.py has the window that cannot place it.
    default = register_planar(A, B, plane="optical")
    assert default.ok, default.reason
    assert abs(default.params[1] - 0.4) < 3 * default.std[1]


def test_malformed_input_raises():
    A = np.random.default_rng(0).normal(size=(100, 3))
    with pytest.raises(PopulationError, match="plane"):
        register_planar(A, A, plane="sideways")
    with pytest.raises(PopulationError, match="shape"):
        register_planar(A[:, :2], A)
    with pytest.raises(PopulationError, match="prior"):
        register_planar(A, A, prior=np.ones((4, 4)))
    with pytest.raises(PopulationError, match="window"):
        register_6dof(A, A, window=(1, 1, 1))


def test_repeating_structure_is_reported_ambiguous():
    rng = np.random.default_rng(17)

    def poles(n, period=2.0):  # identical poles every 2 m along the street, on both sides
        k = rng.integers(-20, 21, n)
        side = rng.choice([-2.0, 2.0], n)
        return np.column_stack([side + rng.normal(0, 0.05, n), rng.uniform(-2, 1.5, n),
                                k * period + rng.normal(0, 0.05, n)])
    A = poles(3000)
    B = transform_points(invert(make_transform(None, [0, 0, 0.3])), poles(3000))
    # A window longer than the period holds several equally good answers.
    res = register_planar(A, B, window=(0.5, 2.5, 0.05), objective="local")
    assert not res.ok
    assert "ambiguous" in res.reason
    assert res.ambiguity > 0.9


def test_lattice_poses_match_the_single_pose_maps():
    from common.registration.register import _POSES, _poses_batch
    rng = np.random.default_rng(18)
    for mode, k in (("optical", 3), ("body", 3), ("6dof", 6)):
        P = rng.normal(size=(40, k)) * 0.4
        if k == 6:
            P[0, 3:] = 0.0          # the zero rotation takes so3_exp's small-angle branch
        Rs, ts = _poses_batch(mode, P)
        for i in range(len(P)):
            R, t = _POSES[mode](P[i])
            np.testing.assert_allclose(Rs[i], R, atol=1e-12)
            np.testing.assert_allclose(ts[i], t, atol=1e-12)


def test_timings_report_every_stage(street_flies):
    rng = np.random.default_rng(19)
    B = noisy_replica(street_flies, make_transform(rot_y(0.02), [0.2, 0, 0.3]), rng)
    res = register_planar(street_flies, B)
    stages = ("setup_ms", "field_ms", "lattice_ms", "polish_ms", "refine_ms", "covariance_ms")
    assert all(res.timings[s] >= 0 for s in stages)
    assert sum(res.timings[s] for s in stages) <= res.timings["total_ms"] + 1e-6


def test_sharp_minimum_of_equivalent_populations_at_small_eps_is_accepted():
    """Two populations on the same surface points (as two evolutions on one stereo pair are) give δ
    a cusp at the identity when ε is small.  The registration lands on it and must say so: the
    curvature check used to call these "not a minimum" (gradient differences across the cusp)."""
    rng = np.random.default_rng(3)
    n = 3000
    wall = rng.integers(0, 4, n)                        # a corridor: two walls, floor, far wall
    P = np.column_stack([rng.uniform(-1.2, 1.2, n), rng.uniform(-1.0, 1.2, n), rng.uniform(1.0, 8.0, n)])
    P[wall == 0, 0], P[wall == 1, 0], P[wall == 2, 1], P[wall == 3, 2] = -1.2, 1.2, 1.2, 8.0
    A = P + rng.normal(0, 0.0005, P.shape)
    B = P + rng.normal(0, 0.0005, P.shape)
    res = register_planar(A, B, eps=0.03, window=(0.5, 0.5, 0.2))
    assert res.ok, res.reason
    assert np.all(np.abs(res.params[:2]) < 0.002) and abs(res.params[2]) < 1e-3
    assert np.all(np.isfinite(res.covariance)) and np.all(np.linalg.eigvalsh(res.covariance) > 0)


def test_without_curvature_the_same_answer_faster_and_no_covariance(street_flies):
    """curvature=False (what the localiser asks for: it has its own measurement model) gives the same
    estimate without the Hessian stage, reports no covariance, and still refuses a minimum on the window's
    edge."""
    rng = np.random.default_rng(12)
    T_f = make_transform(rot_y(np.deg2rad(2.0)), [0.2, 0, 0.4])
    B = noisy_replica(street_flies, T_f, rng)
    full = register_planar(street_flies, B, plane="optical")
    quick = register_planar(street_flies, B, plane="optical", curvature=False)
    assert quick.ok and full.ok
    np.testing.assert_allclose(quick.params, full.params, atol=1e-9)
    assert np.all(np.isnan(quick.covariance)) and quick.hessian is None
    assert "covariance_ms" not in quick.timings and "covariance_ms" in full.timings
    narrow = register_planar(street_flies, B, plane="optical", window=(0.1, 0.1, np.deg2rad(5)), curvature=False)
    assert not narrow.ok and narrow.reason.startswith("minimum on the search window boundary")
