"""Multiplicative coarse-grid correction (iterative aggregation) for the log-space harmonic system.

SOR fixes local errors fast but moves a *long-range* change slowly: when an object narrows a corridor,
everything farther from the target must drop by a common factor (e^16 in the benchmark's worst case)
and SOR diffuses that factor along the corridor a little per sweep, leaving a spurious local maximum at
the narrowing meanwhile.  An additive linear correction cannot fix it either: a change by a factor 1e7
needs relative, not absolute, accuracy.

So the correction is *multiplicative*: the ACTIVE cells are aggregated into B x B blocks, phi is
restricted to ``exp(s) * q[block]`` (one unknown factor per block, the fine-scale shape kept in s), and
the Galerkin projection of Laplace's equation onto that space is solved exactly (SuperLU).  The scaled
system ``r = W r + b`` is the similarity transform ``D^-1 A D`` (D = diag(exp(s))) of the symmetric
``A phi = b``; the coarse system is ``R (I - W) P q = R b`` with P piecewise constant and
``R = P^T diag(exp(2 (s - s_block)))`` (the symmetric projection, scaled per block so nothing underflows).
It is an M-matrix with b >= 0, so the factors q are positive and accurate however small, and
``s += log q[block]`` moves whole regions by the right factor at once.  SOR then repairs the detail.

The planner applies it once after every change of the map (and on a cold start), followed by a couple of
Gauss-Seidel sweeps to blend the block edges.  Repeating it every few sweeps does not converge faster:
with over-relaxed SOR between corrections the block edges keep re-exciting the error, and with plain
Gauss-Seidel the two-level cycle contracts only ~0.7 per cycle (measured; see the report).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numba import njit

from . import harmonic as hk


@njit(cache=True)
def block_aggregates(cells, width, block):
    """Compact index of the B x B block (of the padded grid) of every cell in ``cells``, the number of
    blocks, and for every block the compact index of its +x, -x, +y, -y neighbour blocks (-1: none)."""
    nbx = (width + block - 1) // block
    n = cells.size
    key = np.empty(n, dtype=np.int64)
    maxkey = 0
    for k in range(n):
        i = cells[k]
        key[k] = (i // width // block) * nbx + (i % width) // block
        if key[k] > maxkey:
            maxkey = key[k]
    remap = np.full(maxkey + nbx + 2, -1, dtype=np.int64)
    nc = 0
    for k in range(n):
        if remap[key[k]] < 0:
            remap[key[k]] = nc
            nc += 1
    agg = np.empty(n, dtype=np.int64)
    keys = np.empty(nc, dtype=np.int64)
    for k in range(n):
        agg[k] = remap[key[k]]
        keys[agg[k]] = key[k]
    nbr = np.full((nc, 4), -1, dtype=np.int64)
    for a in range(nc):
        kk = keys[a]
        nbr[a, 0] = remap[kk + 1]
        if kk >= 1:
            nbr[a, 1] = remap[kk - 1]
        nbr[a, 2] = remap[kk + nbx]
        if kk >= nbx:
            nbr[a, 3] = remap[kk - nbx]
    return agg, nc, nbr


@njit(cache=True)
def galerkin_system(cells, wt, s, state, agg, nc, nbr, block):
    """CSR arrays (indptr, indices, data) of R (I - W) P and the vector R b (b: weights towards TARGET
    cells).  A cell's neighbour is in its own block or the adjacent block in the same direction, so the
    coarse operator is a 5-point stencil on the block grid and is assembled without sorting."""
    width = s.shape[1]
    n = cells.size
    sf = s.ravel()
    stf = state.ravel()
    smax = np.full(nc, -np.inf)
    for k in range(n):
        v = sf[cells[k]]
        if v > smax[agg[k]]:
            smax[agg[k]] = v
    st = np.zeros((nc, 5))
    rhs = np.zeros(nc)
    for k in range(n):
        i = cells[k]
        a = agg[k]
        d2 = np.exp(2.0 * (sf[i] - smax[a]))
        st[a, 0] += d2
        y = i // width
        x = i - y * width
        for d in range(4):
            w = wt[k, d]
            if w == 0.0:
                continue
            if d == 0:
                nb = i + 1
                same = (x + 1) // block == x // block
            elif d == 1:
                nb = i - 1
                same = (x - 1) // block == x // block
            elif d == 2:
                nb = i + width
                same = (y + 1) // block == y // block
            else:
                nb = i - width
                same = (y - 1) // block == y // block
            if stf[nb] == hk.TARGET:
                rhs[a] += d2 * w
            elif same:
                st[a, 0] -= d2 * w
            else:
                st[a, 1 + d] -= d2 * w
    indptr = np.zeros(nc + 1, dtype=np.int64)
    indices = np.empty(5 * nc, dtype=np.int64)
    data = np.empty(5 * nc)
    m = 0
    for a in range(nc):
        indices[m] = a
        data[m] = st[a, 0]
        m += 1
        for d in range(4):
            if st[a, 1 + d] != 0.0 and nbr[a, d] >= 0:
                indices[m] = nbr[a, d]
                data[m] = st[a, 1 + d]
                m += 1
        indptr[a + 1] = m
    return indptr, indices[:m], data[:m], rhs


def block_factors(cells: np.ndarray, wt: np.ndarray, s: np.ndarray, state: np.ndarray,
                  block: int) -> tuple[np.ndarray, np.ndarray]:
    """(agg, log q): block of every ACTIVE cell and the log of its block's coarse-solution factor
    (valid right after a re-basing, when r = 1 everywhere)."""
    agg, nc, nbr = block_aggregates(cells, s.shape[1], block)
    indptr, indices, data, rhs = galerkin_system(cells, wt, s, state, agg, nc, nbr, block)
    A = sp.csr_matrix((data, indices, indptr), shape=(nc, nc))
    q = spla.splu(A.tocsc()).solve(rhs)
    with np.errstate(divide="ignore", invalid="ignore"):
        logq = np.where(q > 0, np.log(q), 0.0)     # q > 0 for an M-matrix; never trust a rounding sign
    return agg, logq
