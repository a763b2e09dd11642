"""`flyslam eval RECORDING --out DIR`: run evolver and localiser in lockstep on a recording and score the trajectory.

Runs the chain in lockstep (every frame, a fixed number of generations per frame, deterministic for a
seed; see common.lockstep), then writes to DIR:
- ``estimated.tum`` (the final trajectory, as the live localiser writes it: after loop closures),
  ``groundtruth.tum`` and, when the recording has odometry, ``odometry.tum``;
- ``metrics.json``: ATE RMSE after SE(3) alignment, mean RPE (translation, rotation), drift in % of path
  length, frames per second — for the final trajectory ("flyslam"), for the poses as published frame by
  frame ("flyslam_online") and for odometry alone; every loop closure attempted (keyframes, accepted,
  how far it moved the new keyframe, why it was refused);
- ``trajectories.png``: the three trajectories seen from above.
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
from pathlib import Path

import numpy as np

from common.config_args import add_config_arguments, config_from_args
from common.fly import EvolverConfig
from common.lockstep import run_lockstep
from common.recording import RecordingError, RecordingReader
from common.trajectory import write_tum
from common.trajectory_metrics import TrajectoryMismatch, evaluate, factor_nees, path_length
from deploy.progress import Progress


def loop_record(lc) -> dict:
    """One loop closure attempt (common.slam.backend.LoopClosure) as metrics.json keeps it."""
    return {"old_keyframe": lc.old_id, "new_keyframe": lc.new_id, "accepted": lc.accepted,
            "correction_m": round(float(lc.correction_m), 4), **({"reason": lc.reason} if lc.reason else {})}


def loop_line(loops) -> str:
    """The summary's line on loop closures: how many held, and what each accepted one corrected."""
    accepted = [lc for lc in loops if lc.accepted]
    held = ", ".join(f"keyframe {lc.new_id} to {lc.old_id} moved it {lc.correction_m:.3f} m" for lc in accepted[:5])
    more = f" and {len(accepted) - 5} more" if len(accepted) > 5 else ""
    refused = len(loops) - len(accepted)
    return (f"loop closures: {len(accepted)} accepted" + (f" ({held}{more})" if accepted else "")
            + (f", {refused} refused (reasons in metrics.json)" if refused else ""))


