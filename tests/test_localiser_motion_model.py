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
    assert loc._implausible(T_pred, turned, source) == ""
