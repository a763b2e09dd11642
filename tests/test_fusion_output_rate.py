"""Fusion's output pacing: at most --publish-hz on average, status changes at once, the last one never lost."""
from __future__ import annotations

import numpy as np

from common.fusion.output_rate import OutputRate

MS = 1_000_000
OK = ("ok", "ok")


def published(rate: OutputRate, stamps_ms, statuses=OK) -> list[float]:
    return [t for t in stamps_ms if rate.due(int(t * MS), statuses, now_s=0.0)]


def test_fifty_hertz_wheels_come_out_at_thirty_hertz_without_long_gaps():
    out = published(OutputRate(30.0), range(0, 10_000, 20))
    assert 298 <= len(out) <= 302
    assert max(np.diff(out)) <= 40          # never more than two readings' worth of staleness


def test_slower_readings_all_go_out_and_zero_means_every_reading():
    assert published(OutputRate(30.0), range(0, 2000, 100)) == list(range(0, 2000, 100))
    assert published(OutputRate(0.0), range(0, 200, 5)) == list(range(0, 200, 5))


def test_a_source_jittering_around_the_rate_is_not_halved():
    rng = np.random.default_rng(0)
    stamps = np.cumsum(1000 / 29.97 + rng.normal(0.0, 1.0, 3000))
    assert len(published(OutputRate(30.0), stamps)) >= 0.99 * len(stamps)


def test_no_burst_after_a_gap_and_a_restarted_source_is_published():
    rate = OutputRate(30.0)
    assert published(rate, [0, 500, 510, 520, 530, 540]) == [0, 500, 530]   # 530: within EARLY of 533
    assert rate.due(100 * MS, OK, 0.0)          # stamps went back: the source started over


def test_a_status_change_is_published_at_once_but_a_flagged_stretch_is_paced():
    rate = OutputRate(30.0)
    assert rate.due(0, OK, 0.0)
    assert not rate.due(10 * MS, OK, 0.0)
    assert rate.due(20 * MS, ("flagged: speed 41.3 rad/s", "flagged: speed 41.3 rad/s"), 0.0)
    assert rate.due(25 * MS, OK, 0.0)
    # 200 Hz readings, all flagged with a different measured number: still at most 30 a second
    flagged = [rate.due(int((100 + 5 * i) * MS), (f"flagged: speed {40 + i} rad/s",) * 2, 0.0) for i in range(200)]
    assert sum(flagged) <= 32


def test_a_held_output_goes_out_once_a_period_of_wall_time_passes():
    rate = OutputRate(30.0)
    assert rate.due(0, OK, now_s=100.0)
    assert not rate.due(20 * MS, OK, now_s=100.02)
    assert not rate.overdue(now_s=100.04)            # held 20 ms: a newer reading may still come
    assert rate.overdue(now_s=100.06)                # the readings stopped: publish the held one
    assert not rate.overdue(now_s=100.2)             # nothing held any more
    assert not rate.due(40 * MS, OK, now_s=100.2)    # paced from the flushed output's stamp
    assert rate.due(60 * MS, OK, now_s=100.22)
