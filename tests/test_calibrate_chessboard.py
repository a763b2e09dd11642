"""`flyslam calibrate` on OpenCV's real stereo chessboard pairs, and its YAML feeding the driver's rectifier."""
from __future__ import annotations

import re
import shutil

import cv2
import numpy as np
import pytest

from common.camera import CalibrationError
from common.chessboard_calibration import calibrate_stereo, find_corners
from common.stereo_rectify import StereoRectifier, load_calibration, load_stereo_yaml
from deploy.commands import calibrate

PATTERN = (9, 6)
# Reference from shared/data/opencv-stereo-chessboard/README.md (25 mm squares).
REF = dict(fx_left=536.07, fx_right=542.35, baseline_mm=83.6, rms_stereo=0.45)


def _near(value, ref, rel=0.10):
    return abs(value - ref) <= rel * abs(ref)


@pytest.fixture(scope="module")
def calibrated(shared_data, tmp_path_factory):
    folder = shared_data / "opencv-stereo-chessboard"
    out = tmp_path_factory.mktemp("calib") / "stereo.yaml"
    argv = ["--left", str(folder / "left*.jpg"), "--right", str(folder / "right*.jpg"), "--board", "9x6",
            "--square-m", "0.025", "--out", str(out)]
    return folder, out, argv


def test_calibrate_matches_opencv_reference(calibrated, capsys):
    folder, out, argv = calibrated
    assert calibrate.main(argv) == 0
    text = capsys.readouterr().out
    assert "pairs used     13 of 13" in text
    fx_left = float(re.search(r"left\s+RMS [\d.]+ px\s+fx ([\d.]+)", text).group(1))
    fx_right = float(re.search(r"right\s+RMS [\d.]+ px\s+fx ([\d.]+)", text).group(1))
    rms = float(re.search(r"stereo RMS ([\d.]+) px", text).group(1))
    baseline_mm = float(re.search(r"baseline ([\d.]+) mm", text).group(1))
    assert _near(fx_left, REF["fx_left"]) and _near(fx_right, REF["fx_right"])
    assert _near(baseline_mm, REF["baseline_mm"])
    assert _near(rms, REF["rms_stereo"])
    # the YAML holds the same numbers, T in metres
    rig = load_stereo_yaml(out)
    assert rig.size == (640, 480)
    assert rig.K1[0, 0] == pytest.approx(fx_left, abs=0.01)
    assert np.linalg.norm(rig.T) * 1000 == pytest.approx(baseline_mm, abs=0.01)


def test_yaml_rectifies_chessboards_onto_common_rows(calibrated):
    folder, out, argv = calibrated
    if not out.exists():
        assert calibrate.main(argv) == 0
    calib = load_calibration(out)
    assert calib.cx_left == pytest.approx(calib.cx_right)  # zero disparity at infinity
    assert _near(calib.baseline, REF["baseline_mm"] / 1000)
    rectifier = StereoRectifier(calib)
    dv = []
    for n in ("01", "05", "09", "13"):
        left = cv2.imread(str(folder / f"left{n}.jpg"), cv2.IMREAD_GRAYSCALE)
        right = cv2.imread(str(folder / f"right{n}.jpg"), cv2.IMREAD_GRAYSCALE)
        rl, rr = rectifier.rectify(left, right)
        cl, cr = find_corners(rl, PATTERN), find_corners(rr, PATTERN)
        assert cl is not None and cr is not None, f"board lost after rectifying pair {n}"
        dv.append(np.abs(cl[:, 0, 1] - cr[:, 0, 1]))
        # every corner lies in front of the rig: positive disparity
        assert np.all(cl[:, 0, 0] - cr[:, 0, 0] > 0)
    dv = np.concatenate(dv)
    assert dv.mean() < 0.5, f"rectified rows differ by {dv.mean():.2f} px on average"
    # unrectified rows differ a lot more: the check above is not trivially true
    raw_l = find_corners(cv2.imread(str(folder / "left01.jpg"), 0), PATTERN)
    raw_r = find_corners(cv2.imread(str(folder / "right01.jpg"), 0), PATTERN)
    assert np.abs(raw_l[:, 0, 1] - raw_r[:, 0, 1]).mean() > 2.0


def test_rejected_pairs_are_reported_and_too_few_is_an_error(shared_data, tmp_path, capsys):
    folder = shared_data / "opencv-stereo-chessboard"
    for n in ("01", "02", "03"):
        shutil.copy(folder / f"left{n}.jpg", tmp_path / f"left{n}.jpg")
        shutil.copy(folder / f"right{n}.jpg", tmp_path / f"right{n}.jpg")
    cv2.imwrite(str(tmp_path / "right02.jpg"), np.full((480, 640), 128, np.uint8))  # no board
    code = calibrate.main(["--left", str(tmp_path / "left*.jpg"), "--right", str(tmp_path / "right*.jpg"),
                           "--square-m", "0.025", "--out", str(tmp_path / "c.yaml")])
    err = capsys.readouterr().err
    assert code == 2
    assert "only 2 usable chessboard pair(s)" in err and "no 9x6 board in the right image" in err
    assert not (tmp_path / "c.yaml").exists()


def test_unequal_image_counts_name_the_globs(tmp_path, capsys):
    for name in ("left1.png", "left2.png", "right1.png"):
        cv2.imwrite(str(tmp_path / name), np.zeros((10, 10), np.uint8))
    code = calibrate.main(["--left", str(tmp_path / "left*.png"), "--right", str(tmp_path / "right*.png"),
                           "--square-m", "0.025", "--out", str(tmp_path / "c.yaml")])
    assert code == 2
    assert "2 left images" in capsys.readouterr().err


def test_calibrate_stereo_rejects_a_size_mismatch(shared_data):
    folder = shared_data / "opencv-stereo-chessboard"
    pairs = []
    for n in ("01", "02", "03", "04"):
        pairs.append((n, cv2.imread(str(folder / f"left{n}.jpg"), 0), cv2.imread(str(folder / f"right{n}.jpg"), 0)))
    pairs.append(("small", pairs[0][1][:240, :320], pairs[0][2][:240, :320]))
    result = calibrate_stereo(pairs, PATTERN, 0.025)
    assert result.used == ["01", "02", "03", "04"]
    assert result.rejected[0][0] == "small" and "differs from the first pair" in result.rejected[0][1]
    with pytest.raises(CalibrationError, match="square size"):
        calibrate_stereo(pairs, PATTERN, -1.0)
