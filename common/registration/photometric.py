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

from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

from common.geometry import orthonormalised, so3_exp

PATTERN = np.array([(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], np.float32)   # (9, 2) px
PATTERN_F64 = PATTERN.astype(np.float64)


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


def pyramid(image: np.ndarray, levels: int) -> list[np.ndarray]:
    """float32 grey pyramid, level 0 = the image; each level halves the size (cv2.pyrDown)."""
    img = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    out = [img.astype(np.float32)]
    for _ in range(levels - 1):
        out.append(cv2.pyrDown(out[-1]))
    return out


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


@njit(cache=True)
def _residuals(P, T, img, fx, fy, cx, cy, z_min, pattern, ref0, valid_ref, r, valid):
    """Zero-mean neighbourhood residuals r (N, 9) of the flies P moved by T in img (bilinear), and
    which flies are in view (valid); flies out of view get r = 0."""
    h, w = img.shape
    m = pattern.shape[0]
    vals = np.empty(m)
    for i in range(P.shape[0]):
        x = T[0, 0] * P[i, 0] + T[0, 1] * P[i, 1] + T[0, 2] * P[i, 2] + T[0, 3]
        y = T[1, 0] * P[i, 0] + T[1, 1] * P[i, 1] + T[1, 2] * P[i, 2] + T[1, 3]
        z = T[2, 0] * P[i, 0] + T[2, 1] * P[i, 1] + T[2, 2] * P[i, 2] + T[2, 3]
        ok = valid_ref[i] and z > z_min
        if ok:
            u0 = fx * x / z + cx
            v0 = fy * y / z + cy
            mean = 0.0
            for k in range(m):
                u = u0 + pattern[k, 0]
                v = v0 + pattern[k, 1]
                if not (u >= 0.0 and v >= 0.0 and u < w - 1 and v < h - 1):
                    ok = False
                    break
                iu, iv = int(u), int(v)
                a, b = u - iu, v - iv
                val = ((1 - a) * (1 - b) * img[iv, iu] + a * (1 - b) * img[iv, iu + 1]
                       + (1 - a) * b * img[iv + 1, iu] + a * b * img[iv + 1, iu + 1])
                vals[k] = val
                mean += val
            if ok:
                mean /= m
                for k in range(m):
                    r[i, k] = vals[k] - mean - ref0[i, k]
        valid[i] = ok
        if not ok:
            for k in range(m):
                r[i, k] = 0.0


@njit(cache=True)
def _normal_equations(J, r, valid, weights, huber_k):
    """Gauss-Newton H = Σ w h JᵀJ and g = Σ w h Jᵀr with Huber weights h, and the inlier share."""
    H = np.zeros((6, 6))
    g = np.zeros(6)
    inliers, count = 0, 0
    for i in range(J.shape[0]):
        if not valid[i]:
            continue
        for p in range(J.shape[1]):
            a = abs(r[i, p])
            hub = 1.0 if a <= huber_k else huber_k / a
            wt = hub * weights[i]
            inliers += a <= huber_k
            count += 1
            for c in range(6):
                jc = wt * J[i, p, c]
                g[c] += jc * r[i, p]
                for d in range(c, 6):
                    H[c, d] += jc * J[i, p, d]
    for c in range(6):
        for d in range(c):
            H[c, d] = H[d, c]
    return H, g, inliers / max(count, 1)


def _project(P: np.ndarray, fx, fy, cx, cy):
    z = P[:, 2]
    return fx * P[:, 0] / z + cx, fy * P[:, 1] / z + cy


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
    P, w = P[ok], w[ok]
    if len(P) < min_flies:
        return Alignment(T, np.full((6, 6), np.nan), np.nan, 0.0, len(P), 0, False,
                         f"too few flies to align: {len(P)} (need {min_flies})")
    fx0, fy0, cx0, cy0 = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    total_iters = 0
    H = np.eye(6)
    sigma = np.nan
    inlier_frac, used = 0.0, 0
    rng = np.random.default_rng(0)
    P_all, w_all = P, w
    for level in range(len(ref_pyramid) - 1, -1, -1):
        # a coarse level sees fewer pixels: fewer flies carry its information
        n_level = max(min_flies, int(len(P_all) * 0.25 ** level * 4))
        if n_level < len(P_all):
            pick = np.sort(rng.choice(len(P_all), n_level, replace=False))
            P, w = P_all[pick], w_all[pick]
        else:
            P, w = P_all, w_all
        s = 0.5 ** level
        fx, fy = fx0 * s, fy0 * s
        cx, cy = (cx0 + 0.5) * s - 0.5, (cy0 + 0.5) * s - 0.5
        Iref, Inew = ref_pyramid[level], new_pyramid[level]
        u, v = _project(P, fx, fy, cx, cy)
        uo = u[:, None] + PATTERN[None, :, 0]
        vo = v[:, None] + PATTERN[None, :, 1]
        ref = _sample(Iref, uo, vo)
        gx = _sample(cv2.Sobel(Iref, cv2.CV_32F, 1, 0, ksize=3, scale=0.125), uo, vo)
        gy = _sample(cv2.Sobel(Iref, cv2.CV_32F, 0, 1, ksize=3, scale=0.125), uo, vo)
        valid_ref = np.isfinite(ref).all(1) & np.isfinite(gx).all(1) & np.isfinite(gy).all(1)
        # Jacobian of the projection w.r.t. a right perturbation of the point: dπ/dp · [I | −[p]×]
        x, y, z = P[:, 0], P[:, 1], P[:, 2]
        iz = 1.0 / z
        du = np.stack([fx * iz, np.zeros_like(z), -fx * x * iz * iz,
                       -fx * x * y * iz * iz, fx * (1 + x * x * iz * iz), -fx * y * iz], 1)
        dv = np.stack([np.zeros_like(z), fy * iz, -fy * y * iz * iz,
                       -fy * (1 + y * y * iz * iz), fy * x * y * iz * iz, fy * x * iz], 1)
        J = gx[:, :, None] * du[:, None, :] + gy[:, :, None] * dv[:, None, :]      # (N, 9, 6)
        J = np.where(valid_ref[:, None, None], J - J.mean(1, keepdims=True), 0.0)   # zero-mean patches
        ref0 = np.where(valid_ref[:, None], ref - ref.mean(1, keepdims=True), 0.0)
        Jc = np.ascontiguousarray(J)
        r = np.empty((len(P), len(PATTERN)))
        valid = np.empty(len(P), np.bool_)
        for _ in range(iterations):
            total_iters += 1
            _residuals(P, T, Inew, fx, fy, cx, cy, depth_range[0], PATTERN_F64, ref0, valid_ref, r, valid)
            used = int(valid.sum())
            if used < min_flies:
                return Alignment(T, np.full((6, 6), np.nan), np.nan, 0.0, used, total_iters, False,
                                 f"too few flies in view: {used} (need {min_flies})")
            sigma = 1.4826 * float(np.median(np.abs(r[valid]))) + 1e-6
            H, g, inlier_frac = _normal_equations(Jc, r, valid, w, huber_px * sigma)
            try:
                dxi = np.linalg.solve(H + 1e-9 * np.trace(H) * np.eye(6), g)
            except np.linalg.LinAlgError:
                return Alignment(T, np.full((6, 6), np.nan), sigma, 0.0, used, total_iters, False,
                                 "singular alignment: the flies do not constrain all six degrees of freedom")
            T = orthonormalised(T @ np.linalg.inv(se3_exp(dxi)))
            if np.max(np.abs(dxi[:3])) < 1e-4 and np.max(np.abs(dxi[3:])) < 1e-5:
                break
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
    """The best start for :func:`align_flies` when the motion is unknown: a lattice of camera motions
    (lateral x, forward z, yaw about the optical y axis) around ``T_center``, scored at the coarsest
    pyramid level by the robust mean residual of the flies' zero-mean neighbourhoods.

    The lattice spans what keeps the views overlapping — ±0.1 × the flies' median depth sideways,
    ±0.25 × it forwards, ±5° of yaw — with steps that move a fly ~1.5 coarse pixels."""
    P = np.asarray(points_ref, np.float64)
    w = np.asarray(weights, np.float64)
    ok = np.isfinite(P).all(1) & (P[:, 2] > 0.1) & np.isfinite(w) & (w > 0)
    P, w = P[ok], w[ok]
    T0 = np.eye(4) if T_center is None else np.asarray(T_center, float)
    if len(P) < 10:
        return T0
    if len(P) > max_flies:
        pick = np.random.default_rng(0).choice(len(P), max_flies, replace=False)
        P, w = P[pick], w[pick]
    level = len(ref_pyramid) - 1
    s = 0.5 ** level
    fx, fy = K[0, 0] * s, K[1, 1] * s
    cx, cy = (K[0, 2] + 0.5) * s - 0.5, (K[1, 2] + 0.5) * s - 0.5
    # the fitter half's median depth: young flies, drawn uniform in 1/z, sit mostly near the camera
    fit = w >= np.median(w)
    z_med = float(np.median(P[fit, 2]))
    step_px = 1.5

    def axis(half, step):
        n = int(min(max_candidates_per_axis, 2 * np.ceil(half / step) + 1)) | 1
        return np.linspace(-half, half, n)
    xs = axis(0.1 * z_med, step_px * z_med / fx)
    zs = axis(0.25 * z_med, step_px * z_med / (0.5 * fx))
    yaws = axis(np.deg2rad(5.0), step_px / fx)
    if max_candidates_per_axis > 5:
        yaws = yaws[::2]                 # every other yaw: a lateral step mostly looks like one
    X, Z, Y = np.meshgrid(xs, zs, yaws, indexing="ij")
    X, Z, Y = X.ravel(), Z.ravel(), Y.ravel()
    c, sn = np.cos(Y), np.sin(Y)
    Pc = P @ T0[:3, :3].T + T0[:3, 3]                                  # flies under the centre motion
    # candidate m: rot_y(yaw) · p + (x, 0, z)
    px = c[:, None] * Pc[None, :, 0] + sn[:, None] * Pc[None, :, 2] + X[:, None]
    pz = -sn[:, None] * Pc[None, :, 0] + c[:, None] * Pc[None, :, 2] + Z[:, None]
    py = np.broadcast_to(Pc[None, :, 1], px.shape)
    front = pz > 0.1
    pz = np.where(front, pz, 1.0)
    u = fx * px / pz + cx
    v = fy * py / pz + cy
    Iref, Inew = ref_pyramid[level], new_pyramid[level]
    u0, v0 = _project(P, fx, fy, cx, cy)
    ref = _sample(Iref, u0[:, None] + PATTERN[None, :, 0], v0[:, None] + PATTERN[None, :, 1])
    ref = ref - ref.mean(1, keepdims=True)
    cur = _sample(Inew, u[:, :, None] + PATTERN[None, None, :, 0], v[:, :, None] + PATTERN[None, None, :, 1])
    r = np.abs(cur - cur.mean(2, keepdims=True) - ref[None])          # (M, N, 9)
    valid = front & np.isfinite(r).all(2) & np.isfinite(ref).all(1)[None]
    per_fly = np.where(valid, np.minimum(np.nan_to_num(r.mean(2), nan=0.0), 20.0), 20.0)   # truncated
    score = (per_fly * w[None]).sum(1) / w.sum()
    best = int(np.argmin(score))
    D = np.eye(4)
    D[:3, :3] = np.array([[c[best], 0, sn[best]], [0, 1, 0], [-sn[best], 0, c[best]]])
    D[:3, 3] = (X[best], 0.0, Z[best])
    return D @ T0
