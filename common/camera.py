"""Rectified stereo camera model.

Everything downstream of a source (the evolver, the localiser, the bridge) works on *rectified* images:
both cameras share the focal lengths and the row ``v``; the right camera sits ``baseline`` metres along
the left camera's optical +x axis.  A point (X, Y, Z) in the left optical frame projects to

    u_left  = fx·X/Z + cx_left        v = fy·Y/Z + cy
    u_right = fx·(X − B)/Z + cx_right

so the disparity d = u_left − u_right = fx·B/Z + (cx_left − cx_right).  Middlebury calls
``cx_right − cx_left`` *doffs*; for an ordinary rectified rig it is 0.

The raw-camera parameters (K, D, R, P per camera, as produced by cv2.stereoRectify) travel with the model
so a calibration can be published and re-read without loss.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class CalibrationError(ValueError):
    """A calibration that is inconsistent in itself or with the images it is used on."""


@dataclass
class StereoCalibration:
    width: int
    height: int
    fx: float
    fy: float
    cx_left: float
    cx_right: float
    cy: float
    baseline: float  # metres, right camera along +x of the left optical frame
    # Raw-camera parameters (before rectification). Identity/zero for an already-rectified source.
    K_left: np.ndarray = field(default_factory=lambda: np.eye(3))
    D_left: np.ndarray = field(default_factory=lambda: np.zeros(5))
    R_left: np.ndarray = field(default_factory=lambda: np.eye(3))
    K_right: np.ndarray = field(default_factory=lambda: np.eye(3))
    D_right: np.ndarray = field(default_factory=lambda: np.zeros(5))
    R_right: np.ndarray = field(default_factory=lambda: np.eye(3))
    # Pose of the left optical frame in base_link (REP-103 body frame); identity when unknown.
    T_base_camera: np.ndarray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self):
        self.validate()

    # ----------------------------------------------------------------------------------- checks
    def validate(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise CalibrationError(f"image size must be positive, got {self.width}×{self.height}")
        for name in ("fx", "fy", "baseline"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise CalibrationError(f"{name} must be a positive finite number, got {v}")
        for name in ("cx_left", "cx_right", "cy"):
            if not np.isfinite(getattr(self, name)):
                raise CalibrationError(f"{name} is not finite")
        if self.baseline > 10:
            raise CalibrationError(f"baseline {self.baseline} m is implausible (units should be metres)")
        T = np.asarray(self.T_base_camera, dtype=float)
        if T.shape != (4, 4) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-5):
            raise CalibrationError("T_base_camera must be a 4×4 rigid transform")

    def check_image(self, image: np.ndarray, which: str = "image") -> None:
        """Raise CalibrationError when an image does not have the calibrated size."""
        h, w = image.shape[:2]
        if (w, h) != (self.width, self.height):
            raise CalibrationError(
                f"{which} is {w}×{h} but the calibration is for {self.width}×{self.height}")

    # ------------------------------------------------------------------------------ projection
    @property
    def doffs(self) -> float:
        """cx_right − cx_left (Middlebury's name); 0 for a conventionally rectified rig."""
        return self.cx_right - self.cx_left

    @property
    def K_rectified(self) -> np.ndarray:
        """3×3 intrinsics of the rectified left image, the one every algorithm sees (``K_left`` is the
        raw camera's before rectification, or whatever the source gave: not for the images)."""
        return self.P_left[:, :3].copy()

    @property
    def P_left(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx_left, 0], [0, self.fy, self.cy, 0], [0, 0, 1, 0]])

    @property
    def P_right(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx_right, -self.fx * self.baseline],
                         [0, self.fy, self.cy, 0], [0, 0, 1, 0]])

    def project(self, points: np.ndarray):
        """Project (N, 3) left-optical points. Returns (u_left, u_right, v) arrays (float64).

        Points with Z <= 0 get NaN coordinates.
        """
        p = np.asarray(points, dtype=np.float64)
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_z = np.where(z > 0, 1.0 / z, np.nan)
        u_left = self.fx * p[:, 0] * inv_z + self.cx_left
        u_right = self.fx * (p[:, 0] - self.baseline) * inv_z + self.cx_right
        v = self.fy * p[:, 1] * inv_z + self.cy
        return u_left, u_right, v

    def disparity_from_depth(self, z):
        return self.fx * self.baseline / np.asarray(z, dtype=np.float64) - self.doffs

    def depth_from_disparity(self, d):
        with np.errstate(divide="ignore"):
            return self.fx * self.baseline / (np.asarray(d, dtype=np.float64) + self.doffs)

    def backproject(self, u_left, v, disparity) -> np.ndarray:
        """(N, 3) left-optical points from left pixel coordinates and disparity."""
        z = self.depth_from_disparity(disparity)
        x = (np.asarray(u_left, dtype=np.float64) - self.cx_left) * z / self.fx
        y = (np.asarray(v, dtype=np.float64) - self.cy) * z / self.fy
        return np.stack([x, y, z], axis=-1)

    # ---------------------------------------------------------------------------- construction
    @classmethod
    def ideal(cls, width=640, height=480, fx=None, baseline=0.12, hfov_deg=None, T_base_camera=None):
        """A perfect rectified rig: square pixels, principal point at the image centre.

        Give either ``fx`` in pixels or a horizontal field of view (default 70°).
        """
        if fx is None:
            hfov = np.deg2rad(70.0 if hfov_deg is None else hfov_deg)
            fx = (width / 2) / np.tan(hfov / 2)
        K = np.array([[fx, 0, width / 2], [0, fx, height / 2], [0, 0, 1]])
        return cls(width=width, height=height, fx=float(fx), fy=float(fx),
                   cx_left=width / 2, cx_right=width / 2, cy=height / 2, baseline=float(baseline),
                   K_left=K, K_right=K.copy(),
                   T_base_camera=np.eye(4) if T_base_camera is None else np.asarray(T_base_camera, float))

    @classmethod
    def from_middlebury(cls, f, cx_left, cy, doffs, baseline_m, width, height):
        """Middlebury 2014 calib.txt convention: Z = baseline·f / (d + doffs)."""
        K_l = np.array([[f, 0, cx_left], [0, f, cy], [0, 0, 1]])
        K_r = np.array([[f, 0, cx_left + doffs], [0, f, cy], [0, 0, 1]])
        return cls(width=int(width), height=int(height), fx=float(f), fy=float(f),
                   cx_left=float(cx_left), cx_right=float(cx_left + doffs), cy=float(cy),
                   baseline=float(baseline_m), K_left=K_l, K_right=K_r)

    def scaled(self, factor: float) -> "StereoCalibration":
        """The same rig with images resized by ``factor`` (pixel quantities scale, metres do not)."""
        S = np.diag([factor, factor, 1.0])
        return StereoCalibration(
            width=int(round(self.width * factor)), height=int(round(self.height * factor)),
            fx=self.fx * factor, fy=self.fy * factor, cx_left=self.cx_left * factor,
            cx_right=self.cx_right * factor, cy=self.cy * factor, baseline=self.baseline,
            K_left=S @ self.K_left, D_left=self.D_left, R_left=self.R_left,
            K_right=S @ self.K_right, D_right=self.D_right, R_right=self.R_right,
            T_base_camera=self.T_base_camera)
