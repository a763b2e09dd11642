"""When the evolver service publishes a new frame's population: anytime publication.

The pipeline's latency runs from a frame's stamp to the localiser's pose for that frame: the evolver's
work on the frame, then the localiser's registration of its population. A population moved by odometry
and re-scored on the new frame is already most of the answer, so :func:`settle` evolves it only until
its quality (:func:`population_quality`) is back to a fraction of what it was before the frame
(:class:`SettlePolicy`), within a time budget, and the service publishes it then instead of after a
fixed settle time.
"""
from __future__ import annotations

import time
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
    then until its quality is back to ``recovery`` × the previous frame's, at most ``budget_s`` seconds
    (``recovery`` > 1 is never reached in practice: the whole budget, as a fixed settle time)."""
    budget_s: float
    min_generations: int = 1
    recovery: float = 0.95

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
