"""Each Fly-algorithm operator does what it says: sampling, mutation, crossovers, sharing, fitness."""
import numpy as np
import pytest
from scipy import stats

from common.camera import StereoCalibration
from common.fly.fitness import OUTSIDE_FITNESS, ImageError, image_fitness, prepare_frame, prepare_images
from common.fly.operators import (CROSSOVER2, CROSSOVER3, EXCHANGE, IMMIGRANT, MUTATION, SharingGrid,
                                  backproject_uvd, camera_vector, cell_order, crossover2, crossover3, exchange_depth,
                                  make_offspring, mutate, plan_batch, project_uvd)
from common.fly.sampling import SamplingError, sample_flies
from common.fly.synthetic import textured_plane_pair


@pytest.fixture
def calib():
    return StereoCalibration.ideal(width=320, height=240, baseline=0.12)


def test_immigrants_lie_in_both_fields_of_view_with_uniform_inverse_depth(calib):
    rng = np.random.default_rng(1)
    pts = sample_flies(calib, 20000, depth_min=0.5, depth_max=20.0, rng=rng, margin=4)
    ul, ur, v = calib.project(pts)
    for name, u in (("left", ul), ("right", ur)):
        assert u.min() >= 4 and u.max() <= calib.width - 5, f"{name} projection leaves the image"
    assert v.min() >= 4 and v.max() <= calib.height - 5
    # Every disparity of this range is seen by both cameras, so 1/z must be uniform on [1/20, 1/0.5].
    iz = 1.0 / pts[:, 2]
    assert stats.kstest(iz, stats.uniform(loc=1 / 20, scale=1 / 0.5 - 1 / 20).cdf).pvalue > 1e-3
    # At each depth the left pixel is uniform over the part of the image also seen by the right camera.
    d = ul - ur
    u_min, u_max = np.maximum(4, 4 + d), np.minimum(calib.width - 5, calib.width - 5 + d)
    assert stats.kstest((ul - u_min) / (u_max - u_min), "uniform").pvalue > 1e-3
    assert stats.kstest(v, stats.uniform(loc=4, scale=calib.height - 9).cdf).pvalue > 1e-3


def test_infinite_depth_max_reaches_zero_disparity(calib):
    pts = sample_flies(calib, 5000, depth_min=1.0, depth_max=np.inf, rng=np.random.default_rng(2))
    assert np.all(np.isfinite(pts))
    d = calib.fx * calib.baseline / pts[:, 2]
    assert d.min() < 0.05 * d.max()


def test_impossible_depth_range_is_refused(calib):
    # At 1 mm the disparity is far wider than the image: no point is seen by both cameras.
    with pytest.raises(SamplingError, match="disparit"):
        sample_flies(calib, 10, depth_min=0.0005, depth_max=0.001, rng=np.random.default_rng(0))


def test_uvd_round_trip(calib):
    pts = sample_flies(calib, 1000, 0.5, 10.0, np.random.default_rng(3))
    u, v, d = project_uvd(calib, pts)
    np.testing.assert_allclose(backproject_uvd(calib, u, v, d), pts, rtol=1e-4, atol=1e-5)


def test_mutation_is_gaussian_in_disparity_with_the_given_step(calib):
    rng = np.random.default_rng(4)
    pts = np.repeat(calib.backproject([160.0], [120.0], [30.0]).astype(np.float32), 20000, axis=0)
    kids = mutate(calib, pts, sigma_px=0.5, sigma_d=np.full(20000, 2.0, np.float32),
                  d_range=(0.0, 200.0), rng=rng)
    u, v, d = project_uvd(calib, kids)
    assert abs(d.mean() - 30) < 0.05 and abs(d.std() - 2.0) < 0.05
    assert abs(u.std() - 0.5) < 0.02 and abs(v.std() - 0.5) < 0.02
    # The step is the same in disparity wherever the fly is: far flies move further in metres.
    far = np.repeat(calib.backproject([160.0], [120.0], [5.0]).astype(np.float32), 20000, axis=0)
    kids_far = mutate(calib, far, 0.5, np.full(20000, 2.0, np.float32), (0.5, 200.0), rng)
    assert kids_far[:, 2].std() > 10 * kids[:, 2].std()


def test_mutation_respects_disparity_range(calib):
    pts = np.repeat(calib.backproject([160.0], [120.0], [10.0]).astype(np.float32), 5000, axis=0)
    kids = mutate(calib, pts, 0.0, np.full(5000, 50.0, np.float32), (8.0, 12.0), np.random.default_rng(5))
    _, _, d = project_uvd(calib, kids)
    assert d.min() >= 8.0 - 1e-3 and d.max() <= 12.0 + 1e-3


