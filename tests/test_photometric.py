"""Photometric tracking on the flies' neighbourhoods: a camera motion between two images of a textured
scene is recovered from flies on it, starting from no motion, and an unknown large motion is found by
the coarse lattice first."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from numba import njit

from common.geometry import invert, make_transform, rot_x, rot_y, so3_log
from common.registration.photometric import AlignmentError, align_flies, coarse_candidates, coarse_search, pyramid

W, H, F = 480, 200, 300.0
K = np.array([[F, 0, W / 2 - 0.5], [0, F, H / 2 - 0.5], [0, 0, 1.0]])
# a slanted textured plane n·p = d in the reference camera frame: 7.2 m deep on the left, 16.6 m on the right
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


def test_the_lattice_offers_distinct_starts_and_the_true_motion_fits_best():
    """When the motion is unknown the tracker aligns from several lattice minima (distinct basins,
    best-scored first) and keeps the best fit: the true 0.9 m step is among them and fits best."""
    T_ref_new = make_transform(np.eye(3), [0.9, 0.0, 0.0])
    ref, new = pyramid(render(np.eye(4)), 4), pyramid(render(T_ref_new), 4)
    P = flies_on_the_plane()
    w = np.ones(len(P))
    starts = coarse_candidates(P, w, ref, new, K, np.eye(4), count=3)
    assert len(starts) == 3 and np.allclose(starts[0], coarse_search(P, w, ref, new, K, np.eye(4)))
    assert min(np.linalg.norm(a[:3, 3] - b[:3, 3]) for i, a in enumerate(starts) for b in starts[i + 1:]) > 0.05
    fits = [align_flies(P, w, ref, new, K, T) for T in starts]
    best = min((f for f in fits if f.ok), key=lambda f: f.residual)
    assert errors(best.T, invert(T_ref_new))[0] < 0.02


def test_the_lattice_holds_the_straight_ahead_motion():
    """A pure forward step: the lattice's best start turns by exactly nothing (its yaw axis keeps the
    centre) and moves forward, so the alignment starts in the right basin."""
    T_ref_new = make_transform(np.eye(3), [0.0, 0.0, 1.0])
    ref, new = pyramid(render(np.eye(4)), 4), pyramid(render(T_ref_new), 4)
    P = flies_on_the_plane()
    start = coarse_search(P, np.ones(len(P)), ref, new, K, np.eye(4))
    assert np.allclose(start[:3, :3], np.eye(3))
    assert start[2, 3] < -0.5                         # T_new_ref: the scene comes closer


def test_the_lattice_finds_a_pitch_with_a_step_forward():
    """A swaying rig: 0.9 m forward with 6° of pitch (31 px of vertical image shift here; a KITTI
    camera's 3° is 38 px).  From no motion the alignment ends 2.7 m off; the lattice's pitch axis
    starts it in the right basin."""
    T_ref_new = make_transform(rot_x(np.deg2rad(6.0)), [0.0, 0.0, 0.9])
    ref, new = pyramid(render(np.eye(4)), 4), pyramid(render(T_ref_new), 4)
    P = flies_on_the_plane()
    w = np.ones(len(P))
    blind = align_flies(P, w, ref, new, K, np.eye(4))
    assert max(errors(blind.T, invert(T_ref_new))[0] / 0.1, errors(blind.T, invert(T_ref_new))[1]) > 1.0
    fits = [align_flies(P, w, ref, new, K, T) for T in coarse_candidates(P, w, ref, new, K, np.eye(4), count=3)]
    best = min((f for f in fits if f.ok), key=lambda f: f.residual)
    t_err, r_err = errors(best.T, invert(T_ref_new))
    print(f"\nfrom the lattice: {100 * t_err:.2f} cm, {r_err:.3f}°")
    assert t_err < 0.02 and r_err < 0.1


def test_malformed_flies_are_refused_with_a_reason():
    ref = pyramid(render(np.eye(4)), 2)
    with pytest.raises(AlignmentError):
        align_flies(np.ones((10, 2)), np.ones(10), ref, ref, K)
    few = align_flies(flies_on_the_plane(10), np.ones(10), ref, ref, K)
    assert not few.ok and few.reason.startswith("too few flies")


def reference_gauss_newton(P, w, ref_pyr, new_pyr, T, iterations=12, huber_px=1.345, min_flies=50, z_min=0.1):
    """align_flies written out in plain numpy (a Jacobian array per level, a full median, the normal
    equations summed per residual, LAPACK solves): what the fused kernels must reproduce."""
    from common.geometry import orthonormalised
    from common.registration.photometric import COARSE_STOP_PX, FINE_STOP_PX, PATTERN, _sample, se3_exp
    rng, T, iters, H = np.random.default_rng(0), T.copy(), 0, np.eye(6)
    z_typical = np.median(P[:, 2])
    for level in range(len(ref_pyr) - 1, -1, -1):
        n_level = max(min_flies, int(len(P) * 0.25 ** level * 4))
        pick = np.sort(rng.choice(len(P), n_level, replace=False)) if n_level < len(P) else np.arange(len(P))
        Pl, wl = P[pick], w[pick]
        s = 0.5 ** level
        fx, fy, cx, cy = K[0, 0] * s, K[1, 1] * s, (K[0, 2] + 0.5) * s - 0.5, (K[1, 2] + 0.5) * s - 0.5
        Iref, Inew = ref_pyr[level], new_pyr[level].astype(np.float64)
        x, y, z = Pl.T
        uo = (fx * x / z + cx)[:, None] + PATTERN[:, 0]
        vo = (fy * y / z + cy)[:, None] + PATTERN[:, 1]
        ref = _sample(Iref, uo, vo)
        gx = _sample(cv2.Sobel(Iref, cv2.CV_32F, 1, 0, ksize=3, scale=0.125), uo, vo)
        gy = _sample(cv2.Sobel(Iref, cv2.CV_32F, 0, 1, ksize=3, scale=0.125), uo, vo)
        valid_ref = np.isfinite(ref).all(1) & np.isfinite(gx).all(1) & np.isfinite(gy).all(1)
        iz, zero = 1 / z, np.zeros_like(z)
        du = np.stack([fx * iz, zero, -fx * x * iz ** 2,
                       -fx * x * y * iz ** 2, fx * (1 + (x * iz) ** 2), -fx * y * iz], 1)
        dv = np.stack([zero, fy * iz, -fy * y * iz ** 2,
                       -fy * (1 + (y * iz) ** 2), fy * x * y * iz ** 2, fy * x * iz], 1)
        J = gx[:, :, None] * du[:, None] + gy[:, :, None] * dv[:, None]
        J = np.where(valid_ref[:, None, None], J - J.mean(1, keepdims=True), 0.0)
        ref0 = np.where(valid_ref[:, None], ref - ref.mean(1, keepdims=True), 0.0)
        h, wd = Inew.shape
        for _ in range(iterations):
            iters += 1
            q = Pl @ T[:3, :3].T + T[:3, 3]
            qz = np.where(q[:, 2] > z_min, q[:, 2], 1.0)
            u = (fx * q[:, 0] / qz + cx)[:, None] + PATTERN[:, 0]
            v = (fy * q[:, 1] / qz + cy)[:, None] + PATTERN[:, 1]
            valid = valid_ref & (q[:, 2] > z_min) & ((u >= 0) & (v >= 0) & (u < wd - 1) & (v < h - 1)).all(1)
            iu, iv = np.clip(u, 0, wd - 2).astype(int), np.clip(v, 0, h - 2).astype(int)
            a, b = u - iu, v - iv
            val = ((1 - a) * (1 - b) * Inew[iv, iu] + a * (1 - b) * Inew[iv, iu + 1]
                   + (1 - a) * b * Inew[iv + 1, iu] + a * b * Inew[iv + 1, iu + 1])
            r = np.where(valid[:, None], val - val.mean(1, keepdims=True) - ref0, 0.0)
            sigma = 1.4826 * np.median(np.abs(r[valid])) + 1e-6
            k = huber_px * sigma
            hub = np.minimum(1.0, k / np.maximum(np.abs(r), 1e-300)) * wl[:, None] * valid[:, None]
            H = np.einsum("np,npc,npd->cd", hub, J, J)
            g = np.einsum("np,npc,np->c", hub, J, r)
            inliers = float((np.abs(r) <= k)[valid].mean())
            dxi = np.linalg.solve(H + 1e-9 * np.trace(H) * np.eye(6), g)
            T = orthonormalised(T @ np.linalg.inv(se3_exp(dxi)))
            # converged: the step moves a fly at the median depth by under the level's stop, in its pixels
            if fx * (np.linalg.norm(dxi[:3]) / z_typical + np.linalg.norm(dxi[3:])) < (
                    FINE_STOP_PX if level == 0 else COARSE_STOP_PX):
                break
    return T, sigma, inliers, iters


@pytest.mark.parametrize("motion", [make_transform(rot_y(np.deg2rad(1.5)), [0.15, 0.05, 0.4]),
                                    make_transform(rot_y(np.deg2rad(-3.0)), [0.5, 0.0, 1.5])])
def test_the_fused_kernels_compute_the_plain_gauss_newton(motion):
    """Same pose, robust scale, inlier share and iteration count as the numpy formulation, also when
    flies leave the view and many residuals are Huber outliers (the second motion)."""
    ref, new = pyramid(render(np.eye(4)), 4), pyramid(render(motion), 4)
    P = flies_on_the_plane()
    w = np.random.default_rng(2).uniform(0.2, 1.0, len(P))
    res = align_flies(P, w, ref, new, K, np.eye(4))
    T, sigma, inliers, iters = reference_gauss_newton(P, w, ref, new, np.eye(4))
    assert res.ok and res.iterations == iters
    np.testing.assert_allclose(res.T, T, atol=1e-9)
    assert res.residual == pytest.approx(sigma, rel=1e-9) and res.inliers == pytest.approx(inliers, abs=1e-12)


def test_a_reference_changed_between_calls_is_not_aligned_with_stale_terms():
    """The per-reference terms are reused across frames only for the very same pyramid and equal flies:
    another pyramid, or flies / weights changed in place, give what a fresh computation gives."""
    from common.registration import photometric
    motion = make_transform(rot_y(np.deg2rad(1.0)), [0.1, 0.0, 0.3])
    ref_a, ref_b = pyramid(render(np.eye(4)), 4), pyramid(render(invert(motion)), 4)
    new = pyramid(render(motion), 4)
    P = flies_on_the_plane()
    w = np.random.default_rng(3).uniform(0.2, 1.0, len(P))

    def fresh(*args):
        photometric._REFERENCE_CACHE.clear()
        return align_flies(*args).T

    first = align_flies(P, w, ref_a, new, K)
    assert np.array_equal(align_flies(P, w, ref_a, new, K).T, first.T)
    assert np.array_equal(align_flies(P, w, ref_b, new, K).T, fresh(P, w, ref_b, new, K))
    align_flies(P, w, ref_a, new, K)
    P[:, :] *= 1.05
    assert np.array_equal(align_flies(P, w, ref_a, new, K).T, fresh(P, w, ref_a, new, K))
    align_flies(P, w, ref_a, new, K)
    w[: len(w) // 2] = 0.0
    assert np.array_equal(align_flies(P, w, ref_a, new, K).T, fresh(P, w, ref_a, new, K))


def test_the_motion_found_the_other_way_round_matches_the_true_one():
    """The map's first fix may also take its start from the new image's flies aligned back into the
    reference image (common.slam.tracking.reverse_motion): that gives the same 0.9 m step."""
    from common.slam.tracking import ReferenceView, reverse_motion
    T_ref_new = make_transform(np.eye(3), [0.9, 0.0, 0.0])
    ref_image, new_image = render(np.eye(4)), render(T_ref_new)
    P_ref = flies_on_the_plane()
    P_new = (P_ref - T_ref_new[:3, 3]) @ T_ref_new[:3, :3]          # the same surface, new camera frame
    view = ReferenceView(np.eye(4), P_ref.astype(np.float32), np.ones(len(P_ref), np.float32), ref_image)
    T_new_ref = reverse_motion(view, P_new, np.ones(len(P_new)), pyramid(new_image, 4), K, 0.5)
    assert T_new_ref is not None
    t_err, r_err = errors(T_new_ref, invert(T_ref_new))
    assert t_err < 0.02 and r_err < 0.1


@pytest.mark.parametrize("results, chosen", [
    ([(True, 0.7, 6.0), (True, 0.7, 1.8)], 1),   # a clearly better fit from a later start wins
    ([(True, 0.7, 2.0), (True, 0.7, 1.9)], 0),   # near-equal fits: the preferred (first) start stays
    ([(True, 0.4, 3.0), (True, 0.8, 2.9)], 1),   # the first is below min_inliers: an accepted one replaces it
    ([(False, 0.0, np.nan), (True, 0.7, 5.0)], 1),
    ([(True, 0.7, 2.0), (False, 0.0, 0.5)], 0),  # a failed alignment never replaces an accepted one
])
def test_best_alignment_prefers_the_first_start_unless_another_clearly_fits_better(monkeypatch, results, chosen):
    from common.registration.photometric import Alignment
    from common.slam import tracking
    fits = iter([Alignment(np.eye(4) * (i + 1), np.eye(6), r, inl, 100, 5, ok, "")
                 for i, (ok, inl, r) in enumerate(results)])
    monkeypatch.setattr(tracking, "align_flies", lambda *a, **k: next(fits))
    best = tracking.best_alignment(None, None, None, None, K, [np.eye(4)] * len(results), min_inliers=0.5)
    assert best.T[0, 0] == chosen + 1


def test_the_lattice_kernel_scores_as_the_plain_numpy_sum():
    """_lattice_scores (one numba pass) against the score written out in numpy: bilinear 3×3
    neighbourhoods, zero-mean, mean |difference| truncated at the cap, weighted sum; flies behind the
    camera or off the image count the cap."""
    from scipy.ndimage import map_coordinates
    from common.registration.photometric import _SCORE_CAP, PATTERN, _lattice_scores
    rng = np.random.default_rng(5)
    img = pyramid(render(make_transform(np.eye(3), [0.2, 0.0, 0.5])), 3)[-1].copy()
    img[10:14, 40:60] = np.nan                                 # a hole in the image counts the cap
    fx = fy = F / 4
    cx, cy = (K[0, 2] + 0.5) / 4 - 0.5, (K[1, 2] + 0.5) / 4 - 0.5
    Q = flies_on_the_plane(300)
    Q[:5, 2] = -1.0                                            # behind the camera
    ref = rng.normal(0, 10, (len(Q), 9)).astype(np.float32)
    ref[5:40, ::2] += 60.0                                     # residuals past the cap
    w = rng.uniform(0.5, 1.0, len(Q))
    X, Z, yaw = rng.uniform(-1, 1, 40), rng.uniform(-2, 2, 40), rng.uniform(-0.1, 0.1, 40)
    got = _lattice_scores(img, ref, w, Q, X, Z, np.cos(yaw), np.sin(yaw), fx, fy, cx, cy)
    H, W_ = img.shape
    for m in range(len(X)):
        c, s = np.cos(yaw[m]), np.sin(yaw[m])
        px, pz = c * Q[:, 0] + s * Q[:, 2] + X[m], -s * Q[:, 0] + c * Q[:, 2] + Z[m]
        u, v = fx * px / np.where(pz > 0.1, pz, 1) + cx, fy * Q[:, 1] / np.where(pz > 0.1, pz, 1) + cy
        inside = (pz > 0.1) & (u >= 1) & (u < W_ - 2) & (v >= 1) & (v < H - 2)
        cur = map_coordinates(img.astype(np.float64), [v[:, None] + PATTERN[:, 1], u[:, None] + PATTERN[:, 0]],
                              order=1, mode="nearest")
        r = np.abs(cur - cur.mean(1, keepdims=True) - ref).mean(1)
        want = np.sum(w * np.where(inside & np.isfinite(r), np.minimum(r, _SCORE_CAP), _SCORE_CAP))
        assert got[m] == pytest.approx(want, rel=1e-5)


def test_half_a_pixel_of_smoothing_aligns_noisy_images_better():
    """A cheaper camera's sensor noise (σ 6 grey levels, independent in each image): the pyramids'
    half-pixel smoothing (LocaliserConfig.photometric_smooth_px) brings the motion closer to the truth."""
    T_ref_new = make_transform(rot_y(np.deg2rad(1.5)), [0.15, 0.05, 0.4])
    clean_ref, clean_new = render(np.eye(4)), render(T_ref_new)
    P = flies_on_the_plane()
    err = {0.0: [], 0.5: []}
    for seed in range(4):
        rng = np.random.default_rng(seed)
        ref, new = (np.clip(img + rng.normal(0.0, 6.0, img.shape), 0, 255).astype(np.uint8)
                    for img in (clean_ref, clean_new))
        for smooth in err:
            res = align_flies(P, np.ones(len(P)), pyramid(ref, 4, smooth), pyramid(new, 4, smooth), K, np.eye(4))
            assert res.ok
            err[smooth].append(errors(res.T, invert(T_ref_new))[0])
    print(f"\nmean error {1000 * np.mean(err[0.0]):.2f} mm unsmoothed, {1000 * np.mean(err[0.5]):.2f} mm smoothed")
    assert np.mean(err[0.5]) < 0.85 * np.mean(err[0.0])


@pytest.mark.parametrize("step_m", [0.85, 1.7])
def test_a_cars_step_forward_is_tracked_to_its_full_length(step_m):
    """A car's step between frames (0.85 m at KITTI's 10 Hz, 1.7 m at 5 Hz): the slanted plane's texture
    grows by 6-13 % (12-30 % at 1.7 m) between the images and the 3×3 neighbourhoods are compared
    unwarped, yet the step's length comes out unbiased: a scale error here is a drift in every
    trajectory on a car."""
    T_ref_new = make_transform(np.eye(3), [0.0, 0.0, step_m])
    ref, new = pyramid(render(np.eye(4)), 4, 0.5), pyramid(render(T_ref_new), 4, 0.5)
    P = flies_on_the_plane()
    res = align_flies(P, np.ones(len(P)), ref, new, K, np.eye(4))
    moved = invert(res.T)[:3, 3]                                      # the new camera in the reference
    print(f"\nforward {moved[2]:.4f} m of {step_m}, sideways {1000 * moved[0]:+.1f} mm, "
          f"vertical {1000 * moved[1]:+.1f} mm")
    assert res.ok
    assert abs(moved[2] / step_m - 1) < 0.0015
    assert np.hypot(moved[0], moved[1]) < 0.005


def test_the_residual_scale_median_is_numpys_to_the_bit():
    """The Gauss-Newton's robust scale σ̂ comes from photometric._median (histogram, then sorting only
    the middle bins): the same value as np.median, so the tracked trajectory does not change with it.
    Odd and even counts, ties, zeros, heavy tails, one huge outlier."""
    from common.registration.photometric import _median
    rng = np.random.default_rng(0)
    counts, picked = np.empty(4096, np.int64), np.empty(20_000)
    cases = [np.abs(rng.standard_normal(18_000)) * 3, np.abs(rng.standard_t(1.5, 17_999)),
             np.round(np.abs(rng.standard_normal(9_001)) * 4) / 4, np.zeros(450), np.full(451, 2.5),
             np.r_[np.abs(rng.standard_normal(999)), 1e12], np.array([0.7]), np.array([0.2, 0.9])]
    cases += [np.abs(rng.standard_normal(int(n))) * rng.uniform(0.1, 50) for n in rng.integers(2, 20_000, 40)]
    for values in cases:
        assert _median(values, len(values), counts, picked) == np.median(values)
    # Outside the histogram's domain it falls back to numba's own np.median (which, unlike numpy's, does
    # not return NaN for a NaN), and never indexes outside its histogram (numba does not check).
    numba_median = njit(lambda a: np.median(a))
    for values in (np.array([np.nan, 1.0, 2.0]), np.array([5.0, np.nan, 1.0, 0.5]), np.array([3.0, -1.0, 2.0]),
                   np.array([1.0, np.inf, 2.0, np.nan]), np.array([1e-310, 2e-310, 3e-310]),
                   np.array([0.0, 0.0, 1e-310, 0.0]), np.array([5e-307, 1e-306, 2e-307])):
        guard = np.full(3 * 4096, -7, np.int64)
        got = _median(values, len(values), guard[4096:8192], picked)
        assert got == numba_median(values) or (np.isnan(got) and np.isnan(numba_median(values)))
        assert np.all(guard[:4096] == -7) and np.all(guard[8192:] == -7)


class _Keyframe:
    """What align_keyframes reads of a keyframe: pose, flies (base = camera frame here), fitness, image."""

    def __init__(self, T_map_base, points, image):
        self.T_map_base, self.points = T_map_base, points.astype(np.float32)
        self.fitness, self.image = np.ones(len(points), np.float32), cv2.pyrDown(image)


def _flies_seen_from(T_ref_cam, n=1500, seed=2):
    """Points of the plane at random pixels of a camera at T_ref_cam, in that camera's frame."""
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(20, W - 20, n), rng.uniform(20, H - 20, n)
    rays = np.stack([(u - K[0, 2]) / F, (v - K[1, 2]) / F, np.ones(n)], 1)
    o, R = T_ref_cam[:3, 3], T_ref_cam[:3, :3]
    return rays * ((D - NORMAL @ o) / ((rays @ R.T) @ NORMAL))[:, None]


