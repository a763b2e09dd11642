"""The gradient normaliser G's energy: the least of the four half-window means, replicated borders."""
import numpy as np
import pytest

from common.fly.fitness import gradient_energy


def brute_force(sq: np.ndarray, h: int) -> np.ndarray:
    """Each pixel's four (2h+1)×(h+1) half-windows summed one by one on a replicated-border copy."""
    p = np.pad(sq.astype(np.float64), h, mode="edge")
    H, W = sq.shape
    out = np.empty((H, W))
    for y in range(H):
        for x in range(W):
            cy, cx = y + h, x + h
            win = p[cy - h:cy + h + 1, cx - h:cx + h + 1]
            out[y, x] = min(win[:, :h + 1].mean(), win[:, h:].mean(), win[:h + 1].mean(), win[h:].mean())
    return out


@pytest.mark.parametrize("shape", [(23, 31), (5, 40), (40, 4), (1, 1)])
@pytest.mark.parametrize("n", [3, 7, 9])
def test_min_half_window_matches_the_definition(shape, n):
    sq = (np.random.default_rng(n).random(shape, dtype=np.float32) * 60) ** 2
    got = gradient_energy(sq, n, min_half_window=True)
    assert got.shape == shape and got.dtype == np.float32
    np.testing.assert_allclose(got, brute_force(sq, n // 2), rtol=1e-4)


def test_an_edge_beside_a_flat_side_gets_the_flat_sides_energy():
    """The property G is built for: beside a one-sided texture, the flat half-window wins."""
    sq = np.zeros((21, 21), np.float32)
    sq[:, 11:] = 100.0
    g = gradient_energy(sq, 7, min_half_window=True)
    assert g[10, 10] == 0.0 and g[10, 14] == pytest.approx(100.0)
    assert gradient_energy(sq, 7, min_half_window=False)[10, 10] > 0
