"""The evolver's in-kernel random generator: right distributions, reproducible from its seed."""
import numba
import numpy as np

from common.fly.operators import below, new_state, normal, uniform


@numba.njit
def _draw(seed, n, k):
    s = new_state(seed)
    u = np.empty(n)
    b = np.empty(n, np.int64)
    z = np.empty(n)
    spare = np.nan
    for i in range(n):
        u[i] = uniform(s)
        b[i] = below(s, k)
    for i in range(n):
        z[i], spare = normal(s, spare)
    return u, b, z


def test_draws_have_the_distributions_the_operators_assume():
    u, b, z = _draw(12345, 200_000, 10)
    assert u.min() >= 0.0 and u.max() < 1.0 and abs(u.mean() - 0.5) < 0.005
    counts = np.bincount(b, minlength=10)
    assert b.min() == 0 and b.max() == 9
    assert ((counts - 20_000) ** 2 / 20_000).sum() < 40          # chi² with 9 dof: p ≈ 1e-5 at 40
    assert abs(z.mean()) < 0.01 and abs(z.std() - 1.0) < 0.01
    assert abs(np.mean(np.abs(z) > 1.96) - 0.05) < 0.003          # normal tails, not a uniform's
    assert abs(np.corrcoef(z[:-1], z[1:])[0, 1]) < 0.01           # the two halves of a pair are independent


def test_a_seed_gives_one_stream_and_another_seed_another():
    a, b = _draw(7, 1000, 5), _draw(7, 1000, 5)
    c = _draw(8, 1000, 5)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[0], c[0])
