"""How often fusion publishes: at most ``hz`` outputs a second on average, decided on the readings' stamps.

Wheel encoders may report at 50–200 Hz, but nothing downstream needs the odometry that often: the evolver
and the localiser look poses up at camera stamps (interpolating, or extrapolating at constant velocity),
the planner steers at 10 Hz. Every output costs each subscriber a delivery, so fusion publishes at a fixed
rate, as robot_localization's ``frequency`` does (30 Hz by default there too).

Invariants: outputs come at most ``hz`` a second on average (one period of credit, no burst after a gap;
a stamp up to ``EARLY`` of a period ahead of its slot counts as on time, so a source jittering around the
rate is not halved), plus one at each change of status kind (``ok``, ``odometry only``, ``flagged``...,
the text before any ':'), so a reading that starts or ends a flagged stretch always goes out; the
held-back newest output is published by :meth:`OutputRate.overdue` once a period of wall time has passed
without a newer one, so the final pose of a robot that stops reporting reaches the bus.
"""
from __future__ import annotations

EARLY = 0.1     # fraction of a period a stamp may come before its slot and still be on time


class OutputRate:
    """Publish-or-hold decisions for one output stream; ``hz <= 0`` publishes every reading."""

    def __init__(self, hz: float):
        self.period_ns = int(1e9 / hz) if hz > 0 else 0
        self._next_ns: int | None = None          # stamp from which the next output is due
        self._last_stamp: int | None = None
        self._last_kind: tuple[str, ...] | None = None
        self._held_since: float | None = None     # wall time (s) of the oldest output held back, if any

    def due(self, stamp_ns: int, statuses: tuple[str, ...], now_s: float) -> bool:
        """Whether the output stamped ``stamp_ns`` with these ``statuses`` (one per stream it holds) is to
        be published now."""
        kind = tuple(status.split(":", 1)[0] for status in statuses)
        changed = kind != self._last_kind
        self._last_kind = kind
        restarted = self._last_stamp is not None and stamp_ns < self._last_stamp   # a source started over
        self._last_stamp = stamp_ns
        if self.period_ns == 0 or changed or restarted or self._next_ns is None:
            self._next_ns = stamp_ns + self.period_ns     # out of schedule: pace the next ones from here
        elif stamp_ns >= self._next_ns - EARLY * self.period_ns:
            self._next_ns += self.period_ns               # on schedule: what is left of the period carries over
            if self._next_ns <= stamp_ns:                 # after a gap: no burst to catch up
                self._next_ns = stamp_ns + self.period_ns
        else:
            if self._held_since is None:
                self._held_since = now_s
            return False
        self._held_since = None
        return True

    def overdue(self, now_s: float) -> bool:
        """True once the newest output has been held back for a period of wall time: publish it (the
        readings stopped or slowed down); the next ones are then paced from its stamp."""
        if self._held_since is None or now_s - self._held_since < self.period_ns * 1e-9:
            return False
        self._held_since = None
        self._next_ns = self._last_stamp + self.period_ns
        return True
