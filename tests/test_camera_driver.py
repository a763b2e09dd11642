"""The stereo camera driver on video files: raw distorted pairs in, the rectified truth out.

The fixture renders a rectified textured scene (constant disparity), *un*-rectifies it through a known
raw rig (distortion, a small rotation between the cameras) into two MJPG videos, and writes the rig as
an OpenCV stereo_calib-style YAML (M1/D1/M2/D2/R/T, T in centimetres). The driver must recover the
rectified images and the rig's calibration.
"""
from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from common.calibration_files import load_rig
from common.geometry import make_transform, rot_x, rot_y
from common.images import frame_images
from common.messages import StereoFrame, calibration_from_msg, calibration_to_msg, decode, encode
from common.stereo_rectify import RawStereoRig, StereoRectifier, load_calibration, rectify_rig
from services import camera

W, H, N_FRAMES, DISPARITY = 320, 240, 5, 8


def _rig() -> RawStereoRig:
    K1 = np.array([[300.0, 0, 158], [0, 302, 121], [0, 0, 1]])
    K2 = np.array([[305.0, 0, 163], [0, 304, 118], [0, 0, 1]])
    return RawStereoRig(W, H, K1, [-0.12, 0.03, 0.001, -0.0005, 0], K2, [-0.09, 0.02, 0, 0.001, 0],
                        rot_y(0.03) @ rot_x(-0.01), [-0.10, 0.003, 0.002])


def _texture(seed: int, h: int, w: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (h, w, 3)).astype(np.float32), (0, 0), 2.5)
    img = (img - img.min()) / (img.max() - img.min()) * 230 + 10
    return img.astype(np.uint8)


def _truth_pairs():
    """Rectified (left, right) RGB pairs: the texture slides 3 px per frame; right = left shifted by d."""
    big = _texture(1, H, W + DISPARITY + 3 * N_FRAMES)
    out = []
    for i in range(N_FRAMES):
        left = big[:, 3 * i: 3 * i + W]
        right = big[:, 3 * i + DISPARITY: 3 * i + DISPARITY + W]
        out.append((np.ascontiguousarray(left), np.ascontiguousarray(right)))
    return out


