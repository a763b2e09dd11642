"""The closed-loop demo's tally against issue 16's targets: runs, a CPU hog, wheel-slip bursts, a loop, a kidnap.

1. Demo runs: ``flyslam run`` (deploy/launch/demo.toml, its services unchanged) ``--runs`` times, every
   other run with a CPU hog beside it (``python -c 'while True: pass'`` at nice 0), on the corridor
   scenario with the simulator's wheel-slip bursts at ``--burst-rate-hz`` (OdometryConfig.burst_rate_hz;
   the scenario file is a copy of recordings/scenarios/corridor.toml with that one field set, passed as
   ``--var scenario=FILE``).  Each run has its own bus prefix (``--robot``), so runs of other people on
   the same machine cannot talk to it.  Scored from the run's summary.json (deploy/report.py): target
   reached, ATE, final position error; the run folder's ``map.*`` file is listed.
2. Loop: ``flyslam eval`` (deploy/commands/evaluate.py) on a recording simulated from
   recordings/scenarios/loop.toml, with ``--localiser loop_closure=True`` and ``=False``: ATE in % of the
   path and the final position error (estimate against truth at the last frame, anchored at the start).
   The ``loop_*`` keys are ``--seed``'s loop; ``loop_by_seed`` repeats it for ``--loop-seeds`` seeds, since
   one simulated loop says little about whether closure helps.
3. Kidnapped robot: bench/kidnapped.py's ``run_kidnapped(trials, seed)`` when that module exists; else
   the keys are null and ``kidnapped_note`` says why.
4. Registration covariance: the NEES of the registrations of bench/paper.py (the runs' localiser calls
   the registration with curvature=False, so the runs make none with a covariance): from ``--paper-json``
   (a saved ``bench/paper.py --json`` last line) or by running ``bench/paper.py --quick --json``.

Progress on stderr, a table on stdout, with --json one JSON object as the last stdout line.  Load
averages are recorded with every run.  Never pass/fail: the figures are the output.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from common.sim import load_scenario, scenario_path  # noqa: E402
from common.trajectory import TrajectoryFormatError, read_tum  # noqa: E402
from common.trajectory_metrics import associate  # noqa: E402

FLYSLAM = ROOT / ".venv" / "bin" / "flyslam"
PYTHON = ROOT / ".venv" / "bin" / "python"
OUT = ROOT / "bench" / "out" / "demo"
HOG = "while True: pass"


def log(*a):
    print(*a, file=sys.stderr, flush=True)


def load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def slip_scenario(path: Path, burst_rate_hz: float) -> Path:
    """The corridor scenario with wheel-slip bursts at `burst_rate_hz`, written to `path` (and checked by
    loading it back: the simulator reads what the bench says)."""
    text = scenario_path("corridor").read_text()
    if not re.search(r"^\[odometry\]\s*$", text, re.M):
        raise ValueError("recordings/scenarios/corridor.toml has no [odometry] table to add the bursts to")
    text = re.sub(r"^burst_rate_hz\s*=.*$\n", "", text, flags=re.M)
    text = re.sub(r"^\[odometry\]\s*$", f"[odometry]\nburst_rate_hz = {burst_rate_hz!r}", text, count=1, flags=re.M)
    path.write_text(text)
    got = load_scenario(path).odometry.burst_rate_hz
    if abs(got - burst_rate_hz) > 1e-12:
        raise ValueError(f"{path}: burst_rate_hz reads back as {got}, not {burst_rate_hz}")
    return path


def start_hog() -> subprocess.Popen:
    """A busy loop at nice 0 (the demo's own services run at 0, 5 and 10)."""
    def nice0():
        try:
            os.setpriority(os.PRIO_PROCESS, 0, 0)
        except OSError:
            pass   # not allowed to lower it: the hog keeps the bench's niceness, recorded below
    return subprocess.Popen([sys.executable, "-c", HOG], preexec_fn=nice0,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def demo_run(index: int, hog: bool, scenario: Path, out: Path, duration: float | None) -> dict:
    """One `flyslam run` of the demo; its summary.json figures, the map file, loads and wall time."""
    out.mkdir(parents=True, exist_ok=True)
    run_dir = out / f"run_{index:02d}{'_hog' if hog else ''}"
    cmd = [str(FLYSLAM), "run", "--out", str(run_dir), "--var", f"scenario={scenario}",
           "--robot", f"demobench{os.getpid()}r{index}"]
    if duration is not None:
        cmd += ["--duration", str(duration)]
    rec = dict(run=index, hog=hog, out=str(run_dir), load_start=load())
    hog_proc = start_hog() if hog else None
    if hog_proc is not None:
        try:
            rec["hog_nice"] = os.getpriority(os.PRIO_PROCESS, hog_proc.pid)
        except OSError:
            rec["hog_nice"] = None
    t0 = time.perf_counter()
    try:
        with open(out / f"run_{index:02d}.log", "w") as fh:
            proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, cwd=ROOT,
                                  timeout=(duration or 240.0) + 180.0)
        rec["exit_code"] = proc.returncode
    except subprocess.TimeoutExpired:
        rec["exit_code"] = None
        rec["error"] = "flyslam run did not end within its duration + 180 s"
    finally:
        if hog_proc is not None:
            hog_proc.kill()
            hog_proc.wait()
    rec["seconds"] = round(time.perf_counter() - t0, 1)
    rec["load_end"] = load()
    summary_path = run_dir / "summary.json"
    s = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    rec["reached"] = s.get("target") == "reached"
    rec["target"] = s.get("target", "no summary.json")
    rec["ate_m"] = s.get("ate_rmse_m")
    rec["final_error_m"] = s.get("final_position_error_m")
    rec["true_distance_to_target_m"] = s.get("true_distance_to_target_m")
    rec["path_length_m"] = s.get("path_length_m")
    rec["restarts"] = s.get("restarts") or {}
    maps = sorted(p.name for p in run_dir.glob("map.*")) if run_dir.exists() else []
    rec["map_file"] = maps[0] if maps else None
    return rec


def final_error(est_path: Path, gt_path: Path) -> float | None:
    """Distance between estimate and truth at the last associated frame, the estimate anchored at the
    true start pose (the map frame starts at the first frame's pose; no other alignment)."""
    try:
        es, ep = read_tum(est_path)
        gs, gp = read_tum(gt_path)
    except (OSError, TrajectoryFormatError):
        return None
    i, j = associate(es, gs, 60_000_000)
    if not len(i):
        return None
    T_gt_map = gp[j[0]] @ np.linalg.inv(ep[i[0]])
    return float(np.linalg.norm((T_gt_map @ ep[i[-1]])[:2, 3] - gp[j[-1]][:2, 3]))


def loop_eval(recording: Path, out: Path, closure: bool, extra: list[str]) -> dict:
    """`flyslam eval` of the loop recording with loop closure on or off: ATE (m, % of path), final error."""
    d = out / f"loop_closure_{'on' if closure else 'off'}"
    cmd = [str(FLYSLAM), "eval", str(recording), "--out", str(d), "--localiser", f"loop_closure={closure}", *extra]
    rec = dict(closure=closure, load_start=load())
    t0 = time.perf_counter()
    with open(out / f"loop_closure_{'on' if closure else 'off'}.log", "w") as fh:
        proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, cwd=ROOT)
    rec.update(exit_code=proc.returncode, seconds=round(time.perf_counter() - t0, 1), load_end=load())
    metrics_path = d / "metrics.json"
    if proc.returncode != 0 or not metrics_path.exists():
        rec["error"] = f"flyslam eval exited {proc.returncode}; see {out}/loop_closure_{'on' if closure else 'off'}.log"
        return rec
    m = json.loads(metrics_path.read_text()).get("flyslam", {})
    rec.update(ate_m=m.get("ate_rmse_m"), ate_pct_of_path=m.get("ate_pct_of_path"),
               path_length_m=m.get("path_length_m"),
               final_error_m=final_error(d / "estimated.tum", d / "groundtruth.tum"))
    return rec


