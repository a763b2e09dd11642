"""The map-pose EKF behind fusion/pose: corrections from the localiser, delayed fixes, gating, statuses."""
from __future__ import annotations

import numpy as np
import pytest

from common.fusion.core import FusionCore
from common.fusion.planar import compose, covariance6, from_transform, to_transform
from common.fusion.pose_filter import FilterConfig
from common.geometry import pose_from_transform
from common.messages import PoseEstimate, TransformMsg, WheelOdometry, header, pose_msg, transform_of
from tests.test_fusion_odometry import PERIOD_NS, reading


def planar(msg) -> np.ndarray:
    return from_transform(transform_of(msg))


def drive(core: FusionCore, start: int, stop: int, step_m: float = 0.01):
    out = None
    for i in range(start, stop):
        out = core.on_odometry(reading(i, i * step_m, i * step_m))
    return out


def stamp(i: int) -> int:
    return 10**9 + i * PERIOD_NS


def map_to_odom(xyyaw, stamp_ns: int) -> TransformMsg:
    t, q = pose_from_transform(to_transform(xyyaw))
    return TransformMsg(child_frame_id="odom", translation=t, rotation=q, header=header(0, stamp_ns, "map"))


def slam_pose(xyyaw, sigma_xy: float, sigma_yaw: float, stamp_ns: int) -> PoseEstimate:
    cov = covariance6(np.diag([sigma_xy ** 2, sigma_xy ** 2, sigma_yaw ** 2]))
    return pose_msg(to_transform(xyyaw), cov, stamp_ns=stamp_ns, frame_id="map")


def test_without_corrections_the_map_pose_is_the_odom_pose():
    core = FusionCore()
    odom, pose = drive(core, 0, 50)
    assert pose.status == "odometry only" and odom.status == "ok"
    assert (odom.header.frame_id, pose.header.frame_id) == ("odom", "map")
    np.testing.assert_allclose(planar(pose), planar(odom))
    np.testing.assert_allclose(pose.covariance, odom.covariance)


def test_map_to_odom_correction_moves_fusion_pose_accordingly():
    core = FusionCore()
    drive(core, 0, 50)
    m2o = np.array([1.0, 2.0, np.pi / 2])
    assert core.on_map_to_odom(map_to_odom(m2o, stamp(49))).accepted
    odom, pose = drive(core, 50, 100)
    assert pose.status == "ok"
    np.testing.assert_allclose(planar(pose), compose(m2o, planar(odom)), atol=1e-9)
    assert planar(pose) == pytest.approx([1.0, 2.0 + 0.99, np.pi / 2], abs=1e-3)
    # A later, slightly different map→odom pulls the pose part of the way (both have uncertainty).
    before = planar(pose)
    core.on_map_to_odom(map_to_odom(m2o + [0.05, 0.0, 0.0], stamp(99)))
    _, pose = drive(core, 100, 101)
    moved = planar(pose)[0] - (before[0])
    assert 0.0 < moved < 0.05


def test_delayed_slam_pose_is_carried_forward_and_weighted_by_covariance():
    core = FusionCore()
    drive(core, 0, 100)
    core.on_slam_pose(slam_pose([0.0, 0.0, 0.0], 0.01, 0.01, stamp(0)))      # initialise map at odom start
    _, pose = drive(core, 100, 200)                                          # 1 m more: P grows
    prior = planar(pose)
    # The localiser says that at reading 150 (0.5 m ago) the robot was 0.10 m further left than we think.
    z150 = core.filter.odom_at(stamp(150)) + [0.0, 0.10, 0.0]
    tight = core.on_slam_pose(slam_pose(z150, 0.005, 0.002, stamp(150)))
    assert tight.accepted
    _, pose = drive(core, 200, 201)
    after = planar(pose)
    # Carried forward 0.5 m (heading unchanged): the correction lands on the current pose, mostly
    # believed because the fix is much tighter than the dead-reckoned pose.
    assert 0.07 < after[1] - prior[1] < 0.12
    assert after[0] == pytest.approx(prior[0] + 0.01, abs=0.01)
    assert pose.covariance[1, 1] < 0.5 * core.odometry.cov[1, 1]


def test_outlier_correction_is_rejected_flagged_then_accepted_if_it_persists():
    core = FusionCore(config=FilterConfig(max_rejections=3))
    drive(core, 0, 20)
    core.on_slam_pose(slam_pose([0.0, 0.0, 0.0], 0.01, 0.01, stamp(19)))
    drive(core, 20, 21)
    far = core.filter.odom_at(stamp(20)) + [5.0, 0.0, 0.0]
    r = core.on_slam_pose(slam_pose(far, 0.01, 0.01, stamp(20)))
    assert not r.accepted and "rejected" in r.reason
    odom, pose = drive(core, 21, 22)
    assert pose.status.startswith("flagged: correction rejected")
    assert planar(pose)[0] < 1.0
    for i in (21, 22):
        far = core.filter.odom_at(stamp(i)) + [5.0, 0.0, 0.0]
        r = core.on_slam_pose(slam_pose(far, 0.01, 0.01, stamp(i)))
    assert r.accepted and "re-initialised" in r.reason
    _, pose = drive(core, 22, 23)
    assert planar(pose)[0] > 5.0


