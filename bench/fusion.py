"""Does the sonar term put more flies on real surfaces in a texture-poor corridor?

On the simulated ``corridor_poor_texture`` scenario (texture-poor painted walls), at ``--frames`` camera
frames spaced ``--every-s`` apart along the scripted drive, a fresh fly population (same seed in both
arms) evolves ``--generations`` generations on the rendered stereo pair, once with image fitness only
and once with the sonar term added (``--weight``), using the sonar sweep nearest before the frame.  The
scan is brought to the frame's time with the simulator's true motion between the two stamps (≤ 100 ms;
the pipeline uses fusion/odom for this).

Figures (pooled over frames):
  surface_fraction_with_sonar / _without_sonar   fraction of in-image flies whose depth Z is within
      ``--tolerance`` (5 cm) of the renderer's depth at the fly's left pixel
  wall_error_m_with_sonar / _without_sonar       median |Z_fly − Z_true| over flies whose pixel shows a
      wall (the true point at that pixel lies within 2 cm of a wall or box side, 5 cm–2 m up)
  *_in_beams                                     the same over flies inside a beam that had an echo
      (the only place the term can act), with the fraction of flies that are there
On the 20 m corridor run (``corridor`` scenario, its whole scripted drive, ``--drift-fps`` frames/s,
miscalibrated odometry as configured there), evolver and localiser run in lockstep (common.lockstep,
as ``flyslam eval`` does):
  drift_pct_odometry_only / drift_pct_fused      final position error in % of the path length, for wheel
      odometry alone and for odometry fused with the localiser; ate_m_* the ATE RMSE of both

Figures only, no pass/fail.  Progress goes to stderr; with --json the last stdout line is one JSON object.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from common.fly.config import EvolverConfig
from common.fly.evolver import FlyEvolver
from common.fusion.sonar_term import SonarTerm, SonarTermConfig, in_echo_beams
from common.geometry import invert
from common.messages import SonarScan, header
from common.sim import Simulator, load_scenario
from common.sim.scenario import scenario_path
from common.sim.sensors import SonarReading
from common.sim.simulator import CameraDue
from common.sim.world import point_segment_distance


def log(*a):
    print(*a, file=sys.stderr, flush=True)


def scan_msg(r: SonarReading) -> SonarScan:
    return SonarScan(transducer_poses=np.asarray(r.transducer_poses, float), ranges=np.asarray(r.ranges, np.float32),
                     beam_width_rad=float(r.beam_width), min_range_m=float(r.min_range), max_range_m=float(r.max_range),
                     header=header(0, r.stamp_ns, "base_link"))


def collect_frames(sim: Simulator, times_s: list[float]):
    """(images, latest SonarReading before the frame) at the first camera frame at or after each time."""
    out, sonar, wanted = [], None, list(times_s)
    while wanted and not sim.finished:
        for ev in sim.advance(0.05):
            if isinstance(ev, SonarReading):
                sonar = ev
            elif isinstance(ev, CameraDue) and wanted and ev.stamp_ns * 1e-9 >= wanted[0] and sonar is not None:
                out.append((sim.render(ev.stamp_ns), sonar, sim.truth_at(sonar.stamp_ns)))
                wanted.pop(0)
    return out


def fly_metrics(pos, images, calib, T_map_camera, wall_segments, beams, tol):
    """Per-fly booleans/errors against the renderer's depth (see the module docstring)."""
    u, _, v = calib.project(pos)
    ok = np.isfinite(u) & np.isfinite(v)
    ui = np.clip(np.round(np.nan_to_num(u)).astype(int), 0, calib.width - 1)
    vi = np.clip(np.round(np.nan_to_num(v)).astype(int), 0, calib.height - 1)
    ok &= (u >= 0) & (u <= calib.width - 1) & (v >= 0) & (v <= calib.height - 1)
    depth = images.depth[vi, ui].astype(np.float64)
    ok &= np.isfinite(depth)
    err = np.abs(pos[:, 2] - depth)
    true_pts = np.stack([(ui - calib.cx_left) * depth / calib.fx, (vi - calib.cy) * depth / calib.fy, depth], 1)
    true_map = np.nan_to_num(true_pts) @ T_map_camera[:3, :3].T + T_map_camera[:3, 3]
    wall = ok & (point_segment_distance(true_map[:, :2], wall_segments) < 0.02) & \
        (true_map[:, 2] > 0.05) & (true_map[:, 2] < 2.0)
    return ok, ok & (err < tol), wall, err, ok & beams


