"""Which flies of a population to trust: the one selection rule the planner and the localiser share."""
from __future__ import annotations

import numpy as np


def fittest(fitness: np.ndarray, fraction: float, min_fitness: float = -np.inf) -> np.ndarray:
    """Indices of the ``max(1, int(N · fraction))`` fittest flies, fittest first (``np.argsort(-fitness)``
    order), less those not above ``min_fitness`` or not finite (flies outside the images score −inf).

    Unconverged flies — a young population, fresh immigrants — sit at the bottom and must not become
    obstacles or map points; ``min_fitness`` also drops a whole population that has not converged.
    """
    f = np.asarray(fitness)
    if f.ndim != 1 or f.size == 0 or not 0.0 < fraction <= 1.0:
        return np.zeros(0, dtype=np.int64)
    top = np.argsort(-f)[: max(1, int(len(f) * fraction))]
    keep = np.isfinite(f[top]) & (f[top] > min_fitness)
    return top if keep.all() else top[keep]


def spread_fittest(u: np.ndarray, v: np.ndarray, fitness: np.ndarray, count: int, width: int, height: int,
                   grid: tuple[int, int] = (8, 6)) -> np.ndarray:
    """Indices of up to ``count`` flies spread over the image: the fittest of every ``grid`` cell
    (columns × rows) first, then the second fittest of every cell, and so on (fittest first within a
    round).  Flies projecting outside the image or with non-finite fitness are never chosen.

    Why: the fittest flies of a population crowd on its best-textured surface, often one near wall at
    an image edge; a view held by them alone loses sight of everything when the camera turns away
    from that edge, and constrains the motion worse than flies spread over the whole view."""
    u, v, f = np.asarray(u, float), np.asarray(v, float), np.asarray(fitness, float)
    ok = np.flatnonzero(np.isfinite(u) & np.isfinite(v) & np.isfinite(f)
                        & (u >= 0) & (u < width) & (v >= 0) & (v < height))
    if count <= 0 or len(ok) == 0:
        return np.zeros(0, dtype=np.int64)
    order = ok[np.argsort(-f[ok], kind="stable")]
    gx, gy = grid
    cell = (np.minimum((v[order] * gy / height).astype(np.int64), gy - 1) * gx
            + np.minimum((u[order] * gx / width).astype(np.int64), gx - 1))
    by_cell = np.argsort(cell, kind="stable")              # fitness order kept within each cell
    sorted_cells = cell[by_cell]
    starts = np.flatnonzero(np.r_[True, sorted_cells[1:] != sorted_cells[:-1]])
    rank = np.empty(len(order), dtype=np.int64)
    rank[by_cell] = np.arange(len(order)) - np.repeat(starts, np.diff(np.r_[starts, len(order)]))
    pick = np.lexsort((np.arange(len(order)), rank))[:count]   # by round, then by fitness
    return order[pick]
