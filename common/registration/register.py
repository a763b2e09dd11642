"""Register two fly populations: the rigid displacement f minimising δ(A, f(B)).

Louchet et al. find the robot's motion between two frames as the displacement that best superposes
the population B seen at the second pose onto the population A seen at the first.  Here

    f* = argmin_f δ(A, f(B)),    δ(A, f(B)) = (P/N) Σᵢ wᵃᵢ / S_B(f⁻¹(aᵢ))

(a rigid f moves B's field with it, so B's field is built *once* and read at f⁻¹(aᵢ)).  f maps points
of B's frame into A's frame: if A was seen from camera pose 1 and B from pose 2, f = T_cam1_cam2.

Parametrisations (``res.params``):

* ``plane="optical"`` (the paper's camera optical frame, y down): params (x, z, θ); f rotates by θ about
  the y axis (``rot_y``) and translates by (x, 0, z).
* ``plane="body"`` (REP-103 body/map frame, z up): params (x, y, θ); rotation θ about z, translation
  (x, y, 0).
* 6-DoF: params (tx, ty, tz, ωx, ωy, ωz), ω the rotation vector of f's rotation (``so3_exp``).

Search (coarse to fine, in scale and in position):

1. a lattice over the search window (prior ± window), scored on a random subset of A with B's
   *far* field only — B smoothed within r_c, a wide-basin version of δ;
2. the best distinct lattice minima are polished on that smoothed δ (L-BFGS-B, bounded by the window);
3. the best two are refined on the full δ (near-field included) with a larger subset of A;
   both are kept to detect ambiguity.

Covariance (``res.covariance``): δ is a mean of per-fly terms cᵢ, so f* is an M-estimator and its
covariance is the sandwich H⁻¹ (Σᵢ gᵢ gᵢᵀ) H⁻¹, with H the Hessian of the summed objective (central
differences of the analytic gradient) and gᵢ = ∂cᵢ/∂params the per-fly gradients at the minimum.  This
fixes the otherwise arbitrary scale of "curvature of δ": it is in params² units and shrinks as 1/n,
and it is large along directions where δ is flat.  The sum runs over A's flies only; B's flies
carry the same kind of noise and, for populations of similar size, contribute an equal term, hence
a factor 2.  It still treats flies as independent and ignores model bias, so it is optimistic: on
the deep street (bench/registration_variants.py) the median NEES eᵀΣ⁻¹e of the default StereoModel
registration was ≈ 5–15 instead of 3 (standard deviations ≈ 1.5–2× too small), and 25–50 for the
paper's δ, whose error there is mostly bias — inflate before fusing.

Speed (bench/registration.py, 5,000 flies per population, CPU time on the shared 2-core machine;
``res.timings`` holds the wall time per stage): ≈26 ms for a planar registration with the paper's δ
(field build ≈11 ms — deposit, zero-padding-aware FFT, cell list —, lattice ≈2.5 ms, polish ≈1.5 ms,
refine ≈5 ms, Hessian and covariance ≈5 ms), ≈33 ms with StereoModel (no FFT: lattice ≈9 ms on the
wide local kernel, polish ≈6 ms, refine ≈13 ms), ≈62 ms for 6-DoF (3,375 lattice candidates).
Before (same bench): 67, 99 and 196 ms.  The localiser's calls (≈2–3k flies against a ≤6k-point
map, 0.25 m / 8° windows, StereoModel) took ≈37 ms on average, ≈24 ms since the lattice follows
the window (StereoModel.lattice_step: 125 instead of 343 candidates), extra seeds stop in a basin
already polished, and the planar flatness check reuses H's in-plane block; ≈20 ms since the refine
starts from the polish's inverse-Hessian estimate (≈21 → 8 evaluations of the full objective; its
steps are capped at half a lattice step so that estimate, from the smoother objective, cannot throw
it into another basin; a warm-started refine that ends on the window's edge is redone from the
identity).  Results moved by ≤ 2 mm on 95 % of those calls (max 12 mm), none changed ok/failed;
on the demo1 replay boundary-minimum rejections still rose from 35 to 53 of 1,200 updates (42 with
the lattice change alone).  Bench: StereoModel 33 → 21 ms, paper's δ 26 → 23–27 ms, same errors.  What it took: vectorisable float32 near-field loops (see
field.py), vectorised lattice poses, analytic planar pose Jacobians with a numba per-fly gradient,
no input re-validation inside the optimiser, and a refine tolerance of 1e-3 of the window (1 mm on a
1 m window; 1e-4 cost twice the evaluations for sub-millimetre changes).  Tried and dropped: a
Shanno-scaled BFGS and a step cap of one lattice spacing (no fewer evaluations overall, different
minima on some runs); a smaller registration grid (80k cells: −3 ms, results moved by 1–2 cm).

Failures (``res.ok`` False with ``res.reason``; never an exception for well-formed input): too few
flies; a minimum on the window boundary; a Hessian that is not positive definite (from differences
of the analytic gradient, or, when those are indefinite, from second differences of δ's values —
a cusp at a sharp small-ε minimum passes, a saddle does not: see _value_hessian); a flat minimum (the
smallest eigenvalue of the Hessian, rotations scaled to metres by the population's radius, below
``flat_ratio`` of the stiffest curvature, that of the larger of the Hessian's largest eigenvalue and
the curvature of δ under a free 3-D translation — so a ground plane under a planar search, flat in
all three parameters, is caught too); an ambiguous minimum (a second distinct minimum nearly as deep).
Malformed input (wrong shapes, NaN, a non-rigid prior) raises PopulationError.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field as dc_field

import numpy as np
import scipy.ndimage

from ..camera import StereoCalibration
from ..geometry import make_transform, rot_y, rot_z, so3_exp, so3_log
from . import _kernels
from .field import PseudoDistanceField
from .local import LocalCorrelationField
from .pseudo_distance import PopulationError, as_population, as_weights, check_eps
from .weights import covisible_masks, depth_weights, footprint_weights

PLANES = ("optical", "body")
OBJECTIVES = ("delta", "local")


@dataclass
class RegistrationResult:
    """Outcome of a registration.  ``T`` is f (4×4) with f(B) ≈ A; see the module docstring."""
    T: np.ndarray
    params: np.ndarray
    covariance: np.ndarray
    delta: float
    ok: bool
    reason: str = ""
    mode: str = ""
    hessian: np.ndarray | None = None
    flatness: float = float("nan")     # λ_min/λ_max of the scaled Hessian (0 = perfectly flat)
    ambiguity: float = float("nan")    # depth of the 2nd minimum relative to the best's (1 = as deep)
    evaluations: int = 0
    timings: dict = dc_field(default_factory=dict)

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of the params (sqrt of the covariance diagonal)."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0, None))


# ------------------------------------------------------------------------------ parametrisations
def _pose_optical(p):
    return rot_y(p[2]), np.array([p[0], 0.0, p[1]])


def _pose_body(p):
    return rot_z(p[2]), np.array([p[0], p[1], 0.0])


def _pose_6dof(p):
    return so3_exp(p[3:]), np.asarray(p[:3], dtype=float)


def _params_from_T(mode: str, T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    if mode == "optical":
        return np.array([t[0], t[2], np.arctan2(R[0, 2], R[2, 2])])
    if mode == "body":
        return np.array([t[0], t[1], np.arctan2(R[1, 0], R[0, 0])])
    return np.concatenate([t, so3_log(R)])


_POSES = {"optical": _pose_optical, "body": _pose_body, "6dof": _pose_6dof}


_K_Y = np.array([[0.0, 0, 1], [0, 0, 0], [-1, 0, 0]])   # d rot_y(θ)/dθ = rot_y(θ) @ _K_Y
_K_Z = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 0]])   # d rot_z(θ)/dθ = rot_z(θ) @ _K_Z
_PLANAR_DT = {"optical": np.array([[1.0, 0, 0], [0, 0, 1], [0, 0, 0]]),
              "body": np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 0]])}


def _pose_jacobians(pose, p, step=1e-6):
    """dR/dp_k (k, 3, 3) and dt/dp_k (k, 3): analytic for the planar poses, else central differences
    of the (cheap) param→pose map."""
    if pose is _pose_optical or pose is _pose_body:
        R = pose(p)[0]
        dR = np.zeros((3, 3, 3))
        dR[2] = R @ (_K_Y if pose is _pose_optical else _K_Z)
        return dR, _PLANAR_DT["optical" if pose is _pose_optical else "body"]
    k = len(p)
    dR = np.empty((k, 3, 3))
    dt = np.empty((k, 3))
    for i in range(k):
        e = np.zeros(k)
        e[i] = step
        Rp, tp = pose(p + e)
        Rm, tm = pose(p - e)
        dR[i] = (Rp - Rm) / (2 * step)
        dt[i] = (tp - tm) / (2 * step)
    return dR, dt


class _Objective:
    """J(p) on a fixed subset of A, with its gradient and per-fly gradients.

    kind "delta": J = δ(A, f_p(B)) = scale Σ wᵃᵢ / S_B(qᵢ), qᵢ = f_p⁻¹(aᵢ) (PseudoDistanceField).
    kind "local": J = −C(A, f_p(B)) = −Σ wᵃᵢ S_B(qᵢ) / Σ wᵃ  (LocalCorrelationField).
    """

    def __init__(self, field, A, wa, pose, near: bool, kind: str = "delta"):
        self.field, self.A, self.wa, self.pose, self.near, self.kind = field, A, wa, pose, near, kind
        self.scale = field.weight_sum / wa.sum() if kind == "delta" else 1.0 / wa.sum()
        self.count = 0

    def _terms(self, S, G=None):
        """Per-fly costs cᵢ and, with G = ∇S, their gradients ∂cᵢ/∂qᵢ."""
        if self.kind == "delta":
            c = self.scale * self.wa / S
            return c, None if G is None else (-c / S)[:, None] * G
        c = -self.scale * self.wa * S
        return c, None if G is None else (-self.scale * self.wa)[:, None] * G

    def _points(self, p):
        R, t = self.pose(p)
        D = self.A - t
        return R, t, D, D @ R  # rows of D @ R are Rᵀ(aᵢ − t)

    def value(self, p) -> float:
        self.count += 1
        _, _, _, Q = self._points(p)
        return float(self._terms(self.field._field(Q, False, self.near)[0])[0].sum())

    def per_fly(self, p):
        """(J, per-fly gradients (n, k)) at p."""
        self.count += 1
        R, t, D, Q = self._points(p)
        S, G = self.field._field(Q, True, self.near)
        c, Gq = self._terms(S, G)                       # cᵢ and ∂cᵢ/∂qᵢ
        dR, dt = _pose_jacobians(self.pose, p)
        # ∂qᵢ/∂p_k = dR_kᵀ(aᵢ − t) − Rᵀ dt_k ; as rows: dᵢ @ dR_k − dt_k @ R
        J = _kernels.param_gradients(D, dR, np.ascontiguousarray(dt @ R), np.ascontiguousarray(Gq))
        return float(c.sum()), J

    def translation_hessian(self, p, step, axes=(0, 1, 2)):
        """3×3 Hessian of J under a free translation u of all of f⁻¹(A) (central differences); only
        the rows (and, by symmetry, columns) of `axes` are computed, the others are left zero."""
        _, _, _, Q = self._points(p)
        H = np.zeros((3, 3))
        for i in axes:
            e = np.zeros(3)
            e[i] = step
            g = []
            for sgn in (1, -1):
                S, G = self.field._field(Q + sgn * e, True, self.near)
                g.append(self._terms(S, G)[1].sum(0))
            H[i] = (g[0] - g[1]) / (2 * step)
        for i in axes:
            H[:, i] = H[i]
        return H

    def value_and_grad(self, p):
        v, J = self.per_fly(p)
        return v, J.sum(0)


def _bfgs_box(fun, x0, lo, hi, maxiter, xtol=1e-5, ftol=1e-10, stop=None, H0=None, out=None, max_step=None):
    """Minimise fun (returns value, gradient) inside the box [lo, hi]: projected BFGS, Armijo backtracking.

    A few parameters only; written here because scipy's L-BFGS-B spends milliseconds per call in its
    Fortran/BLAS layer on this busy machine, more than our objective itself.  stop(x): optional test
    after each accepted step; True ends the search there (the registration's extra seeds stop once
    they reach a basin already polished).  H0: initial inverse-Hessian estimate (identity when None);
    out: a list whose last item is set to the final estimate.  max_step: cap on each component of a
    search direction (before the line search).
    """
    x = np.clip(np.asarray(x0, dtype=float), lo, hi)
    f, g = fun(x)
    Hinv = np.eye(len(x)) if H0 is None else H0.copy()
    if out is not None:
        out.append(Hinv)
    for _ in range(maxiter):
        d = -Hinv @ g
        if g @ d >= 0:
            Hinv = np.eye(len(x))
            d = -g
        alpha = 1.0
        if max_step is not None:
            big = np.max(np.abs(d) / max_step)
            if big > 1.0:
                d = d / big
        for _ in range(30):
            xn = np.clip(x + alpha * d, lo, hi)
            s = xn - x
            if not np.any(s):
                break
            fn, gn = fun(xn)
            if fn <= f + 1e-4 * (g @ s):
                break
            alpha *= 0.5
        else:
            return x, f
        if not np.any(s):
            return x, f
        y = gn - g
        sy = s @ y
        done = np.max(np.abs(s)) < xtol or abs(f - fn) <= ftol * max(abs(f), 1e-300)
        x, f, g = xn, fn, gn
        if done or (stop is not None and stop(x)):
            break
        if sy > 1e-300:
            rho = 1.0 / sy
            I = np.eye(len(x))
            Hinv = (I - rho * np.outer(s, y)) @ Hinv @ (I - rho * np.outer(y, s)) + rho * np.outer(s, s)
            if out is not None:
                out[-1] = Hinv
    return x, f


def _value_hessian(fun, p, fd):
    """Hessian of the scalar `fun` at p from second differences of its values, step fd[i] per parameter:
    H_ii from the axis stencils, H_ij by polarisation from the stencil along e_i + e_j
    (c(e_i + e_j) = H_ii + H_jj + 2 H_ij for the second differences c); 1 + k + k² evaluations.

    The registration's fallback when the Hessian from differences of the analytic gradient is not
    positive definite.  At small ε two populations seen on the same pixels give δ a cusp at the
    minimum, where the gradient jumps; the gradient differences across it measured a large secant
    curvature on each axis but cross terms that made the matrix indefinite, and 98 % of such
    registrations (bench/paper.py, equivalent populations, ε = 0.03 m), within a millimetre of the
    truth, were reported "not a minimum".  Second differences of values ask what the check means —
    is J larger all around p at the step's scale — and equal the gradient Hessian where J is smooth.
    Not used everywhere: they weight the curvature towards p itself (a triangle kernel over ±step,
    where gradient differences average it uniformly), so on a rough but flat valley — a plane
    sliding along itself — the micro-basin the optimiser stopped in looks stiffer than it is and the
    flat-minimum check would pass it.
    """
    k = len(p)
    E = np.diag(np.asarray(fd, dtype=float))
    f0 = fun(p)
    c = np.array([fun(p + E[i]) + fun(p - E[i]) - 2.0 * f0 for i in range(k)])
    H = np.diag(c / np.diag(E) ** 2)
    for i in range(k):
        for j in range(i + 1, k):
            d = E[i] + E[j]
            cij = fun(p + d) + fun(p - d) - 2.0 * f0
            H[i, j] = H[j, i] = (cij - c[i] - c[j]) / (2.0 * E[i, i] * E[j, j])
    return H


def _lattice(center, half, counts):
    axes = [np.linspace(c - h, c + h, n) if n > 1 else np.array([c]) for c, h, n in zip(center, half, counts)]
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([m.ravel() for m in mesh], 1), tuple(len(a) for a in axes)


_MIN_COUNT = 5   # 3 per axis put 2 of 3 candidates on the window's edge: more boundary rejections


def _lattice_counts(mode, A, wa, half, counts, step):
    """Lattice candidates per parameter: `counts`, fewer where the window is narrow for `step`.

    A pinned parameter (half-width 0) gets one candidate (more would only repeat it).  With a `step`
    (metres), a free one gets the fewest odd count, at least _MIN_COUNT and at most counts[i], whose
    spacing moves A's flies by at most `step`: translations by their spacing, rotations by spacing ×
    the flies' rms lever arm about the rotation axis.  The coarse objective is smooth over its
    cut-off, so candidates much closer than that only repeat each other's basin: on the localiser's
    0.25 m / 8° windows 7³ = 343 candidates 8 cm apart became 5³ = 125 (the lattice stage ≈15 → ≈5 ms;
    a floor of 3 per axis was faster still but rejected more registrations as boundary minima).
    """
    counts = np.array([int(c) if h > 0 else 1 for c, h in zip(counts, half)])
    if step is None:
        return tuple(counts)
    step = float(step)
    if not np.isfinite(step) or step <= 0:
        raise PopulationError(f"lattice_step must be a positive distance, got {step}")
    k = len(half)
    axis = {"optical": 1, "body": 2}.get(mode)
    if axis is None:
        lever = np.full(3, np.sqrt(np.average(np.sum(A * A, 1), weights=wa)))
    else:
        perp = np.delete(A, axis, 1)
        lever = np.full(1, np.sqrt(np.average(np.sum(perp * perp, 1), weights=wa)))
    n_rot = 1 if mode in PLANES else 3
    metres = np.concatenate([half[:k - n_rot], half[k - n_rot:] * lever])
    need = 2 * np.ceil(metres / step).astype(int) + 1
    return tuple(int(c) if c <= 1 else int(min(c, max(_MIN_COUNT, n))) for c, n in zip(counts, need))


def _poses_batch(mode: str, P: np.ndarray):
    """Rotations (m, 3, 3) and translations (m, 3) of every row of params P, vectorised (the lattice
    holds 343 planar or 3,375 6-DoF candidates; one Python pose call each cost milliseconds)."""
    m = len(P)
    Rs = np.zeros((m, 3, 3))
    ts = np.zeros((m, 3))
    if mode in PLANES:
        c, s = np.cos(P[:, 2]), np.sin(P[:, 2])
        if mode == "optical":      # rot_y, t = (x, 0, z)
            Rs[:, 0, 0], Rs[:, 0, 2], Rs[:, 1, 1], Rs[:, 2, 0], Rs[:, 2, 2] = c, s, 1.0, -s, c
            ts[:, 0], ts[:, 2] = P[:, 0], P[:, 1]
        else:                      # rot_z, t = (x, y, 0)
            Rs[:, 0, 0], Rs[:, 0, 1], Rs[:, 1, 0], Rs[:, 1, 1], Rs[:, 2, 2] = c, -s, s, c, 1.0
            ts[:, 0], ts[:, 1] = P[:, 0], P[:, 1]
        return Rs, ts
    w = P[:, 3:]
    th = np.linalg.norm(w, axis=1)
    k = w / np.where(th > 1e-12, th, 1.0)[:, None]
    small = th <= 1e-12                     # so3_exp: I + [w]ₓ for tiny angles, Rodrigues otherwise
    K = np.where(small[:, None, None], _skew_batch(w), _skew_batch(k))
    sin_t = np.where(small, 1.0, np.sin(th))[:, None, None]
    one_c = np.where(small, 0.0, 1.0 - np.cos(th))[:, None, None]
    Rs = np.eye(3) + sin_t * K + one_c * (K @ K)
    ts[:] = P[:, :3]
    return Rs, ts


def _skew_batch(w):
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 0] = -w[:, 2], w[:, 1], w[:, 2]
    K[:, 1, 2], K[:, 2, 0], K[:, 2, 1] = -w[:, 0], -w[:, 1], w[:, 0]
    return K


def _reach_bounds(A, Rs, ts):
    """Bounding box of f⁻¹(A) over every candidate (Rs (m, 3, 3), ts (m, 3)): where the field will be read."""
    c_lo, c_hi = A.min(0), A.max(0)
    corners = np.array([[x, y, z] for x in (c_lo[0], c_hi[0]) for y in (c_lo[1], c_hi[1])
                        for z in (c_lo[2], c_hi[2])])
    q = np.einsum("cj,mjl->mcl", corners, Rs) - np.einsum("mj,mjl->ml", ts, Rs)[:, None, :]
    return q.min((0, 1)), q.max((0, 1))


def _fail(mode, k, reason, T=None, params=None, delta=float("nan"), **kw):
    return RegistrationResult(T=np.eye(4) if T is None else T,
                              params=np.full(k, np.nan) if params is None else params,
                              covariance=np.full((k, k), np.nan), delta=delta, ok=False,
                              reason=reason, mode=mode, **kw)


def _register(mode, A, B, eps, prior, window, weights_a, weights_b, lattice_counts, max_points,
              coarse_points, min_flies, flat_ratio, ambiguity_ratio, field_options, seed,
              objective="delta", local_radius=0.5, lattice_step=None, curvature=True):
    t0 = time.perf_counter()
    pose = _POSES[mode]
    k = 3 if mode in PLANES else 6
    A = as_population(A, "A", allow_empty=True)
    B = as_population(B, "B", allow_empty=True)
    eps = check_eps(eps)
    wa = as_weights(weights_a, len(A), "weights_a")
    wb = as_weights(weights_b, len(B), "weights_b")
    if prior is None:
        prior = np.eye(4)
    prior = np.asarray(prior, dtype=float)
    if prior.shape != (4, 4) or not np.allclose(prior[:3, :3] @ prior[:3, :3].T, np.eye(3), atol=1e-6):
        raise PopulationError("prior must be a 4×4 rigid transform")
    center = _params_from_T(mode, prior)
    half = np.asarray(window, dtype=float).reshape(-1)
    if half.shape != (k,) or not np.all(np.isfinite(half)) or np.any(half < 0):
        raise PopulationError(f"window must be {k} non-negative half-widths, got {window}")

    # --- well-formed but unusable input: report, do not raise
    na, nb = int((wa > 0).sum()), int((wb > 0).sum())
    if min(na, nb) < min_flies:
        return _fail(mode, k, f"too few flies: A has {na}, B has {nb} (need at least {min_flies} each)")
    radius = float(np.sqrt(np.mean(np.sum((A - np.average(A, 0, wa)) ** 2, 1))))
    spread_b = float(np.sqrt(np.linalg.eigvalsh(np.cov(B[wb > 0].T)).max()))
    if spread_b < 4 * eps or radius < 4 * eps:
        return _fail(mode, k, f"degenerate populations: spread {min(spread_b, radius):.3g} m is "
                              f"not larger than eps={eps} m")

    keep_b = wb > 1e-3 * wb.max()          # flies that would add < 0.1 % each only cost time
    B, wb = B[keep_b], wb[keep_b]
    rng = np.random.default_rng(seed)
    live = np.flatnonzero(wa > 0)
    fine_idx = live if len(live) <= max_points else np.sort(rng.choice(live, max_points, replace=False))
    coarse_idx = fine_idx if len(fine_idx) <= coarse_points else np.sort(
        rng.choice(fine_idx, coarse_points, replace=False))

    # --- candidate lattice and the field that covers every place A can reach under it
    lattice_counts = _lattice_counts(mode, A[fine_idx], wa[fine_idx], half, lattice_counts, lattice_step)
    cand, lat_shape = _lattice(center, half, lattice_counts)
    Rs, ts = _poses_batch(mode, cand)
    lo, hi = _reach_bounds(A[fine_idx], Rs, ts)
    pad = 0.02 * float(np.max(hi - lo))
    Ac, wac = A[coarse_idx], wa[coarse_idx]
    marks = [("setup", time.perf_counter())]
    if objective == "delta":
        # The field is rebuilt for every registration, so its build counts: a 120,000-cell grid over
        # the whole search reach (≈10 ms) with near_cells=1 (r_c = 2 spacings would gather hundreds
        # of neighbours per fly; with the TSC deposit δ stays within ≈0.05–0.2 %).
        opts = dict(dict(near_cells=1.0, max_cells=120_000), **(field_options or {}))
        fld = PseudoDistanceField(B, eps, weights_b=wb, bounds=(lo - pad, hi + pad), **opts)
        fld_coarse, coarse_near = fld, False
    else:
        # local correlation: the coarse level is the same kernel with a 2× wider cut-off
        fld = LocalCorrelationField(B, eps, local_radius, weights_b=wb)
        fld_coarse, coarse_near = LocalCorrelationField(B, eps, 2 * local_radius, weights_b=wb), True
    marks.append(("field", time.perf_counter()))

    # --- 1. coarse lattice on the smoothed objective (far field only / wide local kernel)
    sums = fld_coarse.batch_sums(Ac, wac, Rs, ts, near=coarse_near)
    coarse = sums * (fld.weight_sum / wac.sum()) if objective == "delta" else -sums / wac.sum()
    evals = len(cand)
    grid_vals = coarse.reshape(lat_shape)
    is_min = grid_vals == scipy.ndimage.minimum_filter(grid_vals, size=3, mode="nearest")
    seeds = np.flatnonzero(is_min.ravel())
    seeds = seeds[np.argsort(coarse[seeds])][:3]
    contrast = float(np.median(coarse) - coarse[seeds[0]])

    scale = np.where(half > 0, half, 1.0)
    free = half > 0
    lo_b = np.where(free, -1.0, 0.0)
    hi_b = np.where(free, 1.0, 0.0)

    def on_edge(p):
        """Free parameters of p on the search window's edge."""
        return free & (np.abs(p - center) > 0.99 * half)

    def polish(obj, p_start, maxiter, xtol, stop=None, H0=None, out=None, max_step=None):
        x0 = np.clip((p_start - center) / scale, -1, 1)

        def fun(x):
            v, g = obj.value_and_grad(center + x * scale)
            return v, g * scale
        x, v = _bfgs_box(fun, x0, lo_b, hi_b, maxiter, xtol=xtol, stop=stop, H0=H0, out=out, max_step=max_step)
        return center + x * scale, v

    marks.append(("lattice", time.perf_counter()))
    # --- 2. polish the lattice minima on the smoothed δ
    smooth = _Objective(fld_coarse, Ac, wac, pose, near=coarse_near, kind=objective)
    # distinct minima only (closer than one lattice step in every scaled coordinate = same basin)
    step = np.where(np.asarray(lattice_counts) > 1, 2.0 / (np.maximum(lattice_counts, 2) - 1), 1.0)
    # Most extra seeds roll into the best seed's basin (on the localiser's replays ≈95 % of them):
    # stop one as soon as it comes within half a lattice step of a minimum already polished, where
    # the distinct-minima filter below would drop it anyway.
    polished = []
    hinvs = []
    for s in seeds:
        known = [(p - center) / scale for p, _ in polished]
        polished.append(polish(smooth, cand[s], 20, 1e-3, stop=(lambda x, known=known: any(
            np.all(np.abs(x - q) <= 0.5 * step) for q in known)) if known else None, out=hinvs if not known else None))
    polished.sort(key=lambda pv: pv[1])
    distinct = []
    for p, v in polished:
        if all(np.any(np.abs((p - q) / scale) > step) for q, _ in distinct):
            distinct.append((p, v))

    marks.append(("polish", time.perf_counter()))
    # --- 3. refine the best two on the full δ
    full = _Objective(fld, A[fine_idx], wa[fine_idx], pose, near=True, kind=objective)
    # the runner-up is worth refining only if, smoothed, it is already nearly as deep as the best
    rivals = [pv for pv in distinct[1:2] if pv[1] - distinct[0][1] < 3 * (1 - ambiguity_ratio) * contrast]
    def refine(p):
        # warm start from the polish's curvature estimate; if that walks onto the window's edge (the
        # smoother objective's curvature can send it along a flat valley), refine again from p
        # with the identity, as before the warm start
        if hinvs:
            q, v = polish(full, p, 60, 1e-3, H0=hinvs[0], max_step=0.5 * step)
            if not np.any(on_edge(q)):
                return q, v
        return polish(full, p, 60, 1e-3)
    refined = [refine(p) for p, _ in distinct[:1] + rivals]
    refined.sort(key=lambda pv: pv[1])
    p_best, d_best = refined[0]
    evals += smooth.count + full.count
    R, t = pose(p_best)
    T = make_transform(R, t)
    ambiguity = float("nan")
    if len(refined) > 1 and np.any(np.abs((refined[1][0] - p_best) / scale) > step):
        ambiguity = float(np.clip(1.0 - (refined[1][1] - d_best) / max(contrast, 1e-300), 0, 1))

    marks.append(("refine", time.perf_counter()))
    curv = None
    if curvature:
        curv = _curvature(mode, k, full, pose, p_best, fld.rc, radius)
        evals += curv.evaluations
        marks.append(("covariance", time.perf_counter()))
    # wall-clock milliseconds per stage: setup (validation, subsets, lattice poses), field (build),
    # lattice, polish, refine, covariance (Hessian and checks; absent without curvature), and the total
    timings = {f"{name}_ms": 1e3 * (t - t_prev) for (name, t), (_, t_prev) in zip(marks, [("", t0)] + marks)}
    timings["total_ms"] = 1e3 * (time.perf_counter() - t0)
    common = dict(T=T, params=p_best, delta=d_best, mode=mode, ambiguity=ambiguity, evaluations=evals,
                  timings=timings, hessian=None if curv is None else curv.H,
                  flatness=float("nan") if curv is None else curv.flatness)
    at_edge = on_edge(p_best)
    if np.any(at_edge):
        return _fail(reason=f"minimum on the search window boundary in parameter(s) "
                            f"{list(np.flatnonzero(at_edge))}: widen the window or improve the prior",
                     k=k, **common)
    if curv is not None and curv.eig[0] <= 0:
        return _fail(reason="not a minimum: the Hessian of δ is not positive definite (flat or saddle)",
                     k=k, **common)
    if curv is not None and curv.flatness < flat_ratio:
        v = np.linalg.eigh(curv.Hs)[1][:, 0]
        return _fail(reason=f"flat minimum: curvature along {np.round(v, 2).tolist()} is "
                            f"{curv.flatness:.2g} of the strongest (threshold {flat_ratio})", k=k, **common)
    if np.isfinite(ambiguity) and ambiguity > ambiguity_ratio:
        return _fail(reason=f"ambiguous: a second minimum at {np.round(refined[1][0], 3).tolist()} is "
                            f"nearly as deep ({ambiguity:.2f} of the best's depth)", k=k, **common)
    if curv is None:   # curvature=False: the caller has its own measurement model
        return RegistrationResult(covariance=np.full((k, k), np.nan), ok=True, reason="", **common)
    Hi = np.linalg.inv(curv.H)
    cov = 2.0 * Hi @ (curv.Jf.T @ curv.Jf) @ Hi       # ×2: B's flies are as noisy as A's (see module doc)
    cov = 0.5 * (cov + cov.T)
    return RegistrationResult(covariance=cov, ok=True, reason="", **common)


