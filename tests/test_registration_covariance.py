"""The covariance a registration reports: consistent with the scatter it describes, blind to cloned flies,
and a flat minimum only when the window cannot place it."""
import numpy as np
import pytest

from common.geometry import invert, make_transform, rot_y, transform_points
from common.registration import StereoModel, register_planar, scenes

RIG = scenes.deep_rig()
MOTION = make_transform(rot_y(np.deg2rad(2.0)), [0.1, 0.0, 0.4])
TRUTH = np.array([0.1, 0.4, np.deg2rad(2.0)])
WINDOW = (0.5, 0.5, np.deg2rad(8.0))


@pytest.fixture(scope="module")
def street():
    return scenes.street_scene(np.random.default_rng(3), length=40.0)


def test_reported_sigma_brackets_the_scatter_of_independent_pairs(street):
    """16 independent pairs of noisy populations (0.4 px disparity noise, 3 % outliers) of one street:
    per axis, the median of |error| / reported σ is within a factor 2 of a Gaussian's 0.674."""
    errors, sigmas = [], []
    for k in range(16):
        rng = np.random.default_rng(100 + k)
        A = scenes.observe(street, np.eye(4), RIG, 2000, rng, max_depth=20.0)[0]
        B = scenes.observe(street, MOTION, RIG, 2000, rng, max_depth=20.0)[0]
        res = register_planar(A, B, plane="optical", window=WINDOW, eps=0.05, stereo=StereoModel(RIG), seed=k)
        if np.all(np.isfinite(res.covariance)):
            errors.append(res.params - TRUTH)
            sigmas.append(res.std)
    assert len(errors) >= 12
    ratio = np.median(np.abs(np.array(errors)) / np.array(sigmas), axis=0)
    assert np.all(ratio > 0.674 / 2) and np.all(ratio < 0.674 * 2), ratio


def test_cloned_flies_add_no_information(street):
    """Every fly of A repeated four times (1 mm apart) measures nothing new: the covariance must not
    shrink (an independent-fly sandwich halves the standard deviations)."""
    rng = np.random.default_rng(1)
    A = scenes.observe(street, np.eye(4), RIG, 1500, rng, max_depth=20.0)[0]
    B = scenes.observe(street, MOTION, RIG, 1500, rng, max_depth=20.0)[0]
    clones = np.repeat(A, 4, axis=0) + rng.normal(0, 0.001, (4 * len(A), 3))
    kw = dict(plane="optical", window=WINDOW, eps=0.05, max_points=10**6)
    single, cloned = register_planar(A, B, **kw), register_planar(clones, B, **kw)
    assert single.ok and cloned.ok, (single.reason, cloned.reason)
    np.testing.assert_allclose(cloned.std, single.std, rtol=0.2)


def test_flat_only_when_the_window_cannot_place_the_minimum():
    """Two walls along the line of sight: z is the soft direction.  Searched over ±1 m it is pinned to
    ≈0.1–0.2 m and reported (ok); searched over a window narrower than its σ it is flat, and the
    covariance still says how well x and θ are known."""
    rng = np.random.default_rng(16)

    def corridor(n):
        side = rng.choice([-1.0, 1.0], n)
        return np.column_stack([side + rng.normal(0, 0.01, n), rng.uniform(-1.2, 1.2, n), rng.uniform(2, 30, n)])
    T = make_transform(rot_y(0.02), [0.1, 0, 0.4])
    A, B = corridor(3000), transform_points(invert(T), corridor(3000))
    wide = register_planar(A, B, plane="optical")
    assert wide.ok, wide.reason
    assert wide.flatness >= 1.0
    assert wide.std[1] > 5 * wide.std[0]
    assert abs(wide.params[1] - 0.4) < 3 * wide.std[1]
    narrow = register_planar(A, B, plane="optical", prior=T, window=(0.3, 0.2, np.deg2rad(5.0)))
    assert not narrow.ok and narrow.reason.startswith("flat minimum"), narrow.reason
    assert narrow.flatness < 1.0
    sx, sz, sth = narrow.std
    assert sz > 0.2 and sx < 0.05 and sth < np.deg2rad(0.5)