@pytest.mark.parametrize("new_depth_scale, new_flies", [(0.97, 1500), (1.0, 0)])
def test_a_loop_is_measured_both_ways_and_their_errors_along_the_view_cancel(new_depth_scale, new_flies):
    """Two keyframes 2.5 m apart along the view, the loop aligned from a start other than the new
    keyframe's tracked pose.  The old keyframe's flies 3 % too deep (a population that had not settled)
    make the old-into-new way ~75 mm long; the new keyframe's flies 3 % too shallow make the way back
    ~75 mm short; the loop is their midpoint.  A new keyframe with no flies still closes the loop, on
    the old keyframe's alone (then one way's error remains)."""
    from common.slam.tracking import align_keyframes

    T_old_new = make_transform(np.eye(3), [0.0, 0.0, 2.5])          # the new camera 2.5 m ahead
    old = _Keyframe(np.eye(4), flies_on_the_plane() * 1.03, render(np.eye(4)))
    new = _Keyframe(T_old_new @ make_transform(np.eye(3), [0.1, 0.0, -0.3]),        # tracked pose, off
                    _flies_seen_from(T_old_new, max(new_flies, 1))[:new_flies] * new_depth_scale,
                    render(T_old_new))
    start = T_old_new @ make_transform(np.eye(3), [0.02, 0.0, -0.1])               # e.g. δ's minimum
    T, why = align_keyframes(old, new, K, np.eye(4), [start], 3, 0.5)
    assert T is not None, why
    along, across = T[2, 3] - 2.5, np.hypot(T[0, 3], T[1, 3])
    print(f"\nalong the view {1000 * along:+.1f} mm, across {1000 * across:.1f} mm")
    if new_flies:
        assert abs(along) < 0.015 and across < 0.01
    else:
        assert 0.05 < along < 0.1            # the old keyframe's way alone: its flies' 3 % too deep
