"""Harmonic-function kernels on a 2-D grid for a field solved in log space, so its gradient never underflows.

The classic harmonic planner solves Laplace's equation for a potential ``u`` that is 1 on obstacles and
0 on the target, and steers down ``-grad u``.  Far from the target ``u`` is ``1 - tiny``: in a corridor of
width ``w`` cells ``1 - u`` falls like ``exp(-pi d / w)``, so after a dozen corridor widths it is below
float64's epsilon, ``u`` rounds to exactly 1 and the gradient is exactly zero.

The planner therefore solves for the complementary potential ``phi = 1 - u`` (1 on the target, 0 on
obstacles and the border) stored as ``phi = exp(s) * r`` — ``s`` a per-cell log scale, ``r`` a relative
factor near 1 — with the multigrid of multigrid.py.  The field handed out is ``psi = log phi``
(finite wherever the target is reachable, ``-inf`` elsewhere); steering is its steepest ascent, i.e.
the steepest descent of ``u``.  This module holds the grid kernels around that solve: connectivity,
warm-start guesses, discrete steepest ascent and the usable-gradient measure, and the textbook
relaxation kept as the baseline that shows the underflow.

Grids are padded by one cell whose state is BLOCKED, so kernels need no bounds checks.
"""
from __future__ import annotations

import numpy as np
from numba import njit

BLOCKED = 0   # obstacle, border, or free space not connected to the target: phi = 0
ACTIVE = 1    # free cell connected to the target: unknown
TARGET = 2    # target region: phi = 1 (Dirichlet)

# 8-neighbourhood as (dy, dx, length), orthogonal first.
_NB8 = np.array([[0, 1], [0, -1], [1, 0], [-1, 0], [1, 1], [1, -1], [-1, 1], [-1, -1]], dtype=np.int64)


@njit(cache=True)
def flood_from_target(passable, target):
    """BFS (4-connected, matching the 5-point stencil) from the target cells over passable cells.

    passable, target: (H, W) bool, padded (border False).  Returns int32 steps from the target, -1 where
    the target cannot be reached."""
    h, w = passable.shape
    dist = np.full((h, w), -1, dtype=np.int32)
    qy = np.empty(h * w, dtype=np.int32)
    qx = np.empty(h * w, dtype=np.int32)
    head = 0
    tail = 0
    for y in range(h):
        for x in range(w):
            if target[y, x] and passable[y, x]:
                dist[y, x] = 0
                qy[tail] = y
                qx[tail] = x
                tail += 1
    while head < tail:
        y = qy[head]
        x = qx[head]
        head += 1
        d = dist[y, x] + 1
        for k in range(4):
            ny = y + (k == 2) - (k == 3)
            nx = x + (k == 0) - (k == 1)
            if passable[ny, nx] and dist[ny, nx] < 0:
                dist[ny, nx] = d
                qy[tail] = ny
                qx[tail] = nx
                tail += 1
    return dist


@njit(cache=True)
def plain_sor(u, state, omega, max_sweeps, tol):
    """Classic relaxation of the potential ``u`` (1 on BLOCKED, 0 on TARGET) in the array's own dtype.

    This is the textbook method kept as the comparison baseline: far from the target ``u`` rounds to 1
    and its gradient vanishes.  Returns the number of sweeps run."""
    h, w = u.shape
    one = u.dtype.type(1.0)
    quarter = u.dtype.type(0.25)
    om = u.dtype.type(omega)
    for sweep in range(max_sweeps):
        worst = 0.0
        for y in range(1, h - 1):
            for x in range(1, w - 1):
                if state[y, x] != ACTIVE:
                    continue
                old = u[y, x]
                avg = quarter * (u[y, x + 1] + u[y, x - 1] + u[y + 1, x] + u[y - 1, x])
                new = old + om * (avg - old)
                if new > one:
                    new = one
                u[y, x] = new
                d = abs(float(new) - float(old))
                if d > worst:
                    worst = d
        if worst < tol:
            return sweep + 1
    return max_sweeps


@njit(cache=True)
def _steepest_neighbour(psi, state, y, x):
    """(row, col) of the neighbour of (y, x), among 8, with the steepest strict ascent of ``psi``, or
    (-1, -1). Diagonal moves need both orthogonal cells passable (no corner cutting)."""
    pc = psi[y, x]
    best = 0.0
    by = -1
    bx = -1
    inv_sqrt2 = 1.0 / np.sqrt(2.0)
    for k in range(8):
        ny = y + _NB8[k, 0]
        nx = x + _NB8[k, 1]
        if state[ny, nx] == BLOCKED:
            continue
        scale = 1.0
        if k >= 4:
            if state[y, nx] == BLOCKED or state[ny, x] == BLOCKED:
                continue
            scale = inv_sqrt2
        slope = (psi[ny, nx] - pc) * scale
        if slope > best:
            best = slope
            by = ny
            bx = nx
    return by, bx


