"""Sonar scans in the robot frame, and their echoes as obstacle points for the planner.

A SonarScan gives each transducer's planar pose (x, y, yaw) in its ``frame_id``; :func:`scan_in_base`
re-expresses it in base_link given the planar mount of that frame (identity when it already is base_link).
The ring's height above the floor is not on the wire, so it is a parameter here (``height_m``).

:func:`echo_points` turns every echo into points on its arc: an echo at range r only says that *something*
lies at distance r somewhere across the beam, so the planner gets ``arc_samples`` points spread over the
beam width at that range (the conservative reading for obstacle avoidance).
"""
from __future__ import annotations

import numpy as np

from common.fusion.planar import compose
from common.messages import BASE_LINK, SonarScan, header


class SonarScanError(ValueError):
    """A scan that cannot be interpreted (mismatched lengths, bad beam width or limits)."""


def check_scan(scan: SonarScan) -> None:
    poses, ranges = np.asarray(scan.transducer_poses), np.asarray(scan.ranges)
    if poses.ndim != 2 or poses.shape[1] != 3 or ranges.shape != (len(poses),):
        raise SonarScanError(f"sonar scan: {len(poses)} transducer poses but ranges of shape {ranges.shape}")
    if not np.all(np.isfinite(poses)):
        raise SonarScanError("sonar scan: non-finite transducer pose")
    if not (np.isfinite(scan.beam_width_rad) and 0 < scan.beam_width_rad < np.pi):
        raise SonarScanError(f"sonar scan: beam width {scan.beam_width_rad} rad is not in (0, π)")
    if not (np.isfinite(scan.max_range_m) and 0 <= scan.min_range_m < scan.max_range_m):
        raise SonarScanError(f"sonar scan: range limits [{scan.min_range_m}, {scan.max_range_m}] are not valid")
    if np.any(np.isinf(ranges)) or np.any(ranges[np.isfinite(ranges)] < 0):
        raise SonarScanError("sonar scan: ranges must be >= 0 or NaN (no echo)")


def scan_in_base(scan: SonarScan, mount_xyyaw=None) -> SonarScan:
    """The scan with transducer poses in base_link. ``mount_xyyaw``: planar pose of the scan's frame in
    base_link (required unless frame_id is already base_link). Ranges outside [min, max] become NaN."""
    check_scan(scan)
    if scan.header.frame_id == BASE_LINK:
        poses = np.array(scan.transducer_poses, float)
    elif mount_xyyaw is None:
        raise SonarScanError(f"sonar scan in frame {scan.header.frame_id!r}: its mount on {BASE_LINK} is unknown")
    else:
        poses = np.array([compose(mount_xyyaw, p) for p in np.asarray(scan.transducer_poses, float)]).reshape(-1, 3)
    ranges = np.array(scan.ranges, np.float64)
    with np.errstate(invalid="ignore"):
        ranges[(ranges < scan.min_range_m) | (ranges > scan.max_range_m)] = np.nan
    return SonarScan(transducer_poses=poses, ranges=ranges.astype(np.float32), beam_width_rad=scan.beam_width_rad,
                     min_range_m=scan.min_range_m, max_range_m=scan.max_range_m,
                     header=header(scan.header.seq, scan.header.stamp_ns, BASE_LINK))


def echo_points(scan: SonarScan, height_m: float, arc_samples: int = 5) -> np.ndarray:
    """(M, 3) float32 points in the scan's frame: ``arc_samples`` per echo spread evenly over the beam
    width at the echo range, at ``height_m``. Transducers without an echo contribute nothing."""
    if arc_samples < 1:
        raise SonarScanError(f"arc_samples must be >= 1, got {arc_samples}")
    poses = np.asarray(scan.transducer_poses, float)
    ranges = np.asarray(scan.ranges, float)
    hit = np.isfinite(ranges)
    half = 0.5 * scan.beam_width_rad
    offsets = np.linspace(-half, half, arc_samples) if arc_samples > 1 else np.zeros(1)
    ang = poses[hit, 2][:, None] + offsets[None, :]                      # (E, S)
    r = ranges[hit][:, None]
    x = poses[hit, 0][:, None] + r * np.cos(ang)
    y = poses[hit, 1][:, None] + r * np.sin(ang)
    z = np.full_like(x, float(height_m))
    return np.stack([x, y, z], -1).reshape(-1, 3).astype(np.float32)
