"""A camera turning away from where its fittest flies crowd keeps its pose (visual-only tracking).

The fittest flies of a population often sit on one well-textured surface at an image edge.  The
tracking reference is renewed only every few degrees, so a camera turning away from that edge loses
sight of all its flies within a frame or two; it then tracks against its newest view, with flies
spread over the whole image, instead of guessing from a weak constant-velocity prediction."""
from __future__ import annotations

import numpy as np

from common.camera import StereoCalibration
from common.geometry import R_BODY_OPTICAL, invert, make_transform, planar_from_transform, planar_pose
from common.slam.localiser import FlyLocaliser, LocaliserConfig
from tests.test_photometric import D, F, H, K, NORMAL, W, render

T_BASE_CAMERA = make_transform(R_BODY_OPTICAL)
CALIBRATION = StereoCalibration(width=W, height=H, fx=F, fy=F, cx_left=K[0, 2], cx_right=K[0, 2], cy=K[1, 2],
                                baseline=0.3, K_left=K.copy(), K_right=K.copy(), T_base_camera=T_BASE_CAMERA)
STEP_DEG, FRAMES = 3.0, 10


def population(T_ref_cam: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray]:
    """Flies on the plane seen by a camera at T_ref_cam (in its own frame): the fittest in a strip at the
    right image edge narrower than one frame's turn, weaker ones all over the image."""
    u = np.r_[rng.uniform(W - 20, W - 8, 1500), rng.uniform(10, W - 10, 2500)]
    v = rng.uniform(10, H - 10, len(u))
    rays = np.stack([(u - K[0, 2]) / F, (v - K[1, 2]) / F, np.ones(len(u))], 1) @ T_ref_cam[:3, :3].T
    o = T_ref_cam[:3, 3]
    points_ref = o + rays * ((D - NORMAL @ o) / (rays @ NORMAL))[:, None]
    points_cam = (points_ref - o) @ T_ref_cam[:3, :3]
    fitness = np.r_[rng.uniform(0.8, 0.9, 1500), rng.uniform(0.5, 0.7, 2500)]
    return points_cam, fitness


def test_a_camera_turning_away_from_its_fittest_flies_keeps_its_heading():
    rng = np.random.default_rng(0)
    loc = FlyLocaliser(T_BASE_CAMERA, LocaliserConfig(odometry="visual"), calibration=CALIBRATION)
    for k in range(FRAMES):
        T_map_base = planar_pose(0.0, 0.0, np.deg2rad(STEP_DEG * k))      # turning left on the spot
        T_ref_cam = invert(T_BASE_CAMERA) @ T_map_base @ T_BASE_CAMERA     # camera k in camera 0's frame
        points, fitness = population(T_ref_cam, rng)
        est = loc.update(k * 100_000_000, points, fitness, generation=500, image=render(T_ref_cam))
        x, y, yaw = planar_from_transform(invert(T_map_base) @ est.T_map_base)
        assert abs(np.degrees(yaw)) < 0.5 and np.hypot(x, y) < 0.05, (k, est.status)
        assert k < 2 or est.status == "ok", (k, est.status)
