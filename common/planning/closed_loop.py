"""Kinematic closed-loop harness: a differential-drive robot, a fly-producing perception stand-in, an
optional sonar ring, and the HarmonicPlanner in the loop at a fixed rate.

The world is an (M, 2, 2) array of wall segments (map x, y).  Each planner cycle the camera casts rays
over its horizontal field of view; every visible wall point becomes a few "flies" at random heights with
Gaussian noise, plus a share of outliers scattered through the view cone, and the sonar ring reports its
echoes.  The planner folds them in, solves (warm, with a cycle budget so runs are reproducible) and
commands (v, omega), which the robot integrates in sub-steps while collisions are checked.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .config import PlannerConfig, PlannerInputError
from .planner import HarmonicPlanner


@dataclass(frozen=True)
class PerceptionConfig:
    fov_rad: float = math.radians(70.0)
    max_range_m: float = 6.0
    rays: int = 120
    flies_per_hit: int = 3
    noise_m: float = 0.025
    outlier_fraction: float = 0.05
    fly_z_range: tuple[float, float] = (0.1, 0.9)
    sonar_beams: int = 12                 # 0 disables the sonar ring
    sonar_range_m: float = 2.5
    sonar_noise_m: float = 0.01


@dataclass
class LoopResult:
    reached: bool
    time_s: float
    path: np.ndarray                      # (K, 3) x, y, yaw at every sub-step
    min_clearance_m: float                # smallest distance from the robot's edge to a wall
    collided: bool
    reason: str                           # last stop reason, 'collision' or 'timeout'
    cycles: int
    solve_ms: list = field(default_factory=list)


def ray_hits(origin: np.ndarray, angles: np.ndarray, segments: np.ndarray, max_range: float) -> np.ndarray:
    """Range along each ray (from ``origin`` at ``angles``) to the nearest segment, inf if none within
    ``max_range``.  Vectorised over rays x segments."""
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1)[:, None, :]          # (R,1,2)
    a = segments[None, :, 0, :]                                                 # (1,M,2)
    e = segments[None, :, 1, :] - a                                             # (1,M,2)
    ao = a - origin                                                             # (1,M,2)
    denom = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]                        # cross(d, e)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ao[..., 0] * e[..., 1] - ao[..., 1] * e[..., 0]) / denom          # along the ray
        u = (ao[..., 0] * d[..., 1] - ao[..., 1] * d[..., 0]) / denom          # along the segment
    ok = (np.abs(denom) > 1e-12) & (t > 1e-9) & (u >= 0) & (u <= 1) & (t <= max_range)
    t = np.where(ok, t, np.inf)
    return t.min(axis=1)


def distance_to_segments(p: np.ndarray, segments: np.ndarray) -> float:
    a = segments[:, 0, :]
    e = segments[:, 1, :] - a
    t = np.clip(((p - a) * e).sum(1) / np.maximum((e * e).sum(1), 1e-18), 0.0, 1.0)
    return float(np.sqrt((((a + t[:, None] * e) - p) ** 2).sum(1)).min())


def perceive_flies(pose, segments: np.ndarray, pc: PerceptionConfig, rng: np.random.Generator):
    """(N, 3) map-frame flies and (N,) fitness seen by a forward camera at ``pose`` (x, y, yaw)."""
    x, y, yaw = pose
    origin = np.array([x, y])
    angles = yaw + np.linspace(-pc.fov_rad / 2, pc.fov_rad / 2, pc.rays)
    rng_hit = ray_hits(origin, angles, segments, pc.max_range_m)
    vis = np.isfinite(rng_hit)
    a = np.repeat(angles[vis], pc.flies_per_hit)
    r = np.repeat(rng_hit[vis], pc.flies_per_hit)
    n = a.size
    pts = np.stack([x + r * np.cos(a), y + r * np.sin(a), rng.uniform(*pc.fly_z_range, n)], axis=1)
    pts += rng.normal(0.0, pc.noise_m, pts.shape)
    fit = rng.uniform(0.6, 1.0, n)
    n_out = int(round(pc.outlier_fraction * n))
    if n_out:
        ao = yaw + rng.uniform(-pc.fov_rad / 2, pc.fov_rad / 2, n_out)
        ro = rng.uniform(0.3, pc.max_range_m, n_out)
        out = np.stack([x + ro * np.cos(ao), y + ro * np.sin(ao), rng.uniform(0.0, 1.5, n_out)], axis=1)
        pts = np.vstack([pts, out])
        fit = np.concatenate([fit, rng.uniform(0.1, 0.6, n_out)])
    return pts, fit


def perceive_sonar(pose, segments: np.ndarray, pc: PerceptionConfig, rng: np.random.Generator) -> np.ndarray:
    """(M, 2) map-frame echo points of a ring of ``sonar_beams`` beams."""
    if pc.sonar_beams <= 0:
        return np.zeros((0, 2))
    x, y, yaw = pose
    angles = yaw + np.arange(pc.sonar_beams) * (2 * math.pi / pc.sonar_beams)
    r = ray_hits(np.array([x, y]), angles, segments, pc.sonar_range_m)
    ok = np.isfinite(r)
    r = r[ok] + rng.normal(0.0, pc.sonar_noise_m, int(ok.sum()))
    return np.stack([x + r * np.cos(angles[ok]), y + r * np.sin(angles[ok])], axis=1)


def run_closed_loop(segments, start, target, bounds, *, config: PlannerConfig | None = None,
                    perception: PerceptionConfig | None = None, rate_hz: float = 10.0,
                    substeps: int = 5, timeout_s: float = 90.0, solver_cycles: int = 8,
                    seed: int = 0) -> LoopResult:
    """Drive from ``start`` (x, y, yaw) to ``target`` (x, y, radius) among ``segments`` (M, 2, 2).

    ``bounds`` (xmin, ymin, xmax, ymax) sizes the planner grid (with a 0.5 m margin) unless ``config``
    is given.  Returns a LoopResult; the run ends on 'target reached', a collision or ``timeout_s``."""
    segs = np.asarray(segments, dtype=float)
    if segs.ndim != 3 or segs.shape[1:] != (2, 2):
        raise PlannerInputError(f"segments must be (M, 2, 2), got {segs.shape}")
    pc = perception or PerceptionConfig()
    if config is None:
        xmin, ymin, xmax, ymax = bounds
        config = PlannerConfig(resolution=0.1, origin=(xmin - 0.5, ymin - 0.5),
                               size_m=(xmax - xmin + 1.0, ymax - ymin + 1.0))
    rng = np.random.default_rng(seed)
    pl = HarmonicPlanner(config)
    pl.set_target(*target)
    pose = np.array(start, dtype=float)
    dt = 1.0 / rate_hz
    path = [pose.copy()]
    min_clear = distance_to_segments(pose[:2], segs) - config.robot_radius
    solve_ms: list = []
    reason = "timeout"
    reached = collided = False
    cycles = int(round(timeout_s * rate_hz))
    for k in range(cycles):
        stamp = int(k * dt * 1e9)
        pts, fit = perceive_flies(pose, segs, pc, rng)
        pl.update_flies(pts, fit, stamp)
        sonar = perceive_sonar(pose, segs, pc, rng)
        if len(sonar):
            pl.update_sonar(sonar, stamp)
        rep = pl.solve(max_cycles=solver_cycles)
        solve_ms.append(rep.elapsed_ms)
        cmd = pl.command(pose)
        if cmd.stop:
            reason = cmd.reason
            if cmd.reason == "target reached":
                reached = True
                break
        for _ in range(substeps):
            h = dt / substeps
            pose[0] += cmd.v * math.cos(pose[2]) * h
            pose[1] += cmd.v * math.sin(pose[2]) * h
            pose[2] = (pose[2] + cmd.omega * h + math.pi) % (2 * math.pi) - math.pi
            path.append(pose.copy())
            clear = distance_to_segments(pose[:2], segs) - config.robot_radius
            min_clear = min(min_clear, clear)
            if clear <= 0:
                collided = True
        if collided:
            reason = "collision"
            break
    return LoopResult(reached, (k + 1) * dt if cycles else 0.0, np.asarray(path), min_clear, collided,
                      reason, k + 1 if cycles else 0, solve_ms)
