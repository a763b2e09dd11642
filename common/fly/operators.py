"""Genetic operators and 2-D sharing of the Fly algorithm.

Flies are 3-D points, but mutation works in (u_left, v, disparity) — the coordinates in which stereo
uncertainty is isotropic-ish — so that a Gaussian step has the same meaning near and far.

All operators are one numba loop, ``make_offspring``, driven by random numbers drawn by the caller's numpy
Generator (so a seeded evolver is reproducible).  The small public wrappers (``mutate``, ``crossover2``,
``crossover3``, ``exchange_depth``) call that same loop, so what the tests check is what the evolver runs.
Inside the loops the draws come from the splitmix64 generator below, seeded at every call from the caller's
Generator (numba's global generator is left alone).
"""
from __future__ import annotations

import numba
import numpy as np

from common.camera import StereoCalibration

MUTATION, CROSSOVER2, CROSSOVER3, IMMIGRANT, EXCHANGE = 0, 1, 2, 3, 4


# ---------------------------------------------------------------------------- random numbers
# A splitmix64 generator (Steele, Lea & Flood 2014; the seeder of the xoshiro family: passes BigCrush)
# on a one-word state array, seeded per call from the caller's Generator.  numba's own np.random
# fetches its per-thread state on every draw, which made drawing cost as much as scoring.  It lives in
# this module, not its own: numba's cache checks only the caller's source file, so kernels cached here
# would keep an edited generator's old code.  ``uniform``: [0, 1), 53 bits; ``below(s, n)``: [0, n) for
# 0 < n < 2³² (multiply-shift, bias below n / 2³²); ``normal_pair``: two independent standard normals,
# which ``normal`` serves one at a time.
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11, _S32 = (np.uint64(k) for k in (30, 27, 31, 11, 32))


@numba.njit(cache=True, nogil=True)
def new_state(seed):
    """A generator state (one uint64 word) for the kernels below, from a non-negative int64 seed."""
    state = np.empty(1, np.uint64)
    state[0] = np.uint64(seed)
    return state


@numba.njit(cache=True, nogil=True)
def next_u64(state):
    """The next 64 random bits (state advances by one step)."""
    state[0] += _GOLDEN
    z = state[0]
    z = (z ^ (z >> _S30)) * _MIX1
    z = (z ^ (z >> _S27)) * _MIX2
    return z ^ (z >> _S31)


@numba.njit(cache=True, nogil=True)
def uniform(state):
    """A float64 uniform on [0, 1)."""
    return float(next_u64(state) >> _S11) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True, nogil=True)
def below(state, n):
    """An int64 uniform on [0, n), 0 < n < 2³²."""
    return np.int64(((next_u64(state) >> _S32) * np.uint64(n)) >> _S32)


@numba.njit(cache=True, nogil=True)
def normal_pair(state):
    """Two independent float64 standard normals (Marsaglia's polar method: one logarithm per pair)."""
    while True:
        x = 2.0 * uniform(state) - 1.0
        y = 2.0 * uniform(state) - 1.0
        s = x * x + y * y
        if 0.0 < s < 1.0:
            f = np.sqrt(-2.0 * np.log(s) / s)
            return x * f, y * f


@numba.njit(cache=True, nogil=True)
def normal(state, spare):
    """A float64 standard normal and the new ``spare``: a kernel keeps ``spare`` (start with NaN) between
    calls so that each polar pair serves two draws."""
    if spare == spare:                 # not NaN: the second half of the last pair
        return spare, np.nan
    z, spare = normal_pair(state)
    return z, spare


def camera_vector(calib: StereoCalibration) -> np.ndarray:
    """(fx, fy, cx_left, cy, fx·baseline, doffs) as float64, the projection constants the kernels need."""
    return np.array([calib.fx, calib.fy, calib.cx_left, calib.cy, calib.fx * calib.baseline, calib.doffs])


