"""The summary a person reads after `flyslam run` of the pipeline: what happened, how well, where the files are.

Built from what the run left in its output folder: the supervisor's ``run.json`` (last heartbeat of every
service), the trajectories (``estimated.tum``, ``truth.tum``) and the recording (the planner's last command).
Anything missing is reported as missing, never guessed. A restarted recorder or bridge leaves several
segments (``recording.1.mcap``, ``run.1.rrd``, …): the recording is read across all of them, ``files``
lists every segment (each entry a list of paths) and the view command opens every .rrd at once.
"""
from __future__ import annotations

import json
import os
import shlex
import sys
from pathlib import Path

import numpy as np

from common import messages as m
from common.recording import RecordingError, RecordingReader, segments_of
from common.trajectory import TrajectoryFormatError, read_tum
from common.trajectory_metrics import TrajectoryMismatch, associate, evaluate, path_length


def _last_command(recording: Path) -> tuple[m.VelocityCommand | None, int, m.Target | None]:
    """The planner's last command (its own shutdown excluded), how many there were, and the target."""
    last, count, target = None, 0, None
    try:
        for rec in RecordingReader(recording).messages():
            if rec.key.endswith("/planner/target"):
                try:
                    target = m.decode(rec.payload, m.Target)
                except m.DecodeError:
                    pass
            if rec.key.endswith("/planner/cmd_vel"):
                count += 1
                try:
                    cmd = m.decode(rec.payload, m.VelocityCommand)
                except m.DecodeError:
                    continue
                if cmd.reason != "planner stopped":   # the planner's own shutdown is not an outcome
                    last = cmd
    except RecordingError:
        pass
    return last, count, target


def pipeline_summary(out: Path) -> dict:
    out = Path(out)
    summary: dict = {"out": str(out)}
    run = json.loads((out / "run.json").read_text()) if (out / "run.json").exists() else {}
    services = run.get("services", {})
    sim = services.get("sim", {})
    evolver = services.get("evolver", {})
    replay = services.get("replay", {})
    camera = services.get("camera", {})
    # the simulator's and the camera's progress is frames; a replay's is messages, of which it counts the frames
    if sim or camera:
        summary["frames"] = (sim or camera).get("progress")
        summary["frames_source"] = "rendered" if sim else "captured"
    else:
        summary["frames"] = replay.get("counters", {}).get("frames_replayed")
        summary["frames_source"] = "replayed" if replay else "rendered"
    summary["frames_used_by_evolver"] = evolver.get("progress")
    rates = evolver.get("rates", {})
    summary["frames_skipped"] = int(rates.get("frames_skipped", 0)) if rates else None
    # the mean while frames came (the last heartbeat's own rate is taken after the frames stopped)
    rate = rates.get("generations_per_s_while_frames", rates.get("generations_per_s"))
    summary["generations_per_s"] = round(rate, 1) if rate is not None else None
    summary["frames_degraded"] = evolver.get("counters", {}).get("degraded_frames") if rates else None   # starved of CPU
    summary["restarts"] = {name: s.get("restarts", 0) for name, s in services.items() if s.get("restarts")}
    est_path, gt_path = out / "estimated.tum", out / "truth.tum"
    if est_path.exists() and gt_path.exists():
        try:
            es, ep = read_tum(est_path)
            gs, gp = read_tum(gt_path)
            metrics = evaluate(es, ep, gs, gp, tolerance_ns=60_000_000)
            summary["ate_rmse_m"] = round(metrics.ate_rmse_m, 3)
            summary["path_length_m"] = round(metrics.path_length_m, 2)
            summary["ate_pct_of_path"] = round(metrics.ate_pct_of_path, 2)
            # ATE aligns the whole trajectories; a navigating robot lives in its map frame, so also
            # report where it believed it was at the end versus where it really was, the two frames
            # tied only where the map started (its first pose: a robot that drove on while its flies
            # converged, or a replay whose truth starts earlier, starts its map away from the truth's
            # origin).
            i, j = associate(es, gs, 60_000_000)
            if len(i):
                T_truth_map = gp[j[0]] @ np.linalg.inv(ep[i[0]])
                end = T_truth_map @ ep[i[-1]]
                summary["final_position_error_m"] = round(float(np.linalg.norm(end[:2, 3] - gp[j[-1]][:2, 3])), 3)
                summary["final_true_xy"] = [round(float(v), 2) for v in gp[-1][:2, 3]]
        except (TrajectoryFormatError, TrajectoryMismatch, ValueError) as e:
            summary["ate_error"] = str(e)
    elif est_path.exists():   # a live camera: no truth, but what the localiser made of the run
        summary["ate_error"] = "no ground truth to compare with"
        try:
            es, ep = read_tum(est_path)
            summary["estimated_poses"] = len(es)
            summary["estimated_path_m"] = round(path_length(ep[:, :3, 3]), 2)
        except (TrajectoryFormatError, ValueError) as e:
            summary["ate_error"] += f"; {est_path.name}: {e}"
    else:
        summary["ate_error"] = "no estimated and ground-truth trajectories"
    cmd, n_cmd, target = _last_command(out / "recording.mcap")
    summary["commands"] = n_cmd
    # a launch without a planner (a replayed recording, a camera) has no target to report on
    summary["planner"] = bool(n_cmd) or "planner" in services or not services
    if cmd is not None:
        summary["target"] = "reached" if cmd.reason == "target reached" else f"not reached: last command '{cmd.reason}'"
    if target is not None and "final_true_xy" in summary:
        x, y = summary["final_true_xy"]
        distance = float(np.hypot(target.x - x, target.y - y))
        summary["true_distance_to_target_m"] = round(distance, 2)
        # At the edge of the target's radius the planner's last commands flicker between 'target reached'
        # and 'following field'; the robot's true position is what decides.
        if distance <= target.radius_m:
            summary["target"] = "reached"
    files = {"rerun": out / "run.rrd", "recording": out / "recording.mcap", "estimated": est_path,
             "truth": gt_path, "logs": out / "logs"}
    summary["files"] = {k: [str(p) for p in (segments_of(v) if v.is_file() else [v])]
                        for k, v in files.items() if v.exists()}
    return summary


