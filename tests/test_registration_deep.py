"""Registration on a deep outdoor scene: weights, co-visibility and the StereoModel variant."""
import numpy as np
import pytest

from common.geometry import R_BODY_OPTICAL, make_transform
from common.registration import (
    LocalCorrelationField,
    PopulationError,
    StereoModel,
    covisible_masks,
    depth_sigma,
    depth_weights,
    footprint_weights,
    register_planar,
    scenes,
)


def test_depth_sigma_grows_with_depth_squared_and_weights_fall_off():
    rig = scenes.deep_rig()
    pts = np.array([[0, 0, 5.0], [0, 0, 10.0], [0, 0, 30.0]])
    s = depth_sigma(pts, rig, disparity_sigma=1.0)
    assert s[1] / s[0] == pytest.approx(4.0)
    assert s[2] > 3.0        # one pixel at 30 m with a 0.5 m baseline is metres of depth
    w = depth_weights(pts, rig)
    assert w[0] > 0.9 and w[0] > w[1] > w[2] and w[2] < 0.05
    assert footprint_weights(pts, rig)[2] / footprint_weights(pts, rig)[0] == pytest.approx(36.0)


def test_body_frame_weights_use_the_camera_mount():
    rig = scenes.deep_rig()
    rig.T_base_camera = make_transform(R_BODY_OPTICAL, [0.2, 0, 1.2])
    p_opt = np.array([[1.0, 0.5, 12.0]])
    p_body = p_opt @ R_BODY_OPTICAL.T + [0.2, 0, 1.2]
    assert depth_weights(p_body, rig, frame="body") == pytest.approx(depth_weights(p_opt, rig))
    with pytest.raises(PopulationError, match="frame"):
        depth_weights(p_opt, rig, frame="map")


def test_covisible_masks_drop_what_the_other_camera_cannot_see():
    rig = scenes.deep_rig()
    A = np.array([[0, 0, 10.0], [12.0, 0, 10.0], [0, 0, 2.5]])     # ahead, far right, close
    T_f = make_transform(None, [0, 0, 1.0])                          # second camera 1 m ahead
    ma, mb = covisible_masks(A, A, T_f, rig, depth_range=(2.0, 40.0))
    assert ma.tolist() == [True, False, False]   # 2.5 m is 1.5 m from the second camera: too close


def test_visible_mask_needs_both_stereo_projections_inside_the_images():
    """A point seen near the left image's left edge projects off the right image (by its disparity):
    no fly can stand there, so it is not visible to the rig."""
    from common.registration import visible_mask
    rig = scenes.deep_rig()
    z = 3.0
    disparity = rig.fx * rig.baseline / z                     # tens of pixels at 3 m
    u_strip = 0.03 * rig.width + 0.5 * disparity               # inside the left image's margin-free area
    u_centre = rig.cx_left
    pts = np.array([[(u - rig.cx_left) * z / rig.fx, 0.0, z] for u in (u_strip, u_centre)])
    ul, ur, _ = rig.project(pts)
    assert 0.03 * rig.width < ul[0] and ur[0] < 0.03 * rig.width   # left inside, right outside
    assert visible_mask(pts, rig).tolist() == [False, True]


def test_local_correlation_peaks_at_alignment():
    rng = np.random.default_rng(0)
    B = rng.uniform(-3, 3, size=(2000, 3))
    fld = LocalCorrelationField(B, 0.1, 0.5)
    c0 = fld.correlation(B + rng.normal(0, 0.01, B.shape))
    assert c0 > fld.correlation(B + [0.2, 0, 0]) > fld.correlation(B + [0.6, 0, 0]) >= 0


def test_stereo_model_recovers_motion_between_independent_deep_views(deep_street_views):
    rig, truth, A, B = deep_street_views
    res = register_planar(A, B, stereo=StereoModel(rig, depth_range=(2.0, 40.0)))
    assert res.ok, res.reason
    err = np.hypot(*(res.params[:2] - truth[:2]))
    assert err < 0.3
    assert abs(res.params[2] - truth[2]) < np.deg2rad(2.0)
    # The paper's δ on the same data is pulled towards zero motion.
    paper = register_planar(A, B)
    assert np.hypot(*(paper.params[:2] - truth[:2])) > err


def test_stereo_model_in_the_body_frame_matches_the_optical_result(deep_street_views):
    rig, truth, A, B = deep_street_views
    mounted = scenes.deep_rig()
    mounted.T_base_camera = make_transform(R_BODY_OPTICAL, [0.3, 0.0, 1.2])
    T_bc = mounted.T_base_camera

    def to_body(P):
        return P @ T_bc[:3, :3].T + T_bc[:3, 3]
    optical = register_planar(A, B, stereo=StereoModel(rig))
    body = register_planar(to_body(A), to_body(B), plane="body", stereo=StereoModel(mounted))
    assert body.ok, body.reason
    # The same motion seen in base_link: f_body = T_base_cam · f_optical · T_cam_base.
    expected = T_bc @ optical.T @ np.linalg.inv(T_bc)
    np.testing.assert_allclose(body.T[:3, 3], expected[:3, 3], atol=0.05)
    assert body.params[2] == pytest.approx(-optical.params[2], abs=np.deg2rad(0.3))
