"""`flyslam import kitti` on a small synthetic sequence in the KITTI odometry layout."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.geometry import R_BODY_OPTICAL, make_transform, planar_from_transform, rot_y
from common.images import frame_images
from common.messages import (PoseEstimate, StereoCalibrationMsg, StereoFrame, calibration_from_msg, decode,
                             transform_of)
from common.recording import RecordingReader
from deploy.commands import importer

W, H, N = 64, 48, 4
TIMES = ["0.000000e+00", "1.036000e-01", "2.072000e-01", "3.108000e-01"]
STAMPS = [0, 103_600_000, 207_200_000, 310_800_000]
FX, CX, CY, BASELINE = 200.0, 31.5, 23.5, 0.54


def read_recording(path):
    """{key: [decoded messages]} and the calibration metadata payload of a recording."""
    reader = RecordingReader(path)
    out = {}
    for m in reader.messages():
        msg = decode(m.payload)
        assert m.log_time_ns == m.publish_time_ns == msg.header.stamp_ns
        out.setdefault(m.key, []).append(msg)
    assert reader.error is None
    return out, reader.calibration_payload()


def _camera_poses():
    """Left camera poses (KITTI: in the first camera's frame): forward along optical z, drifting right, turning."""
    return [make_transform(rot_y(0.1 * i), [0.1 * i, 0.0, 0.8 * i]) for i in range(N)]


def _kitti(root, with_poses=True):
    seq = root / "sequences" / "03"
    rng = np.random.default_rng(3)
    images = []
    for cam in ("image_0", "image_1"):
        (seq / cam).mkdir(parents=True)
    for i in range(N):
        left, right = rng.integers(0, 256, (2, H, W), dtype=np.uint8)
        cv2.imwrite(str(seq / "image_0" / f"{i:06d}.png"), left)
        cv2.imwrite(str(seq / "image_1" / f"{i:06d}.png"), right)
        images.append((left, right))
    P0 = [FX, 0, CX, 0, 0, FX, CY, 0, 0, 0, 1, 0]
    P1 = [FX, 0, CX, -FX * BASELINE, 0, FX, CY, 0, 0, 0, 1, 0]
    row = lambda v: " ".join(f"{x:.12e}" for x in v)  # noqa: E731
    (seq / "calib.txt").write_text(f"P0: {row(P0)}\nP1: {row(P1)}\nP2: {row(P0)}\nP3: {row(P1)}\n"
                                   f"Tr: {row([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0])}\n")
    (seq / "times.txt").write_text("\n".join(TIMES) + "\n")
    if with_poses:
        (root / "poses").mkdir()
        (root / "poses" / "03.txt").write_text(
            "".join(" ".join(f"{x:.9e}" for x in T[:3].ravel()) + "\n" for T in _camera_poses()))
    return images


def test_kitti_round_trip(tmp_path, capsys):
    images = _kitti(tmp_path / "kitti")
    out = tmp_path / "kitti03.mcap"
    assert importer.main(["kitti", str(tmp_path / "kitti"), "--sequence", "3", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "frames 4/4" in captured.err
    assert "frames     4 over 0.31 s" in captured.out and "truth      4 poses" in captured.out

    msgs, calib_payload = read_recording(out)
    calib = calibration_from_msg(decode(calib_payload, StereoCalibrationMsg))
    (cal_msg,) = msgs["rig/stereo/calibration"]
    assert calibration_from_msg(cal_msg).fx == calib.fx == FX
    assert (calib.width, calib.height, calib.cx_left, calib.cy) == (W, H, CX, CY)
    assert calib.baseline == pytest.approx(BASELINE)
    assert np.allclose(calib.T_base_camera[:3, :3], R_BODY_OPTICAL)

    frames = msgs["rig/stereo/frame"]
    assert [f.header.stamp_ns for f in frames] == STAMPS
    assert all(isinstance(f, StereoFrame) and f.encoding == "png" for f in frames)
    for f, (left, right) in zip(frames, images):
        got_l, got_r = frame_images(f)
        assert np.array_equal(got_l, left) and np.array_equal(got_r, right)  # lossless

    poses = msgs["rig/truth/pose"]
    assert [p.header.stamp_ns for p in poses] == STAMPS
    assert all(isinstance(p, PoseEstimate) and p.header.frame_id == "map" and p.child_frame_id == "base_link"
               for p in poses)
    for i, p in enumerate(poses):
        x, y, yaw = planar_from_transform(transform_of(p))
        # optical z forward → map +x; optical x right → map −y; turning towards optical +x → negative yaw
        assert (x, y, yaw) == pytest.approx((0.8 * i, -0.1 * i, -0.1 * i), abs=1e-9)
        assert transform_of(p)[2, 3] == pytest.approx(0.0, abs=1e-9)


def test_kitti_sequence_folder_max_frames_and_no_truth(tmp_path, capsys):
    _kitti(tmp_path / "kitti", with_poses=False)
    out = tmp_path / "short.mcap"
    assert importer.main(["kitti", str(tmp_path / "kitti" / "sequences" / "03"), "--max-frames", "2",
                          "--encoding", "jpeg", "--out", str(out)]) == 0
    assert "no ground truth" in capsys.readouterr().out
    msgs, _ = read_recording(out)
    assert len(msgs["rig/stereo/frame"]) == 2 and msgs["rig/stereo/frame"][0].encoding == "jpeg"
    assert "rig/truth/pose" not in msgs


def test_kitti_layout_errors_name_what_is_missing(tmp_path, capsys):
    root = tmp_path / "kitti"
    _kitti(root)
    assert importer.main(["kitti", str(root), "--out", str(tmp_path / "x.mcap")]) == 2
    assert "--sequence" in capsys.readouterr().err
    for p in (root / "sequences" / "03" / "image_1").iterdir():
        p.unlink()
    (root / "sequences" / "03" / "image_1").rmdir()
    assert importer.main(["kitti", str(root), "--sequence", "03", "--out", str(tmp_path / "x.mcap")]) == 2
    err = capsys.readouterr().err
    assert f"KITTI: {root / 'sequences' / '03' / 'image_1'} not found" in err and "Traceback" not in err
    assert not (tmp_path / "x.mcap").exists()


def test_kitti_times_count_mismatch(tmp_path, capsys):
    root = tmp_path / "kitti"
    _kitti(root)
    (root / "sequences" / "03" / "times.txt").write_text("\n".join(TIMES[:3]) + "\n")
    assert importer.main(["kitti", str(root), "--sequence", "03", "--out", str(tmp_path / "x.mcap")]) == 2
    assert "has 3 times for 4 images" in capsys.readouterr().err