def _unrectify(rect: np.ndarray, rectifier: StereoRectifier, which: str) -> np.ndarray:
    """Raw camera image whose rectification is ``rect``: look up every raw pixel's rectified position."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rect_uv = rectifier.rectify_points(np.stack([u.ravel(), v.ravel()], 1), which)
    mx = rect_uv[:, 0].reshape(H, W).astype(np.float32)
    my = rect_uv[:, 1].reshape(H, W).astype(np.float32)
    return cv2.remap(rect, mx, my, cv2.INTER_LINEAR)


def _write_video(path, frames_rgb):
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (frames_rgb[0].shape[1], frames_rgb[0].shape[0]))
    assert w.isOpened()
    for f in frames_rgb:
        w.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    w.release()


def _write_opencv_yaml(path, rig: RawStereoRig, width=W, height=H, t_scale=100.0, units=True, size=True):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if size:
        fs.write("image_width", width)
        fs.write("image_height", height)
    for name, value in (("M1", rig.K1), ("D1", rig.D1.reshape(1, -1)), ("M2", rig.K2),
                        ("D2", rig.D2.reshape(1, -1)), ("R", rig.R), ("T", rig.T.reshape(3, 1) * t_scale)):
        fs.write(name, value)
    if units:
        fs.write("units_m", 1.0 / t_scale)
    fs.release()


@pytest.fixture(scope="module")
def videos(tmp_path_factory):
    d = tmp_path_factory.mktemp("camera")
    rig = _rig()
    rectifier = StereoRectifier(rectify_rig(rig))
    truth = _truth_pairs()
    raw_l = [_unrectify(l, rectifier, "left") for l, _ in truth]
    raw_r = [_unrectify(r, rectifier, "right") for _, r in truth]
    _write_video(d / "left.avi", raw_l)
    _write_video(d / "right.avi", raw_r)
    _write_video(d / "sbs.avi", [np.hstack([l, r]) for l, r in zip(raw_l, raw_r)])
    _write_opencv_yaml(d / "stereo.yaml", rig)
    return d, rig, truth


def _interior_error(a, b, margin=10):
    return np.abs(a.astype(float) - b.astype(float))[margin:-margin, margin:-margin].mean()


def test_driver_recovers_rectified_frames_and_calibration(videos):
    d, rig, truth = videos
    calib = load_calibration(d / "stereo.yaml")
    expected = rectify_rig(rig)
    assert calib.baseline == pytest.approx(np.linalg.norm(rig.T), rel=1e-3)  # T given in cm, read in m
    assert calib.fx == pytest.approx(expected.fx) and calib.cx_left == pytest.approx(expected.cx_left)

    capture = camera.StereoCapture(calib, left=str(d / "left.avi"), right=str(d / "right.avi"))
    pipeline = camera.StereoPipeline(calib, "rgb8")
    frames = []
    while (pair := capture.read()) is not None:
        frames.append(decode(encode(pipeline.frame(*pair, seq=len(frames) + 1, stamp_ns=123)), StereoFrame))
    capture.close()
    assert len(frames) == N_FRAMES
    for msg, (tl, tr) in zip(frames, truth):
        left, right = frame_images(msg)
        assert left.shape == (H, W, 3)
        assert _interior_error(left, tl) < 6 and _interior_error(right, tr) < 6
    # the raw images are far from the truth: the comparison above is not trivially satisfied
    raw = cv2.cvtColor(cv2.VideoCapture(str(d / "left.avi")).read()[1], cv2.COLOR_BGR2RGB)
    assert _interior_error(raw, truth[0][0]) > 4 * _interior_error(frame_images(frames[0])[0], truth[0][0])

    # the calibration the driver publishes survives the wire
    back = calibration_from_msg(decode(encode(calibration_to_msg(calib)), type(calibration_to_msg(calib))))
    assert back.fx == pytest.approx(calib.fx) and back.baseline == pytest.approx(calib.baseline)
    assert np.allclose(back.D_left, rig.D1) and np.allclose(back.R_left, calib.R_left)


def test_side_by_side_jpeg_and_loop(videos):
    d, _, truth = videos
    calib = load_calibration(d / "stereo.yaml")
    capture = camera.StereoCapture(calib, sbs=str(d / "sbs.avi"), loop=True)
    pipeline = camera.StereoPipeline(calib, "jpeg", quality=95)
    pairs = [capture.read() for _ in range(N_FRAMES + 2)]  # loops past the end
    capture.close()
    assert all(p is not None for p in pairs)
    left, right = frame_images(pipeline.frame(*pairs[N_FRAMES + 1], seq=1, stamp_ns=0))  # = frame 1 again
    assert _interior_error(left, truth[1][0]) < 7 and _interior_error(right, truth[1][1]) < 7


def _run_main(capsys, argv):
    code = camera.main(argv)
    err = capsys.readouterr().err
    return code, err


def test_wrong_resolution_is_a_clear_error(videos, tmp_path, capsys):
    d, rig, _ = videos
    _write_opencv_yaml(tmp_path / "vga.yaml", rig, width=640, height=480)
    code, err = _run_main(capsys, ["--left", str(d / "left.avi"), "--right", str(d / "right.avi"),
                                   "-c", str(tmp_path / "vga.yaml")])
    assert code == 2
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err
    assert str(d / "left.avi") in lines[0] and "320×240" in lines[0] and "640×480" in lines[0]


def test_missing_file_and_unknown_units_are_clear_errors(videos, tmp_path, capsys):
    d, rig, _ = videos
    code, err = _run_main(capsys, ["--left", str(tmp_path / "nope.avi"), "--right", str(d / "right.avi"),
                                   "-c", str(d / "stereo.yaml")])
    assert code == 2 and f"video file {tmp_path / 'nope.avi'} not found" in err
    _write_opencv_yaml(tmp_path / "squares.yaml", rig, units=False)
    code, err = _run_main(capsys, ["--sbs", str(d / "sbs.avi"), "-c", str(tmp_path / "squares.yaml")])
    assert code == 2 and "units_m" in err and "Traceback" not in err
    # with --units-m the same file is accepted (T was written in centimetres)
    calib = load_calibration(tmp_path / "squares.yaml", units_m=0.01)
    assert calib.baseline == pytest.approx(np.linalg.norm(rig.T), rel=1e-3)


def test_a_calibration_without_image_size_takes_it_from_the_camera(videos, tmp_path, capsys):
    # OpenCV's stereo_calib sample writes no image size: the source's frames give it
    d, rig, truth = videos
    _write_opencv_yaml(tmp_path / "sample.yml", rig, size=False, units=False)
    src = dict(left=str(d / "left.avi"), right=str(d / "right.avi"), sbs=None)
    calib = load_rig([tmp_path / "sample.yml"], units_m=0.01,
                     image_size=lambda: camera.source_frame_size(**src)).calibration
    assert (calib.width, calib.height) == (W, H)
    _assert_plays_the_truth(camera.StereoCapture(calib, **src), camera.StereoPipeline(calib, "rgb8"), truth)
    sbs = load_rig([tmp_path / "sample.yml"], units_m=0.01,
                   image_size=lambda: camera.source_frame_size(None, None, str(d / "sbs.avi"))).calibration
    assert (sbs.width, sbs.height) == (W, H)
    # a calibration made at twice the resolution does not fit these frames: said, not used
    big = RawStereoRig(width=2 * W, height=2 * H, K1=rig.K1 * [[2], [2], [1]], D1=rig.D1, K2=rig.K2 * [[2], [2], [1]],
                       D2=rig.D2, R=rig.R, T=rig.T)
    small = RawStereoRig(width=W // 2, height=H // 2, K1=rig.K1 * [[0.5], [0.5], [1]], D1=rig.D1,
                         K2=rig.K2 * [[0.5], [0.5], [1]], D2=rig.D2, R=rig.R, T=rig.T)
    for name, other in (("big.yml", big), ("small.yml", small)):     # made at twice or half the resolution
        _write_opencv_yaml(tmp_path / name, other, size=False)
        code, err = _run_main(capsys, ["--left", src["left"], "--right", src["right"], "-c", str(tmp_path / name)])
        assert code == 2 and "principal point" in err and f"{W}×{H}" in err and "Traceback" not in err, err


def _assert_plays_the_truth(capture, pipeline, truth):
    """Every pair the capture gives, rectified by the pipeline, is the rectified truth, in order."""
    frames = []
    while (pair := capture.read()) is not None:
        frames.append(pipeline.frame(*pair, seq=len(frames) + 1, stamp_ns=0))
    capture.close()
    assert len(frames) == N_FRAMES
    for msg, (tl, tr) in zip(frames, truth):
        left, right = frame_images(msg)
        assert _interior_error(left, tl) < 6 and _interior_error(right, tr) < 6


def _numbers(a) -> str:
    return "[" + ", ".join(repr(float(v)) for v in np.ravel(a)) + "]"


def _write_kalibr(path, rig: RawStereoRig):
    """The rig as Kalibr writes it: radtan k1 k2 p1 p2, cam0 → cam1 as T_cn_cnm1 (x_cam1 = T·x_cam0)."""
    T = make_transform(rig.R, rig.T.ravel())
    cams = []
    for name, K, D in (("cam0", rig.K1, rig.D1), ("cam1", rig.K2, rig.D2)):
        extra = "".join(f"  - {_numbers(row)}\n" for row in T) if name == "cam1" else ""
        cams.append(f"{name}:\n" + (f"  T_cn_cnm1:\n{extra}" if extra else "") +
                    f"  camera_model: pinhole\n  distortion_coeffs: {_numbers(D[:4])}\n"
                    f"  distortion_model: radtan\n  intrinsics: {_numbers([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])}\n"
                    f"  resolution: [{W}, {H}]\n  rostopic: /{name}/image_raw\n")
    path.write_text("".join(cams))
    return path


def _write_camera_info(d, rig: RawStereoRig, echo: bool = False):
    """The rig as ROS's camera_calibration writes it (left.yaml and right.yaml: K, D raw; R, P rectified),
    or with ``echo`` as ``ros2 topic echo --once`` prints each camera's CameraInfo message."""
    rect = rectify_rig(rig)
    paths = []
    for side, K, D, R, P in (("left", rig.K1, rig.D1, rect.R_left, rect.P_left),
                             ("right", rig.K2, rig.D2, rect.R_right, rect.P_right)):
        path = d / f"{side}.yaml"
        if echo:
            rows = lambda a: "".join(f"- {float(v)!r}\n" for v in np.ravel(a))  # noqa: E731
            path.write_text(
                f"header:\n  stamp:\n    sec: 0\n    nanosec: 0\n  frame_id: {side}\nheight: {H}\nwidth: {W}\n"
                f"distortion_model: plumb_bob\nd:\n{rows(D)}k:\n{rows(K)}r:\n{rows(R)}p:\n{rows(P)}"
                "binning_x: 0\nbinning_y: 0\nroi:\n  x_offset: 0\n  y_offset: 0\n  height: 0\n  width: 0\n"
                "  do_rectify: false\n---\n")
        else:
            path.write_text(
                f"image_width: {W}\nimage_height: {H}\ncamera_name: {side}\n"
                f"camera_matrix:\n  rows: 3\n  cols: 3\n  data: {_numbers(K)}\n"
                f"distortion_model: plumb_bob\n"
                f"distortion_coefficients:\n  rows: 1\n  cols: {np.size(D)}\n  data: {_numbers(D)}\n"
                f"rectification_matrix:\n  rows: 3\n  cols: 3\n  data: {_numbers(R)}\n"
                f"projection_matrix:\n  rows: 3\n  cols: 4\n  data: {_numbers(P)}\n")
        paths.append(path)
    return paths


