"""Photometric tracking on the flies' neighbourhoods: a camera motion between two images of a textured
scene is recovered from flies on it, starting from no motion, and an unknown large motion is found by
the coarse lattice first."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.geometry import invert, make_transform, rot_y, so3_log
from common.registration.photometric import AlignmentError, align_flies, coarse_search, pyramid

W, H, F = 480, 200, 300.0
K = np.array([[F, 0, W / 2 - 0.5], [0, F, H / 2 - 0.5], [0, 0, 1.0]])
# a slanted textured plane n·p = d in the reference camera frame: 6 m deep on the left, 14 m on the right
NORMAL = np.array([-0.5, 0.0, 1.0]) / np.linalg.norm([-0.5, 0.0, 1.0])
D = 10.0 * NORMAL[2]
# texture at several scales, as real surfaces have: fine grain and blobs visible at the coarsest level
_noise = np.random.default_rng(0).standard_normal((4, 1600, 1600)).astype(np.float32)
TEXTURE = sum(cv2.GaussianBlur(n, (0, 0), s) * s for n, s in zip(_noise, (2.5, 8.0, 24.0, 64.0)))
TEXTURE = cv2.normalize(TEXTURE, None, 0, 255, cv2.NORM_MINMAX)


def render(T_ref_cam: np.ndarray) -> np.ndarray:
    """The image a camera at T_ref_cam (in the reference camera's frame) sees of the plane."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays = np.stack([(u - K[0, 2]) / F, (v - K[1, 2]) / F, np.ones_like(u)], -1) @ T_ref_cam[:3, :3].T
    o = T_ref_cam[:3, 3]
    lam = (D - NORMAL @ o) / (rays @ NORMAL)
    p = o + lam[..., None] * rays
    tx, ty = (p[..., 0] * 40 + 800).astype(np.float32), (p[..., 1] * 40 + 800).astype(np.float32)
    return cv2.remap(TEXTURE, tx, ty, cv2.INTER_LINEAR).astype(np.uint8)


def flies_on_the_plane(n: int = 1500) -> np.ndarray:
    """Points of the plane seen by the reference camera, at random pixels away from the border."""
    rng = np.random.default_rng(1)
    u, v = rng.uniform(20, W - 20, n), rng.uniform(20, H - 20, n)
    rays = np.stack([(u - K[0, 2]) / F, (v - K[1, 2]) / F, np.ones(n)], 1)
    return rays * (D / (rays @ NORMAL))[:, None]


def errors(T_est, T_true):
    E = invert(T_true) @ T_est
    return float(np.linalg.norm(E[:3, 3])), float(np.degrees(np.linalg.norm(so3_log(E[:3, :3]))))


def test_alignment_recovers_a_small_motion_from_no_motion():
    T_ref_new = make_transform(rot_y(np.deg2rad(1.5)), [0.15, 0.05, 0.4])     # the new camera in the reference
    ref, new = pyramid(render(np.eye(4)), 4), pyramid(render(T_ref_new), 4)
    P = flies_on_the_plane()
    res = align_flies(P, np.ones(len(P)), ref, new, K, np.eye(4))
    t_err, r_err = errors(res.T, invert(T_ref_new))                          # res.T is T_new_ref
    print(f"\nerror {100 * t_err:.2f} cm, {r_err:.3f}°, inliers {res.inliers:.2f}")
    assert res.ok and res.inliers > 0.6
    assert t_err < 0.01 and r_err < 0.05
    assert np.all(np.isfinite(res.covariance)) and np.all(np.linalg.eigvalsh(res.covariance) > 0)


def test_an_unknown_large_motion_is_found_by_the_lattice_first():
    """0.9 m sideways (90 px on the near side): from no motion the alignment ends in another minimum."""
    T_ref_new = make_transform(np.eye(3), [0.9, 0.0, 0.0])
    ref, new = pyramid(render(np.eye(4)), 4), pyramid(render(T_ref_new), 4)
    P = flies_on_the_plane()
    w = np.ones(len(P))
    blind = align_flies(P, w, ref, new, K, np.eye(4))
    assert errors(blind.T, invert(T_ref_new))[0] > 0.5
    start = coarse_search(P, w, ref, new, K, np.eye(4))
    res = align_flies(P, w, ref, new, K, start)
    t_err, r_err = errors(res.T, invert(T_ref_new))
    print(f"\nfrom the lattice: {100 * t_err:.2f} cm, {r_err:.3f}°")
    assert res.ok and t_err < 0.02 and r_err < 0.1


def test_malformed_flies_are_refused_with_a_reason():
    ref = pyramid(render(np.eye(4)), 2)
    with pytest.raises(AlignmentError):
        align_flies(np.ones((10, 2)), np.ones(10), ref, ref, K)
    few = align_flies(flies_on_the_plane(10), np.ones(10), ref, ref, K)
    assert not few.ok and few.reason.startswith("too few flies")