@dataclass
class _Curvature:
    H: np.ndarray          # Hessian of the objective in the pose params
    Hs: np.ndarray         # the same with rotations as metres of arc at the populations' radius
    eig: np.ndarray        # eigenvalues of Hs
    flatness: float        # eig_min / the stiffest curvature (see the module docstring)
    Jf: np.ndarray         # per-fly gradients, centred (for the sandwich covariance)
    evaluations: int


def _curvature(mode, k, full, pose, p_best, rc, radius) -> _Curvature:
    """The minimum's curvature: the Hessian (gradient differences, or values at a cusp), its scaled
    eigenvalues, the flatness against the stiffest curvature, and the per-fly gradients."""
    evals = 0
    L = max(radius, 1e-9)
    fd = np.array([min(0.25 * rc, 0.02) if (mode == "6dof" and i < 3) or (mode in PLANES and i < 2)
                   else min(0.25 * rc, 0.02) / L for i in range(k)])
    H = np.zeros((k, k))
    for i in range(k):
        e = np.zeros(k)
        e[i] = fd[i]
        gp = full.value_and_grad(p_best + e)[1]
        gm = full.value_and_grad(p_best - e)[1]
        H[i] = (gp - gm) / (2 * fd[i])
    H = 0.5 * (H + H.T)
    evals += 2 * k
    if np.linalg.eigvalsh(H)[0] <= 0:
        # Not positive definite from gradient differences: a saddle, or a cusp (see _value_hessian).
        # Ask the values whether J rises all around p; a true cusp minimum passes, a saddle does not.
        H = _value_hessian(full.value, p_best, fd)
        evals += k * k + 1
    _, Jf = full.per_fly(p_best)
    Jf = Jf - Jf.mean(0)
    evals += 1
    rot = np.array([i >= (2 if mode in PLANES else 3) for i in range(k)])
    units = np.where(rot, L, 1.0)               # rotations expressed as metres of arc at radius L
    Hs = H / np.outer(units, units)
    eig = np.linalg.eigvalsh(Hs)
    # Stiffness reference: the populations' own stiffest direction under a free 3-D translation (so a
    # planar search over a ground plane, flat in all three of its parameters, is still seen as flat).
    if mode in PLANES:
        # The in-plane block is the translation block of H seen through the rotation (a shift e of
        # f⁻¹(A) is the pose translation t − R e): only the out-of-plane row needs evaluations.
        normal = 2 if mode == "body" else 1
        inplane = [i for i in range(3) if i != normal]
        Rb = pose(p_best)[0]
        Htt = np.zeros((3, 3))
        Htt[np.ix_(inplane, inplane)] = H[:2, :2]
        H3 = full.translation_hessian(p_best, fd[0], axes=(normal,))
        H3[np.ix_(inplane, inplane)] = (Rb.T @ Htt @ Rb)[np.ix_(inplane, inplane)]
        evals += 2
    else:
        H3 = full.translation_hessian(p_best, fd[0])
        evals += 6
    stiff = max(eig[-1], float(np.linalg.eigvalsh(H3)[-1]))
    flatness = float(eig[0] / stiff) if stiff > 0 else float("nan")
    return _Curvature(H, Hs, eig, flatness, Jf, evals)


