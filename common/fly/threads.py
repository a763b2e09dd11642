"""Choosing, at run time, between the all-cores and the calling-thread fitness kernel.

On a small machine shared with other busy processes a parallel region can stall for a scheduler time
slice waiting for a descheduled worker, so the parallel kernel may be twice as fast as the serial one
(idle machine) or several times slower (loaded machine), and the situation changes by the second.
``KernelChooser`` keeps an exponentially weighted cost per fly of each kernel, uses the cheaper one, and
tries the other every ``explore_every`` calls so it notices when the load changes.
"""
from __future__ import annotations

import time


class KernelChooser:
    def __init__(self, explore_every: int = 16, smoothing: float = 0.3):
        if explore_every < 2 or not 0 < smoothing <= 1:
            raise ValueError(f"explore_every must be ≥ 2 and smoothing in (0, 1], got {explore_every}, {smoothing}")
        self.explore_every = int(explore_every)
        self.smoothing = float(smoothing)
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
        """Call ``fn(parallel)`` with the chosen kernel, time it and learn; returns fn's result."""
        parallel = self.choose()
        t0 = time.perf_counter()
        out = fn(parallel)
        self.record(parallel, time.perf_counter() - t0, n)
        return out
