"""When the evolver service publishes a new frame's population: anytime publication.

The pipeline's latency runs from a frame's stamp to the localiser's pose for that frame: the evolver's
work on the frame, then the localiser's registration of its population. A population moved by odometry
and re-scored on the new frame is already most of the answer, so :func:`settle` evolves it only until
its quality (:func:`population_quality`) is back to a fraction of what it was before the frame
(:class:`SettlePolicy`), within a time budget, and the service publishes it then instead of after a
fixed settle time. :class:`CpuGovernor` decides how much the evolver may spend and notices when the machine
does not give it the CPU it asks for (the pipeline then runs degraded).
"""
from __future__ import annotations

import os
import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np


def population_quality(fitness: np.ndarray) -> float:
    """Mean fitness with flies outside the images (−inf) counted as 0: how well the population as a whole
    sits on visible surfaces, comparable from one frame to the next."""
    f = np.asarray(fitness, np.float32)
    return float(np.where(np.isfinite(f), f, 0.0).mean()) if f.size else 0.0


@dataclass(frozen=True)
class SettlePolicy:
    """How long a new frame's population evolves before it is published: at least ``min_generations``,
    then until its quality is back to ``recovery`` × the reference (recent frames' best), at most ``budget_s`` seconds
    (``recovery`` > 1 is never reached in practice: the whole budget, as a fixed settle time)."""
    budget_s: float
    min_generations: int = 1
    recovery: float = 0.9

    def __post_init__(self):
        if not self.budget_s >= 0 or self.min_generations < 0 or not 0 <= self.recovery <= 2:
            raise ValueError(f"settle budget ≥ 0 s, min_generations ≥ 0 and recovery in [0, 2] expected, "
                             f"got {self.budget_s}, {self.min_generations}, {self.recovery}")

    def good_enough(self, generations: int, quality: float, reference: float | None) -> bool:
        if generations < self.min_generations:
            return False
        return reference is not None and reference > 0 and quality >= self.recovery * reference


def settle(evolver, reference: float | None, policy: SettlePolicy, clock=time.monotonic) -> int:
    """Evolve the freshly re-scored population of ``evolver`` (a :class:`common.fly.FlyEvolver`) until
    ``policy`` says it is good enough or its time budget is spent (a generation is never cut short);
    returns the number of generations run. With no reference (first frame, new calibration) the whole
    budget is used."""
    deadline = clock() + policy.budget_s
    generations = 0
    while not policy.good_enough(generations, population_quality(evolver.fitness), reference):
        if generations >= policy.min_generations and clock() >= deadline:
            break
        evolver.step(1)
        generations += 1
    return generations


try:
    _CLOCK_TICKS = float(os.sysconf("SC_CLK_TCK"))
except (AttributeError, ValueError, OSError):
    _CLOCK_TICKS = 100.0


def machine_idle_seconds() -> float | None:
    """CPU-seconds the whole machine has been idle since boot, summed over its cores (Linux /proc/stat:
    idle + iowait), or None where that is not available."""
    try:
        with open("/proc/stat") as fh:
            fields = fh.readline().split()
        return (int(fields[4]) + int(fields[5])) / _CLOCK_TICKS
    except (OSError, ValueError, IndexError):
        return None


