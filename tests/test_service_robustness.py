"""A service fed 1,000 random or mutated payloads on its input keys keeps running and counts them."""
from __future__ import annotations

import time

import numpy as np

from common import messages as m
from common.bus import BusOptions, Node
from common.camera import StereoCalibration
from common.images import make_frame
from tests.helpers import hub, resend_until, start_module, stop, wait_until


def _garbage(rng, valid: bytes) -> bytes:
    if rng.random() < 0.5:
        return rng.integers(0, 256, rng.integers(0, 300), dtype=np.uint8).tobytes()
    data = bytearray(valid)
    for _ in range(rng.integers(1, 6)):
        data[rng.integers(0, len(data))] = rng.integers(0, 256)
    return bytes(data[: rng.integers(1, len(data) + 1)])


def test_evolver_survives_and_counts_a_flood_of_bad_payloads(tmp_path, zenoh_port):
    rng = np.random.default_rng(1)
    proc = start_module("services.evolver", "--population", "400", "--settle-ms", "5", port=zenoh_port,
                        log_path=tmp_path / "evolver.log")
    try:
        with Node("tester", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
            heartbeats, populations = [], []
            node.subscribe("status/evolver", m.Heartbeat, heartbeats.append)
            node.subscribe("flies/population", m.FlyPopulation, populations.append)
            assert wait_until(lambda: heartbeats, 30), "evolver did not come up"
            calib = StereoCalibration.ideal(96, 72)
            raw = {k: node.session.declare_publisher(node.key(k)) for k in
                   ("stereo/calibration", "fusion/odom", "fusion/sonar", "stereo/frame")}
            node.publisher("stereo/calibration", latched=True).publish(m.calibration_to_msg(calib, 1, 1))
            frames = node.publisher("stereo/frame", reliable=True)
            img = rng.integers(0, 255, (72, 96, 3), dtype=np.uint8)

            def evolved(seq, since=0) -> bool:
                """Frame ``seq`` sent until a population of it comes back: the calibration and a frame
                travel on two keys with no order between them, and a frame taken before its calibration
                is applied is refused ('no calibration')."""
                return resend_until(lambda: frames.publish(make_frame(img, np.roll(img, -4, axis=1), seq,
                                                                      time.time_ns())),
                                    lambda: any(p.source_seq == seq for p in populations[since:]))

            assert evolved(1), "no population for a valid frame"
            valid = {"stereo/calibration": m.encode(m.calibration_to_msg(calib, 2, 2)),
                     "fusion/odom": m.encode(m.pose_msg(np.eye(4), frame_id="odom", stamp_ns=5)),
                     "fusion/sonar": m.encode(m.SonarScan(transducer_poses=np.zeros((8, 3)),
                                                          ranges=np.ones(8, np.float32))),
                     "stereo/frame": m.encode(make_frame(img, img, 3, 3))}
            keys = list(raw)
            sent = dict.fromkeys(keys, 0)
            for i in range(1000):
                key = keys[i % len(keys)]
                raw[key].put(_garbage(rng, valid[key]))
                sent[key] += 1
                if i % 50 == 0:
                    time.sleep(0.01)
            time.sleep(0.5)
            assert evolved(100, since=len(populations)), "the evolver must keep working on valid frames after the flood"
            assert proc.poll() is None, "the evolver process died"

            def counted():
                c = heartbeats[-1].counters
                callback_keys = sum(c.get(k.replace("/", "_") + "_rejected", 0) for k in keys[:3])
                return callback_keys, c.get("stereo_frame_rejected", 0)
            # Callback streams decode every payload; the latest-value frame stream only the ones it takes.
            assert wait_until(lambda: counted()[0] >= 0.95 * sum(sent[k] for k in keys[:3]), 15), counted()
            assert counted()[1] >= 1
            print(f"\nrejected on callback streams: {counted()[0]} of {sum(sent[k] for k in keys[:3])} bad payloads; "
                  f"on stereo/frame (latest-value): {counted()[1]} of {sent['stereo/frame']}")
    finally:
        assert stop(proc) == 0, (tmp_path / "evolver.log").read_text()[-3000:]