def run(args) -> dict:
    path = args.scenario if args.scenario.endswith(".toml") else scenario_path(args.scenario)
    scenario = load_scenario(path)
    sim = Simulator(scenario, seed=args.seed, width=args.width, height=args.height)
    calib = sim.calibration
    wall_segments = sim.world.obstacle_segments(0.05, 2.0)
    term_cfg = SonarTermConfig(height_m=scenario.sonar.height_m, reward_gain=args.reward_gain)
    times = [args.start_s + k * args.every_s for k in range(args.frames)]
    t0 = time.perf_counter()
    frames = collect_frames(sim, times)
    log(f"rendered {len(frames)} frames ({calib.width}×{calib.height}) in {time.perf_counter() - t0:.1f} s")
    cfg = EvolverConfig(population=args.population)
    pooled = {arm: {"ok": 0, "surface": 0, "wall_err": [], "beam": 0, "beam_surface": 0, "beam_err": []}
              for arm in ("with", "without")}
    timing = {"with": 0.0, "without": 0.0}
    for k, (images, sonar, T_map_base_scan) in enumerate(frames):
        T_map_camera = images.T_map_base @ calib.T_base_camera
        # Camera in the base_link of the scan's time: the frame's camera pose seen from the scan's base.
        T_scanbase_camera = invert(T_map_base_scan) @ T_map_camera
        scan = scan_msg(sonar)
        for arm in ("without", "with"):
            ev = FlyEvolver(calib, cfg, seed=args.seed + k)
            ev.set_images(images.left, images.right)
            if arm == "with":
                term = SonarTerm(term_cfg)
                term.update(scan, T_scanbase_camera)
                ev.add_fitness_term("sonar", term, args.weight)
            t = time.perf_counter()
            ev.step(args.generations)
            timing[arm] += time.perf_counter() - t
            pos = np.array(ev.positions, np.float64)
            beams = in_echo_beams(pos.astype(np.float32), T_scanbase_camera, scan, term_cfg)
            ok, surface, wall, err, in_beam = fly_metrics(pos, images, calib, T_map_camera, wall_segments, beams,
                                                          args.tolerance)
            p = pooled[arm]
            p["ok"] += int(ok.sum())
            p["surface"] += int(surface.sum())
            p["wall_err"].append(err[wall])
            p["beam"] += int(in_beam.sum())
            p["beam_surface"] += int((surface & in_beam).sum())
            p["beam_err"].append(err[wall & in_beam])
            log(f"frame {k} t={images.stamp_ns * 1e-9:.1f}s {arm:>7} sonar: surface {surface.sum() / max(ok.sum(), 1):.3f}"
                f"  wall median err {np.median(err[wall]) if wall.any() else float('nan'):.3f} m"
                f"  in beams {in_beam.sum()} flies ({np.isfinite(sonar.ranges).sum()} echoes)")

    def med(chunks):
        a = np.concatenate(chunks) if chunks else np.zeros(0)
        return float(np.median(a)) if len(a) else None

    result = {"scenario": scenario.name, "frames": len(frames), "population": args.population,
              "generations": args.generations, "weight": args.weight, "reward_gain": args.reward_gain, "tolerance_m": args.tolerance,
              "width": calib.width, "height": calib.height}
    for arm in ("with", "without"):
        p = pooled[arm]
        result[f"surface_fraction_{arm}_sonar"] = p["surface"] / max(p["ok"], 1)
        result[f"wall_error_m_{arm}_sonar"] = med(p["wall_err"])
        result[f"fraction_in_beams_{arm}_sonar"] = p["beam"] / max(p["ok"], 1)
        result[f"surface_fraction_in_beams_{arm}_sonar"] = p["beam_surface"] / max(p["beam"], 1)
        result[f"wall_error_m_in_beams_{arm}_sonar"] = med(p["beam_err"])
        result[f"evolve_s_per_generation_{arm}_sonar"] = timing[arm] / max(len(frames) * args.generations, 1)
    if not args.skip_drift:
        result.update(drift(args))
    return result


def drift(args) -> dict:
    """Odometry-only vs odometry + localiser on the 20 m corridor run (lockstep, deterministic)."""
    import numpy as np

    from common.lockstep import run_lockstep
    from common.recording import RecordingReader
    from common.sim.offline import cached_recording
    from common.trajectory_metrics import evaluate

    log(f"drift: rendering (or reusing) the corridor run at {args.drift_fps:g} frames/s ...")
    rec = cached_recording("corridor", seed=args.seed, fps=args.drift_fps, encoding="jpeg", quality=90)
    res = run_lockstep(RecordingReader(rec).messages(), generations_per_frame=30, seed=args.seed,
                       progress=lambda n, status: n % 25 == 0 and log(f"drift: frame {n}: {status[:50]}"))
    idx = [i for i, T in enumerate(res.odometry) if T is not None]
    stamps = np.array(res.stamps, np.int64)[idx]
    T0 = res.estimated[idx[0]] @ np.linalg.inv(res.odometry[idx[0]])
    odom = [T0 @ res.odometry[i] for i in idx]
    fused = [res.estimated[i] for i in idx]
    m_odo = evaluate(stamps, odom, res.truth_stamps, res.truth)
    m_fus = evaluate(stamps, fused, res.truth_stamps, res.truth)
    return {"drift_pct_odometry_only": round(m_odo.drift_pct, 3), "drift_pct_fused": round(m_fus.drift_pct, 3),
            "ate_m_odometry_only": round(m_odo.ate_rmse_m, 4), "ate_m_fused": round(m_fus.ate_rmse_m, 4),
            "drift_path_length_m": round(m_fus.path_length_m, 2), "drift_frames": res.frames,
            "drift_registered_fraction": round(res.registered_fraction, 3)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="corridor_poor_texture")
    p.add_argument("--frames", type=int, default=6)
    p.add_argument("--start-s", type=float, default=0.5)
    p.add_argument("--every-s", type=float, default=4.0)
    p.add_argument("--generations", type=int, default=60)
    p.add_argument("--population", type=int, default=5000)
    p.add_argument("--weight", type=float, default=0.5, help="sonar term weight (image fitness is in [0, 1))")
    p.add_argument("--reward-gain", type=float, default=SonarTermConfig.reward_gain,
                   help="sonar term: echo-range reward relative to the free-space penalty")
    p.add_argument("--tolerance", type=float, default=0.05, help="m, 'on a surface'")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--drift-fps", type=float, default=5.0, help="camera rate of the 20 m drift run")
    p.add_argument("--skip-drift", action="store_true", help="only the sonar surface figures")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    result = run(args)
    for k, v in result.items():
        print(f"{k:40s} {v:.4f}" if isinstance(v, float) else f"{k:40s} {v}")
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
