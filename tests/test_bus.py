"""Two real processes exchange messages over Zenoh on loopback; latest-value semantics."""
from __future__ import annotations

import subprocess
import sys
import textwrap
import time


from common.bus import BusOptions, Node
from common.messages import StereoFrame, Target, header
from tests.helpers import ROOT, hub, wait_until

PUBLISHER = textwrap.dedent("""
    import sys, time, numpy as np
    from common.bus import BusOptions, Node
    from common.images import make_frame
    from common.messages import Target, header
    with Node("pubtest", BusOptions(hub=sys.argv[1])) as node:
        frames = node.publisher("stereo/frame")
        targets = node.publisher("planner/target", latched=True)
        targets.publish(Target(x=4.0, y=2.0, header=header(0, 1, "map")))
        img = np.zeros((48, 64, 3), np.uint8)
        for i in range(int(sys.argv[2])):
            img[:] = i % 256
            frames.publish(make_frame(img, img, 0, time.time_ns()))
            time.sleep(0.01)
        time.sleep(1.0)
""")


def test_two_processes_exchange_messages_and_a_slow_consumer_gets_the_newest(zenoh_port):
    n = 150
    with Node("subtest", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
        sub = node.subscribe_latest("stereo/frame", StereoFrame)
        proc = subprocess.Popen([sys.executable, "-c", PUBLISHER, hub(zenoh_port), str(n)], cwd=ROOT)
        try:
            first = sub.wait(timeout=20)
            assert first is not None, "no frame arrived from the other process"
            # The latched target is served to a late joiner on request.
            target = node.query_latest("planner/target", Target, timeout=2.0)
            taken = [first]
            while proc.poll() is None or len(taken) < 3:
                msg = sub.take()
                if msg is not None:
                    taken.append(msg)
                    time.sleep(0.1)  # a consumer ten times slower than the stream
                elif proc.poll() is not None:
                    break
                else:
                    time.sleep(0.005)
        finally:
            proc.wait(timeout=20)
        seqs = [m.header.seq for m in taken]
        assert seqs == sorted(seqs)
        assert len(taken) < n / 3, "the slow consumer should not see a backlog of every frame"
        assert sub.skipped > n / 2, f"skipped frames are counted ({sub.skipped})"
        assert seqs[-1] >= n - 2, "the last frame taken is the newest one"
        assert target is not None and (target.x, target.y) == (4.0, 2.0)


def test_latched_publisher_answers_late_joiners(zenoh_port):
    opts = BusOptions(hub=hub(zenoh_port))
    with Node("latcher", opts, handle_signals=False) as a:
        pub = a.publisher("stereo/calibration_test", latched=True)
        pub.publish(Target(x=1.5, y=-2.0, header=header(0, 5, "map")))
        with Node("late", opts, handle_signals=False) as b:
            assert wait_until(lambda: b.query_latest("stereo/calibration_test", Target, 0.5) is not None, 10)
            msg = b.query_latest("stereo/calibration_test", Target, 1.0)
            assert (msg.x, msg.y) == (1.5, -2.0)


def test_rejected_payloads_are_counted_not_raised(zenoh_port):
    opts = BusOptions(hub=hub(zenoh_port))
    with Node("rx", opts, handle_signals=False) as rx, Node("tx", opts, handle_signals=False) as tx:
        got = []
        rx.subscribe("planner/target", Target, got.append)
        time.sleep(0.5)
        raw = tx.session.declare_publisher(tx.key("planner/target"))
        for payload in (b"garbage", b"\x81\xa1a\x01", b""):
            raw.put(payload)
        tx.publisher("planner/target").publish(Target(x=1.0, header=header(0, 1, "map")))
        assert wait_until(lambda: len(got) == 1 and rx.counters.get("rejected") == 3, 10), rx.counters.snapshot()


def test_a_populations_image_reaches_subscribers_beside_the_payload_and_stays_out_of_raw_payloads(zenoh_port):
    """The grey image of a population is a side field: typed subscribers (the localiser) get it, a raw
    subscriber (the recorder) gets the payload without it, 300 kB lighter per frame."""
    import numpy as np
    from common import messages as m
    opts = BusOptions(hub=hub(zenoh_port))
    image = np.arange(480 * 640, dtype=np.uint32).astype(np.uint8).reshape(480, 640)
    pop = m.FlyPopulation(positions=np.ones((50, 3), np.float32), fitness=np.ones(50, np.float32), source_seq=7,
                          image=image, header=m.header(0, 5, m.CAMERA_LEFT_OPTICAL))
    with Node("pub", opts, handle_signals=False) as a, Node("sub", opts, handle_signals=False) as b:
        latest = b.subscribe_latest("flies/population", m.FlyPopulation)
        typed, raw = [], []
        b.subscribe("flies/population", m.FlyPopulation, typed.append)
        b.subscribe("flies/population", None, lambda key, payload: raw.append(payload), raw=True)
        time.sleep(0.5)
        pub = a.publisher("flies/population")
        got = None
        for _ in range(40):
            pub.publish(pop)
            got = got or latest.wait(0.25)
            if got is not None and typed and raw:
                break
        assert got is not None and np.array_equal(got.image, image) and got.source_seq == 7
        assert np.array_equal(typed[0].image, image)
        assert len(raw[0]) < 10_000 and m.decode(raw[0]).image is None
