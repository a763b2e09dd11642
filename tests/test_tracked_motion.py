"""Without wheels the pose graph's factors say what the camera knows: the tracked motion between
keyframes is as uncertain as the flies' depths make it, and a planar δ registration in a 6-DoF graph
says nothing of height, roll or pitch."""
from __future__ import annotations

import numpy as np
import pytest

from common.geometry import planar_pose
from common.slam.backend import tracked_motion_cov
from common.slam.posegraph import UNCONSTRAINED_SIGMA, PoseGraph, planar_covariance

FX, BASELINE = 718.856, 0.537       # KITTI's rectified left camera


def sigmas(cov):
    return np.sqrt(np.diag(cov))


def test_tracked_motion_is_as_uncertain_as_the_flies_depths_make_it():
    two_m = planar_pose(2.0, 0.0, 0.0)
    near, far = (sigmas(tracked_motion_cov(two_m, depth, FX, BASELINE, 1.0)) for depth in (10.0, 20.0))
    # a 1 px disparity error at 10 m is 10 / 386 of the depth: that share of the 2 m driven
    assert near[:3] == pytest.approx([2.0 * 10.0 / (FX * BASELINE)] * 3)
    assert far[:3] == pytest.approx(2 * near[:3])                       # twice as deep, twice as uncertain
    four_m = sigmas(tracked_motion_cov(planar_pose(4.0, 0.0, 0.0), 10.0, FX, BASELINE, 1.0))
    assert four_m[:3] == pytest.approx(2 * near[:3])                    # twice as far, twice as uncertain
    assert near[3:] == pytest.approx([1.0 / FX] * 3)                   # a pixel's worth of rotation
    standing = sigmas(tracked_motion_cov(np.eye(4), 10.0, FX, BASELINE, 1.0))
    assert np.all(standing > 0)                                          # floored: no axis is exact


def climbing_chain(loop_cov) -> PoseGraph:
    """Four 2 m steps climbing 0.25 m each (1 m in all), closed by a planar registration 0 -> 4 that is
    8 cm shorter and claims no climb (its z is whatever the estimate it was built from said)."""
    climb = planar_pose(2.0, 0.0, 0.0)
    climb[2, 3] = 0.25
    graph = PoseGraph(robust="cauchy", planar=False)
    pose = np.eye(4)
    graph.add_keyframe(0, pose)
    graph.add_prior(0, pose, np.diag([1e-4] * 6))
    for k in range(1, 5):
        pose = pose @ climb
        graph.add_keyframe(k, pose)
        graph.add_odometry(k - 1, k, climb, np.diag([0.02] * 3 + [0.002] * 3) ** 2)
    graph.add_registration(0, 4, planar_pose(7.9, 0.0, 0.0), loop_cov)
    graph.optimise(batch=True)
    return graph


def test_a_planar_loop_factor_leaves_a_6dof_chains_height_alone():
    planar = np.diag([0.02, 0.02, 0.002]) ** 2
    end = climbing_chain(planar_covariance(planar, *UNCONSTRAINED_SIGMA)).poses()[4]
    assert end[2, 3] == pytest.approx(1.0, abs=0.01)          # the height the chain says
    assert end[0, 3] == pytest.approx(7.92, abs=0.01)         # x pulled most of the way to the loop's
    # with a planar robot's 1 mm / 1 mrad out of the plane the loop contradicts the climb by hundreds of
    # sigmas: the robust kernel discards it, and its x with it
    assert climbing_chain(planar_covariance(planar)).poses()[4][0, 3] > 7.99
