"""The loop scenario: a closed 40-60 m corridor circuit, driven without touching a wall, whose last view
is the first one again while every other stretch looks different (what loop closure needs)."""
from __future__ import annotations

import numpy as np
import pytest

from common.geometry import wrap_angle
from common.sim import Simulator, World, load_scenario, scenario_path


def textured_fraction(img) -> float:
    """Pixels with a horizontal step of more than 2 grey levels."""
    g = img.astype(float).mean(axis=2)
    return float(np.mean(np.abs(np.diff(g, axis=1)) > 2))


@pytest.fixture(scope="module")
def lap():
    """Drive the whole scripted lap (noise-free 160×120 renders every 10 s and at the end)."""
    scn = load_scenario(scenario_path("loop"))
    scn.camera.read_noise = scn.camera.shot_noise = 0.0
    sim = Simulator(scn, seed=0, width=160, height=120)
    world = sim.world
    poses, frames = [sim.pose], [sim.render()]
    clearance = [world.min_clearance(*sim.pose[:2])]
    while not sim.finished and sim.time_ns < 300e9:
        sim.advance(0.5)
        poses.append(sim.pose)
        clearance.append(world.min_clearance(*sim.pose[:2]))
        if sim.time_ns % int(10e9) == 0:
            frames.append(sim.render())
    frames.append(sim.render())
    return scn, sim, np.array(poses), np.array(clearance), frames


def test_loop_is_a_closed_circuit_of_40_to_60_m(lap):
    scn, sim, poses, clearance, _ = lap
    assert scn.name == "loop" and sim.finished
    start, end = poses[0], poses[-1]
    assert np.hypot(*(end[:2] - start[:2])) < 0.03
    assert abs(np.rad2deg(wrap_angle(end[2] - start[2]))) < 2.0
    length = np.sum(np.hypot(*np.diff(poses[:, :2], axis=0).T))
    assert 40.0 <= length <= 60.0
    # A circuit, not an out-and-back: the path encloses the block (shoelace area, 16 m × 9 m centre line).
    x, y = poses[:, 0], poses[:, 1]
    area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    assert area > 100.0
    assert clearance.min() > 0.2                   # never near a wall or a box


def shift_tolerant_difference(a, b, max_shift: int = 4) -> float:
    """Mean absolute grey-level difference of two views, minimised over small horizontal shifts (the
    scripted lap ends within ~1.5° of its start heading: ~3 px here)."""
    a, b = a.astype(float).mean(axis=2), b.astype(float).mean(axis=2)
    w = a.shape[1]
    return min(np.abs(a[:, max_shift + s:w - max_shift + s] - b[:, max_shift:w - max_shift]).mean()
               for s in range(-max_shift, max_shift + 1))


def test_loop_renders_textured_views_and_only_the_last_one_repeats_the_first(lap):
    _, _, _, _, frames = lap
    assert len(frames) >= 10
    for f in frames:
        assert textured_fraction(f.left) > 0.1
        assert np.isfinite(f.depth).mean() > 0.95 and np.nanmax(f.depth[np.isfinite(f.depth)]) < 20.0
    first, last = frames[0], frames[-1]
    same_place = shift_tolerant_difference(last.left, first.left)
    # Views away from the start (> 2 m: the lap's last metres re-drive its first) all look different.
    elsewhere = [shift_tolerant_difference(f.left, first.left) for f in frames[1:-1]
                 if np.hypot(*(f.T_map_base[:2, 3] - first.T_map_base[:2, 3])) > 2.0]
    assert len(elsewhere) >= 8
    assert same_place < 3.0
    assert min(elsewhere) > 3 * same_place + 5.0


def test_loop_start_is_clear_of_the_walls():
    scn = load_scenario(scenario_path("loop"))
    assert World(scn).min_clearance(*scn.start[:2]) > 0.5
