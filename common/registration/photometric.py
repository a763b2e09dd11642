"""Refine a registration on the flies' image neighbourhoods: direct alignment of a keyframe's flies.

A fly is a 3-D point that the evolver put where the neighbourhoods of its left and right projections
agree. The same neighbourhood, seen again from the next camera pose, pins that pose to a fraction of a
pixel. Given the reference flies ``P`` (left optical frame of the reference view), the reference left
image and a new left image, :func:`align_flies` finds the 6-DoF ``T_new_ref`` minimising

    Σᵢ wᵢ Σₒ ρ( Ĩ_new(π(T Pᵢ) + o) − Ĩ_ref(π(Pᵢ) + o) )

over a 3×3 pattern of offsets ``o`` per fly, where Ĩ is the neighbourhood with its mean removed (an
exposure change between frames adds a constant) and ρ a Huber kernel. Inverse-compositional
Gauss-Newton (the Jacobians come from the reference image and are computed once per pyramid level),
coarse to fine over an image pyramid, so the start may be a few pixels off at full resolution times
2^levels. No features: only flies, their fitness (the weights) and their neighbourhoods.

The result's ``covariance`` is σ̂² H⁻¹ over the tangent (tx, ty, tz, ωx, ωy, ωz) of T_new_ref (right
perturbation, metres and radians), σ̂ the robust residual scale; ``inliers`` is the fraction of fly
neighbourhoods within the Huber threshold at the end.
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit
from scipy.ndimage import minimum_filter

from common.geometry import orthonormalised, rot_x, rot_y, so3_exp

# Gauss-Newton stops when a step moves a fly at the flies' median depth by less than this, in pixels of
# the level: at full resolution a hundredth of a pixel; a coarse level only has to bring the next one
# into its basin.
FINE_STOP_PX = 0.01
COARSE_STOP_PX = 0.1
PATTERN = np.array([(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], np.float32)   # (9, 2) px


class AlignmentError(ValueError):
    """Malformed input to align_flies (shapes, non-finite values)."""


@dataclass
class Alignment:
    T: np.ndarray              # T_new_ref, 4×4
    covariance: np.ndarray     # 6×6 over (tx, ty, tz, ωx, ωy, ωz), right perturbation of T
    residual: float            # robust residual scale σ̂ (grey levels) at the end
    inliers: float             # fraction of neighbourhoods within the Huber threshold
    used: int                  # flies that projected into both images at the end
    iterations: int
    ok: bool
    reason: str = ""


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """exp of a twist (tx, ty, tz, ωx, ωy, ωz) with the translation taken as is (first-order V):
    accurate for the small increments of Gauss-Newton."""
    T = np.eye(4)
    T[:3, :3] = so3_exp(xi[3:])
    T[:3, 3] = xi[:3]
    return T


def pyramid(image: np.ndarray, levels: int, smooth_px: float = 0.0) -> list[np.ndarray]:
    """float32 grey pyramid, level 0 = the image (Gaussian-smoothed by ``smooth_px`` when > 0); each
    level halves the size (cv2.pyrDown).  Both images of an alignment need the same ``smooth_px``.

    Why smooth: bilinear samples and 3×3 Sobel gradients of an unsmoothed image are biased towards whole
    pixels, and sensor noise goes straight into the residuals; half a pixel of Gaussian (about what
    pyrDown gives every coarser level) removes both at little cost to the texture."""
    img = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    out = [img.astype(np.float32)]
    if smooth_px > 0:
        out[0] = cv2.GaussianBlur(out[0], (0, 0), smooth_px)
    for _ in range(levels - 1):
        out.append(cv2.pyrDown(out[-1]))
    return out


def level_intrinsics(K: np.ndarray, level: int) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of pyramid level ``level`` (:func:`pyramid`): each level halves the focal length,
    and a pixel centre c maps to (c + 0.5)/2 − 0.5 (pyrDown itself centres on c/2, a quarter pixel
    away; the finest level corrects what a coarse one is off)."""
    s = 0.5 ** level
    return (float(K[0, 0] * s), float(K[1, 1] * s), float((K[0, 2] + 0.5) * s - 0.5),
            float((K[1, 2] + 0.5) * s - 0.5))


