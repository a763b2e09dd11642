"""The evolver's anytime publication: a new frame's population is published once it is good enough; and its
CPU governor: it evolves between frames within its CPU budget, and runs degraded when starved of CPU."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from common.fly.scheduling import (
    CpuGovernor,
    SettlePolicy,
    machine_idle_seconds,
    population_quality,
    settle,
)


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


class Machine:
    """Wall and thread-CPU clocks of a thread that gets ``share`` of a core while it works."""

    def __init__(self):
        self.wall, self.cpu, self.share = 0.0, 0.0, 1.0
        self.idle_cpu, self.idle_cores = 0.0, 0.0     # the whole machine's idle CPU-seconds, and its rate

    def work(self, governor: CpuGovernor, wall_s: float) -> None:
        with governor.work():
            self.advance(wall_s)
            self.cpu += wall_s * self.share

    def idle(self, wall_s: float) -> None:
        self.advance(wall_s)

    def advance(self, wall_s: float) -> None:
        self.wall += wall_s
        self.idle_cpu += wall_s * self.idle_cores


def _governor(machine: Machine, budget: float = 0.3, knows_idle: bool = False) -> CpuGovernor:
    return CpuGovernor(budget=budget, degraded_below=0.6, recovered_above=0.75, free_floor=0.1,
                       thread_clock=lambda: machine.cpu, clock=lambda: machine.wall,
                       idle_clock=(lambda: machine.idle_cpu) if knows_idle else None)


def test_evolution_between_frames_stops_once_the_cpu_budget_of_the_last_second_is_spent():
    machine = Machine()
    governor = _governor(machine, budget=0.3)
    for _ in range(45):                     # 30 frames/s, 10 ms of work each: 0.3 of a core
        machine.work(governor, 0.010)
        machine.idle(1 / 30 - 0.010)
    assert 0.27 <= governor.spent <= 0.33
    machine.work(governor, 0.050)
    assert not governor.optional_allowed()
    machine.idle(1.5)                       # the window has moved past all of that work
    assert governor.spent == 0.0 and governor.optional_allowed()
    assert not governor.degraded and governor.settle_scale() == 1.0


def test_a_starved_evolver_runs_degraded_with_shorter_settles_and_recovers_with_hysteresis():
    machine = Machine()
    governor = _governor(machine, budget=1.0)
    machine.share = 0.4                     # another busy process on its core
    for _ in range(40):
        machine.work(governor, 0.010)
    assert governor.degraded and not governor.optional_allowed()
    assert governor.settle_scale() == pytest.approx(0.4, abs=0.05)
    machine.share = 0.7                     # between the two thresholds: still degraded
    for _ in range(40):
        machine.work(governor, 0.010)
    assert governor.degraded
    machine.share = 1.0
    for _ in range(40):
        machine.work(governor, 0.010)
    assert not governor.degraded and governor.settle_scale() == 1.0 and governor.optional_allowed()


def test_a_low_share_on_a_machine_with_idle_cpu_is_not_overload():
    machine = Machine()
    governor = _governor(machine, budget=1.0, knows_idle=True)
    machine.share, machine.idle_cores = 0.6 * 0.9, 0.5   # waits for a core now and then; half a core idle
    for _ in range(200):
        machine.work(governor, 0.010)
    assert governor.free == pytest.approx(0.5) and governor.share < 0.6
    assert not governor.degraded and governor.optional_allowed() and governor.settle_scale() == 1.0
    machine.idle_cores = 0.0                               # a busy process takes the idle core too
    for _ in range(200):
        machine.work(governor, 0.010)
    assert governor.degraded and not governor.optional_allowed()
    machine.idle_cores = 0.15                              # between the floor and twice it: still degraded
    for _ in range(200):
        machine.work(governor, 0.010)
    assert governor.degraded
    machine.idle_cores = 0.3                               # the busy process has gone
    for _ in range(200):
        machine.work(governor, 0.010)
    assert not governor.degraded and governor.optional_allowed()


def test_idle_time_that_stops_being_readable_leaves_the_share_to_decide():
    machine = Machine()
    readable = [True]
    governor = CpuGovernor(budget=1.0, degraded_below=0.6, recovered_above=0.75, free_floor=0.1,
                           thread_clock=lambda: machine.cpu, clock=lambda: machine.wall,
                           idle_clock=lambda: machine.idle_cpu if readable[0] else None)
    machine.share, machine.idle_cores = 0.4, 0.5
    for _ in range(200):
        machine.work(governor, 0.010)
    assert governor.free == pytest.approx(0.5) and not governor.degraded
    readable[0] = False                      # /proc/stat unreadable from now on (e.g. out of file handles)
    for _ in range(200):
        machine.work(governor, 0.010)
    assert governor.free is None and governor.degraded


def test_the_machine_idle_time_is_read_where_the_system_gives_it():
    idle = machine_idle_seconds()
    if not Path("/proc/stat").exists():
        assert idle is None
        return
    time.sleep(0.05)
    assert idle is not None and machine_idle_seconds() >= idle >= 0


def test_one_slow_start_up_frame_does_not_decide_the_state_alone():
    machine = Machine()
    governor = _governor(machine)
    machine.share = 0.05                    # e.g. the first frame loads the compiled kernels from disk
    machine.work(governor, 0.5)
    assert not governor.degraded


def test_cpu_governor_rejects_nonsense():
    with pytest.raises(ValueError):
        CpuGovernor(budget=1.5)
    with pytest.raises(ValueError):
        CpuGovernor(degraded_below=0.8, recovered_above=0.7)
