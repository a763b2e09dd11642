"""Speed and accuracy of the pseudo-distance and of registration, for 5,000 and 20,000 flies.

Populations: the deep street scene of common.registration.scenes (0.5 m-baseline rig, depths 2–40 m,
0.4 px disparity noise, 3 % outliers), A seen from the origin and B from a pose moved by
(x, z, θ) = (0.3 m, 0.8 m, 4°) — two independent populations, as in real use.

Figures (milliseconds are medians of repeated runs, numba compile time excluded by a warm-up):
  exact_delta_ms          pseudo_distance_exact: float64 numpy, chunked (the reference)
  exact_numba_delta_ms    the same sum with the parallel numba kernel (field_exact)
  field_build_ms          PseudoDistanceField(B, eps, bounds=A's box) build with the default options
                          (TSC deposit, FFT far field, near-field cell list) — NOT included in:
  fast_delta_ms           field.delta(A): δ evaluated at A's 5,000 (20,000) points on that PREBUILT
                          field, i.e. one far-field interpolation + one near sum per point of A;
                          fast_rel_error = |fast − exact| / exact, fast_grid_shape the grid;
                          fast_grad_rel_error the median over A of |∇S_fast − ∇S_exact| / |∇S_exact|
  fast_before_*           the same with a cloud-in-cell deposit and near_cells=2 (the comparison),
                          timed interleaved with fast_delta_ms on the same run
  fast_lean_*             the same with the registration's field options (max_cells=120,000,
                          near_cells=1): cheaper build
  register_3dof_ms        register_planar(A, B) with the paper's δ (field build included; every call
                          builds its own field over the search reach)
  register_3dof_stereo_ms register_planar(..., stereo=StereoModel(rig)): the deep-scene variant the
                          SLAM localiser uses (local objective, no FFT grid)
  register_6dof_ms        register_6dof(A, B) with the paper's δ
  *_stages_ms             median wall time per stage of that registration (res.timings): setup,
                          field (build), lattice, polish, refine, covariance
  *_err_m / *_err_deg     translation / rotation error of those registrations against the truth
  *_cpu_ms                process CPU time (all threads) of the same calls: on the shared machine the
                          wall clock also counts time spent waiting for a core

The last stdout line with --json is one JSON object; "scaling" holds the same keys for 20,000 flies.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from common.geometry import make_transform, rot_y
from common.registration import (PseudoDistanceField, StereoModel, field_exact, pseudo_distance_exact,
                                 register_6dof, register_planar, scenes)

TRUTH = (0.3, 0.8, np.deg2rad(4.0))

# PseudoDistanceField options per figure prefix: "" the defaults (TSC deposit, r_c = h); "before_" the
# cloud-in-cell comparison (CIC deposit, r_c = 2h, x-y columns of 2 r_c); "lean_" the options the
# registration uses (coarser grid, cheaper build).
FIELD_OPTIONS = {"": {},
                 "before_": dict(deposit="cic", near_cells=2.0, cells_per_radius=0.5),
                 "lean_": dict(max_cells=120_000, near_cells=1.0)}


CPU = {}


STAGES = {}


def timed(fn, repeat, key=None):
    """(last result, median wall ms); also records the median process CPU ms in CPU[key] and, for
    registrations, the median of each stage's wall ms in STAGES[key]."""
    out = None
    ts, cs, stages = [], [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        ts.append(time.perf_counter() - t0)
        cs.append(time.process_time() - c0)
        stages.append(getattr(out, "timings", {}))
    if key:
        CPU[key] = 1e3 * float(np.median(cs))
        STAGES[key] = {k.removesuffix("_ms"): float(np.median([st.get(k, np.nan) for st in stages]))
                       for k in stages[-1] if k != "total_ms"}
    return out, 1e3 * float(np.median(ts))


def populations(n, seed=3):
    rng = np.random.default_rng(seed)
    rig = scenes.deep_rig()
    scene = scenes.street_scene(rng)
    T2 = make_transform(rot_y(TRUTH[2]), [TRUTH[0], 0, TRUTH[1]])
    A, _, _ = scenes.observe(scene, np.eye(4), rig, n, rng)
    B, _, _ = scenes.observe(scene, T2, rig, n, rng)
    return rig, A, B


def errors(res, truth):
    p = res.params
    if res.mode == "6dof":
        return float(np.linalg.norm(p[:3] - [truth[0], 0, truth[1]])), float(np.rad2deg(np.linalg.norm(
            p[3:] - [0, truth[2], 0])))
    return float(np.hypot(p[0] - truth[0], p[1] - truth[1])), float(np.rad2deg(abs(p[2] - truth[2])))


def measure(n, eps, repeat):
    print(f"[{n} flies] building populations", file=sys.stderr)
    rig, A, B = populations(n)
    out = {"flies": n, "eps": eps,
           "fast_delta_times": "field.delta(A) at A's points on a prebuilt field; the build is field_build_ms"}
    exact, out["exact_delta_ms"] = timed(lambda: pseudo_distance_exact(A, B, eps), 1 if n > 5000 else 2)
    field_exact(A[:10], B, eps)  # compile
    _, out["exact_numba_delta_ms"] = timed(lambda: field_exact(A, B, eps), 2)
    bounds = (A.min(0), A.max(0))
    _, G_exact = field_exact(A, B, eps, with_grad=True)
    fields = {}
    for key, opts in FIELD_OPTIONS.items():
        PseudoDistanceField(B[:100], eps, **opts).delta(A[:10])  # compile
        tag = "fast_" + key
        field, build_ms = timed(lambda: PseudoDistanceField(B, eps, bounds=bounds, **opts), 3, "b")
        fields[key] = field
        out[("field_build_ms" if not key else tag + "field_build_ms")] = build_ms
        out[("field_build_cpu_ms" if not key else tag + "field_build_cpu_ms")] = CPU["b"]
        fast = field.delta(A)
        out[tag + "rel_error"] = abs(fast - exact) / exact
        G = field.field(A, with_grad=True)[1]
        out[tag + "grad_rel_error"] = float(np.median(np.linalg.norm(G - G_exact, axis=1)
                                                      / np.linalg.norm(G_exact, axis=1)))
        out[tag + "grid_shape"] = list(field.shape)
        out[tag + "near_radius_m"] = field.rc
    # The configurations are timed in interleaved rounds, so that load from other processes on the
    # shared machine falls on all of them alike.
    walls = {key: [] for key in fields}
    cpus = {key: [] for key in fields}
    for _ in range(repeat):
        for key, field in fields.items():
            t0, c0 = time.perf_counter(), time.process_time()
            field.delta(A)
            walls[key].append(time.perf_counter() - t0)
            cpus[key].append(time.process_time() - c0)
    for key in fields:
        out["fast_" + key + "delta_ms"] = 1e3 * float(np.median(walls[key]))
        out["fast_" + key + "delta_cpu_ms"] = 1e3 * float(np.median(cpus[key]))
    print(f"[{n} flies] registering", file=sys.stderr)
    register_planar(A[:500], B[:500])  # compile
    register_planar(A[:500], B[:500], stereo=StereoModel(rig))
    register_6dof(A[:500], B[:500])
    res, out["register_3dof_ms"] = timed(lambda: register_planar(A, B, eps=eps), 3, "r")
    out["register_3dof_cpu_ms"] = CPU["r"]
    out["register_3dof_stages_ms"] = STAGES["r"]
    out["register_3dof_err_m"], out["register_3dof_err_deg"] = errors(res, TRUTH)
    out["register_3dof_ok"] = res.ok
    res, out["register_3dof_stereo_ms"] = timed(
        lambda: register_planar(A, B, eps=eps, stereo=StereoModel(rig)), 3, "r")
    out["register_3dof_stereo_cpu_ms"] = CPU["r"]
    out["register_3dof_stereo_stages_ms"] = STAGES["r"]
    out["register_3dof_stereo_err_m"], out["register_3dof_stereo_err_deg"] = errors(res, TRUTH)
    out["register_3dof_stereo_ok"] = res.ok
    res, out["register_6dof_ms"] = timed(lambda: register_6dof(A, B, eps=eps), 2, "r")
    out["register_6dof_cpu_ms"] = CPU["r"]
    out["register_6dof_stages_ms"] = STAGES["r"]
    out["register_6dof_err_m"], out["register_6dof_err_deg"] = errors(res, TRUTH)
    out["register_6dof_ok"] = res.ok
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--eps", type=float, default=0.1)
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    small = measure(5000, args.eps, args.repeat)
    large = measure(20000, args.eps, max(3, args.repeat // 4))
    for res in (small, large):
        print(f"--- {res['flies']} flies, eps = {res['eps']} m ({res['fast_delta_times']})")
        for k, v in res.items():
            if k in ("flies", "eps", "fast_delta_times"):
                continue
            if isinstance(v, dict):
                v = ", ".join(f"{a} {b:.3g}" for a, b in v.items())
            print(f"  {k:32s} {v:.4g}" if isinstance(v, float) else f"  {k:32s} {v}")
    if args.json:
        result = {k: v for k, v in small.items()}
        result["scaling"] = {"20000": large}
        print(json.dumps(result))


if __name__ == "__main__":
    main()
