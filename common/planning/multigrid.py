"""Multiplicative aggregation multigrid for the log-space harmonic field (numba): the cycle and the solver.
Level 0's operator and the aggregation hierarchy are built in multigrid_hierarchy.py; why the field is
solved this way is in docs/design/planner.md.

The unknown is ``phi = exp(s) * x`` on the ACTIVE cells (compact numbering): ``s`` a fixed log scale
(the previous solution on a warm start), ``x`` a relative factor near 1.  Laplace's 5-point equation
``4 phi_i = sum phi_n`` becomes the linear system ``x_i - sum_n w_in x_n = f_i`` with
``w_in = exp(s_n - s_i) / 4`` (ACTIVE neighbours) and ``f_i`` the same weights towards TARGET cells
(phi = 1 there): the similarity transform ``D^-1 A D`` (``D = diag(exp s)``) of the symmetric M-matrix
``A``.  Every level stores its operator in this form (diagonal ``dg``, couplings ``vals >= 0``,
right-hand side ``f >= 0``, log scale ``s``; level 0 as an ELL table with ``dg = 1``, coarser levels as
CSR), so nothing ever underflows however small phi gets.

The coarse problem solves for the *full* factor of each aggregate (iterative aggregation-disaggregation,
applied recursively): cells are aggregated in 2 x 2 blocks of the level's grid, split into 4-connected
pieces so no aggregate spans a wall; the interpolation is ``x * P0`` (the iterate's shape times a
per-aggregate factor ``q``) and the coarse operator its Galerkin projection, again a similarity-scaled
M-matrix with ``f >= 0``, so ``q > 0``.  One cycle (``_cycle``):
- level 0: one Gauss-Seidel sweep, the coarse factors interpolated bilinearly between aggregates and
  over-corrected (``q ** mg_over_correction``), one sweep back;
- levels 1..``mg_krylov_levels``: K-cycles (two repetitions combined by GCR steps that minimise the
  relative residual, Notay); deeper levels one over-corrected repetition;
- the coarsest level, the first that fits a narrow band (multigrid_hierarchy.BAND_MAX), solved exactly
  by banded elimination.

Invariants:
- over-correction and the Krylov steps are linear ideas: they are used only while every factor of a
  repetition is within ``exp(+-LINEAR_BAND)`` of 1; outside it (a cold start) corrections are plain
  multiplicative, the fine level's over-correction clipped to e^OVER_CLIP;
- the coarsest level's factors are clipped to ``exp(+-COARSE_FACTOR_LOG_MAX)``, so squared iterates
  stay in float64's range;
- a NaN reaches the cycle's convergence measure (never read as "no change"), so the planner discards a
  non-finite field instead of reporting it converged;
- ``LogFieldSolver.block`` takes cells out of level 0 (couplings zeroed, row fixed at x = 1, log scale
  DEAD_LOG_SCALE) and keeps the hierarchy: the live cells' field is exactly the rebuilt map's.

What keeps a cycle cheap: level 0 on a fixed-width ELL table; Gauss-Seidel multiplying by ``1 / dg``
computed ahead of the row; one-pass Galerkin builds with the per-aggregate normalisation divided out per
coarse row; exponentials and logarithms over whole arrays done by numpy; kernels that inline their
per-row work (a numba call with many array arguments costs ~100 ns).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .multigrid_hierarchy import Hierarchy, ell_emap, fine_system, interp_table, update_interp_table
from .multigrid_hierarchy import pad_rows4  # noqa: F401 (re-exported)


# Outside the linear band the fine level's factor is still over-corrected, by at most e^OVER_CLIP, so a
# warm update's first cycles carry the factor of a new narrowing at full strength; a larger clip ends
# converged fields further inside the tolerance's slack.
OVER_CLIP = 2.0
# Over-correction and Krylov steps are used only while every factor is within exp(+-LINEAR_BAND) of 1.
LINEAR_BAND = 0.5
# The coarsest level's factors are clipped to exp(+-COARSE_FACTOR_LOG_MAX).  Solved exactly, a long
# chain-like level (a narrow serpentine's, on a cold start) can ask for factors far below e^-700, and the
# levels above square their iterate (the Galerkin weights phi^2).  At e^+-100 two K-cycle repetitions and
# level 0's over-correction stay within e^+-250, whose squares float64 holds; the field reaches the true
# factor over a few more cycles.
COARSE_FACTOR_LOG_MAX = 100.0


@njit(cache=True)
def _gs(x, dg, ip, ind, vals, f, forward, four):
    """One Gauss-Seidel sweep.  ``acc * (1 / dg)``, not ``acc / dg``: the reciprocal does not wait for
    the previous row, so the division leaves the sweep's row-to-row dependency chain.
    ``four``: every row has exactly 4 entries (``pad_rows4``), a fixed-length row."""
    n = x.size
    for kk in range(n):
        i = kk if forward else n - 1 - kk
        inv = 1.0 / dg[i]
        acc = f[i]
        if four:
            e = 4 * i
            acc += (vals[e] * x[ind[e]] + vals[e + 1] * x[ind[e + 1]]) \
                + (vals[e + 2] * x[ind[e + 2]] + vals[e + 3] * x[ind[e + 3]])
        else:
            for e in range(ip[i], ip[i + 1]):
                acc += vals[e] * x[ind[e]]
        x[i] = acc * inv


@njit(cache=True)
def relative_residual(x, dg, ip, ind, vals, f, out):
    """``out = f - M x``; returns max |out_i| / (dg_i x_i): the largest relative change a Jacobi sweep
    would make."""
    worst = 0.0
    for i in range(x.size):
        acc = f[i] - dg[i] * x[i]
        for e in range(ip[i], ip[i + 1]):
            acc += vals[e] * x[ind[e]]
        out[i] = acc
        r = abs(acc) / (dg[i] * x[i])
        if not r <= worst:              # NaN propagates (see _fine_prolong_gs_back)
            worst = r
    return worst


@njit(cache=True)
def _coarse_operator(x, s, dg, ip, ind, vals, f, agg, emap, sc, dgc, vc, fc):
    """Galerkin operator for the interpolation ``x * P0``, written to (sc, dgc, vc, fc) = the coarse
    level's (s, dg, vals, f): row a is the sum over the aggregate's cells of their equations rescaled to
    phi and weighted by phi_i^2 / max phi^2 (the symmetric projection, normalised per aggregate)."""
    n = x.size
    t = np.empty(n)
    sc[:] = -np.inf
    for i in range(n):
        t[i] = s[i] + np.log(x[i])          # log phi
        if t[i] > sc[agg[i]]:
            sc[agg[i]] = t[i]
    dgc[:] = 0.0
    fc[:] = 0.0
    vc[:] = 0.0
    for i in range(n):
        a = agg[i]
        g = np.exp(2.0 * (t[i] - sc[a]))
        inv = 1.0 / x[i]
        dgc[a] += g * dg[i]
        fc[a] += g * f[i] * inv
        for e in range(ip[i], ip[i + 1]):
            c = g * vals[e] * x[ind[e]] * inv
            k = emap[e]
            if k < 0:
                dgc[a] -= c
            else:
                vc[k] += c


@njit(cache=True)
def _coarse_operator_scaled(x, E2, S, dg, ip, ind, vals, f, agg, emap, cptr, sc, dgc, vc, fc, r, w, four):
    """``_coarse_operator`` for a level whose log scale is fixed between calls, in one pass: with
    ``E2_i = exp(2 (s_i - S_a))`` and ``S_a`` = max s over aggregate a precomputed (``_level_scales_into``),
    ``g_i = (phi_i / max phi)^2 = E2_i x_i^2 / m_a`` where ``m_a = max(E2 x^2)`` is common to coarse row
    a, so it is divided out per row at the end: no exponential, logarithm or division per cell."""
    nc = sc.size
    m = np.zeros(nc)
    dgc[:] = 0.0
    fc[:] = 0.0
    vc[:] = 0.0
    for i in range(x.size):
        a = agg[i]
        xi = x[i]
        ex = E2[i] * xi
        u = ex * xi
        if u > m[a]:
            m[a] = u
        # the diagonal's contributions summed in a register first: read-modify-writes of dgc[a] by
        # every entry would form a chain through memory
        dsum = u * dg[i]
        e0, e1 = (4 * i, 4 * i + 4) if four else (ip[i], ip[i + 1])
        for e in range(e0, e1):
            c = ex * vals[e] * x[ind[e]]
            k = emap[e]
            if k < 0:
                dsum -= c
            else:
                vc[k] += c
        dgc[a] += dsum
        fc[a] += ex * f[i]
    _normalise_coarse_rows(nc, m, dgc, fc, vc, cptr, S, sc, r, w)


@njit(cache=True)
def _normalise_coarse_rows(nc, m, dgc, fc, vc, cptr, S, sc, r, w):
    """The end of a Galerkin coarse-operator build (both the CSR and the fixed-width level-0 variant): each
    coarse row divided by its aggregate's largest scale m, the coarse scales sc, and the coarse level's
    residual at its starting point q = 1 and its GCR weights, which a K-cycle level needs on entry (here
    for free instead of another pass there)."""
    for a in range(nc):
        inv = 1.0 / m[a]
        dgc[a] *= inv
        fc[a] *= inv
        acc = fc[a] - dgc[a]
        for k in range(cptr[a], cptr[a + 1]):
            vc[k] *= inv
            acc += vc[k]
        sc[a] = S[a] + 0.5 * np.log(m[a])
        r[a] = acc
        w[a] = 1.0 / (dgc[a] * dgc[a])


@njit(cache=True)
def level_scales(s, agg, nc):
    """(E, S): ``S_a`` = max s over aggregate a, ``E_i = exp(s_i - S_a)``."""
    S = np.full(nc, -np.inf)
    for i in range(s.size):
        if s[i] > S[agg[i]]:
            S[agg[i]] = s[i]
    E = np.empty(s.size)
    for i in range(s.size):
        E[i] = np.exp(s[i] - S[agg[i]])
    return E, S


@njit(cache=True)
def _level_scales_into(s, agg, E2, S):
    """``level_scales`` written into (E2, S), squared: ``E2_i = exp(2 (s_i - S_a))``."""
    S[:] = -np.inf
    for i in range(s.size):
        if s[i] > S[agg[i]]:
            S[agg[i]] = s[i]
    for i in range(s.size):
        E2[i] = np.exp(2.0 * (s[i] - S[agg[i]]))


@njit(cache=True)
def _fine_gs(x, nb, w4, f, forward):
    """One Gauss-Seidel sweep of level 0 (dg = 1) on its ELL table.  The neighbour updated just before
    (west going forward, east going backward) is added last, so only one addition waits for it."""
    n = x.size
    if forward:
        for i in range(n):
            x[i] = (f[i] + w4[i, 0] * x[nb[i, 0]] + w4[i, 2] * x[nb[i, 2]] + w4[i, 3] * x[nb[i, 3]]) \
                + w4[i, 1] * x[nb[i, 1]]
    else:
        for i in range(n - 1, -1, -1):
            x[i] = (f[i] + w4[i, 1] * x[nb[i, 1]] + w4[i, 2] * x[nb[i, 2]] + w4[i, 3] * x[nb[i, 3]]) \
                + w4[i, 0] * x[nb[i, 0]]


@njit(cache=True)
def _fine_gs_saving(x, prev, nb, w4, f):
    """``_fine_gs`` forward that first copies every x_i to prev (the cycle's starting point): one pass
    instead of a copy and a sweep."""
    for i in range(x.size):
        prev[i] = x[i]
        x[i] = (f[i] + w4[i, 0] * x[nb[i, 0]] + w4[i, 2] * x[nb[i, 2]] + w4[i, 3] * x[nb[i, 3]]) \
            + w4[i, 1] * x[nb[i, 1]]


@njit(cache=True)
def _interp_factors(q, agg, tab, Q):
    """The coarse factors q interpolated bilinearly to level 0's cells: 9/16 of the cell's own
    aggregate, 3/16 of each of the two beside / above it, 1/16 of the diagonal one (``interp_table``).
    Piecewise-constant factors leave a step at every block edge that one post-smoothing sweep cannot
    remove."""
    for i in range(agg.size):
        Q[i] = 0.5625 * q[agg[i]] + 0.1875 * (q[tab[i, 0]] + q[tab[i, 1]]) + 0.0625 * q[tab[i, 2]]


@njit(cache=True)
def _fine_prolong_gs_back(x, nb, w4, f, Q, prev, measure):
    """The end of a cycle in one pass: ``x *= Q`` (the interpolated coarse factors), a backward
    ``_fine_gs`` and ``_max_rel_change`` against prev.  Going backward, the east and south neighbours
    (higher compact index) are final already; the west and north ones are read times their factor.  The
    same arithmetic as the three passes, in the same order (identical results); returns the largest
    relative change (0 unless ``measure``: more sweeps follow)."""
    worst = 0.0
    for i in range(x.size - 1, -1, -1):
        jw = nb[i, 1]
        jn = nb[i, 3]
        v = (f[i] + w4[i, 1] * (x[jw] * Q[jw]) + w4[i, 2] * x[nb[i, 2]] + w4[i, 3] * (x[jn] * Q[jn])) \
            + w4[i, 0] * x[nb[i, 0]]
        x[i] = v
        if measure:
            r = abs(v - prev[i]) / v
            if not r <= worst:          # not max(): a NaN must propagate, not read as "no change"
                worst = r
    return worst


@njit(cache=True)
def _fine_gs_back_change(x, nb, w4, f, prev):
    """The last backward ``_fine_gs`` of a cycle with ``_max_rel_change`` against prev in the same pass."""
    worst = 0.0
    for i in range(x.size - 1, -1, -1):
        v = (f[i] + w4[i, 1] * x[nb[i, 1]] + w4[i, 2] * x[nb[i, 2]] + w4[i, 3] * x[nb[i, 3]]) \
            + w4[i, 0] * x[nb[i, 0]]
        x[i] = v
        r = abs(v - prev[i]) / v
        if not r <= worst:              # NaN propagates (see _fine_prolong_gs_back)
            worst = r
    return worst


@njit(cache=True)
def fine_residual(x, nb, w4, f):
    """``relative_residual`` of level 0: max |f + W x - x| / x."""
    worst = 0.0
    for i in range(x.size):
        acc = (f[i] + w4[i, 0] * x[nb[i, 0]] + w4[i, 1] * x[nb[i, 1]] + w4[i, 2] * x[nb[i, 2]]
               + w4[i, 3] * x[nb[i, 3]] - x[i])
        r = abs(acc) / x[i]
        if not r <= worst:              # NaN propagates (see _fine_prolong_gs_back)
            worst = r
    return worst


@njit(cache=True)
def _aggregate_max(s, agg, nc):
    S = np.full(nc, -np.inf)
    for i in range(s.size):
        if s[i] > S[agg[i]]:
            S[agg[i]] = s[i]
    return S


def fine_scales(s, agg, nc):
    """(E2, S) of level 0, fixed until the next rebase: ``S_a`` = max s over aggregate a and
    ``E2_i = exp(2 (s_i - S_a))`` (see ``_coarse_operator_scaled``); numpy's vectorised exp is several
    times faster than numba's scalar one."""
    S = _aggregate_max(s, agg, nc)
    return np.exp(2.0 * (s - S[agg])), S


@njit(cache=True)
def _fine_restrict(x, nb, w4, f, E2, S, agg, emap4, cptr, sc, dgc, vc, fc, r, w):
    """Galerkin operator of level 1 from level 0 (``_coarse_operator_scaled`` with dg = 1 on the ELL
    table), written to (sc, dgc, vc, fc)."""
    nc = sc.size
    m = np.zeros(nc)
    dgc[:] = 0.0
    fc[:] = 0.0
    vc[:] = 0.0
    for p in range(x.size):
        a = agg[p]
        xp = x[p]
        ex = E2[p] * xp
        u = ex * xp
        if u > m[a]:
            m[a] = u
        dsum = u                  # the diagonal's share summed in a register (see _coarse_operator_scaled)
        for d in range(4):
            c = ex * w4[p, d] * x[nb[p, d]]
            k = emap4[p, d]
            if k < 0:
                dsum -= c
            else:
                vc[k] += c
        dgc[a] += dsum
        fc[a] += ex * f[p]
    _normalise_coarse_rows(nc, m, dgc, fc, vc, cptr, S, sc, r, w)


@njit(cache=True)
def _over_correct(q, over):
    """The coarse factors' over-correction ``q ** over`` in place (clipped to e^OVER_CLIP outside the
    linear band); returns whether every factor was within ``exp(+-LINEAR_BAND)`` of 1."""
    hi = np.exp(LINEAR_BAND)
    lo = 1.0 / hi
    linear = True
    for a in range(q.size):
        if q[a] > hi or q[a] < lo:
            linear = False
            break
    if over != 1.0:
        if linear:
            if over == 2.0:
                for a in range(q.size):
                    q[a] *= q[a]
            else:
                for a in range(q.size):
                    q[a] = q[a] ** over
        elif OVER_CLIP > 0.0 and over == 2.0:
            # q * clip(q, e^-OVER_CLIP, e^OVER_CLIP): the same as below without an exponential and a
            # logarithm per factor
            chi = np.exp(OVER_CLIP)
            clo = 1.0 / chi
            for a in range(q.size):
                q[a] *= min(max(q[a], clo), chi)
        elif OVER_CLIP > 0.0:
            for a in range(q.size):
                q[a] *= np.exp(min(max((over - 1.0) * np.log(q[a]), -OVER_CLIP), OVER_CLIP))
    return linear


@njit(cache=True)
def _band_solve(dg, ip, ind, vals, f, rank, b, A, rhs, out):
    """The coarsest level solved by banded Gaussian elimination without pivoting (an M-matrix needs
    none) in the bandwidth-reducing order ``rank`` (node i is row rank[i]; |rank i - rank j| <= b for
    every coupling): O(n b^2) instead of the dense O(n^3).  ``A`` (n, 2b+1) and ``rhs`` (n,) are
    scratch; entry (r, c) of the permuted matrix is A[r, c - r + b].  The factors written to ``out`` are
    clipped to exp(+-COARSE_FACTOR_LOG_MAX) (see there)."""
    n = dg.size
    A[:, :] = 0.0
    for i in range(n):
        r = rank[i]
        A[r, b] = dg[i]
        rhs[r] = f[i]
        for e in range(ip[i], ip[i + 1]):
            j = ind[e]
            if j != i:
                A[r, rank[j] - r + b] -= vals[e]
    for k in range(n):
        inv = 1.0 / A[k, b]
        top = min(b, n - 1 - k)
        for t in range(1, top + 1):
            i = k + t
            m = A[i, b - t] * inv
            if m != 0.0:
                for j in range(1, top + 1):
                    A[i, b - t + j] -= m * A[k, b + j]
                rhs[i] -= m * rhs[k]
    for k in range(n - 1, -1, -1):
        acc = rhs[k]
        for j in range(1, min(b, n - 1 - k) + 1):
            acc -= A[k, b + j] * rhs[k + j]
        rhs[k] = acc / A[k, b]
    lo = np.exp(-COARSE_FACTOR_LOG_MAX)
    hi = 1.0 / lo
    for i in range(n):
        out[i] = min(max(rhs[rank[i]], lo), hi)


@njit(cache=True)
def _dense_solve_ell(nb, w4, f):
    """Gaussian elimination (``_eliminate``) of level 0 (dg = 1) from its ELL table: a map small enough to
    have no coarser level."""
    n = f.size
    A = np.zeros((n, n))
    for i in range(n):
        A[i, i] = 1.0
        for d in range(4):
            if nb[i, d] != i:
                A[i, nb[i, d]] -= w4[i, d]
    return _eliminate(A, f.copy())


@njit(cache=True)
def _eliminate(A, b):
    """Solve A x = b in place by Gaussian elimination without pivoting."""
    n = b.size
    for k in range(n):
        for i in range(k + 1, n):
            if A[i, k] != 0.0:
                m = A[i, k] / A[k, k]
                for j in range(k + 1, n):
                    A[i, j] -= m * A[k, j]
                b[i] -= m * b[k]
    x = np.empty(n)
    for k in range(n - 1, -1, -1):
        acc = b[k]
        for j in range(k + 1, n):
            acc -= A[k, j] * x[j]
        x[k] = acc / A[k, k]
    return x


@njit(cache=True)
def _gs_saving(x, xs, dg, ip, ind, vals, f, four):
    """Forward Gauss-Seidel sweep that first copies every x_i to xs (the repetition's starting point)."""
    for i in range(x.size):
        xs[i] = x[i]
        inv = 1.0 / dg[i]           # off the row-to-row dependency chain (see _gs)
        acc = f[i]
        if four:
            e = 4 * i
            acc += (vals[e] * x[ind[e]] + vals[e + 1] * x[ind[e + 1]]) \
                + (vals[e + 2] * x[ind[e + 2]] + vals[e + 3] * x[ind[e + 3]])
        else:
            for e in range(ip[i], ip[i + 1]):
                acc += vals[e] * x[ind[e]]
        x[i] = acc * inv


@njit(cache=True)
def _descend(l, NN, NNZ, PO, EO, NO, IP, IND, AGG, EMAP, S, DG, VALS, F, X, XS, R, W, nu, EB, SB, scaled,
             PAD):
    """Start one repetition at coarse level l >= 1: remember x, pre-smooth, and pose the coarse problem
    for the factor q (level l+1's buffers, q = 1)."""
    n, no, eo = NN[l], NO[l], EO[l]
    nc, nco, eoc = NN[l + 1], NO[l + 1], EO[l + 1]
    ip = IP[PO[l]:PO[l] + n + 1]
    ind = IND[eo:eo + NNZ[l]]
    x = X[no:no + n]
    dg = DG[no:no + n]
    vals = VALS[eo:eo + NNZ[l]]
    f = F[no:no + n]
    four = PAD[l]
    if nu > 0:
        _gs_saving(x, XS[no:no + n], dg, ip, ind, vals, f, four)
    else:
        XS[no:no + n] = x
    for _ in range(nu - 1):
        _gs(x, dg, ip, ind, vals, f, True, four)
    agg = AGG[no:no + n]
    emap = EMAP[eo:eo + NNZ[l]]
    out = (S[nco:nco + nc], DG[nco:nco + nc], VALS[eoc:eoc + NNZ[l + 1]], F[nco:nco + nc])
    if scaled:
        _coarse_operator_scaled(x, EB[no:no + n], SB[nco:nco + nc], dg, ip, ind, vals, f, agg, emap,
                                IP[PO[l + 1]:PO[l + 1] + nc + 1], out[0], out[1], out[2], out[3],
                                R[nco:nco + nc], W[nco:nco + nc], four)
    else:
        _coarse_operator(x, S[no:no + n], dg, ip, ind, vals, f, agg, emap, out[0], out[1], out[2], out[3])
    X[nco:nco + nc] = 1.0


@njit(cache=True)
def _ascend(l, NN, NNZ, PO, EO, NO, IP, IND, AGG, S, DG, VALS, F, X, XS, R, W, D, D1, V, V1, state,
            over, krylov, nu, PAD):
    """Finish one repetition at level l: apply the coarse factors q (over-corrected at a non-Krylov
    level), post-smooth, and at a Krylov level take the GCR step.  ``state`` = [rep_lin, vv1] of this
    level (the previous repetition's Krylov direction and its norm)."""
    n, no, eo = NN[l], NO[l], EO[l]
    nc, nco = NN[l + 1], NO[l + 1]
    ip = IP[PO[l]:PO[l] + n + 1]
    ind = IND[eo:eo + NNZ[l]]
    x, xs = X[no:no + n], XS[no:no + n]
    dg, f = DG[no:no + n], F[no:no + n]
    vals = VALS[eo:eo + NNZ[l]]
    agg = AGG[no:no + n]
    q = X[nco:nco + nc]
    # Over-correction and the Krylov combination rest on the linear picture (corrections small relative
    # to x); far from the solution (a cold start: factors of e^30) they diverge, so both are used only
    # when every factor of this repetition is within LINEAR_BAND of 1 (over-correction outside it is
    # clipped to e^OVER_CLIP).
    linear = _over_correct(q, over)
    hi = np.exp(LINEAR_BAND)
    lo = 1.0 / hi
    for i in range(n):
        x[i] *= q[agg[i]]
    four = PAD[l]
    for _ in range(nu):
        _gs(x, dg, ip, ind, vals, f, False, four)
    if not krylov:
        return
    r, w = R[no:no + n], W[no:no + n]
    d, d1, v, v1 = D[no:no + n], D1[no:no + n], V[no:no + n], V1[no:no + n]
    # v = M d for d = x - xs (formed on the fly), with the linear-band check and the dot products of
    # the GCR step, in one pass
    has1 = state[0] > 0.0
    rv = 0.0
    vv = 0.0
    vv1 = 0.0
    for i in range(n):
        di = x[i] - xs[i]
        if x[i] > hi * xs[i] or x[i] < lo * xs[i]:
            linear = False
            break
        d[i] = di
        acc = dg[i] * di
        e0, e1 = (4 * i, 4 * i + 4) if four else (ip[i], ip[i + 1])
        for e in range(e0, e1):
            j = ind[e]
            acc -= vals[e] * (x[j] - xs[j])
        v[i] = acc
        wi = w[i]
        rv += r[i] * acc * wi
        vv += acc * acc * wi
        if has1:
            vv1 += acc * v1[i] * wi
    if not linear:
        relative_residual(x, dg, ip, ind, vals, f, r)
        state[0] = 0.0
        return
    if has1:
        # orthogonalise against the previous repetition's direction (dot products recomputed from the
        # orthogonalised vectors, not by expanding them: v is often nearly parallel to v1)
        b = vv1 / max(state[1], 1e-300)
        rv = 0.0
        vv = 0.0
        for i in range(n):
            d[i] -= b * d1[i]
            v[i] -= b * v1[i]
            rv += r[i] * v[i] * w[i]
            vv += v[i] * v[i] * w[i]
    a = rv / max(vv, 1e-300)
    for i in range(n):
        # GCR step; positivity kept (phi > 0 on every connected cell), the clamp is never active near
        # convergence
        x[i] = max(xs[i] + a * d[i], 0.05 * xs[i])
        r[i] -= a * v[i]
        d1[i] = d[i]
        v1[i] = v[i]
    state[0] = 1.0
    state[1] = vv


@njit(cache=True)
def _cycle(L, NN, NNZ, PO, EO, NO, IP, IND, AGG, EMAP, S, DG, VALS, F, X, XS, R, W, D, D1, V, V1, EB, SB,
           over_correction, kdepth, nu, nb, w4, emap4, E0, S0, prev, PAD, nu0, tab, RANK, BAND, BA, BR):
    """One cycle from the fine level, written as a loop over an explicit level pointer (numba cannot
    cache a recursive function); returns the largest relative change of phi it made.  Level 0 (its own
    ELL kernels, ``nb, w4``) and levels deeper than ``kdepth`` do one repetition: pre-smooth, coarse
    factor q solved at the next level, ``x *= q ** over_correction`` (on level 0 interpolated bilinearly
    between aggregates, ``tab``), post-smooth.  Levels 1..kdepth are
    K-cycles: two repetitions (no over-correction) combined by two GCR steps that minimise the relative
    residual, which makes the under-sized piecewise-constant corrections exact in their span.  The
    coarsest level is solved directly (``_band_solve``).  All levels' arrays live in the flat buffers at
    offsets NO (nodes) / EO (entries); level 0's operator is only in ``nb, w4`` (its VALS slice is
    scratch)."""
    n0 = NN[0]
    x0 = X[:n0]
    rep = np.zeros(L, dtype=np.int64)
    state = np.zeros((L, 2))
    if L == 1:
        prev[:] = x0
        sol = _dense_solve_ell(nb, w4, F[:n0])
        for i in range(n0):
            X[i] = max(sol[i], 1e-300)
        return _max_rel_change(x0, prev)
    l = 0
    entering = True
    while True:
        if l == L - 1:
            n, no, eo = NN[l], NO[l], EO[l]
            _band_solve(DG[no:no + n], IP[PO[l]:PO[l] + n + 1], IND[eo:eo + NNZ[l]], VALS[eo:eo + NNZ[l]],
                        F[no:no + n], RANK, BAND, BA, BR, X[no:no + n])
            l -= 1
            entering = False
            continue
        krylov = 1 <= l <= kdepth
        if entering:
            rep[l] = 0
            state[l, 0] = 0.0
            if krylov:
                # R and W (residual at q = 1, GCR weights) were written with the level's operator
                n, no = NN[l], NO[l]
                # the level's log scale is fixed during its two repetitions: exp(s - max s) once, not
                # a log and an exp per cell and repetition in _coarse_operator
                nco = NO[l + 1]
                _level_scales_into(S[no:no + n], AGG[no:no + n], EB[no:no + n], SB[nco:nco + NN[l + 1]])
        elif l == 0:
            q = X[n0:n0 + NN[1]]
            _over_correct(q, over_correction)
            Q = XS[:n0]             # level 0 has no repetition to remember: its XS slice is scratch
            _interp_factors(q, AGG[:n0], tab, Q)
            if nu0 == 1:
                return _fine_prolong_gs_back(x0, nb, w4, F[:n0], Q, prev, True)
            _fine_prolong_gs_back(x0, nb, w4, F[:n0], Q, prev, False)
            for _ in range(nu0 - 2):
                _fine_gs(x0, nb, w4, F[:n0], False)
            return _fine_gs_back_change(x0, nb, w4, F[:n0], prev)
        else:
            _ascend(l, NN, NNZ, PO, EO, NO, IP, IND, AGG, S, DG, VALS, F, X, XS, R, W, D, D1, V, V1,
                    state[l], 1.0 if krylov else over_correction, krylov, nu, PAD)
            rep[l] += 1
            if rep[l] >= (2 if krylov else 1):
                l -= 1
                entering = False
                continue
        if l == 0:
            _fine_gs_saving(x0, prev, nb, w4, F[:n0])
            for _ in range(nu0 - 1):
                _fine_gs(x0, nb, w4, F[:n0], True)
            n1, e1 = NN[1], EO[1]
            _fine_restrict(x0, nb, w4, F[:n0], E0, S0, AGG[:n0], emap4, IP[PO[1]:PO[1] + n1 + 1],
                           S[n0:n0 + n1], DG[n0:n0 + n1], VALS[e1:e1 + NNZ[1]], F[n0:n0 + n1], R[n0:n0 + n1],
                           W[n0:n0 + n1])
            X[n0:n0 + n1] = 1.0
        else:
            _descend(l, NN, NNZ, PO, EO, NO, IP, IND, AGG, EMAP, S, DG, VALS, F, X, XS, R, W, nu, EB, SB, krylov,
                     PAD)
        l += 1
        entering = True


@njit(cache=True)
def _max_rel_change(x, prev):
    worst = 0.0
    for i in range(x.size):
        r = abs(x[i] - prev[i]) / x[i]
        if not r <= worst:              # NaN propagates (see _fine_prolong_gs_back)
            worst = r
    return worst


@njit(cache=True)
def _log_extent(x):
    lo = np.inf
    hi = 0.0
    for v in x:
        lo = min(lo, v)
        hi = max(hi, v)
    return max(np.log(hi), -np.log(lo))


@njit(cache=True)
def _rescale(x, nb, w4, f):
    """Level 0's operator rescaled for ``s += log x``: ``w_ij *= x_j / x_i``, ``f_i /= x_i``."""
    for i in range(x.size):
        inv = 1.0 / x[i]
        for d in range(4):
            w4[i, d] *= x[nb[i, d]] * inv
        f[i] *= inv


def rebase(x, s, nb, w4, f):
    """Fold the relative factors into the log scale: ``s += log x``, level 0's operator rescaled to
    match, ``x = 1``.  No exponentials; the logarithms vectorised by numpy."""
    _rescale(x, nb, w4, f)
    s += np.log(x)
    x[:] = 1.0


# Log scale given to a removed cell (``LogFieldSolver.block``): exp(2 (s - max s)) of it underflows to 0,
# so it carries no weight in any aggregate that still has a live cell.
DEAD_LOG_SCALE = -1e6


@njit(cache=True)
def _block_cells(dead, nb, w4, f, x, s):
    """Cut the compact cells ``dead`` out of level 0's system in place: their couplings (both directions)
    set to 0, their row ``x_i = f_i = 1`` (a fixed point Gauss-Seidel keeps exactly), their log scale to
    DEAD_LOG_SCALE.  Returns how many were not dead already."""
    fresh = 0
    for k in range(dead.size):
        i = dead[k]
        if s[i] == DEAD_LOG_SCALE:
            continue
        fresh += 1
        for d in range(4):
            j = nb[i, d]
            if j != i:
                w4[j, d ^ 1] = 0.0      # east <-> west, south <-> north
            w4[i, d] = 0.0
        f[i] = 1.0
        x[i] = 1.0
        s[i] = DEAD_LOG_SCALE
    return fresh


@njit(cache=True)
def _rescale_dead_aggregates(s, agg, dead, E2, S):
    """``fine_scales`` (E2, S) brought up to date after ``_block_cells`` set the log scale of the cells
    ``dead`` to DEAD_LOG_SCALE: only the aggregates holding one of them change (their max may have
    died), so only their cells are recomputed."""
    touched = np.zeros(S.size, dtype=np.bool_)
    for k in range(dead.size):
        a = agg[dead[k]]
        touched[a] = True
        S[a] = -np.inf
    for i in range(s.size):
        a = agg[i]
        if touched[a] and s[i] > S[a]:
            S[a] = s[i]
    for i in range(s.size):
        a = agg[i]
        if touched[a]:
            E2[i] = np.exp(2.0 * (s[i] - S[a]))


class LogFieldSolver:
    """The ACTIVE cells' system for one map (which cells are ACTIVE / TARGET), solved by cycles.

    ``s`` (compact log scale) and ``x`` (relative factor) hold the iterate: log phi = s + log x."""

    _BUFFERS = ("S", "DG", "F", "X", "XS", "R", "W", "D", "D1", "V", "V1", "E", "SA", "VALS")

    def __init__(self, state: np.ndarray, s_padded: np.ndarray, coarsest: int = 48,
                 recycle: "LogFieldSolver | None" = None):
        """``recycle``: a solver that will not be used again (the previous map's), whose work buffers are
        reused when large enough — fresh memory costs a page fault per 4 kB on first touch (every
        buffer is written before it is read)."""
        cells, nb, w4, f, ip, ind, cy, cx = fine_system(state, s_padded)
        self.cells, self.nb, self.w4, self._cy, self._cx = cells, nb, w4, cy, cx
        self.hier = Hierarchy(ip, ind, cy, cx, coarsest)
        self.emap4 = ell_emap(nb, self.hier.emap0)
        # level 0's bilinear prolongation (none without a coarser level)
        self._interp = (interp_table(nb, w4, cy, cx, self.hier.agg[:cells.size]) if self.hier.levels > 1
                        else np.zeros((0, 3), np.int64))
        n, nodes, entries = cells.size, int(self.hier.n.sum()), int(self.hier.nnz.sum())
        # Every level's arrays in flat buffers (offsets in the hierarchy); level 0's are slices of them,
        # taken on access (stored views would come apart under copy.deepcopy).
        old = recycle._store if recycle is not None else {}
        self._store = {}
        for k in self._BUFFERS:
            size = entries if k == "VALS" else nodes
            base = old.get(k)
            self._store[k] = base if base is not None and base.size >= size else np.empty(size + size // 8)
        self._buf = {k: self._store[k][:nodes] for k in self._BUFFERS if k != "VALS"}
        self._vals = self._store["VALS"][:entries]
        self.s[:] = s_padded.ravel()[cells]
        self.x[:] = 1.0
        self.f[:] = f
        self._buf["DG"][:n] = 1.0
        self._prev = np.empty(n)
        self._band_a = np.empty((self.hier.rank.size, 2 * self.hier.band + 1))    # the coarsest level's
        self._band_r = np.empty(self.hier.rank.size)                              # elimination scratch
        self.dead = 0           # cells cut out by ``block`` since the hierarchy was built
        self._scales = None     # level-0 constants of the coarse operator (fine_scales), until the next rebase

    @property
    def s(self) -> np.ndarray:
        """Log scale of the ACTIVE cells (compact order of ``cells``)."""
        return self._buf["S"][:self.cells.size]

    @property
    def x(self) -> np.ndarray:
        """Relative factor: log phi = s + log x."""
        return self._buf["X"][:self.cells.size]

    @property
    def f(self) -> np.ndarray:
        return self._buf["F"][:self.cells.size]

    @property
    def size(self) -> int:
        """Unknowns in the system (including cells cut out by ``block``)."""
        return int(self.cells.size)

    @property
    def live_size(self) -> int:
        """ACTIVE cells still in the system (``size`` minus the cells cut out by ``block``)."""
        return int(self.cells.size) - self.dead

    def block(self, flat_cells: np.ndarray) -> None:
        """Take ACTIVE cells (padded flat indices, all in ``cells``) out of the system without rebuilding
        the hierarchy: a map change that only blocks cells (an object appeared) keeps the aggregates and
        coarse patterns, which depend only on the graph.  Each removed cell becomes an isolated unknown
        fixed at x = 1 with a log scale so low that it weighs nothing in the Galerkin operators, so the
        live cells' field is exactly that of the rebuilt map's (same equations); only the coarse spaces
        are the old map's.  The iterate carries over as it is (a warm start)."""
        idx = np.searchsorted(self.cells, np.asarray(flat_cells, dtype=np.int64))
        if idx.size and (idx.max() >= self.cells.size or not np.array_equal(self.cells[idx], flat_cells)):
            raise ValueError("LogFieldSolver.block: every cell to block must be one of the solver's cells")
        self.dead += int(_block_cells(idx, self.nb, self.w4, self.f, self.x, self.s))
        if self._interp.size:
            update_interp_table(self._interp, idx, self.nb, self.w4, self._cy, self._cx,
                                self.hier.agg[:self.size])
        if self._scales is not None and self._scales[1].size:
            _rescale_dead_aggregates(self.s, self.hier.agg[:self.size], idx, *self._scales)

    def cycle(self, over_correction: float, smoothing: int, krylov_levels: int,
              fine_sweeps: int | None = None) -> float:
        """One fine-level cycle; returns the largest relative change of phi it made.  ``smoothing``:
        Gauss-Seidel sweeps before and after each coarse correction on the coarse levels, and on level 0
        unless ``fine_sweeps`` is given."""
        if fine_sweeps is None:
            fine_sweeps = smoothing
        L, NN, NNZ, PO, EO, NO, IP, IND, AGG, EMAP, PAD = self.hier.arrays()
        if self._scales is None:
            if L > 1:
                self._scales = fine_scales(self.s, AGG[:NN[0]], NN[1])
            else:
                self._scales = (np.zeros(0), np.zeros(0))
        b = self._buf
        return float(_cycle(L, NN, NNZ, PO, EO, NO, IP, IND, AGG, EMAP, b["S"], b["DG"], self._vals, b["F"],
                            b["X"], b["XS"], b["R"], b["W"], b["D"], b["D1"], b["V"], b["V1"], b["E"], b["SA"],
                            float(over_correction), int(krylov_levels), int(smoothing), self.nb, self.w4,
                            self.emap4, *self._scales, self._prev, PAD, int(fine_sweeps), self._interp,
                            self.hier.rank, self.hier.band, self._band_a, self._band_r))

    def residual(self) -> float:
        """Largest relative residual of level 0 (see ``relative_residual``)."""
        return float(fine_residual(self.x, self.nb, self.w4, self.f)) if self.size else 0.0

    def drift(self) -> float:
        """Largest |log x|: how far the factors have moved from 1 since the last ``rebase``."""
        return float(_log_extent(self.x)) if self.size else 0.0

    def log_phi(self) -> np.ndarray:
        """log phi of every cell (compact order; DEAD_LOG_SCALE-ish for cells cut out by ``block``)."""
        return self.s + np.log(self.x)

    def rebase(self) -> None:
        rebase(self.x, self.s, self.nb, self.w4, self.f)
        self._scales = None
