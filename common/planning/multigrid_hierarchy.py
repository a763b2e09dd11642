"""The multigrid's hierarchy: level 0's operator from the planner's grid, the aggregation of each level
into the next, the coarse sparsity patterns, and their flattening for the numba cycle (multigrid.py);
the banded coarsest level's ordering; level 0's bilinear prolongation table.

multigrid.py keeps the cycle and the solver; this part depends only on which cells are
ACTIVE (and level 0's weights on the log scale), so it runs once per map change, not per cycle.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.sparse.csgraph import reverse_cuthill_mckee

from . import harmonic as hk


@njit(cache=True)
def fine_system(state, s):
    """Level-0 operator from the padded state and log scale: (cells, nb, w4, f, ip, ind, cy, cx).

    ``cells`` are the flat indices of the ACTIVE cells (ascending, = compact numbering), ``cy, cx``
    their padded row / column.  The operator is stored twice: as a fixed-width (ELL) table — ``nb[i, d]``
    the compact index of the neighbour in direction d (east, west, south, north), ``w4[i, d]`` its weight
    ``exp(s_j - s_i) / 4``, a missing neighbour pointing at i itself with weight 0 — which the cycle's
    level-0 kernels run on (no row pointers, a fixed four-term sum), and as the
    CSR pattern ``ip, ind`` (the ELL entries that are not missing, in the same order) from which the
    hierarchy is built.  One exponential per edge between ACTIVE cells: the east / south weight, whose
    reciprocal is the neighbour's west / north weight."""
    h, w = state.shape
    stf = state.ravel()
    sf = s.ravel()
    comp = np.empty(h * w, dtype=np.int64)
    n = 0
    for i in range(h * w):
        comp[i] = n
        n += stf[i] == hk.ACTIVE
    cells = np.empty(n, dtype=np.int64)
    cy = np.empty(n, dtype=np.int64)
    cx = np.empty(n, dtype=np.int64)
    nb = np.empty((n, 4), dtype=np.int64)
    w4 = np.empty((n, 4))
    f = np.empty(n)
    ip = np.empty(n + 1, dtype=np.int64)
    ind = np.empty(4 * n, dtype=np.int64)
    ip[0] = 0
    m = 0
    k = 0
    for y in range(1, h - 1):
        for x in range(1, w - 1):
            i = y * w + x
            if stf[i] != hk.ACTIVE:
                continue
            cells[k] = i
            cy[k] = y
            cx[k] = x
            f[k] = 0.0
            for d in range(4):
                j = i + 1 if d == 0 else (i - 1 if d == 1 else (i + w if d == 2 else i - w))
                st = stf[j]
                if st == hk.ACTIVE:
                    kj = comp[j]
                    nb[k, d] = kj
                    if d == 0 or d == 2:        # later in the order: set both directions of the edge
                        e = np.exp(sf[j] - sf[i])
                        w4[k, d] = 0.25 * e
                        w4[kj, d + 1] = 0.25 / e
                    ind[m] = kj
                    m += 1
                else:
                    nb[k, d] = k
                    w4[k, d] = 0.0
                    if st == hk.TARGET:
                        f[k] += 0.25 * np.exp(sf[j] - sf[i])
            k += 1
            ip[k] = m
    return cells, nb, w4, f, ip, ind[:m].copy(), cy, cx


