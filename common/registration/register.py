"""Register two fly populations: the rigid displacement f minimising δ(A, f(B)).

    res = register_planar(A, B, prior=T_odom, window=(0.25, 0.25, np.deg2rad(8)), stereo=StereoModel(rig))
    if res.ok: T_cam1_cam2, cov = res.T, res.covariance

f maps points of B's frame into A's frame (A seen from camera pose 1, B from pose 2: f = T_cam1_cam2).
``res.params`` are (x, z, θ) for ``plane="optical"`` (θ about y), (x, y, θ) for ``plane="body"`` (θ about
z) and (tx, ty, tz, ωx, ωy, ωz) for :func:`register_6dof`.  B's field is built once per call; the
search is a coarse lattice on a smoothed objective, a polish of its distinct minima and a refine of
the best two on the full objective (see docs/design/registration.md for the design).

Invariants: the result stays inside prior ± window; ``res.covariance`` is the clustered sandwich
estimate in params² (curvature.py), also on a flat minimum (ok False, large along the flat direction),
NaN with ``curvature=False`` or on any other failure; a minimum is flat when one σ along some direction
reaches past the window (``res.flatness`` < ``flat_ratio`` = 1); well-formed but unusable input — too
few flies, a minimum on the window's edge, not a minimum, a flat or ambiguous minimum — gives
``res.ok`` False with ``res.reason`` and never raises; malformed input (wrong shapes, NaN, a non-rigid
prior) raises PopulationError.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field as dc_field

import numpy as np
import scipy.ndimage

from ..geometry import make_transform
from .bfgs import _bfgs_box
from .curvature import _curvature
from .field import PseudoDistanceField
from .lattice import _lattice, _lattice_counts, _poses_batch, _reach_bounds
from .local import LocalCorrelationField
from .objective import _POSES, PLANES, _Objective, _params_from_T
from .pseudo_distance import PopulationError, as_population, as_weights, check_eps
from .stereo_model import StereoModel, _register_stereo

__all__ = ["RegistrationResult", "StereoModel", "register_6dof", "register_planar", "PLANES", "OBJECTIVES"]

OBJECTIVES = ("delta", "local")


@dataclass
class RegistrationResult:
    """Outcome of a registration.  ``T`` is f (4×4) with f(B) ≈ A; ``timings``: wall ms per stage."""
    T: np.ndarray
    params: np.ndarray
    covariance: np.ndarray
    delta: float
    ok: bool
    reason: str = ""
    mode: str = ""
    hessian: np.ndarray | None = None
    flatness: float = float("nan")     # 1/σ along the worst direction, window units (< 1: flat)
    ambiguity: float = float("nan")    # depth of the 2nd minimum relative to the best's (1 = as deep)
    evaluations: int = 0
    timings: dict = dc_field(default_factory=dict)

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of the params (sqrt of the covariance diagonal)."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0, None))


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
        # the whole search reach with near_cells=1 (r_c = 2 spacings would gather hundreds of
        # neighbours per fly; with the TSC deposit δ stays within ≈0.05–0.2 % of exact).
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
    # Most extra seeds roll into the best seed's basin: stop one as soon as it comes within half a
    # lattice step of a minimum already polished, where the distinct-minima filter below would drop it.
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
        # with the identity
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
        curv = _curvature(mode, k, full, pose, p_best, fld.rc, radius, half)
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
        # Still a minimum: its covariance is kept (large along the flat direction) for callers that fuse
        # what the registration does pin down.
        v = np.linalg.eigh(curv.covariance / np.outer(scale, scale))[1][:, -1]
        return RegistrationResult(
            covariance=curv.covariance, ok=False, **common,
            reason=f"flat minimum: σ along {np.round(v, 2).tolist()} (window units) is "
                   f"{1 / curv.flatness:.2g}× the window's half-width (threshold flatness {flat_ratio})")
    if np.isfinite(ambiguity) and ambiguity > ambiguity_ratio:
        return _fail(reason=f"ambiguous: a second minimum at {np.round(refined[1][0], 3).tolist()} is "
                            f"nearly as deep ({ambiguity:.2f} of the best's depth)", k=k, **common)
    if curv is None:   # curvature=False: the caller has its own measurement model
        return RegistrationResult(covariance=np.full((k, k), np.nan), ok=True, reason="", **common)
    return RegistrationResult(covariance=curv.covariance, ok=True, reason="", **common)


def register_planar(A, B, plane: str = "optical", prior=None, window=(1.0, 1.0, np.deg2rad(10.0)),
                    weights_a=None, weights_b=None, eps: float = 0.1, lattice=(7, 7, 7),
                    max_points: int = 1000, coarse_points: int = 192, min_flies: int = 20,
                    flat_ratio: float = 1.0, ambiguity_ratio: float = 0.9, field_options=None,
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
    Returns a RegistrationResult; the covariance and failure rules: module docstring, docs/design/registration.md.
    """
    if plane not in PLANES:
        raise PopulationError(f"plane must be one of {PLANES}, got {plane!r}")
    if objective not in OBJECTIVES:
        raise PopulationError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
    rest = (lattice, max_points, coarse_points, min_flies, flat_ratio, ambiguity_ratio, field_options, seed,
            objective, local_radius)
    if stereo is not None:
        return _register_stereo(plane, A, B, stereo, prior, window, weights_a, weights_b,
                                dict(eps=eps, rest=rest, lattice_step=lattice_step, curvature=curvature), _register)
    return _register(plane, A, B, eps, prior, window, weights_a, weights_b, *rest, lattice_step=lattice_step,
                     curvature=curvature)


def register_6dof(A, B, prior=None, window=(1.0, 1.0, 1.0, 0.2, 0.2, 0.2), weights_a=None,
                  weights_b=None, eps: float = 0.1, lattice=(5, 5, 5, 3, 3, 3), max_points: int = 1000,
                  coarse_points: int = 128, min_flies: int = 20, flat_ratio: float = 1.0,
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
                                dict(eps=eps, rest=rest, lattice_step=lattice_step), _register)
    return _register("6dof", A, B, eps, prior, window, weights_a, weights_b, *rest, lattice_step=lattice_step)
