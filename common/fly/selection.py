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
