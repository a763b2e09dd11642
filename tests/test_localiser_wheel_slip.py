"""A wheel-slip burst (one wheel spinning on a slippery patch: the odometry reports a fast turn that never
happened) does not turn the localiser's heading: the images, not the odometry, decide the turn."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from common import messages as m
from common.fly import EvolverConfig
from common.geometry import invert, planar_from_transform, planar_pose
from common.lockstep import run_lockstep
from common.recording import RecordedMessage, RecordingReader

CORRIDOR = Path(__file__).resolve().parent.parent / "recordings" / "corridor.mcap"
BURST_START_S, BURST_S, BURST_YAW_DEG = 8.0, 0.3, 10.0     # 33°/s: faster than the localiser believes


def with_slip_burst(messages):
    """The recording with its wheel odometry turned by BURST_YAW_DEG about the pose where the burst starts,
    ramping in over BURST_S (afterwards the odometry frame stays turned, as after a real burst)."""
    t0 = T_burst = None
    for rec in messages:
        if rec.key.endswith("/odom/wheels"):
            msg = m.decode(rec.payload)
            t0 = msg.header.stamp_ns if t0 is None else t0
            t = (msg.header.stamp_ns - t0) * 1e-9
            if t >= BURST_START_S and msg.pose_xyyaw is not None:
                T = planar_pose(*msg.pose_xyyaw)
                T_burst = T if T_burst is None else T_burst
                turn = np.deg2rad(BURST_YAW_DEG) * min(1.0, (t - BURST_START_S) / BURST_S)
                T_fake = T_burst @ planar_pose(0.0, 0.0, turn) @ invert(T_burst) @ T
                msg = dataclasses.replace(msg, pose_xyyaw=np.array(planar_from_transform(T_fake)))
                rec = RecordedMessage(rec.key, rec.schema, rec.log_time_ns, rec.publish_time_ns, m.encode(msg))
        yield rec


def test_a_wheel_slip_burst_does_not_turn_the_estimate():
    res = run_lockstep(with_slip_burst(RecordingReader(CORRIDOR).messages()), generations_per_frame=20,
                       evolver_config=EvolverConfig(population=3000, parallel=False), max_frames=160)
    assert res.localiser.config.odometry == "wheels" and res.frames == 160
    stamps = np.array(res.truth_stamps)
    truth = res.truth[int(np.clip(np.searchsorted(stamps, res.stamps[-1]), 0, len(stamps) - 1))]
    heading_error = np.rad2deg(planar_from_transform(invert(truth) @ res.estimated[-1])[2])
    odometry_error = np.rad2deg(planar_from_transform(invert(truth) @ res.odometry[-1])[2])
    assert abs(odometry_error) > 0.8 * BURST_YAW_DEG - 3       # the burst is in the odometry ...
    assert abs(heading_error) < 1.5, heading_error              # ... not in the estimate
