"""Reference stereo visual odometry in plain OpenCV — the yardstick flyslam's localiser is measured against.

Per frame: ORB keypoints on the rectified left and right images, left-right matches kept when they lie on
the same row (epipolar constraint, ±``row_tol_px``) with positive disparity, triangulated to 3-D points in
the left camera's optical frame. Frame to frame: the current left keypoints are matched by descriptor
(Lowe ratio test) to the previous frame's 3-D points and ``cv2.solvePnPRansac`` gives the camera motion,
refined on the inliers with Levenberg-Marquardt. No map, no keyframes, no bundle adjustment: the error of
each step accumulates. A step with too few inliers repeats the previous motion (constant velocity).

Output convention as flyslam's eval: T_map_base (REP-103 base_link in map) with the map the base frame of
the first frame, via the calibration's T_base_camera: T_map_base = T_bc · T_cam0_cam · T_bc⁻¹.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from common.camera import StereoCalibration
from common.geometry import invert


@dataclass
class StereoVOConfig:
    features: int = 3000
    row_tol_px: float = 1.5          # rectified: a left-right match lies on the same image row
    min_disparity_px: float = 1.0    # positive disparity, and not so small that depth is meaningless
    ratio: float = 0.8               # Lowe ratio test for frame-to-frame matches
    ransac_reprojection_px: float = 2.0
    min_inliers: int = 15
    refine: bool = True


def _grey(img: np.ndarray) -> np.ndarray:
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)


class StereoVO:
    """Frame-to-frame ORB + PnP stereo odometry; :meth:`track` returns T_map_base for each new pair."""

    def __init__(self, calib: StereoCalibration, config: StereoVOConfig | None = None):
        self.calib = calib
        self.config = config or StereoVOConfig()
        self.orb = cv2.ORB_create(nfeatures=self.config.features)
        self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self.K = np.array([[calib.fx, 0, calib.cx_left], [0, calib.fy, calib.cy], [0, 0, 1]], np.float64)
        self.T_bc = np.asarray(calib.T_base_camera, np.float64)
        self.T_cam0_cam = np.eye(4)
        self.last_motion = np.eye(4)         # T_prev_cur of the last step
        self.prev_points = None              # (M, 3) in the previous left camera's optical frame
        self.prev_desc = None
        self.inliers: list[int] = []         # PnP inliers per step (0: fell back to constant velocity)

    def stereo_points(self, left: np.ndarray, right: np.ndarray):
        """(keypoints, descriptors) of the left image, and (3-D points, their descriptors) from stereo."""
        c = self.config
        kl, dl = self.orb.detectAndCompute(_grey(left), None)
        kr, dr = self.orb.detectAndCompute(_grey(right), None)
        if dl is None or dr is None or len(kl) == 0 or len(kr) == 0:
            return kl, dl, np.zeros((0, 3)), None
        pl = np.array([k.pt for k in kl], np.float64)
        pr = np.array([k.pt for k in kr], np.float64)
        # Rectified pair: search each left keypoint's match only among right keypoints on its row.
        mask = (np.abs(pl[:, None, 1] - pr[None, :, 1]) <= c.row_tol_px).astype(np.uint8)
        matches = self.matcher.match(dl, dr, mask) if mask.any() else []
        if not matches:
            return kl, dl, np.zeros((0, 3)), None
        il = np.array([m.queryIdx for m in matches])
        ir = np.array([m.trainIdx for m in matches])
        dist = np.array([m.distance for m in matches])
        disparity = (pl[il, 0] - self.calib.cx_left) - (pr[ir, 0] - self.calib.cx_right)
        ok = (disparity >= c.min_disparity_px) & (np.abs(pl[il, 1] - pr[ir, 1]) <= c.row_tol_px) & (dist <= 64)
        il, disparity = il[ok], disparity[ok]
        z = self.calib.fx * self.calib.baseline / disparity
        x = (pl[il, 0] - self.calib.cx_left) * z / self.calib.fx
        y = (pl[il, 1] - self.calib.cy) * z / self.calib.fy
        return kl, dl, np.stack([x, y, z], 1), dl[il]

    def track(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        c = self.config
        kl, dl, points, pdesc = self.stereo_points(left, right)
        motion, n_in = None, 0
        if self.prev_desc is not None and dl is not None and len(self.prev_points) >= c.min_inliers:
            pairs = self.matcher.knnMatch(self.prev_desc, dl, k=2)
            good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < c.ratio * p[1].distance]
            if len(good) >= c.min_inliers:
                obj = self.prev_points[[m.queryIdx for m in good]]
                img = np.array([kl[m.trainIdx].pt for m in good], np.float64)
                ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, self.K, None, iterationsCount=200,
                                                         reprojectionError=c.ransac_reprojection_px,
                                                         confidence=0.999, flags=cv2.SOLVEPNP_ITERATIVE)
                if ok and inl is not None and len(inl) >= c.min_inliers:
                    inl = inl.ravel()
                    if c.refine:
                        rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], self.K, None, rvec, tvec)
                    T_cur_prev = np.eye(4)
                    T_cur_prev[:3, :3] = cv2.Rodrigues(rvec)[0]
                    T_cur_prev[:3, 3] = tvec.ravel()
                    motion, n_in = invert(T_cur_prev), len(inl)
        if self.prev_desc is not None:
            if motion is None:
                motion = self.last_motion
            self.T_cam0_cam = self.T_cam0_cam @ motion
            self.last_motion = motion
            self.inliers.append(n_in)
        self.prev_points, self.prev_desc = points, pdesc
        return self.T_bc @ self.T_cam0_cam @ invert(self.T_bc)
