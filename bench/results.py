"""Today's benchmark figures: store a bench's JSON result, and render docs/results.md from the stored ones.

    python bench/results.py save NAME [-- BENCH_ARGS...]   # run bench/NAME.py --json BENCH_ARGS, store it
    python bench/results.py render                         # docs/results/*.json -> docs/results.md

``save`` passes the bench's output through, parses its last stdout line as one JSON object and writes
it to ``docs/results/NAME.json`` with ``date`` (UTC, ISO 8601), ``load_avg`` (the 1/5/15-minute load
averages when the bench ended), ``load_avg_before`` (when it started), ``command`` and ``commit`` (the
code measured: ``-dirty`` when common/, services/ or bench/ had uncommitted changes), then renders.
``render`` writes one table row per stored bench: its key figures, the date and the load it ran at.
A bench that fails or prints no JSON stores nothing and exits non-zero.
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS_DIR = ROOT / "docs" / "results"
RESULTS_MD = ROOT / "docs" / "results.md"


def _get(result: dict, dotted: str):
    """``result["a"]["b"]`` for ``"a.b"``; None when any part is missing."""
    value = result
    for part in dotted.split("."):
        if not isinstance(value, dict) or part not in value:
            return None
        value = value[part]
    return value


def _num(value, digits: int = 3) -> str:
    """A number with ``digits`` significant digits and thousands separators for large ones."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return str(value)
    if value == 0:
        return "0"
    if abs(value) >= 10 ** digits:
        return f"{value:,.0f}"
    return f"{value:.{digits}g}"


