"""Benchmark: flyslam (``flyslam eval``'s lockstep code path, default settings) against a plain stereo VO on real clips.

Every clip under the data folder (default ``../shared/data`` beside the repository) that has ground truth
— a KITTI odometry layout with ``poses/NN.txt``, or EuRoC with ``state_groundtruth_estimate0`` — is
imported into ``.cache/real/<clip>.mcap`` (again only when an importer changed) and run twice in the same process: through
``common.lockstep.run_lockstep`` with no configuration (whatever the defaults are today), and through the
reference ORB + PnP odometry of ``bench/stereo_vo_reference.py``. Both are scored with
``common.trajectory_metrics.evaluate`` (ATE after SE(3) alignment, mean RPE, drift % of path) and frames/s
(decode + estimate, wall clock).

``--frames A:B`` (repeatable) runs frames A..B-1 of each clip as if the recording started at A, e.g.
``--frames 0:50 --frames 50:100`` for the halves settings are chosen on and checked on.
``--variants`` also runs each clip changed as ``bench/real_variants.py`` describes (every 2nd / 3rd
frame, reversed, there and back, three laps of there and back, half resolution, a 640-px crop,
base_link at the camera, sensor noise, mismatched and swinging exposure, a swaying rig), keyed
``<clip>~<variant>``:
sequences flyslam has not seen, made from the one it has.
Writes ``bench/out/real/<clip>[_A-B]/trajectories.png`` (top view, map x right / y up; the estimates
aligned on the first truth pose). With --json the last stdout line is one JSON object: per run (key
``<clip>`` or ``<clip>@A:B``) ``flyslam_ate_m``, ``reference_ate_m``, ``flyslam_drift_pct``,
``reference_drift_pct``, ``flyslam_fps``, ``reference_fps``, ``truth_disputed`` (stretches where the ground
truth disagrees with both methods, see :func:`disputed_truth`) and more, plus ``load_avg`` (1/5/15 min).
The ``flyslam_*`` figures are the poses as published, frame by frame; ``flyslam_corrected_ate_m`` is the
trajectory the pose graph leaves at the end (``flyslam eval``'s estimated.tum) and ``sliding_window_ate_m``
the localiser run again without its back-end (``pose_graph=False``), issue 16's comparison.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench import real_variants  # noqa: E402
from bench.stereo_vo_reference import StereoVO  # noqa: E402
from common import messages as m  # noqa: E402
from common.geometry import invert  # noqa: E402
from common.images import frame_images  # noqa: E402
from common.importers import DatasetLayoutError, StereoDataset, write_recording  # noqa: E402
from common.lockstep import run_lockstep  # noqa: E402
from common.recording import RecordedMessage, RecordingReader  # noqa: E402
from common.slam.config import LocaliserConfig  # noqa: E402
from common.trajectory_metrics import TrajectoryMetrics, evaluate  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
CACHE = ROOT / ".cache" / "real"
OUT = ROOT / "bench" / "out" / "real"


@dataclass
class Clip:
    name: str
    load: Callable[[], StereoDataset]


def find_clips(data: Path) -> list[Clip]:
    """Real clips with ground truth under ``data``: KITTI sequences with poses, EuRoC with ground truth."""
    from common.importers.euroc import load_euroc
    from common.importers.kitti import load_kitti
    clips = []
    for d in sorted(p for p in data.iterdir() if p.is_dir()) if data.is_dir() else []:
        sequences = sorted(s for s in (d / "sequences").glob("*") if (s / "image_0").is_dir()
                           and (d / "poses" / f"{s.name}.txt").is_file())
        for s in sequences:
            name = d.name if len(sequences) == 1 else f"{d.name}-{s.name}"
            clips.append(Clip(name, lambda s=s: load_kitti(s)))
        if (d / "mav0" / "state_groundtruth_estimate0" / "data.csv").is_file():
            clips.append(Clip(d.name, lambda d=d: load_euroc(d)))
    return clips


def cached_recording(clip: Clip) -> Path:
    """The clip as a flyslam recording, imported on first use (written aside, then renamed into place)
    and again whenever an importer module (or the variants') is newer than the cached recording."""
    path = CACHE / f"{clip.name}.mcap"
    importers = Path(write_recording.__code__.co_filename).parent
    newest = max(f.stat().st_mtime for f in [*importers.glob("*.py"), Path(real_variants.__file__)])
    if not path.is_file() or path.stat().st_mtime < newest:
        CACHE.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".partial")
        t = time.perf_counter()
        write_recording(clip.load(), tmp)
        tmp.rename(path)
        print(f"imported {clip.name} into {path} in {time.perf_counter() - t:.1f} s", file=sys.stderr)
    return path


