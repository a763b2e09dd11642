"""Visual-only tracking of a car that stops and backs up the street it came down (the real KITTI clip's
last 30 frames forwards, the last one held for 5 frames, then backwards): the constant-velocity model
predicts standing still, the images say 0.45 m a frame backwards."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from bench.real_variants import variant
from common.importers.base import write_recording
from common.importers.kitti import load_kitti
from common.lockstep import run_lockstep
from common.recording import RecordingReader

FIRST = 70        # frames 70..99 of the clip: 0.4-0.8 m a frame, 19 m


@pytest.fixture(scope="module")
def there_and_back(shared_data, tmp_path_factory):
    seq = shared_data / "kitti-00-frames-0-99" / "sequences" / "00"
    if not seq.is_dir():
        pytest.skip(f"{seq} not found (the shared real KITTI clip)")

    def load():
        ds = load_kitti(seq)
        keep = slice(FIRST, None)
        return replace(ds, stamps_ns=ds.stamps_ns[keep], truth_stamps_ns=ds.truth_stamps_ns[keep],
                       truth_poses=ds.truth_poses[keep], load_pair=lambda i: ds.load_pair(FIRST + i))

    out = tmp_path_factory.mktemp("reversal") / "there_and_back.mcap"
    write_recording(variant(load, "outback"), out)
    return run_lockstep(RecordingReader(out).messages())


def test_backing_up_after_a_stop_is_tracked_and_the_end_meets_the_start(there_and_back):
    result = there_and_back
    assert result.frames == 30 + 5 + 29
    turn = 30 + 5                        # the first frame backwards
    refused = [k for k, s in enumerate(result.statuses) if k >= turn and s != "ok"]
    assert len(refused) <= 1, [result.statuses[k] for k in refused]
    errors = [np.linalg.norm(E[:3, 3] - T[:3, 3]) for E, T in zip(result.estimated, result.truth)]
    assert max(errors[turn:]) < 0.5
    # back at the start: the truth's end is its start, 19 m away and back
    assert np.linalg.norm(result.estimated[-1][:3, 3] - result.estimated[0][:3, 3]) < 0.3