def _sample(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples of img at float pixel coordinates (any shape); outside → NaN."""
    shape, n = u.shape, u.size
    cols = 1024                                  # cv2.remap maps must stay below 32767 per side
    rows = -(-n // cols)
    mu = np.full(rows * cols, -10.0, np.float32)
    mv = np.full(rows * cols, -10.0, np.float32)
    mu[:n], mv[:n] = u.ravel(), v.ravel()
    s = cv2.remap(img, mu.reshape(rows, cols), mv.reshape(rows, cols), cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    return s.ravel()[:n].reshape(shape)


@njit(cache=True, nogil=True)
def _reference_terms(P, fx, fy, ref, gx, gy, J, A):
    """Per-level terms of the inverse-compositional step, from the reference image only: which flies'
    neighbourhoods are in the reference (returned), the zero-mean Jacobians J (N, 9, 6) of their
    residuals w.r.t. a right perturbation of the pose (image gradient · dπ/dp · [I | −[p]×]) and
    A (N, 6, 6) = Σₒ JᵀJ per fly (upper triangle), the normal equations of a fly whose 9 residuals are
    all Huber inliers. Flies not in the reference get zeros."""
    n, m = ref.shape
    valid_ref = np.zeros(n, np.bool_)
    du = np.empty(6)
    dv = np.empty(6)
    mean = np.empty(6)
    Ji = np.empty((m, 6))
    Ai = np.empty((6, 6))
    for i in range(n):
        ok = True
        for k in range(m):
            if not (np.isfinite(ref[i, k]) and np.isfinite(gx[i, k]) and np.isfinite(gy[i, k])):
                ok = False
        valid_ref[i] = ok
        if not ok:
            J[i] = 0.0
            A[i] = 0.0
            continue
        x, y, z = P[i, 0], P[i, 1], P[i, 2]
        iz = 1.0 / z
        du[0], du[1], du[2] = fx * iz, 0.0, -fx * x * iz * iz
        du[3], du[4], du[5] = -fx * x * y * iz * iz, fx * (1 + x * x * iz * iz), -fx * y * iz
        dv[0], dv[1], dv[2] = 0.0, fy * iz, -fy * y * iz * iz
        dv[3], dv[4], dv[5] = -fy * (1 + y * y * iz * iz), fy * x * y * iz * iz, fy * x * iz
        mean[:] = 0.0
        for k in range(m):
            for c in range(6):
                jc = gx[i, k] * du[c] + gy[i, k] * dv[c]
                Ji[k, c] = jc
                mean[c] += jc
        Ai[:] = 0.0
        for k in range(m):
            for c in range(6):
                Ji[k, c] -= mean[c] / m
                J[i, k, c] = Ji[k, c]
            for c in range(6):
                for d in range(c, 6):
                    Ai[c, d] += Ji[k, c] * Ji[k, d]
        A[i] = Ai
    return valid_ref


@njit(cache=True, nogil=True)
def _unit_patch_residuals(P, T, img, fx, fy, cx, cy, z_min, ref0, valid_ref, r, valid):
    """Zero-mean residuals r (N, 9) of the flies P moved by T in img over the 3×3 unit PATTERN
    (bilinear; the nine samples share one 4×4 block of pixels and one pair of fractions), and which
    flies are in view (valid, returned as their count); flies out of view get r = 0."""
    h, w = img.shape
    used = 0
    vals = np.empty(9)
    blk = np.empty((4, 4))
    for i in range(P.shape[0]):
        x = T[0, 0] * P[i, 0] + T[0, 1] * P[i, 1] + T[0, 2] * P[i, 2] + T[0, 3]
        y = T[1, 0] * P[i, 0] + T[1, 1] * P[i, 1] + T[1, 2] * P[i, 2] + T[1, 3]
        z = T[2, 0] * P[i, 0] + T[2, 1] * P[i, 1] + T[2, 2] * P[i, 2] + T[2, 3]
        ok = valid_ref[i] and z > z_min
        if ok:
            u0 = fx * x / z + cx
            v0 = fy * y / z + cy
            ok = u0 - 1.0 >= 0.0 and v0 - 1.0 >= 0.0 and u0 + 1.0 < w - 1 and v0 + 1.0 < h - 1
        if ok:
            iu, iv = int(u0 - 1.0), int(v0 - 1.0)
            a, b = u0 - 1.0 - iu, v0 - 1.0 - iv
            for dy in range(4):
                for dx in range(4):
                    blk[dy, dx] = img[iv + dy, iu + dx]
            mean = 0.0
            for dy in range(3):
                for dx in range(3):
                    val = ((1 - a) * (1 - b) * blk[dy, dx] + a * (1 - b) * blk[dy, dx + 1]
                           + (1 - a) * b * blk[dy + 1, dx] + a * b * blk[dy + 1, dx + 1])
                    vals[3 * dy + dx] = val
                    mean += val
            mean /= 9.0
            for k in range(9):
                r[i, k] = vals[k] - mean - ref0[i, k]
            used += 1
        else:
            for k in range(9):
                r[i, k] = 0.0
        valid[i] = ok
    return used


@njit(cache=True, nogil=True)
def _robust_normal_equations(J, A, r, valid, weights, huber_k, H, g):
    """Gauss-Newton H = Σ w h JᵀJ and g = Σ w h Jᵀr with Huber weights h (into H, g), and the inlier
    share. A fly's precomputed A = Σₒ JᵀJ is taken as is and only its outliers' (1 − h) JᵀJ removed."""
    H[:] = 0.0
    g[:] = 0.0
    inliers, count = 0, 0
    for i in range(J.shape[0]):
        if not valid[i]:
            continue
        wi = weights[i]
        for c in range(6):
            for d in range(c, 6):
                H[c, d] += wi * A[i, c, d]
        for p in range(J.shape[1]):
            e = r[i, p]
            a = abs(e)
            count += 1
            if a <= huber_k:
                inliers += 1
                for c in range(6):
                    g[c] += wi * J[i, p, c] * e
            else:
                hub = huber_k / a
                for c in range(6):
                    g[c] += wi * hub * J[i, p, c] * e
                    jc = wi * (1.0 - hub) * J[i, p, c]
                    for d in range(c, 6):
                        H[c, d] -= jc * J[i, p, d]
    for c in range(6):
        for d in range(c):
            H[c, d] = H[d, c]
    return inliers / max(count, 1)


@njit(cache=True, nogil=True)
def _solve6(M, b, x):
    """x = M⁻¹ b for a 6×6 M (Gaussian elimination with partial pivoting; M and b are overwritten);
    False when a pivot is exactly zero, as LAPACK's gesv reports a singular matrix."""
    n = 6
    for col in range(n):
        piv = col
        for row in range(col + 1, n):
            if abs(M[row, col]) > abs(M[piv, col]):
                piv = row
        if M[piv, col] == 0.0:
            return False
        if piv != col:
            for k in range(n):
                M[col, k], M[piv, k] = M[piv, k], M[col, k]
            b[col], b[piv] = b[piv], b[col]
        for row in range(col + 1, n):
            f = M[row, col] / M[col, col]
            for k in range(col, n):
                M[row, k] -= f * M[col, k]
            b[row] -= f * b[col]
    for row in range(n - 1, -1, -1):
        s = b[row]
        for k in range(row + 1, n):
            s -= M[row, k] * x[k]
        x[row] = s / M[row, row]
    return True


@njit(cache=True, nogil=True)
def _compose_inverse_increment(T, xi):
    """T ← T · se3_exp(xi)⁻¹ in place (Rodrigues rotation, first-order translation, as se3_exp)."""
    wx, wy, wz = xi[3], xi[4], xi[5]
    th = np.sqrt(wx * wx + wy * wy + wz * wz)
    R = np.eye(3)
    if th < 1e-12:
        s, c1, kx, ky, kz = 1.0, 0.0, wx, wy, wz
    else:
        s, c1, kx, ky, kz = np.sin(th), 1.0 - np.cos(th), wx / th, wy / th, wz / th
    K = np.array([[0.0, -kz, ky], [kz, 0.0, -kx], [-ky, kx, 0.0]])
    for a in range(3):
        for b in range(3):
            kk = K[a, 0] * K[0, b] + K[a, 1] * K[1, b] + K[a, 2] * K[2, b]
            R[a, b] += s * K[a, b] + c1 * kk
    # inverse: rotation Rᵀ, translation −Rᵀ t
    ti = np.empty(3)
    for a in range(3):
        ti[a] = -(R[0, a] * xi[0] + R[1, a] * xi[1] + R[2, a] * xi[2])
    out = np.empty((3, 4))
    for a in range(3):
        for b in range(3):
            out[a, b] = T[a, 0] * R[b, 0] + T[a, 1] * R[b, 1] + T[a, 2] * R[b, 2]
        out[a, 3] = T[a, 0] * ti[0] + T[a, 1] * ti[1] + T[a, 2] * ti[2] + T[a, 3]
    T[:3, :] = out


@njit(cache=True, nogil=True)
def _median(values, n, counts, picked):
    """np.median(values[:n]) to the bit, without sorting or selecting over all n: a histogram of
    ``counts.size`` bins over [0, max] finds the bins holding the middle elements, and only those are
    sorted.  ``picked`` holds n.  A NaN, a negative or an infinite value, or a largest value
    so small that 4095 / max overflows, falls back to np.median: numba does not check indices, and the
    histogram must never be indexed outside."""
    top = 0.0
    for i in range(n):
        v = values[i]
        if v > top:
            top = v
        elif not v >= 0.0:              # NaN or negative
            return np.median(values[:n])
    if n < 2 or not top < np.inf or 0.0 < top < 1e-300:
        return np.median(values[:n])
    scale = (counts.shape[0] - 1) / top if top > 0 else 0.0
    counts[:] = 0
    for i in range(n):
        counts[int(values[i] * scale)] += 1
    k = (n >> 1) - 1                    # the middle pair is the k-th and (k+1)-th smallest (0-based)
    below, first = 0, 0
    while below + counts[first] <= k:
        below += counts[first]
        first += 1
    last, upto = first, below + counts[first]
    while upto <= k + 1:
        last += 1
        upto += counts[last]
    m = 0
    for i in range(n):
        b = int(values[i] * scale)
        if first <= b <= last:
            picked[m] = values[i]
            m += 1
    middle = np.sort(picked[:m])
    if n & 1 == 0:
        return (middle[k - below] + middle[k + 1 - below]) / 2
    return middle[k + 1 - below]


@njit(cache=True, nogil=True)
def _gauss_newton(P, weights, valid_ref, ref0, J, A, T, img, fx, fy, cx, cy, z_min, iterations, min_flies,
                  huber_px, r, valid, H, z_typical, stop_px):
    """Up to ``iterations`` robust Gauss-Newton steps of one pyramid level, T updated in place and H
    the last normal matrix; converged when a step moves a fly at depth ``z_typical`` by under
    ``stop_px`` pixels of this level. Returns (iterations run, status, robust scale σ̂, inlier share,
    flies in view); status 0 converged or ran out of iterations, 1 too few flies in view, 2 singular."""
    g = np.empty(6)
    M = np.empty((6, 6))
    dxi = np.empty(6)
    absr = np.empty(r.shape[0] * r.shape[1])
    counts = np.empty(4096, np.int64)       # _median's scratch
    picked = np.empty(absr.size)
    sigma, inlier_frac, used = np.nan, 0.0, 0
    for it in range(iterations):
        used = _unit_patch_residuals(P, T, img, fx, fy, cx, cy, z_min, ref0, valid_ref, r, valid)
        if used < min_flies:
            return it + 1, 1, np.nan, 0.0, used
        n = 0
        for i in range(r.shape[0]):
            if valid[i]:
                for k in range(r.shape[1]):
                    absr[n] = abs(r[i, k])
                    n += 1
        sigma = 1.4826 * _median(absr, n, counts, picked) + 1e-6
        inlier_frac = _robust_normal_equations(J, A, r, valid, weights, huber_px * sigma, H, g)
        tr = 0.0
        for c in range(6):
            tr += H[c, c]
        M[:, :] = H
        for c in range(6):
            M[c, c] += 1e-9 * tr
        if not _solve6(M, g, dxi):
            return it + 1, 2, sigma, 0.0, used
        _compose_inverse_increment(T, dxi)
        moved = np.sqrt(dxi[0] ** 2 + dxi[1] ** 2 + dxi[2] ** 2) / z_typical
        turned = np.sqrt(dxi[3] ** 2 + dxi[4] ** 2 + dxi[5] ** 2)
        if fx * (moved + turned) < stop_px:
            return it + 1, 0, sigma, inlier_frac, used
    return iterations, 0, sigma, inlier_frac, used


def _project(P: np.ndarray, fx, fy, cx, cy):
    z = P[:, 2]
    return fx * P[:, 0] / z + cx, fy * P[:, 1] / z + cy


_REFERENCE_CACHE: list[dict] = []     # the last few reference_levels results, newest last
_REFERENCE_CACHE_SIZE = 2


def _level_terms(P_all, w_all, ref_pyramid, K, min_flies):
    """Per pyramid level, coarse to fine: (level, flies, weights, fx, fy, cx, cy, valid_ref, ref0, J, A),
    everything of the Gauss-Newton step that comes from the reference view alone."""
    rng = np.random.default_rng(0)
    out = []
    for level in range(len(ref_pyramid) - 1, -1, -1):
        # a coarse level sees fewer pixels: fewer flies carry its information
        n_level = max(min_flies, int(len(P_all) * 0.25 ** level * 4))
        if n_level < len(P_all):
            pick = np.sort(rng.choice(len(P_all), n_level, replace=False))
            P, w = P_all[pick], w_all[pick]
        else:
            P, w = P_all, w_all
        fx, fy, cx, cy = level_intrinsics(K, level)
        Iref = ref_pyramid[level]
        u, v = _project(P, fx, fy, cx, cy)
        uo = u[:, None] + PATTERN[None, :, 0]
        vo = v[:, None] + PATTERN[None, :, 1]
        ref = _sample(Iref, uo, vo)
        gx = _sample(cv2.Sobel(Iref, cv2.CV_32F, 1, 0, ksize=3, scale=0.125), uo, vo)
        gy = _sample(cv2.Sobel(Iref, cv2.CV_32F, 0, 1, ksize=3, scale=0.125), uo, vo)
        J = np.empty((len(P), len(PATTERN), 6))
        A = np.empty((len(P), 6, 6))
        valid_ref = _reference_terms(P, fx, fy, ref, gx, gy, J, A)
        # zero-mean reference neighbourhoods kept in float32 as sampled: the tracked trajectory is
        # sensitive to their rounding
        ref0 = np.where(valid_ref[:, None], ref - ref.mean(1, keepdims=True), 0.0)
        out.append((level, P, w, fx, fy, cx, cy, valid_ref, ref0, J, A))
    return out


def reference_levels(points_ref, weights, P, w, ref_pyramid, K, min_flies, depth_range):
    """:func:`_level_terms` of the filtered flies P, w, reused while the same reference is tracked.

    A tracking reference is aligned into frame after frame; its terms are kept for the last
    ``_REFERENCE_CACHE_SIZE`` references and reused when the pyramid levels are the very same arrays
    (held by weak reference: an array freed and another allocated at its address does not match) and
    the flies, weights, K, min_flies and depth range are equal. Invariant: a pyramid level is not
    modified in place once built (:func:`pyramid` always returns new arrays)."""
    pts, wts, Km = np.asarray(points_ref), np.asarray(weights), np.asarray(K, np.float64)
    for entry in reversed(_REFERENCE_CACHE):
        if (len(entry["levels"]) == len(ref_pyramid)
                and all(ref() is lvl for ref, lvl in zip(entry["levels"], ref_pyramid))
                and entry["params"] == (min_flies, tuple(depth_range))
                and np.array_equal(entry["points"], pts) and np.array_equal(entry["weights"], wts)
                and np.array_equal(entry["K"], Km)):
            return [(t[0], t[1:]) for t in entry["terms"]]
    terms = _level_terms(P, w, ref_pyramid, Km, min_flies)
    try:
        levels = tuple(weakref.ref(lvl) for lvl in ref_pyramid)
    except TypeError:               # not weak-referenceable (not an ndarray): nothing to key on
        return [(t[0], t[1:]) for t in terms]
    _REFERENCE_CACHE.append({"levels": levels, "params": (min_flies, tuple(depth_range)), "points": pts.copy(),
                             "weights": wts.copy(), "K": Km.copy(), "terms": terms})
    del _REFERENCE_CACHE[:-_REFERENCE_CACHE_SIZE]
    return [(t[0], t[1:]) for t in terms]


def align_flies(points_ref: np.ndarray, weights: np.ndarray, ref_pyramid: list[np.ndarray],
                new_pyramid: list[np.ndarray], K: np.ndarray, T_init: np.ndarray | None = None,
                iterations: int = 12, huber_px: float = 1.345, min_flies: int = 50,
                depth_range=(0.1, np.inf)) -> Alignment:
    """Direct alignment of reference flies into a new image (see the module docstring).

    points_ref (N, 3): flies in the reference left optical frame; weights (N,) ≥ 0 (fitness);
    ref_pyramid / new_pyramid: :func:`pyramid` of the two left images (same number of levels);
    K: 3×3 rectified left intrinsics at level 0; T_init: the starting T_new_ref (identity if None).
    """
    P = np.asarray(points_ref, np.float64)
    w = np.asarray(weights, np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or w.shape != (len(P),):
        raise AlignmentError(f"points must be (N, 3) with (N,) weights, got {P.shape} and {w.shape}")
    if len(ref_pyramid) != len(new_pyramid) or not ref_pyramid:
        raise AlignmentError("reference and new pyramids must have the same, non-zero number of levels")
    T = np.eye(4) if T_init is None else np.asarray(T_init, np.float64).copy()
    if not (np.all(np.isfinite(T)) and np.all(np.isfinite(K))):
        raise AlignmentError("T_init and K must be finite")
    ok = np.isfinite(P).all(1) & np.isfinite(w) & (w > 0) & (P[:, 2] > depth_range[0]) & (P[:, 2] < depth_range[1])
    P_all, w_all = P[ok], w[ok]
    if len(P_all) < min_flies:
        return Alignment(T, np.full((6, 6), np.nan), np.nan, 0.0, len(P_all), 0, False,
                         f"too few flies to align: {len(P_all)} (need {min_flies})")
    z_typical = max(float(np.median(P_all[:, 2])), 1e-6)
    total_iters = 0
    H = np.eye(6)
    sigma = np.nan
    inlier_frac, used = 0.0, 0
    for level, (P, w, fx, fy, cx, cy, valid_ref, ref0, J, A) in reference_levels(
            points_ref, weights, P_all, w_all, ref_pyramid, K, min_flies, depth_range):
        Inew = new_pyramid[level]
        r = np.empty((len(P), len(PATTERN)))
        valid = np.empty(len(P), np.bool_)
        its, status, sigma, inlier_frac, used = _gauss_newton(
            P, w, valid_ref, ref0, J, A, T, Inew, fx, fy, cx, cy, float(depth_range[0]), int(iterations),
            int(min_flies), float(huber_px), r, valid, H, z_typical, FINE_STOP_PX if level == 0 else COARSE_STOP_PX)
        total_iters += its
        T = orthonormalised(T)
        if status == 1 and level > 0:
            # a coarse level only widens the basin: with too few of its (subsampled, border-trimmed)
            # flies in view, the finer levels carry on from the motion so far
            continue
        if status == 1:
            return Alignment(T, np.full((6, 6), np.nan), np.nan, 0.0, used, total_iters, False,
                             f"too few flies in view: {used} (need {min_flies})")
        if status == 2:
            return Alignment(T, np.full((6, 6), np.nan), sigma, 0.0, used, total_iters, False,
                             "singular alignment: the flies do not constrain all six degrees of freedom")
    wsum = float(w.sum())
    # H is Σ wᵢ hᵢ JᵀJ: with weights normalised to mean 1, σ̂² H⁻¹ is the Gauss-Newton covariance.
    scale = len(w) / wsum if wsum > 0 else 1.0
    try:
        cov = sigma ** 2 * np.linalg.inv(H * scale)
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.nan)
    return Alignment(T, cov, sigma, inlier_frac, used, total_iters, True)


def coarse_search(points_ref: np.ndarray, weights: np.ndarray, ref_pyramid: list[np.ndarray],
                  new_pyramid: list[np.ndarray], K: np.ndarray, T_center: np.ndarray | None = None,
                  max_candidates_per_axis: int = 11, max_flies: int = 200) -> np.ndarray:
    """The best start for :func:`align_flies` when the motion is unknown (the first of
    :func:`coarse_candidates`)."""
    return coarse_candidates(points_ref, weights, ref_pyramid, new_pyramid, K, T_center, 1,
                             max_candidates_per_axis, max_flies)[0]


def coarse_candidates(points_ref: np.ndarray, weights: np.ndarray, ref_pyramid: list[np.ndarray],
                      new_pyramid: list[np.ndarray], K: np.ndarray, T_center: np.ndarray | None = None,
                      count: int = 3, max_candidates_per_axis: int = 11, max_flies: int = 200) -> list[np.ndarray]:
    """Starts for :func:`align_flies` when the motion is unknown, best first: a lattice of camera
    motions (lateral x, forward z, yaw about the optical y axis, pitch about its x axis) around
    ``T_center``, scored at the coarsest pyramid level by the robust mean residual of the flies'
    zero-mean neighbourhoods; the ``count`` deepest local minima of that score (distinct basins: on a
    deep scene a sideways step with a turn can score nearly as well as the forward motion, and only
    the full alignment tells).

    The lattice spans what keeps the views overlapping — ±0.1 × the flies' median depth sideways,
    ±0.25 × it forwards, ±5° of yaw and of pitch — with steps that move a fly ~1.5 coarse pixels (about
    half as many yaws and pitches: a lateral step mostly looks like a yaw, a vertical image shift is what
    a pitch makes and the alignment's basin holds a few coarse pixels of it).  A pitching rig (hand-held,
    rough ground) needs the pitch axis: without it the best start is a sideways step with a turn."""
    P = np.asarray(points_ref, np.float64)
    w = np.asarray(weights, np.float64)
    ok = np.isfinite(P).all(1) & (P[:, 2] > 0.1) & np.isfinite(w) & (w > 0)
    P, w = P[ok], w[ok]
    T0 = np.eye(4) if T_center is None else np.asarray(T_center, float)
    if len(P) < 10:
        return [T0]
    if len(P) > max_flies:
        pick = np.random.default_rng(0).choice(len(P), max_flies, replace=False)
        P, w = P[pick], w[pick]
    level = len(ref_pyramid) - 1
    fx, fy, cx, cy = level_intrinsics(K, level)
    # the fitter half's median depth: young flies, drawn uniform in 1/z, sit mostly near the camera
    fit = w >= np.median(w)
    z_med = float(np.median(P[fit, 2]))
    step_px = 1.5

    def axis(half, step, halved=False):
        n = int(min(max_candidates_per_axis, 2 * np.ceil(half / step) + 1)) | 1
        if halved:   # about half as many, still spanning ±half with the centre's among them
            n = (n + 1) // 2 | 1
        return np.linspace(-half, half, n)
    xs = axis(0.1 * z_med, step_px * z_med / fx)
    zs = axis(0.25 * z_med, step_px * z_med / (0.5 * fx))
    yaws = axis(np.deg2rad(5.0), step_px / fx, halved=max_candidates_per_axis > 5)
    pitches = axis(np.deg2rad(5.0), step_px / fy, halved=max_candidates_per_axis > 5)
    X, Z, Y = (a.ravel() for a in np.meshgrid(xs, zs, yaws, indexing="ij"))
    c, sn = np.cos(Y), np.sin(Y)
    Iref, Inew = ref_pyramid[level], new_pyramid[level]
    u0, v0 = _project(P, fx, fy, cx, cy)
    ref = _sample(Iref, u0[:, None] + PATTERN[None, :, 0], v0[:, None] + PATTERN[None, :, 1])
    ref = ref - ref.mean(1, keepdims=True)
    Pc = P @ T0[:3, :3].T + T0[:3, 3]                                  # flies under the centre motion
    ref_ok = np.isfinite(ref).all(1)
    ref = np.ascontiguousarray(np.where(ref_ok[:, None], ref, 0.0), np.float32)
    w_ok = np.where(ref_ok, w, 0.0)        # a fly without a reference neighbourhood scores the cap
    cap = float(w[~ref_ok].sum()) * _SCORE_CAP    # the same for every candidate: keeps the score a mean
    Inew32 = np.ascontiguousarray(Inew, np.float32)
    scores = []
    for pitch in pitches:               # one (x, z, yaw) lattice per pitch (a loop of ≤ 11, not over flies)
        Q = np.ascontiguousarray(Pc @ rot_x(pitch).T)
        # candidate m: rot_y(yaw) · rot_x(pitch) · p + (x, 0, z)
        scores.append((_lattice_scores(Inew32, ref, w_ok, Q, X, Z, c, sn, float(fx), float(fy), float(cx),
                                       float(cy)) + cap) / w.sum())
    score = np.stack(scores, axis=1).ravel()                           # (x, z, yaw, pitch) order
    grid = score.reshape(len(xs), len(zs), len(yaws), len(pitches))
    minima = np.flatnonzero(grid.ravel() <= minimum_filter(grid, size=3, mode="nearest").ravel())
    starts = []
    for best in minima[np.argsort(score[minima], kind="stable")][:max(1, count)]:
        m, k = divmod(int(best), len(pitches))
        D = np.eye(4)
        D[:3, :3] = rot_y(Y[m]) @ rot_x(pitches[k])
        D[:3, 3] = (X[m], 0.0, Z[m])
        starts.append(D @ T0)
    return starts


_SCORE_CAP = 20.0   # a fly's lattice residual is truncated here (grey levels), and is this when not seen


@njit(cache=True, nogil=True)
def _lattice_scores(img, ref, w, Q, X, Z, c, sn, fx, fy, cx, cy):
    """Σ weight × truncated mean |zero-mean 3×3 neighbourhood − ref| over the flies Q (N, 3), for each
    candidate m: rot_y(yaw_m)·q + (X_m, 0, Z_m) (c, sn its yaw's cos, sin), projected with fx, fy, cx,
    cy.  A fly behind the camera or whose neighbourhood leaves the image counts _SCORE_CAP.  One pass
    over candidates and flies, no M×N×9 temporaries."""
    H, W = img.shape
    M, N = X.shape[0], Q.shape[0]
    out = np.zeros(M)
    patch = np.empty(9)
    for m in range(M):
        acc = 0.0
        for n in range(N):
            if w[n] == 0.0:
                continue
            qx, qy, qz = Q[n, 0], Q[n, 1], Q[n, 2]
            px = c[m] * qx + sn[m] * qz + X[m]
            pz = -sn[m] * qx + c[m] * qz + Z[m]
            if pz <= 0.1:
                acc += w[n] * _SCORE_CAP
                continue
            u = fx * px / pz + cx
            v = fy * qy / pz + cy
            if not (u >= 1.0 and u < W - 2.0 and v >= 1.0 and v < H - 2.0):
                acc += w[n] * _SCORE_CAP
                continue
            mean = 0.0
            k = 0
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    x, y = u + dx, v + dy
                    x0, y0 = int(x), int(y)
                    ax, ay = x - x0, y - y0
                    val = ((1 - ay) * ((1 - ax) * img[y0, x0] + ax * img[y0, x0 + 1])
                           + ay * ((1 - ax) * img[y0 + 1, x0] + ax * img[y0 + 1, x0 + 1]))
                    patch[k] = val
                    mean += val
                    k += 1
            mean /= 9.0
            r = 0.0
            for k in range(9):
                r += abs(patch[k] - mean - ref[n, k])
            r /= 9.0
            acc += w[n] * (r if r < _SCORE_CAP else _SCORE_CAP)     # (NaN from the image: the cap)
        out[m] = acc
    return out

