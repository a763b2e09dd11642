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


# --- the real KITTI clip in ../shared/data -------------------------------------------------------------

KITTI_CLIP = "kitti-00-frames-0-99"
# optical (x right, y down, z forward) → REP-103 body (x forward, y left, z up), written out independently
C_BODY_FROM_OPTICAL = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]], float)
# base_link on the road, 1.65 m under the left camera (KITTI's mounting)
MOUNT = C_BODY_FROM_OPTICAL.copy()
MOUNT[2, 3] = 1.65


@pytest.fixture(scope="module")
def real_root(shared_data):
    root = shared_data / KITTI_CLIP
    if not (root / "sequences" / "00").is_dir():
        pytest.skip(f"{root} not found (the shared real KITTI clip)")
    return root


@pytest.fixture(scope="module")
def real_slice(real_root, tmp_path_factory):
    """The clip's first 20 frames imported with `flyslam import kitti`, and run_lockstep's result on them."""
    from common.lockstep import run_lockstep
    out = tmp_path_factory.mktemp("kitti_real") / "k00_20.mcap"
    assert importer.main(["kitti", str(real_root / "sequences" / "00"), "--max-frames", "20", "--out", str(out)]) == 0
    return out, run_lockstep(RecordingReader(out).messages())


def test_real_calib_times_and_poses_match_the_files(real_root):
    from common.importers.kitti import load_kitti
    seq = real_root / "sequences" / "00"
    ds = load_kitti(seq)
    c = ds.calibration
    assert (c.width, c.height) == (1241, 376)
    assert (c.fx, c.fy, c.cx_left, c.cx_right, c.cy) == (718.856, 718.856, 607.1928, 607.1928, 185.2157)
    assert c.baseline == pytest.approx(386.1448 / 718.856, rel=1e-12) and c.baseline == pytest.approx(0.537, abs=1e-3)
    times = np.loadtxt(seq / "times.txt")
    assert len(ds.stamps_ns) == len(times) == 100
    assert np.array_equal(ds.stamps_ns, np.round(times * 1e9).astype(np.int64))
    assert np.array_equal(ds.truth_stamps_ns, ds.stamps_ns)
    rows = np.loadtxt(real_root / "poses" / "00.txt").reshape(-1, 3, 4)
    T_w_cam = np.tile(np.eye(4), (len(rows), 1, 1))
    T_w_cam[:, :3] = rows
    expected = MOUNT @ np.linalg.inv(T_w_cam[0]) @ T_w_cam @ np.linalg.inv(MOUNT)
    assert np.allclose(ds.truth_poses, expected, atol=1e-9)
    # the README's description of the drive, in REP-103: 83.9 m ahead (+x), 5.0 m to the left (+y)
    assert ds.truth_poses[99][:2, 3] == pytest.approx((83.9, 5.0), abs=0.1)


def test_real_slice_imports_losslessly_with_its_truth(real_root, real_slice):
    out, _ = real_slice
    msgs, calib_payload = read_recording(out)
    assert calibration_from_msg(decode(calib_payload, StereoCalibrationMsg)).fx == 718.856
    frames, truth = msgs["rig/stereo/frame"], msgs["rig/truth/pose"]
    assert len(frames) == len(truth) == 20
    seq = real_root / "sequences" / "00"
    for k in (0, 19):
        left, right = frame_images(frames[k])
        assert np.array_equal(left, cv2.imread(str(seq / "image_0" / f"{k:06d}.png"), cv2.IMREAD_UNCHANGED))
        assert np.array_equal(right, cv2.imread(str(seq / "image_1" / f"{k:06d}.png"), cv2.IMREAD_UNCHANGED))
    rows = np.loadtxt(real_root / "poses" / "00.txt")
    for k in (1, 19):   # poses/00.txt row 0 is the identity, so row k is the camera's motion since frame 0
        T = np.eye(4)
        T[:3] = rows[k].reshape(3, 4)
        assert np.allclose(transform_of(truth[k]), MOUNT @ T @ np.linalg.inv(MOUNT),
                           atol=1e-6)


