"""bench/pipeline.py's CPU budget: counted only while frames flow, a process that ends still counted."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))
from pipeline import cpu_while_flowing  # noqa: E402


def test_cpu_budget_skips_start_up_and_keeps_a_service_that_ended():
    # (monotonic s, frames seen, {pid: CPU s}): pid 1 spends 5 s of CPU starting up before any frame;
    # pid 2 (the replay) ends before the last frame arrives.
    snaps = [(0.0, 0, {1: 0.0, 2: 0.0}), (10.0, 1, {1: 5.0, 2: 0.1}), (11.0, 31, {1: 5.5, 2: 0.2}),
             (12.0, 61, {1: 6.0}), (13.0, 61, {1: 6.5})]
    pct, ms = cpu_while_flowing(snaps, {1: "evolver", 2: "replay"})
    assert pct == {"evolver": 50.0, "replay": 5.0, "total": 55.0}     # over the 2 s from 10 s to 12 s
    assert ms == {"evolver": 16.67, "replay": 1.67, "total": 18.33}   # over the 60 frames in between
    assert cpu_while_flowing(snaps[:1], {}) == (None, None)


def test_cpu_budget_counts_a_service_restarted_while_frames_flow():
    # pid 3 (a restarted localiser) appears at 11 s with 2 s of CPU already (its start-up); it counts
    # from then on, with the pid 4 it replaced.
    snaps = [(10.0, 1, {1: 5.0, 4: 1.0}), (11.0, 31, {1: 5.5, 3: 2.0}), (12.0, 61, {1: 6.0, 3: 2.5})]
    pct, _ = cpu_while_flowing(snaps, {1: "evolver", 3: "localiser", 4: "localiser"})
    assert pct == {"evolver": 50.0, "localiser": 25.0, "total": 75.0}