def loop_recording(seed: int) -> Path:
    """The loop scenario simulated for ``seed`` (common.sim.offline.cached_recording: made again whenever
    the scenario or the simulator's code changed, never a stale file's figures)."""
    from common.sim.offline import cached_recording
    log(f"simulating (or reusing) recordings/scenarios/loop.toml, seed {seed}")
    return cached_recording("loop", seed=seed)


def loop_pair(seed: int, out_dir: Path) -> tuple[dict, dict]:
    """The loop of ``seed`` evaluated with loop closure on and off: (on, off) figures of loop_eval."""
    rec = loop_recording(seed)
    out_dir.mkdir(parents=True, exist_ok=True)
    figures = []
    for closure in (True, False):
        log(f"flyslam eval on the loop (seed {seed}), loop closure {'on' if closure else 'off'} (load {load()[0]:.1f})")
        r = loop_eval(rec, out_dir, closure, ["--seed", str(seed)])
        log(f"  ATE {r.get('ate_m')} m ({r.get('ate_pct_of_path')} % of the path), "
            f"final error {r.get('final_error_m')} m, {r['seconds']} s")
        figures.append(r)
    return figures[0], figures[1]


def kidnapped(trials: int, seed: int) -> dict:
    if trials == 0:
        return dict(kidnapped_relocalised=None, kidnapped_trials=None,
                    kidnapped_note="not run (--kidnapped-trials 0)")
    try:
        from bench.kidnapped import run_kidnapped
    except ImportError as e:
        return dict(kidnapped_relocalised=None, kidnapped_trials=None,
                    kidnapped_note=f"bench/kidnapped.py not importable ({e}); no kidnapped trials were run")
    t0 = time.perf_counter()
    try:
        r = run_kidnapped(trials=trials, seed=seed)
    except Exception as e:  # noqa: BLE001 - another bench's failure is reported, not raised
        return dict(kidnapped_relocalised=None, kidnapped_trials=None,
                    kidnapped_note=f"bench/kidnapped.py's run_kidnapped failed: {type(e).__name__}: {e}")
    out = dict(r)
    out.setdefault("kidnapped_relocalised", None)
    out.setdefault("kidnapped_trials", None)
    out["kidnapped_seconds"] = round(time.perf_counter() - t0, 1)
    out["kidnapped_load"] = load()
    return out


