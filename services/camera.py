"""Real stereo camera (or stereo video files or images) as a live source: rectified frames and the calibration.

Inputs, through OpenCV VideoCapture:
- two devices or two video files: ``--left 0 --right 1`` / ``--left l.avi --right r.avi``;
- one side-by-side device or file (left half = left camera): ``--sbs 0`` / ``--sbs pair.avi``;
- two image sequences: ``--left 'cap/left_*.png' --right 'cap/right_*.png' --fps 10`` (a glob pattern or
  a folder each, paired in natural order: common/image_sequence.py), played like video files.
A digit string is a device index, ``/dev/...`` a device path, a glob pattern or a folder an image
sequence, anything else a video file.

``--calibration`` names the rig's calibration: OpenCV stereo YAML (format in common/stereo_rectify.py;
repeat the option to merge OpenCV's intrinsics.yml + extrinsics.yml), a Kalibr camchain.yaml, or the
left and right ROS camera_info YAML files (common/calibration_files.py). Rectification maps are
computed once.
Publishes ``<robot>/stereo/frame`` (rectified, ``--encoding`` rgb8 | mono8 | jpeg | png) stamped with the
capture wall-clock time (a video file: its frame's time in the video from the start of the run, late
frames skipped as a camera would have moved on), and ``<robot>/stereo/calibration`` (latched, re-published every
``--calibration-period`` s). Devices are asked for the calibrated resolution; a device, file or
calibration that does not fit ends the process with status 2 and a one-line message saying which.
"""
from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from common import streams as S
from common.camera import CalibrationError, StereoCalibration
from common.images import COMPRESSED_ENCODINGS, RAW_ENCODINGS, make_frame
from common.messages import StereoFrame, calibration_to_msg
from common.calibration_files import CalibratedRig, load_rig
from common.image_sequence import IMAGE_SUFFIXES, ImageSequence, ImageSequenceError, is_image_sequence
from common.stereo_rectify import StereoRectifier, split_side_by_side

log = logging.getLogger("flyslam.camera")


class CameraError(ValueError):
    """A device or video file that cannot be opened, read, or does not fit the calibration."""


def _quiet_opencv():
    """Silence OpenCV's own multi-line warnings while probing devices: our message says what failed."""
    logging_mod = getattr(getattr(cv2, "utils", None), "logging", None)
    if logging_mod is not None:
        logging_mod.setLogLevel(logging_mod.LOG_LEVEL_ERROR)


def is_device(spec: str) -> bool:
    """A device index or a device path, not a file."""
    return spec.isdigit() or spec.startswith("/dev/")


def describe(spec: str) -> str:
    if is_device(spec):
        return f"camera device {spec}"
    return f"image sequence {spec}" if is_image_sequence(spec) else f"video file {spec}"


def open_capture(spec: str, size: tuple[int, int] | None = None, fps: float | None = None):
    """VideoCapture of a device index / device path / video file, or an ImageSequence (a glob pattern or a
    folder of images); devices are asked for ``size`` and ``fps`` and for a one-frame buffer (a paced
    reader then gets fresh frames, not queued ones)."""
    device = is_device(spec)
    if not device and is_image_sequence(spec):
        sequence = ImageSequence(spec)
        if not sequence.isOpened():
            raise CameraError(f"{describe(spec)}: no image files ({', '.join(s[1:] for s in IMAGE_SUFFIXES)})")
        return sequence
    if not device and not Path(spec).is_file():
        raise CameraError(f"{describe(spec)} not found")
    _quiet_opencv()
    cap = cv2.VideoCapture(int(spec) if spec.isdigit() else spec)
    if not cap.isOpened():
        raise CameraError(f"{describe(spec)} could not be opened")
    if device:
        if size is not None:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, size[0])
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, size[1])
        if fps:
            cap.set(cv2.CAP_PROP_FPS, fps)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
    return cap


