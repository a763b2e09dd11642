"""Box-constrained BFGS for the registration's few (3 or 6) parameters, scaled to the window box."""
from __future__ import annotations

import numpy as np


def _bfgs_box(fun, x0, lo, hi, maxiter, xtol=1e-5, ftol=1e-10, stop=None, H0=None, out=None, max_step=None):
    """Minimise fun (returns value, gradient) inside the box [lo, hi]: projected BFGS, Armijo backtracking.

    A few parameters only; written here because scipy's L-BFGS-B's per-call overhead in its Fortran/BLAS
    layer exceeds the cost of the registration objective itself.  stop(x): optional test
    after each accepted step; True ends the search there (the registration's extra seeds stop once
    they reach a basin already polished).  H0: initial inverse-Hessian estimate (identity when None);
    out: a list whose last item is set to the final estimate.  max_step: cap on each component of a
    search direction (before the line search).
    """
    x = np.clip(np.asarray(x0, dtype=float), lo, hi)
    f, g = fun(x)
    Hinv = np.eye(len(x)) if H0 is None else H0.copy()
    if out is not None:
        out.append(Hinv)
    for _ in range(maxiter):
        d = -Hinv @ g
        if g @ d >= 0:
            Hinv = np.eye(len(x))
            d = -g
        alpha = 1.0
        if max_step is not None:
            big = np.max(np.abs(d) / max_step)
            if big > 1.0:
                d = d / big
        for _ in range(30):
            xn = np.clip(x + alpha * d, lo, hi)
            s = xn - x
            if not np.any(s):
                break
            fn, gn = fun(xn)
            if fn <= f + 1e-4 * (g @ s):
                break
            alpha *= 0.5
        else:
            return x, f
        if not np.any(s):
            return x, f
        y = gn - g
        sy = s @ y
        done = np.max(np.abs(s)) < xtol or abs(f - fn) <= ftol * max(abs(f), 1e-300)
        x, f, g = xn, fn, gn
        if done or (stop is not None and stop(x)):
            break
        if sy > 1e-300:
            rho = 1.0 / sy
            I = np.eye(len(x))
            Hinv = (I - rho * np.outer(s, y)) @ Hinv @ (I - rho * np.outer(y, s)) + rho * np.outer(s, s)
            if out is not None:
                out[-1] = Hinv
    return x, f