def project_uvd(calib: StereoCalibration, positions: np.ndarray):
    """(u_left, v, disparity) float32 arrays of (N, 3) points; NaN for points with z ≤ 0."""
    p = np.asarray(positions, dtype=np.float32)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        iz = np.where(z > 0, np.float32(1.0) / z, np.float32(np.nan))
        u = np.float32(calib.fx) * p[:, 0] * iz + np.float32(calib.cx_left)
        v = np.float32(calib.fy) * p[:, 1] * iz + np.float32(calib.cy)
        d = np.float32(calib.fx * calib.baseline) * iz - np.float32(calib.doffs)
    return u, v, d


def backproject_uvd(calib: StereoCalibration, u, v, d) -> np.ndarray:
    """(N, 3) float32 points from left pixel (u, v) and pixel disparity d (d + doffs must be > 0)."""
    with np.errstate(divide="ignore"):
        z = np.float32(calib.fx * calib.baseline) / (np.asarray(d, np.float32) + np.float32(calib.doffs))
    x = (np.asarray(u, np.float32) - np.float32(calib.cx_left)) * z / np.float32(calib.fx)
    y = (np.asarray(v, np.float32) - np.float32(calib.cy)) * z / np.float32(calib.fy)
    return np.stack([x, y, z], axis=1).astype(np.float32, copy=False)


@numba.njit(cache=True, nogil=True)
def _uvd(x, y, z, cam):
    iz = 1.0 / z
    return cam[0] * x * iz + cam[2], cam[1] * y * iz + cam[3], cam[4] * iz - cam[5]


@numba.njit(cache=True, nogil=True)
def _to_point(u, v, d, cam, out, i):
    z = cam[4] / (d + cam[5])
    out[i, 0] = (u - cam[2]) * z / cam[0]
    out[i, 1] = (v - cam[3]) * z / cam[1]
    out[i, 2] = z


@numba.njit(cache=True, nogil=True)
def _mate_at(p, n, reach, r):
    """Neighbour ``r`` (in [0, 2·reach)) of ``p`` in the cell-ordered population: ±1…±reach places."""
    off = r - reach if r < reach else r - reach + 1
    m = p + off
    if m < 0 or m >= n:
        m = p - off
    return min(max(m, 0), n - 1)


@numba.njit(cache=True, nogil=True)
def _local_mate(p, n, reach, rng):
    """A random neighbour of ``p`` in the cell-ordered population: ±1…±reach places."""
    return _mate_at(p, n, reach, below(rng, 2 * reach))


@numba.njit(cache=True, nogil=True)
def _mate_bits(reach, extra):
    """Bits per mate when ``extra`` uniform mates among 2·reach can share one ≤62-bit draw (2·reach a
    power of two), else 0."""
    b = 1
    while (1 << b) < 2 * reach:
        b += 1
    return b if (1 << b) == 2 * reach and b * extra <= 62 else 0


@numba.njit(cache=True, nogil=True)
def _fittest_local_mate(p, m1, n, reach, best_of, bits, fit, rng):
    """The fittest of ``m1`` and ``best_of`` − 1 more random neighbours of ``p``.  With ``bits`` > 0
    (see _mate_bits) the extra neighbours come from the bit fields of one draw: the same distribution as
    one draw each, at a fraction of the cost (this is most of what the exchange operator spends)."""
    if bits > 0 and best_of > 1:
        word = np.int64(next_u64(rng) >> np.uint64(2))     # 62 random bits
        mask = (1 << bits) - 1
        best = fit[m1]
        for j in range(best_of - 1):
            q = _mate_at(p, n, reach, (word >> (bits * j)) & mask)
            fq = fit[q]
            better = fq > best         # selects, not branches: the comparisons are coin flips
            m1 = q if better else m1
            best = fq if better else best
        return m1
    for _ in range(best_of - 1):
        q = _local_mate(p, n, reach, rng)
        if fit[q] > fit[m1]:
            m1 = q
    return m1