def paper_json_line(path: Path) -> str:
    """The last line of a saved `bench/paper.py --json` output; ValueError (one line) when it holds no
    JSON object."""
    try:
        lines = path.read_text(errors="replace").strip().splitlines()
    except OSError as e:
        raise ValueError(f"--paper-json {path}: cannot be read ({e.strerror})") from None
    try:
        if lines and isinstance(json.loads(lines[-1]), dict):
            return lines[-1]
    except ValueError:
        pass
    raise ValueError(f"--paper-json {path}: its last line is not a bench/paper.py --json object")


def registration_nees(paper_json: Path | None, out: Path) -> dict:
    """NEES of bench/paper.py's registrations (headline variant, viewpoint experiment: populations from
    two trolley poses, truth from the simulator), from a saved JSON line or a --quick run."""
    if paper_json is not None:
        line = paper_json_line(paper_json)
        source = f"bench/paper.py JSON read from {paper_json}"
    else:
        log("running bench/paper.py --quick --json for the registration NEES")
        proc = subprocess.run([str(PYTHON), str(ROOT / "bench" / "paper.py"), "--quick", "--json",
                               "--out", str(out / "paper")], cwd=ROOT, capture_output=True, text=True)
        if proc.returncode != 0 or not proc.stdout.strip():
            return dict(registration_nees=None, registration_dof=3,
                        registration_nees_source=f"bench/paper.py --quick failed: {proc.stderr.strip()[-200:]}")
        line = proc.stdout.strip().splitlines()[-1]
        source = "bench/paper.py --quick run by this bench"
    p = json.loads(line)
    if "viewpoint_nees" not in p:
        return dict(registration_nees=None, registration_dof=3,
                    registration_nees_source=f"{source}: it has no viewpoint_nees (a bench/paper.py from before NEES)")
    return dict(registration_nees=p["viewpoint_nees"], registration_dof=p.get("viewpoint_nees_dof", 3),
                registration_nees_ok=p.get("viewpoint_nees_ok"),
                registration_nees_registrations=p.get("viewpoint_nees_registrations"),
                registration_flat=p.get("viewpoint_flat"),
                registration_nees_equivalent=p.get("equivalent_nees"),
                registration_nees_source=(f"{source}: headline variant {p.get('headline_variant')!r}, viewpoint "
                                          f"experiment (simulated trolley, truth from the simulator), load "
                                          f"{p.get('load_average')}"))


