"""The paper's viewpoint experiment (Louchet et al., figures 11–13) on consecutive real KITTI stereo pairs.

bench/paper.py runs it on the simulated trolley; this is the same measurement on real images, with
KITTI's ground truth as the true motion. For each frame k of ``--pairs``, ``--populations`` populations
are evolved (common.fly.FlyEvolver, one seed each, ``--generations`` generations, the lockstep's
evolver settings) on frame k and as many on frame k+1; every (seed i at k, seed j at k+1) pair is
registered, f(B) ≈ A, and compared with T_cam_k_cam_k+1 from poses/NN.txt as (x, z, θ) in the left
optical frame (x right, z forward, θ about y), as the paper reports it.

Registrations (identity prior, as in the paper; a window wide enough for a car's 1 m per frame):
- ``localiser``: what common/slam/localiser.py does with its default LocaliserConfig: its fly selection
  (select_flies: depth, height band, fittest fraction, base_link), register_planar(plane="body") with
  its ε, fitness weights and StereoModel; converted to the optical frame for the comparison;
- ``stereo_all``: every fly of both populations, register_planar(plane="optical") with the localiser's
  ε and a StereoModel over the evolver's depth range (what the registration can do when the selection
  does not throw the scene away);
- ``paper_delta``: every fly, the paper's plain δ (ε = 0.1 m, no StereoModel).

Every finite estimate counts, reported failures included (as in bench/paper.py). σ and bias are
pooled over all pairs of frames: σ is the spread of the estimates about their own pair's
mean (the population-to-population noise the paper's figures show), bias the mean error against the
truth. Writes bench/out/paper_real/fig11_13_viewpoint_<k>_<k+1>.png (bench/paper.py's
scatter panels) per pair of frames. Prints a table beside the paper's σ (19 mm, 21 mm, 0.85°); with --json the last stdout line is
one JSON object (per variant ``sigma_*``, ``bias_*``, ``rms_*``, failures, ``flat`` (minima reported
flat), ``nees`` / ``nees_ok`` (mean eᵀΣ⁻¹e against the truth under the covariance each registration
reports, 3 degrees of freedom; see bench/paper.py's ``consistency``), ``nees_about_pair_mean`` (the
same about each frame pair's mean estimate: the seed-to-seed noise alone); ``paper_sigma``; ``load_avg``).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from common.fly import EvolverConfig, FlyEvolver  # noqa: E402
from common.geometry import invert, planar_pose  # noqa: E402
from common.importers import DatasetLayoutError  # noqa: E402
from common.importers.kitti import load_kitti  # noqa: E402
from common.registration import PopulationError, StereoModel, register_planar  # noqa: E402
from common.slam import FlyLocaliser  # noqa: E402
from paper import AXES, DOF, PAPER, consistency, figure_scatter, optical_params  # noqa: E402

PAPER_EPS = 0.1
OPTICAL_WINDOW = (0.5, 1.5, np.deg2rad(12.0))    # x right, z forward, θ
BODY_WINDOW = (1.5, 0.5, np.deg2rad(12.0))       # x forward, y left, yaw
SCALE = np.array([1e3, 1e3, np.rad2deg(1.0)])    # (m, m, rad) → (mm, mm, °)
OUT = ROOT / "bench" / "out" / "paper_real"


def evolve(calib, left, right, seed: int, flies: int, generations: int, depth_max: float):
    ev = FlyEvolver(calib, EvolverConfig(population=flies, depth_max=depth_max), seed=seed)
    ev.set_images(left, right)
    ev.step(generations)
    return np.array(ev.positions, np.float64), np.array(ev.fitness, np.float64)


class Registrations:
    """The three ways of registering population B (frame k+1) onto A (frame k); each returns (params, ok,
    covariance of the params, flat): the curvature stage runs (curvature=True) so every estimate comes
    with the covariance it reports, in the optical (x, z, θ) the error is measured in."""

    def __init__(self, calib, depth_max: float):
        self.loc = FlyLocaliser(calib.T_base_camera, calibration=calib)
        self.C = np.asarray(calib.T_base_camera, np.float64)
        self.eps = self.loc.config.eps
        self.stereo_all = StereoModel(calib, depth_range=(0.3, depth_max))

    def localiser(self, A, fa, B, fb, seed):
        a, wa = self.loc.select_flies(A, fa)
        b, _ = self.loc.select_flies(B, fb)
        try:
            r = register_planar(a, b, plane="body", window=BODY_WINDOW, eps=self.eps, weights_a=wa / wa.max(),
                                stereo=self.loc.stereo, seed=seed)
        except (PopulationError, ValueError):   # too few flies survive the selection
            return np.full(3, np.nan), False, np.full((3, 3), np.nan), False
        J = self._body_to_optical_jacobian(r.params)
        return (optical_params(invert(self.C) @ r.T @ self.C), bool(r.ok), J @ r.covariance @ J.T,
                r.reason.startswith("flat"))

    def _body_to_optical_jacobian(self, p, step=1e-6):
        """d optical (x, z, θ) / d body (x, y, yaw) of the same camera motion, by central differences."""
        if not np.all(np.isfinite(p)):
            return np.full((3, 3), np.nan)
        f = lambda q: optical_params(invert(self.C) @ planar_pose(*q) @ self.C)  # noqa: E731
        return np.column_stack([(f(p + e) - f(p - e)) / (2 * step) for e in np.eye(3) * step])

    def stereo(self, A, fa, B, fb, seed):
        ok_a, ok_b = np.isfinite(fa), np.isfinite(fb)
        r = register_planar(A[ok_a], B[ok_b], plane="optical", window=OPTICAL_WINDOW, eps=self.eps,
                            weights_a=np.clip(fa[ok_a], 0, None) / np.nanmax(fa), stereo=self.stereo_all,
                            seed=seed)
        return np.asarray(r.params, float), bool(r.ok), r.covariance, r.reason.startswith("flat")

    def paper(self, A, fa, B, fb, seed):
        r = register_planar(A[np.isfinite(fa)], B[np.isfinite(fb)], plane="optical", window=OPTICAL_WINDOW,
                            eps=PAPER_EPS, seed=seed)
        return np.asarray(r.params, float), bool(r.ok), r.covariance, r.reason.startswith("flat")


def pooled(estimates: dict[int, np.ndarray], oks: dict[int, np.ndarray], truth: dict[int, np.ndarray]) -> dict:
    """σ about each frame pair's own mean (pooled), bias and RMS against the truth, in mm, mm, °."""
    errs, devs, fails, nonfinite = [], [], 0, 0
    for k, P in estimates.items():
        fin = np.all(np.isfinite(P), 1)
        nonfinite += int((~fin).sum())
        fails += int((~oks[k]).sum())
        if fin.sum() < 2:
            continue
        e = (P[fin] - truth[k]) * SCALE
        errs.append(e)
        devs.append((e - e.mean(0)) * np.sqrt(len(e) / (len(e) - 1)))   # unbiased per-pair variance
    out = dict(registrations=int(sum(len(P) for P in estimates.values())), failures=fails, nonfinite=nonfinite)
    E = np.concatenate(errs) if errs else np.full((0, 3), np.nan)
    D = np.concatenate(devs) if devs else np.full((0, 3), np.nan)
    for i, ax in enumerate(AXES):
        out[f"sigma_{ax}"] = float(np.sqrt(np.mean(D[:, i] ** 2))) if len(D) else float("nan")
        out[f"bias_{ax}"] = float(np.mean(E[:, i])) if len(E) else float("nan")
        out[f"rms_{ax}"] = float(np.sqrt(np.mean(E[:, i] ** 2))) if len(E) else float("nan")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--clip", default="kitti-00-frames-0-99")
    ap.add_argument("--pairs", default="10,30,50,70", help="frames k registered against k+1 (comma-separated)")
    ap.add_argument("--populations", type=int, default=6, help="populations (seeds) per frame")
    ap.add_argument("--generations", type=int, default=300)
    ap.add_argument("--flies", type=int, default=5000)
    ap.add_argument("--depth-max", type=float, default=30.0, help="the evolver's depth bound (as in lockstep)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    try:
        frames = [int(k) for k in args.pairs.split(",")]
        ds = load_kitti(args.data / args.clip / "sequences" / "00")
    except ValueError as e:   # DatasetLayoutError is a ValueError
        print(f"bench/paper_real.py: {e if isinstance(e, DatasetLayoutError) else f'--pairs {args.pairs!r}: {e}'}",
              file=sys.stderr)
        return 2
    if len(ds.truth_poses) == 0 or any(not 0 <= k < len(ds.stamps_ns) - 1 for k in frames):
        print(f"bench/paper_real.py: need ground truth and frames k, k+1 within {len(ds.stamps_ns)} frames",
              file=sys.stderr)
        return 2
    calib = ds.calibration
    C = np.asarray(calib.T_base_camera, np.float64)
    regs = Registrations(calib, args.depth_max)
    variants = {"localiser": regs.localiser, "stereo_all": regs.stereo, "paper_delta": regs.paper}
    est = {v: {} for v in variants}
    oks = {v: {} for v in variants}
    covs = {v: {} for v in variants}
    flats = {v: {} for v in variants}
    truth, seconds = {}, {v: 0.0 for v in variants}
    t_start = time.perf_counter()
    for k in frames:
        # truth poses are base_link in map; the camera motion k → k+1 in optical frames
        truth[k] = optical_params(invert(C) @ invert(ds.truth_poses[k]) @ ds.truth_poses[k + 1] @ C)
        t = time.perf_counter()
        pops = [[evolve(calib, *ds.load_pair(f), seed=1000 * f + s, flies=args.flies, generations=args.generations,
                        depth_max=args.depth_max) for s in range(args.populations)] for f in (k, k + 1)]
        print(f"frame {k}/{k + 1}: {2 * args.populations} populations in {time.perf_counter() - t:.1f} s; "
              f"truth x {truth[k][0] * 1e3:.0f} mm, z {truth[k][1] * 1e3:.0f} mm, "
              f"θ {np.rad2deg(truth[k][2]):.2f}°", file=sys.stderr, flush=True)
        for name, register in variants.items():
            t = time.perf_counter()
            res = [register(*pops[0][i], *pops[1][j], seed=i * args.populations + j)
                   for i in range(args.populations) for j in range(args.populations)]
            seconds[name] += time.perf_counter() - t
            est[name][k] = np.array([r[0] for r in res])
            oks[name][k] = np.array([r[1] for r in res])
            covs[name][k] = np.array([r[2] for r in res])
            flats[name][k] = np.array([r[3] for r in res])
        OUT.mkdir(parents=True, exist_ok=True)
        figure_scatter(str(OUT / f"fig11_13_viewpoint_{k}_{k + 1}.png"),
                       [(name, est[name][k], oks[name][k]) for name in ("stereo_all", "paper_delta", "localiser")],
                       truth[k], f"frames {k} -> {k + 1}: {args.populations ** 2} registrations", half=500.0)
    load = os.getloadavg()
    out = {"clip": args.clip, "frame_pairs": [[k, k + 1] for k in frames], "populations_per_frame": args.populations,
           "generations": args.generations, "flies": args.flies,
           "true_motion": {str(k): dict(zip(AXES, (truth[k] * SCALE).round(2).tolist())) for k in frames},
           "paper_sigma": dict(zip(AXES, PAPER["viewpoint"]))}
    print(f"viewpoint experiment on {args.clip}, frames {', '.join(f'{k}->{k + 1}' for k in frames)}: "
          f"{args.populations}x{args.populations} registrations per pair, {args.generations} generations, "
          f"{args.flies} flies")
    print(f"{'variant':12s} {'σx mm':>7s} {'σz mm':>7s} {'σθ °':>6s} {'bias x':>7s} {'bias z':>7s} {'bias θ':>7s} "
          f"{'failed':>7s} {'flat':>7s} {'NEES':>6s} {'NEES ok':>7s} {'spread':>7s} {'ms/reg':>7s}")
    for name in variants:
        s = pooled(est[name], oks[name], truth)
        s["ms_per_registration"] = 1e3 * seconds[name] / max(s["registrations"], 1)
        err = np.concatenate([est[name][k] - truth[k] for k in frames])
        s.update(consistency(err, np.concatenate([covs[name][k] for k in frames]),
                             np.concatenate([oks[name][k] for k in frames])))
        s["flat"] = int(sum(flats[name][k].sum() for k in frames))
        # the same covariances against the spread about each frame pair's own mean: the population-to-
        # population noise they model, without the pair's bias that every seed shares
        spread = np.concatenate([(est[name][k] - np.nanmean(est[name][k], 0))
                                 * np.sqrt(len(est[name][k]) / max(len(est[name][k]) - 1, 1)) for k in frames])
        s["nees_about_pair_mean"] = consistency(spread, np.concatenate([covs[name][k] for k in frames]),
                                                np.concatenate([oks[name][k] for k in frames]))["nees"]
        out[name] = {key: (round(v, 3) if isinstance(v, float) else v) for key, v in s.items()}
        print(f"{name:12s} {s['sigma_x_mm']:7.1f} {s['sigma_z_mm']:7.1f} {s['sigma_theta_deg']:6.2f} "
              f"{s['bias_x_mm']:7.1f} {s['bias_z_mm']:7.1f} {s['bias_theta_deg']:7.2f} "
              f"{s['failures']:3d}/{s['registrations']:<3d} {s['flat']:3d}/{s['registrations']:<3d} "
              f"{s['nees']:6.2f} {s['nees_ok']:7.2f} {s['nees_about_pair_mean']:7.2f} {s['ms_per_registration']:7.0f}")
    print(f"NEES: mean eᵀΣ⁻¹e, e = estimate − truth (x, z, θ), Σ the covariance the registration reports, over "
          f"every estimate with one (flat minima included; 'NEES ok': ok=True only; 'spread': e about each frame "
          f"pair's mean, the pair's bias shared by every seed removed); {DOF} degrees of freedom")
    p = PAPER["viewpoint"]
    print(f"{'paper':12s} {p[0]:7.1f} {p[1]:7.1f} {p[2]:6.2f}   (σ only; the paper reports no bias)")
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; {time.perf_counter() - t_start:.0f} s")
    out["load_avg"] = [round(x, 2) for x in load]
    out["seconds"] = round(time.perf_counter() - t_start, 1)
    if args.json:
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
