"""The registration objective J(p) and its pose parametrisations.

A parameter vector p is one of three parametrisations of the rigid f (PLANES and "6dof"):
"optical" (x, z, θ) with θ about y, "body" (x, y, θ) with θ about z, "6dof" (tx, ty, tz, ωx, ωy, ωz).
:class:`_Objective` evaluates J on a fixed subset of A by reading B's field at f_p⁻¹(aᵢ), with its
analytic gradient and per-fly gradients (for the sandwich covariance); it counts its evaluations.
"""
from __future__ import annotations

import numpy as np

from ..geometry import rot_y, rot_z, so3_exp, so3_log
from . import _kernels

PLANES = ("optical", "body")


def _pose_optical(p):
    return rot_y(p[2]), np.array([p[0], 0.0, p[1]])


def _pose_body(p):
    return rot_z(p[2]), np.array([p[0], p[1], 0.0])


def _pose_6dof(p):
    return so3_exp(p[3:]), np.asarray(p[:3], dtype=float)


def _params_from_T(mode: str, T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    if mode == "optical":
        return np.array([t[0], t[2], np.arctan2(R[0, 2], R[2, 2])])
    if mode == "body":
        return np.array([t[0], t[1], np.arctan2(R[1, 0], R[0, 0])])
    return np.concatenate([t, so3_log(R)])


_POSES = {"optical": _pose_optical, "body": _pose_body, "6dof": _pose_6dof}


_K_Y = np.array([[0.0, 0, 1], [0, 0, 0], [-1, 0, 0]])   # d rot_y(θ)/dθ = rot_y(θ) @ _K_Y
_K_Z = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 0]])   # d rot_z(θ)/dθ = rot_z(θ) @ _K_Z
_PLANAR_DT = {"optical": np.array([[1.0, 0, 0], [0, 0, 1], [0, 0, 0]]),
              "body": np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 0]])}


def _pose_jacobians(pose, p, step=1e-6):
    """dR/dp_k (k, 3, 3) and dt/dp_k (k, 3): analytic for the planar poses, else central differences
    of the (cheap) param→pose map."""
    if pose is _pose_optical or pose is _pose_body:
        R = pose(p)[0]
        dR = np.zeros((3, 3, 3))
        dR[2] = R @ (_K_Y if pose is _pose_optical else _K_Z)
        return dR, _PLANAR_DT["optical" if pose is _pose_optical else "body"]
    k = len(p)
    dR = np.empty((k, 3, 3))
    dt = np.empty((k, 3))
    for i in range(k):
        e = np.zeros(k)
        e[i] = step
        Rp, tp = pose(p + e)
        Rm, tm = pose(p - e)
        dR[i] = (Rp - Rm) / (2 * step)
        dt[i] = (tp - tm) / (2 * step)
    return dR, dt


class _Objective:
    """J(p) on a fixed subset of A, with its gradient and per-fly gradients.

    kind "delta": J = δ(A, f_p(B)) = scale Σ wᵃᵢ / S_B(qᵢ), qᵢ = f_p⁻¹(aᵢ) (PseudoDistanceField).
    kind "local": J = −C(A, f_p(B)) = −Σ wᵃᵢ S_B(qᵢ) / Σ wᵃ  (LocalCorrelationField).
    """

    def __init__(self, field, A, wa, pose, near: bool, kind: str = "delta"):
        self.field, self.A, self.wa, self.pose, self.near, self.kind = field, A, wa, pose, near, kind
        self.scale = field.weight_sum / wa.sum() if kind == "delta" else 1.0 / wa.sum()
        self.count = 0

    def _terms(self, S, G=None):
        """Per-fly costs cᵢ and, with G = ∇S, their gradients ∂cᵢ/∂qᵢ."""
        if self.kind == "delta":
            c = self.scale * self.wa / S
            return c, None if G is None else (-c / S)[:, None] * G
        c = -self.scale * self.wa * S
        return c, None if G is None else (-self.scale * self.wa)[:, None] * G

    def _points(self, p):
        R, t = self.pose(p)
        D = self.A - t
        return R, t, D, D @ R  # rows of D @ R are Rᵀ(aᵢ − t)

    def value(self, p) -> float:
        self.count += 1
        _, _, _, Q = self._points(p)
        return float(self._terms(self.field._field(Q, False, self.near)[0])[0].sum())

    def per_fly(self, p):
        """(J, per-fly gradients (n, k)) at p."""
        self.count += 1
        R, t, D, Q = self._points(p)
        S, G = self.field._field(Q, True, self.near)
        c, Gq = self._terms(S, G)                       # cᵢ and ∂cᵢ/∂qᵢ
        dR, dt = _pose_jacobians(self.pose, p)
        # ∂qᵢ/∂p_k = dR_kᵀ(aᵢ − t) − Rᵀ dt_k ; as rows: dᵢ @ dR_k − dt_k @ R
        J = _kernels.param_gradients(D, dR, np.ascontiguousarray(dt @ R), np.ascontiguousarray(Gq))
        return float(c.sum()), J

    def translation_hessian(self, p, step, axes=(0, 1, 2)):
        """3×3 Hessian of J under a free translation u of all of f⁻¹(A) (central differences); only
        the rows (and, by symmetry, columns) of `axes` are computed, the others are left zero."""
        _, _, _, Q = self._points(p)
        H = np.zeros((3, 3))
        for i in axes:
            e = np.zeros(3)
            e[i] = step
            g = []
            for sgn in (1, -1):
                S, G = self.field._field(Q + sgn * e, True, self.near)
                g.append(self._terms(S, G)[1].sum(0))
            H[i] = (g[0] - g[1]) / (2 * step)
        for i in axes:
            H[:, i] = H[i]
        return H

    def value_and_grad(self, p):
        v, J = self.per_fly(p)
        return v, J.sum(0)
