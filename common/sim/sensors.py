"""Wheel odometry and sonar ring models, with the errors real ones have.

Odometry: the wheels turn by (ground distance / true radius) × (1 + slip); the encoders count that
rotation; the robot's own dead reckoning uses the *nominal* radius and track width.  So a nominal radius
2 % above the true one makes every odometry distance 2 % long, unequal radii make it curve, a wrong track
width scales turns, and slip (small random, plus occasional bursts on one wheel) adds random drift.

Sonar: each transducer casts a fan of rays across its beam against the 2-D obstacle segments at its
height; a ray hitting a surface more obliquely than the critical angle is reflected away (no echo, as
with smooth walls seen at a glancing angle); the reported range is the nearest echo, with noise, random
drop-outs, NaN when nothing answers within range.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.sim.scenario import OdometryConfig, SonarConfig


@dataclass
class OdometryReading:
    """One wheel-encoder sample. ``ticks`` are cumulative [left, right] counts; ``wheel_speeds`` are
    [left, right] rad/s over the last period; ``pose_xyyaw_integrated`` is the robot's own dead reckoning
    (x, y, yaw) in the odom frame, which starts at the robot's start pose as (0, 0, 0); ``wheel_radius``,
    ``track_width`` are the nominal values that dead reckoning uses."""
    stamp_ns: int
    ticks: np.ndarray
    wheel_speeds: np.ndarray
    pose_xyyaw_integrated: np.ndarray
    wheel_radius: float
    track_width: float
    ticks_per_rev: int


@dataclass
class SonarReading:
    """One sweep of the ring. ``transducer_poses`` (K, 3) are (x, y, yaw) in base_link; ``ranges`` (K,)
    metres, NaN = no echo; ``beam_width`` is the full cone angle in radians."""
    stamp_ns: int
    transducer_poses: np.ndarray
    ranges: np.ndarray
    beam_width: float
    min_range: float
    max_range: float


class WheelOdometry:
    """Turns true body motion into encoder ticks, wheel speeds and a dead-reckoned pose."""

    def __init__(self, cfg: OdometryConfig, rng: np.random.Generator):
        self.cfg = cfg
        self.rng = rng
        self.r_nominal = cfg.wheel_radius
        self.b_nominal = cfg.track_width
        self.r_true = np.array([cfg.wheel_radius / (1 + cfg.radius_error_left),
                                cfg.wheel_radius / (1 + cfg.radius_error_right)])
        self.b_true = cfg.track_width / (1 + cfg.track_error)
        self.angle = np.zeros(2)          # true wheel rotation, rad
        self._angle_at_sample = np.zeros(2)
        self._ticks_at_sample = np.zeros(2, np.int64)
        self._slip = np.zeros(2)
        self._burst_left_s = 0.0
        self._burst_wheel = 0
        self.pose = np.zeros(3)           # dead reckoning in the odom frame

    def _draw_slip(self, period_s: float):
        c = self.cfg
        self._slip = c.slip_sigma * self.rng.standard_normal(2)
        if self._burst_left_s <= 0 and c.burst_rate_hz > 0 and self.rng.random() < c.burst_rate_hz * period_s:
            self._burst_left_s = c.burst_duration_s
            self._burst_wheel = int(self.rng.integers(2))
        if self._burst_left_s > 0:
            self._slip[self._burst_wheel] += c.burst_slip
            self._burst_left_s -= period_s

    def move(self, vx: float, omega: float, dt: float):
        """Accumulate wheel rotation for dt seconds of body motion (forward speed vx, turn rate omega)."""
        ground = np.array([vx - omega * self.b_true / 2, vx + omega * self.b_true / 2]) * dt
        self.angle += ground / self.r_true * (1 + self._slip)

    def sample(self, stamp_ns: int, period_s: float) -> OdometryReading:
        c = self.cfg
        ticks = np.floor(self.angle / (2 * np.pi) * c.ticks_per_rev).astype(np.int64)
        dticks = ticks - self._ticks_at_sample
        speeds = (self.angle - self._angle_at_sample) / period_s + c.speed_noise * self.rng.standard_normal(2)
        self._angle_at_sample = self.angle.copy()
        self._ticks_at_sample = ticks
        # Dead reckoning with nominal parameters (midpoint rule).
        dl, dr = dticks * (2 * np.pi / c.ticks_per_rev) * self.r_nominal
        ds, dth = (dl + dr) / 2, (dr - dl) / self.b_nominal
        x, y, th = self.pose
        self.pose = np.array([x + ds * np.cos(th + dth / 2), y + ds * np.sin(th + dth / 2),
                              (th + dth + np.pi) % (2 * np.pi) - np.pi])
        self._draw_slip(period_s)
        return OdometryReading(int(stamp_ns), ticks.copy(), speeds, self.pose.copy(), self.r_nominal,
                               self.b_nominal, c.ticks_per_rev)


class SonarRing:
    """K transducers evenly spaced around a ring, pointing outwards (the first one straight ahead)."""

    def __init__(self, cfg: SonarConfig, rng: np.random.Generator):
        self.cfg = cfg
        self.rng = rng
        yaw = np.arange(cfg.count) * 2 * np.pi / cfg.count
        yaw = (yaw + np.pi) % (2 * np.pi) - np.pi
        self.poses = np.stack([cfg.ring_radius * np.cos(yaw), cfg.ring_radius * np.sin(yaw), yaw], 1)
        half = np.deg2rad(cfg.beam_width_deg) / 2
        self.ray_offsets = np.linspace(-half, half, cfg.rays) if cfg.rays > 1 else np.zeros(1)

    def measure(self, stamp_ns: int, base_pose, segments: np.ndarray) -> SonarReading:
        c = self.cfg
        ranges = self.true_ranges(base_pose, segments)
        finite = np.isfinite(ranges)
        r0 = np.where(finite, ranges, 0.0)
        noisy = np.where(finite, r0 + (c.noise_sigma + c.noise_rel * r0) * self.rng.standard_normal(len(ranges)),
                         np.nan)
        drop = self.rng.random(len(ranges)) < c.dropout
        noisy[drop | ~finite | ~(noisy <= c.max_range)] = np.nan
        noisy[np.isfinite(noisy)] = np.maximum(noisy[np.isfinite(noisy)], c.min_range)
        return SonarReading(int(stamp_ns), self.poses.copy(), noisy, np.deg2rad(c.beam_width_deg),
                            c.min_range, c.max_range)

    def true_ranges(self, base_pose, segments: np.ndarray) -> np.ndarray:
        """Noise-free nearest-echo range per transducer (inf when no echo), vectorised over rays×segments."""
        c = self.cfg
        x, y, yaw = base_pose
        cy, sy = np.cos(yaw), np.sin(yaw)
        ox = x + cy * self.poses[:, 0] - sy * self.poses[:, 1]
        oy = y + sy * self.poses[:, 0] + cy * self.poses[:, 1]
        ang = yaw + self.poses[:, 2][:, None] + self.ray_offsets[None, :]     # (K, R)
        dx, dy = np.cos(ang), np.sin(ang)
        if len(segments) == 0:
            return np.full(c.count, np.inf)
        a, b = segments[:, 0], segments[:, 1]                                  # (M, 2)
        ex, ey = (b - a)[:, 0], (b - a)[:, 1]
        # Solve o + t d = a + s e  for every (transducer, ray, segment).
        den = dx[..., None] * ey - dy[..., None] * ex                          # (K, R, M)
        wx = a[:, 0][None, None, :] - ox[:, None, None]
        wy = a[:, 1][None, None, :] - oy[:, None, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (wx * ey - wy * ex) / den
            s = (wx * dy[..., None] - wy * dx[..., None]) / den
        hit = (np.abs(den) > 1e-12) & (t > 0) & (s >= 0) & (s <= 1)
        # Incidence: angle between the ray and the segment normal; |sin| of ray-to-segment angle = |den|/|e|.
        seg_len = np.hypot(ex, ey)
        cos_inc = np.abs(den) / np.maximum(seg_len, 1e-12)                     # cos of angle to the normal
        echo = hit & (cos_inc >= np.cos(np.deg2rad(c.critical_angle_deg)))
        # A glancing surface in front still blocks the rays behind it: take the nearest hit per ray and
        # keep it only if it echoes.
        t_hit = np.where(hit, t, np.inf)
        nearest = np.argmin(t_hit, axis=2)
        t_near = np.take_along_axis(t_hit, nearest[..., None], 2)[..., 0]
        echoes = np.take_along_axis(echo, nearest[..., None], 2)[..., 0]
        r = np.where(echoes & (t_near <= c.max_range), t_near, np.inf).min(axis=1)
        return r