def frame_window(path: Path, first: int, stop: int | None) -> tuple[int, int, int]:
    """(start_ns, end_ns, n_frames) spanning frames first..stop-1 of the recording."""
    stamps = [r.log_time_ns for r in RecordingReader(path).messages() if r.key.endswith("/stereo/frame")]
    chosen = stamps[first:stop]
    if not chosen:
        raise ValueError(f"{path} has {len(stamps)} frames; the range {first}:{stop} is empty")
    return chosen[0], chosen[-1], len(chosen)


def sliced(path: Path, start_ns: int, end_ns: int) -> Iterator[RecordedMessage]:
    """The recording's calibration, and every other message stamped within [start_ns, end_ns]."""
    for rec in RecordingReader(path).messages():
        if rec.key.endswith("/stereo/calibration") or start_ns <= rec.log_time_ns <= end_ns:
            yield rec


def run_reference(messages: Iterator[RecordedMessage]):
    """(stamps, T_map_base list, seconds) of the reference VO over a recording's frames."""
    vo, stamps, poses = None, [], []
    t0 = time.perf_counter()
    for rec in messages:
        if rec.key.endswith("/stereo/calibration") and vo is None:
            vo = StereoVO(m.calibration_from_msg(m.decode(rec.payload)))
        elif rec.key.endswith("/stereo/frame") and vo is not None:
            msg = m.decode(rec.payload)
            left, right = frame_images(msg)
            poses.append(vo.track(left, right))
            stamps.append(msg.header.stamp_ns)
    return stamps, poses, time.perf_counter() - t0


def plot(path: Path, truth: np.ndarray, tracks: dict[str, np.ndarray]) -> None:
    """Top view (map x right, y up, equal scale) of the truth and each estimate aligned on the first truth pose."""
    size, margin = 800, 40
    colours = {"ground truth": (60, 160, 60), "flyslam": (200, 90, 20), "reference VO": (40, 40, 220)}
    xy = {"ground truth": truth[:, :2, 3]}
    for name, est in tracks.items():
        align = truth[0] @ invert(est[0])
        xy[name] = (align @ est)[:, :2, 3]
    pts = np.concatenate(list(xy.values()))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    scale = (size - 2 * margin) / max(float(np.max(hi - lo)), 1e-3)
    img = np.full((size, size, 3), 255, np.uint8)
    for i, (name, p) in enumerate(xy.items()):
        q = np.stack([margin + (p[:, 0] - lo[0]) * scale, size - margin - (p[:, 1] - lo[1]) * scale], 1)
        colour = colours.get(name, (0, 0, 0))
        cv2.polylines(img, [q.astype(np.int32)], False, colour, 2, cv2.LINE_AA)
        cv2.putText(img, name, (margin, 25 + 22 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour, 2, cv2.LINE_AA)
    cv2.putText(img, f"{1 / scale:.3f} m/px", (size - 180, size - 12), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), img)


def parse_range(text: str) -> tuple[int, int | None]:
    a, sep, b = text.partition(":")
    try:
        first, stop = int(a or 0), (int(b) if b else None)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--frames {text!r}: expected A:B (frame numbers)") from None
    if not sep or first < 0 or (stop is not None and stop <= first):
        raise argparse.ArgumentTypeError(f"--frames {text!r}: expected A:B with 0 <= A < B")
    return first, stop


