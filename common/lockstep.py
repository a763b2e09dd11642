"""The evolver → localiser chain run in lockstep on a recording, deterministically.

Live, the services run asynchronously and the evolver works on whatever frame is newest. For
evaluation that is not reproducible, so ``flyslam eval`` drives the services' own cores
(:class:`EvolverCore`, :class:`LocaliserCore`) in one process: every frame is used, the evolver gets a
fixed number of generations per frame, odometry is read at each frame's stamp. Same recording + same
seed → same trajectory, to the bit with ``EvolverConfig(parallel=False)``; with ``parallel='auto'`` the
kernel chosen by timing (common/fly/threads.py) can change the last bits of fitness, and so the result.

Odometry: the wheel odometry's own integrated pose (``pose_xyyaw``) when the recording has it; image-only
datasets (KITTI, EuRoC) run with the localiser's constant-velocity prediction instead.  A recording has
wheels when ``odom/wheels`` appears within ``WHEELS_LOOKAHEAD_NS`` of its first frame (a simulator
writes its first frame before its first odometry message).
"""
from __future__ import annotations

import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from itertools import chain
from typing import Callable, Iterable, Iterator

import numpy as np

from common import messages as m
from common.camera import CalibrationError, StereoCalibration
from common.fly import EvolverConfig
from common.fly.core import EvolverCore
from common.fly.evolver import images_ahead
from common.fly.fitness import FrameImages, ImageError
from common.geometry import planar_pose
from common.images import COMPRESSED_ENCODINGS, frame_images
from common.pose_buffer import PoseBuffer
from common.recording import RecordedMessage
from common.slam import LocaliserConfig
from common.slam.core import LocaliserCore


WHEELS_LOOKAHEAD_NS = 1_000_000_000
_STREAMS = ("stereo/calibration", "odom/wheels", "truth/pose", "stereo/frame")


def _decoded(messages: Iterator[RecordedMessage], evolver_config: EvolverConfig,
             ahead: int = 2) -> Iterator[tuple[str, object, FrameImages | None]]:
    """(stream, decoded message or None, prepared images or None) for each recorded message, in order.

    Stereo frames are decompressed to raw images by a worker thread up to ``ahead`` frames in advance,
    and their fitness images prepared there too (``images_ahead`` with the calibration recorded before
    them): OpenCV and the numba kernels release the GIL, so the next frames get ready on the core the
    evolver's serial loops leave idle.  The evolver uses the images only for the arrays they were
    computed from (common.fly.fitness.prepare_frame), so the result is the same, to the bit."""
    def decode_and_prepare(rec: RecordedMessage, calib: StereoCalibration | None):
        try:
            msg = m.decode(rec.payload)
        except m.DecodeError:
            return None, None
        if not isinstance(msg, m.StereoFrame):
            return msg, None
        try:
            left, right = frame_images(msg)
        except m.DecodeError:
            return msg, None          # EvolverCore reports it as it would live
        if msg.encoding in COMPRESSED_ENCODINGS:
            msg = replace(msg, left=left, right=right, encoding="mono8" if left.ndim == 2 else "rgb8")
        try:
            images = None if calib is None else images_ahead(calib, evolver_config, left, right)
        except (ImageError, CalibrationError):
            images = None             # the evolver finds out and reports it itself
        return msg, images

    pending: deque = deque()
    frames_queued = 0
    calib = None
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="lockstep-prepare")
    try:
        for rec in messages:
            stream = rec.key.split("/", 1)[-1]
            if stream not in _STREAMS:
                continue
            is_frame = stream == "stereo/frame"
            item = pool.submit(decode_and_prepare, rec, calib) if is_frame else decode_and_prepare(rec, None)
            if stream == "stereo/calibration" and isinstance(item[0], m.StereoCalibrationMsg):
                try:
                    calib = m.calibration_from_msg(item[0])
                except CalibrationError:
                    calib = None
            pending.append((stream, item))
            frames_queued += is_frame
            while pending and (frames_queued > ahead or pending[0][0] != "stereo/frame"):
                stream, item = pending.popleft()
                frames_queued -= stream == "stereo/frame"
                yield (stream, *(item.result() if isinstance(item, Future) else item))
        for stream, item in pending:
            yield (stream, *(item.result() if isinstance(item, Future) else item))
    finally:        # a caller that stops early (max_frames) does not wait for frames it will not use
        pool.shutdown(wait=True, cancel_futures=True)


