"""Choosing, at run time, between the all-cores and the calling-thread fitness kernel.

On a small machine shared with other busy processes a parallel region can stall for a scheduler time
slice waiting for a descheduled worker, so the parallel kernel may be twice as fast as the serial one
(idle machine) or several times slower (loaded machine), and the situation changes by the second.
``KernelChooser`` keeps an exponentially weighted cost per fly of each kernel, uses the cheaper one, and
tries the other every ``explore_every`` calls so it notices when the load changes.

Batches under ``min_parallel_flies`` (default ``PARALLEL_MIN_FLIES``) always run serially and are not
timed: the kernel is about a fifth of a steady-state generation, so at 5,000 flies two cores save at most
~0.15 ms of ~1.7 ms, while one stalled or slow-to-wake worker (a busy core, a virtual machine's idle
vCPU) costs milliseconds; a single measured call is also too noisy to steer by.  With no parallel
region entered, numba never starts its worker threads.
"""
from __future__ import annotations

import time

PARALLEL_MIN_FLIES = 50_000


class KernelChooser:
    def __init__(self, explore_every: int = 16, smoothing: float = 0.3, min_parallel_flies: int = PARALLEL_MIN_FLIES):
        if explore_every < 2 or not 0 < smoothing <= 1 or min_parallel_flies < 1:
            raise ValueError(f"explore_every must be ≥ 2, smoothing in (0, 1] and min_parallel_flies ≥ 1, got "
                             f"{explore_every}, {smoothing}, {min_parallel_flies}")
        self.explore_every = int(explore_every)
        self.smoothing = float(smoothing)
        self.min_parallel_flies = int(min_parallel_flies)
        self.cost = {True: None, False: None}   # seconds per fly, per kernel (True = parallel)
        self.calls = 0

    def choose(self) -> bool:
        """True for the parallel kernel, False for the serial one."""
        self.calls += 1
        par, ser = self.cost[True], self.cost[False]
        if par is None or ser is None:
            return par is None           # measure each kernel once first
        best = par <= ser
        return (not best) if self.calls % self.explore_every == 0 else best

    def record(self, parallel: bool, seconds: float, n: int) -> None:
        per = seconds / max(n, 1)
        old = self.cost[parallel]
        self.cost[parallel] = per if old is None else old + self.smoothing * (per - old)

    def run(self, fn, n: int):
        """Call ``fn(parallel)`` with the chosen kernel, time it and learn; returns fn's result.
        Batches of fewer than ``min_parallel_flies`` run serially, untimed."""
        if n < self.min_parallel_flies:
            return fn(False)
        parallel = self.choose()
        t0 = time.perf_counter()
        out = fn(parallel)
        self.record(parallel, time.perf_counter() - t0, n)
        return out
