"""flyslam eval --deterministic: the same recording gives the same trajectory, byte for byte, run after run."""
from __future__ import annotations

import json
from pathlib import Path

from deploy.commands.evaluate import main

CORRIDOR = Path(__file__).resolve().parent.parent / "recordings" / "corridor.mcap"


def test_deterministic_eval_repeats_its_trajectory_exactly(tmp_path):
    runs = []
    for name in ("a", "b"):
        out = tmp_path / name
        assert main([str(CORRIDOR), "--out", str(out), "--max-frames", "12", "--population", "1500",
                     "--generations", "10", "--deterministic"]) == 0
        metrics = json.loads((out / "metrics.json").read_text())
        assert metrics["frames"] == 12 and "ate_rmse_m" in metrics["flyslam"] and metrics["loop_closures"] == []
        runs.append((out / "estimated.tum").read_bytes())
    assert runs[0] == runs[1]


def test_eval_refuses_an_impossible_population_in_one_line(tmp_path, capsys):
    assert main([str(CORRIDOR), "--out", str(tmp_path), "--population", "3"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "population" in err


def test_a_recording_without_ground_truth_gets_its_estimate_drawn_and_measured(tmp_path, capsys):
    """A user's own camera has no truth: eval still plots the trajectory and says how far it went."""
    from common.recording import RecordingReader, RecordingWriter

    no_truth = tmp_path / "camera.mcap"
    with RecordingWriter(no_truth) as rec:
        for msg in RecordingReader(CORRIDOR).messages():
            if "/truth/" not in msg.key:
                rec.write(msg.key, msg.payload, msg.log_time_ns, msg.publish_time_ns, schema=msg.schema)
    out = tmp_path / "eval"
    assert main([str(no_truth), "--out", str(out), "--max-frames", "12", "--population", "1500",
                 "--generations", "10", "--deterministic"]) == 0
    estimated = json.loads((out / "metrics.json").read_text())["estimated"]
    assert estimated["poses"] >= 8 and estimated["path_length_m"] > 0.05
    assert (out / "trajectories.png").stat().st_size > 1000
    assert "no ground truth" in capsys.readouterr().out


def test_ctrl_c_ends_an_eval_where_it_is_and_keeps_what_was_done(tmp_path):
    """A long eval stopped with Ctrl-C writes the trajectory and metrics of the frames it got through
    (exit 130), as a truncated recording's readable part is evaluated; before, everything was lost."""
    import signal
    import subprocess
    import sys

    from tests.helpers import ROOT

    out = tmp_path / "eval"
    proc = subprocess.Popen([sys.executable, "-m", "deploy.cli", "eval", str(CORRIDOR), "--out", str(out),
                             "--population", "1500", "--generations", "10"], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    lines = []
    for line in proc.stdout:          # the progress line every 25 frames: well into the run
        lines.append(line)
        if "[eval] 25 frames" in line:
            proc.send_signal(signal.SIGINT)
            break
    rest, _ = proc.communicate(timeout=120)
    text = "".join(lines) + rest
    assert proc.returncode == 130, text
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["interrupted"] and 25 <= metrics["frames"] < 301, metrics["frames"]
    assert "ate_rmse_m" in metrics["flyslam"] and (out / "estimated.tum").stat().st_size > 0
    assert "interrupted: evaluating the first" in text


def test_the_summary_says_which_loops_closed_and_metrics_keep_every_attempt():
    from common.slam.backend import LoopClosure
    from deploy.commands.evaluate import loop_line, loop_record
    loops = [LoopClosure(0, 32, 0.0, False, "photometric: 12 % inliers (< 50 %)"), LoopClosure(0, 33, 0.1503, True)]
    line = loop_line(loops)
    assert line.startswith("loop closures: 1 accepted") and "keyframe 33 to 0 moved it 0.150 m" in line
    assert "1 refused" in line
    assert [loop_record(lc) for lc in loops] == [
        {"old_keyframe": 0, "new_keyframe": 32, "accepted": False, "correction_m": 0.0,
         "reason": "photometric: 12 % inliers (< 50 %)"},
        {"old_keyframe": 0, "new_keyframe": 33, "accepted": True, "correction_m": 0.1503}]
    json.dumps([loop_record(lc) for lc in loops])      # metrics.json can hold them