def _wheels_ahead(messages: Iterator[RecordedMessage]) -> tuple[bool, list[RecordedMessage]]:
    """(whether ``odom/wheels`` is recorded near the first frame, the messages read to find out)."""
    seen, first_frame_ns = [], None
    for rec in messages:
        seen.append(rec)
        stream = rec.key.split("/", 1)[-1]
        if stream == "odom/wheels":
            return True, seen
        if stream == "stereo/frame" and first_frame_ns is None:
            first_frame_ns = rec.log_time_ns
        if first_frame_ns is not None and rec.log_time_ns - first_frame_ns > WHEELS_LOOKAHEAD_NS:
            break
    return False, seen


@dataclass
class LockstepResult:
    stamps: list = field(default_factory=list)
    estimated: list = field(default_factory=list)        # T_map_base per frame
    odometry: list = field(default_factory=list)         # T_odom_base per frame (None when no odometry)
    statuses: list = field(default_factory=list)
    truth_stamps: list = field(default_factory=list)
    truth: list = field(default_factory=list)
    frames: int = 0
    seconds: float = 0.0
    keyframes: int = 0
    graph_failed_updates: int = 0     # iSAM2 updates that raised and were solved again (common.slam.posegraph)
    graph_failures: int = 0           # keyframes the pose graph could not solve at all
    localiser: LocaliserCore | None = None     # the core at the end (its map, e.g. to save)

    @property
    def frames_per_s(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else 0.0

    @property
    def registered_fraction(self) -> float:
        return float(np.mean([s == "ok" for s in self.statuses])) if self.statuses else 0.0


def run_lockstep(messages: Iterable[RecordedMessage], generations_per_frame: int = 30, seed: int = 0,
                 evolver_config: EvolverConfig | None = None, localiser_config: LocaliserConfig | None = None,
                 max_frames: int | None = None,
                 progress: Callable[[int, str], None] | None = None) -> LockstepResult:
    """Run the live services' cores (EvolverCore → LocaliserCore) over every frame of ``messages``."""
    res = LockstepResult()
    evolver = EvolverCore(evolver_config or EvolverConfig(), settle=generations_per_frame,
                          seed=seed, odometry=PoseBuffer(maxlen=100_000, max_extrapolation_ns=100_000_000))
    localiser_config = localiser_config or LocaliserConfig()
    messages = iter(messages)
    wheels, ahead = _wheels_ahead(messages)
    localiser = _start_localiser(localiser_config, wheels, seed, evolver)
    calibration = None
    first_frame = True
    t0 = time.perf_counter()
    for stream, msg, images in _decoded(chain(ahead, messages), evolver.config):
        if msg is None:
            continue
        if stream == "stereo/calibration":
            evolver.on_calibration(msg)
            calibration = msg
        elif stream == "odom/wheels" and msg.pose_xyyaw is not None:
            evolver.on_odometry(msg.header.stamp_ns, planar_pose(*msg.pose_xyyaw))
        elif stream == "truth/pose":
            res.truth_stamps.append(msg.header.stamp_ns)
            res.truth.append(m.transform_of(msg))
        elif stream == "stereo/frame":
            if calibration is not None and not localiser.has_calibration:
                localiser.on_calibration(calibration)
            frame = evolver.on_frame(msg, images=images)
            if frame.population is None:
                continue
            if first_frame:      # the map starts from a converged population, as it does live
                evolver.evolve(max(0, localiser.config.min_generations - evolver.generation))
                frame.population = evolver.population(with_image=True)
                first_frame = False
            out = localiser.on_population(frame.population)
            if out.estimate is None:
                continue
            if not wheels:       # visual-only: the localiser's own estimates move the flies
                evolver.on_odometry(frame.population.header.stamp_ns, out.estimate.T_map_base)
            res.stamps.append(frame.population.header.stamp_ns)
            res.estimated.append(out.estimate.T_map_base)
            res.odometry.append(frame.T_odom_base if wheels else None)   # visual-only: no odometry of its own
            res.statuses.append(out.estimate.status)
            res.frames += 1
            if progress:
                progress(res.frames, out.estimate.status)
            if max_frames and res.frames >= max_frames:
                break
    res.seconds = time.perf_counter() - t0
    res.keyframes = len(localiser.keyframes)
    if localiser.localiser is not None:
        res.graph_failed_updates = localiser.localiser.graph_failed_updates
        res.graph_failures = localiser.localiser.graph_failures
    res.localiser = localiser
    return res


def _start_localiser(config: LocaliserConfig, wheels: bool, seed: int, evolver: EvolverCore) -> LocaliserCore:
    """The localiser for this recording: with wheel odometry as recorded, or visual-only (its own
    constant-velocity prediction, fed back to the evolver as the motion that moves the flies)."""
    if not wheels:
        config = replace(config, odometry="visual")
        evolver.odometry = PoseBuffer(maxlen=100_000, max_extrapolation_ns=1_000_000_000, extrapolate=True)
    return LocaliserCore(config, seed=seed)
