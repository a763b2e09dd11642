"""The evolver's choice of fitness kernel: small batches never enter a parallel region."""
from common.fly.threads import PARALLEL_MIN_FLIES, KernelChooser


def test_small_batches_run_serially_and_large_ones_try_both_kernels():
    ch = KernelChooser(explore_every=4)
    calls = []
    for _ in range(20):
        ch.run(lambda parallel: calls.append(parallel), PARALLEL_MIN_FLIES - 1)
    assert calls == [False] * 20, "a 5,000-fly generation must not wake numba's worker threads"
    assert ch.cost == {True: None, False: None}, "untimed: one noisy call would steer the large batches"
    calls.clear()
    for _ in range(8):
        ch.run(lambda parallel: calls.append(parallel), PARALLEL_MIN_FLIES)
    assert True in calls and False in calls
