"""Rigid-body geometry in SI units, with the project's frame conventions.

Frames follow ROS REP-103: a body frame (base_link) has x forward, y left, z up; a camera *optical*
frame has z forward, x right, y down.  Poses are 4×4 homogeneous matrices ``T_a_b`` that map points
expressed in frame ``b`` into frame ``a`` (``p_a = T_a_b @ p_b``).  Quaternions are xyzw, as on the wire.
"""
from __future__ import annotations

import numpy as np

# Rotation taking optical-frame coordinates into the body-style camera frame (x fwd, y left, z up):
# optical z (forward) -> body x, optical x (right) -> body -y, optical y (down) -> body -z.
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0],
                           [-1.0, 0.0, 0.0],
                           [0.0, -1.0, 0.0]])


def make_transform(rotation: np.ndarray | None = None, translation=None) -> np.ndarray:
    """4×4 homogeneous transform from a 3×3 rotation and a 3-vector translation."""
    T = np.eye(4)
    if rotation is not None:
        T[:3, :3] = rotation
    if translation is not None:
        T[:3, 3] = np.asarray(translation, dtype=float)
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (cheaper and better conditioned than np.linalg.inv)."""
    R = T[:3, :3]
    Ti = np.eye(4)
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


_I3 = np.eye(3)
NEAR_ORTHONORMAL = 1e-7     # max |RᵀR − I| below which one Newton–Schulz step replaces the SVD


def _det3(R: np.ndarray) -> float:
    a, b, c, d, e, f, g, h, i = R.ravel().tolist()
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


def orthonormalised(T: np.ndarray) -> np.ndarray:
    """T with its rotation replaced by the nearest rotation matrix: chains of composed estimates
    otherwise let rounding grow until a consumer's rigidity check refuses them.

    A rotation within NEAR_ORTHONORMAL of one (the usual case: rounding) takes one Newton–Schulz step
    R(3I − RᵀR)/2, which squares its error (1e-7 → ~1e-14) at a fraction of an SVD's cost; anything
    else (a reflection, a sheared or scaled matrix) gets the SVD's exact nearest rotation."""
    out = np.array(T, dtype=float, copy=True)
    R = out[:3, :3]
    RtR = R.T @ R
    if np.abs(RtR - _I3).max() < NEAR_ORTHONORMAL and _det3(R) > 0:
        out[:3, :3] = R @ (1.5 * _I3 - 0.5 * RtR)
        return out
    U, _, Vt = np.linalg.svd(R)
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return out


def scaled_motion(rel: np.ndarray, a: float) -> np.ndarray:
    """The body-frame motion ``rel`` carried on for ``a`` times as long (rotation along its geodesic,
    translation scaled): the constant-velocity step."""
    T = np.eye(4)
    T[:3, :3] = so3_exp(a * so3_log(rel[:3, :3]))
    T[:3, 3] = a * rel[:3, 3]
    return T


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4×4 transform to an (N, 3) array of points; keeps the input dtype."""
    pts = np.asarray(points)
    out = pts @ T[:3, :3].T.astype(pts.dtype, copy=False) + T[:3, 3].astype(pts.dtype, copy=False)
    return out


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=float)


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=float)


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=float)


def planar_pose(x: float, y: float, yaw: float) -> np.ndarray:
    """Pose of a ground robot (base_link in odom/map): translation in the x-y plane, rotation about z."""
    return make_transform(rot_z(yaw), [x, y, 0.0])


def planar_from_transform(T: np.ndarray) -> tuple[float, float, float]:
    """(x, y, yaw) of a transform, projecting its rotation onto the z axis."""
    return float(T[0, 3]), float(T[1, 3]), float(np.arctan2(T[1, 0], T[0, 0]))


def wrap_angle(a):
    """Wrap an angle (or array of angles) into [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix, with w >= 0."""
    R = np.asarray(R, dtype=float)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def matrix_from_quat(q) -> np.ndarray:
    """Rotation matrix of a quaternion (x, y, z, w); the quaternion is normalised first."""
    x, y, z, w = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def transform_from_pose(position, quat_xyzw) -> np.ndarray:
    return make_transform(matrix_from_quat(quat_xyzw), position)


def pose_from_transform(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,), quaternion xyzw (4,)) of a 4×4 transform."""
    return T[:3, 3].copy(), quat_from_matrix(T[:3, :3])


def so3_exp(w) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    w = np.asarray(w, dtype=float)
    th = np.linalg.norm(w)
    if th < 1e-12:
        K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        return np.eye(3) + K
    k = w / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix."""
    c = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    th = np.arccos(c)
    if th < 1e-9:
        return np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2
    if np.pi - th < 1e-6:
        # Near pi: take the axis from the diagonal.
        axis = np.sqrt(np.clip((np.diag(R) + 1) / 2, 0, None))
        i = int(np.argmax(axis))
        axis[(i + 1) % 3] = np.copysign(axis[(i + 1) % 3], R[i, (i + 1) % 3])
        axis[(i + 2) % 3] = np.copysign(axis[(i + 2) % 3], R[i, (i + 2) % 3])
        return axis / np.linalg.norm(axis) * th
    return th / (2 * np.sin(th)) * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