def bench_clip(clip: Clip, first: int, stop: int | None) -> dict:
    path = cached_recording(clip)
    start_ns, end_ns, n = frame_window(path, first, stop)
    tag = "" if (first, stop) == (0, None) else f"_{first}-{first + n - 1}"

    def progress(k, status):
        if k % 10 == 0 or k == n:
            print(f"  {clip.name}{tag} flyslam frame {k}/{n}: {status[:60]}", file=sys.stderr)

    result = run_lockstep(sliced(path, start_ns, end_ns), progress=progress)
    ref_stamps, ref_poses, ref_seconds = run_reference(sliced(path, start_ns, end_ns))
    # issue 16's check: the localiser without its back-end (the sliding window of keyframes alone)
    window = run_lockstep(sliced(path, start_ns, end_ns), localiser_config=LocaliserConfig(pose_graph=False))
    truth = np.array(result.truth)
    fly: TrajectoryMetrics = evaluate(result.stamps, result.estimated, result.truth_stamps, truth)
    ref: TrajectoryMetrics = evaluate(ref_stamps, ref_poses, result.truth_stamps, truth)
    win: TrajectoryMetrics = evaluate(window.stamps, window.estimated, window.truth_stamps, np.array(window.truth))
    corrected: TrajectoryMetrics = evaluate(*result.localiser.trajectory(), result.truth_stamps, truth)
    plot(OUT / f"{clip.name}{tag}" / "trajectories.png", truth,
         {"flyslam": np.array(result.estimated), "reference VO": np.array(ref_poses)})
    return {"clip": clip.name, "frames": f"{first}:{first + n}", "path_length_m": round(fly.path_length_m, 3),
            "flyslam_ate_m": round(fly.ate_rmse_m, 4), "reference_ate_m": round(ref.ate_rmse_m, 4),
            "flyslam_ate_pct": round(fly.ate_pct_of_path, 3), "reference_ate_pct": round(ref.ate_pct_of_path, 3),
            "flyslam_drift_pct": round(fly.drift_pct, 3), "reference_drift_pct": round(ref.drift_pct, 3),
            "flyslam_rpe_mm": round(fly.rpe_trans_mean_m * 1000, 1), "reference_rpe_mm": round(ref.rpe_trans_mean_m * 1000, 1),
            "flyslam_rpe_deg": round(fly.rpe_rot_mean_deg, 3), "reference_rpe_deg": round(ref.rpe_rot_mean_deg, 3),
            "flyslam_fps": round(result.frames_per_s, 2), "reference_fps": round(len(ref_poses) / ref_seconds, 2),
            "flyslam_registered_pct": round(100 * result.registered_fraction, 1), "flyslam_keyframes": result.keyframes,
            "flyslam_corrected_ate_m": round(corrected.ate_rmse_m, 4),
            "sliding_window_ate_m": round(win.ate_rmse_m, 4),
            "truth_disputed": disputed_truth(result.truth_stamps, truth,
                                             {"flyslam": (result.stamps, result.estimated),
                                              "reference": (ref_stamps, ref_poses)})}


def disputed_truth(truth_stamps, truth, tracks: dict, min_frames: int = 3, rel: float = 0.05) -> list[list]:
    """Stretches where the ground truth's step length disagrees with every method while the methods agree
    with each other: [first frame, last frame, truth m/frame, methods' m/frame] for runs of at least
    ``min_frames`` frames.  A step is disputed when the methods' mean is more than ``rel`` of the truth's
    step away from it and the methods are less than half that far apart.  The ATE there measures the
    truth as much as the methods (KITTI 00's frames 1-14: a constant 0.860 m/frame that neither visual
    method sees)."""
    ts = np.asarray(truth_stamps)
    steps = {}
    for name, (stamps, poses) in tracks.items():
        at = {int(np.argmin(np.abs(ts - st))): T for st, T in zip(stamps, poses)}
        steps[name] = {k: float(np.linalg.norm(at[k][:3, 3] - at[k - 1][:3, 3])) for k in at if k - 1 in at}
    common = sorted(set.intersection(*(set(v) for v in steps.values()))) if steps else []
    rows = []                                   # (frame, truth's step, methods' mean step) of disputed steps
    for k in common:
        s_t = float(np.linalg.norm(truth[k][:3, 3] - truth[k - 1][:3, 3]))
        s = np.array([steps[name][k] for name in steps])
        gap = abs(s.mean() - s_t)
        if gap > rel * s_t and np.ptp(s) < 0.5 * gap:
            rows.append((k, s_t, s.mean()))
    if not rows:
        return []
    rows = np.array(rows)
    runs = np.split(rows, np.flatnonzero(np.diff(rows[:, 0]) != 1) + 1)
    return [[int(r[0, 0]), int(r[-1, 0]), round(float(r[:, 1].mean()), 3), round(float(r[:, 2].mean()), 3)]
            for r in runs if len(r) >= min_frames]