def rerun_command() -> str:
    """The rerun viewer installed beside this Python (the venv's), as a path the user can type here:
    relative to the current folder when it is inside it, else absolute; plain ``rerun`` when there is none."""
    exe = Path(sys.executable).parent / "rerun"
    if not exe.is_file():
        return "rerun"
    try:
        shown = os.path.relpath(exe) if exe.resolve().is_relative_to(Path.cwd().resolve()) else str(exe)
    except (OSError, ValueError):
        shown = str(exe)
    return shlex.quote(shown if os.sep in shown else os.path.join(".", shown))   # (a bare name is a PATH lookup)


def format_pipeline_summary(s: dict) -> str:
    def v(key, unit=""):
        return "-" if s.get(key) is None else f"{s[key]}{unit}"
    lines = ["", "pipeline summary",
             f"  frames {s.get('frames_source', 'rendered'):13s} {v('frames')}",
             f"  frames evolved       {v('frames_used_by_evolver')}  (skipped: {v('frames_skipped')}; "
             f"degraded, the evolver starved of CPU: {v('frames_degraded')})",
             f"  generations/s        {v('generations_per_s')}"]
    if "ate_rmse_m" in s:
        lines.append(f"  ATE vs ground truth  {s['ate_rmse_m']} m RMSE over {s['path_length_m']} m "
                     f"({s['ate_pct_of_path']} % of the path)")
    else:
        lines.append(f"  ATE vs ground truth  - ({s.get('ate_error')})")
    if "estimated_path_m" in s:
        lines.append(f"  estimated path       {s['estimated_poses']} poses, {s['estimated_path_m']} m")
    if "final_position_error_m" in s:
        lines.append(f"  final pose error     {s['final_position_error_m']} m (estimate vs truth at the end, from where the map started)")
    if s.get("planner", True):
        target_line = s.get('target', 'unknown (no planner command recorded)')
        if "true_distance_to_target_m" in s:
            target_line += f" (true distance to the target at the end: {s['true_distance_to_target_m']} m)"
        lines.append(f"  target               {target_line}")
    if s.get("restarts"):
        lines.append(f"  restarts             {s['restarts']}")
    lines.append("  files:")
    lines += [f"    {k:<10} {' '.join(paths)}" for k, paths in s.get("files", {}).items()]
    if "rerun" in s.get("files", {}):
        lines.append(f"  view it:  {rerun_command()} {' '.join(shlex.quote(f) for f in s['files']['rerun'])}")
    return "\n".join(lines)
