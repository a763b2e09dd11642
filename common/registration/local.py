"""Local correlation of two populations: a short-range alternative to δ for deep, real scenes.

    C(A, B) = Σᵢ wᵃᵢ Σⱼ wᵇⱼ k(|aᵢ − bⱼ|) / Σᵢ wᵃᵢ,   k = (K − K_far) with cut-off r  (see _kernels)

k is the paper's kernel 1/(ε + d) with its long-range part removed: a bump, 1/ε − K_far(0) at zero,
vanishing with zero slope at r.  Registration *maximises* C (minimises −C): kernel correlation, an
M-estimator whose flies beyond r of the other population carry no pull at all.

Why (measured with bench/registration_variants.py and a noise-free street): with two independent
populations the 1/(ε + d) tail acts like gravity between the two clouds, and the minimum of δ moved
by 0.2–0.8 m along the street depending on which flies were kept; the local kernel does not see
where the bulk of the other cloud is, only whether each fly has neighbours.
"""
from __future__ import annotations

import numpy as np

from . import _kernels
from .cells import CellList
from .pseudo_distance import PopulationError, as_population, as_weights, check_eps


class LocalCorrelationField:
    """B's short-range field Σⱼ wᵇⱼ k(|x − bⱼ|), summed exactly over a cell list (no grid)."""

    def __init__(self, B, eps, radius, weights_b=None):
        self.B = as_population(B, "B")
        self.eps = check_eps(eps)
        self.rc = float(radius)
        if not np.isfinite(self.rc) or self.rc <= 0:
            raise PopulationError(f"radius must be a positive distance, got {radius}")
        self.wb = as_weights(weights_b, len(self.B), "weights_b")
        self.weight_sum = float(self.wb.sum())
        span = self.B.max(0) - self.B.min(0)
        if np.prod(span / self.rc + 1) > 5e7:
            raise PopulationError(f"radius {radius} m is too small for a population spanning "
                                  f"{np.round(span, 1).tolist()} m")
        self.cells = CellList(self.B, self.wb, self.rc)
        self.last_outside = 0

    def _args(self):
        return (*self.cells.args(), self.eps, self.rc)

    def field(self, Q, with_grad: bool = False, near: bool = True):
        S, G = self._field(as_population(Q, "Q", allow_empty=True), with_grad, near)
        return (S, G) if with_grad else S

    def _field(self, Q, with_grad: bool, near: bool = True):
        """(S, G) at the rows of a validated (n, 3) float64 C array Q (no checks; see field.py)."""
        return _kernels.near_field(Q, *self._args(), with_grad)

    def correlation(self, A, weights_a=None) -> float:
        """C(A, B) of the module docstring."""
        A = as_population(A, "A")
        wa = as_weights(weights_a, len(A), "weights_a")
        return float((wa * self.field(A)).sum() / wa.sum())

    def batch_sums(self, A, wa, Rs, ts, near: bool = True) -> np.ndarray:
        """Σᵢ wa_i · field(Rₖᵀ(aᵢ − tₖ)) for each candidate k."""
        return _kernels.batch_near(A, wa, np.ascontiguousarray(Rs, dtype=float),
                                   np.ascontiguousarray(ts, dtype=float), *self._args())