def print_table(runs: dict[str, dict]) -> None:
    print(f"{'clip':34s} {'method':10s} {'ATE m':>8s} {'% path':>7s} {'RPE mm':>8s} {'RPE °':>6s} "
          f"{'drift %':>8s} {'frames/s':>9s}")
    for key, r in runs.items():
        for method in ("flyslam", "reference"):
            print(f"{key:34s} {method:10s} {r[f'{method}_ate_m']:8.3f} {r[f'{method}_ate_pct']:7.2f} "
                  f"{r[f'{method}_rpe_mm']:8.1f} {r[f'{method}_rpe_deg']:6.2f} {r[f'{method}_drift_pct']:8.2f} "
                  f"{r[f'{method}_fps']:9.2f}")
        print(f"{'':34s} flyslam registered {r['flyslam_registered_pct']:.0f} % of frames, "
              f"{r['flyslam_keyframes']} keyframes, path {r['path_length_m']:.1f} m")
        print(f"{'':34s} flyslam as corrected by its pose graph (estimated.tum): ATE {r['flyslam_corrected_ate_m']:.3f} m; "
              f"without the pose graph (sliding window): {r['sliding_window_ate_m']:.3f} m")
        for a, b, t, e in r.get("truth_disputed", []):
            print(f"{'':34s} ground truth disputed by both methods on frames {a}-{b}: truth {t:.3f} m/frame, "
                  f"both estimates {e:.3f}")


def variant_summary(runs: dict[str, dict]) -> dict:
    """Over the variant runs (keys with ``~``): how many flyslam did no worse than the reference on, and
    each method's worst ATE in % of the path ({} without variants)."""
    chosen = [r for key, r in runs.items() if "~" in key]
    if not chosen:
        return {}
    return {"runs": len(chosen),
            "flyslam_no_worse": sum(r["flyslam_ate_m"] <= r["reference_ate_m"] for r in chosen),
            "backend_no_worse_than_sliding_window": sum(r["flyslam_ate_m"] <= r["sliding_window_ate_m"] for r in chosen),
            "flyslam_worst_ate_pct": max(r["flyslam_ate_pct"] for r in chosen),
            "reference_worst_ate_pct": max(r["reference_ate_pct"] for r in chosen)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data", help="folder of real clips")
    ap.add_argument("--frames", type=parse_range, action="append", default=None, metavar="A:B",
                    help="run frames A..B-1 only (repeatable; default: the whole clip)")
    ap.add_argument("--clip", action="append", default=None, help="only this clip (repeatable)")
    ap.add_argument("--variants", nargs="*", default=None, metavar="NAME",
                    help=f"also run each clip's variants (default all: {', '.join(real_variants.VARIANTS)})")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    clips = [c for c in find_clips(args.data) if args.clip is None or c.name in args.clip]
    if not clips:
        print(f"bench/real.py: no real clip with ground truth under {args.data}", file=sys.stderr)
        return 2
    if args.variants is not None:
        names = args.variants or list(real_variants.VARIANTS)
        unknown = sorted(set(names) - set(real_variants.VARIANTS))
        if unknown:
            print(f"bench/real.py: unknown variant(s) {', '.join(unknown)} (use {', '.join(real_variants.VARIANTS)})",
                  file=sys.stderr)
            return 2
        clips += [Clip(f"{c.name}~{v}", lambda c=c, v=v: real_variants.variant(c.load, v)) for c in list(clips)
                  for v in names]
    load_before = os.getloadavg()
    runs = {}
    for clip in clips:
        variant = "~" in clip.name          # variants run whole: they are other sequences, not halves
        for first, stop in [(0, None)] if variant else args.frames or [(0, None)]:
            key = clip.name if args.frames is None or variant else f"{clip.name}@{first}:{'' if stop is None else stop}"
            try:
                runs[key] = bench_clip(clip, first, stop)
            except (DatasetLayoutError, ValueError) as e:
                print(f"bench/real.py: {clip.name}: {e}", file=sys.stderr)
                return 2
    load = os.getloadavg()
    print_table(runs)
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} (at start {load_before[0]:.2f}); "
          f"plots in {OUT}/")
    variants = variant_summary(runs)
    if variants:
        print(f"variants: flyslam's ATE no worse than the reference's in {variants['flyslam_no_worse']} of "
              f"{variants['runs']}; worst ATE flyslam {variants['flyslam_worst_ate_pct']} % of the path, "
              f"reference {variants['reference_worst_ate_pct']} %; the back-end no worse than the sliding window in "
              f"{variants['backend_no_worse_than_sliding_window']} of {variants['runs']}")
    if args.json:
        print(json.dumps({"clips": runs, **({"variants": variants} if variants else {}),
                          "load_avg": [round(x, 2) for x in load],
                          "load_avg_before": [round(x, 2) for x in load_before]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