# bench name -> (what it measures, [(label, dotted JSON key, unit)]); unit "share" shows a fraction as a
# percentage, "M/s" divides by a million. A bench not listed here shows its first top-level numbers.
KEY_FIGURES: dict[str, tuple[str, list[tuple[str, str, str]]]] = {
    "bus": ("640×480 RGB stereo frames between two processes on loopback", [
        ("latency p50", "latency_p50_ms", "ms"),
        ("p99", "latency_p99_ms", "ms"),
        ("throughput", "frames_per_s", "frames/s"),
        ("shared memory: p50", "shm.latency_p50_ms", "ms"),
        ("p99", "shm.latency_p99_ms", "ms"),
        ("throughput", "shm.frames_per_s", "frames/s"),
    ]),
    "sim": ("simulator: 640×480 stereo + depth on the corridor, one process", [
        ("rate", "frames_per_s", "frames/s"),
        ("CPU", "cpu_ms_per_frame", "ms/frame"),
    ]),
    "evolver": ("fly fitness (7×7×3, 5,000 flies) and flies on the Middlebury motorcycle pair", [
        ("fitness", "fly_evals_per_s", "M/s"),
        ("serial kernel", "fly_evals_per_s_serial", "M/s"),
        ("numpy reference ×", "speedup_vs_naive", ""),
        ("a generation", "generation_ms", "ms"),
        ("90 % inliers after", "time_to_90pct_inliers_s", "s"),
        ("inliers at 1 s", "inliers_at_1s", "share"),
        ("SGBM", "sgbm_time_s", "s"),
        ("inliers at SGBM's time", "inliers_at_sgbm_time", "share"),
    ]),
    "real": ("real KITTI clip 00, frames 0-99 (84 m): `flyslam eval` defaults vs an ORB + PnP stereo VO", [
        ("flyslam ATE", "clips.kitti-00-frames-0-99@0:100.flyslam_ate_m", "m"),
        ("reference ATE", "clips.kitti-00-frames-0-99@0:100.reference_ate_m", "m"),
        ("flyslam drift", "clips.kitti-00-frames-0-99@0:100.flyslam_drift_pct", "%"),
        ("reference drift", "clips.kitti-00-frames-0-99@0:100.reference_drift_pct", "%"),
        ("flyslam", "clips.kitti-00-frames-0-99@0:100.flyslam_fps", "frames/s"),
        ("frames 0-49 ATE: flyslam", "clips.kitti-00-frames-0-99@0:50.flyslam_ate_m", "m"),
        ("reference", "clips.kitti-00-frames-0-99@0:50.reference_ate_m", "m"),
        ("frames 50-99 ATE: flyslam", "clips.kitti-00-frames-0-99@50:100.flyslam_ate_m", "m"),
        ("reference", "clips.kitti-00-frames-0-99@50:100.reference_ate_m", "m"),
        ("variants (bench/real_variants.py): flyslam no worse than the reference in", "variants.flyslam_no_worse", ""),
        ("of", "variants.runs", ""),
        ("worst ATE: flyslam", "variants.flyslam_worst_ate_pct", "% of the path"),
        ("reference", "variants.reference_worst_ate_pct", "% of the path"),
        ("back-end no worse than the sliding window in", "variants.backend_no_worse_than_sliding_window", ""),
        ("of", "variants.runs", ""),
    ]),
    "pipeline": ("whole pipeline at 30 frames/s, 640×480, every service incl. bridge and recorder", [
        ("pose latency p50", "pose_latency_p50_ms", "ms"),
        ("p99", "pose_latency_p99_ms", "ms"),
        ("frames skipped", "frames_skipped_fraction", "share"),
        ("CPU, all services", "cpu_pct_of_one_core.total", "% of a core"),
        ("per frame", "cpu_ms_per_frame.total", "ms"),
        ("machine references", "cpu_per_frame_in_references", ""),
        ("ATE", "ate_rmse_m", "m"),
    ]),
    "registration": ("pseudo-distance δ and registration, 5,000 flies", [
        ("δ exact (numba)", "exact_numba_delta_ms", "ms"),
        ("δ fast", "fast_delta_ms", "ms"),
        ("its error", "fast_rel_error", "share"),
        ("field build", "field_build_ms", "ms"),
        ("3-DoF", "register_3dof_ms", "ms"),
        ("3-DoF stereo", "register_3dof_stereo_ms", "ms"),
        ("its error", "register_3dof_stereo_err_m", "m"),
        ("6-DoF", "register_6dof_ms", "ms"),
    ]),
    "planner": ("harmonic planner at 200 × 200 (400 × 400)", [
        ("usable descent", "usable_gradient_fraction.200x200", "share"),
        ("plain float64 relaxation", "plain_float64_usable_gradient_fraction.200x200", "share"),
        ("warm update", "warm_update_ms.200x200", "ms"),
        ("cycles", "warm_update_cycles.200x200", ""),
        ("cold solve", "full_solve_ms.200x200", "ms"),
        ("warm update at 400²", "warm_update_ms.400x400", "ms"),
        ("cold solve at 400²", "full_solve_ms.400x400", "ms"),
    ]),
    "demo": ("closed-loop demo (every other run beside a CPU hog, wheel-slip bursts), the loop, a kidnap", [
        ("runs", "runs", ""),
        ("reached", "reached", ""),
        ("with a hog", "runs_with_hog", ""),
        ("reached", "reached_with_hog", ""),
        ("loop ATE", "loop_ate_pct_of_path", "%"),
        ("without closure", "loop_ate_pct_without_closure", "%"),
        ("loop final error", "loop_final_error_m", "m"),
        ("kidnapped: relocalised", "kidnapped_relocalised", ""),
        ("of", "kidnapped_trials", ""),
        ("registration NEES", "registration_nees", ""),
    ]),
    "faults": ("break-it: bad files and flags, hostile messages, kills, a 10× flood, an attacker", [
        ("tracebacks", "tracebacks", ""),
        ("of cases", "file_and_flag_cases", ""),
        ("crashes from hostile messages", "hostile_crashes", ""),
        ("recording kept", "recording_kept_fraction", "share"),
        ("trajectory kept", "trajectory_kept_fraction", "share"),
        ("poses after a localiser restart", "pose_gap_after_restart_s", "s"),
        ("flood: most RSS added by a service", "flood_rss_excess_max_mb", "MB"),
        ("flood reached", "flood_multiplier_reached", "×"),
        ("attacker's commands delivered", "attacker_commands_delivered", ""),
        ("secured poses", "secured_poses", ""),
    ]),
    "fusion": ("sonar term on the texture-poor corridor; 20 m corridor in lockstep", [
        ("flies on a surface with sonar", "surface_fraction_with_sonar", "share"),
        ("without", "surface_fraction_without_sonar", "share"),
        ("drift with odometry only", "drift_pct_odometry_only", "%"),
        ("fused with the localiser", "drift_pct_fused", "%"),
        ("ATE fused", "ate_m_fused", "m"),
    ]),
}


def key_figures(name: str, result: dict) -> tuple[str, str]:
    """(what, figures) cells of one bench's row."""
    what, keys = KEY_FIGURES.get(name, (name, []))
    cells = []
    for label, key, unit in keys:
        value = _get(result, key)
        if value is None:
            continue
        if unit == "share":                     # a fraction in [0, 1], shown as a percentage
            value, unit = 100 * value, "%"
        elif unit == "M/s":
            value = value / 1e6
        cells.append(f"{label} {_num(value)}{' ' + unit if unit else ''}")
    if not keys:
        skip = {"date", "load_avg", "load_avg_before", "command", "commit"}
        cells = [f"{k} {_num(v)}" for k, v in result.items()
                 if k not in skip and isinstance(v, (int, float)) and not isinstance(v, bool)][:6]
    return what, ", ".join(cells) or "(no figures)"


