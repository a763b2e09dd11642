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
        assert metrics["frames"] == 12 and "ate_rmse_m" in metrics["flyslam"]
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
