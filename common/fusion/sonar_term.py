"""Sonar fitness term for the fly evolver: flies in a beam's free space lose, (optionally) flies at its echo win.

A sonar echo at range r says two things about the cone of its beam: nothing reflective lies nearer than
r (free space), and something lies at r.  So, for a fly at distance d from a transducer and inside its
beam (an elliptic cone around the transducer's horizontal axis: ``beam_width/2`` horizontally and
``vertical_half_angle_rad`` vertically, by default the same),

* penalty  ``−(½ + ½·(r − d)/r) · clip((r − d − σ)/σ, 0, 1)``: 0 within σ of the echo, −½ from 2σ nearer,
  deepening to −1 at the transducer (a flat penalty gives a fly deep in free space no reason to move —
  its mutated children score the same — the slope leads it out towards the echo range);
* reward   ``reward_gain · exp(−½((d − r)/σ)²)``,     σ = ``echo_sigma_m`` + ``echo_sigma_rel``·r,

and nothing beyond r + 3σ (the beam may be occluded there), nearer than the ring's minimum range (blind),
below ``floor_clearance_m`` (the floor lies inside a horizontal cone but, seen at grazing incidence, never
echoes: it is not free space) or outside every beam.  Beams without an echo say nothing by default: a
smooth wall seen obliquely returns no echo, so "no echo" is not "free" (``no_echo_is_free`` turns that
reading on).  Contributions of overlapping beams add up and the total is clipped to [−1, 1]; the evolver
multiplies it by its weight (image fitness lies in [0, 1)).

The reward is OFF by default (``reward_gain=0``): an echo says the *nearest* surface in the cone is at r,
so only one part of the arc of radius r is on a surface — for a wall seen obliquely (a corridor's side
walls in the ±30° beams) the rest of the arc is free space.  On bench/fusion.py (texture-poor corridor)
rewarding the arc drew most flies onto it and the fraction of flies on real surfaces fell from 0.33–0.39 to
0.02–0.10; the free-space penalty alone changed it by less than the run-to-run noise (±0.02).

Evaluation is one numba loop over flies × beams with early rejection (most flies are outside most beams).  The flies arrive in the LEFT OPTICAL
camera frame; ``T_base_camera`` (StereoCalibration.T_base_camera, possibly composed with the robot's
motion between the scan and the frame) brings them into base_link, where the scan is expressed.

Use with the evolver::

    term = SonarTerm(SonarTermConfig(height_m=0.25))
    evolver.add_fitness_term("sonar", term, weight=0.5)
    ...
    term.update(scan_in_base_link, calib.T_base_camera)   # on every new scan; evolver rescoring follows
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from common.fusion.sonar import SonarScanError, check_scan
from common.messages import BASE_LINK, SonarScan


@dataclass(frozen=True)
class SonarTermConfig:
    height_m: float = 0.25                  # transducer ring height in base_link (not on the wire)
    echo_sigma_m: float = 0.05
    echo_sigma_rel: float = 0.01
    vertical_half_angle_rad: float | None = None   # None: same as the horizontal half beam width
    no_echo_is_free: bool = False
    floor_clearance_m: float = 0.10         # flies lower than this (base_link z) are ignored: see below
    reward_gain: float = 0.0                # scales the echo-range reward (off by default: see above)
    penalty_gain: float = 1.0               # scales the free-space penalty

    def __post_init__(self):
        if not np.isfinite(self.height_m):
            raise SonarScanError("height_m must be finite")
        if not (self.echo_sigma_m > 0 and self.echo_sigma_rel >= 0):
            raise SonarScanError("echo_sigma_m must be > 0 and echo_sigma_rel >= 0")
        if not (0 <= self.reward_gain <= 1 and 0 <= self.penalty_gain <= 1):
            raise SonarScanError("reward_gain and penalty_gain must be in [0, 1]")
        v = self.vertical_half_angle_rad
        if v is not None and not (0 < v < np.pi / 2):
            raise SonarScanError(f"vertical_half_angle_rad must be in (0, π/2), got {v}")


@numba.njit(cache=True, nogil=True)
def _sonar_kernel(p, bx, by, bc, bs, r, echo, height, half_h, half_v, min_range, floor, sigma0, sigma_rel,
                  reward_gain, penalty_gain, score, in_echo_beam):
    """Loop over flies × beams with early rejection (most flies lie outside most beams)."""
    for i in range(p.shape[0]):
        total = 0.0
        hit = False
        if p[i, 2] >= floor:
            for k in range(bx.shape[0]):
                dx, dy = p[i, 0] - bx[k], p[i, 1] - by[k]
                ax = bc[k] * dx + bs[k] * dy
                if ax <= 0.0:
                    continue
                lat = -bs[k] * dx + bc[k] * dy
                dz = p[i, 2] - height
                horizontal = math.sqrt(ax * ax + lat * lat)
                d = math.sqrt(horizontal * horizontal + dz * dz)
                if d < min_range:
                    continue
                az = math.atan2(lat, ax) / half_h
                el = math.atan2(dz, horizontal) / half_v
                if az * az + el * el > 1.0:
                    continue
                hit = hit or echo[k]
                sigma = sigma0 + sigma_rel * r[k]
                u = (d - r[k]) / sigma
                if echo[k] and u <= 3.0:
                    total += reward_gain * math.exp(-0.5 * u * u)
                if u < -1.0:
                    depth_in_free = min(max((r[k] - d) / r[k], 0.0), 1.0)
                    total -= penalty_gain * min(-u - 1.0, 1.0) * (0.5 + 0.5 * depth_in_free)
        score[i] = min(max(total, -1.0), 1.0)
        in_echo_beam[i] = hit


def _evaluate(positions, T_base_camera, scan: SonarScan, cfg: "SonarTermConfig"):
    """(score (N,) float32, in_echo_beam (N,) bool) — see the module docstring."""
    pos = np.asarray(positions, dtype=np.float32)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions must be (N, 3), got {pos.shape}")
    T = np.asarray(T_base_camera, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError("T_base_camera must be a finite 4×4 transform")
    if scan.header.frame_id != BASE_LINK:
        raise SonarScanError(f"the sonar term needs a scan in {BASE_LINK}, got {scan.header.frame_id!r} "
                             "(use common.fusion.sonar.scan_in_base)")
    check_scan(scan)
    poses = np.asarray(scan.transducer_poses, np.float64)
    ranges = np.asarray(scan.ranges, np.float64)
    use = np.isfinite(ranges) | cfg.no_echo_is_free
    poses, ranges = poses[use], ranges[use]
    r = np.where(np.isfinite(ranges), ranges, scan.max_range_m)
    # Flies into base_link (one matrix product), then the kernel goes into every beam's frame.
    p = np.ascontiguousarray(pos.astype(np.float64) @ T[:3, :3].T + T[:3, 3])
    half_h = 0.5 * scan.beam_width_rad
    score = np.zeros(len(pos), np.float32)
    mask = np.zeros(len(pos), np.bool_)
    _sonar_kernel(p, np.ascontiguousarray(poses[:, 0]), np.ascontiguousarray(poses[:, 1]), np.cos(poses[:, 2]),
                  np.sin(poses[:, 2]), np.ascontiguousarray(r), np.isfinite(ranges), float(cfg.height_m), half_h,
                  float(cfg.vertical_half_angle_rad or half_h), float(scan.min_range_m), float(cfg.floor_clearance_m),
                  float(cfg.echo_sigma_m), float(cfg.echo_sigma_rel), float(cfg.reward_gain),
                  float(cfg.penalty_gain), score, mask)
    return score, mask


def sonar_fitness(positions: np.ndarray, T_base_camera: np.ndarray, scan: SonarScan,
                  config: SonarTermConfig | None = None) -> np.ndarray:
    """(N,) float32 additive fitness of flies (N, 3) in the camera optical frame against a base_link scan."""
    return _evaluate(positions, T_base_camera, scan, config or SonarTermConfig())[0]


def in_echo_beams(positions: np.ndarray, T_base_camera: np.ndarray, scan: SonarScan,
                  config: SonarTermConfig | None = None) -> np.ndarray:
    """(N,) bool: the fly lies inside the cone of at least one beam that returned an echo (where the term
    can act at all; used by the benchmark to report figures where sonar has something to say)."""
    return _evaluate(positions, T_base_camera, scan, config or SonarTermConfig())[1]


class SonarTerm:
    """Callable fitness term ``fn(positions) -> (N,)`` holding the latest scan (evolver plug-in form).
    Before the first :meth:`update` (or after :meth:`clear`) it returns zeros."""

    def __init__(self, config: SonarTermConfig | None = None):
        self.config = config or SonarTermConfig()
        self.scan: SonarScan | None = None
        self.T_base_camera: np.ndarray | None = None

    def update(self, scan: SonarScan, T_base_camera: np.ndarray) -> None:
        if scan.header.frame_id != BASE_LINK:
            raise SonarScanError(f"SonarTerm.update needs a scan in {BASE_LINK}, got {scan.header.frame_id!r}")
        check_scan(scan)
        self.scan, self.T_base_camera = scan, np.array(T_base_camera, float)

    def clear(self) -> None:
        self.scan = None

    def __call__(self, positions: np.ndarray) -> np.ndarray:
        if self.scan is None:
            return np.zeros(len(positions), np.float32)
        return sonar_fitness(positions, self.T_base_camera, self.scan, self.config)
