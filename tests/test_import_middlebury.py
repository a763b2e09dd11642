"""`flyslam import middlebury` on a small synthetic scene in the Middlebury 2014 layout."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.images import frame_images
from common.importers.middlebury import read_pfm
from common.messages import DepthImage, StereoCalibrationMsg, calibration_from_msg, decode, transform_of
from common.recording import RecordingReader
from deploy.commands import importer

W, H = 80, 60
F, CX0, CY, DOFFS, BASELINE_MM = 120.0, 39.5, 29.5, 6.0, 193.001


def _write_pfm(path, img: np.ndarray):
    """Little-endian greyscale PFM, rows bottom to top (as the format says)."""
    with open(path, "wb") as f:
        f.write(f"Pf\n{img.shape[1]} {img.shape[0]}\n-1\n".encode())
        f.write(np.ascontiguousarray(img[::-1], dtype="<f4").tobytes())


def _disparity() -> np.ndarray:
    """Disparity growing down the image (nearer at the bottom), unknown in the top-left corner."""
    d = np.repeat(np.linspace(10, 40, H, dtype=np.float32)[:, None], W, axis=1)
    d[:5, :5] = np.inf
    return d


def _scene(folder, calib_lines=None):
    folder.mkdir()
    rng = np.random.default_rng(5)
    left, right = rng.integers(0, 256, (2, H, W, 3), dtype=np.uint8)
    cv2.imwrite(str(folder / "im0.png"), left)
    cv2.imwrite(str(folder / "im1.png"), right)
    lines = calib_lines or [f"cam0=[{F} 0 {CX0}; 0 {F} {CY}; 0 0 1]", f"cam1=[{F} 0 {CX0 + DOFFS}; 0 {F} {CY}; 0 0 1]",
                            f"doffs={DOFFS}", f"baseline={BASELINE_MM}", f"width={W}", f"height={H}", "ndisp=64",
                            "isint=0", "vmin=10", "vmax=40", "dyavg=0", "dymax=0"]
    (folder / "calib.txt").write_text("\n".join(lines) + "\n")
    _write_pfm(folder / "disp0.pfm", _disparity())
    return cv2.cvtColor(left, cv2.COLOR_BGR2RGB), cv2.cvtColor(right, cv2.COLOR_BGR2RGB)


def _read(path):
    reader = RecordingReader(path)
    msgs = {}
    for m in reader.messages():
        msgs.setdefault(m.key, []).append(decode(m.payload))
    return msgs, calibration_from_msg(decode(reader.calibration_payload(), StereoCalibrationMsg))


def test_pfm_reader_keeps_row_order(tmp_path):
    d = _disparity()
    _write_pfm(tmp_path / "d.pfm", d)
    back = read_pfm(tmp_path / "d.pfm")
    assert back.shape == (H, W) and np.array_equal(back, d)


def test_middlebury_round_trip_with_depth_truth(tmp_path, capsys):
    left, right = _scene(tmp_path / "Toy-perfect")
    out = tmp_path / "toy.mcap"
    assert importer.main(["middlebury", str(tmp_path / "Toy-perfect"), "--repeat", "3", "--out", str(out)]) == 0
    assert "3 depth images" in capsys.readouterr().out
    msgs, calib = _read(out)
    assert (calib.width, calib.height, calib.fx, calib.cx_left, calib.cy) == (W, H, F, CX0, CY)
    assert calib.doffs == pytest.approx(DOFFS) and calib.baseline == pytest.approx(BASELINE_MM / 1000)

    frames = msgs["rig/stereo/frame"]
    assert [f.header.stamp_ns for f in frames] == [0, 100_000_000, 200_000_000]
    got_l, got_r = frame_images(frames[0])
    assert np.array_equal(got_l, left) and np.array_equal(got_r, right)

    depths = msgs["rig/truth/depth"]
    assert len(depths) == 3 and all(isinstance(d, DepthImage) for d in depths)
    z = depths[0].depth
    d = _disparity()
    known = np.isfinite(d)
    assert np.allclose(z[known], (BASELINE_MM / 1000) * F / (d[known] + DOFFS), rtol=1e-6)
    assert np.all(np.isinf(z[~known]))
    assert z[-1, 40] < z[10, 40]  # bottom rows are nearer: the PFM was not read upside down
    # the depth agrees with the calibration's own disparity model
    assert np.allclose(calib.depth_from_disparity(d[known]), z[known], rtol=1e-6)

    poses = msgs["rig/truth/pose"]
    assert len(poses) == 3 and all(np.allclose(transform_of(p), np.eye(4)) for p in poses)


def test_middlebury_scale(tmp_path):
    _scene(tmp_path / "Toy")
    out = tmp_path / "half.mcap"
    assert importer.main(["middlebury", str(tmp_path / "Toy"), "--scale", "0.5", "--out", str(out)]) == 0
    msgs, calib = _read(out)
    assert (calib.width, calib.height, calib.fx) == (W // 2, H // 2, F / 2)
    assert calib.baseline == pytest.approx(BASELINE_MM / 1000)
    left, _ = frame_images(msgs["rig/stereo/frame"][0])
    z = msgs["rig/truth/depth"][0].depth
    assert left.shape == (H // 2, W // 2, 3) and z.shape == (H // 2, W // 2)
    # metres do not scale: the depth of a known row stays what the full-size disparity says
    assert z[20, 10] == pytest.approx((BASELINE_MM / 1000) * F / (_disparity()[40, 20] + DOFFS), rel=0.05)


def test_middlebury_layout_errors(tmp_path, capsys):
    _scene(tmp_path / "A")
    (tmp_path / "A" / "im1.png").unlink()
    assert importer.main(["middlebury", str(tmp_path / "A"), "--out", str(tmp_path / "x.mcap")]) == 2
    assert f"Middlebury: {tmp_path / 'A' / 'im1.png'} not found" in capsys.readouterr().err
    _scene(tmp_path / "B", calib_lines=[f"cam0=[{F} 0 {CX0}; 0 {F} {CY}; 0 0 1]", f"width={W}", f"height={H}"])
    assert importer.main(["middlebury", str(tmp_path / "B"), "--out", str(tmp_path / "x.mcap")]) == 2
    assert "has no cam1, doffs, baseline" in capsys.readouterr().err
