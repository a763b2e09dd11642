"""The shared accuracy measure: fittest fraction, tolerance, unknown ground truth, outside flies."""
import numpy as np
import pytest

from common.camera import StereoCalibration
from common.fly.metrics import inlier_fraction, inlier_stats


@pytest.fixture
def scene():
    calib = StereoCalibration.ideal(width=100, height=80, baseline=0.1)
    gt = np.full((80, 100), 10.0, np.float32)
    gt[:, 50:] = np.inf                      # unknown ground truth on the right half
    return calib, gt


def test_counts_fittest_flies_against_ground_truth(scene):
    calib, gt = scene
    u = np.array([10.0, 20.0, 30.0, 40.0, 60.0])
    v = np.full(5, 40.0)
    d = np.array([10.4, 10.0, 12.0, 9.2, 10.0])   # 0.4 ok, exact, 2 px off, 0.8 ok, unknown GT
    pts = calib.backproject(u, v, d)
    fit = np.array([5.0, 4.0, 3.0, 2.0, 1.0], np.float32)
    s = inlier_stats(pts, fit, calib, gt, keep=1.0, tol_px=1.0)
    assert (s.kept, s.skipped_unknown_gt, s.counted, s.inliers) == (5, 1, 4, 3)
    assert s.fraction == pytest.approx(0.75)
    # keep=0.6 → the three fittest: two inliers out of three.
    assert inlier_fraction(pts, fit, calib, gt, keep=0.6) == pytest.approx(2 / 3)
    # Reordering fitness changes which flies count.
    assert inlier_fraction(pts, fit[::-1].copy(), calib, gt, keep=0.4) == pytest.approx(1.0)  # 9.2 and unknown
    assert inlier_fraction(pts, fit, calib, gt, keep=1.0, tol_px=0.3) == pytest.approx(0.25)


def test_flies_outside_the_image_count_as_outliers(scene):
    calib, gt = scene
    pts = np.concatenate([calib.backproject([10.0], [40.0], [10.0]),
                          calib.backproject([-20.0], [40.0], [10.0]), [[0.0, 0.0, -1.0]]])
    s = inlier_stats(pts, np.array([1.0, 2.0, 3.0]), calib, gt, keep=1.0)
    assert (s.counted, s.inliers) == (3, 1)


def test_bad_arguments(scene):
    calib, gt = scene
    with pytest.raises(ValueError, match="keep"):
        inlier_fraction(np.zeros((2, 3)), np.zeros(2), calib, gt, keep=0)
    with pytest.raises(ValueError, match="gt_disparity"):
        inlier_fraction(np.zeros((2, 3)), np.zeros(2), calib, gt[:10])
    with pytest.raises(ValueError, match="positions"):
        inlier_fraction(np.zeros((2, 2)), np.zeros(2), calib, gt)
