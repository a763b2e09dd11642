"""The paper's pseudo-distance between two fly populations, computed exactly.

Louchet et al. ("Flies open a door to SLAM") compare a population A = {aᵢ}, i ≤ n with a population
B = {bⱼ}, j ≤ p by

    δ(A, B) = (p / n) · Σᵢ 1 / Σⱼ 1 / (ε + d(aᵢ, bⱼ))

i.e. the mean over A of p / S_B(aᵢ), where S_B(x) = Σⱼ 1/(ε + |x − bⱼ|) is B's *field*.  p / S_B(x)
is a harmonic mean of the distances from x to B (plus ε), so δ has units of metres: it is small when
every fly of A sits where B is dense.  It is not symmetric.

Weighted form (our extension, reduces to the paper's with unit weights):

    δ_w(A, B) = (P / N) · Σᵢ wᵃᵢ / Σⱼ wᵇⱼ / (ε + d(aᵢ, bⱼ)),   N = Σ wᵃ,  P = Σ wᵇ

This module is the reference: float64, chunked so memory stays bounded.  `field.py` holds the fast
approximation used by registration.
"""
from __future__ import annotations

import numpy as np

from . import _kernels


class PopulationError(ValueError):
    """A fly population, a weight vector or a parameter that cannot be used as given."""


def as_population(points, name: str, allow_empty: bool = False) -> np.ndarray:
    """(n, 3) float64 C-contiguous copy-or-view of `points`; raise PopulationError when malformed."""
    try:
        P = np.ascontiguousarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PopulationError(f"{name} is not a numeric array: {exc}") from None
    if P.ndim != 2 or P.shape[1] != 3:
        raise PopulationError(f"{name} must have shape (n, 3), got {P.shape}")
    if not allow_empty and P.shape[0] == 0:
        raise PopulationError(f"{name} is empty")
    if not np.all(np.isfinite(P)):
        raise PopulationError(f"{name} contains non-finite coordinates")
    return P


def as_weights(weights, n: int, name: str) -> np.ndarray:
    """(n,) float64 non-negative weights with a positive sum; ones when `weights` is None."""
    if weights is None:
        return np.ones(n)
    w = np.ascontiguousarray(weights, dtype=np.float64)
    if w.shape != (n,):
        raise PopulationError(f"{name} must have shape ({n},), got {w.shape}")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise PopulationError(f"{name} must be finite and non-negative")
    if n and w.sum() <= 0:
        raise PopulationError(f"{name} sum to zero")
    return w


def check_eps(eps) -> float:
    eps = float(eps)
    if not np.isfinite(eps) or eps <= 0:
        raise PopulationError(f"eps must be a positive finite distance in metres, got {eps}")
    return eps


def field_exact(Q, B, eps, weights_b=None, with_grad: bool = False):
    """B's field S_B at every row of Q (and its gradient (n, 3) when `with_grad`), exact, float64."""
    Q = as_population(Q, "Q")
    B = as_population(B, "B")
    wb = as_weights(weights_b, len(B), "weights_b")
    eps = check_eps(eps)
    if with_grad:
        return _kernels.exact_field(Q, B, wb, eps)
    return _kernels.exact_field_value(Q, B, wb, eps)


def pseudo_distance_exact(A, B, eps, weights_a=None, weights_b=None, chunk_elems: int = 2_000_000) -> float:
    """δ(A, B) of the paper, exactly, in float64 numpy, chunked over A (≤ chunk_elems pairs at once).

    With weights, the weighted form δ_w described in the module docstring.
    """
    A = as_population(A, "A")
    B = as_population(B, "B")
    eps = check_eps(eps)
    wa = as_weights(weights_a, len(A), "weights_a")
    wb = as_weights(weights_b, len(B), "weights_b")
    rows = max(1, int(chunk_elems) // len(B))
    total = 0.0
    for i0 in range(0, len(A), rows):
        a = A[i0:i0 + rows]
        d = np.sqrt(((a[:, None, :] - B[None, :, :]) ** 2).sum(-1))
        S = (wb[None, :] / (eps + d)).sum(1)
        total += float((wa[i0:i0 + rows] / S).sum())
    return wb.sum() / wa.sum() * total
