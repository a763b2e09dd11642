"""Curvature of the registration objective at its minimum: Hessian, flatness, per-fly gradients.

The Hessian H comes from central differences of the analytic gradient, or, where that is not positive
definite, from second differences of the values (_value_hessian: a cusp minimum passes, a saddle does
not).  Flatness is the smallest eigenvalue of H, rotations scaled to metres of arc at the populations'
radius, over the stiffest curvature: the larger of H's largest eigenvalue and the curvature under a
free 3-D translation (so a ground plane under a planar search, flat in all three parameters, is flat).
The centred per-fly gradients feed the sandwich covariance.  Design: docs/design/registration.md.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .objective import PLANES


@dataclass
class _Curvature:
    H: np.ndarray          # Hessian of the objective in the pose params
    Hs: np.ndarray         # the same with rotations as metres of arc at the populations' radius
    eig: np.ndarray        # eigenvalues of Hs
    flatness: float        # eig_min / the stiffest curvature (module docstring)
    Jf: np.ndarray         # per-fly gradients, centred (for the sandwich covariance)
    evaluations: int


def _curvature(mode, k, full, pose, p_best, rc, radius) -> _Curvature:
    """The minimum's curvature: the Hessian (gradient differences, or values at a cusp), its scaled
    eigenvalues, the flatness against the stiffest curvature, and the per-fly gradients."""
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
    flatness = float(eig[0] / stiff) if stiff > 0 else float("nan")
    return _Curvature(H, Hs, eig, flatness, Jf, evals)


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
