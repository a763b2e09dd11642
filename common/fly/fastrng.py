"""A small random generator for numba kernels: splitmix64 on a one-word state array.

numba's own ``np.random`` fetches its per-thread state on every draw, which costs far more than the
arithmetic; the evolver's operators draw several numbers per child, so drawing cost about as much as
scoring. splitmix64 (Steele, Lea & Flood, 2014; the seeder of the xoshiro family) passes BigCrush, keeps
one 64-bit word and inlines to a few multiplies. Kernels take the state array, so a run seeded from the
evolver's numpy Generator stays reproducible.

Invariants: ``uniform`` is in [0, 1) with 53 random bits; ``below(s, n)`` is in [0, n) for 0 < n < 2³²
(multiply-shift: bias below n / 2³²); ``normal_pair`` is two independent standard normals, and ``normal`` serves them one at a time.
"""
from __future__ import annotations

import numba
import numpy as np

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11, _S32 = (np.uint64(k) for k in (30, 27, 31, 11, 32))


@numba.njit(cache=True)
def new_state(seed):
    """A generator state (one uint64 word) for the kernels below, from a non-negative int64 seed."""
    state = np.empty(1, np.uint64)
    state[0] = np.uint64(seed)
    return state


@numba.njit(cache=True)
def next_u64(state):
    """The next 64 random bits (state advances by one step)."""
    state[0] += _GOLDEN
    z = state[0]
    z = (z ^ (z >> _S30)) * _MIX1
    z = (z ^ (z >> _S27)) * _MIX2
    return z ^ (z >> _S31)


@numba.njit(cache=True)
def uniform(state):
    """A float64 uniform on [0, 1)."""
    return float(next_u64(state) >> _S11) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True)
def below(state, n):
    """An int64 uniform on [0, n), 0 < n < 2³²."""
    return np.int64(((next_u64(state) >> _S32) * np.uint64(n)) >> _S32)


@numba.njit(cache=True)
def normal_pair(state):
    """Two independent float64 standard normals (Marsaglia's polar method: one logarithm per pair)."""
    while True:
        x = 2.0 * uniform(state) - 1.0
        y = 2.0 * uniform(state) - 1.0
        s = x * x + y * y
        if 0.0 < s < 1.0:
            f = np.sqrt(-2.0 * np.log(s) / s)
            return x * f, y * f


@numba.njit(cache=True)
def normal(state, spare):
    """A float64 standard normal and the new ``spare``: a kernel keeps ``spare`` (start with NaN) between
    calls so that each polar pair serves two draws."""
    if spare == spare:                 # not NaN: the second half of the last pair
        return spare, np.nan
    z, spare = normal_pair(state)
    return z, spare

