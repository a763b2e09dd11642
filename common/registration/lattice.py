"""The registration's coarse lattice: candidate counts, the candidates, their poses and reach.

The lattice spans prior ± window in params; its poses are built vectorised (_poses_batch matches
objective._POSES row by row), and _reach_bounds is the box B's field must cover for every candidate.
"""
from __future__ import annotations

import numpy as np

from .objective import PLANES
from .pseudo_distance import PopulationError


def _lattice(center, half, counts):
    axes = [np.linspace(c - h, c + h, n) if n > 1 else np.array([c]) for c, h, n in zip(center, half, counts)]
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([m.ravel() for m in mesh], 1), tuple(len(a) for a in axes)


_MIN_COUNT = 5   # 3 per axis put 2 of 3 candidates on the window's edge: more boundary rejections


def _lattice_counts(mode, A, wa, half, counts, step):
    """Lattice candidates per parameter: `counts`, fewer where the window is narrow for `step`.

    A pinned parameter (half-width 0) gets one candidate (more would only repeat it).  With a `step`
    (metres), a free one gets the fewest odd count, at least _MIN_COUNT and at most counts[i], whose
    spacing moves A's flies by at most `step`: translations by their spacing, rotations by spacing ×
    the flies' rms lever arm about the rotation axis.  The coarse objective is smooth over its
    cut-off, so candidates much closer than that only repeat each other's basin.
    """
    counts = np.array([int(c) if h > 0 else 1 for c, h in zip(counts, half)])
    if step is None:
        return tuple(counts)
    step = float(step)
    if not np.isfinite(step) or step <= 0:
        raise PopulationError(f"lattice_step must be a positive distance, got {step}")
    k = len(half)
    axis = {"optical": 1, "body": 2}.get(mode)
    if axis is None:
        lever = np.full(3, np.sqrt(np.average(np.sum(A * A, 1), weights=wa)))
    else:
        perp = np.delete(A, axis, 1)
        lever = np.full(1, np.sqrt(np.average(np.sum(perp * perp, 1), weights=wa)))
    n_rot = 1 if mode in PLANES else 3
    metres = np.concatenate([half[:k - n_rot], half[k - n_rot:] * lever])
    need = 2 * np.ceil(metres / step).astype(int) + 1
    return tuple(int(c) if c <= 1 else int(min(c, max(_MIN_COUNT, n))) for c, n in zip(counts, need))


def _poses_batch(mode: str, P: np.ndarray):
    """Rotations (m, 3, 3) and translations (m, 3) of every row of params P, vectorised (the lattice
    holds 343 planar or 3,375 6-DoF candidates; one Python pose call each cost milliseconds)."""
    m = len(P)
    Rs = np.zeros((m, 3, 3))
    ts = np.zeros((m, 3))
    if mode in PLANES:
        c, s = np.cos(P[:, 2]), np.sin(P[:, 2])
        if mode == "optical":      # rot_y, t = (x, 0, z)
            Rs[:, 0, 0], Rs[:, 0, 2], Rs[:, 1, 1], Rs[:, 2, 0], Rs[:, 2, 2] = c, s, 1.0, -s, c
            ts[:, 0], ts[:, 2] = P[:, 0], P[:, 1]
        else:                      # rot_z, t = (x, y, 0)
            Rs[:, 0, 0], Rs[:, 0, 1], Rs[:, 1, 0], Rs[:, 1, 1], Rs[:, 2, 2] = c, -s, s, c, 1.0
            ts[:, 0], ts[:, 1] = P[:, 0], P[:, 1]
        return Rs, ts
    w = P[:, 3:]
    th = np.linalg.norm(w, axis=1)
    k = w / np.where(th > 1e-12, th, 1.0)[:, None]
    small = th <= 1e-12                     # so3_exp: I + [w]ₓ for tiny angles, Rodrigues otherwise
    K = np.where(small[:, None, None], _skew_batch(w), _skew_batch(k))
    sin_t = np.where(small, 1.0, np.sin(th))[:, None, None]
    one_c = np.where(small, 0.0, 1.0 - np.cos(th))[:, None, None]
    Rs = np.eye(3) + sin_t * K + one_c * (K @ K)
    ts[:] = P[:, :3]
    return Rs, ts


def _skew_batch(w):
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 0] = -w[:, 2], w[:, 1], w[:, 2]
    K[:, 1, 2], K[:, 2, 0], K[:, 2, 1] = -w[:, 0], -w[:, 1], w[:, 0]
    return K


def _reach_bounds(A, Rs, ts):
    """Bounding box of f⁻¹(A) over every candidate (Rs (m, 3, 3), ts (m, 3)): where the field will be read."""
    c_lo, c_hi = A.min(0), A.max(0)
    corners = np.array([[x, y, z] for x in (c_lo[0], c_hi[0]) for y in (c_lo[1], c_hi[1])
                        for z in (c_lo[2], c_hi[2])])
    q = np.einsum("cj,mjl->mcl", corners, Rs) - np.einsum("mj,mjl->ml", ts, Rs)[:, None, :]
    return q.min((0, 1)), q.max((0, 1))
