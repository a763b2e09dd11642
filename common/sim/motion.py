"""Robot motion: scripted paths (waypoints, trolley poses, velocity profiles) and external commands.

Each motion source advances a planar pose (x, y, yaw) by a time step and reports the body-frame velocity
(vx forward, vy left, omega) it used, which the wheel-odometry model turns into wheel rotations.  A
differential-drive robot has vy = 0; the trolley of the paper is pushed by hand, so its moves may
translate sideways (vy ≠ 0) — wheel odometry cannot see that, as on the real rig.
"""
from __future__ import annotations

import numpy as np

from common.geometry import wrap_angle
from common.sim.scenario import PathConfig

ARRIVE_M = 1e-3
ALIGN_RAD = np.deg2rad(0.2)


def integrate_unicycle(x: float, y: float, yaw: float, v: float, omega: float, dt: float):
    """Exact pose after moving at constant forward speed v and turn rate omega for dt seconds."""
    if abs(omega) < 1e-9:
        return x + v * dt * np.cos(yaw), y + v * dt * np.sin(yaw), yaw
    yaw2 = yaw + omega * dt
    r = v / omega
    return x + r * (np.sin(yaw2) - np.sin(yaw)), y - r * (np.cos(yaw2) - np.cos(yaw)), float(wrap_angle(yaw2))


class CommandMotion:
    """Follows the last (v, omega) command (closed loop with a planner)."""
    finished = False

    def __init__(self, v: float = 0.0, omega: float = 0.0):
        self.v, self.omega = float(v), float(omega)

    def step(self, pose, dt):
        x, y, yaw = integrate_unicycle(*pose, self.v, self.omega, dt)
        return (x, y, yaw), (self.v, 0.0, self.omega)


class WaypointMotion:
    """Diff-drive turn-then-drive through waypoints: rotate in place to face the next point, drive to it."""

    def __init__(self, waypoints, speed: float, turn_rate: float):
        self.points = [tuple(map(float, w)) for w in waypoints]
        self.speed, self.turn_rate = float(speed), float(turn_rate)
        self.index = 0

    @property
    def finished(self) -> bool:
        return self.index >= len(self.points)

    def step(self, pose, dt):
        x, y, yaw = pose
        while not self.finished:
            gx, gy = self.points[self.index]
            dist = np.hypot(gx - x, gy - y)
            if dist < ARRIVE_M:
                self.index += 1
                continue
            err = float(wrap_angle(np.arctan2(gy - y, gx - x) - yaw))
            if abs(err) > ALIGN_RAD and dist > 0.02:
                omega = np.clip(err / dt, -self.turn_rate, self.turn_rate)
                nx, ny, nyaw = integrate_unicycle(x, y, yaw, 0.0, omega, dt)
                return (nx, ny, nyaw), (0.0, 0.0, omega)
            v = min(self.speed, dist / dt)
            # Small heading correction while driving keeps the arrival point exact.
            omega = np.clip(err / max(dist / max(v, 1e-9), dt), -self.turn_rate, self.turn_rate)
            nx, ny, nyaw = integrate_unicycle(x, y, yaw, v, omega, dt)
            return (nx, ny, nyaw), (v, 0.0, omega)
        return (x, y, yaw), (0.0, 0.0, 0.0)


class PoseSequenceMotion:
    """Trolley moves: straight-line interpolation of x, y and yaw between poses (all at once), each
    move lasting long enough for both the speed and turn-rate limits, with a pause after each move."""

    def __init__(self, start, poses, speed: float, turn_rate: float, pause_s: float):
        pts = [tuple(start)] + [(p[0], p[1], np.deg2rad(p[2])) for p in poses]
        self.knots_t, self.knots = [0.0], [np.array(pts[0], float)]
        t = 0.0
        for a, b in zip(pts[:-1], pts[1:]):
            a, b = np.array(a, float), np.array(b, float)
            dyaw = float(wrap_angle(b[2] - a[2]))
            dur = max(np.hypot(*(b[:2] - a[:2])) / speed, abs(dyaw) / turn_rate, 1e-3)
            t += dur
            self.knots_t.append(t)
            self.knots.append(np.array([b[0], b[1], self.knots[-1][2] + dyaw]))  # unwrapped yaw
            t += pause_s
            self.knots_t.append(t)
            self.knots.append(self.knots[-1].copy())
        self.knots_t = np.array(self.knots_t)
        self.knots = np.array(self.knots)
        self.t = 0.0

    @property
    def finished(self) -> bool:
        return self.t >= self.knots_t[-1] - 1e-9

    def pose_at(self, t: float) -> np.ndarray:
        return np.array([np.interp(t, self.knots_t, self.knots[:, k]) for k in range(3)])

    def step(self, pose, dt):
        p0 = self.pose_at(self.t)
        self.t += dt
        p1 = self.pose_at(self.t)
        dxy = p1[:2] - p0[:2]
        yaw_mid = 0.5 * (p0[2] + p1[2])
        c, s = np.cos(yaw_mid), np.sin(yaw_mid)
        vx, vy = (c * dxy[0] + s * dxy[1]) / dt, (-s * dxy[0] + c * dxy[1]) / dt
        return (float(p1[0]), float(p1[1]), float(wrap_angle(p1[2]))), (vx, vy, (p1[2] - p0[2]) / dt)


class VelocityProfileMotion:
    """A list of (duration_s, v, omega) segments, integrated exactly."""

    def __init__(self, segments):
        self.ends = np.cumsum([s[0] for s in segments])
        self.segments = [(float(v), float(w)) for _, v, w in segments]
        self.t = 0.0

    @property
    def finished(self) -> bool:
        return self.t >= self.ends[-1] - 1e-12

    def step(self, pose, dt):
        x, y, yaw = pose
        remaining = dt
        v_avg = w_avg = 0.0
        while remaining > 1e-12 and not self.finished:
            k = int(np.searchsorted(self.ends, self.t + 1e-12, side="right"))
            h = min(remaining, self.ends[k] - self.t)
            v, w = self.segments[k]
            x, y, yaw = integrate_unicycle(x, y, yaw, v, w, h)
            v_avg += v * h / dt
            w_avg += w * h / dt
            self.t += h
            remaining -= h
        return (x, y, yaw), (v_avg, 0.0, w_avg)


def make_motion(path: PathConfig | None, start):
    """Motion source of a scenario's [path] (CommandMotion, standing still, when there is none)."""
    if path is None:
        return CommandMotion()
    turn = np.deg2rad(path.turn_rate_deg)
    if path.mode == "waypoints":
        return WaypointMotion(path.waypoints, path.speed, turn)
    if path.mode == "poses":
        return PoseSequenceMotion(start, path.poses, path.speed, turn, path.pause_s)
    return VelocityProfileMotion(path.segments)
