"""Trajectory accuracy: ATE after SE(3) alignment, RPE, drift — the numbers `flyslam eval` reports.

Estimated and ground-truth trajectories are associated by stamp (nearest within a tolerance), the
estimate is aligned to the truth with Umeyama's closed form (rotation + translation, no scale), and:
- ATE RMSE: RMS of the position differences after alignment;
- RPE: mean translation / rotation error of the relative motion between consecutive associated poses;
- drift: final position error, with the trajectories aligned on their first pose, in % of path length.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from common.geometry import invert, so3_log


class TrajectoryMismatch(ValueError):
    """Trajectories that cannot be compared (too few common stamps)."""


@dataclass
class TrajectoryMetrics:
    poses: int
    path_length_m: float
    ate_rmse_m: float
    ate_pct_of_path: float
    rpe_trans_mean_m: float
    rpe_rot_mean_deg: float
    drift_pct: float
    final_error_m: float

    def as_dict(self) -> dict:
        return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in asdict(self).items()}


def path_length(positions) -> float:
    """Length (m) of the polyline through (N, 3) positions."""
    p = np.asarray(positions, dtype=float).reshape(-1, 3)
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def associate(stamps_a, stamps_b, tolerance_ns: int = 20_000_000):
    """Index pairs (i, j) of a's and b's stamps closer than the tolerance (each a-stamp at most once)."""
    a = np.asarray(stamps_a, np.int64)
    b = np.asarray(stamps_b, np.int64)
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    order = np.argsort(b)
    bs = b[order]
    pos = np.clip(np.searchsorted(bs, a), 1, len(bs) - 1) if len(bs) > 1 else np.zeros(len(a), int)
    left = bs[np.maximum(pos - 1, 0)]
    right = bs[pos]
    pick = np.where(np.abs(a - left) <= np.abs(a - right), np.maximum(pos - 1, 0), pos)
    ok = np.abs(a - bs[pick]) <= tolerance_ns
    return np.flatnonzero(ok), order[pick[ok]]


def umeyama(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """4×4 rigid transform T minimising Σ |T·source − target|² (Umeyama 1991, no scale)."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    S = (target - mu_t).T @ (source - mu_s) / len(source)
    U, _, Vt = np.linalg.svd(S)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = mu_t - R @ mu_s
    return T


def evaluate(est_stamps, est_poses, gt_stamps, gt_poses, tolerance_ns: int = 20_000_000) -> TrajectoryMetrics:
    i, j = associate(est_stamps, gt_stamps, tolerance_ns)
    if len(i) < 3:
        raise TrajectoryMismatch(f"only {len(i)} estimated poses have a ground-truth pose within "
                                 f"{tolerance_ns / 1e6:.0f} ms")
    E = np.asarray(est_poses)[i]
    G = np.asarray(gt_poses)[j]
    pe, pg = E[:, :3, 3], G[:, :3, 3]
    path = path_length(pg)
    A = umeyama(pe, pg)
    aligned = pe @ A[:3, :3].T + A[:3, 3]
    ate = float(np.sqrt(np.mean(np.sum((aligned - pg) ** 2, axis=1))))
    rel_t, rel_r = [], []
    for k in range(len(E) - 1):
        de = invert(E[k]) @ E[k + 1]
        dg = invert(G[k]) @ G[k + 1]
        err = invert(dg) @ de
        rel_t.append(np.linalg.norm(err[:3, 3]))
        rel_r.append(np.linalg.norm(so3_log(err[:3, :3])))
    first = G[0] @ invert(E[0])
    final_err = float(np.linalg.norm((first @ E[-1])[:3, 3] - G[-1][:3, 3]))
    return TrajectoryMetrics(
        poses=int(len(i)), path_length_m=path, ate_rmse_m=ate,
        ate_pct_of_path=100 * ate / path if path > 0 else float("nan"),
        rpe_trans_mean_m=float(np.mean(rel_t)), rpe_rot_mean_deg=float(np.rad2deg(np.mean(rel_r))),
        drift_pct=100 * final_err / path if path > 0 else float("nan"), final_error_m=final_err)


def factor_nees(edges, keyframe_stamps: dict, truth_stamps, truth, planar: bool,
                tolerance_ns: int = 20_000_000) -> dict:
    """How far a pose graph's factors can be trusted: per factor kind, the NEES against the truth.

    For each between-factor i→j (priors skipped) whose two keyframes have a truth pose within
    ``tolerance_ns``: e = log(T_true_ij⁻¹ · T_i_j) in frame j, flyslam order (x, y, z, rx, ry, rz), and
    NEES = eᵀ Σ⁻¹ e under the factor's own covariance, over the axes the graph estimates (x, y, yaw for a
    planar graph, all six otherwise). A consistent covariance gives a mean NEES near ``dof``: well above,
    the factors claim more than they know; well below, less.  Returns {kind: {factors, nees_mean,
    nees_median, dof}}; kinds with no factor next to the truth are left out.
    """
    axes = [0, 1, 5] if planar else list(range(6))
    ids = list(keyframe_stamps)
    i_kf, j_truth = associate([keyframe_stamps[k] for k in ids], truth_stamps, tolerance_ns)
    truth_of = {ids[a]: np.asarray(truth[b]) for a, b in zip(i_kf, j_truth)}
    nees: dict[str, list[float]] = {}
    for edge in edges:
        if edge.i == edge.j or edge.i not in truth_of or edge.j not in truth_of:
            continue
        E = invert(invert(truth_of[edge.i]) @ truth_of[edge.j]) @ np.asarray(edge.T_i_j)
        e = np.r_[E[:3, 3], so3_log(E[:3, :3])][axes]
        cov = np.asarray(edge.cov)[np.ix_(axes, axes)]
        nees.setdefault(edge.kind, []).append(float(e @ np.linalg.solve(cov, e)))
    return {kind: {"factors": len(v), "nees_mean": round(float(np.mean(v)), 3),
                   "nees_median": round(float(np.median(v)), 3), "dof": len(axes)} for kind, v in nees.items()}