@dataclass
class StereoModel:
    """How the flies were measured, for registration on deep (outdoor) scenes: what the SLAM service
    should pass.  The defaults are the variant that won on the deep street scene.

    Measured by bench/registration_variants.py (street scene, 3,000 flies per view from two poses,
    independent populations, 0.5 m / 460 px rig, 0.4 px disparity noise, depths 2–40 m, 3 % outliers,
    8 random planar motions up to 1.2 m / 6°; translation error median / p90, rotation error median):

        variant                                t med    t p90   r med   reported failures
        delta (the paper, unweighted)          0.37 m   0.65 m  1.04°   0 of 8 (wrong but confident)
        delta, depth weights                   0.47     0.71    0.89°   7
        delta, co-visible (2 passes)           0.70     0.81    0.57°   2
        delta, footprint × depth weights       0.15     0.30    0.95°   0
        local                                  0.59     0.97    2.61°   8
        local, footprint                       0.48     0.84    0.52°   8
        local, footprint × depth               0.074    0.12    0.39°   2
        local, footprint × depth, co-visible   0.087    0.28    0.15°   2   (2 passes, 1.5× the time)
        the default: local, footprint × depth, 0.090    0.21    0.57°   2   (thin_b: 30 % less time)
          B thinned by Russian roulette

    Why: flies spread evenly over the image are 400× denser per m² at 2 m than at 40 m and that
    pattern moves with the camera, pulling both objectives towards zero motion (footprint weights
    undo it); far flies are smeared along their rays (depth weights); and the 1/(ε + d) tail of δ acts
    between the whole clouds (the local kernel does not).  Co-visibility masks, derived from the
    estimate, did not help here and cost a second pass: off by default, kept for experiments.

    calib: the rig (both populations were seen through it).  depth_range: the depths flies can have
    (metres), for co-visibility.  frame: the populations' frame for 6-DoF ("optical" or "body"; the
    planar modes use their plane's frame).  depth_weighting: 1/(1 + (σ_z/sigma_ref)²).
    footprint_weighting: (z/10 m)².  covisibility: keep only flies the other camera could see under
    the current estimate, re-derived for each of `passes` registrations.  objective: "local"
    (LocalCorrelationField with cut-off `local_radius`) or "delta" (the paper's δ, weighted).
    lattice_step: coarse-lattice spacing in metres of fly motion (see _lattice_counts; None: the full
    `lattice` counts).  0.5 m, half the coarse kernel's 2 × local_radius cut-off: on the localiser's
    replays the same estimates (within 0.1 mm on 98 % of the calls where both succeeded, the rest a
    different minimum), the lattice stage ≈15 → ≈5 ms.
    """
    calib: StereoCalibration
    depth_range: tuple = (0.0, np.inf)
    disparity_sigma: float = 0.4
    sigma_ref: float = 0.25
    depth_weighting: bool = True
    footprint_weighting: bool = True
    covisibility: bool = False
    margin: float = 0.03
    passes: int = 1
    frame: str = "optical"
    objective: str = "local"
    local_radius: float = 0.5
    thin_b: bool = True
    lattice_step: float | None = 0.5