@numba.njit(cache=True, nogil=True)
def plan_batch(cum_rates, shared, tournament_size, pool, own_for_local, seed, ops, parents):
    """Operators and parents of one batch, written into ``ops`` and ``parents`` sorted by parent.

    Operator i is drawn with the cumulative probabilities ``cum_rates`` (indexed by operator code).  Its
    parent is fly i itself for mutation and exchange when ``own_for_local`` (deterministic crowding over a
    whole-population batch), else the fittest by ``shared`` of ``tournament_size`` random flies, or with
    ``tournament_size`` 0 a uniform draw from ``pool`` (elitist selection).  The sort (a stable counting
    sort) puts children next to their parents' image neighbours: the batch is evaluated in image order."""
    rng = new_state(seed)
    m, n = ops.shape[0], shared.shape[0]
    raw_ops = np.empty(m, np.int64)
    raw_parents = np.empty(m, np.int64)
    counts = np.zeros(n + 1, np.int64)
    for i in range(m):
        r = uniform(rng)
        op = 0
        while op < cum_rates.shape[0] - 1 and r >= cum_rates[op]:
            op += 1
        if own_for_local and (op == MUTATION or op == EXCHANGE):
            p = i
        elif tournament_size > 0:
            p = below(rng, n)
            for _ in range(tournament_size - 1):
                q = below(rng, n)
                if shared[q] > shared[p]:
                    p = q
        else:
            p = pool[below(rng, pool.shape[0])]
        raw_ops[i] = op
        raw_parents[i] = p
        counts[p + 1] += 1
    for j in range(n):
        counts[j + 1] += counts[j]
    for i in range(m):
        k = counts[raw_parents[i]]
        counts[raw_parents[i]] += 1
        ops[k] = raw_ops[i]
        parents[k] = raw_parents[i]


@numba.njit(cache=True, nogil=True)
def make_offspring(ops, parents, mates1, mates2, pos, fit, parent_sigma, immigrants, cam, sigma_px, d_lo,
                   d_hi, exchange_sigma, immigrant_sigma, mate_reach, exchange_best_of, seed, out_child,
                   out_sigma):
    """One child per entry of ``ops`` (operator codes above).

    * MUTATION: parent's (u, v) + N(0, sigma_px²) each, disparity + N(0, parent_sigma²), clipped to
      [d_lo, d_hi];
    * EXCHANGE: parent's pixel with the mate's disparity (+ N(0, exchange_sigma²)) — uniform crossover of
      the (u, v | d) genes, which spreads a found surface along the image; the mate is the fittest of
      ``exchange_best_of`` local mates;
    * CROSSOVER2: λ·parent + (1−λ)·mate, λ ~ U(0, 1) — on the parents' segment;
    * CROSSOVER3: barycentric weights uniform on the simplex (normalised exponentials) — in the
      parents' triangle, hence their plane;
    * IMMIGRANT: the next row of ``immigrants`` (drawn like the initialisation).
    With ``mate_reach`` > 0 mates are drawn among population neighbours (±mate_reach places), else they
    are ``mates1``/``mates2``.  Random numbers come from the splitmix64 generator above, seeded with ``seed``.
    """
    rng = new_state(seed)
    spare = np.nan
    n = pos.shape[0]
    k = 0
    bits = _mate_bits(mate_reach, exchange_best_of - 1) if mate_reach > 0 else 0
    for i in range(ops.shape[0]):
        p = parents[i]
        op = ops[i]
        out_sigma[i] = parent_sigma[i]
        m1 = 0
        m2 = 0
        if op != MUTATION and op != IMMIGRANT:
            if mate_reach > 0:
                m1 = _local_mate(p, n, mate_reach, rng)
                if op == CROSSOVER3:
                    m2 = _local_mate(p, n, mate_reach, rng)
            else:
                m1 = mates1[i]
                m2 = mates2[i]
        if op == MUTATION or op == EXCHANGE:
            u, v, d = _uvd(pos[p, 0], pos[p, 1], pos[p, 2], cam)
            if op == MUTATION:
                gu, spare = normal(rng, spare)
                gv, spare = normal(rng, spare)
                gd, spare = normal(rng, spare)
                u += gu * sigma_px
                v += gv * sigma_px
                d += gd * parent_sigma[i]
            else:
                if mate_reach > 0:
                    m1 = _fittest_local_mate(p, m1, n, mate_reach, exchange_best_of, bits, fit, rng)
                _, _, d = _uvd(pos[m1, 0], pos[m1, 1], pos[m1, 2], cam)
                gd, spare = normal(rng, spare)
                d += gd * exchange_sigma
            d = min(max(d, d_lo), d_hi)
            _to_point(u, v, d, cam, out_child, i)
        elif op == CROSSOVER2:
            lam = uniform(rng)
            for a in range(3):
                out_child[i, a] = lam * pos[p, a] + (1.0 - lam) * pos[m1, a]
        elif op == CROSSOVER3:
            e0 = -np.log(1.0 - uniform(rng))
            e1 = -np.log(1.0 - uniform(rng))
            e2 = -np.log(1.0 - uniform(rng))
            s = e0 + e1 + e2
            if not s > 0.0:
                e0, e1, e2, s = 1.0, 1.0, 1.0, 3.0
            for a in range(3):
                out_child[i, a] = (e0 * pos[p, a] + e1 * pos[m1, a] + e2 * pos[m2, a]) / s
        else:  # IMMIGRANT
            for a in range(3):
                out_child[i, a] = immigrants[k, a]
            k += 1
            out_sigma[i] = immigrant_sigma


