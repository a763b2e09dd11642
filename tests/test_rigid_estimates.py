"""Every pose the localiser gives out is rigid, whatever rounding its inputs carry.

Its estimates become keyframes, tracking references and graph corrections, and each correction was
composed with the last: on a long real sequence that revisits a street, the skew of a rotation doubled
with each keyframe until, after ~270 frames, the evolver refused the motion it was given as not rigid
and `flyslam eval` stopped."""
from __future__ import annotations

import numpy as np

from common.geometry import planar_pose
from common.slam.localiser import FlyLocaliser, LocaliserConfig


def _skew(R: np.ndarray) -> float:
    return float(np.abs(R @ R.T - np.eye(3)).max())


def test_an_estimate_from_skewed_odometry_is_rigid():
    loc = FlyLocaliser(np.eye(4), LocaliserConfig())
    skewed = planar_pose(1.0, 0.5, 0.3)
    skewed[:3, :3] *= 1 + 1e-6                 # float32 odometry, or a chain of composed estimates
    few = np.zeros((0, 3), np.float32)
    for k in range(3):
        est = loc.update((k + 1) * 100_000_000, few, np.zeros(0, np.float32), T_odom_base=skewed)
        assert _skew(est.T_map_base[:3, :3]) < 1e-12
        assert np.allclose(est.T_map_base[:2, 3], [1.0, 0.5])


def test_a_skewed_graph_correction_leaves_the_state_it_moves_rigid():
    loc = FlyLocaliser(np.eye(4), LocaliserConfig(odometry="visual"))
    loc.relocalised(0, planar_pose(2.0, 1.0, 0.2))
    loc._track_update(100_000_000, planar_pose(3.0, 1.0, 0.2))
    C = planar_pose(0.1, -0.05, 0.01)
    C[:3, :3] *= 1 + 1e-6
    for _ in range(40):                 # one correction per keyframe, as on a long revisiting run
        loc._apply_correction(C)
    assert _skew(loc.T_map_odom[:3, :3]) < 1e-12
    assert _skew(loc._track.last_T_map_base[:3, :3]) < 1e-12


def _nearest_rotation(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def test_orthonormalised_gives_the_nearest_rotation_for_rounding_and_for_worse():
    from common.geometry import make_transform, orthonormalised, so3_exp
    rng = np.random.default_rng(3)
    for scale in (0.0, 1e-12, 1e-9, 3e-8, 5e-7, 1e-4, 0.3):      # rounding, up to a sheared matrix
        for _ in range(20):
            M = so3_exp(rng.normal(0, 1.0, 3)) @ (np.eye(3) + rng.normal(0, scale, (3, 3)))
            T = make_transform(M, rng.normal(0, 5.0, 3))
            out = orthonormalised(T)
            assert _skew(out[:3, :3]) < 1e-12 and np.linalg.det(out[:3, :3]) > 0
            assert np.abs(out[:3, :3] - _nearest_rotation(M)).max() < 1e-11
            assert np.array_equal(out[:3, 3], T[:3, 3]) and np.array_equal(out[3], [0, 0, 0, 1])


def test_orthonormalised_turns_a_reflection_into_a_rotation():
    from common.geometry import make_transform, orthonormalised
    out = orthonormalised(make_transform(np.diag([1.0, 1.0, -1.0])))
    assert np.linalg.det(out[:3, :3]) > 0 and _skew(out[:3, :3]) < 1e-12
