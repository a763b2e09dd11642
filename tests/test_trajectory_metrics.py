import numpy as np
import pytest

from common.geometry import planar_pose
from common.trajectory_metrics import TrajectoryMismatch, evaluate


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
