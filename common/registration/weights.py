"""Per-fly weights for registration on deep (outdoor) scenes: depth uncertainty and co-visibility.

A stereo fly's depth error grows as z²: σ_z = z² σ_d / (f·b) for a disparity error σ_d (pixels), focal
length f (pixels) and baseline b (metres).  At 30 m with a 0.5 m baseline and f ≈ 460 px, one pixel of
disparity is ≈ 4 m of depth, so far flies are smeared along their viewing rays and, under the paper's
isotropic δ, they pull the registration as hard as precise near flies.

Co-visibility: δ(A, f(B)) averages over *all* of A, so flies of A that the second camera could not
see (outside its image or depth range after the motion) attract f(B) towards them; on a street the
field-of-view mismatch after a turn or a step forward biased the paper's δ by 0.3–0.6 m in our
measurements (bench/registration_variants.py).  Masking both populations to the part of the scene
both cameras can see removes that pull.
"""
from __future__ import annotations

import numpy as np

from ..camera import StereoCalibration
from ..geometry import invert, transform_points
from .pseudo_distance import PopulationError, as_population


def to_optical(points: np.ndarray, calib: StereoCalibration, frame: str) -> np.ndarray:
    """Points in the left camera optical frame, from "optical" or "body" (base_link) coordinates."""
    if frame == "optical":
        return points
    if frame == "body":
        return transform_points(invert(np.asarray(calib.T_base_camera, dtype=float)), points)
    raise PopulationError(f"frame must be 'optical' or 'body', got {frame!r}")


def depth_sigma(points, calib: StereoCalibration, disparity_sigma: float = 0.4,
                frame: str = "optical") -> np.ndarray:
    """Standard deviation of each fly's depth (metres) for a disparity error of `disparity_sigma` px."""
    P = to_optical(as_population(points, "points", allow_empty=True), calib, frame)
    z = np.maximum(P[:, 2], 1e-6)
    return z * z * float(disparity_sigma) / (calib.fx * calib.baseline)


def depth_weights(points, calib: StereoCalibration, disparity_sigma: float = 0.4,
                  sigma_ref: float = 0.25, frame: str = "optical") -> np.ndarray:
    """Soft weights 1 / (1 + (σ_z / σ_ref)²): ≈1 for flies known to `sigma_ref` metres, → 0 far away.

    Not the inverse variance 1/σ_z² (∝ z⁻⁴): that hands the whole registration to the nearest few
    metres.  With σ_ref = 0.25 m, 0.4 px and the 0.5 m / 460 px rig, the weight halves at z ≈ 12 m.
    """
    s = depth_sigma(points, calib, disparity_sigma, frame)
    return 1.0 / (1.0 + (s / float(sigma_ref)) ** 2)


def footprint_weights(points, calib: StereoCalibration, frame: str = "optical",
                      z_ref: float = 10.0) -> np.ndarray:
    """(z / z_ref)²: the surface area a fly stands for when flies are spread evenly over the image.

    A converged population has about as many flies per pixel at 40 m as at 2 m, so per square metre
    it is 400× denser near the camera, and that density pattern moves with the camera: two
    independent populations then correlate best at *zero* motion.  Weighting each fly by its pixel
    footprint (∝ z², ignoring the surface's slant) turns both into an even surface density; on the
    street scene this removed a 0.6 m pull towards no motion (bench/registration_variants.py).
    """
    P = to_optical(as_population(points, "points", allow_empty=True), calib, frame)
    return (np.maximum(P[:, 2], 0.0) / float(z_ref)) ** 2


def visible_mask(points, calib: StereoCalibration, depth_range=(0.0, np.inf), margin: float = 0.03,
                 frame: str = "optical") -> np.ndarray:
    """Which points (in this rig's frame) a stereo fly could stand on: in front of the rig, projecting
    inside BOTH images, `margin` of the size away from their borders, and within `depth_range` metres.

    Both images: a fly is evaluated on its left and right projections, so the left image's strip
    where the right projection falls off the right image's left edge (as wide as the disparity: tens
    of pixels at short range) never holds a fly.  That strip is fixed to the camera; a mask that
    checks the left image only leaves it in, i.e. a camera-fixed hole in one population, which pulls
    the registration towards no motion.
    """
    P = to_optical(as_population(points, "points", allow_empty=True), calib, frame)
    ul, ur, v = calib.project(P)
    mu, mv = margin * calib.width, margin * calib.height
    with np.errstate(invalid="ignore"):
        return ((ul >= mu) & (ul <= calib.width - mu) & (ur >= mu) & (ur <= calib.width - mu)
                & (v >= mv) & (v <= calib.height - mv) & (P[:, 2] > 0)
                & (P[:, 2] >= depth_range[0]) & (P[:, 2] <= depth_range[1]))


def covisible_masks(A, B, T_f, calib: StereoCalibration, depth_range=(0.0, np.inf), margin: float = 0.03,
                    frame: str = "optical"):
    """(mask_a, mask_b): flies of A the second camera sees (f⁻¹(A) in view) and flies of B the first
    camera sees (f(B) in view), for f = T_f mapping B's frame into A's."""
    A = as_population(A, "A", allow_empty=True)
    B = as_population(B, "B", allow_empty=True)
    mask_a = visible_mask(transform_points(invert(T_f), A), calib, depth_range, margin, frame)
    mask_b = visible_mask(transform_points(T_f, B), calib, depth_range, margin, frame)
    return mask_a, mask_b