def test_real_slice_evaluates_end_to_end(real_slice):
    from common.trajectory_metrics import evaluate
    _, result = real_slice
    assert result.frames == len(result.estimated) == 20
    assert result.stamps == result.truth_stamps
    assert all(np.isfinite(T).all() for T in result.estimated)
    metrics = evaluate(result.stamps, result.estimated, result.truth_stamps, result.truth)
    assert metrics.poses == 20 and metrics.path_length_m == pytest.approx(16.4, abs=0.5)


def test_real_slice_estimate_moves_forward_with_the_car(real_slice):
    _, result = real_slice
    travelled = np.linalg.norm(result.estimated[-1][:3, 3] - result.estimated[0][:3, 3])
    truth = np.linalg.norm(result.truth[-1][:3, 3] - result.truth[0][:3, 3])
    assert travelled == pytest.approx(truth, rel=0.2)


@pytest.fixture
def real_copy(real_root, tmp_path):
    """A 3-frame KITTI layout in tmp_path made of the real clip's files (images, calib, first times and poses)."""
    src, root = real_root / "sequences" / "00", tmp_path / "kitti"
    seq = root / "sequences" / "00"
    for cam in ("image_0", "image_1"):
        (seq / cam).mkdir(parents=True)
        for k in range(3):
            (seq / cam / f"{k:06d}.png").write_bytes((src / cam / f"{k:06d}.png").read_bytes())
    (seq / "calib.txt").write_text((src / "calib.txt").read_text())
    (seq / "times.txt").write_text("".join((src / "times.txt").read_text().splitlines(keepends=True)[:3]))
    (root / "poses").mkdir()
    (root / "poses" / "00.txt").write_text(
        "".join((real_root / "poses" / "00.txt").read_text().splitlines(keepends=True)[:3]))
    return seq


def _drop_right_frame(seq):
    (seq / "image_1" / "000001.png").unlink()
    return seq / "image_1" / "000001.png"


def _drop_p1(seq):
    calib = seq / "calib.txt"
    calib.write_text("".join(l for l in calib.read_text().splitlines(keepends=True) if not l.startswith("P1:")))
    return calib


def _garble_times(seq):
    times = seq / "times.txt"
    lines = times.read_text().splitlines()
    lines[1] = "0.1 s"
    times.write_text("\n".join(lines) + "\n")
    return f"{times}:2"


@pytest.mark.parametrize("breakage, says", [(_drop_right_frame, "not found"), (_drop_p1, "P1"),
                                            (_garble_times, "is not a time")])