def test_status_turns_stale_and_duplicates_and_bad_frames_are_not_fused():
    core = FusionCore(config=FilterConfig(stale_after_s=1.0))
    drive(core, 0, 10)
    assert core.on_slam_pose(slam_pose([0.0, 0.0, 0.0], 0.01, 0.01, stamp(9))).accepted
    dup = core.on_map_to_odom(map_to_odom([3.0, 0.0, 0.0], stamp(9)))
    assert not dup.accepted and dup.reason.startswith("duplicate")
    wrong = slam_pose([0.0, 0.0, 0.0], 0.01, 0.01, stamp(9))
    wrong.header.frame_id = "odom"
    assert "unusable" in core.on_slam_pose(wrong).reason
    _, pose = drive(core, 10, 40)
    assert pose.status == "ok"
    _, pose = drive(core, 40, 70)          # 1.2 s after the last fix
    assert pose.status == "odometry only"
    too_old = core.on_slam_pose(slam_pose([0.0, 0.0, 0.0], 0.01, 0.01, 10))
    assert not too_old.accepted and "history" in too_old.reason


def test_flagged_odometry_reading_republishes_the_held_pose_with_the_reason():
    core = FusionCore()
    odom0, _ = drive(core, 0, 30)
    nan = WheelOdometry(wheel_speeds=np.array([np.nan, 0.0]), wheel_radius_m=0.05, track_width_m=0.3,
                        header=header(99, stamp(30), "base_link"))
    odom, pose = core.on_odometry(nan)
    assert odom.status.startswith("flagged: non-finite") and pose.status == odom.status
    np.testing.assert_allclose(odom.position, odom0.position)
    assert odom.header.stamp_ns == odom0.header.stamp_ns
    assert core.counters.flagged == {"non_finite": 1}


def test_a_fix_at_1e308_is_rejected_before_and_after_initialisation_and_never_poisons_the_pose():
    core = FusionCore()
    drive(core, 0, 20)
    wild = core.on_slam_pose(slam_pose([1e308, 0.0, 0.0], 0.01, 0.01, stamp(19)))
    assert not wild.accepted and not core.filter.initialised
    assert core.on_slam_pose(slam_pose([0.0, 0.0, 0.0], 0.01, 0.01, stamp(19))).accepted
    drive(core, 20, 22)
    for i, x in ((21, 1e308), (21, -1e300)):
        assert not core.on_slam_pose(slam_pose([x, 0.0, 0.0], 0.01, 0.01, stamp(i))).accepted
    _, pose = drive(core, 22, 23)
    assert np.all(np.isfinite(pose.position)) and abs(planar(pose)[0]) < 1.0


def test_a_nan_mahalanobis_distance_is_a_rejection():
    core = FusionCore()
    drive(core, 0, 10)
    assert core.on_slam_pose(slam_pose([0.0, 0.0, 0.0], 0.01, 0.01, stamp(9))).accepted
    drive(core, 10, 12)
    core.filter.cov = np.full((3, 3), np.inf)       # an overflowed prior: every innovation's d² is NaN
    r = core.filter.correct_pose(stamp(11), [0.1, 0.0, 0.0], np.eye(3) * 1e-4)
    assert not r.accepted and "rejected" in r.reason


def test_the_first_fix_is_gated_against_the_prior_but_a_plausible_one_initialises():
    far = FusionCore()
    drive(far, 0, 10)
    assert not far.on_slam_pose(slam_pose([5e3, 0.0, 0.0], 0.01, 0.01, stamp(9))).accepted
    near = FusionCore()
    drive(near, 0, 10)
    assert near.on_slam_pose(slam_pose([20.0, -5.0, 2.0], 0.01, 0.01, stamp(9))).accepted


def test_rejected_fixes_that_disagree_with_each_other_never_re_initialise_the_filter():
    core = FusionCore(config=FilterConfig(max_rejections=3))
    drive(core, 0, 20)
    assert core.on_slam_pose(slam_pose([0.0, 0.0, 0.0], 0.01, 0.01, stamp(19))).accepted
    for k, i in enumerate(range(20, 26)):
        drive(core, i, i + 1)
        wild = core.filter.odom_at(stamp(i)) + [5.0 * (k + 1) * (-1) ** k, 3.0 * k, 0.0]
        assert not core.on_slam_pose(slam_pose(wild, 0.01, 0.01, stamp(i))).accepted
    _, pose = drive(core, 26, 27)
    assert abs(planar(pose)[0]) < 1.0
