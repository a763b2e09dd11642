"""Planar (x, y, yaw) pose algebra for a ground robot, with the Jacobians the odometry and the filter share.

A planar pose ``p = (x, y, yaw)`` stands for ``common.geometry.planar_pose(x, y, yaw)``.  The robot moves in
the plane, so the fusion works in three degrees of freedom; :func:`covariance6` embeds a 3×3 covariance into
the wire's 6×6 (x, y, z, roll, pitch, yaw) with a small fixed variance on the three unobserved axes (a
consumer inverting it must not divide by zero, and z/roll/pitch really are only known to that precision).
"""
from __future__ import annotations

import numpy as np

from common.geometry import planar_from_transform, planar_pose, wrap_angle

PLANAR_AXES = (0, 1, 5)          # x, y, yaw inside the 6×6 (x, y, z, roll, pitch, yaw) covariance
UNOBSERVED_VARIANCE = 1e-6       # z (m²), roll and pitch (rad²) of a robot on a flat floor


def compose(a, b) -> np.ndarray:
    """a ⊕ b: pose b (expressed in a's frame) chained after pose a."""
    x, y, th = a
    c, s = np.cos(th), np.sin(th)
    return np.array([x + c * b[0] - s * b[1], y + s * b[0] + c * b[1], float(wrap_angle(th + b[2]))])


def inverse(a) -> np.ndarray:
    x, y, th = a
    c, s = np.cos(th), np.sin(th)
    return np.array([-c * x - s * y, s * x - c * y, float(wrap_angle(-th))])


def between(a, b) -> np.ndarray:
    """a⁻¹ ⊕ b: pose b seen from pose a (the motion that takes a to b)."""
    return compose(inverse(a), b)


def compose_jacobian_first(a, b) -> np.ndarray:
    """∂(a ⊕ b)/∂a."""
    th = a[2]
    c, s = np.cos(th), np.sin(th)
    return np.array([[1.0, 0.0, -s * b[0] - c * b[1]],
                     [0.0, 1.0, c * b[0] - s * b[1]],
                     [0.0, 0.0, 1.0]])


def compose_jacobian_second(a) -> np.ndarray:
    """∂(a ⊕ b)/∂b."""
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def drive_step(pose, cov, dl: float, dr: float, track_width: float, var_left: float, var_right: float):
    """Advance a differential-drive pose by wheel travels ``dl``, ``dr`` (metres) and propagate its covariance.

    Midpoint integration: ds = (dl + dr)/2, dθ = (dr − dl)/b, the translation is taken along θ + dθ/2.
    Covariance: Σ' = F Σ Fᵀ + G diag(var_left, var_right) Gᵀ with F = ∂f/∂pose and G = ∂f/∂(dl, dr)
    (the classic error model of Siegwart & Nourbakhsh).  Returns (pose', Σ').
    """
    b = float(track_width)
    ds, dth = 0.5 * (dl + dr), (dr - dl) / b
    phi = pose[2] + 0.5 * dth
    c, s = np.cos(phi), np.sin(phi)
    new = np.array([pose[0] + ds * c, pose[1] + ds * s, float(wrap_angle(pose[2] + dth))])
    F = np.array([[1.0, 0.0, -ds * s], [0.0, 1.0, ds * c], [0.0, 0.0, 1.0]])
    G = np.array([[0.5 * c + ds * s / (2 * b), 0.5 * c - ds * s / (2 * b)],
                  [0.5 * s - ds * c / (2 * b), 0.5 * s + ds * c / (2 * b)],
                  [-1.0 / b, 1.0 / b]])
    Q = np.diag([var_left, var_right])
    new_cov = F @ cov @ F.T + G @ Q @ G.T
    return new, 0.5 * (new_cov + new_cov.T)


def interpolate(a, b, f: float) -> np.ndarray:
    """Pose a fraction f of the way from a to b (yaw along the shorter arc)."""
    dyaw = float(wrap_angle(b[2] - a[2]))
    return np.array([a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), float(wrap_angle(a[2] + f * dyaw))])


def covariance6(cov3) -> np.ndarray:
    """Embed a planar (x, y, yaw) covariance into the wire's 6×6 (x, y, z, roll, pitch, yaw)."""
    out = np.diag([0.0, 0.0, UNOBSERVED_VARIANCE, UNOBSERVED_VARIANCE, UNOBSERVED_VARIANCE, 0.0])
    idx = np.array(PLANAR_AXES)
    out[np.ix_(idx, idx)] = cov3
    return out


def covariance3(cov6) -> np.ndarray:
    """The planar (x, y, yaw) block of a 6×6 covariance."""
    idx = np.array(PLANAR_AXES)
    return np.array(cov6, float)[np.ix_(idx, idx)]


def to_transform(p) -> np.ndarray:
    return planar_pose(float(p[0]), float(p[1]), float(p[2]))


def from_transform(T) -> np.ndarray:
    return np.array(planar_from_transform(np.asarray(T, float)))

