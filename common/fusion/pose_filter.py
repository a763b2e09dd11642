"""Best current pose of base_link in map: a small planar EKF fed by odometry and the localiser's corrections.

Why an EKF and not a complementary filter: the localiser publishes a covariance with each pose and the
odometry covariance grows with distance, so the right blend changes all the time — right after a good
fix the odometry is trusted, after a long blind stretch the next fix should win almost entirely.  A
complementary filter has a fixed gain and would also leave consumers without a meaningful covariance;
the EKF weighs each correction by both covariances for the price of a few 3×3 products per message.

* State: planar pose (x, y, yaw) of base_link in map and its 3×3 covariance P.
* Predict: every accepted wheel increment is applied exactly as in the odom frame (``drive_step``), so
  between corrections the map pose moves rigidly with odometry (map→odom constant) and P grows.
* Update: a correction is a pose of base_link in map at the *camera* stamp t, which is in the past.  It
  is carried forward to now with the odometry motion since t (``z_now = z_t ⊕ (odom_t⁻¹ ⊕ odom_now)``,
  its covariance grown by the covariance of that relative motion, re-integrated from the wheel increments
  since t), then fused with H = I.
  ``slam/pose`` (PoseEstimate) brings its own covariance; ``slam/map_to_odom`` (TransformMsg, no
  covariance) is turned into ``T_map_odom ⊕ odom_t`` with a configured covariance.  When the localiser
  publishes both for one frame, the second (same stamp) is skipped so a fix is not counted twice.
* Gating: an innovation beyond the χ² gate, or one whose Mahalanobis² is not a number, is rejected
  (and reported); after ``max_rejections`` consecutive rejections that agree with each other (the
  map→odom each implies within the same gate) the filter re-initialises on the newest (the localiser
  relocalised: a long-lived, consistent disagreement means the filter is the one that is wrong; rejected
  fixes that disagree among themselves are noise and never take over).
* Before the first correction the map pose is the odom pose (map ≡ odom) and status 'odometry only'.
  The first correction is gated too, against that prior widened by ``prior_sigma`` (how far the map
  frame may start from odom), so a wild first fix cannot initialise the filter.
"""
from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass

import numpy as np

from common.fusion.planar import (between, compose, compose_jacobian_first, compose_jacobian_second, drive_step,
                                  interpolate, inverse)
from common.geometry import wrap_angle


def _mahalanobis2(nu, S) -> float:
    """νᵀ S⁻¹ ν of a planar innovation (yaw wrapped); NaN when S is singular or the numbers overflow."""
    nu = np.array(nu, float)
    nu[2] = float(wrap_angle(nu[2]))
    try:
        with np.errstate(all="ignore"):
            return float(nu @ np.linalg.solve(S, nu))
    except np.linalg.LinAlgError:
        return float("nan")


class CorrectionError(ValueError):
    """A correction that cannot be used (non-finite, bad covariance, unknown time)."""


@dataclass(frozen=True)
class FilterConfig:
    """``map_to_odom_sigma``: (σ_xy m, σ_yaw rad) assumed for a map→odom transform (it has no covariance).
    ``gate_chi2``: Mahalanobis² gate (16.27 = χ²(3) at 99.9 %). ``prior_sigma``: (σ_xy m, σ_yaw rad) of
    the map frame about odom before the first correction, added to the prior the first fix is gated
    against. ``stale_after_s``: 'ok' turns into
    'odometry only' when the last fused correction is older than this. ``history_s``: how far back a
    delayed correction may refer."""
    map_to_odom_sigma: tuple[float, float] = (0.05, 0.035)
    gate_chi2: float = 16.27
    max_rejections: int = 3
    prior_sigma: tuple[float, float] = (100.0, 3.1416)
    stale_after_s: float = 5.0
    history_s: float = 10.0
    min_variance: float = 1e-8


@dataclass
class CorrectionResult:
    accepted: bool
    reason: str = ""
    mahalanobis2: float = 0.0