def _register_stereo(mode, A, B, stereo: StereoModel, prior, window, weights_a, weights_b, args):
    """Registration with depth-uncertainty weights and co-visibility masks, iterated `passes` times."""
    frame = {"optical": "optical", "body": "body"}.get(mode, stereo.frame)
    A = as_population(A, "A", allow_empty=True)
    B = as_population(B, "B", allow_empty=True)
    wa = as_weights(weights_a, len(A), "weights_a").copy()
    wb = as_weights(weights_b, len(B), "weights_b").copy()
    if stereo.depth_weighting:
        wa *= depth_weights(A, stereo.calib, stereo.disparity_sigma, stereo.sigma_ref, frame)
        wb *= depth_weights(B, stereo.calib, stereo.disparity_sigma, stereo.sigma_ref, frame)
    if stereo.footprint_weighting:
        wa *= footprint_weights(A, stereo.calib, frame)
        wb *= footprint_weights(B, stereo.calib, frame)
    if stereo.thin_b and len(B):
        # Russian roulette on B: keep a fly with probability min(1, w / median w) and divide its
        # weight by that probability.  The field is unchanged in expectation, but the dense, light
        # near-camera flies (most of the neighbour work) are mostly gone.
        rng = np.random.default_rng(args["rest"][7])
        ref = float(np.median(wb[wb > 0])) if np.any(wb > 0) else 1.0
        p_keep = np.minimum(1.0, wb / ref)
        keep = rng.random(len(B)) < p_keep
        B, wb = B[keep], wb[keep] / p_keep[keep]
    T = np.eye(4) if prior is None else np.asarray(prior, dtype=float)
    res = None
    for _ in range(max(1, int(stereo.passes))):
        wa_p, wb_p = wa, wb
        if stereo.covisibility:
            ma, mb = covisible_masks(A, B, T, stereo.calib, stereo.depth_range, stereo.margin, frame)
            wa_p, wb_p = wa * ma, wb * mb
        rest = args["rest"][:-2] + (stereo.objective, stereo.local_radius)
        step = stereo.lattice_step if args["lattice_step"] is None else args["lattice_step"]
        res = _register(mode, A, B, args["eps"], T, window, wa_p, wb_p, *rest, lattice_step=step,
                        curvature=args.get("curvature", True))
        if not res.ok:
            return res
        T = res.T
    return res