def _run(ops, pos, parents, mates1, mates2, parent_sigma, rng, calib=None, sigma_px=0.0,
         d_range=(-1e9, 1e9), exchange_sigma=0.0):
    m = len(ops)
    child = np.empty((m, 3), np.float32)
    sigma = np.empty(m, np.float32)
    cam = camera_vector(calib) if calib is not None else np.ones(6)
    pos = np.ascontiguousarray(pos, np.float32)
    make_offspring(np.asarray(ops, np.int64), np.asarray(parents, np.int64), np.asarray(mates1, np.int64),
                   np.asarray(mates2, np.int64), pos, np.zeros(len(pos), np.float32),
                   np.asarray(parent_sigma, np.float32), np.zeros((0, 3), np.float32), cam, float(sigma_px),
                   float(d_range[0]), float(d_range[1]), float(exchange_sigma), 0.0, 0, 1,
                   int(rng.integers(2 ** 62)), child, sigma)
    return child


def mutate(calib: StereoCalibration, positions: np.ndarray, sigma_px: float, sigma_d: np.ndarray,
           d_range: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """Gaussian mutation of each point: left pixel ± N(0, sigma_px²) per axis, disparity ± N(0, sigma_d²)
    (per point), disparity clipped to ``d_range``.  Returns new (N, 3) float32 points."""
    n = len(positions)
    idx = np.arange(n)
    return _run(np.full(n, MUTATION), positions, idx, idx, idx, np.broadcast_to(sigma_d, (n,)), rng, calib,
                sigma_px, d_range)


def exchange_depth(calib: StereoCalibration, parents: np.ndarray, mates: np.ndarray, rng: np.random.Generator,
                   sigma: float = 0.0) -> np.ndarray:
    """Children at each parent's left pixel with the corresponding mate's disparity (+ N(0, sigma²))."""
    n = len(parents)
    pos = np.concatenate([parents, mates]).astype(np.float32)
    idx = np.arange(n)
    return _run(np.full(n, EXCHANGE), pos, idx, idx + n, idx + n, np.zeros(n), rng, calib, 0.0,
                exchange_sigma=sigma)


def crossover2(p1: np.ndarray, p2: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Barycentric 2-parent crossover: λ·p1 + (1 − λ)·p2, λ ~ U(0, 1) — children on the parents' segment
    (so a population on a straight edge fills it in)."""
    n = len(p1)
    idx = np.arange(n)
    return _run(np.full(n, CROSSOVER2), np.concatenate([p1, p2]), idx, idx + n, idx + n, np.zeros(n), rng)


def crossover3(p1: np.ndarray, p2: np.ndarray, p3: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Barycentric 3-parent crossover with weights uniform on the simplex — children in the parents'
    triangle, hence in their plane (a population on a planar surface fills it in)."""
    n = len(p1)
    idx = np.arange(n)
    return _run(np.full(n, CROSSOVER3), np.concatenate([p1, p2, p3]), idx, idx + n, idx + 2 * n, np.zeros(n),
                rng)


@numba.njit(cache=True, nogil=True)
def _shared(f, count, expected, strength):
    factor = 1.0 + strength * max(0.0, count / expected - 1.0)
    return f / factor if f > 0 else f * factor


@numba.njit(cache=True, nogil=True)
def insert_offspring(ops, parents, n_candidates, seed, child, child_sigma, child_fit, pos, fit, sigma_d,
                     cells, counts, expected, strength, cell_px, cols, rows, cam, crowding, adaptive, step_up,
                     step_down, sigma_min, sigma_max):
    """Steady-state insertion, one child at a time (sharing counts kept exact as flies move).

    The victim is the parent for mutation and exchange children when ``crowding`` (deterministic
    crowding), else the worst (by shared fitness) of ``n_candidates`` random flies (reverse tournament,
    the splitmix64 generator above, seeded with ``seed``).
    A child replaces its victim when its shared fitness is at least the victim's; immigrants always do.
    With ``adaptive``, a mutation that wins multiplies its step by ``step_up`` and one that loses
    multiplies its parent's by ``step_down`` (a per-fly success rule).  Returns the number inserted.
    """
    rng = new_state(seed)
    n = pos.shape[0]
    inserted = 0
    for i in range(ops.shape[0]):
        op = ops[i]
        x, y, z = child[i, 0], child[i, 1], child[i, 2]
        cc = -1
        if z > 0:
            u, v, _ = _uvd(x, y, z, cam)
            cu = np.floor(u / cell_px)
            cv = np.floor(v / cell_px)
            if 0 <= cu < cols and 0 <= cv < rows:
                cc = int(cv) * cols + int(cu)
        local = crowding and (op == MUTATION or op == EXCHANGE)
        if local:
            victim = parents[i]
        else:
            victim = 0
            best = np.inf
            for _ in range(n_candidates):
                c = below(rng, n)
                s = _shared(fit[c], counts[cells[c]] if cells[c] >= 0 else 0, expected, strength)
                if s < best:
                    best = s
                    victim = c
        fc = child_fit[i]
        vc = cells[victim]
        if op == IMMIGRANT:
            accept = True
        elif not np.isfinite(fc):
            accept = False
        else:
            extra = 1 if cc != vc else 0
            cs = _shared(fc, counts[cc] + extra if cc >= 0 else 0, expected, strength)
            vs = _shared(fit[victim], counts[vc] if vc >= 0 else 0, expected, strength)
            accept = cs >= vs
        s_new = child_sigma[i]
        if adaptive and local and op == MUTATION:
            if accept:
                s_new = min(s_new * step_up, sigma_max)
            else:
                p = parents[i]
                sigma_d[p] = max(sigma_d[p] * step_down, sigma_min)
        if accept:
            if vc >= 0:
                counts[vc] -= 1
            if cc >= 0:
                counts[cc] += 1
            pos[victim, 0] = x
            pos[victim, 1] = y
            pos[victim, 2] = z
            fit[victim] = fc
            sigma_d[victim] = s_new
            cells[victim] = cc
            inserted += 1
    return inserted


@numba.njit(cache=True, nogil=True)
def cell_order(cells, n_cells):
    """Order of flies by sharing cell, flies outside the image (cell −1) last, ties in index order: a
    counting sort, O(N + cells)."""
    start = np.zeros(n_cells + 2, np.int64)
    for c in cells:
        start[(c if c >= 0 else n_cells) + 1] += 1
    for j in range(n_cells + 1):
        start[j + 1] += start[j]
    order = np.empty(cells.shape[0], np.int64)
    for i in range(cells.shape[0]):
        c = cells[i] if cells[i] >= 0 else n_cells
        order[start[c]] = i
        start[c] += 1
    return order


@numba.njit(cache=True, nogil=True)
def permuted(order, pos, fit, sigma, cells):
    """(pos, fit, sigma, cells) rearranged by ``order`` in one pass (numpy's four fancy-index copies
    cost several times more, once per generation)."""
    n = order.shape[0]
    pos2 = np.empty((n, 3), pos.dtype)
    fit2 = np.empty(n, fit.dtype)
    sigma2 = np.empty(n, sigma.dtype)
    cells2 = np.empty(n, cells.dtype)
    for k in range(n):
        i = order[k]
        pos2[k, 0] = pos[i, 0]
        pos2[k, 1] = pos[i, 1]
        pos2[k, 2] = pos[i, 2]
        fit2[k] = fit[i]
        sigma2[k] = sigma[i]
        cells2[k] = cells[i]
    return pos2, fit2, sigma2, cells2


class SharingGrid:
    """2-D fitness sharing over square cells of the left image.

    A fly in a cell holding ``count`` flies where ``expected`` would be the even share has its fitness
    divided by ``1 + strength · max(0, count/expected − 1)`` (negative fitness is multiplied instead), so
    crowded image areas lose selection pressure and flies spread over the whole image.
    """

    def __init__(self, width: int, height: int, cell_px: float, strength: float):
        if not cell_px > 0:
            raise ValueError(f"sharing cell size must be positive, got {cell_px}")
        self.cell = float(cell_px)
        self.cols = int(np.ceil(width / self.cell))
        self.rows = int(np.ceil(height / self.cell))
        self.strength = float(strength)
        self.counts = np.zeros(self.cols * self.rows, np.int64)
        self.expected = 1.0

    def cells(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Cell index per fly; −1 for flies outside the image (or NaN)."""
        with np.errstate(invalid="ignore"):
            cu = np.floor(np.asarray(u, np.float64) / self.cell)
            cv = np.floor(np.asarray(v, np.float64) / self.cell)
            ok = (cu >= 0) & (cu < self.cols) & (cv >= 0) & (cv < self.rows)
        idx = np.full(len(cu), -1, np.int64)
        idx[ok] = cv[ok].astype(np.int64) * self.cols + cu[ok].astype(np.int64)
        return idx

    def update(self, cells: np.ndarray) -> None:
        inside = cells[cells >= 0]
        self.counts = np.bincount(inside, minlength=self.cols * self.rows).astype(np.int64)
        self.expected = max(len(inside) / (self.cols * self.rows), 1e-9)

    def factor(self, cells: np.ndarray, extra: np.ndarray | int = 0) -> np.ndarray:
        """Crowding divisor (≥ 1) of flies in ``cells`` (with ``extra`` flies added to their count)."""
        c = np.where(cells >= 0, self.counts[np.maximum(cells, 0)] + extra, 0)
        return (1.0 + self.strength * np.maximum(0.0, c / self.expected - 1.0)).astype(np.float32)

    @staticmethod
    def apply(fitness: np.ndarray, factor: np.ndarray) -> np.ndarray:
        f = np.asarray(fitness, np.float32)
        return np.where(f > 0, f / factor, f * factor).astype(np.float32, copy=False)
