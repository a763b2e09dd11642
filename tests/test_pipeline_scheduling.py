"""The evolver's anytime publication: a new frame's population is published once it is good enough."""
from __future__ import annotations

import numpy as np
import pytest

from common.fly.scheduling import SettlePolicy, population_quality, settle


class RisingEvolver:
    """Stands in for FlyEvolver: each generation raises every fly's fitness by ``gain``."""

    def __init__(self, start: float, gain: float, n: int = 100):
        self.fitness = np.full(n, start, np.float32)
        self.gain = gain
        self.generations = 0

    def step(self, n: int = 1) -> None:
        self.fitness = self.fitness + np.float32(self.gain * n)
        self.generations += n


class FakeClock:
    """Advances by ``tick`` seconds per reading, so a budget is spent after a known number of readings."""

    def __init__(self, tick: float):
        self.t, self.tick = 0.0, tick

    def __call__(self) -> float:
        self.t += self.tick
        return self.t


def test_population_quality_counts_flies_outside_the_images_as_zero():
    assert population_quality(np.array([0.4, 0.2, -np.inf, -np.inf], np.float32)) == pytest.approx(0.15)
    assert population_quality(np.zeros(0, np.float32)) == 0.0


def test_settle_publishes_as_soon_as_quality_has_recovered():
    ev = RisingEvolver(start=0.035, gain=0.005)
    policy = SettlePolicy(budget_s=10.0, min_generations=1, recovery=0.95)
    # 0.95 × 0.05 = 0.0475 is reached after 3 generations (0.040, 0.045, 0.050).
    assert settle(ev, reference=0.05, policy=policy) == 3
    assert ev.generations == 3


def test_settle_runs_at_least_min_generations_even_when_already_good():
    ev = RisingEvolver(start=0.06, gain=0.001)
    assert settle(ev, 0.05, SettlePolicy(budget_s=10.0, min_generations=2, recovery=0.95)) == 2
    assert settle(RisingEvolver(0.06, 0.001), 0.05, SettlePolicy(budget_s=10.0, min_generations=0)) == 0


def test_settle_stops_at_its_budget_when_quality_does_not_recover():
    ev = RisingEvolver(start=0.01, gain=0.0)
    # Each clock reading advances 10 ms: a 45 ms budget allows a few generations, never more.
    n = settle(ev, 0.05, SettlePolicy(budget_s=0.045, min_generations=1, recovery=0.95), clock=FakeClock(0.010))
    assert 1 <= n <= 5


def test_settle_without_reference_uses_the_whole_budget():
    n_none = settle(RisingEvolver(0.5, 0.01), None, SettlePolicy(budget_s=0.1, recovery=0.5), clock=FakeClock(0.01))
    n_ref = settle(RisingEvolver(0.5, 0.01), 0.05, SettlePolicy(budget_s=0.1, recovery=0.5), clock=FakeClock(0.01))
    assert n_ref == 1 and n_none >= 8


def test_settle_policy_rejects_nonsense():
    with pytest.raises(ValueError, match="recovery"):
        SettlePolicy(budget_s=0.02, recovery=-0.1)
    with pytest.raises(ValueError, match="budget"):
        SettlePolicy(budget_s=float("nan"))
