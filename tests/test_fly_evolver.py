"""FlyEvolver behaviour on small synthetic scenes: convergence in both modes and selections, plug-in
fitness terms, proprioceptive moves, immigration after a scene change, input validation."""
import numpy as np
import pytest

from common.fly import (EvolverConfig, EvolverConfigError, FitnessTermError, FlyEvolver, NoImagesError,
                        inlier_fraction)
from common.fly.operators import project_uvd
from common.geometry import make_transform, rot_y, transform_points
from common.fly.synthetic import textured_plane_pair

SMALL = dict(population=600, depth_min=0.5, depth_max=np.inf)


def _plane(disparity=12.0):
    calib, left, right, depth = textured_plane_pair(disparity=disparity)
    gt = np.full((calib.height, calib.width), disparity, np.float32)
    return calib, left, right, gt


@pytest.mark.parametrize("mode,selection", [("steady", "tournament"), ("steady", "elitist"),
                                            ("generational", "tournament"), ("generational", "elitist")])
def test_population_converges_on_the_plane(mode, selection):
    calib, left, right, gt = _plane()
    ev = FlyEvolver(calib, EvolverConfig(mode=mode, selection=selection, **SMALL), seed=3)
    ev.set_images(left, right)
    before = inlier_fraction(ev.positions, ev.fitness, calib, gt)
    ev.step(40)
    after = inlier_fraction(ev.positions, ev.fitness, calib, gt)
    assert before < 0.2
    assert after > 0.8, f"{mode}/{selection}: {after:.2f}"
    assert ev.generation == 40
    assert ev.positions.shape == (600, 3) and ev.fitness.shape == (600,)


def test_adaptive_mutation_steps_shrink_as_flies_converge():
    calib, left, right, _ = _plane()
    only_mutation = dict(crossover2_rate=0, crossover3_rate=0, exchange_rate=0, immigration_rate=0)
    ev = FlyEvolver(calib, EvolverConfig(**only_mutation, **SMALL), seed=1)
    ev.set_images(left, right)
    s0 = np.median(ev.mutation_sigma_disparity)
    ev.step(40)
    assert np.median(ev.mutation_sigma_disparity) < 0.5 * s0
    # Fixed steps stay put.
    ev = FlyEvolver(calib, EvolverConfig(adaptive_mutation=False, **only_mutation, **SMALL), seed=1)
    ev.set_images(left, right)
    ev.step(10)
    assert np.all(ev.mutation_sigma_disparity == s0)


def test_sharing_spreads_flies_over_the_image():
    calib, left, right, _ = _plane()
    occupied = {}
    for strength in (0.0, 2.0):
        ev = FlyEvolver(calib, EvolverConfig(sharing_strength=strength, **SMALL), seed=2)
        ev.set_images(left, right)
        ev.step(40)
        occupied[strength] = np.count_nonzero(ev.sharing.counts)
    assert occupied[2.0] > 1.2 * occupied[0.0], occupied


def test_immigration_catches_a_new_surface():
    calib, left, right, _ = _plane(12.0)
    ev = FlyEvolver(calib, EvolverConfig(immigration_rate=0.05, **SMALL), seed=4)
    ev.set_images(left, right)
    ev.step(30)
    _, left2, right2, _ = textured_plane_pair(disparity=20.0, seed=9)
    gt2 = np.full((calib.height, calib.width), 20.0, np.float32)
    ev.set_images(left2, right2)
    assert inlier_fraction(ev.positions, ev.fitness, calib, gt2) < 0.3
    ev.step(40)
    assert inlier_fraction(ev.positions, ev.fitness, calib, gt2) > 0.7


def test_move_flies_applies_the_robot_motion_to_every_fly():
    calib, left, right, _ = _plane()
    ev = FlyEvolver(calib, EvolverConfig(**SMALL), seed=5)
    ev.set_images(left, right)
    ev.step(5)
    before = ev.positions.copy()
    T = make_transform(rot_y(0.05), [0.02, -0.01, -0.3])
    ev.move_flies(T)
    np.testing.assert_allclose(ev.positions, transform_points(T, before.astype(np.float64)), atol=1e-5)
    # ... and re-scored on the current frame.
    np.testing.assert_allclose(ev.fitness, ev.evaluate(ev.positions), rtol=1e-6)
    with pytest.raises(ValueError, match="rigid"):
        ev.move_flies(np.diag([2.0, 1, 1, 1]))
    with pytest.raises(ValueError, match="4×4"):
        ev.move_flies(np.eye(3))


def test_fitness_terms_plug_in_additively_with_weights():
    calib, left, right, _ = _plane()
    ev = FlyEvolver(calib, EvolverConfig(**SMALL), seed=6)
    ev.set_images(left, right)
    base = ev.fitness.copy()
    near_2m = lambda p: np.exp(-((p[:, 2] - 2.0) ** 2)).astype(np.float32)  # noqa: E731
    ev.add_fitness_term("sonar", near_2m, weight=0.5)
    inside = np.isfinite(base)
    np.testing.assert_allclose(ev.fitness[inside], base[inside] + 0.5 * near_2m(ev.positions)[inside],
                               rtol=1e-5, atol=1e-6)
    ev.remove_fitness_term("sonar")
    np.testing.assert_allclose(ev.fitness, base, rtol=1e-6)
    with pytest.raises(FitnessTermError, match="bad"):
        ev.add_fitness_term("bad", lambda p: np.zeros(3), 1.0)
    with pytest.raises(FitnessTermError, match="callable"):
        ev.add_fitness_term("x", 3.0, 1.0)


