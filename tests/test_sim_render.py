"""Renderer geometry and photometry: what a stereo algorithm downstream relies on."""
import cv2
import numpy as np
import pytest

from common.geometry import invert, transform_points
from common.sim import Simulator, parse_scenario


def wall_scenario(distance=3.0, texture=None, light_panel=False, **extra):
    """Robot at the origin facing +x; a big wall at x = distance (+ an optional emissive panel)."""
    data = {
        "name": "wall",
        "robot": {"start": [0.0, 0.0, 0.0]},
        "camera": {"height_m": 0.5, "forward_m": 0.0, "read_noise": 0.5, "shot_noise": 0.0, "vignetting": 0.0},
        "lighting": {"ambient": 0.9, "sun_intensity": 0.0},
        "walls": [{"from": [distance, -20.0], "to": [distance, 20.0], "z": [-5.0, 10.0],
                   "texture": texture or {"kind": "noise", "size_m": [1.0, 1.0], "contrast": 2.0, "seed": 3}}],
    }
    if light_panel:
        data["walls"] = []
        data["panels"] = [{"origin": [distance, 0.4, 0.2], "u": [0.0, -0.7, 0.0], "v": [0.0, 0.0, 0.6],
                           "texture": "light"}]
    data.update(extra)
    return parse_scenario(data, "wall-test")


def test_world_points_land_where_the_camera_model_projects_them():
    sim = Simulator(wall_scenario(4.0, light_panel=True), seed=0, width=320, height=240)
    frame = sim.render()
    cal = sim.calibration
    # Panel corners in map → left optical frame → pixels, with the project's own camera model.
    corners = np.array([[4.0, 0.4, 0.2], [4.0, -0.3, 0.2], [4.0, -0.3, 0.8], [4.0, 0.4, 0.8]])
    T_cam_map = invert(frame.T_map_base @ cal.T_base_camera)
    u, _, v = cal.project(transform_points(T_cam_map, corners))
    mask = np.isfinite(frame.depth)
    rows, cols = np.nonzero(mask)
    # Pixel centres are at integer coordinates: the covered pixels are those inside [min, max].
    assert cols.min() == pytest.approx(np.ceil(u.min()), abs=1)
    assert cols.max() == pytest.approx(np.floor(u.max()), abs=1)
    assert rows.min() == pytest.approx(np.ceil(v.min()), abs=1)
    assert rows.max() == pytest.approx(np.floor(v.max()), abs=1)
    # The panel's depth is the analytic Z of the plane, and the sky has none.
    assert np.allclose(frame.depth[mask], 4.0, atol=1e-4)
    assert np.isinf(frame.depth[~mask]).all()