def test_real_copy_bad_layout_is_one_line_naming_the_file(real_copy, tmp_path, capsys, breakage, says):
    out = tmp_path / "x.mcap"
    assert importer.main(["kitti", str(real_copy), "--out", str(out)]) == 0   # the unbroken copy imports
    capsys.readouterr()
    out.unlink()
    named = breakage(real_copy)
    assert importer.main(["kitti", str(real_copy), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err
    assert str(named) in err and says in err
    assert not out.exists()


def test_real_slice_tracks_alike_when_the_calibration_keeps_the_raw_cameras_intrinsics(real_slice):
    """A calibration made by ``flyslam calibrate`` keeps the raw cameras' K (and distortion) beside the
    rectified projection the images were rectified to. Tracking uses the rectified one: the same images
    with a raw K that differs by a few pixels and per cent must give the same trajectory."""
    from dataclasses import replace

    from common.lockstep import run_lockstep
    from common.messages import calibration_to_msg, encode
    from common.recording import RecordedMessage
    from common.trajectory_metrics import evaluate
    out, rectified = real_slice
    raw_K = np.array([[718.856 * 1.03, 0.0, 607.19 + 25.0], [0.0, 718.856 * 1.03, 185.22 - 12.0], [0.0, 0.0, 1.0]])

    def with_raw_K():
        for rec in RecordingReader(out).messages():
            if rec.key.endswith("stereo/calibration"):
                msg = decode(rec.payload)
                calib = replace(calibration_from_msg(msg), K_left=raw_K, D_left=np.array([-0.3, 0.1, 0.0, 0.0, 0.0]))
                payload = encode(calibration_to_msg(calib, msg.header.seq, msg.header.stamp_ns))
                rec = RecordedMessage(rec.key, rec.schema, rec.log_time_ns, rec.publish_time_ns, payload)
            yield rec

    raw = run_lockstep(with_raw_K())
    ate = [evaluate(r.stamps, r.estimated, r.truth_stamps, r.truth).ate_rmse_m for r in (rectified, raw)]
    assert ate[1] == pytest.approx(ate[0], abs=0.02), ate


def test_kitti_colour_download_is_read_when_the_grey_one_is_absent(tmp_path):
    """KITTI's colour download has image_2/image_3 and rows P2/P3 only: read in colour, calibrated from
    P2/P3, its truth carried from grey camera 0 (the poses' camera) to colour camera 2 beside it."""
    from common.importers.kitti import load_kitti

    root = tmp_path / "kitti"
    _kitti(root)
    seq = root / "sequences" / "03"
    offset = 0.06                                            # camera 2 sits 6 cm right of camera 0
    P2 = [FX, 0, CX, -FX * offset, 0, FX, CY, 0, 0, 0, 1, 0]
    P3 = [FX, 0, CX, -FX * (offset + 0.5), 0, FX, CY, 0, 0, 0, 1, 0]
    row = lambda v: " ".join(f"{x:.12e}" for x in v)  # noqa: E731
    (seq / "calib.txt").write_text(f"P2: {row(P2)}\nP3: {row(P3)}\n")
    for grey, colour in (("image_0", "image_2"), ("image_1", "image_3")):
        (seq / colour).mkdir()
        for p in sorted((seq / grey).iterdir()):
            cv2.imwrite(str(seq / colour / p.name), cv2.cvtColor(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE),
                                                                  cv2.COLOR_GRAY2BGR))
            p.unlink()
        (seq / grey).rmdir()
    ds = load_kitti(root, sequence="03")
    assert ds.calibration.baseline == pytest.approx(0.5) and ds.calibration.fx == FX
    left, right = ds.load_pair(0)
    assert left.shape == (H, W, 3) and right.shape == (H, W, 3)
    grey_truth = _camera_poses()
    for k in (1, N - 1):   # camera 2's motion: camera 0's seen from 6 cm to its right (optical +x)
        c0 = np.linalg.inv(grey_truth[0]) @ grey_truth[k]
        shift = make_transform(np.eye(3), [offset, 0.0, 0.0])
        c2 = np.linalg.inv(shift) @ c0 @ shift
        moved = np.linalg.inv(ds.truth_poses[0]) @ ds.truth_poses[k]
        assert np.linalg.norm(moved[:3, 3]) == pytest.approx(np.linalg.norm(c2[:3, 3]), abs=1e-6)
        assert np.linalg.norm(c2[:3, 3] - c0[:3, 3]) > 1e-3          # (the test can tell the two apart)


def test_an_interrupted_import_leaves_no_recording_that_passes_for_the_whole_sequence(real_root, tmp_path):
    """Ctrl-C half-way through the real clip: exit 130 and no k.mcap (it held the first frames, finalised,
    and looked like the whole sequence)."""
    import signal
    import subprocess
    import sys

    from tests.helpers import ROOT

    out = tmp_path / "k.mcap"
    proc = subprocess.Popen([sys.executable, "-m", "deploy.cli", "import", "kitti", str(real_root), "--sequence", "00",
                             "--out", str(out)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    for line in proc.stdout:
        if line.startswith("frames ") and int(line.split()[1].split("/")[0]) >= 5:
            proc.send_signal(signal.SIGINT)
            break
    text, _ = proc.communicate(timeout=60)
    assert proc.returncode == 130, text
    assert "interrupted" in text and not out.exists()
