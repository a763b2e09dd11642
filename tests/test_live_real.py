"""The live pipeline on real stereo images, as a user runs it: the shared KITTI clip's first 40 frames
through `flyslam run` with the two real-data launch files, visual-only (KITTI has no wheels).

* ``deploy/launch/kitti.toml``: an imported recording replayed at its real 10 Hz, scored against its
  ground truth in the run's summary.
* ``deploy/launch/camera.toml``: the same frames as two video files and a calibration YAML, as a user's
  own stereo camera (``flyslam calibrate``, then this one launch file); no ground truth, so the
  estimate is checked against the car's known speed.

Both used to lose the car from the start: the pre-map populations (a second of frames while the flies
converge) taught the constant-velocity model a standing camera, which then refused the true motion."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from common.trajectory import read_tum
from tests.helpers import ROOT, hub

FRAMES = 40
SEQUENCE = "kitti-00-frames-0-99/sequences/00"


@pytest.fixture(scope="module")
def kitti(shared_data):
    from common.importers.kitti import load_kitti
    seq = shared_data / SEQUENCE
    if not seq.is_dir():
        pytest.skip(f"{seq} not found (the shared real KITTI clip)")
    return seq, load_kitti(seq, max_frames=FRAMES)


def run(launch: str, out, port: int, *variables: str) -> subprocess.CompletedProcess:
    argv = [sys.executable, "-m", "deploy.cli", "run", str(ROOT / "deploy" / "launch" / launch), "--out", str(out),
            "--hub", hub(port)]
    for v in variables:
        argv += ["--var", v]
    return subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=240,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)))


def test_a_replayed_kitti_recording_is_tracked_live(kitti, tmp_path, zenoh_port):
    from common.importers import write_recording
    _, dataset = kitti
    write_recording(dataset, tmp_path / "k00.mcap")
    done = run("kitti.toml", tmp_path / "run", zenoh_port, f"recording={tmp_path / 'k00.mcap'}")
    assert done.returncode == 0, done.stdout + done.stderr
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["path_length_m"] > 15.0, summary          # the map started within the clip's first half
    # The map starts within the first frames, where KITTI's truth holds 0.86 m a frame while every
    # visual method sees the car speed up: ~0.6 % of the path. A lost car ends tens of metres off.
    assert summary["ate_pct_of_path"] < 2.0, summary
    assert summary["final_position_error_m"] < 0.1 * summary["path_length_m"], summary


def test_a_stereo_camera_with_this_launch_file_follows_the_car(kitti, tmp_path, zenoh_port):
    from common.stereo_rectify import RawStereoRig, save_stereo_yaml
    _, dataset = kitti
    c = dataset.calibration
    width = c.width - c.width % 2                       # MJPG frames have an even width
    for side, name in ((0, "left.avi"), (1, "right.avi")):
        video = cv2.VideoWriter(str(tmp_path / name), cv2.VideoWriter_fourcc(*"MJPG"), 10, (width, c.height))
        for i in range(FRAMES):
            video.write(cv2.cvtColor(np.ascontiguousarray(dataset.load_pair(i)[side][:, :width]), cv2.COLOR_GRAY2BGR))
        video.release()
    # the rig as `flyslam calibrate` writes it: KITTI's grey cameras are rectified already
    save_stereo_yaml(tmp_path / "stereo.yaml", RawStereoRig(width, c.height, c.K_left, np.zeros(5), c.K_right,
                                                            np.zeros(5), np.eye(3), [-c.baseline, 0.0, 0.0]))
    done = run("camera.toml", tmp_path / "run", zenoh_port, f"calibration={tmp_path / 'stereo.yaml'}",
               f"left={tmp_path / 'left.avi'}", f"right={tmp_path / 'right.avi'}")
    assert done.returncode == 0, done.stdout + done.stderr
    stamps, poses = read_tum(tmp_path / "run" / "estimated.tum")
    assert len(stamps) >= 8, done.stdout
    seconds = (stamps[-1] - stamps[0]) * 1e-9
    truth = dataset.truth_poses
    true_speed = np.linalg.norm(truth[-1][:3, 3] - truth[0][:3, 3]) / ((FRAMES - 1) * 0.1)   # ~8.8 m/s
    ahead = poses[-1][:3, 3] - poses[0][:3, 3]
    assert ahead[0] / seconds == pytest.approx(true_speed, rel=0.2), (ahead, seconds)   # forward (x), at its speed
    assert abs(ahead[1]) < 0.1 * ahead[0]
