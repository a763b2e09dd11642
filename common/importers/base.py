"""What every dataset importer shares: the dataset description, frame conventions, the recording writer.

Frames for datasets without a robot body (all three supported ones): base_link is a REP-103 body frame
(x forward, y left, z up) at the left camera, so ``T_base_camera`` is the rotation ``R_BODY_OPTICAL``
with no translation; the map frame is the body-style frame of the left camera at the first frame, so a
dataset pose ``T_w_cam`` (camera optical frame in the dataset world) becomes

    T_map_base = C · T_w_cam0⁻¹ · T_w_cam · C⁻¹        with C = [R_BODY_OPTICAL, 0; 0, 1]

and moving the camera along its optical z (forward) moves base_link along map +x.

Recording keys, under the robot prefix (default ``rig``): ``stereo/calibration`` (once, also stored as
metadata), ``stereo/frame``, ``truth/pose`` (PoseEstimate of base_link in map) and ``truth/depth``
(DepthImage, Middlebury). log_time = publish_time = the dataset's timestamp (ns); messages are written
in timestamp order.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from common.camera import StereoCalibration
from common.geometry import R_BODY_OPTICAL, invert, make_transform
from common.images import make_frame
from common.messages import CAMERA_LEFT_OPTICAL, DepthImage, calibration_to_msg, encode, header, pose_msg
from common.recording import RecordingWriter

C_BODY_OPTICAL = make_transform(R_BODY_OPTICAL)
T_BASE_CAMERA = C_BODY_OPTICAL  # base_link coincides with the left camera, body-style axes


class DatasetLayoutError(ValueError):
    """A dataset folder that does not have the expected layout; the message names what is missing."""


def require(path: Path, what: str) -> Path:
    """``path`` if it exists, else DatasetLayoutError "<what>: <path> not found"."""
    if not path.exists():
        raise DatasetLayoutError(f"{what}: {path} not found")
    return path


def load_yaml(path: Path, what: str):
    """The first document of a YAML file (a ``rostopic echo`` dump ends with ``---``), read with rosbags'
    own YAML reader; DatasetLayoutError "<what>: <path> ..." when it cannot be read."""
    from ruamel.yaml import YAML, YAMLError

    path = require(Path(path), what)
    try:
        docs = YAML(typ="safe", pure=True).load_all(path.read_text())
        return next((d for d in docs if d is not None), None)
    except OSError as e:
        raise DatasetLayoutError(f"{what}: {path} cannot be read ({e.strerror or e})") from None
    except (YAMLError, UnicodeDecodeError) as e:
        raise DatasetLayoutError(f"{what}: {path} is not readable YAML ({str(e).splitlines()[0]})") from None


def numbers(value, count: int | None, where: str) -> np.ndarray:
    """``value`` (a YAML list) as finite float64 numbers, ``count`` of them if given; DatasetLayoutError
    "<where> ..." otherwise."""
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetLayoutError(f"{where} is not numeric") from None
    if count is not None and a.size != count:
        raise DatasetLayoutError(f"{where} has {a.size} numbers, expected {count}")
    if not np.all(np.isfinite(a)):
        raise DatasetLayoutError(f"{where} contains NaN or inf")
    return a


def map_poses_from_camera(T_w_cam: np.ndarray, reference: np.ndarray | None = None,
                          T_base_camera: np.ndarray = C_BODY_OPTICAL) -> np.ndarray:
    """(N, 4, 4) camera-optical poses in a dataset world → base_link poses in map (see module doc).

    ``reference`` is the camera pose that defines the map (default: the first pose); ``T_base_camera``
    the camera's mounting (default: at base_link), the map being base_link at the reference pose.
    """
    T_w_cam = np.asarray(T_w_cam, np.float64)
    ref_inv = invert(T_w_cam[0] if reference is None else reference)
    return T_base_camera @ (ref_inv @ T_w_cam) @ invert(T_base_camera)


@dataclass
class StereoDataset:
    """A dataset ready to write: rectified calibration, frames loaded on demand, ground truth.

    ``load_pair(i)`` returns the i-th rectified (left, right) pair, RGB (H×W×3) or mono (H×W) uint8.
    """
    name: str
    calibration: StereoCalibration
    stamps_ns: np.ndarray
    load_pair: Callable[[int], tuple[np.ndarray, np.ndarray]]
    truth_stamps_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    truth_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))  # T_map_base
    load_depth: Callable[[int], np.ndarray] | None = None  # ground-truth depth of frame i (metres)
    notes: list[str] = field(default_factory=list)

    def __post_init__(self):
        self.stamps_ns = np.asarray(self.stamps_ns, np.int64)
        self.truth_stamps_ns = np.asarray(self.truth_stamps_ns, np.int64)
        if len(self.stamps_ns) == 0:
            raise DatasetLayoutError(f"{self.name}: no frames")
        if len(self.truth_stamps_ns) != len(self.truth_poses):
            raise DatasetLayoutError(f"{self.name}: {len(self.truth_stamps_ns)} truth stamps for "
                                     f"{len(self.truth_poses)} poses")


@dataclass
class ImportSummary:
    path: Path
    name: str
    frames: int
    truth_poses: int
    depth_images: int
    duration_s: float
    size_bytes: int
    seconds: float
    notes: list[str]

    def format(self) -> str:
        lines = [f"imported   {self.name}", f"recording  {self.path}",
                 f"frames     {self.frames} over {self.duration_s:.2f} s",
                 f"truth      {self.truth_poses} poses" + (f", {self.depth_images} depth images" if self.depth_images else ""),
                 f"size       {self.size_bytes / 1e6:.1f} MB (written in {self.seconds:.1f} s)"]
        lines += [f"note       {n}" for n in self.notes]
        return "\n".join(lines)


def write_recording(dataset: StereoDataset, out, robot: str = "rig", encoding: str = "png", quality: int = 95,
                    progress: Callable[[int, int], None] | None = None) -> ImportSummary:
    """Write ``dataset`` as a flyslam recording at ``out``; ``progress(done, total)`` after each frame."""
    t0 = time.monotonic()
    out = Path(out)
    calib = dataset.calibration
    stamps, truth_stamps = dataset.stamps_ns, dataset.truth_stamps_ns
    first = int(min(stamps.min(), truth_stamps.min() if len(truth_stamps) else stamps.min()))
    # Merge frames (kind 0) and truth poses (kind 1) by stamp; a frame goes before a pose of equal stamp.
    events = sorted([(int(s), 0, i) for i, s in enumerate(stamps)] +
                    [(int(s), 1, j) for j, s in enumerate(truth_stamps)])
    key = lambda stream: f"{robot}/{stream}"  # noqa: E731
    n_depth = 0
    with RecordingWriter(out) as writer:
        payload = encode(calibration_to_msg(calib, seq=1, stamp_ns=first))
        writer.add_calibration(payload)
        writer.add_config({"source": dataset.name, "encoding": encoding, "robot": robot})
        writer.write(key("stereo/calibration"), payload, log_time_ns=first, publish_time_ns=first)
        done = 0
        for stamp, kind, idx in events:
            if kind == 1:
                msg = pose_msg(dataset.truth_poses[idx], seq=idx + 1, stamp_ns=stamp)
                writer.write(key("truth/pose"), encode(msg), log_time_ns=stamp, publish_time_ns=stamp)
                continue
            left, right = dataset.load_pair(idx)
            calib.check_image(left, f"{dataset.name} frame {idx} left image")
            frame = make_frame(left, right, seq=idx + 1, stamp_ns=stamp, encoding=encoding, quality=quality)
            writer.write(key("stereo/frame"), encode(frame), log_time_ns=stamp, publish_time_ns=stamp)
            if dataset.load_depth is not None:
                depth = DepthImage(depth=np.asarray(dataset.load_depth(idx), np.float32),
                                   header=header(idx + 1, stamp, CAMERA_LEFT_OPTICAL))
                writer.write(key("truth/depth"), encode(depth), log_time_ns=stamp, publish_time_ns=stamp)
                n_depth += 1
            done += 1
            if progress is not None:
                progress(done, len(stamps))
    duration = (int(stamps.max()) - int(stamps.min())) * 1e-9
    return ImportSummary(out, dataset.name, len(stamps), len(truth_stamps), n_depth, duration,
                         out.stat().st_size, time.monotonic() - t0, list(dataset.notes))
