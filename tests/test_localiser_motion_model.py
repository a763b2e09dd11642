"""Visual-only prediction (constant velocity): how far from it a fix may land.

A fix 10° off the prediction right after a confirmed update is a wrong minimum (the next prediction
would double that turn); after two updates that nothing confirmed, the prediction itself may be that
far off (a turn that ended), so the same fix is believed."""
from __future__ import annotations

import numpy as np

from common.geometry import planar_pose
from common.slam.localiser import FlyLocaliser, LocaliserConfig


def _visual_localiser_moving(step_m: float = 1.0) -> FlyLocaliser:
    loc = FlyLocaliser(np.eye(4), LocaliserConfig(odometry="visual"))
    loc.relocalised(0, np.eye(4))
    loc._track_update(100_000_000, planar_pose(step_m, 0.0, 0.0))     # moving 1 m per 0.1 s
    return loc


def test_a_fix_far_from_a_fresh_prediction_is_refused_and_one_near_it_is_not():
    loc = _visual_localiser_moving()
    T_pred, source = loc._predict(200_000_000, None)
    assert source == "constant velocity" and np.isclose(T_pred[0, 3], 2.0)
    assert loc._implausible(T_pred, T_pred @ planar_pose(0.1, 0.05, np.deg2rad(2.0)), source) == ""
    assert "limit" in loc._implausible(T_pred, T_pred @ planar_pose(0.0, 0.0, np.deg2rad(10.0)), source)
    assert "limit" in loc._implausible(T_pred, T_pred @ planar_pose(1.5, 0.0, 0.0), source)


def test_the_limit_grows_while_nothing_confirms_the_prediction():
    loc = _visual_localiser_moving()
    T_pred, source = loc._predict(200_000_000, None)
    turned = T_pred @ planar_pose(0.0, 0.0, np.deg2rad(10.0))
    assert loc._implausible(T_pred, turned, source)
    loc._updates_since_fix = 2
    loc._steps_since_fix = loc._prediction_steps(200_000_000)
    assert loc._implausible(T_pred, turned, source) == ""


def test_the_limit_grows_with_the_time_since_the_last_fix_when_populations_were_skipped():
    """Live, a localiser busy with one population misses the next ones: 0.6 s after the last fix the
    prediction has run six steps on a velocity nothing has confirmed since."""
    loc = _visual_localiser_moving()
    T_pred, source = loc._predict(700_000_000, None)
    off = T_pred @ planar_pose(-2.0, 0.3, 0.0)          # 2 m behind the prediction: the speed was off
    loc._steps_since_fix = loc._prediction_steps(200_000_000)
    assert loc._implausible(T_pred, off, source)
    loc._steps_since_fix = loc._prediction_steps(700_000_000)
    assert loc._implausible(T_pred, off, source) == ""


def test_a_fix_after_unconfirmed_updates_teaches_the_motion_since_the_last_fix():
    """The updates that nothing confirmed carried the prediction on; the next fix's motion is measured
    from the last fix over the whole time, not as one step from the last placeholder."""
    loc = _visual_localiser_moving()
    loc._track_update(200_000_000, planar_pose(2.0, 0.0, 0.0), registered=False)    # placeholders
    loc._track_update(300_000_000, planar_pose(3.0, 0.0, 0.0), registered=False)
    loc._track_update(400_000_000, planar_pose(2.4, 0.0, 0.0))                      # the fix: slower
    T_next, _ = loc._predict(500_000_000, None)
    assert np.isclose(T_next[0, 3], 2.4 + 0.1 * (2.4 - 1.0) / 0.3)                 # 0.47 m a step, not -0.6
