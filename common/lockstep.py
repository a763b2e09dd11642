"""The evolver → localiser chain run in lockstep on a recording, deterministically.

Live, the services run asynchronously and the evolver works on whatever frame is newest. For
evaluation that is not reproducible, so ``flyslam eval`` drives the same library classes in one
process: every frame is used, the evolver gets a fixed number of generations per frame, odometry is
read at each frame's stamp. Same recording + same seed → same trajectory.

Odometry: the wheel odometry's own integrated pose (``pose_xyyaw``) when the recording has it; image-only
datasets (KITTI, EuRoC) run with the localiser's constant-velocity prediction instead.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np

from common import messages as m
from common.fly import EvolverConfig, FlyEvolver
from common.geometry import invert, planar_pose
from common.images import frame_images
from common.pose_buffer import PoseBuffer
from common.recording import RecordedMessage
from common.slam import FlyLocaliser, LocaliserConfig


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
    res = LockstepResult()
    odom = PoseBuffer(maxlen=100_000, max_extrapolation_ns=100_000_000)
    evolver = localiser = calib = None
    last_T_odom_cam = None
    t0 = time.perf_counter()
    for rec in messages:
        stream = rec.key.split("/", 1)[-1]
        if stream not in ("stereo/calibration", "odom/wheels", "truth/pose", "stereo/frame"):
            continue
        try:
            msg = m.decode(rec.payload)
        except m.DecodeError:
            continue
        if stream == "stereo/calibration" and calib is None:
            calib = m.calibration_from_msg(msg)
            evolver = FlyEvolver(calib, evolver_config or EvolverConfig(depth_max=30.0), seed=seed)
            localiser = FlyLocaliser(calib.T_base_camera, localiser_config, seed=seed, calibration=calib)
        elif stream == "odom/wheels" and msg.pose_xyyaw is not None:
            odom.add(msg.header.stamp_ns, planar_pose(*msg.pose_xyyaw))
        elif stream == "truth/pose":
            res.truth_stamps.append(msg.header.stamp_ns)
            res.truth.append(m.transform_of(msg))
        elif stream == "stereo/frame" and evolver is not None:
            stamp = msg.header.stamp_ns
            left, right = frame_images(msg)
            T_odom_base = odom.at(stamp)
            T_odom_cam = None if T_odom_base is None else T_odom_base @ calib.T_base_camera
            if T_odom_cam is not None and last_T_odom_cam is not None:
                evolver.move_flies(invert(T_odom_cam) @ last_T_odom_cam, rescore=False)   # set_images re-scores
            last_T_odom_cam = T_odom_cam
            evolver.set_images(left, right)
            evolver.step(generations_per_frame)
            est = localiser.update(stamp, evolver.positions, evolver.fitness, T_odom_base, evolver.generation)
            res.stamps.append(stamp)
            res.estimated.append(est.T_map_base)
            res.odometry.append(T_odom_base)
            res.statuses.append(est.status)
            res.frames += 1
            if progress:
                progress(res.frames, est.status)
            if max_frames and res.frames >= max_frames:
                break
    res.seconds = time.perf_counter() - t0
    res.keyframes = len(localiser.keyframes) if localiser else 0
    return res