def source_frame_size(left: str | None, right: str | None, sbs: str | None) -> tuple[int, int]:
    """(width, height) of one camera's raw frames, read from the source's first frame (a side-by-side
    frame holds two): for a calibration file that does not say (OpenCV's stereo_calib sample)."""
    spec = sbs or left
    if spec is None or (sbs is None and right is None):
        raise CameraError("give either --sbs, or both --left and --right")
    cap = open_capture(spec)
    try:
        try:
            ok, img = cap.retrieve() if cap.grab() else (False, None)
        except ImageSequenceError as e:
            raise CameraError(str(e)) from None
        if not ok or img is None:
            raise CameraError(f"{describe(spec)} gave no frame")
    finally:
        cap.release()
    width = img.shape[1] // 2 if sbs else img.shape[1]
    log.info("the calibration gives no image size: %s gives %dx%d frames", describe(spec), width, img.shape[0])
    return width, img.shape[0]


class StereoCapture:
    """Raw (unrectified) BGR stereo pairs from two captures or one side-by-side capture.

    The first pair is read on opening, to check the image size against ``calib`` before anything is
    published. :meth:`read` returns None at the end of the files (or rewinds with ``loop``). Two image
    sequences pair their images in order, so they must hold as many.
    """

    def __init__(self, calib: StereoCalibration, left: str | None = None, right: str | None = None,
                 sbs: str | None = None, loop: bool = False, calibration_name: str = "the calibration",
                 fps: float | None = None):
        if (sbs is None) == (left is None or right is None):
            raise CameraError("give either --sbs, or both --left and --right")
        self.specs = [sbs] if sbs is not None else [left, right]
        self.side_by_side = sbs is not None
        self.is_file = not any(is_device(s) for s in self.specs)
        self.loop = loop
        w, h = calib.width, calib.height
        want = (2 * w, h) if self.side_by_side else (w, h)
        self.caps = []
        try:
            self.caps = [open_capture(s, want, fps) for s in self.specs]
            self.is_sequence = any(isinstance(c, ImageSequence) for c in self.caps)
            counts = [len(c.files) for c in self.caps if isinstance(c, ImageSequence)]
            if len(counts) == 2 and counts[0] != counts[1]:
                raise CameraError(f"{describe(self.specs[0])} holds {counts[0]} images but {describe(self.specs[1])} "
                                  f"{counts[1]}: the pairs would not match")
            self.fps = self.caps[0].get(cv2.CAP_PROP_FPS) or 0.0
            self._first = self._grab()
            if self._first is None:
                raise CameraError(f"{describe(self.specs[0])} gave no frame")
            for spec, img in zip(self.specs, self._raw_images):
                if (img.shape[1], img.shape[0]) != want:
                    kind = "side-by-side " if self.side_by_side else ""
                    raise CameraError(
                        f"{describe(spec)} gives {img.shape[1]}×{img.shape[0]} frames but {calibration_name} is for "
                        f"{kind}{want[0]}×{want[1]}")
        except Exception:
            self.close()
            raise

    def _grab(self):
        # grab() all first, then retrieve(): the two sensors are sampled as close together as possible.
        if not all(c.grab() for c in self.caps):
            return None
        imgs = []
        for c in self.caps:
            try:
                ok, img = c.retrieve()
            except ImageSequenceError as e:
                raise CameraError(str(e)) from None
            if not ok or img is None:
                return None
            imgs.append(img)
        self._raw_images = imgs
        return split_side_by_side(imgs[0]) if self.side_by_side else (imgs[0], imgs[1])

    def read(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Next raw (left, right) BGR pair; None at the end of the files."""
        if self._first is not None:
            pair, self._first = self._first, None
            return pair
        pair = self._grab()
        if pair is None and self.is_file and self.loop:
            for c in self.caps:
                c.set(cv2.CAP_PROP_POS_FRAMES, 0)
            pair = self._grab()
        if pair is None and not self.is_file:
            raise CameraError(f"{', '.join(describe(s) for s in self.specs)}: no frame (disconnected?)")
        return pair

    def skip(self, n: int) -> bool:
        """Pass over the next ``n`` frames (grabbed, not retrieved); False when the files end first."""
        for _ in range(n):
            if self._first is not None:
                self._first = None
                continue
            if all(c.grab() for c in self.caps):
                continue
            if not (self.is_file and self.loop):
                return False
            for c in self.caps:                   # a looped video: the skipped frame is the first again
                c.set(cv2.CAP_PROP_POS_FRAMES, 0)
            if not all(c.grab() for c in self.caps):
                return False
        return True

    def close(self) -> None:
        for c in self.caps:
            c.release()


class StereoPipeline:
    """Raw BGR pairs → rectified StereoFrames in the requested encoding (no bus: testable as is)."""

    def __init__(self, rig: CalibratedRig | StereoCalibration, encoding: str = "rgb8", quality: int = 90):
        if encoding not in RAW_ENCODINGS + COMPRESSED_ENCODINGS:
            raise CameraError(f"unknown encoding {encoding!r} (use one of {', '.join(RAW_ENCODINGS + COMPRESSED_ENCODINGS)})")
        if isinstance(rig, StereoCalibration):
            rig = CalibratedRig(rig, StereoRectifier(rig).rectify, "calibration")
        self.calib, self.rectify = rig.calibration, rig.rectify      # rectify(left, right): raw → rectified
        self.encoding, self.quality = encoding, quality

    def frame(self, left_bgr: np.ndarray, right_bgr: np.ndarray, seq: int, stamp_ns: int) -> StereoFrame:
        code = cv2.COLOR_BGR2GRAY if self.encoding == "mono8" else cv2.COLOR_BGR2RGB
        left, right = (cv2.cvtColor(img, code) if img.ndim == 3 else img for img in (left_bgr, right_bgr))
        if self.encoding != "mono8" and left.ndim == 2:
            left, right = cv2.cvtColor(left, cv2.COLOR_GRAY2RGB), cv2.cvtColor(right, cv2.COLOR_GRAY2RGB)
        left, right = self.rectify(left, right)
        return make_frame(left, right, seq=seq, stamp_ns=stamp_ns, encoding=self.encoding, quality=self.quality)


# ------------------------------------------------------------------------------------------ process


def _optional_float(text: str) -> float | None:
    """A number, or None for an empty value (a launch file passes its unset variables empty)."""
    return float(text) if text.strip() else None


def build_parser():
    from services.base import service_parser
    p = service_parser("camera", __doc__.splitlines()[0])
    src = p.add_argument_group("source")
    src.add_argument("--left", help="left camera: device index, /dev/videoN, video file, or images ('l/*.png', a folder)")
    src.add_argument("--right", help="right camera: device index, /dev/videoN, video file, or images ('r/*.png', a folder)")
    src.add_argument("--sbs", help="one side-by-side device or video file (left half = left camera)")
    src.add_argument("--calibration", "-c", action="append", required=True,
                     help="OpenCV stereo YAML (repeatable), Kalibr camchain.yaml, or ROS camera_info left.yaml "
                          "then right.yaml")
    src.add_argument("--units-m", type=_optional_float, default=None,
                     help="metres per unit of T in an OpenCV YAML (overrides units_m; T in squares: the square size)")
    src.add_argument("--fps", type=_optional_float, default=None,
                     help="frame rate to publish at (needed for images); unset: a video's own rate, a device's pace")
    src.add_argument("--loop", action="store_true", help="rewind video files at their end")
    src.add_argument("--encoding", default="rgb8", choices=RAW_ENCODINGS + COMPRESSED_ENCODINGS)
    src.add_argument("--quality", type=int, default=90, help="JPEG quality")
    src.add_argument("--calibration-period", type=float, default=2.0,
                     help="seconds between re-publications of the calibration")
    return p


FILE_WAIT_SUBSCRIBERS_S = 10.0   # a video file waits this long at most for the first frame's subscriber


def publish_loop(node, capture: StereoCapture, pipeline: StereoPipeline, fps: float | None,
                 calibration_period: float) -> int:
    frames = node.publisher(S.STEREO_FRAME)
    calib_pub = node.publisher(S.STEREO_CALIBRATION)
    period = 1.0 / fps if fps and fps > 0 else 0.0
    # A video file stands in for a camera: its frame i was taken at start + i·period.  A late reader
    # skips to the frame the camera would show now (a camera does not wait) and stamps each frame with
    # its own time, so a busy machine drops frames instead of slowing the world down.
    on_file_clock = bool(period) and capture.is_file
    if on_file_clock:
        # ... and it starts when someone watches: frames played to nobody would be lost to the run.
        deadline = time.monotonic() + FILE_WAIT_SUBSCRIBERS_S
        while not frames.has_subscribers() and time.monotonic() < deadline and node.sleep(0.05):
            pass
    start, start_ns, index = time.monotonic(), time.time_ns(), 0
    next_due = start
    next_calib = 0.0
    seq = 0
    while not node.stopping:
        now = time.monotonic()
        if now >= next_calib:
            calib_pub.publish(calibration_to_msg(pipeline.calib, stamp_ns=time.time_ns()))
            next_calib = now + calibration_period
        if on_file_clock:
            due = start + index * period
            if now < due and not node.sleep(due - now):
                break
            behind = int((time.monotonic() - due) / period)
            if behind > 0 and not capture.skip(behind):
                log.info("end of the video after %d frames", seq)
                return 0
            index += behind
        elif period:
            if now < next_due and not node.sleep(next_due - now):
                break
            next_due = max(next_due + period, time.monotonic())  # late: restart the clock, no burst
        try:
            pair = capture.read()
        except CameraError as e:
            log.error("%s", e)
            return 1
        if pair is None:
            log.info("end of the video after %d frames", seq)
            return 0
        seq += 1
        stamp_ns = start_ns + int(round(index * period * 1e9)) if on_file_clock else time.time_ns()
        index += 1
        frames.publish(pipeline.frame(*pair, seq=seq, stamp_ns=stamp_ns))
        node.progress = seq
    return 0


def main(argv: list[str] | None = None) -> int:
    from common.bus import Node, bus_options, setup_logging
    from services.base import one_opencv_thread
    args = build_parser().parse_args(argv)
    one_opencv_thread()
    setup_logging("camera")
    try:
        calibration_files = [c for c in args.calibration if c]
        left, right, sbs = args.left or None, args.right or None, args.sbs or None
        rig = load_rig(calibration_files, args.units_m, image_size=lambda: source_frame_size(left, right, sbs))
        calib = rig.calibration
        pipeline = StereoPipeline(rig, args.encoding, args.quality)
        # an empty value is no value: a launch file passes every source option, the unused ones empty
        capture = StereoCapture(calib, left, right, sbs, loop=args.loop,
                                calibration_name=f"calibration {', '.join(calibration_files)}", fps=args.fps)
        if capture.is_sequence and not args.fps:
            capture.close()
            raise CameraError(f"{', '.join(map(describe, capture.specs))}: images have no frame rate of their own; "
                              "give --fps (the rate they were taken at)")
    except (CalibrationError, CameraError) as e:
        print(f"flyslam camera: {e}", file=sys.stderr)
        return 2
    fps = args.fps if args.fps else (capture.fps if capture.is_file and capture.fps > 0 else None)
    log.info("%s → %dx%d rectified, fx %.1f px, baseline %.1f mm, %s; calibration: %s", ", ".join(capture.specs),
             calib.width, calib.height, calib.fx, calib.baseline * 1000, f"{fps:g} fps" if fps else "device rate",
             rig.source)
    try:
        with Node("camera", bus_options(args)) as node:
            return publish_loop(node, capture, pipeline, fps, args.calibration_period)
    finally:
        capture.close()


if __name__ == "__main__":
    sys.exit(main())
