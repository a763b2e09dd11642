"""Synthetic fly populations for testing and measuring registration (no I/O).

A scene is a set of axis-aligned boxes plus an optional ground plane, in a world frame with the
optical convention (x right, y down, z forward).  `observe` imitates what a converged fly population
looks like from a rectified stereo rig: flies are spread evenly over the *image* (so a far surface gets
as many flies per pixel as a near one, i.e. far fewer per square metre), each lands on the first
surface its pixel ray hits, and its depth is read through a noisy disparity, so the depth error grows
as z² along the viewing ray.  A fraction of flies are outliers spread uniformly in (u, v, disparity).

The project simulator (common/sim/) is richer; this module is deliberately small so the registration
tests and benches do not depend on it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import StereoCalibration
from ..geometry import transform_points


@dataclass
class BoxScene:
    boxes: np.ndarray            # (m, 2, 3): lower and upper corners, world frame (optical convention)
    ground_y: float | None = None  # world y of a horizontal ground plane (y is down), None for none


def street_scene(rng: np.random.Generator, length: float = 80.0) -> BoxScene:
    """An outdoor street: building blocks on both sides at 6–12 m, parked cars, poles, a ground plane.

    The camera starts near the origin looking down +z; surfaces reach 2–`length` m.
    """
    boxes = []
    z = -10.0
    while z < length:  # facades, with gaps between blocks
        w = rng.uniform(8, 20)
        for side in (-1, 1):
            x0 = side * rng.uniform(6, 9)
            depth = rng.uniform(5, 10)
            lo = [min(x0, x0 + side * depth), -rng.uniform(6, 15), z]
            hi = [max(x0, x0 + side * depth), 1.5, z + w]
            boxes.append([lo, hi])
        z += w + rng.uniform(1, 6)
    for _ in range(10):  # parked cars
        side = rng.choice([-1, 1])
        x = side * rng.uniform(3.0, 4.5)
        zc = rng.uniform(3, length)
        boxes.append([[x - 0.9, 0.0, zc], [x + 0.9, 1.5, zc + 4.2]])
    for _ in range(12):  # poles and trees
        side = rng.choice([-1, 1])
        x = side * rng.uniform(4.8, 5.8)
        zc = rng.uniform(2, length)
        boxes.append([[x - 0.15, -rng.uniform(3, 6), zc], [x + 0.15, 1.5, zc + 0.3]])
    return BoxScene(boxes=np.asarray(boxes, dtype=float), ground_y=1.5)


def corridor_scene(half_width: float = 1.0, length: float = 60.0, height: float = 2.5) -> BoxScene:
    """Two parallel walls along z (the paper's corridor, without floor or ceiling)."""
    t = 0.2
    boxes = [[[-half_width - t, -height, -5.0], [-half_width, height, length]],
             [[half_width, -height, -5.0], [half_width + t, height, length]]]
    return BoxScene(boxes=np.asarray(boxes, dtype=float), ground_y=None)


def wall_scene(distance: float = 5.0, width: float = 60.0, height: float = 40.0) -> BoxScene:
    """A single plane z = `distance` facing the camera, far wider than the field of view."""
    boxes = [[[-width / 2, -height / 2, distance], [width / 2, height / 2, distance + 0.2]]]
    return BoxScene(boxes=np.asarray(boxes, dtype=float), ground_y=None)


def _first_hit(scene: BoxScene, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Ray parameter of the first surface hit for every ray (inf when none); rays origin + t·dirs."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        lo = scene.boxes[None, :, 0, :]
        hi = scene.boxes[None, :, 1, :]
        t1 = (lo - origin) * inv[:, None, :]
        t2 = (hi - origin) * inv[:, None, :]
        tmin = np.nanmax(np.minimum(t1, t2), axis=2)
        tmax = np.nanmin(np.maximum(t1, t2), axis=2)
    hit = (tmax >= tmin) & (tmin > 1e-6)
    t = np.where(hit, tmin, np.inf).min(axis=1) if len(scene.boxes) else np.full(len(dirs), np.inf)
    if scene.ground_y is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            tg = (scene.ground_y - origin[1]) / dirs[:, 1]
        t = np.where((dirs[:, 1] > 0) & (tg > 1e-6), np.minimum(t, tg), t)
    return t


def observe(scene: BoxScene, T_world_cam: np.ndarray, calib: StereoCalibration, n: int,
            rng: np.random.Generator, disparity_sigma: float = 0.4, pixel_sigma: float = 0.3,
            outlier_fraction: float = 0.03, min_depth: float = 2.0, max_depth: float = 40.0):
    """n flies seen from a camera at `T_world_cam`, in that camera's optical frame.

    Returns (points (n, 3), true_points (n, 3), is_outlier (n,)).  Flies are uniform over the image;
    depth comes through a disparity with Gaussian noise of `disparity_sigma` px, image position with
    `pixel_sigma` px.  Pixels whose ray hits nothing within [min_depth, max_depth] are redrawn.
    """
    R = T_world_cam[:3, :3]
    o = T_world_cam[:3, 3]
    n_out = int(round(outlier_fraction * n))
    n_in = n - n_out
    good_pts = []
    have = 0
    for _ in range(50):
        m = max(2 * (n_in - have), 256)
        u = rng.uniform(0, calib.width, m)
        v = rng.uniform(0, calib.height, m)
        d_cam = np.stack([(u - calib.cx_left) / calib.fx, (v - calib.cy) / calib.fy, np.ones(m)], 1)
        t = _first_hit(scene, o, d_cam @ R.T)
        ok = np.isfinite(t) & (t >= min_depth) & (t <= max_depth)
        good_pts.append(d_cam[ok] * t[ok, None])
        have += int(ok.sum())
        if have >= n_in:
            break
    true_pts = np.concatenate(good_pts)[:n_in]
    if len(true_pts) < n_in:
        raise ValueError("the scene is not visible from this pose: too few pixel rays hit it")
    u, ur, v = calib.project(true_pts)
    disp = (u - ur) + rng.normal(0, disparity_sigma, n_in)
    disp = np.maximum(disp, 0.2)
    noisy = calib.backproject(u + rng.normal(0, pixel_sigma, n_in), v + rng.normal(0, pixel_sigma, n_in), disp)
    d_lo = float(calib.disparity_from_depth(max_depth))
    d_hi = float(calib.disparity_from_depth(min_depth))
    out = calib.backproject(rng.uniform(0, calib.width, n_out), rng.uniform(0, calib.height, n_out),
                            rng.uniform(d_lo, d_hi, n_out))
    pts = np.concatenate([noisy, out])
    truth = np.concatenate([true_pts, out])
    is_out = np.concatenate([np.zeros(n_in, bool), np.ones(n_out, bool)])
    perm = rng.permutation(n)
    return pts[perm], truth[perm], is_out[perm]


def deep_rig(width: int = 640, height: int = 480, baseline: float = 0.5) -> StereoCalibration:
    """The rig of the deep-scene experiments: 640×480, 70° horizontal field of view, 0.5 m baseline."""
    return StereoCalibration.ideal(width=width, height=height, baseline=baseline)


def pose_in_world(T_world_cam: np.ndarray, points_cam: np.ndarray) -> np.ndarray:
    """Camera-frame points expressed in the world frame."""
    return transform_points(T_world_cam, points_cam)