@pytest.mark.parametrize("fmt", ["kalibr", "camera_info", "camera_info_echo"])
def test_a_kalibr_camchain_or_ros_camera_info_files_drive_the_camera_as_well(videos, tmp_path, fmt):
    # the same raw rig, calibrated with Kalibr or ROS's camera_calibration instead of flyslam's, or as its
    # driver publishes it
    d, rig, truth = videos
    files = [_write_kalibr(tmp_path / "camchain.yaml", rig)] if fmt == "kalibr" else \
        _write_camera_info(tmp_path, rig, echo=fmt.endswith("echo"))
    loaded = load_rig(files)
    assert ("Kalibr camchain" if fmt == "kalibr" else "ROS camera_info") in loaded.source
    assert loaded.calibration.baseline == pytest.approx(np.linalg.norm(rig.T), rel=1e-3)
    capture = camera.StereoCapture(loaded.calibration, left=str(d / "left.avi"), right=str(d / "right.avi"))
    _assert_plays_the_truth(capture, camera.StereoPipeline(loaded, "rgb8"), truth)


def test_calibration_files_of_another_format_give_one_line_errors(videos, tmp_path, capsys):
    d, rig, _ = videos
    left_yaml, _ = _write_camera_info(tmp_path, rig)
    source = ["--left", str(d / "left.avi"), "--right", str(d / "right.avi")]
    code, err = _run_main(capsys, [*source, "-c", str(left_yaml)])      # the right camera's file forgotten
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert str(left_yaml) in err and "two files" in err
    right_yaml = tmp_path / "right.yaml"
    right_yaml.write_text(right_yaml.read_text().split("projection_matrix")[0])     # cut short
    code, err = _run_main(capsys, [*source, "-c", str(left_yaml), "-c", str(right_yaml)])
    assert code == 2 and len(err.strip().splitlines()) == 1 and f"{right_yaml} has no projection_matrix" in err
    camchain = _write_kalibr(tmp_path / "camchain.yaml", rig)
    camchain.write_text(camchain.read_text().replace("resolution", "resolutoin"))
    code, err = _run_main(capsys, [*source, "-c", str(camchain)])
    assert code == 2 and len(err.strip().splitlines()) == 1 and str(camchain) in err and "resolution" in err