@njit(cache=True)
def _find(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit(cache=True)
def aggregate(indptr, indices, cy, cx):
    """Aggregate of every node: the 4-connected pieces of the nodes sharing a parent cell
    (cy // 2, cx // 2) — so an aggregate never joins cells on two sides of a wall.  Returns
    (agg, number of aggregates, their cy, their cx)."""
    n = cy.size
    parent = np.arange(n)
    for i in range(n):
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            if cy[j] // 2 == cy[i] // 2 and cx[j] // 2 == cx[i] // 2:
                ri = _find(parent, i)
                rj = _find(parent, j)
                if ri != rj:
                    parent[max(ri, rj)] = min(ri, rj)
    agg = np.full(n, -1, dtype=np.int64)
    nc = 0
    for i in range(n):
        r = _find(parent, i)
        if agg[r] < 0:
            agg[r] = nc
            nc += 1
        agg[i] = agg[r]
    ccy = np.empty(nc, dtype=np.int64)
    ccx = np.empty(nc, dtype=np.int64)
    for i in range(n):
        ccy[agg[i]] = cy[i] // 2
        ccx[agg[i]] = cx[i] // 2
    return agg, nc, ccy, ccx


@njit(cache=True)
def coarse_pattern(indptr, indices, agg, nc):
    """CSR pattern (cptr, cind) of the aggregate graph and, for every fine entry, the coarse entry it
    adds to (-1: both ends in one aggregate, it goes to the diagonal).  O(nnz), no sorting."""
    n = agg.size
    # nodes grouped by aggregate (counting sort)
    start = np.zeros(nc + 1, dtype=np.int64)
    for i in range(n):
        start[agg[i] + 1] += 1
    for a in range(nc):
        start[a + 1] += start[a]
    order = np.empty(n, dtype=np.int64)
    fill = start[:-1].copy()
    for i in range(n):
        order[fill[agg[i]]] = i
        fill[agg[i]] += 1
    mark = np.full(nc, -1, dtype=np.int64)     # coarse entry of neighbour aggregate b in the current row
    cptr = np.zeros(nc + 1, dtype=np.int64)
    cind = np.empty(indices.size, dtype=np.int64)
    emap = np.full(indices.size, -1, dtype=np.int64)
    m = 0
    for a in range(nc):
        row0 = m
        for k in range(start[a], start[a + 1]):
            i = order[k]
            for e in range(indptr[i], indptr[i + 1]):
                b = agg[indices[e]]
                if b == a:
                    continue
                if mark[b] < row0:
                    mark[b] = m
                    cind[m] = b
                    m += 1
                emap[e] = mark[b]
        cptr[a + 1] = m
    return cptr, cind[:m].copy(), emap


def pad_rows4(cptr, cind, emap):
    """A CSR pattern whose rows have at most 4 entries, padded to exactly 4 (a padding entry points at its
    own row and its value stays 0), and the finer level's entry map moved to the padded positions.  The
    kernels run such a level with a fixed four-term row (``four``), which the compiler unrolls (level 1
    of a grid map has every row <= 4 entries)."""
    nc = cptr.size - 1
    deg = np.diff(cptr)
    rows = np.repeat(np.arange(nc), deg)
    pos = np.arange(cind.size) - cptr[:-1][rows] + 4 * rows
    ind4 = np.repeat(np.arange(nc, dtype=np.int64), 4)
    ind4[pos] = cind
    emap4 = np.where(emap >= 0, pos[np.maximum(emap, 0)], -1)
    return np.arange(0, 4 * nc + 1, 4, dtype=np.int64), ind4, emap4


# The coarsest level.  The hierarchy stops at the first coarse level whose couplings fit in a band of
# half-width BAND_MAX once its nodes are in reverse Cuthill-McKee order; the cycle solves that level
# exactly by banded elimination, O(n b^2) (multigrid._band_solve).  Corridors give such chain-like
# levels early (a few hundred unknowns); solving them exactly is what lets K-cycles on level 1 alone
# converge (PlannerConfig.mg_krylov_levels).  An open room stops at ~50-170 unknowns.
BAND_MAX = 8
BAND_PROBE_MAX = 4000       # larger levels are not probed (scipy's ordering of them costs ~1 ms)


def band_order(indptr, indices):
    """(rank, b): reverse Cuthill-McKee position of every node and the half-bandwidth in that order."""
    n = indptr.size - 1
    if n <= 1:
        return np.zeros(n, np.int64), 0
    A = sp.csr_matrix((np.ones(indices.size), indices, indptr), shape=(n, n))
    perm = reverse_cuthill_mckee((A + A.T).tocsr(), symmetric_mode=True)
    rank = np.empty(n, np.int64)
    rank[perm] = np.arange(n)
    rows = np.repeat(np.arange(n), np.diff(indptr))
    return rank, int(np.abs(rank[rows] - rank[indices]).max(initial=0))


class Hierarchy:
    """Aggregates and coarse sparsity patterns of every level, flattened for the numba cycle.  Depends
    only on which cells are ACTIVE, so it is rebuilt when the map changes, not per cycle.  Level 0's
    own entries are not copied into the flat arrays (the cycle reads level 0 from the solver's ELL
    table; ``nnz[0]`` is 0 there): ``emap0`` maps its CSR entries to level 1's.  The coarsest level is
    solved by banded elimination in the order ``rank`` (its node -> row), whose half-bandwidth is
    ``band`` (see BAND_MAX)."""

    def __init__(self, indptr, indices, cy, cx, coarsest: int = 48, band_max: int = BAND_MAX):
        ips, inds, aggs, emaps, sizes = [indptr], [np.zeros(0, np.int64)], [], [], [cy.size]
        pads = [False]
        ip, ind = indptr, indices
        rank, band = None, 0
        while cy.size > coarsest:
            if len(sizes) > 1 and cy.size <= BAND_PROBE_MAX:
                rank, band = band_order(ip, ind)
                if band <= band_max:
                    break
                rank = None
            agg, nc, cy2, cx2 = aggregate(ip, ind, cy, cx)
            shift = 1
            while nc == cy.size and shift < 62:
                # No node shares its parent cell with a neighbour (a pathological map): look at coarser
                # parent cells until something merges (the whole grid is one connected piece at last),
                # so the directly solved coarsest level stays small.
                agg, nc, cy2, cx2 = aggregate(ip, ind, cy >> shift, cx >> shift)
                shift += 1
            if nc == cy.size:
                break
            cptr, cind, emap = coarse_pattern(ip, ind, agg, nc)
            pad = bool(cind.size) and int(np.diff(cptr).max()) <= 4
            if pad:
                cptr, cind, emap = pad_rows4(cptr, cind, emap)
            pads.append(pad)
            aggs.append(agg)
            emaps.append(emap)
            ips.append(cptr)
            inds.append(cind)
            sizes.append(nc)
            ip, ind, cy, cx = cptr, cind, cy2, cx2
        if rank is None and len(sizes) > 1:
            rank, band = band_order(ip, ind)
        self.rank = rank if rank is not None else np.zeros(0, np.int64)
        self.band = int(band)                  # the coarsest level's half-bandwidth in the order rank
        self.levels = len(sizes)
        self.pad4 = np.array(pads, dtype=np.bool_)      # level stored with exactly 4 entries per row
        self.emap0 = emaps.pop(0) if emaps else np.zeros(0, np.int64)
        emaps.insert(0, np.zeros(0, np.int64))
        self.n = np.array(sizes, dtype=np.int64)
        self.nnz = np.array([len(v) for v in inds], dtype=np.int64)
        self.ip_off = np.concatenate([[0], np.cumsum(self.n + 1)]).astype(np.int64)
        self.e_off = np.concatenate([[0], np.cumsum(self.nnz)]).astype(np.int64)
        self.n_off = np.concatenate([[0], np.cumsum(self.n)]).astype(np.int64)
        self.ip = np.concatenate(ips)
        self.ind = np.concatenate(inds)
        self.agg = np.concatenate(aggs + [np.zeros(0, np.int64)])
        self.emap = np.concatenate(emaps + [np.zeros(0, np.int64)])

    def arrays(self):
        return (self.levels, self.n, self.nnz, self.ip_off, self.e_off, self.n_off, self.ip, self.ind,
                self.agg, self.emap, self.pad4)


@njit(cache=True)
def ell_emap(nb, emap):
    """``coarse_pattern``'s entry map moved from level 0's CSR entries to its ELL slots (-1: missing
    neighbour or same aggregate, i.e. the diagonal)."""
    n = nb.shape[0]
    out = np.full((n, 4), -1, dtype=np.int64)
    e = 0
    for i in range(n):
        for d in range(4):
            if nb[i, d] != i:
                if emap.size:
                    out[i, d] = emap[e]
                e += 1
    return out


@njit(cache=True)
def _interp_rows(rows, nb, w4, cy, cx, agg, tab):
    """Rows ``rows`` of ``interp_table`` (re)computed in place."""
    for k in range(rows.size):
        i = rows[k]
        a = agg[i]
        dh = 1 if cx[i] % 2 == 0 else 0         # a 2 x 2 block's west column looks west, its east one east
        dv = 3 if cy[i] % 2 == 0 else 2         # its north row looks north, its south row south
        jh = nb[i, dh] if w4[i, dh] > 0.0 else -1
        jv = nb[i, dv] if w4[i, dv] > 0.0 else -1
        jd = -1
        if jh >= 0 and w4[jh, dv] > 0.0:
            jd = nb[jh, dv]
        elif jv >= 0 and w4[jv, dh] > 0.0:
            jd = nb[jv, dh]
        tab[i, 0] = agg[jh] if jh >= 0 else a
        tab[i, 1] = agg[jv] if jv >= 0 else a
        tab[i, 2] = agg[jd] if jd >= 0 else a


def interp_table(nb, w4, cy, cx, agg):
    """Level 0's smoothed (bilinear) prolongation: for every cell the aggregates of the three nearest
    other 2 x 2 blocks — beside it, above or below it, and diagonally — reached through live couplings
    only (a wall, the grid's edge or a cell cut out by ``block`` in the way: its own aggregate instead),
    so a factor is never interpolated across a wall.  See multigrid._interp_factors."""
    tab = np.empty((nb.shape[0], 3), dtype=np.int64)
    _interp_rows(np.arange(nb.shape[0]), nb, w4, cy, cx, agg, tab)
    return tab


def update_interp_table(tab, dead, nb, w4, cy, cx, agg):
    """``interp_table`` brought up to date after ``_block_cells`` cut the cells ``dead`` out: only rows
    within two couplings of a removed cell can change (their neighbour, or the diagonal path through
    it, is gone)."""
    ring1 = nb[dead]
    _interp_rows(np.unique(np.concatenate([ring1.ravel(), nb[ring1].ravel()])), nb, w4, cy, cx, agg, tab)