def render(results_dir: Path = RESULTS_DIR) -> str:
    """The markdown page for every ``*.json`` in ``results_dir``, sorted by bench name."""
    lines = [
        "# Benchmark figures",
        "",
        "Generated by `bench/results.py render` from `docs/results/*.json`; do not edit by hand.",
        "Each row is the last `--json` result of `bench/<bench>.py`, stored by",
        "`python bench/results.py save <bench>`. Wall-clock figures depend on how busy the machine was:",
        "the load column gives the 1-minute load average when the bench started → ended. The commit",
        "column names the code measured (`-dirty`: with uncommitted changes; `?`: not recorded).",
        "",
        "| bench | what | figures | date (UTC) | load | commit |",
        "|---|---|---|---|---|---|",
    ]
    for path in sorted(results_dir.glob("*.json")):
        name = path.stem
        try:
            result = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise SystemExit(f"results: cannot read {path}: {e}")
        what, figures = key_figures(name, result)
        load = result.get("load_avg") or [float("nan")]
        before = result.get("load_avg_before")
        load_cell = f"{before[0]:.1f} → {load[0]:.1f}" if before else f"{load[0]:.1f}"
        date = str(result.get("date", "?"))[:16].replace("T", " ")
        lines.append(f"| `{name}` | {what} | {figures} | {date} | {load_cell} | {result.get('commit') or '?'} |")
    lines += ["", "The full JSON of each run, with every figure the bench reports, is in `docs/results/`.", ""]
    return "\n".join(lines)


def last_json_line(stdout: str) -> dict:
    """The JSON object on the last non-empty line of ``stdout``; ValueError if there is none."""
    lines = [line for line in stdout.splitlines() if line.strip()]
    if not lines:
        raise ValueError("the bench printed nothing on stdout")
    result = json.loads(lines[-1])
    if not isinstance(result, dict):
        raise ValueError("the last stdout line is JSON but not an object")
    return result


def source_commit() -> str | None:
    """The checked-out commit, with "-dirty" when tracked code (common/, services/, bench/ but this
    script) has uncommitted changes, so a figure can be traced to the code it measured; None outside git."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", "common",
                                "services", "bench", ":!bench/results.py"], cwd=ROOT, capture_output=True, text=True,
                               check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + ("-dirty" if dirty else "")


def save(name: str, bench_args: list[str]) -> int:
    script = ROOT / "bench" / f"{name}.py"
    if not script.is_file():
        print(f"results: no bench {script.relative_to(ROOT)}", file=sys.stderr)
        return 2
    cmd = [sys.executable, str(script), "--json", *bench_args]
    before = os.getloadavg()
    proc = subprocess.run(cmd, cwd=ROOT, stdout=subprocess.PIPE, text=True)
    after = os.getloadavg()
    sys.stdout.write(proc.stdout)
    if proc.returncode != 0:
        print(f"results: {name} exited with status {proc.returncode}; nothing stored", file=sys.stderr)
        return 1
    try:
        result = last_json_line(proc.stdout)
    except ValueError as e:
        print(f"results: {name}: {e}; nothing stored", file=sys.stderr)
        return 1
    result["date"] = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
    result["load_avg"] = [round(x, 2) for x in after]
    result["load_avg_before"] = [round(x, 2) for x in before]
    result["command"] = shlex.join(["python", f"bench/{name}.py", "--json", *bench_args])
    result["commit"] = source_commit()
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    (RESULTS_DIR / f"{name}.json").write_text(json.dumps(result, indent=1) + "\n")
    RESULTS_MD.write_text(render())
    print(f"results: stored docs/results/{name}.json (load {after[0]:.2f}), wrote docs/results.md",
          file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="mode", required=True)
    p_save = sub.add_parser("save", help="run bench/NAME.py --json and store its result")
    p_save.add_argument("name", help="bench name, e.g. registration")
    p_save.add_argument("bench_args", nargs=argparse.REMAINDER, help="after --: arguments for the bench")
    sub.add_parser("render", help="write docs/results.md from docs/results/*.json")
    args = ap.parse_args(argv)
    if args.mode == "save":
        extra = args.bench_args[1:] if args.bench_args[:1] == ["--"] else args.bench_args
        return save(args.name, extra)
    RESULTS_MD.write_text(render())
    print(f"results: wrote {RESULTS_MD.relative_to(ROOT)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
