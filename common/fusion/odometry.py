"""Differential-drive dead reckoning with a growing covariance and a plausibility check on every reading.

:class:`WheelIntegrator` turns WheelOdometry readings (``common.messages.WheelOdometry``: cumulative encoder
ticks and/or wheel speeds in rad/s, wheel radius, track width) into the pose of base_link in odom.

* Ticks are preferred when present (cumulative counts lose nothing when a reading is dropped: the next
  good one covers the interval); otherwise wheel speeds × the time since the previous reading.
* Each wheel's travel d gets the variance ``k_wheel · |d|`` (errors grow with distance, not time), and
  :func:`common.fusion.planar.drive_step` propagates it: driving straight, x grows linearly while y grows
  faster and faster through the growing heading uncertainty; turning on the spot grows mostly yaw.
* A reading is *flagged* — reported with a reason, counted by the caller, and never integrated — when a
  value is NaN/inf, time does not move forward, no usable wheel data or geometry is present, a wheel
  speed is impossible (a jump in the ticks or a spike in the speeds), or a speeds-only gap is too long to
  integrate blindly.
* Resynchronisation: a flagged reading (with finite values) is kept as a candidate baseline.  If the next
  reading is implausible from the old baseline but plausible from the candidate (an encoder counter
  reset, a source whose clock restarted), the integrator adopts the candidate and carries on instead of
  flagging forever; the interval between the two baselines is lost and the result says so.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.fusion.planar import drive_step


class OdometryConfigError(ValueError):
    """An odometry model parameter that cannot be right (negative variance, zero limits...)."""


@dataclass(frozen=True)
class OdometryModel:
    """Robot geometry fallbacks, error model and plausibility limits.

    ``wheel_radius_m``/``track_width_m`` are used when a reading carries 0 for them.  ``k_wheel_m``:
    variance of a wheel's travel per metre travelled (m²/m; 2.5e-4 ≈ 1.6 cm σ after 1 m).  A wheel turning
    faster than ``max_wheel_speed_radps`` is a jump.  Speeds-only readings more than ``max_gap_s`` after
    the previous one are not integrated (nobody knows what the wheels did meanwhile)."""
    wheel_radius_m: float = 0.0
    track_width_m: float = 0.0
    k_wheel_m: float = 2.5e-4
    max_wheel_speed_radps: float = 60.0
    max_gap_s: float = 0.5

    def __post_init__(self):
        for name in ("wheel_radius_m", "track_width_m", "k_wheel_m"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise OdometryConfigError(f"{name} must be finite and >= 0, got {v}")
        for name in ("max_wheel_speed_radps", "max_gap_s"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise OdometryConfigError(f"{name} must be finite and > 0, got {v}")


@dataclass
class OdometryStep:
    """What one reading did. ``flag`` is None for an accepted reading, else the reason it was dropped;
    ``dl``/``dr`` are the wheel travels integrated (0 when flagged or when it only set a baseline);
    ``note`` explains accepted-but-special readings ('baseline', 'resynchronised: ...')."""
    stamp_ns: int
    flag: str | None
    kind: str = ""          # 'non_finite', 'time_backwards', 'jump', 'gap', 'no_data', 'no_geometry'
    dl: float = 0.0
    dr: float = 0.0
    track_width: float = 0.0
    note: str = ""

    @property
    def ok(self) -> bool:
        return self.flag is None


@dataclass
class _Baseline:
    stamp_ns: int
    ticks: np.ndarray | None


class WheelIntegrator:
    """Pose of base_link in odom (x, y, yaw) and its 3×3 covariance, integrated from wheel readings."""

    def __init__(self, model: OdometryModel | None = None):
        self.model = model or OdometryModel()
        self.pose = np.zeros(3)
        self.cov = np.zeros((3, 3))
        self.stamp_ns: int | None = None      # stamp of the last accepted reading
        self._base: _Baseline | None = None
        self._candidate: _Baseline | None = None

    # ------------------------------------------------------------------------------ restart
    def restore(self, pose, cov, stamp_ns: int) -> None:
        """Continue from a pose recovered after a restart. The next reading only sets the baseline (the
        motion while the service was down is unknown); readings older than ``stamp_ns`` are flagged."""
        pose, cov = np.asarray(pose, float), np.asarray(cov, float)
        if pose.shape != (3,) or cov.shape != (3, 3) or not (np.all(np.isfinite(pose)) and np.all(np.isfinite(cov))):
            raise OdometryConfigError("restore needs a finite (3,) pose and (3, 3) covariance")
        self.pose, self.cov, self.stamp_ns = pose.copy(), cov.copy(), int(stamp_ns)
        self._base = None
        self._candidate = None

    # ------------------------------------------------------------------------------- readings
    def _geometry(self, msg) -> tuple[float, float]:
        r = msg.wheel_radius_m if msg.wheel_radius_m > 0 else self.model.wheel_radius_m
        b = msg.track_width_m if msg.track_width_m > 0 else self.model.track_width_m
        return float(r), float(b)

    def _travel(self, msg, base: _Baseline, stamp: int, r: float):
        """(dl, dr, None, kind) from ``base`` to this reading, or (0, 0, reason, kind) when implausible."""
        if stamp <= base.stamp_ns:
            what = "repeated" if stamp == base.stamp_ns else "went backwards"
            return 0.0, 0.0, f"time {what} ({(stamp - base.stamp_ns) * 1e-6:+.1f} ms)", "time_backwards"
        dt = (stamp - base.stamp_ns) * 1e-9
        limit = self.model.max_wheel_speed_radps
        use_ticks = msg.ticks is not None and msg.ticks_per_rev > 0
        if use_ticks:
            if base.ticks is None:
                return 0.0, 0.0, None, "baseline"
            angle = (msg.ticks - base.ticks).astype(float) * (2 * np.pi / msg.ticks_per_rev)
            speed = np.abs(angle) / dt
        else:
            if dt > self.model.max_gap_s:
                return 0.0, 0.0, f"gap of {dt:.2f} s in wheel speeds (limit {self.model.max_gap_s:g} s)", "gap"
            speed = np.abs(msg.wheel_speeds)
            angle = np.asarray(msg.wheel_speeds, float) * dt
        if np.any(speed > limit):
            return 0.0, 0.0, (f"impossible wheel speed {float(speed.max()):.1f} rad/s "
                              f"(limit {limit:g}){' from ticks' if use_ticks else ''}"), "jump"
        return float(angle[0] * r), float(angle[1] * r), None, ""

    def update(self, msg) -> OdometryStep:
        """Integrate one WheelOdometry reading (or flag it). Never raises on bad data."""
        stamp = int(msg.header.stamp_ns)
        values = [v for v in (msg.wheel_speeds, msg.ticks, msg.ticks_per_rev, msg.wheel_radius_m,
                              msg.track_width_m) if v is not None]
        if not all(np.all(np.isfinite(np.asarray(v, float))) for v in values):
            return OdometryStep(stamp, "non-finite value in the wheel reading", "non_finite")
        has_ticks = msg.ticks is not None and msg.ticks_per_rev > 0
        if not has_ticks and msg.wheel_speeds is None:
            return OdometryStep(stamp, "no wheel speeds and no usable ticks", "no_data")
        r, b = self._geometry(msg)
        if r <= 0 or b <= 0:
            return OdometryStep(stamp, "unknown wheel radius or track width (0 in the reading and the model)",
                                "no_geometry")
        here = _Baseline(stamp, np.array(msg.ticks, np.int64) if has_ticks else None)
        if self._base is None:
            if self.stamp_ns is not None and stamp <= self.stamp_ns:
                return OdometryStep(stamp, f"time went backwards ({(stamp - self.stamp_ns) * 1e-6:+.1f} ms "
                                           "before the restored pose)", "time_backwards")
            self._base, self.stamp_ns = here, stamp
            return OdometryStep(stamp, None, note="baseline", track_width=b)
        dl, dr, reason, kind = self._travel(msg, self._base, stamp, r)
        note = ""
        if reason is not None and self._candidate is not None:
            cdl, cdr, creason, _ = self._travel(msg, self._candidate, stamp, r)
            if creason is None:
                note = f"resynchronised after: {reason}"
                dl, dr, reason, kind = cdl, cdr, None, ""
        if reason is not None:
            self._candidate = here
            return OdometryStep(stamp, reason, kind)
        self._candidate = None
        self._base = here
        self.stamp_ns = stamp
        if kind == "baseline":
            return OdometryStep(stamp, None, note="baseline", track_width=b)
        k = self.model.k_wheel_m
        self.pose, self.cov = drive_step(self.pose, self.cov, dl, dr, b, k * abs(dl), k * abs(dr))
        return OdometryStep(stamp, None, dl=dl, dr=dr, track_width=b, note=note)