def print_table(out: dict) -> None:
    print(f"closed-loop demo: {out['runs']} runs ({out['runs_with_hog']} with a CPU hog), wheel-slip bursts at "
          f"{out['burst_rate_hz']} Hz")
    print(f"{'run':>3s} {'hog':>4s} {'target':>8s} {'ATE m':>7s} {'final m':>8s} {'to target m':>11s} "
          f"{'map':>9s} {'s':>5s}  load start→end")
    for r in out["per_run"]:
        f = lambda v, w, p=3: f"{v:{w}.{p}f}" if isinstance(v, (int, float)) else f"{'-':>{w}s}"  # noqa: E731
        print(f"{r['run']:3d} {'yes' if r['hog'] else 'no':>4s} {'reached' if r['reached'] else 'NOT':>8s} "
              f"{f(r['ate_m'], 7)} {f(r['final_error_m'], 8)} {f(r['true_distance_to_target_m'], 11, 2)} "
              f"{r['map_file'] or '-':>9s} {r['seconds']:5.0f}  {r['load_start'][0]:.1f}→{r['load_end'][0]:.1f}"
              + ("" if r["reached"] else f"  ({r['target']})"))
    print(f"reached {out['reached']}/{out['runs']}; with the hog {out['reached_with_hog']}/{out['runs_with_hog']}")
    if out.get("loop_error"):
        print(f"loop: {out['loop_error']}")
    else:
        for key, name in (("loop_closure_on", "loop closure on "), ("loop_closure_off", "loop closure off")):
            r = out.get(key) or {}
            print(f"{name}: ATE {r.get('ate_m')} m = {r.get('ate_pct_of_path')} % of {r.get('path_length_m')} m, "
                  f"final error {None if r.get('final_error_m') is None else round(r['final_error_m'], 3)} m "
                  f"({r.get('seconds')} s, load {r.get('load_start')}→{r.get('load_end')})"
                  + (f"  {r['error']}" if r.get("error") else ""))
    for r in out.get("loop_by_seed") or []:
        print(f"loop seed {r['seed']}: {r['ate_pct_of_path']} % of the path with closure, "
              f"{r['ate_pct_without_closure']} % without ({r['improvement']}x), final error "
              f"{None if r['final_error_m'] is None else round(r['final_error_m'], 3)} m")
    print(f"kidnapped: relocalised {out['kidnapped_relocalised']} of {out['kidnapped_trials']}"
          + (f" ({out['kidnapped_note']})" if out.get("kidnapped_note") else ""))
    print(f"registration NEES {out['registration_nees']} ({out['registration_dof']} degrees of freedom; "
          f"{out['registration_nees_source']})")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=None, help="demo runs (default 10; --quick 2); every other one with the hog")
    ap.add_argument("--quick", action="store_true", help="2 demo runs, 3 kidnapped trials")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--burst-rate-hz", type=float, default=0.05,
                    help="wheel-slip bursts per second (the scenario default is 0.02: about one per demo run)")
    ap.add_argument("--duration", type=float, default=None, help="per-run limit in seconds (default: the launch file's 240)")
    ap.add_argument("--seed", type=int, default=0, help="loop recording and kidnapped trials")
    ap.add_argument("--kidnapped-trials", type=int, default=None, help="default 10; --quick 3")
    ap.add_argument("--paper-json", type=Path, default=None,
                    help="a saved `bench/paper.py --json` output to take the registration NEES from (else --quick is run)")
    ap.add_argument("--skip-runs", action="store_true", help="no demo runs (loop, kidnapped and NEES only)")
    ap.add_argument("--skip-loop", action="store_true", help="no loop evaluation (its keys are null)")
    ap.add_argument("--loop-seeds", type=int, default=None,
                    help="loops evaluated, seeds --seed, --seed + 1, ... (default 3; --quick 1); the loop_* keys "
                         "are --seed's, loop_by_seed has every one")
    args = ap.parse_args(argv)
    runs = args.runs if args.runs is not None else (2 if args.quick else 10)
    trials = args.kidnapped_trials if args.kidnapped_trials is not None else (3 if args.quick else 10)
    loop_seeds = args.loop_seeds if args.loop_seeds is not None else (1 if args.quick else 3)
    if runs < 0 or trials < 0 or args.burst_rate_hz < 0 or loop_seeds < 1:
        print("bench/demo.py: --runs, --kidnapped-trials and --burst-rate-hz must not be negative, "
              "--loop-seeds at least 1", file=sys.stderr)
        return 2
    if not FLYSLAM.exists():
        print(f"bench/demo.py: {FLYSLAM} not found (run deploy/setup.sh)", file=sys.stderr)
        return 2
    if args.paper_json is not None:
        try:
            paper_json_line(args.paper_json)      # checked before the runs, not after their half hour
        except ValueError as e:
            print(f"bench/demo.py: {e}", file=sys.stderr)
            return 2
    t_start = time.perf_counter()
    stamp = time.strftime("%Y%m%d-%H%M%S")
    out_dir = args.out / stamp
    out_dir.mkdir(parents=True, exist_ok=True)
    out = dict(out=str(out_dir), burst_rate_hz=args.burst_rate_hz, load_start=load())

    per_run = []
    if not args.skip_runs and runs:
        scenario = slip_scenario(out_dir / "corridor_slip.toml", args.burst_rate_hz)
        for k in range(runs):
            hog = k % 2 == 1
            log(f"demo run {k + 1}/{runs}{' with a CPU hog' if hog else ''} (load {load()[0]:.1f})")
            r = demo_run(k, hog, scenario, out_dir, args.duration)
            per_run.append(r)
            log(f"  {r['target']}; ATE {r['ate_m']} m, final error {r['final_error_m']} m, {r['seconds']} s")
    out.update(runs=len(per_run), reached=sum(r["reached"] for r in per_run),
               runs_with_hog=sum(r["hog"] for r in per_run),
               reached_with_hog=sum(r["reached"] and r["hog"] for r in per_run),
               ate_m=[r["ate_m"] for r in per_run], final_error_m=[r["final_error_m"] for r in per_run],
               per_run=per_run)

    out.update(loop_ate_pct_of_path=None, loop_ate_pct_without_closure=None)
    if args.skip_loop:
        out["loop_error"] = "skipped (--skip-loop)"
    else:
        try:
            # the headline keys are --seed's loop; the further seeds show whether closure helps in general
            out["loop_by_seed"] = []
            for k in range(loop_seeds):
                seed = args.seed + k
                on, off = loop_pair(seed, out_dir if k == 0 else out_dir / f"loop_seed{seed}")
                improvement = round(off["ate_m"] / on["ate_m"], 2) if on.get("ate_m") and off.get("ate_m") else None
                out["loop_by_seed"].append(dict(
                    seed=seed, ate_pct_of_path=on.get("ate_pct_of_path"),
                    ate_pct_without_closure=off.get("ate_pct_of_path"), improvement=improvement,
                    final_error_m=on.get("final_error_m")))
                if k == 0:
                    out.update(loop_closure_on=on, loop_closure_off=off,
                               loop_ate_pct_of_path=on.get("ate_pct_of_path"),
                               loop_ate_pct_without_closure=off.get("ate_pct_of_path"),
                               loop_final_error_m=on.get("final_error_m"),
                               loop_final_error_without_closure_m=off.get("final_error_m"))
                    if improvement is not None:
                        out["loop_ate_improvement"] = improvement
        except Exception as e:  # noqa: BLE001 - after the demo runs: reported, never losing their results
            out["loop_error"] = f"{type(e).__name__}: {e}"

    log(f"kidnapped robot, {trials} trials")
    out.update(kidnapped(trials, args.seed))
    out.update(registration_nees(args.paper_json, out_dir))
    out["load_end"] = load()
    out["seconds"] = round(time.perf_counter() - t_start, 1)
    print_table(out)
    print(f"load average at start {out['load_start']}, at end {out['load_end']}; {out['seconds']:.0f} s; "
          f"run folders under {out_dir}")
    if args.json:
        print(json.dumps(out, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