@njit(cache=True)
def descent_successor(psi, state):
    """Discrete steepest ascent of ``psi`` (= descent of the potential) among the 8 neighbours.

    Diagonal moves need both orthogonal cells passable (no corner cutting).  Returns (H, W) int64 flat
    index of the next cell; -1 for non-active cells and for cells with no strictly better neighbour
    (a spurious local optimum, or a flat field), -2 for target cells."""
    h, w = psi.shape
    nxt = np.full((h, w), -1, dtype=np.int64)
    for y in range(1, h - 1):
        for x in range(1, w - 1):
            st = state[y, x]
            if st == TARGET:
                nxt[y, x] = -2
                continue
            if st != ACTIVE:
                continue
            ny, nx = _steepest_neighbour(psi, state, y, x)
            nxt[y, x] = ny * w + nx if ny >= 0 else -1
    return nxt


@njit(cache=True)
def reaches_target(nxt):
    """For every cell, whether following ``nxt`` (from ``descent_successor``) ends on a target cell."""
    h, w = nxt.shape
    flat = nxt.ravel()
    n = flat.size
    # 0 unknown, 1 reaches, 2 fails, 3 on the current chain
    status = np.zeros(n, dtype=np.int8)
    chain = np.empty(n, dtype=np.int64)
    for start in range(n):
        if status[start] != 0:
            continue
        m = 0
        c = start
        result = 2
        while True:
            if status[c] == 1 or status[c] == 2:
                result = status[c]
                break
            if status[c] == 3:       # cycle: cannot happen with strict ascent, but never loop forever
                result = 2
                break
            nc = flat[c]
            if nc == -2:
                result = 1
                status[c] = 1
                break
            if nc == -1:
                result = 2
                status[c] = 2
                break
            status[c] = 3
            chain[m] = c
            m += 1
            c = nc
        for i in range(m):
            status[chain[i]] = result
    out = np.empty(n, dtype=np.bool_)
    for i in range(n):
        out[i] = status[i] == 1
    return out.reshape(h, w)


@njit(cache=True)
def descent_path(psi, state, y0, x0, max_steps):
    """Cells visited by discrete steepest ascent of ``psi`` from (y0, x0) until a target cell, a stuck cell
    or ``max_steps``.  Returns (K, 2) int64 (y, x)."""
    nxt = np.empty((max_steps + 1, 2), dtype=np.int64)
    y = y0
    x = x0
    k = 0
    nxt[0, 0] = y
    nxt[0, 1] = x
    while k < max_steps and state[y, x] == ACTIVE:
        by, bx = _steepest_neighbour(psi, state, y, x)
        if by < 0:
            break
        y = by
        x = bx
        k += 1
        nxt[k, 0] = y
        nxt[k, 1] = x
    return nxt[: k + 1].copy()


@njit(cache=True)
def extend_scale(s, known, state, step):
    """Give every ACTIVE cell that is not ``known`` a log scale: BFS outwards from the known (and target)
    cells, each step ``step`` lower than its parent.  Used for a cold start (only the target known) and
    for cells that a warm update newly connected.  Modifies ``s`` in place; returns the count filled."""
    h, w = s.shape
    qy = np.empty(h * w, dtype=np.int32)
    qx = np.empty(h * w, dtype=np.int32)
    done = np.zeros((h, w), dtype=np.bool_)
    tail = 0
    for y in range(h):
        for x in range(w):
            if state[y, x] == TARGET or (state[y, x] == ACTIVE and known[y, x]):
                done[y, x] = True
                qy[tail] = y
                qx[tail] = x
                tail += 1
    head = 0
    filled = 0
    while head < tail:
        y = qy[head]
        x = qx[head]
        head += 1
        for k in range(4):
            ny = y + (k == 2) - (k == 3)
            nx = x + (k == 0) - (k == 1)
            if state[ny, nx] == ACTIVE and not done[ny, nx]:
                done[ny, nx] = True
                s[ny, nx] = s[y, x] - step
                filled += 1
                qy[tail] = ny
                qx[tail] = nx
                tail += 1
    return filled


def usable_fraction(psi: np.ndarray, state: np.ndarray) -> float:
    """Share of ACTIVE cells from which discrete steepest ascent of ``psi`` reaches a TARGET cell
    (padded arrays).  1.0 for a correct harmonic field; a flat (underflowed) field scores low."""
    active = state == ACTIVE
    if not active.any():
        return float("nan")
    ok = reaches_target(descent_successor(psi, state))
    return float(ok[active].mean())


def plain_potential(state: np.ndarray, dtype=np.float64, omega: float = 1.9, max_sweeps: int = 100000,
                    tol: float = 0.0) -> np.ndarray:
    """The textbook harmonic potential u (1 on BLOCKED, 0 on TARGET) by SOR in ``dtype``, iterated until
    no cell changes by more than ``tol`` (0: until nothing changes at all in that precision).  Kept as the
    baseline that shows the underflow; returns the padded u."""
    u = np.where(state == TARGET, 0.0, 1.0).astype(dtype)
    plain_sor(u, state, omega, max_sweeps, tol)
    return u