class CpuGovernor:
    """How much of a core the evolver gets and may spend: the basis of graceful degradation.

    ``work()`` wraps every busy stretch of the evolver's thread (a frame, a generation between frames)
    and records its CPU time (``thread_clock``) and wall time. From them:

    * ``share``: CPU / wall time of recent work (exponentially smoothed), ≈ 1 when the evolver gets the
      core it asks for, ~0.5 when another busy process shares that core.
    * ``free``: the machine's idle CPU over the last ``window_s`` (in cores, from ``idle_clock``: the
      machine's cumulative idle CPU-seconds, or None where unknown).
    * ``degraded``: the machine is overloaded — the evolver's share is under ``degraded_below`` *and*
      less than ``free_floor`` of a core is idle. A low share alone is not overload: on a busy 2-core
      machine with idle time left, a thread often waits a moment for a core (where the idle time is
      unknown, the share alone decides). It clears (hysteresis, so it does not flicker) once the share
      is above ``recovered_above`` or twice ``free_floor`` is idle.
    * ``spent``: the CPU time of the last ``window_s`` seconds, in fractions of one core.
      ``optional_allowed()`` — evolving between frames, which only polishes the population — is true
      while ``spent`` is under ``budget`` and the machine is not overloaded: the frames' own work always
      runs, the extra work gives way first.
    * ``settle_scale()``: the factor on a frame's settle budget, ``share`` when degraded (the settle's
      wall budget buys that much less CPU, and shortening it hands the CPU to the localiser), else 1.
    """

    def __init__(self, budget: float = 0.35, degraded_below: float = 0.6, recovered_above: float = 0.75,
                 free_floor: float = 0.1, window_s: float = 1.0, smoothing: float = 0.1,
                 thread_clock=time.thread_time, clock=time.monotonic, idle_clock=machine_idle_seconds):
        if not 0 <= budget <= 1 or not 0 < degraded_below <= recovered_above <= 1 or window_s <= 0 \
                or not 0 < smoothing <= 1 or free_floor < 0:
            raise ValueError(f"budget in [0, 1], 0 < degraded_below <= recovered_above <= 1, free_floor >= 0, "
                             f"window_s > 0 and smoothing in (0, 1] expected, got {budget}, {degraded_below}, "
                             f"{recovered_above}, {free_floor}, {window_s}, {smoothing}")
        self.budget, self.degraded_below, self.recovered_above = budget, degraded_below, recovered_above
        self.free_floor, self.window_s, self.smoothing = free_floor, window_s, smoothing
        self._thread_clock, self._clock, self._idle_clock = thread_clock, clock, idle_clock
        self.share = 1.0
        self.free: float | None = None
        self.degraded = False
        self._recent: list[tuple[float, float]] = []    # (end time, CPU s) of the window's busy stretches
        self._idle_samples: list[tuple[float, float]] = []   # (time, machine idle CPU-s), one per 0.1 s at most

    @contextmanager
    def work(self):
        """Account the enclosed busy stretch (CPU and wall time of this thread)."""
        wall0, cpu0 = self._clock(), self._thread_clock()
        try:
            yield
        finally:
            self.record(self._thread_clock() - cpu0, self._clock() - wall0)

    def record(self, cpu_s: float, wall_s: float) -> None:
        now = self._clock()
        self._recent.append((now, cpu_s))
        self._forget(now)
        self._sample_idle(now)
        if wall_s > 1e-4:     # a stretch too short to time says nothing about the share
            # Weighted by duration: a long stretch says more about the machine than a short one.
            a = min(0.3, self.smoothing * wall_s / 0.002)
            self.share += a * (min(cpu_s / wall_s, 1.0) - self.share)
        idle_left = self.free is not None and self.free >= self.free_floor   # unknown: the share decides
        if self.degraded and (self.share > self.recovered_above
                              or (self.free is not None and self.free >= 2 * self.free_floor)):
            self.degraded = False
        elif not self.degraded and self.share < self.degraded_below and not idle_left:
            self.degraded = True

    def _sample_idle(self, now: float) -> None:
        """Machine idle cores over the window (``free``), from samples at most 0.1 s apart."""
        if self._idle_clock is None or (self._idle_samples and now - self._idle_samples[-1][0] < 0.1):
            return
        idle = self._idle_clock()
        if idle is None:      # no longer readable: unknown from now on (a stale ``free`` would never degrade)
            self._idle_clock, self.free = None, None
            return
        self._idle_samples.append((now, idle))
        while len(self._idle_samples) > 2 and now - self._idle_samples[1][0] >= self.window_s:
            self._idle_samples.pop(0)
        (t0, i0), (t1, i1) = self._idle_samples[0], self._idle_samples[-1]
        if t1 - t0 >= 0.5 * self.window_s:
            self.free = max(0.0, (i1 - i0) / (t1 - t0))

    def _forget(self, now: float) -> None:
        cut = now - self.window_s
        while self._recent and self._recent[0][0] < cut:
            self._recent.pop(0)

    @property
    def spent(self) -> float:
        """CPU time of the last ``window_s`` seconds, as a fraction of one core."""
        self._forget(self._clock())
        return sum(c for _, c in self._recent) / self.window_s

    def optional_allowed(self) -> bool:
        return not self.degraded and self.spent < self.budget

    def settle_scale(self) -> float:
        return max(self.share, 0.25) if self.degraded else 1.0