def test_depth_exchange_keeps_the_pixel_and_takes_the_mates_disparity(calib):
    rng = np.random.default_rng(8)
    parents = sample_flies(calib, 500, 0.5, 10.0, rng)
    mates = sample_flies(calib, 500, 0.5, 10.0, rng)
    kids = exchange_depth(calib, parents, mates, rng)
    uk, vk, dk = project_uvd(calib, kids)
    up, vp, _ = project_uvd(calib, parents)
    _, _, dm = project_uvd(calib, mates)
    np.testing.assert_allclose(uk, up, atol=1e-3)
    np.testing.assert_allclose(vk, vp, atol=1e-3)
    np.testing.assert_allclose(dk, dm, rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("reach", [8, 6])     # 2·8 mates share one random draw; 2·6 are drawn one by one
def test_depth_exchange_copies_the_fittest_of_eight_random_neighbours(calib, reach):
    n, best_of = 4000, 8
    d = np.linspace(1.0, 40.0, n)                  # fly i's disparity tells which fly a child copied
    pos = backproject_uvd(calib, np.full(n, 160.0), np.full(n, 120.0), d)
    fit = np.random.default_rng(1).random(n).astype(np.float32)
    parents = np.arange(reach, n - reach)
    child = np.empty((len(parents), 3), np.float32)
    make_offspring(np.full(len(parents), EXCHANGE), parents, parents, parents, pos, fit,
                   np.zeros(len(parents), np.float32), np.zeros((0, 3), np.float32), camera_vector(calib), 0.0,
                   0.0, 100.0, 0.0, 0.0, reach, best_of, 5, child, np.empty(len(parents), np.float32))
    copied = np.argmin(np.abs(project_uvd(calib, child)[2][:, None] - d[None, :].astype(np.float32)), axis=1)
    offset = copied - parents
    assert set(np.unique(offset)) == set(range(-reach, 0)) | set(range(1, reach + 1))
    # the fittest of the 2·reach neighbours is among best_of uniform draws with this probability
    best = np.array([p + o for p in parents for o in [np.argmax(
        [fit[p + k] if k else -1 for k in range(-reach, reach + 1)]) - reach]])
    expected = 1 - (1 - 1 / (2 * reach)) ** best_of
    assert abs(np.mean(copied == best) - expected) < 0.03


def test_batch_plan_draws_operators_at_their_rates_and_parents_by_tournament():
    n = 20000
    shared = np.random.default_rng(2).random(n).astype(np.float32)
    rates = np.array([0.2, 0.1, 0.1, 0.02, 0.58])          # mutation, crossover2, crossover3, immigrant, exchange
    ops, parents = np.empty(n, np.int64), np.empty(n, np.int64)
    plan_batch(np.cumsum(rates), shared, 2, np.zeros(0, np.int64), True, 3, ops, parents)
    np.testing.assert_allclose(np.bincount(ops, minlength=5) / n, rates, atol=0.01)
    assert np.all(np.diff(parents) >= 0)                   # sorted by parent: evaluated in image order
    local = (ops == MUTATION) | (ops == EXCHANGE)
    assert len(np.unique(parents[local])) == local.sum()   # every fly refines itself at most once
    crossing = np.isin(ops, (CROSSOVER2, CROSSOVER3))
    # the fitter of two random flies is in the top half three times in four
    assert abs(np.mean(shared[parents[crossing]] > np.median(shared)) - 0.75) < 0.03
    assert np.isin(IMMIGRANT, ops)


def test_population_order_is_by_cell_with_flies_outside_the_image_last():
    cells = np.random.default_rng(4).integers(-1, 50, 3000)
    order = cell_order(cells, 50)
    key = np.where(cells < 0, 50, cells)
    np.testing.assert_array_equal(order, np.argsort(key, kind="stable"))


def test_two_parent_crossover_child_lies_between_parents():
    rng = np.random.default_rng(6)
    p1, p2 = rng.normal(size=(1000, 3)).astype(np.float32), rng.normal(size=(1000, 3)).astype(np.float32)
    c = crossover2(p1, p2, rng)
    seg = p2 - p1
    t = np.einsum("ij,ij->i", c - p1, seg) / np.einsum("ij,ij->i", seg, seg)
    np.testing.assert_allclose(p1 + t[:, None] * seg, c, atol=1e-4)
    assert t.min() >= -1e-5 and t.max() <= 1 + 1e-5 and t.std() > 0.2


def test_three_parent_crossover_child_lies_in_parents_plane():
    rng = np.random.default_rng(7)
    p1, p2, p3 = (rng.normal(size=(1000, 3)).astype(np.float32) for _ in range(3))
    c = crossover3(p1, p2, p3, rng)
    normal = np.cross(p2 - p1, p3 - p1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    assert np.abs(np.einsum("ij,ij->i", c - p1, normal)).max() < 1e-4
    # Not just a copy of a parent: children spread over the triangle.
    assert np.linalg.norm(c - p1, axis=1).min() > 0 and np.linalg.norm(c - p1, axis=1).std() > 0.1


def test_sharing_lowers_crowded_flies():
    # 100 cells, 100 flies: ten crowd the first cell, the other 90 have a cell each (the even share).
    grid = SharingGrid(100, 100, cell_px=10, strength=1.0)
    cu, cv = np.meshgrid(np.arange(10), np.arange(10))
    u = (cu.ravel()[10:] * 10 + 5.0).tolist() + [5.0] * 10
    v = (cv.ravel()[10:] * 10 + 5.0).tolist() + [5.0] * 10
    cells = grid.cells(np.array(u), np.array(v))
    grid.update(cells)
    shared = SharingGrid.apply(np.ones(100, np.float32), grid.factor(cells))
    assert np.allclose(shared[:90], 1.0)                       # even share: untouched
    assert np.all(shared[90:] < 0.2)                           # ten times the share: heavily lowered
    # Negative fitness (possible with plug-in terms) is lowered as well, not raised.
    assert SharingGrid.apply(np.full(100, -1.0, np.float32), grid.factor(cells))[95] < -1.0
    # Strength 0 disables sharing.
    grid0 = SharingGrid(100, 100, 10, 0.0)
    grid0.update(cells)
    assert np.all(grid0.factor(cells) == 1.0)
    # Flies outside the image belong to no cell and are not counted.
    assert grid.cells(np.array([-3.0, 150.0, np.nan]), np.array([5.0, 5.0, 5.0])).tolist() == [-1, -1, -1]


def _frame(calib, left, right, **kw):
    args = dict(neighbourhood=7, noise_sigma=None, ssd_floor_scale=2.0, gradient_saturation=6.0,
                window_sigma=None)
    args.update(kw)
    return prepare_frame(calib, left, right, **args)


def test_images_prepared_ahead_are_used_only_for_their_arrays_and_settings():
    """prepare_frame takes precomputed images (common.lockstep prepares them in a worker thread) only
    when they come from these very arrays with these settings; anything else is prepared afresh."""
    calib, left, right, _ = textured_plane_pair(disparity=12)
    settings = dict(neighbourhood=7, mean_removal_px=5, gradient_window=None, min_half_window=True,
                    epipolar_gradient=True)
    fresh = _frame(calib, left, right, **settings)
    ahead = prepare_images(calib, left, right, **settings)
    used = _frame(calib, left, right, images=ahead, **settings)
    assert used.left is ahead.left                       # taken as computed, not recomputed
    for other in (dict(settings, mean_removal_px=None), dict(settings, gradient_window=9),
                  dict(settings, epipolar_gradient=False), dict(settings, min_half_window=False)):
        stale = prepare_images(calib, left, right, **other)
        got = _frame(calib, left, right, images=stale, **settings)
        assert got.left is not stale.left
        assert np.array_equal(got.left, fresh.left) and np.array_equal(got.gradient_norm, fresh.gradient_norm)
    same_pixels = prepare_images(calib, left.copy(), right.copy(), **settings)    # equal, but other arrays
    assert _frame(calib, left, right, images=same_pixels, **settings).left is not same_pixels.left


def test_fitness_peaks_at_the_true_disparity():
    calib, left, right, depth = textured_plane_pair(disparity=12)
    frame = _frame(calib, left, right)
    u = np.full(50, 80.0)
    v = np.linspace(20, 100, 50)
    for subpixel in (True, False):
        fits = [image_fitness(frame, calib, calib.backproject(u, v, np.full(50, d)), subpixel).mean()
                for d in (9.0, 11.0, 11.5, 12.0, 12.5, 13.0, 15.0)]
        assert int(np.argmax(fits)) == 3, fits
    # Full bilinear sampling agrees.
    f_bil = image_fitness(frame, calib, calib.backproject(u, v, np.full(50, 12.0)), True, vertical=True)
    f_off = image_fitness(frame, calib, calib.backproject(u, v, np.full(50, 13.0)), True, vertical=True)
    assert np.all(f_bil > f_off)


def test_subpixel_fitness_is_smooth_in_disparity():
    calib, left, right, _ = textured_plane_pair(disparity=12)
    frame = _frame(calib, left, right)
    u, v = np.full(21, 80.0), np.full(21, 60.0)
    ds = np.linspace(11, 13, 21)
    f_sub = image_fitness(frame, calib, calib.backproject(u, v, ds), subpixel=True)
    f_int = image_fitness(frame, calib, calib.backproject(u, v, ds), subpixel=False)
    assert len(np.unique(np.round(f_int, 6))) <= 3      # nearest pixel: a staircase
    assert len(np.unique(np.round(f_sub, 6))) >= 15     # sub-pixel: varies continuously
    assert abs(ds[np.argmax(f_sub)] - 12.0) <= 0.1


def test_uniform_regions_score_low_even_when_they_match():
    calib, left, right, _ = textured_plane_pair(disparity=12, flat_right_half=True)
    frame = _frame(calib, left, right)
    v = np.full(30, 60.0)
    textured = image_fitness(frame, calib, calib.backproject(np.linspace(20, 60, 30), v, np.full(30, 12.0)))
    flat = image_fitness(frame, calib, calib.backproject(np.linspace(100, 140, 30), v, np.full(30, 12.0)))
    flat_wrong = image_fitness(frame, calib, calib.backproject(np.linspace(100, 140, 30), v, np.full(30, 20.0)))
    assert np.median(flat) < 0.1 * np.median(textured)
    # In a flat region any depth matches, so nothing there should look like a surface.
    assert flat_wrong.max() < 0.1 * np.median(textured)


def test_flies_outside_either_image_get_the_lowest_fitness():
    calib, left, right, depth = textured_plane_pair(disparity=12)
    frame = _frame(calib, left, right)
    inside = calib.backproject([80.0], [60.0], [12.0])
    off_left = calib.backproject([-5.0], [60.0], [12.0])       # outside the left image
    off_right = calib.backproject([8.0], [60.0], [12.0])       # u_right = −4: outside the right image
    off_bottom = calib.backproject([80.0], [118.0], [12.0])    # window crosses the bottom edge
    behind = np.array([[0.0, 0.0, -1.0]])
    pts = np.concatenate([inside, off_left, off_right, off_bottom, behind])
    for subpixel in (True, False):
        f = image_fitness(frame, calib, pts, subpixel)
        assert f[0] > 0
        assert np.all(f[1:] == OUTSIDE_FITNESS) and OUTSIDE_FITNESS == -np.inf


def test_noise_floor_stops_flat_patches_from_winning():
    """Identical saturated patches (SSD = 0) must not beat a well-matched textured patch."""
    calib, left, right, _ = textured_plane_pair(disparity=12)
    left[:, 100:] = 255
    right[:, 100 - 12:] = 255
    frame = _frame(calib, left, right)
    sat = image_fitness(frame, calib, calib.backproject([130.0], [60.0], [12.0]))
    tex = image_fitness(frame, calib, calib.backproject([50.0], [60.0], [12.0]))
    assert sat[0] < tex[0]


def test_bad_images_are_refused():
    calib, left, right, _ = textured_plane_pair()
    args = dict(neighbourhood=7, noise_sigma=None, ssd_floor_scale=2.0, gradient_saturation=6.0,
                window_sigma=None)
    with pytest.raises(ImageError, match="calibration"):
        prepare_frame(calib, left[:-1], right[:-1], **args)
    with pytest.raises(ImageError, match="mono or"):
        prepare_frame(calib, left[..., :2], right[..., :2], **args)
    with pytest.raises(ImageError, match="differ"):
        prepare_frame(calib, left, right[..., 0], **args)


def test_horizontal_stripes_carry_no_disparity_and_score_low():
    """Texture that varies only across the epipolar lines matches at every disparity (aperture problem):
    G, built from the x gradient, must keep such flies well below flies on real texture."""
    calib, left, right, _ = textured_plane_pair(disparity=12)
    stripes = np.repeat((np.arange(calib.height) % 8 < 4)[:, None] * 200 + 20, calib.width, axis=1)
    left[:, 100:] = stripes[:, 100:, None]
    right[:, 100 - 12:] = stripes[:, 100 - 12:, None]
    frame = _frame(calib, left, right)
    v = np.full(20, 60.0)
    tex = image_fitness(frame, calib, calib.backproject(np.linspace(20, 60, 20), v, np.full(20, 12.0)))
    stripe_any_d = image_fitness(frame, calib, calib.backproject(np.linspace(115, 140, 20), v, np.full(20, 30.0)))
    assert stripe_any_d.max() < 0.1 * np.median(tex)
