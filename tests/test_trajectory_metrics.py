import numpy as np
import pytest

from common.geometry import invert, make_transform, planar_pose, rot_z
from common.trajectory_metrics import TrajectoryMismatch, evaluate, factor_nees


def test_a_rigidly_moved_copy_has_zero_ate_and_a_scaled_one_drifts():
    stamps = np.arange(50, dtype=np.int64) * 100_000_000
    gt = np.array([planar_pose(0.1 * k, 0.02 * k, 0.01 * k) for k in range(50)])
    moved = np.array([planar_pose(3, -2, 0.5) @ T for T in gt])
    m = evaluate(stamps, moved, stamps, gt)
    assert m.ate_rmse_m < 1e-9 and m.rpe_trans_mean_m < 1e-9 and m.drift_pct < 1e-6
    scaled = gt.copy()
    scaled[:, :3, 3] *= 1.02          # 2 % odometry scale error
    m = evaluate(stamps, scaled, stamps, gt)
    assert 1.5 < m.drift_pct < 2.5
    assert m.ate_rmse_m > 0.01


def test_no_common_stamps_is_a_clear_error():
    with pytest.raises(TrajectoryMismatch, match="ground-truth"):
        evaluate([0, 1, 2], np.tile(np.eye(4), (3, 1, 1)), [10**12], np.eye(4)[None])


def _chain(n, step=1.0):
    return [make_transform(rot_z(0.05 * k), [step * k, 0.1 * k, 0.0]) for k in range(n)]


def test_factor_nees_is_near_dof_when_errors_match_covariances_and_grows_when_they_do_not():
    from common.slam.posegraph import Edge
    from common.geometry import so3_exp
    rng = np.random.default_rng(0)
    truth = _chain(401)
    stamps = {k: 1_000_000_000 * k for k in range(401)}
    sig = np.array([0.02, 0.01, 0.01, 0.002, 0.002, 0.004])
    edges, tight = [], []
    for k in range(400):
        e = rng.normal(0.0, sig)
        T_true = invert(truth[k]) @ truth[k + 1]
        T_meas = T_true @ make_transform(so3_exp(e[3:]), e[:3])
        edges.append(Edge(k, k + 1, T_meas, np.diag(sig ** 2), "registration"))
        tight.append(Edge(k, k + 1, T_meas, np.diag((sig / 3) ** 2), "odometry"))
    edges.append(Edge(0, 0, truth[0], np.eye(6), "prior"))           # priors are not between-factors
    r = factor_nees(edges + tight, stamps, list(stamps.values()), truth, planar=False)
    assert set(r) == {"registration", "odometry"}
    assert r["registration"]["factors"] == 400 and r["registration"]["dof"] == 6
    assert 5.0 < r["registration"]["nees_mean"] < 7.0
    assert 45.0 < r["odometry"]["nees_mean"] < 63.0                  # σ claimed 3× too small: ~9 × 6
    planar = factor_nees(edges, stamps, list(stamps.values()), truth, planar=True)
    assert planar["registration"]["dof"] == 3 and 2.5 < planar["registration"]["nees_mean"] < 3.5


def test_factor_nees_skips_keyframes_without_truth_nearby():
    from common.slam.posegraph import Edge
    truth = _chain(3)
    edges = [Edge(0, 1, invert(truth[0]) @ truth[1], np.eye(6) * 1e-4, "odometry"),
             Edge(1, 2, invert(truth[1]) @ truth[2], np.eye(6) * 1e-4, "odometry")]
    stamps = {0: 0, 1: 1_000_000_000, 2: 5_000_000_000}
    r = factor_nees(edges, stamps, [0, 1_000_000_000, 2_000_000_000], truth, planar=False)
    assert r == {"odometry": {"factors": 1, "nees_mean": 0.0, "nees_median": 0.0, "dof": 6}}