def register_planar(A, B, plane: str = "optical", prior=None, window=(1.0, 1.0, np.deg2rad(10.0)),
                    weights_a=None, weights_b=None, eps: float = 0.1, lattice=(7, 7, 7),
                    max_points: int = 1000, coarse_points: int = 192, min_flies: int = 20,
                    flat_ratio: float = 0.02, ambiguity_ratio: float = 0.9, field_options=None,
                    seed: int = 0, stereo: StereoModel | None = None, objective: str = "delta",
                    local_radius: float = 0.5, lattice_step: float | None = None,
                    curvature: bool = True) -> RegistrationResult:
    """Planar f minimising δ(A, f(B)): params (x, z, θ) for ``plane="optical"``, (x, y, θ) for "body".

    prior: 4×4 initial guess of f (e.g. from odometry; identity when None), projected onto the plane.
    window: half-widths of the search box around the prior's params (metres, metres, radians); a zero
    half-width pins that parameter.  weights_a / weights_b: per-fly weights (δ_w).  max_points: flies
    of A used for the fine stages (random subset, fixed seed); coarse_points: flies used on the
    lattice.  field_options: passed to PseudoDistanceField.  stereo: a StereoModel to weight flies by
    depth uncertainty and restrict them to the co-visible part of the scene (what the SLAM service
    should use on real, deep scenes; without it this is the paper's δ).  curvature=False skips the
    Hessian, the flatness and not-a-minimum checks and the covariance (NaN): for callers with their own
    measurement model; the window-edge and ambiguity checks still apply.
    Returns a RegistrationResult; see the module docstring for the covariance and the failure rules.
    """
    if plane not in PLANES:
        raise PopulationError(f"plane must be one of {PLANES}, got {plane!r}")
    if objective not in OBJECTIVES:
        raise PopulationError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
    rest = (lattice, max_points, coarse_points, min_flies, flat_ratio, ambiguity_ratio, field_options, seed,
            objective, local_radius)
    if stereo is not None:
        return _register_stereo(plane, A, B, stereo, prior, window, weights_a, weights_b,
                                dict(eps=eps, rest=rest, lattice_step=lattice_step, curvature=curvature))
    return _register(plane, A, B, eps, prior, window, weights_a, weights_b, *rest, lattice_step=lattice_step,
                     curvature=curvature)


