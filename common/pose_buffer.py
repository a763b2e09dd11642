"""A short history of timestamped poses, interpolated at arbitrary stamps.

Sensors run at their own rates: the evolver needs the odometry pose at a camera frame's stamp, the
localiser the fused pose at a population's stamp. :class:`PoseBuffer` keeps the last poses and
interpolates (translation linearly, rotation along the geodesic).
"""
from __future__ import annotations

import bisect
from collections import deque

import numpy as np

from common.geometry import invert, scaled_motion, so3_exp, so3_log


class PoseBuffer:
    """Poses by stamp. Outside the held span, within ``max_extrapolation_ns``, the nearest end is
    returned, or with ``extrapolate=True`` the newest pose moved on at the velocity of the last two
    (a constant-velocity prediction: what visual odometry, which only knows past frames, can offer)."""

    def __init__(self, maxlen: int = 500, max_extrapolation_ns: int = 200_000_000, extrapolate: bool = False):
        self._stamps: deque[int] = deque(maxlen=maxlen)
        self._poses: deque[np.ndarray] = deque(maxlen=maxlen)
        self.max_extrapolation_ns = max_extrapolation_ns
        self.extrapolate = extrapolate

    def __len__(self) -> int:
        return len(self._stamps)

    def add(self, stamp_ns: int, T: np.ndarray) -> bool:
        """Append a pose; refuses (returns False) a stamp older than the newest or a non-finite pose."""
        T = np.asarray(T, dtype=float)
        if not np.all(np.isfinite(T)) or (self._stamps and stamp_ns < self._stamps[-1]):
            return False
        if self._stamps and stamp_ns == self._stamps[-1]:
            self._poses[-1] = T
            return True
        self._stamps.append(int(stamp_ns))
        self._poses.append(T)
        return True

    def latest(self) -> tuple[int, np.ndarray] | None:
        return (self._stamps[-1], self._poses[-1]) if self._stamps else None

    def at(self, stamp_ns: int) -> np.ndarray | None:
        """Pose at ``stamp_ns``; the nearest end when slightly outside; None when too far outside."""
        if not self._stamps:
            return None
        stamps = self._stamps
        if stamp_ns <= stamps[0]:
            return self._poses[0].copy() if stamps[0] - stamp_ns <= self.max_extrapolation_ns else None
        if stamp_ns >= stamps[-1]:
            if stamp_ns - stamps[-1] > self.max_extrapolation_ns:
                return None
            if not self.extrapolate or len(stamps) < 2 or stamp_ns == stamps[-1]:
                return self._poses[-1].copy()
            # The velocity over a span at least half as long as the extrapolation: two readings a
            # millisecond apart would multiply their noise a hundredfold over a frame period.
            ahead = stamp_ns - stamps[-1]
            j = bisect.bisect_right(stamps, stamps[-1] - ahead // 2) - 1
            if j < 0 or stamps[j] == stamps[-1]:
                return self._poses[-1].copy()
            T0, T1 = self._poses[j], self._poses[-1]
            return T1 @ scaled_motion(invert(T0) @ T1, ahead / (stamps[-1] - stamps[j]))
        i = bisect.bisect_right(stamps, stamp_ns)
        t0, t1 = stamps[i - 1], stamps[i]
        a = (stamp_ns - t0) / (t1 - t0)
        T0, T1 = self._poses[i - 1], self._poses[i]
        T = np.eye(4)
        T[:3, 3] = (1 - a) * T0[:3, 3] + a * T1[:3, 3]
        T[:3, :3] = T0[:3, :3] @ so3_exp(a * so3_log(T0[:3, :3].T @ T1[:3, :3]))
        return T