def test_a_strong_fitness_term_steers_the_population():
    """With a term rewarding one depth band much more than the image, flies gather in that band."""
    calib, left, right, _ = _plane()
    ev = FlyEvolver(calib, EvolverConfig(**SMALL), seed=7)
    ev.set_images(left, right)
    ev.add_fitness_term("band", lambda p: (np.abs(p[:, 2] - 4.0) < 0.5).astype(np.float32), 10.0)
    ev.step(30)
    assert np.mean(np.abs(ev.positions[:, 2] - 4.0) < 0.5) > 0.7


def test_state_is_read_only_and_anytime():
    calib, left, right, _ = _plane()
    ev = FlyEvolver(calib, EvolverConfig(**SMALL), seed=8)
    with pytest.raises(NoImagesError):
        ev.step()
    assert np.all(ev.fitness == -np.inf)           # nothing seen yet
    ev.set_images(left[..., 0], right[..., 0])     # mono works too
    ev.step(2)
    with pytest.raises(ValueError):
        ev.positions[0, 0] = 1.0
    u, v, d = project_uvd(calib, ev.positions)
    assert np.all(np.isfinite(ev.positions)) and np.all(ev.positions[:, 2] > 0)
    with pytest.raises(ValueError, match="non-negative"):
        ev.step(-1)


@pytest.mark.parametrize("bad", [dict(population=2), dict(neighbourhood=6), dict(mode="batch"),
                                 dict(selection="roulette"), dict(depth_min=2.0, depth_max=1.0),
                                 dict(crossover2_rate=0.6, crossover3_rate=0.6),
                                 dict(mutation_sigma_px=-1.0), dict(mean_removal_px=4)])
def test_bad_configuration_is_refused(bad):
    with pytest.raises(EvolverConfigError):
        EvolverConfig(**bad)


def test_kernel_chooser_prefers_the_cheaper_kernel_and_keeps_checking():
    from common.fly.threads import KernelChooser

    ch = KernelChooser(explore_every=4)
    cost = {True: 2e-3, False: 1e-3}          # the parallel kernel is currently the slower one
    used = []
    for _ in range(40):
        p = ch.choose()
        used.append(p)
        ch.record(p, cost[p], 1)
    assert used[:2] == [True, False]          # each measured once first
    assert used[2:].count(False) > 25 and used[2:].count(True) >= 5   # mostly serial, still exploring
    cost = {True: 1e-4, False: 1e-3}          # load went away: parallel becomes cheaper
    for _ in range(40):
        p = ch.choose()
        used.append(p)
        ch.record(p, cost[p], 1)
    assert used[-10:].count(True) >= 7
    # Results agree whichever kernel runs.
    calib, left, right, _ = _plane()
    for mode in (True, False, "auto"):
        ev = FlyEvolver(calib, EvolverConfig(parallel=mode, **SMALL), seed=11)
        ev.set_images(left, right)
        np.testing.assert_allclose(ev.evaluate(ev.positions), ev.fitness, rtol=1e-6)
    with pytest.raises(EvolverConfigError, match="parallel"):
        EvolverConfig(parallel="yes")


def test_flies_follow_the_robot_motion_into_the_next_frame():
    """Converged on a plane at disparity 12, the robot drives towards it until it is at disparity 15:
    moving the flies by the odometry keeps them on the surface in the new frame, before any generation."""
    calib, left, right, gt12 = _plane(12.0)
    ev = FlyEvolver(calib, EvolverConfig(**SMALL), seed=12)
    ev.set_images(left, right)
    ev.step(40)
    assert inlier_fraction(ev.positions, ev.fitness, calib, gt12) > 0.8
    fb = calib.fx * calib.baseline
    forward = fb / 12.0 - fb / 15.0                     # metres driven along the optical axis
    T_new_old = make_transform(None, [0.0, 0.0, -forward])
    _, left15, right15, _ = textured_plane_pair(disparity=15.0, seed=3)
    gt15 = np.full_like(gt12, 15.0)
    stay = FlyEvolver(calib, EvolverConfig(**SMALL), seed=12)
    stay.set_images(left, right)
    stay.step(40)
    stay.set_images(left15, right15)                    # no proprioceptive fusion
    ev.move_flies(T_new_old)
    ev.set_images(left15, right15)
    assert inlier_fraction(stay.positions, stay.fitness, calib, gt15) < 0.2
    assert inlier_fraction(ev.positions, ev.fitness, calib, gt15) > 0.8


def test_a_seed_reproduces_a_run():
    calib, left, right, _ = _plane()
    runs = []
    for seed in (21, 21, 22):
        ev = FlyEvolver(calib, EvolverConfig(**SMALL), seed=seed)
        ev.set_images(left, right)
        ev.step(5)
        runs.append(ev.positions.copy())
    assert np.array_equal(runs[0], runs[1]) and not np.array_equal(runs[0], runs[2])
