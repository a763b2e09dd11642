"""Kidnapped robot: relocalisation in a saved corridor map from a random, unknown pose (figures, not pass/fail).

The map is built by ``flyslam eval``'s code path (common.lockstep) on recordings/corridor.mcap and saved
as map.mcap.  Each trial then drives the simulated corridor (the scenario the recording was made in,
a different seed) from a random start pose along the mapped stretch, straight ahead at the scripted
speed, with its odometry in an odom frame of its own (a random offset: odometry says nothing about
the map), into a fresh EvolverCore → LocaliserCore started on the loaded map.  A trial counts when
the core relocalises within ``--frames`` frames to within ``--max-error-m`` and ``--max-error-deg``.

The reference pose: the map's keyframes carry the map run's own drift (metres of dead reckoning are
not undone by a map without loop closure), and relocalisation can only place the robot in the map as
the map is.  So the truth is expressed in the map through the keyframe nearest to the robot (its map
pose times its true offset to the robot's true pose): the pose a locally rigid map gives the robot.
The error against the raw ground truth is reported beside it (``truth_error_m``).

    python -m bench.kidnapped [--trials 10] [--seed 0] [--json]

``run_kidnapped(trials, seed)`` returns the figures (``kidnapped_relocalised``, ``kidnapped_trials``,
``per_trial``) for bench/demo.py; with --json the last stdout line is that object.
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from common import messages as m
from common.fly import EvolverConfig
from common.fly.core import EvolverCore
from common.geometry import invert, planar_from_transform, planar_pose, wrap_angle
from common.lockstep import run_lockstep
from common.pose_buffer import PoseBuffer
from common.recording import RecordingReader
from common.sim import Simulator, load_scenario
from common.sim.bus_messages import camera_messages, odometry_message
from common.sim.scenario import PathConfig, scenario_path
from common.sim.sensors import OdometryReading
from common.sim.simulator import CameraDue
from common.slam.core import LocaliserCore
from common.slam.mapfile import load_map

ROOT = Path(__file__).resolve().parent.parent
RECORDING = ROOT / "recordings" / "corridor.mcap"
T0_NS = 1_800_000_000_000_000_000


def build_map(out: Path, seed: int = 0, recording: Path = RECORDING) -> dict:
    """Run the lockstep chain on the recording, save its map to ``out`` and return the truth of each
    keyframe ({id: T_world_base}) with the run's figures."""
    t0 = time.perf_counter()
    res = run_lockstep(RecordingReader(recording).messages(), seed=seed)
    core = res.localiser
    if core is None or not core.save_map(out):
        raise SystemExit(f"bench/kidnapped: {recording} made no map")
    truth = dict(zip(res.truth_stamps, res.truth))
    kfs = core.localiser.map_keyframes()
    return {"keyframe_truth": {kf.id: truth[kf.stamp_ns] for kf in kfs if kf.stamp_ns in truth},
            "keyframes": len(kfs), "map_seconds": time.perf_counter() - t0, "map_frames": res.frames}


def _reference(T_truth: np.ndarray, keyframes: dict, keyframe_truth: dict) -> np.ndarray:
    """The robot's true pose as the map (locally rigid around its nearest keyframe) places it."""
    kid = min(keyframe_truth, key=lambda k: np.linalg.norm(keyframe_truth[k][:2, 3] - T_truth[:2, 3]))
    return keyframes[kid] @ invert(keyframe_truth[kid]) @ T_truth


def _error(T: np.ndarray, T_ref: np.ndarray) -> tuple[float, float]:
    x, y, yaw = planar_from_transform(T)
    rx, ry, ryaw = planar_from_transform(T_ref)
    return float(np.hypot(x - rx, y - ry)), float(np.degrees(abs(wrap_angle(yaw - ryaw))))


