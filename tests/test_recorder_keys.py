"""Which keys the recorder keeps: Zenoh's key-expression rules (common.recording.KeyFilter), decided
once per key with a bounded memory, and a bad --keys pattern refused with one line before any file."""
from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest

from common.recording import KeyFilter
from tests.helpers import ROOT

DEMO_KEYS = ["rig/stereo/calibration", "rig/stereo/frame", "rig/odom/*", "rig/status/*", "rig/**/field",
             "rig/tr$*/pose"]


@pytest.mark.parametrize("key, kept", [
    ("rig/stereo/frame", True), ("rig/stereo/calibration", True), ("rig/stereo/frames", False),
    ("rig/odom/wheels", True), ("rig/odom", False), ("rig/odom/wheels/raw", False),   # '*' is one chunk
    ("rig/status/evolver", True), ("rig/planner/field", True), ("rig/a/b/field", True),   # '**' any number
    ("rig/truth/pose", True), ("rig/track/pose", True), ("rig/truth/depth", False),      # '$*' in a chunk
    ("other/stereo/frame", False), ("rig/fusion/pose", False),
])
def test_a_key_is_kept_when_a_pattern_includes_it(key, kept):
    assert KeyFilter(DEMO_KEYS)(key) is kept


def test_everything_under_the_robot_and_the_robot_key_itself_with_double_star():
    keep = KeyFilter(["rig/**"])
    assert keep("rig") and keep("rig/a/b/c") and not keep("rigs/a")


def test_decisions_are_remembered_within_a_bound_and_stay_right_past_it():
    keep = KeyFilter(["rig/odom/*"], cache_size=100)
    for i in range(1000):                  # a bus carrying many keys (an attacker's, say)
        assert keep(f"rig/odom/w{i}") and not keep(f"rig/x/w{i}")
        assert keep.remembered_keys <= 100
    assert keep("rig/odom/w5") and keep.remembered_keys <= 100


def test_a_bad_pattern_is_refused_with_one_line_and_no_file(tmp_path):
    with pytest.raises(ValueError, match="--keys 'rig/odom/' is not a Zenoh key expression"):
        KeyFilter(["rig/odom/"])
    done = subprocess.run([sys.executable, "-m", "deploy.cli", "record", "--out", str(tmp_path / "r.mcap"),
                           "--keys", "odom//x"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1 and "not a Zenoh key expression" in lines[0], done.stderr
    assert not list(tmp_path.iterdir())



def test_the_localisers_image_stream_is_not_recorded_even_with_everything(tmp_path, zenoh_port):
    """flies/population/@image is flies/population again plus a 307 kB image the recording has in its
    frames: its verbatim key keeps it out of a recorder's ``**`` (and of its traffic)."""
    from common import messages as m
    from common.bus import BusOptions, Node
    from common.recording import RecordingReader
    from tests.helpers import hub, start_module, stop, wait_until
    out = tmp_path / "all.mcap"
    recorder = start_module("services.recorder", "--out", str(out), "--keys", "flies/**", port=zenoh_port,
                            log_path=tmp_path / "rec.log")
    try:
        with Node("tester", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
            heartbeats = []
            node.subscribe("status/recorder", m.Heartbeat, heartbeats.append)
            pubs = [node.publisher(key, reliable=True) for key in ("flies/population/@image", "flies/population")]
            assert wait_until(lambda: heartbeats and pubs[1].has_subscribers(), 30), "recorder did not come up"
            pop = m.FlyPopulation(positions=np.zeros((3, 3), np.float32), fitness=np.ones(3, np.float32),
                                  image=np.zeros((4, 5), np.uint8), header=m.header(1, 10**9, m.CAMERA_LEFT_OPTICAL))
            for pub in pubs:
                pub.publish(pop)
            assert not pubs[0].has_subscribers()
            assert wait_until(lambda: heartbeats[-1].progress >= 1, 10), "flies/population was not recorded"
    finally:
        assert stop(recorder) == 0, (tmp_path / "rec.log").read_text()[-2000:]
    keys = [msg.key for msg in RecordingReader(out).messages()]
    assert keys == ["rig/flies/population"]
