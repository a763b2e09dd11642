"""Curvature of the registration objective at its minimum: Hessian, covariance, flatness.

The Hessian H comes from central differences of the analytic gradient, or, where that is not positive
definite, from second differences of the values (_value_hessian: a cusp minimum passes, a saddle does
not).  The covariance is a cluster-robust sandwich (_clustered_meat): A's flies are grouped into cells
as wide as the kernel's core, 2 (ε + the flies' median spacing), because flies that close read the
same few B flies and so share B's sampling error; the per-cell sums of the centred per-fly gradients
are the independent terms.  Flatness is how well the minimum is pinned inside the search window: the
window's half-width over the standard deviation along the worst direction, both in window units
(< 1: one σ reaches past the window, the data do not place the minimum).  stiffness_ratio
keeps the old curvature ratio (H's smallest over its stiffest eigenvalue, rotations as metres of arc)
as a diagnostic.  Design: docs/design/registration.md.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .objective import PLANES


@dataclass
class _Curvature:
    H: np.ndarray          # Hessian of the objective in the pose params
    Hs: np.ndarray         # the same with rotations as metres of arc at the populations' radius
    eig: np.ndarray        # eigenvalues of Hs
    stiffness_ratio: float  # eig_min / the stiffest curvature (diagnostic, module docstring)
    Jf: np.ndarray         # per-fly gradients, centred
    evaluations: int
    covariance: np.ndarray | None = None   # clustered sandwich (params²); None when H is not invertible
    flatness: float = float("nan")         # 1 / σ along the worst direction, window units


def _curvature(mode, k, full, pose, p_best, rc, radius, half) -> _Curvature:
    """The minimum's curvature: the Hessian (gradient differences, or values at a cusp), its scaled
    eigenvalues, the stiffness ratio, the covariance and the flatness within the window of half-widths
    `half` (zero: a pinned parameter, left out of the flatness)."""
    evals = 0
    L = max(radius, 1e-9)
    fd = np.array([min(0.25 * rc, 0.02) if (mode == "6dof" and i < 3) or (mode in PLANES and i < 2)
                   else min(0.25 * rc, 0.02) / L for i in range(k)])
    H = np.zeros((k, k))
    for i in range(k):
        e = np.zeros(k)
        e[i] = fd[i]
        gp = full.value_and_grad(p_best + e)[1]
        gm = full.value_and_grad(p_best - e)[1]
        H[i] = (gp - gm) / (2 * fd[i])
    H = 0.5 * (H + H.T)
    evals += 2 * k
    if np.linalg.eigvalsh(H)[0] <= 0:
        # Not positive definite from gradient differences: a saddle, or a cusp (see _value_hessian).
        # Ask the values whether J rises all around p; a true cusp minimum passes, a saddle does not.
        H = _value_hessian(full.value, p_best, fd)
        evals += k * k + 1
    _, Jf = full.per_fly(p_best)
    Jf = Jf - Jf.mean(0)
    evals += 1
    rot = np.array([i >= (2 if mode in PLANES else 3) for i in range(k)])
    units = np.where(rot, L, 1.0)               # rotations expressed as metres of arc at radius L
    Hs = H / np.outer(units, units)
    eig = np.linalg.eigvalsh(Hs)
    # Stiffness reference: the populations' own stiffest direction under a free 3-D translation (so a
    # planar search over a ground plane, flat in all three of its parameters, is still seen as flat).
    if mode in PLANES:
        # The in-plane block is the translation block of H seen through the rotation (a shift e of
        # f⁻¹(A) is the pose translation t − R e): only the out-of-plane row needs evaluations.
        normal = 2 if mode == "body" else 1
        inplane = [i for i in range(3) if i != normal]
        Rb = pose(p_best)[0]
        Htt = np.zeros((3, 3))
        Htt[np.ix_(inplane, inplane)] = H[:2, :2]
        H3 = full.translation_hessian(p_best, fd[0], axes=(normal,))
        H3[np.ix_(inplane, inplane)] = (Rb.T @ Htt @ Rb)[np.ix_(inplane, inplane)]
        evals += 2
    else:
        H3 = full.translation_hessian(p_best, fd[0])
        evals += 6
    stiff = max(eig[-1], float(np.linalg.eigvalsh(H3)[-1]))
    ratio = float(eig[0] / stiff) if stiff > 0 else float("nan")
    curv = _Curvature(H, Hs, eig, ratio, Jf, evals)
    if eig[0] > 0:
        curv.covariance = _sandwich(H, _clustered_meat(full.A, Jf, full.field.eps, full.field.B))
        curv.flatness = _flatness(curv.covariance, half)
    return curv


def _sandwich(H, meat):
    """H⁻¹ (2 · meat) H⁻¹, symmetrised: meat sums over A's flies; B's flies, measured the same way, add
    as much again (docs/design/registration.md)."""
    Hi = np.linalg.inv(H)
    cov = 2.0 * Hi @ meat @ Hi
    return 0.5 * (cov + cov.T)


def _clustered_meat(A, Jf, eps, B):
    """Σ_c G_c G_cᵀ, G_c the sum of the per-fly gradients Jf (centred) of the flies of A in cell c.

    Cells are 2 (ε + s) wide, s the median distance from a fly of B to its nearest neighbour in B: the
    reach of the kernel 1/(ε + d)'s core plus B's sampling, over which two flies of A read the same B
    flies, so their terms move together when B's sampling moves the field.  (So cloning A's flies adds
    no information: the clones share a cell.)  Averaged over two grids offset by half a cell, so the
    result does not hinge on where a cell boundary falls.  Cells of one fly give the plain sandwich.
    """
    if len(A) < 2 or len(B) < 2:
        return Jf.T @ Jf
    spacing = float(np.median(cKDTree(B).query(B, k=2)[0][:, 1]))
    size = 2.0 * (eps + spacing)
    meat = np.zeros((Jf.shape[1], Jf.shape[1]))
    for offset in (0.0, 0.5):
        cells = np.floor(A / size + offset).astype(np.int64)
        _, cell_of = np.unique(cells, axis=0, return_inverse=True)
        G = np.zeros((int(cell_of.max()) + 1, Jf.shape[1]))
        np.add.at(G, cell_of.ravel(), Jf)
        meat += 0.5 * (G.T @ G)
    return meat


def _flatness(cov, half):
    """1 / σ_max, σ_max the largest standard deviation of the free parameters in units of the window's
    half-widths: below 1 the minimum is not pinned down inside the window along some direction."""
    free = np.asarray(half) > 0
    if not free.any():
        return float("inf")
    h = np.asarray(half, dtype=float)[free]
    cu = cov[np.ix_(free, free)] / np.outer(h, h)
    worst = float(np.linalg.eigvalsh(cu)[-1])
    return float(1.0 / np.sqrt(worst)) if worst > 0 else float("inf")


def _value_hessian(fun, p, fd):
    """Hessian of the scalar `fun` at p from second differences of its values, step fd[i] per parameter:
    H_ii from the axis stencils, H_ij by polarisation from the stencil along e_i + e_j
    (c(e_i + e_j) = H_ii + H_jj + 2 H_ij for the second differences c); 1 + k + k² evaluations.

    The fallback when the Hessian from gradient differences is not positive definite: at small ε δ
    can have a cusp at the minimum, where the gradient jumps and its differences give indefinite cross
    terms.  Second differences of values ask whether J rises all around p at the step's scale, and equal
    the gradient Hessian where J is smooth.  Only a fallback: they weight the curvature towards p
    itself, so on a rough but flat valley a micro-basin would look stiffer than it is.
    """
    k = len(p)
    E = np.diag(np.asarray(fd, dtype=float))
    f0 = fun(p)
    c = np.array([fun(p + E[i]) + fun(p - E[i]) - 2.0 * f0 for i in range(k)])
    H = np.diag(c / np.diag(E) ** 2)
    for i in range(k):
        for j in range(i + 1, k):
            d = E[i] + E[j]
            cij = fun(p + d) + fun(p - d) - 2.0 * f0
            H[i, j] = H[j, i] = (cij - c[i] - c[j]) / (2.0 * E[i, i] * E[j, j])
    return H