def register_6dof(A, B, prior=None, window=(1.0, 1.0, 1.0, 0.2, 0.2, 0.2), weights_a=None,
                  weights_b=None, eps: float = 0.1, lattice=(5, 5, 5, 3, 3, 3), max_points: int = 1000,
                  coarse_points: int = 128, min_flies: int = 20, flat_ratio: float = 0.02,
                  ambiguity_ratio: float = 0.9, field_options=None, seed: int = 0,
                  stereo: StereoModel | None = None, objective: str = "delta",
                  local_radius: float = 0.5, lattice_step: float | None = None) -> RegistrationResult:
    """Full rigid f minimising δ(A, f(B)): params (tx, ty, tz, ωx, ωy, ωz), ω a rotation vector.

    The window is around the prior's params (ω of the prior's rotation); otherwise as register_planar.
    """
    if objective not in OBJECTIVES:
        raise PopulationError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
    rest = (lattice, max_points, coarse_points, min_flies, flat_ratio, ambiguity_ratio, field_options, seed,
            objective, local_radius)
    if stereo is not None:
        return _register_stereo("6dof", A, B, stereo, prior, window, weights_a, weights_b,
                                dict(eps=eps, rest=rest, lattice_step=lattice_step))
    return _register("6dof", A, B, eps, prior, window, weights_a, weights_b, *rest, lattice_step=lattice_step)
