"""Pseudo-distance δ of Louchet et al.: exact reference and the fast FFT-grid field."""
import numpy as np
import pytest

from common.registration import (PopulationError, PseudoDistanceField, field_exact,
                                 pseudo_distance_exact)
from common.registration import scenes


def brute_force_delta(A, B, eps):
    n, p = len(A), len(B)
    total = 0.0
    for a in A:
        total += 1.0 / sum(1.0 / (eps + np.linalg.norm(a - b)) for b in B)
    return p / n * total


def test_exact_delta_matches_the_papers_formula_on_small_sets():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(7, 3))
    B = rng.normal(size=(11, 3)) + 0.5
    for eps in (1e-3, 0.1, 2.0):
        assert pseudo_distance_exact(A, B, eps) == pytest.approx(brute_force_delta(A, B, eps), rel=1e-12)


def test_exact_delta_is_chunk_independent_and_weighted_form_reduces_to_the_paper():
    rng = np.random.default_rng(2)
    A = rng.normal(size=(300, 3))
    B = rng.normal(size=(200, 3))
    ref = pseudo_distance_exact(A, B, 0.05)
    assert pseudo_distance_exact(A, B, 0.05, chunk_elems=1000) == pytest.approx(ref, rel=1e-12)
    assert pseudo_distance_exact(A, B, 0.05, np.full(300, 3.0), np.full(200, 0.5)) == pytest.approx(ref)
    # Zero weight on a fly of A removes it from the mean.
    wa = np.ones(300)
    wa[0] = 0
    assert pseudo_distance_exact(A, B, 0.05, wa) == pytest.approx(pseudo_distance_exact(A[1:], B, 0.05))


def test_delta_is_small_when_populations_coincide_and_grows_with_offset():
    rng = np.random.default_rng(3)
    B = rng.uniform(-5, 5, size=(400, 3))
    d0 = pseudo_distance_exact(B, B, 0.01)
    d1 = pseudo_distance_exact(B + [0.3, 0, 0], B, 0.01)
    d2 = pseudo_distance_exact(B + [1.0, 0, 0], B, 0.01)
    assert d0 < d1 < d2


def test_exact_field_gradient_matches_finite_differences():
    rng = np.random.default_rng(4)
    B = rng.normal(size=(50, 3))
    Q = rng.normal(size=(5, 3)) * 2
    S, G = field_exact(Q, B, 0.1, with_grad=True)
    h = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        num = (field_exact(Q + e, B, 0.1) - field_exact(Q - e, B, 0.1)) / (2 * h)
        np.testing.assert_allclose(G[:, k], num, rtol=1e-5, atol=1e-8)


@pytest.fixture(scope="module")
def deep_populations():
    rng = np.random.default_rng(5)
    rig = scenes.deep_rig()
    scene = scenes.street_scene(rng)
    A, _, _ = scenes.observe(scene, np.eye(4), rig, 5000, rng)
    B, _, _ = scenes.observe(scene, np.eye(4), rig, 5000, rng)
    return A, B


@pytest.mark.parametrize("eps", [0.01, 0.1, 1.0])
def test_fast_delta_within_one_percent_of_exact_on_a_deep_scene(deep_populations, eps):
    A, B = deep_populations
    field = PseudoDistanceField(B, eps, bounds=(A.min(0), A.max(0)))
    exact = pseudo_distance_exact(A, B, eps)
    assert field.delta(A) == pytest.approx(exact, rel=0.01)
    assert field.last_outside == 0


