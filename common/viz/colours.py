"""Colour mappings for the viewer: fly fitness → RGB, harmonic field → heat-map image.

Both are one vectorised OpenCV colour-map lookup over the whole array.
"""
from __future__ import annotations

import cv2
import numpy as np

INVALID_RGB = np.array([90, 90, 90], np.uint8)  # flies outside the images (fitness −inf), blocked cells


def _lut_rgb(colormap: int) -> np.ndarray:
    """256×3 RGB lookup table of an OpenCV colour map."""
    ramp = np.arange(256, dtype=np.uint8).reshape(-1, 1)
    return cv2.applyColorMap(ramp, colormap).reshape(256, 3)[:, ::-1].copy()


_TURBO = _lut_rgb(cv2.COLORMAP_TURBO)
_INFERNO = _lut_rgb(cv2.COLORMAP_INFERNO)


def normalise(values: np.ndarray, lo_pct: float = 2.0, hi_pct: float = 98.0) -> tuple[np.ndarray, np.ndarray]:
    """(values scaled to 0..1 by robust percentiles of the finite ones, finite mask).

    Percentiles rather than min/max so that a handful of outliers does not flatten the contrast.
    """
    values = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(values)
    out = np.zeros(values.shape, np.float64)
    if not finite.any():
        return out, finite
    lo, hi = np.percentile(values[finite], [lo_pct, hi_pct])
    span = hi - lo if hi > lo else 1.0
    out[finite] = np.clip((values[finite] - lo) / span, 0.0, 1.0)
    return out, finite


def fitness_colours(fitness: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 RGB: turbo colour map over the population's fitness (blue low, red high), grey for
    flies with non-finite fitness (outside the images)."""
    scaled, finite = normalise(fitness)
    rgb = _TURBO[(scaled * 255).astype(np.uint8)]
    rgb[~finite] = INVALID_RGB
    return rgb


def field_image(values: np.ndarray) -> np.ndarray:
    """H×W×3 uint8 heat map of a harmonic field, rows flipped so that map +y points up on screen.

    Non-finite cells (obstacles, unreachable space: log-potential −inf) are grey.
    """
    values = np.asarray(values)
    if values.ndim != 2 or values.size == 0:
        raise ValueError(f"harmonic field values must be a non-empty 2-D grid, got shape {values.shape}")
    scaled, finite = normalise(values, 0.0, 100.0)
    rgb = _INFERNO[(scaled * 255).astype(np.uint8)]
    rgb[~finite] = INVALID_RGB
    return np.ascontiguousarray(rgb[::-1])


def field_pixels(xy: np.ndarray, origin_xy: np.ndarray, resolution_m: float, height: int) -> np.ndarray:
    """Map-frame (N, 2) points → pixel coordinates in :func:`field_image` (origin = corner of cell 0,0)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    u = (xy[:, 0] - origin_xy[0]) / resolution_m
    v = height - (xy[:, 1] - origin_xy[1]) / resolution_m
    return np.stack([u, v], axis=1)
