"""Two real processes exchange messages over Zenoh on loopback; latest-value semantics."""
from __future__ import annotations

import subprocess
import sys
import textwrap
import time

import pytest

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


@pytest.mark.parametrize("polled", [False, True], ids=["slot", "polled"])
def test_two_processes_exchange_messages_and_a_slow_consumer_gets_the_newest(zenoh_port, polled):
    """Both kinds of latest-value subscription: the slot a callback fills, and the polled one (Zenoh's
    one-sample ring, which drops a stale frame before it reaches Python)."""
    n = 150
    with Node("subtest", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
        sub = node.subscribe_latest("stereo/frame", StereoFrame, polled=polled)
        proc = subprocess.Popen([sys.executable, "-c", PUBLISHER, hub(zenoh_port), str(n)], cwd=ROOT)
        try:
            if polled:
                with pytest.raises(RuntimeError, match="take"):
                    sub.wait(timeout=0.1)
                got = []
                wait_until(lambda: got.append(sub.take()) or got[-1] is not None, timeout=20, poll=0.005)
                first = got[-1]
            else:
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


def test_a_held_stream_answers_with_its_newest_message_after_the_publisher_is_gone(zenoh_port):
    """What the supervisor does for its launch file's latch streams (Node.hold_latched): a restarted
    service asks, and gets the last message of a process that has died."""
    opts = BusOptions(hub=hub(zenoh_port))
    with Node("holder", opts, handle_signals=False) as holder:
        holder.hold_latched("planner/target")
        with Node("talker", opts, handle_signals=False) as talker:
            time.sleep(0.5)
            pub = talker.publisher("planner/target")           # not latched: nobody else keeps it
            for i in range(5):
                pub.publish(Target(x=float(i), y=0.0, header=header(i, 5, "map")))
                time.sleep(0.05)
            time.sleep(0.3)
        with Node("restarted", opts, handle_signals=False) as late:
            msg = late.query_latest("planner/target", Target, 2.0)
            assert msg is not None and msg.x == 4.0, "the newest message, after its publisher left"
            again = late.query_latest("planner/target", Target, 2.0)
            assert again is not None and again.x == 4.0, "asked twice, it still answers (the ring was read)"


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
    """The grey image of a population is a side field: typed subscribers (the localiser, on
    flies/population/@image) get it, a raw subscriber (the recorder) gets the payload without it, 300 kB
    lighter per frame."""
    import numpy as np
    from common import messages as m
    opts = BusOptions(hub=hub(zenoh_port))
    image = np.arange(480 * 640, dtype=np.uint32).astype(np.uint8).reshape(480, 640)
    pop = m.FlyPopulation(positions=np.ones((50, 3), np.float32), fitness=np.ones(50, np.float32), source_seq=7,
                          image=image, header=m.header(0, 5, m.CAMERA_LEFT_OPTICAL))
    with Node("pub", opts, handle_signals=False) as a, Node("sub", opts, handle_signals=False) as b:
        latest = b.subscribe_latest("flies/population", m.FlyPopulation)
        polled = b.subscribe_latest("flies/population", m.FlyPopulation, polled=True)
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
        from_ring = polled.take()
        assert from_ring is not None and np.array_equal(from_ring.image, image)
        assert np.array_equal(typed[0].image, image)
        assert len(raw[0]) < 10_000 and m.decode(raw[0]).image is None


def test_a_closed_polled_subscription_takes_nothing_instead_of_raising(zenoh_port):
    with Node("closing", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
        sub = node.subscribe_latest("stereo/frame", StereoFrame, polled=True)
        sub.close()
        assert sub.take() is None