def test_tsc_deposit_is_more_accurate_than_cic_at_a_short_near_radius(deep_populations):
    """The default (TSC deposit, r_c = one grid spacing) keeps the field within ≈0.1 % at a typical
    fly; the same split with the cloud-in-cell deposit aliases the kernel's core into the grid and is
    further off (≈1.4× here, ≈2.7× on the bench's populations)."""
    A, B = deep_populations
    A = A[:2000]
    S = field_exact(A, B, 0.1)
    bounds = (A.min(0), A.max(0))
    err = {dep: np.median(np.abs(PseudoDistanceField(B, 0.1, bounds=bounds, near_cells=1.0,
                                                     deposit=dep).field(A) - S) / S)
           for dep in ("tsc", "cic")}
    assert err["tsc"] < 2e-3
    assert err["tsc"] < 0.8 * err["cic"]
    with pytest.raises(PopulationError, match="deposit"):
        PseudoDistanceField(B, 0.1, deposit="ngp")


def test_fast_gradient_gives_the_derivative_of_delta_under_translation(deep_populations):
    A, B = deep_populations
    A = A[:1000] + [0.4, -0.2, 0.6]  # displaced, so the translation derivative is far from zero
    field = PseudoDistanceField(B, 0.1, bounds=(A.min(0) - 1, A.max(0) + 1))
    _, g = field.delta_and_grad(A)
    h = 0.02
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        numeric = (pseudo_distance_exact(A + e, B, 0.1) - pseudo_distance_exact(A - e, B, 0.1)) / (2 * h)
        assert g[:, k].sum() == pytest.approx(numeric, rel=0.05, abs=0.02)


def test_points_outside_the_grid_fall_back_to_exact():
    rng = np.random.default_rng(6)
    B = rng.uniform(-2, 2, size=(300, 3))
    field = PseudoDistanceField(B, 0.1)
    far = np.array([[30.0, 0, 0], [0, -40.0, 5]])
    np.testing.assert_allclose(field.field(far), field_exact(far, B, 0.1), rtol=1e-12)
    assert field.last_outside == 2


def test_malformed_input_raises_clear_errors():
    B = np.zeros((10, 3))
    with pytest.raises(PopulationError, match="shape"):
        pseudo_distance_exact(np.zeros((4, 2)), B, 0.1)
    with pytest.raises(PopulationError, match="non-finite"):
        pseudo_distance_exact(np.array([[0, np.nan, 0]]), B, 0.1)
    with pytest.raises(PopulationError, match="eps"):
        pseudo_distance_exact(B, B, 0.0)
    with pytest.raises(PopulationError, match="empty"):
        PseudoDistanceField(np.zeros((0, 3)), 0.1)
    with pytest.raises(PopulationError, match="weights_b"):
        pseudo_distance_exact(B, B, 0.1, weights_b=np.ones(3))


def test_parallel_and_serial_evaluation_agree_with_gradients():
    rng = np.random.default_rng(7)
    B = rng.uniform(-4, 4, size=(3000, 3))
    Q = rng.uniform(-4, 4, size=(5000, 3))
    serial = PseudoDistanceField(B, 0.1)
    parallel = PseudoDistanceField(B, 0.1, parallel_min=1)
    S1, G1 = serial.field(Q, with_grad=True)
    S2, G2 = parallel.field(Q, with_grad=True)
    np.testing.assert_allclose(S2, S1, rtol=1e-12)
    np.testing.assert_allclose(G2, G1, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(serial.field(Q), S1, rtol=1e-12)   # value-only path, same numbers


def test_local_correlation_field_matches_a_brute_force_sum():
    from common.registration import LocalCorrelationField
    rng = np.random.default_rng(8)
    B = rng.uniform(-3, 3, size=(2000, 3))
    w = rng.uniform(0.1, 2.0, size=2000)
    Q = rng.uniform(-3.5, 3.5, size=(200, 3))
    eps, rc = 0.1, 0.6
    d = np.linalg.norm(Q[:, None, :] - B[None, :, :], axis=2)
    dc = eps + rc
    bump = np.where(d < rc, 1 / (eps + d) - (1 / dc - (d ** 2 - rc ** 2) / (2 * rc * dc ** 2)), 0.0)
    expected = (bump * w).sum(1)
    S = LocalCorrelationField(B, eps, rc, weights_b=w).field(Q)
    np.testing.assert_allclose(S, expected, rtol=1e-5, atol=1e-5)
