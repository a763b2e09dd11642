"""Which registration holds up on a deep outdoor scene?  The paper's δ against weighted variants.

Scene: common.registration.scenes.street_scene (facades 6–12 m to the sides, cars, poles, ground),
flies spread evenly over a 640×480 image of a 0.5 m-baseline rig, depths 2–40 m, disparity noise
`--disparity-sigma` px (depth error ∝ z² along the viewing ray), 3 % outliers.  Each trial draws a
random planar motion (|x| ≤ 0.5 m, z ∈ [0.3, 1.2] m forward, |θ| ≤ 6°) and two *independent*
populations, one per pose (not a replica), and registers with each variant from an identity prior.

Prints a table (median / 90th-percentile translation and rotation error, reported failures, time,
and the median NEES eᵀΣ⁻¹e of the successful runs — 3 would mean the covariance is honest, more
means it is over-confident) and, with
--json, one JSON object as the last line.  Progress goes to stderr.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from common.geometry import make_transform, rot_y
from common.registration import StereoModel, register_planar, scenes


def variants(rig, depth_range):
    """name -> kwargs for register_planar (δ = the paper's pseudo-distance, local = LocalCorrelation)."""
    def stereo(**kw):
        return StereoModel(calib=rig, depth_range=depth_range, **kw)
    only = dict(depth_weighting=False, footprint_weighting=False, covisibility=False, passes=1,
                thin_b=False)
    delta = dict(only, objective="delta")
    local = dict(only, objective="local")
    return {
        "delta (paper)": dict(),
        "delta depth": dict(stereo=stereo(**dict(delta, depth_weighting=True))),
        "delta covisible x2": dict(stereo=stereo(**dict(delta, covisibility=True, passes=2))),
        "delta footprint+depth": dict(stereo=stereo(**dict(delta, footprint_weighting=True,
                                                          depth_weighting=True))),
        "local": dict(objective="local"),
        "local footprint": dict(stereo=stereo(**dict(local, footprint_weighting=True))),
        "local depth": dict(stereo=stereo(**dict(local, depth_weighting=True))),
        "local footprint+depth": dict(stereo=stereo(**dict(local, footprint_weighting=True,
                                                          depth_weighting=True))),
        "local footprint+depth+covis x2": dict(stereo=stereo(**dict(local, footprint_weighting=True,
                                                                   depth_weighting=True,
                                                                   covisibility=True, passes=2))),
        "StereoModel() default (thinned B)": dict(stereo=stereo()),
    }


def run(trials: int, n: int, disparity_sigma: float, seed: int):
    rng = np.random.default_rng(seed)
    rig = scenes.deep_rig()
    depth_range = (2.0, 40.0)
    names = list(variants(rig, depth_range))
    errs = {k: [] for k in names}
    fails = {k: 0 for k in names}
    times = {k: [] for k in names}
    nees = {k: [] for k in names}
    for trial in range(trials):
        scene = scenes.street_scene(rng)
        truth = np.array([rng.uniform(-0.5, 0.5), rng.uniform(0.3, 1.2), np.deg2rad(rng.uniform(-6, 6))])
        T2 = make_transform(rot_y(truth[2]), [truth[0], 0, truth[1]])
        A, _, _ = scenes.observe(scene, np.eye(4), rig, n, rng, disparity_sigma=disparity_sigma)
        B, _, _ = scenes.observe(scene, T2, rig, n, rng, disparity_sigma=disparity_sigma)
        for name, kw in variants(rig, depth_range).items():
            t0 = time.perf_counter()
            res = register_planar(A, B, **kw)
            times[name].append(time.perf_counter() - t0)
            p = res.params
            if not np.all(np.isfinite(p)):
                fails[name] += 1
                errs[name].append((np.inf, np.inf))
                continue
            if not res.ok:
                fails[name] += 1
            else:
                e = p - truth
                nees[name].append(float(e @ np.linalg.solve(res.covariance, e)))
            errs[name].append((float(np.hypot(p[0] - truth[0], p[1] - truth[1])),
                               float(np.rad2deg(abs(p[2] - truth[2])))))
        print(f"trial {trial + 1}/{trials} done", file=sys.stderr)
    table = {}
    for name in names:
        e = np.array(errs[name])
        table[name] = dict(
            trans_err_median_m=float(np.median(e[:, 0])), trans_err_p90_m=float(np.percentile(e[:, 0], 90)),
            rot_err_median_deg=float(np.median(e[:, 1])), rot_err_p90_deg=float(np.percentile(e[:, 1], 90)),
            reported_failures=int(fails[name]), time_median_ms=float(1e3 * np.median(times[name])),
            nees_median=float(np.median(nees[name])) if nees[name] else float("nan"))
    return table


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=8)
    ap.add_argument("--flies", type=int, default=3000)
    ap.add_argument("--disparity-sigma", type=float, default=0.4)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    table = run(args.trials, args.flies, args.disparity_sigma, args.seed)
    print(f"deep street scene, {args.flies} flies/view, {args.trials} trials, "
          f"disparity noise {args.disparity_sigma} px, depths 2–40 m")
    print(f"{'variant':34s} {'t med m':>8s} {'t p90 m':>8s} {'r med °':>8s} {'r p90 °':>8s} {'fails':>6s} {'ms':>7s} {'NEES':>8s}")
    for name, r in table.items():
        print(f"{name:34s} {r['trans_err_median_m']:8.3f} {r['trans_err_p90_m']:8.3f} "
              f"{r['rot_err_median_deg']:8.2f} {r['rot_err_p90_deg']:8.2f} {r['reported_failures']:6d} "
              f"{r['time_median_ms']:7.0f} {r['nees_median']:8.3g}")
    if args.json:
        print(json.dumps(dict(trials=args.trials, flies=args.flies, disparity_sigma=args.disparity_sigma,
                              variants=table)))


if __name__ == "__main__":
    main()