def test_floor_depth_matches_the_analytic_ground_plane():
    data = {"robot": {"start": [0.0, 0.0, 0.0]}, "camera": {"height_m": 0.45, "forward_m": 0.0},
            "floor": {"x": [-50.0, 50.0], "y": [-50.0, 50.0], "texture": "tiles"}}
    sim = Simulator(parse_scenario(data, "floor-test"), seed=0, width=160, height=120)
    d = sim.render().depth
    cal = sim.calibration
    rows = np.arange(int(cal.cy) + 5, cal.height)
    expected = 0.45 * cal.fy / (rows - cal.cy)  # ray through row v meets z = 0 at Z = h·fy/(v − cy)
    np.testing.assert_allclose(d[rows, cal.width // 2], expected, rtol=1e-4)
    assert np.isinf(d[: int(cal.cy) - 1]).all()  # above the horizon: sky


def test_block_matching_on_a_rendered_wall_recovers_the_analytic_disparity():
    distance = 2.5
    sim = Simulator(wall_scenario(distance), seed=1, width=320, height=240)
    f = sim.render()
    cal = sim.calibration
    expected = cal.disparity_from_depth(distance)
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=64, blockSize=7, P1=8 * 49, P2=32 * 49,
                                 uniquenessRatio=5, mode=cv2.STEREO_SGBM_MODE_HH)
    disp = sgbm.compute(cv2.cvtColor(f.left, cv2.COLOR_RGB2GRAY), cv2.cvtColor(f.right, cv2.COLOR_RGB2GRAY))
    disp = disp[40:-40, 100:-40].astype(np.float32) / 16.0
    valid = disp > 0
    assert valid.mean() > 0.9
    assert np.median(disp[valid]) == pytest.approx(expected, abs=0.25)
    assert np.mean(np.abs(disp[valid] - expected) < 1.0) > 0.9


def test_render_is_deterministic_for_a_seed_and_noise_differs_between_seeds():
    scn = wall_scenario()
    a = Simulator(scn, seed=7, width=96, height=72).render()
    b = Simulator(scn, seed=7, width=96, height=72).render()
    c = Simulator(scn, seed=8, width=96, height=72).render()
    assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    assert np.array_equal(a.depth, b.depth)
    assert not np.array_equal(a.left, c.left)
    assert np.abs(a.left.astype(int) - c.left.astype(int)).mean() < 3  # only the noise differs


def test_right_camera_has_the_configured_gain_and_offset():
    flat = {"kind": "paint", "color": [120, 120, 120], "contrast": 0.0}
    scn = wall_scenario(3.0, texture=flat)
    scn.camera.gain_right, scn.camera.offset_right = 1.2, 5.0
    f = Simulator(scn, seed=0, width=96, height=72).render()
    left, right = f.left.astype(float).mean(), f.right.astype(float).mean()
    assert right == pytest.approx(1.2 * left + 5.0, abs=1.0)


def test_sensor_noise_has_the_configured_level():
    flat = {"kind": "paint", "color": [120, 120, 120], "contrast": 0.0}
    scn = wall_scenario(3.0, texture=flat)
    scn.camera.read_noise = 3.0
    f = Simulator(scn, seed=0, width=160, height=120).render()
    assert f.left.astype(float).std() == pytest.approx(3.0, rel=0.15)


def test_mip_mapping_averages_fine_texture_instead_of_aliasing():
    # 1 cm checker squares 20 m away are ~100× smaller than a pixel: a filtered renderer shows a flat
    # mid grey; point sampling would show random black/white pixels (std ≈ half the contrast).
    fine = {"kind": "checker", "color": [255, 255, 255], "size_m": [0.02, 0.02], "seed": 0}
    scn = wall_scenario(20.0, texture=fine)
    scn.camera.read_noise = 0.0
    f = Simulator(scn, seed=0, width=160, height=120).render()
    grey = f.left.astype(float).mean(axis=2)[np.isfinite(f.depth)]
    assert grey.size > 5000
    assert grey.std() < 4.0
    assert 80 < grey.mean() < 200


def test_motion_blur_smears_along_the_motion_only_when_enabled():
    scn = wall_scenario(1.5, path={"mode": "velocity", "segments": [[2.0, 0.0, 1.5]]})
    scn.camera.exposure_time_s = 0.03
    sharp = Simulator(scn, seed=0, width=160, height=120)
    blurred = Simulator(scn, seed=0, width=160, height=120, motion_blur_samples=5)
    sharp.advance(0.5)
    blurred.advance(0.5)
    a, b = sharp.render(), blurred.render()
    grad = lambda img: np.abs(np.diff(img.astype(float).mean(axis=2), axis=1)).mean()
    assert grad(b.left) < 0.8 * grad(a.left)
    np.testing.assert_array_equal(a.depth, b.depth)


def test_sgbm_on_the_rendered_corridor_agrees_with_the_ground_truth_depth():
    # End-to-end consistency of left, right and depth over a whole realistic frame (floor, walls at
    # grazing angles, boxes, decals): what the Fly algorithm's evaluation depends on.
    from common.sim import load_scenario, scenario_path
    sim = Simulator(load_scenario(scenario_path("corridor")), seed=0, width=320, height=240)
    sim.advance(3.0)
    f = sim.render()
    gt = sim.calibration.disparity_from_depth(f.depth)
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=64, blockSize=7, P1=8 * 49, P2=32 * 49,
                                 uniquenessRatio=10, mode=cv2.STEREO_SGBM_MODE_HH)
    d = sgbm.compute(cv2.cvtColor(f.left, cv2.COLOR_RGB2GRAY),
                     cv2.cvtColor(f.right, cv2.COLOR_RGB2GRAY)).astype(np.float32) / 16
    valid = (d > 0) & np.isfinite(gt)
    valid[:, :70] = False  # no match possible left of the disparity search range
    err = np.abs(d - gt)[valid]
    assert valid.mean() > 0.5
    assert np.mean(err < 1.0) > 0.8
    assert np.median(err) < 0.5


@pytest.mark.parametrize("flip, visible", [(False, True), (True, False)])
def test_decals_show_on_their_front_side_only(flip, visible):
    wall = {"from": [3.0, 5.0], "to": [3.0, -5.0], "z": [0.0, 3.0],
            "texture": {"kind": "paint", "color": [200, 200, 200], "contrast": 0.0}}
    # from → to runs along +y, so the front (left of it) faces −x, towards the robot.
    poster = {"from": [3.0, -0.5], "to": [3.0, 0.5], "z": [0.2, 0.9], "flip": flip,
              "texture": {"kind": "paint", "color": [20, 20, 200], "contrast": 0.0}}
    scn = parse_scenario({"robot": {"start": [0.0, 0.0, 0.0]}, "walls": [wall], "posters": [poster],
                          "camera": {"height_m": 0.5, "forward_m": 0.0}}, "decal")
    f = Simulator(scn, seed=0, width=64, height=48).render()
    centre = f.left[24, 32].astype(int)
    assert (centre[2] - centre[0] > 100) == visible   # blue poster vs grey wall
    assert f.depth[24, 32] == pytest.approx(3.0, abs=1e-4)  # the decal lies on the wall