def run_trial(map_data, keyframe_truth: dict, start: tuple, odom_offset: np.ndarray, seed: int,
              frames: int = 30, generations: int = 30) -> dict:
    """One kidnapped start: frames until relocalised (or ``frames``), the pose found and its errors."""
    scn = load_scenario(scenario_path("corridor"))
    x, y, yaw = start
    scn = replace(scn, start=start, path=PathConfig(mode="waypoints", waypoints=[[x + 6.0 * np.cos(yaw), y + 6.0 * np.sin(yaw)]],
                                                    speed=scn.path.speed, turn_rate_deg=scn.path.turn_rate_deg))
    sim = Simulator(scn, seed=seed, width=320, height=240, camera_rate_hz=10)
    cal = m.calibration_to_msg(sim.calibration, 1, T0_NS)
    evolver = EvolverCore(EvolverConfig(), settle=generations, seed=seed,
                          odometry=PoseBuffer(maxlen=100_000, max_extrapolation_ns=100_000_000))
    core = LocaliserCore(seed=seed, initial_map=map_data)
    evolver.on_calibration(cal)
    core.on_calibration(cal)
    keyframes = {kf.id: np.asarray(kf.T_map_base, float) for kf in map_data.keyframes}
    seen, first, t0 = 0, True, time.perf_counter()
    out = {"start": [round(float(v), 3) for v in start], "relocalised": False, "frames": None}
    statuses = []
    while seen < frames and not sim.finished:
        for ev in sim.advance(0.02):
            stamp = T0_NS + ev.stamp_ns
            if isinstance(ev, OdometryReading):
                msg = odometry_message(ev, stamp)
                evolver.on_odometry(stamp, odom_offset @ planar_pose(*msg.pose_xyyaw))
            elif isinstance(ev, CameraDue) and seen < frames:
                images = sim.render(ev.stamp_ns)
                frame = evolver.on_frame(camera_messages(images, seen + 1, stamp, "jpeg", quality=85)["stereo/frame"])
                if frame.population is None:
                    continue
                if first:            # as common.lockstep: relocalise from a converged population
                    evolver.evolve(max(0, core.config.min_generations - evolver.generation))
                    frame.population = evolver.population(with_image=True)
                    first = False
                seen += 1
                res = core.on_population(frame.population)
                statuses.append(res.pose.status if res.pose is not None else res.reason)
                if not core.relocalising and not out["relocalised"]:
                    found = core.relocalisation.T_map_base
                    e_m, e_deg = _error(found, _reference(images.T_map_base, keyframes, keyframe_truth))
                    t_m, t_deg = _error(found, images.T_map_base)
                    out.update(relocalised=True, frames=seen, error_m=round(e_m, 4), error_deg=round(e_deg, 3),
                               truth_error_m=round(t_m, 4), truth_error_deg=round(t_deg, 3),
                               how=core.relocalisation.reason)
                    seen = frames     # done
    out["searches"] = core.searches
    out["seconds"] = round(time.perf_counter() - t0, 2)
    out["last_status"] = statuses[-1] if statuses else None
    if not out["relocalised"]:
        out["why"] = core.relocalisation.reason if core.relocalisation is not None else "no population"
    return out


def run_kidnapped(trials: int = 10, seed: int = 0, frames: int = 30, max_error_m: float = 0.2,
                  max_error_deg: float = 2.0, map_path: str | Path | None = None, progress=None) -> dict:
    """Build the corridor map, run ``trials`` kidnapped starts; the figures as a dict."""
    with tempfile.TemporaryDirectory(prefix="kidnapped-") as tmp:
        path = Path(map_path) if map_path else Path(tmp) / "map.mcap"
        built = build_map(path, seed=seed)
        map_data = load_map(path)
        rng = np.random.default_rng(seed)
        xs = [kf.T_map_base[0, 3] for kf in map_data.keyframes]
        per_trial = []
        for i in range(trials):
            # along the mapped stretch, leaving 2.5 m of it ahead for the drive
            start = (float(rng.uniform(min(xs) + 0.3, max(xs) - 2.5)), float(rng.uniform(-0.3, 0.3)),
                     float(rng.uniform(-np.deg2rad(10), np.deg2rad(10))))
            offset = planar_pose(*rng.uniform([-50, -50, -np.pi], [50, 50, np.pi]))
            trial = run_trial(map_data, built["keyframe_truth"], start, offset, seed=seed * 1000 + i + 1, frames=frames)
            trial["ok"] = bool(trial["relocalised"] and trial["error_m"] <= max_error_m
                               and trial["error_deg"] <= max_error_deg)
            per_trial.append(trial)
            if progress:
                progress(i, trial)
    done = [t for t in per_trial if t["relocalised"]]
    return {"kidnapped_relocalised": sum(t["ok"] for t in per_trial), "kidnapped_trials": trials,
            "relocalised_any_error": len(done), "max_frames": frames, "max_error_m": max_error_m,
            "max_error_deg": max_error_deg, "map_keyframes": built["keyframes"],
            "map_seconds": round(built["map_seconds"], 1),
            "median_frames": float(np.median([t["frames"] for t in done])) if done else None,
            "median_error_m": float(np.median([t["error_m"] for t in done])) if done else None,
            "load_average": [round(v, 2) for v in os.getloadavg()], "per_trial": per_trial}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=30, help="frames a trial has to relocalise")
    ap.add_argument("--map", default=None, help="also keep the map built here (map.mcap)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.trials < 1 or args.frames < 1:
        ap.error("--trials and --frames must be at least 1")

    def progress(i, t):
        what = (f"relocalised in {t['frames']} frames, {t['error_m']:.3f} m / {t['error_deg']:.2f}° "
                f"(truth {t['truth_error_m']:.3f} m)" if t["relocalised"] else f"not relocalised: {t['why']}")
        print(f"trial {i + 1}: start {t['start']}: {what} [{t['seconds']:.0f} s]", flush=True)

    result = run_kidnapped(args.trials, args.seed, args.frames, map_path=args.map, progress=progress)
    print(f"relocalised {result['kidnapped_relocalised']}/{result['kidnapped_trials']} within {args.frames} frames "
          f"to {result['max_error_m']} m / {result['max_error_deg']}° (any error: {result['relocalised_any_error']}); "
          f"median {result['median_frames']} frames, {result['median_error_m']} m; load {result['load_average']}")
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
