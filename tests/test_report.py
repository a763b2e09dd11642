"""The summary after `flyslam run`: measured figures from what the run left, never guesses."""
from __future__ import annotations

import json

import numpy as np

from common import messages as m
from common.geometry import planar_pose
from common.recording import RecordingWriter
from common.trajectory import write_tum
from deploy.report import format_pipeline_summary, pipeline_summary


def test_summary_reports_accuracy_target_and_files(tmp_path):
    stamps = np.arange(20, dtype=np.int64) * 100_000_000
    truth = np.array([planar_pose(0.1 * k, 0.0, 0.0) for k in range(20)])
    # the map starts at frame 5 (its origin there), and the estimate drifts 5 cm to the side by the end
    est = np.linalg.inv(truth[5]) @ truth[5:]
    est[:, 1, 3] += 0.05 * np.arange(15) / 14
    write_tum(tmp_path / "truth.tum", stamps, truth)
    write_tum(tmp_path / "estimated.tum", stamps[5:], est)
    (tmp_path / "run.json").write_text(json.dumps({"services": {
        "sim": {"progress": 20, "restarts": 0},
        "evolver": {"progress": 18, "restarts": 1, "rates": {"frames_skipped": 2.0, "generations_per_s": 150.0}}}}))
    with RecordingWriter(tmp_path / "recording.mcap") as rec:
        rec.write("rig/planner/target", m.encode(m.Target(x=2.0, y=0.0, header=m.header(1, 1, "map"))), 1)
        rec.write("rig/planner/cmd_vel", m.encode(m.VelocityCommand(stop=True, reason="target reached")), 2)
        rec.write("rig/planner/cmd_vel", m.encode(m.VelocityCommand(stop=True, reason="planner stopped")), 3)
    s = pipeline_summary(tmp_path)
    assert s["frames"] == 20 and s["frames_used_by_evolver"] == 18 and s["frames_skipped"] == 2
    assert s["target"] == "reached"           # the planner's own shutdown is not the outcome
    # ATE aligns the whole path (a straight drift is a small rotation); the final error ties the two
    # frames only where the map started
    assert abs(s["final_position_error_m"] - 0.05) < 1e-6 and s["ate_rmse_m"] < 1e-3
    assert abs(s["true_distance_to_target_m"] - 0.1) < 1e-6
    assert s["restarts"] == {"evolver": 1}
    text = format_pipeline_summary(s)
    assert "target               reached" in text and str(tmp_path / "recording.mcap") in text


def test_summary_says_what_is_missing(tmp_path):
    text = format_pipeline_summary(pipeline_summary(tmp_path))
    assert "no estimated and ground-truth trajectories" in text and "unknown" in text


def _run_folder(tmp_path, end_x: float, last_reason: str):
    stamps = np.arange(20, dtype=np.int64) * 100_000_000
    truth = np.array([planar_pose(end_x * k / 19, 0.0, 0.0) for k in range(20)])
    write_tum(tmp_path / "truth.tum", stamps, truth)
    write_tum(tmp_path / "estimated.tum", stamps, truth)
    with RecordingWriter(tmp_path / "recording.mcap") as rec:
        rec.write("rig/planner/target", m.encode(m.Target(x=2.0, y=0.0, radius_m=0.4, header=m.header(1, 1, "map"))), 1)
        rec.write("rig/planner/cmd_vel", m.encode(m.VelocityCommand(reason=last_reason)), 2)
    return pipeline_summary(tmp_path)


def test_a_robot_inside_the_target_radius_has_reached_it_whatever_the_last_command(tmp_path):
    """At the radius' edge the planner's last command may flicker back to 'following field' as the run
    ends; the robot's true position decides. Outside the radius the last command still says why not."""
    (tmp_path / "in").mkdir()
    (tmp_path / "out").mkdir()
    assert _run_folder(tmp_path / "in", 1.75, "following field")["target"] == "reached"
    assert _run_folder(tmp_path / "out", 1.0, "no path")["target"] == "not reached: last command 'no path'"


def test_summary_gives_the_evolvers_rate_while_frames_came_not_after(tmp_path):
    # the last heartbeat comes after the frames stopped: its own last-second rate is 0
    (tmp_path / "run.json").write_text(json.dumps({"services": {"evolver": {"progress": 600, "rates": {
        "generations_per_s": 0.0, "generations_per_s_while_frames": 142.46}}}}))
    s = pipeline_summary(tmp_path)
    assert s["generations_per_s"] == 142.5
    assert "generations/s        142.5" in format_pipeline_summary(s)


def test_summary_counts_a_replays_frames_not_its_messages(tmp_path):
    (tmp_path / "run.json").write_text(json.dumps({"services": {
        "replay": {"progress": 201, "counters": {"frames_replayed": 100}},
        "evolver": {"progress": 95, "rates": {"frames_skipped": 5.0}}}}))
    s = pipeline_summary(tmp_path)
    assert s["frames"] == 100
    assert "frames replayed      100" in format_pipeline_summary(s)


def test_summary_counts_a_cameras_frames(tmp_path):
    """camera.toml's run: the camera's frames are the source (the summary said 'frames rendered -')."""
    (tmp_path / "run.json").write_text(json.dumps({"services": {
        "camera": {"progress": 60, "counters": {"published": 68}},
        "evolver": {"progress": 58, "rates": {"frames_skipped": 2.0}}}}))
    stamps = np.arange(58, dtype=np.int64) * 100_000_000
    write_tum(tmp_path / "estimated.tum", stamps, np.array([planar_pose(0.9 * k, 0.0, 0.0) for k in range(58)]))
    text = format_pipeline_summary(pipeline_summary(tmp_path))
    assert "frames captured      60" in text and "skipped: 2" in text
    # no truth for a camera, but the summary says what the localiser made of the run
    assert "no ground truth" in text and "estimated path       58 poses, 51.3 m" in text
    assert "target" not in text          # no planner ran


def test_the_summarys_view_command_runs_from_wherever_the_run_was_started(tmp_path, monkeypatch):
    """`flyslam run` typed outside the repository: the 'view it' line names a rerun that exists there."""
    import shlex
    import shutil
    from pathlib import Path

    (tmp_path / "run.rrd").write_bytes(b"")
    monkeypatch.chdir(tmp_path)
    line = next(x for x in format_pipeline_summary(pipeline_summary(tmp_path)).splitlines() if "view it" in x)
    viewer = shlex.split(line)[2]
    assert Path(viewer).is_file() or shutil.which(viewer), line