def plot(path: Path, result, odom_in_map, stamps, estimated) -> None:
    """Truth (when the recording has it), odometry and the estimate from above, in the map frame: the
    truth is moved so that it starts where the estimate does (a recording's world frame need not start
    at the map's origin)."""
    import cv2
    size, margin = 800, 40
    truth = np.zeros((0, 3))
    if result.truth:
        i = min(int(np.searchsorted(result.truth_stamps, stamps[0])), len(result.truth) - 1)
        T_map_world = estimated[0] @ np.linalg.inv(result.truth[i])
        truth = np.array([(T_map_world @ T)[:3, 3] for T in result.truth])
    tracks = {"ground truth": (truth, (60, 160, 60)),
              "odometry": (np.array([T[:3, 3] for T in odom_in_map]) if odom_in_map else np.zeros((0, 3)), (40, 40, 220)),
              "flyslam": (np.array([T[:3, 3] for T in estimated]), (200, 90, 20))}
    pts = np.concatenate([t for t, _ in tracks.values() if len(t)])[:, :2]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    scale = (size - 2 * margin) / max(float(np.max(hi - lo)), 1e-3)
    img = np.full((size, size, 3), 255, np.uint8)

    def px(p):  # map x right, y up
        return np.stack([margin + (p[:, 0] - lo[0]) * scale, size - margin - (p[:, 1] - lo[1]) * scale], 1).astype(np.int32)

    tracks = {name: t for name, t in tracks.items() if len(t[0])}     # (the legend names what is drawn)
    for i, (name, (track, colour)) in enumerate(tracks.items()):
        if len(track) > 1:
            cv2.polylines(img, [px(track[:, :2])], False, colour, 2, cv2.LINE_AA)
        cv2.putText(img, name, (margin, 25 + 22 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour, 2, cv2.LINE_AA)
    cv2.putText(img, f"{1 / scale:.3f} m/px", (size - 180, size - 12), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
    cv2.imwrite(str(path), img)


class FirstInterruptEnds:
    """Ctrl-C ends the recording where it is: the frames evaluated so far are scored and written (an
    hour's run is not lost to a late Ctrl-C); a second Ctrl-C aborts at once.  Main thread only."""

    def __init__(self):
        self.interrupted = False
        self._previous = None

    def messages(self, messages):
        for msg in messages:
            if self.interrupted:
                return
            yield msg

    def _on_interrupt(self, _signum, _frame):
        if self.interrupted:
            raise KeyboardInterrupt
        self.interrupted = True

    def __enter__(self):
        self._previous = signal.getsignal(signal.SIGINT)
        if self._previous is not signal.SIG_IGN:      # (a background job ignores Ctrl-C: leave it so)
            signal.signal(signal.SIGINT, self._on_interrupt)
        return self

    def __exit__(self, *exc):
        if self._previous is not None:          # (None: a handler not set from Python; leave it)
            signal.signal(signal.SIGINT, self._previous)


def parse_overrides(items: list[str]):
    """LocaliserConfig with FIELD=VALUE overrides: Python literals, true/false in any case, and a bare
    word for a text field (``odometry=visual``)."""
    import ast
    import dataclasses

    from common.slam import LocaliserConfig
    defaults = {f.name: f.default for f in dataclasses.fields(LocaliserConfig)}
    changes = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or name not in defaults:
            raise ValueError(f"--localiser expects FIELD=VALUE with FIELD one of {', '.join(sorted(defaults))}; "
                             f"got {item!r}")
        if value.strip().lower() in ("true", "false"):
            changes[name] = value.strip().lower() == "true"
            continue
        try:
            changes[name] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            if not isinstance(defaults[name], str):
                raise ValueError(f"--localiser {name}: {value!r} is not a number, tuple or boolean") from None
            changes[name] = value
    return LocaliserConfig(**changes)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="flyslam eval", description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("recording", help="MCAP recording with stereo frames and calibration (and truth/pose)")
    p.add_argument("--out", required=True, help="folder for trajectories, metrics.json and the plot")
    p.add_argument("--generations", type=int, default=30, help="evolver generations per frame")
    add_config_arguments(p, EvolverConfig, only=["population"], helps={"population": "number of flies"})
    p.add_argument("--deterministic", action="store_true",
                   help="serial fitness kernel: the same trajectory on every run ('auto' picks kernels by timing)")
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--localiser", action="append", default=[], metavar="FIELD=VALUE",
                   help="override a LocaliserConfig field (common/slam/localiser.py), e.g. --localiser keyframe_distance_m=1.5")
    args = p.parse_args(argv)
    try:
        reader = RecordingReader(args.recording)
    except RecordingError as e:
        print(f"flyslam eval: {e}", file=sys.stderr)
        return 2
    try:
        localiser_config = parse_overrides(args.localiser)
        evolver_config = config_from_args(EvolverConfig, args, only=["population"],
                                          **({"parallel": False} if args.deterministic else {}))
    except ValueError as e:
        print(f"flyslam eval: {e}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    bar = Progress("eval")

    def progress(n, status):
        bar.update(n, f"frames, last: {status[:50]}")

    with FirstInterruptEnds() as interrupt:
        result = run_lockstep(interrupt.messages(reader.messages()), generations_per_frame=args.generations,
                              seed=args.seed, evolver_config=evolver_config, localiser_config=localiser_config,
                              max_frames=args.max_frames, progress=progress)
    bar.done()
    if interrupt.interrupted:
        if result.frames == 0:
            print("flyslam eval: interrupted before the first frame", file=sys.stderr)
            return 130
        print(f"flyslam eval: interrupted: evaluating the first {result.frames} frames", file=sys.stderr)
    if reader.error:
        print(f"flyslam eval: warning: {args.recording}: {reader.error}; evaluated the readable part", file=sys.stderr)
    if result.frames == 0:
        print(f"flyslam eval: {args.recording} has no stereo frames with a calibration", file=sys.stderr)
        return 2
    stamps = np.array(result.stamps, np.int64)
    # The trajectory as the live localiser writes it: every pose re-expressed in the back-end's final
    # keyframe poses (a loop closure corrects what came before it).  The poses as published, frame by
    # frame, are "flyslam_online".
    final_stamps, final_poses = result.localiser.trajectory()
    write_tum(out / "estimated.tum", final_stamps, np.asarray(final_poses))
    metrics = {"recording": str(args.recording), "frames": result.frames, "interrupted": interrupt.interrupted,
               "frames_per_s": round(result.frames_per_s, 3), "registered_fraction": round(result.registered_fraction, 3),
               "keyframes": result.keyframes, "pose_graph_failed_updates": result.graph_failed_updates,
               "pose_graph_unsolved_keyframes": result.graph_failures}
    loops = result.localiser.localiser.loop_closures if result.localiser.localiser is not None else []
    metrics["loop_closures"] = [loop_record(lc) for lc in loops]
    odom_in_map = []
    with_odom = [i for i, T in enumerate(result.odometry) if T is not None]
    have_odom = len(with_odom) > 0.9 * result.frames
    if have_odom:
        # Odometry lives in its own odom frame: express it in the map frame where the estimate first had it.
        i0 = with_odom[0]
        T_map_odom0 = result.estimated[i0] @ np.linalg.inv(result.odometry[i0])
        odom_stamps = stamps[with_odom]
        odom_in_map = [T_map_odom0 @ result.odometry[i] for i in with_odom]
        write_tum(out / "odometry.tum", odom_stamps, np.array(odom_in_map))
    if result.truth:
        write_tum(out / "groundtruth.tum", np.array(result.truth_stamps, np.int64), np.array(result.truth))
        try:
            metrics["flyslam"] = evaluate(final_stamps, final_poses, result.truth_stamps, result.truth).as_dict()
            metrics["flyslam_online"] = evaluate(stamps, result.estimated, result.truth_stamps, result.truth).as_dict()
            if have_odom:
                metrics["odometry_only"] = evaluate(odom_stamps, odom_in_map, result.truth_stamps, result.truth).as_dict()
                metrics["ate_improvement_over_odometry"] = round(
                    metrics["odometry_only"]["ate_rmse_m"] / max(metrics["flyslam"]["ate_rmse_m"], 1e-9), 2)
        except TrajectoryMismatch as e:
            metrics["error"] = str(e)
        backend = result.localiser.localiser.backend if result.localiser.localiser is not None else None
        if backend is not None:
            metrics["factor_nees"] = factor_nees(
                backend.graph.edges().values(), {k: kf.stamp_ns for k, kf in backend.archive.items()},
                result.truth_stamps, result.truth, planar=backend.planar)
    else:     # a user's own camera: no truth to score, but the estimate is still worth a look
        positions = np.asarray(final_poses).reshape(-1, 4, 4)[:, :3, 3]
        metrics["estimated"] = {"poses": len(final_stamps), "path_length_m": round(path_length(positions), 3)}
    if len(final_stamps) > 1:
        plot(out / "trajectories.png", result, odom_in_map, final_stamps, final_poses)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    print(f"frames {result.frames} at {result.frames_per_s:.2f} frames/s, registered {100 * result.registered_fraction:.0f} %, "
          f"{result.keyframes} keyframes")
    if result.graph_failed_updates or result.graph_failures:
        print(f"pose graph: {result.graph_failed_updates} iSAM2 update(s) failed and were solved again from the "
              f"whole graph; {result.graph_failures} keyframe(s) kept the front end's pose (graph unsolvable)")
    if loops:
        print(loop_line(loops))
    for name in ("flyslam", "flyslam_online", "odometry_only"):
        if name in metrics:
            r = metrics[name]
            print(f"{name:14s} ATE {r['ate_rmse_m']:.3f} m ({r['ate_pct_of_path']:.2f} % of {r['path_length_m']:.1f} m)  "
                  f"RPE {r['rpe_trans_mean_m'] * 1000:.1f} mm / {r['rpe_rot_mean_deg']:.2f}°  drift {r['drift_pct']:.2f} %")
    for kind, r in metrics.get("factor_nees", {}).items():
        print(f"pose graph {kind} factors against the truth: NEES {r['nees_mean']:.2f} (median {r['nees_median']:.2f}, "
              f"{r['factors']} factors; {r['dof']} if their covariances are right)")
    if "estimated" in metrics:
        print(f"no ground truth in {args.recording}: the estimate only, {metrics['estimated']['poses']} poses over "
              f"{metrics['estimated']['path_length_m']:.1f} m")
    print(f"wrote {out}/metrics.json, estimated.tum" + (", trajectories.png" if len(final_stamps) > 1 else ""))
    return 130 if interrupt.interrupted else 0


if __name__ == "__main__":
    sys.exit(main())
