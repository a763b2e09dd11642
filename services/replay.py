"""Replay service: publishes a recording on the bus exactly as the live sources did.

Payload bytes are published unchanged on ``<robot>/<stream>`` (the recorded key with its robot prefix
replaced by ``--robot``), paced by the recorded receive times at ``--rate`` × real time (0 = as fast as
possible), from ``--start`` to ``--end`` seconds into the recording, optionally looping. By default only
the source streams are replayed (what a camera, the robot and a simulator publish), so the pipeline
downstream can run live on them; ``--keys`` chooses others (a recorded ``flies/population`` feeds a
planner or a viewer, not a localiser: that takes ``flies/population/@image``, which carries the frame's
image and is never recorded; replay the frames through an evolver instead).

A recording of several segments (a restarted recorder's ``recording.1.mcap``, …) replays as one: give
the base file or the run's folder. A truncated or corrupt segment is replayed up to the damage (then
the next segment), the problem is logged with the file name and the process exits with status 3.
"""
from __future__ import annotations

import logging
import sys
import time

import numpy as np

from common.recording import RecordingError, RecordingReader
from common.trajectory import write_tum
from services.base import run_service, service_parser

log = logging.getLogger("flyslam.replay")

SOURCE_STREAMS = ["stereo/frame", "stereo/calibration", "odom/wheels", "sonar/scan", "truth/pose",
                  "truth/depth", "planner/target"]
LATCHED_SCHEMAS = {"flyslam.StereoCalibration", "flyslam.Target"}


def build_parser():
    p = service_parser("replay", __doc__.splitlines()[0])
    p.add_argument("recording", help="MCAP file written by `flyslam record` or `flyslam import` (its numbered "
                                     "segments follow it), or a run folder holding one recording")
    p.add_argument("--rate", type=float, default=1.0, help="speed factor; 0 publishes as fast as possible")
    p.add_argument("--loop", action="store_true", help="start again at the end")
    p.add_argument("--start", type=float, default=0.0, help="seconds into the recording to start at")
    p.add_argument("--end", type=float, default=None, help="seconds into the recording to stop at")
    p.add_argument("--keys", nargs="+", default=SOURCE_STREAMS,
                   help="streams to replay (without robot prefix); 'all' replays every channel")
    p.add_argument("--truth-tum", default=None,
                   help="write the replayed truth/pose as a TUM trajectory here (at the end of each pass)")
    p.add_argument("--wait-subscribers", type=float, default=0.5,
                   help="seconds to wait after opening the session so subscribers can connect")
    return p


def stream_of(key: str) -> str:
    """'rig/stereo/frame' -> 'stereo/frame'."""
    return key.split("/", 1)[1] if "/" in key else key


def body(node, args) -> int:
    try:
        reader = RecordingReader(args.recording)
    except RecordingError as e:
        log.error("%s", e)
        return 2
    wanted = None if args.keys == ["all"] else set(args.keys)
    publishers = {}
    node.sleep(args.wait_subscribers)
    first_ns = None
    passes = 0
    truth: list[bytes] = []
    while not node.stopping:
        t0_wall = time.monotonic()
        t0_rec = None
        published = 0
        for m in reader.messages():
            if node.stopping:
                break
            if first_ns is None:
                first_ns = m.log_time_ns
            offset_s = (m.log_time_ns - first_ns) * 1e-9
            if offset_s < args.start:
                continue
            if args.end is not None and offset_s > args.end:
                break
            stream = stream_of(m.key)
            if wanted is not None and stream not in wanted:
                continue
            if t0_rec is None:
                t0_rec = m.log_time_ns
            if args.rate > 0:
                due = t0_wall + (m.log_time_ns - t0_rec) * 1e-9 / args.rate
                delay = due - time.monotonic()
                if delay > 0 and not node.sleep(delay):
                    break
            pub = publishers.get(stream)
            if pub is None:
                pub = publishers[stream] = node.publisher(stream, latched=m.schema in LATCHED_SCHEMAS, reliable=True)
            pub.put_raw(m.payload)
            if args.truth_tum and stream == "truth/pose":
                truth.append(m.payload)
            published += 1
            node.progress += 1
            if stream == "stereo/frame":
                node.counters.add("frames_replayed")
        passes += 1
        if args.truth_tum and truth:
            _write_truth(args.truth_tum, truth)
        if reader.errors:
            for path, problem in reader.errors.items():
                log.warning("%s: %s; replayed what it holds before that", path, problem)
            if any(e.startswith(("truncated", "corrupt")) for e in reader.errors.values()):
                return 3
        log.info("pass %d: published %d messages", passes, published)
        if not args.loop or published == 0:
            break
    return 0


def _write_truth(path: str, payloads: list[bytes]) -> None:
    """The replayed ground truth (PoseEstimate payloads) as a TUM file; undecodable ones are skipped."""
    from common import messages as msgs
    stamps, poses = [], []
    for payload in payloads:
        try:
            pose = msgs.decode(payload, msgs.PoseEstimate)
        except msgs.DecodeError:
            continue
        stamps.append(pose.header.stamp_ns)
        poses.append(msgs.transform_of(pose))
    if stamps:
        write_tum(path, np.array(stamps, np.int64), np.array(poses))
        log.info("wrote %d truth poses to %s", len(stamps), path)


def main(argv=None) -> int:
    return run_service("replay", build_parser(), body, argv)


if __name__ == "__main__":
    sys.exit(main())
