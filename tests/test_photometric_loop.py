"""Loop closure without wheels, on real images: the car drives frames 50-99 of the KITTI clip on the
even frames and backs up to where it started on the odd ones, so that a revisit sees each place from
another spot (0.4-0.8 m along the street) than the way out did.  On the way back a new keyframe near
an old one is aligned to it on the old keyframe's fly neighbourhoods; δ's loop factors on these deep
street scenes were decimetres and degrees off, and bent the tracked trajectory instead of correcting it."""
from __future__ import annotations

import numpy as np
import pytest

from common.geometry import invert, so3_log
from common.importers import StereoDataset
from common.importers.base import write_recording
from common.importers.kitti import load_kitti
from common.lockstep import run_lockstep
from common.recording import RecordingReader
from common.slam.localiser import FlyLocaliser
from common.slam.mapfile import load_map
from common.trajectory_metrics import associate

FIRST = 50        # frames 50..99 of the clip: 40 m out, 40 m back
STOP = 5          # frames held at the far end


@pytest.fixture(scope="module")
def there_and_back(shared_data, tmp_path_factory):
    seq = shared_data / "kitti-00-frames-0-99" / "sequences" / "00"
    if not seq.is_dir():
        pytest.skip(f"{seq} not found (the shared real KITTI clip)")
    ds = load_kitti(seq)
    out_leg = np.arange(FIRST, len(ds.stamps_ns), 2)
    index = np.r_[out_leg, np.full(STOP, out_leg[-1]), np.arange(len(ds.stamps_ns) - 1, FIRST - 1, -2)]
    T_map_cam = ds.truth_poses[index] @ ds.calibration.T_base_camera
    T_bc = ds.calibration.T_base_camera
    truth = T_bc @ (invert(T_map_cam[0]) @ T_map_cam) @ invert(T_bc)
    stamps = ds.stamps_ns[0] + np.arange(len(index), dtype=np.int64) * 100_000_000
    drive = StereoDataset("KITTI 00 50-99 out on even frames, back on odd", ds.calibration, stamps,
                          lambda i: ds.load_pair(int(index[i])), stamps, truth)
    out = tmp_path_factory.mktemp("loop") / "there_and_back.mcap"
    write_recording(drive, out)
    result = run_lockstep(RecordingReader(out).messages())
    return result, {int(s): int(k) for s, k in zip(stamps, index)}


def test_the_way_back_closes_a_loop_that_agrees_with_the_truth(there_and_back):
    result, source_frame = there_and_back
    backend = result.localiser.localiser.backend
    accepted = [loop for loop in backend.loops if loop.accepted]
    assert accepted, [loop.reason for loop in backend.loops]
    stamps = {kf.id: kf.stamp_ns for kf in backend.archive.values()}
    ids = list(stamps)
    i_kf, j_truth = associate([stamps[k] for k in ids], result.truth_stamps, 20_000_000)
    truth = {ids[a]: np.asarray(result.truth[b]) for a, b in zip(i_kf, j_truth)}
    loops = [e for e in backend.graph.edges().values() if e.kind == "registration"]
    assert len(loops) == len(accepted)
    for e in loops:
        assert source_frame[stamps[e.i]] % 2 == 0 and source_frame[stamps[e.j]] % 2 == 1   # other images
        E = invert(invert(truth[e.i]) @ truth[e.j]) @ np.asarray(e.T_i_j)
        assert np.linalg.norm(E[:3, 3]) < 0.05 and np.degrees(np.linalg.norm(so3_log(E[:3, :3]))) < 0.5
    # back near the start, 40 m away and back
    assert len(result.estimated) == len(result.truth)
    assert np.linalg.norm(result.estimated[-1][:3, 3] - result.truth[-1][:3, 3]) < 0.3


def test_a_saved_camera_only_map_keeps_the_images_its_loops_align_on(there_and_back, tmp_path):
    core = there_and_back[0].localiser
    loc = core.localiser
    assert core.save_map(tmp_path / "map.mcap")
    data = load_map(tmp_path / "map.mcap")
    fresh = FlyLocaliser(loc.T_base_camera, loc.config, calibration=loc.calibration)
    fresh.load_map(data)
    saved = {kf.id: kf for kf in loc.map_keyframes()}
    loaded = fresh.map_keyframes()
    assert len(loaded) == len(saved)
    assert all(kf.image is not None and np.array_equal(kf.image, saved[kf.id].image) for kf in loaded)
    assert fresh._loop_is_photometric(loaded[0], loaded[-1])
