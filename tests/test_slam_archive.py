"""The map's hard size bound: a long run that keeps mapping the same corridor holds at most
max_archive_keyframes, drops the views it has mapped again before the only ones of a place, keeps
tracking through the rebuilt graph, and saves (and reloads) a bounded map."""
from __future__ import annotations

import numpy as np
import pytest

from common import messages as m
from common.geometry import planar_pose
from common.slam import LocaliserConfig
from common.slam.backend import ArchiveConfig
from common.slam.core import LocaliserCore
from common.slam.mapfile import load_map
from tests.test_relocalise import CALIB, corridor, errors, population


def shuttle():
    """True planar poses, always facing +x: 0 → 12 m, reversing back to 0, and 0 → 12 m again."""
    out, back, again = np.arange(0.0, 12.01, 0.3), np.arange(12.0, -0.01, -0.3), np.arange(0.0, 12.01, 0.3)
    return [(float(x), 0.0, 0.0) for x in np.concatenate([out, back[1:], again[1:]])]


def test_a_long_run_keeps_a_bounded_map_and_drops_remapped_views_first(tmp_path):
    rng = np.random.default_rng(7)
    world = corridor(rng)
    core = LocaliserCore(LocaliserConfig(max_keyframes=4), archive=ArchiveConfig(max_archive_keyframes=12))
    core.on_calibration(m.calibration_to_msg(CALIB, 1, 1))
    sizes, worst = [], 0.0
    poses = shuttle()
    for k, p in enumerate(poses):
        T = planar_pose(*p)
        out = core.on_population(population(T, world, rng, k + 1, (k + 1) * 500_000_000, T))
        assert out.estimate is not None, out.reason
        worst = max(worst, errors(out.estimate.T_map_base, T)[0])
        sizes.append(len(core.localiser.backend.archive))
    backend = core.localiser.backend
    assert max(sizes) <= 12 and backend.dropped > 0
    assert worst < 0.2                                        # tracking went on through every rebuild
    assert len(core.trajectory()[0]) == len(poses)
    # every pass maps the corridor again: twins went first, so every stretch of it is still in the map
    kept = list(backend.archive.values())
    xs = np.array([kf.T_map_base[0, 3] for kf in kept])
    gaps = np.diff(np.sort(np.r_[xs, 0.0, 12.0]))
    assert gaps.max() < 2 * LocaliserConfig().keyframe_distance_m, np.round(np.sort(xs), 1)
    assert core.save_map(tmp_path / "map.mcap")
    saved = load_map(tmp_path / "map.mcap")
    assert len(saved.keyframes) == len(kept) <= 12
    assert all(len(kf.points) > 100 for kf in saved.keyframes)


def test_a_bad_bound_is_refused_with_one_line():
    with pytest.raises(ValueError, match="max_archive_keyframes must be at least 1"):
        ArchiveConfig(max_archive_keyframes=0)


def test_a_population_refused_for_want_of_calibration_counts_when_sent_again():
    """A localiser still asking for the calibration refuses the first population; the same population
    sent again once the calibration is in is localised, not dismissed as a repeat."""
    rng = np.random.default_rng(3)
    T = planar_pose(0.0, 0.0, 0.0)
    pop = population(T, corridor(rng), rng, 1, 500_000_000, T)
    core = LocaliserCore(LocaliserConfig())
    assert core.on_population(pop).reason == "no calibration"
    core.on_calibration(m.calibration_to_msg(CALIB, 1, 1))
    out = core.on_population(pop)
    assert out.estimate is not None, out.reason
    assert core.on_population(pop).reason == "republished"