class MapPoseFilter:
    """Planar EKF for base_link in map; see the module docstring."""

    def __init__(self, config: FilterConfig | None = None):
        self.config = config or FilterConfig()
        self.initialised = False
        self.pose = np.zeros(3)
        self.cov = np.zeros((3, 3))
        self.last_correction_ns: int | None = None
        self.rejections = 0
        self._stamps: deque[int] = deque()
        self._odom: deque[np.ndarray] = deque()
        self._increments: deque[tuple[float, float, float, float, float]] = deque()  # dl, dr, b, var_l, var_r
        self._fused_stamps: deque[int] = deque(maxlen=64)
        self._rejected: list[tuple[np.ndarray, np.ndarray]] = []   # implied map→odom and its covariance

    # ---------------------------------------------------------------------------- odometry side
    def predict(self, stamp_ns: int, odom_pose, odom_cov, dl: float, dr: float, track_width: float,
                var_left: float, var_right: float) -> None:
        """Apply one accepted wheel increment and remember the odom pose at ``stamp_ns``."""
        if self.initialised:
            self.pose, self.cov = drive_step(self.pose, self.cov, dl, dr, track_width, var_left, var_right)
        else:
            self.pose, self.cov = np.array(odom_pose, float), np.array(odom_cov, float)
        self.remember(stamp_ns, odom_pose, (dl, dr, track_width, var_left, var_right))

    def remember(self, stamp_ns: int, odom_pose, increment=(0.0, 0.0, 1.0, 0.0, 0.0)) -> None:
        """Record the odom pose at a stamp and the wheel increment that led to it (for carrying delayed
        corrections forward)."""
        if self._stamps and stamp_ns <= self._stamps[-1]:
            return
        self._stamps.append(int(stamp_ns))
        self._odom.append(np.array(odom_pose, float))
        self._increments.append(tuple(float(v) for v in increment))
        horizon = stamp_ns - int(self.config.history_s * 1e9)
        while len(self._stamps) > 2 and self._stamps[0] < horizon:
            self._stamps.popleft()
            self._odom.popleft()
            self._increments.popleft()

    def motion_since(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """Odometry motion from ``stamp_ns`` to now (odom_t⁻¹ ⊕ odom_now) and its covariance, re-integrated
        from the wheel increments recorded after ``stamp_ns`` (the heading uncertainty accumulated before t
        belongs to the correction's own covariance, not to this relative motion)."""
        odom_t = self.odom_at(stamp_ns)
        delta = between(odom_t, self._odom[-1])
        i = bisect.bisect_right(list(self._stamps), stamp_ns)
        rel, cov = np.zeros(3), np.zeros((3, 3))
        for dl, dr, b, vl, vr in list(self._increments)[i:]:
            rel, cov = drive_step(rel, cov, dl, dr, b, vl, vr)
        return delta, cov

    def odom_at(self, stamp_ns: int) -> np.ndarray:
        """Odom pose at a stamp (interpolated; the newest when the stamp is ahead)."""
        if not self._stamps:
            raise CorrectionError("no odometry yet to place the correction in time")
        stamps = self._stamps
        if stamp_ns >= stamps[-1]:
            return self._odom[-1]
        if stamp_ns < stamps[0]:
            raise CorrectionError(f"correction is {(stamps[-1] - stamp_ns) * 1e-9:.2f} s old, beyond the "
                                  f"{self.config.history_s:g} s of odometry history")
        i = bisect.bisect_right(list(stamps), stamp_ns)
        t0, t1 = stamps[i - 1], stamps[i]
        f = (stamp_ns - t0) / (t1 - t0)
        return interpolate(self._odom[i - 1], self._odom[i], f)

    # -------------------------------------------------------------------------- corrections
    def correct_pose(self, stamp_ns: int, pose, cov) -> CorrectionResult:
        """Fuse a measured planar pose of base_link in map at ``stamp_ns`` with its 3×3 covariance."""
        pose, cov = np.asarray(pose, float), np.asarray(cov, float)
        if pose.shape != (3,) or cov.shape != (3, 3) or not (np.all(np.isfinite(pose)) and np.all(np.isfinite(cov))):
            raise CorrectionError("correction pose/covariance must be finite (3,) and (3, 3)")
        if np.any(np.linalg.eigvalsh(0.5 * (cov + cov.T)) < -1e-12):
            raise CorrectionError("correction covariance is not positive semi-definite")
        if stamp_ns in self._fused_stamps:
            return CorrectionResult(False, "duplicate: a correction for this stamp was already fused")
        delta, delta_cov = self.motion_since(stamp_ns)
        z = compose(pose, delta)
        J1, J2 = compose_jacobian_first(pose, delta), compose_jacobian_second(pose)
        R = J1 @ cov @ J1.T + J2 @ delta_cov @ J2.T + self.config.min_variance * np.eye(3)
        prior_cov = self.cov
        if not self.initialised:
            sxy, syaw = self.config.prior_sigma
            prior_cov = self.cov + np.diag([sxy ** 2, sxy ** 2, syaw ** 2])
        S = prior_cov + R
        d2 = _mahalanobis2(z - self.pose, S)
        if not d2 <= self.config.gate_chi2:    # NaN is a rejection
            return self._reject(stamp_ns, z, R, d2)
        if not self.initialised:
            return self._reset(stamp_ns, z, R, "initialised")
        nu = z - self.pose
        nu[2] = float(wrap_angle(nu[2]))
        K = self.cov @ np.linalg.inv(S)
        IK = np.eye(3) - K
        self.pose = self.pose + K @ nu
        self.pose[2] = float(wrap_angle(self.pose[2]))
        self.cov = IK @ self.cov @ IK.T + K @ R @ K.T      # Joseph form: stays symmetric PSD
        self.cov = 0.5 * (self.cov + self.cov.T)
        self.rejections = 0
        self._rejected.clear()
        self._mark(stamp_ns)
        return CorrectionResult(True, "fused", d2)

    def _reject(self, stamp_ns: int, z, R, d2: float) -> CorrectionResult:
        """Count a gated-out correction; re-initialise on it when the last ``max_rejections`` agree."""
        m2o = compose(z, inverse(self._odom[-1]))
        self._rejected = [(a, c) for a, c in self._rejected if _mahalanobis2(m2o - a, R + c) <= self.config.gate_chi2]
        self._rejected.append((m2o, R))
        self.rejections = len(self._rejected)
        if self.rejections >= self.config.max_rejections:
            return self._reset(stamp_ns, z, R, f"re-initialised after {self.rejections} rejected corrections")
        return CorrectionResult(False, f"correction rejected (Mahalanobis² {d2:.1f} > {self.config.gate_chi2:g})", d2)

    def correct_map_to_odom(self, stamp_ns: int, map_to_odom) -> CorrectionResult:
        """Fuse a planar map→odom transform stated at ``stamp_ns`` (configured covariance)."""
        map_to_odom = np.asarray(map_to_odom, float)
        if map_to_odom.shape != (3,) or not np.all(np.isfinite(map_to_odom)):
            raise CorrectionError("map→odom must be a finite planar pose (x, y, yaw)")
        odom_t = self.odom_at(stamp_ns)
        sxy, syaw = self.config.map_to_odom_sigma
        return self.correct_pose(stamp_ns, compose(map_to_odom, odom_t), np.diag([sxy ** 2, sxy ** 2, syaw ** 2]))

    def _reset(self, stamp_ns: int, z, R, reason: str) -> CorrectionResult:
        self.pose, self.cov = np.array(z, float), np.array(R, float)
        self.initialised = True
        self.rejections = 0
        self._rejected.clear()
        self._mark(stamp_ns)
        return CorrectionResult(True, reason)

    def _mark(self, stamp_ns: int) -> None:
        self._fused_stamps.append(int(stamp_ns))
        if self.last_correction_ns is None or stamp_ns > self.last_correction_ns:
            self.last_correction_ns = int(stamp_ns)

    # ------------------------------------------------------------------------------- status
    def is_fresh(self, now_ns: int) -> bool:
        return (self.initialised and self.last_correction_ns is not None
                and now_ns - self.last_correction_ns <= self.config.stale_after_s * 1e9)

    def restore(self, pose, cov, initialised: bool) -> None:
        """Continue from a map pose recovered after a restart (its correction age is unknown: stale)."""
        self.pose, self.cov = np.array(pose, float), np.array(cov, float)
        self.initialised = bool(initialised)
        self.last_correction_ns = None