def _write_images(folder, frames_rgb, names):
    folder.mkdir()
    for name, f in zip(names, frames_rgb):
        assert cv2.imwrite(str(folder / name), cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    return folder


@pytest.fixture(scope="module")
def image_folders(videos):
    """The videos' raw frames as PNG files, numbered unpadded from 8 (8 ... 12: natural order matters)."""
    d, _, _ = videos
    left, right = (cv2.VideoCapture(str(d / f"{side}.avi")) for side in ("left", "right"))
    frames = [(cv2.cvtColor(left.read()[1], cv2.COLOR_BGR2RGB), cv2.cvtColor(right.read()[1], cv2.COLOR_BGR2RGB))
              for _ in range(N_FRAMES)]
    names = [f"{i}.png" for i in range(8, 8 + N_FRAMES)]
    return (_write_images(d / "left_images", [f[0] for f in frames], [f"left_{n}" for n in names]),
            _write_images(d / "right_images", [f[1] for f in frames], names))


def test_image_folders_play_as_a_camera_in_their_natural_order(videos, image_folders):
    d, _, truth = videos
    left_dir, right_dir = image_folders
    calib = load_calibration(d / "stereo.yaml")
    # a glob pattern for one side, a folder for the other
    capture = camera.StereoCapture(calib, left=str(left_dir / "left_*.png"), right=str(right_dir))
    assert capture.is_file and capture.is_sequence and capture.fps == 0
    _assert_plays_the_truth(capture, camera.StereoPipeline(calib, "rgb8"), truth)   # 8, 9, 10, 11, 12 in order


def test_image_folders_need_a_rate_and_matching_counts(videos, image_folders, tmp_path, capsys):
    d, _, _ = videos
    left_dir, right_dir = image_folders
    calib = ["-c", str(d / "stereo.yaml")]
    code, err = _run_main(capsys, ["--left", str(left_dir), "--right", str(right_dir), *calib])
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--fps" in err and str(left_dir) in err
    fewer = tmp_path / "fewer"
    fewer.mkdir()
    for f in sorted(right_dir.iterdir())[:-1]:
        (fewer / f.name).write_bytes(f.read_bytes())
    code, err = _run_main(capsys, ["--left", str(left_dir), "--right", str(fewer), "--fps", "10", *calib])
    assert code == 2 and len(err.strip().splitlines()) == 1 and "5 images" in err and "4" in err
    code, err = _run_main(capsys, ["--left", str(tmp_path / "none_*.png"), "--right", str(right_dir), "--fps", "10",
                                   *calib])
    assert code == 2 and "no image files" in err and "Traceback" not in err


def test_swapped_cameras_are_refused(videos, tmp_path):
    d, rig, _ = videos
    swapped = RawStereoRig(W, H, rig.K2, rig.D2, rig.K1, rig.D1, rig.R.T, -rig.R.T @ rig.T)
    with pytest.raises(ValueError, match="swap the left and right"):
        rectify_rig(swapped)


def test_camera_process_publishes_frames_and_latched_calibration(videos, zenoh_port, tmp_path):
    from common.bus import BusOptions, Node
    from common.messages import StereoCalibrationMsg
    from tests.helpers import hub, start_module, stop, wait_until

    d, rig, truth = videos
    proc = start_module("services.camera", "--left", str(d / "left.avi"), "--right", str(d / "right.avi"),
                        "-c", str(d / "stereo.yaml"), "--fps", "20", "--loop", "--encoding", "jpeg",
                        port=zenoh_port, log_path=tmp_path / "camera.log")
    try:
        with Node("camera-test", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
            frames = node.subscribe_latest("stereo/frame", StereoFrame)
            got = []
            assert wait_until(lambda: (m := frames.take()) is not None and not got.append(m), timeout=15), \
                (tmp_path / "camera.log").read_text()
            cal = node.query_latest("stereo/calibration", StereoCalibrationMsg, timeout=2.0)  # a late joiner
            assert cal is not None
            assert calibration_from_msg(cal).baseline == pytest.approx(np.linalg.norm(rig.T), rel=1e-3)
            left, _ = frame_images(got[0])
            assert left.shape == (H, W, 3) and got[0].encoding == "jpeg"
            assert min(_interior_error(left, tl) for tl, _ in truth) < 7
    finally:
        code = stop(proc)
    assert code == 0, (tmp_path / "camera.log").read_text()


class _SlowNode:
    """A bus node stand-in whose frame publisher takes 2.5 frame periods (a busy machine)."""
    stopping, progress = False, 0

    def __init__(self):
        self.frames = []

    def publisher(self, stream):
        node = self

        class Pub:
            def has_subscribers(self):
                return True

            def publish(self, msg):
                if isinstance(msg, StereoFrame):
                    node.frames.append(msg)
                    time.sleep(0.25)
        return Pub()

    def sleep(self, seconds):
        time.sleep(seconds)
        return True


def test_a_video_played_as_a_camera_on_a_busy_machine_drops_frames_and_keeps_their_times(videos):
    d, _, truth = videos
    calib = load_calibration(d / "stereo.yaml")
    capture = camera.StereoCapture(calib, left=str(d / "left.avi"), right=str(d / "right.avi"))
    node = _SlowNode()
    assert camera.publish_loop(node, capture, camera.StereoPipeline(calib, "rgb8"), 10.0, 60.0) == 0
    capture.close()
    assert 2 <= len(node.frames) < N_FRAMES                # late frames were skipped, not queued
    for msg in node.frames:
        left, _ = frame_images(msg)
        shown = int(np.argmin([_interior_error(left, t[0]) for t in truth]))
        # each frame is stamped with its time in the video (10 frames/s), not with when it was read
        assert (msg.header.stamp_ns - node.frames[0].header.stamp_ns) * 1e-8 == pytest.approx(shown, abs=1e-6)


def test_skipping_past_the_end_of_a_looped_video_lands_on_the_right_frame(videos):
    d, _, truth = videos
    calib = load_calibration(d / "stereo.yaml")
    capture = camera.StereoCapture(calib, left=str(d / "left.avi"), right=str(d / "right.avi"), loop=True)
    assert capture.skip(N_FRAMES + 1)                       # frames 0-4, then 0 again
    left, _ = frame_images(camera.StereoPipeline(calib, "rgb8").frame(*capture.read(), seq=1, stamp_ns=0))
    capture.close()
    assert int(np.argmin([_interior_error(left, t[0]) for t in truth])) == 1
