"""Small synthetic stereo pairs (tests, examples): a textured fronto-parallel plane at a known depth."""
from __future__ import annotations

import cv2
import numpy as np

from common.camera import StereoCalibration


def textured_plane_pair(disparity: float = 12.0, width: int = 160, height: int = 120, seed: int = 0,
                        flat_right_half: bool = False):
    """(calib, left, right, depth): RGB uint8 images of a plane seen at a constant integer disparity.

    With ``flat_right_half`` the right half of the left image (and its match) is a uniform grey.
    """
    calib = StereoCalibration.ideal(width=width, height=height, baseline=0.1)
    rng = np.random.default_rng(seed)
    big = rng.integers(0, 256, (height, width + int(disparity) + 8, 3)).astype(np.float32)
    big = cv2.GaussianBlur(big, (0, 0), 1.0)
    big = np.clip((big - big.mean()) * 3 + 128, 0, 255).astype(np.uint8)
    d = int(disparity)
    left = np.ascontiguousarray(big[:, :width])
    right = np.ascontiguousarray(big[:, d:d + width])   # right(x − d) = left(x): x_right = x_left − d
    if flat_right_half:
        left[:, width // 2:] = 128
        right[:, width // 2 - d:] = 128   # the same scene points, seen d pixels further left
    depth = calib.fx * calib.baseline / disparity
    return calib, left, right, depth
