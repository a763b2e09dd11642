"""Closed loop: a differential-drive robot with a fly-producing camera stand-in and a sonar ring reaches
its target among walls, with the harmonic planner in the loop at 10 Hz."""
import math
import time

import numpy as np
import pytest

from common.planning.closed_loop import PerceptionConfig, perceive_flies, ray_hits, run_closed_loop
from common.planning.scenarios import make_scenario


def test_ray_hits_finds_the_nearest_wall():
    segs = np.array([[[2.0, -1.0], [2.0, 1.0]], [[3.0, -5.0], [3.0, 5.0]]])
    r = ray_hits(np.zeros(2), np.array([0.0, math.pi, math.atan2(0.5, 2.0)]), segs, 10.0)
    assert r[0] == pytest.approx(2.0) and np.isinf(r[1]) and r[2] == pytest.approx(math.hypot(2, 0.5))
    assert np.isinf(ray_hits(np.zeros(2), np.array([0.0]), segs, 1.5)[0])


def test_camera_stand_in_sees_only_walls_in_its_field_of_view():
    segs = np.array([[[-10.0, 3.0], [1.0, 3.0]]])           # a wall along y = 3, to the robot's left
    pc = PerceptionConfig(outlier_fraction=0.0)
    rng = np.random.default_rng(0)
    pts, fit = perceive_flies((0.0, 0.0, 0.0), segs, pc, rng)  # looking along +x: wall outside the view
    assert len(pts) == 0
    pts, fit = perceive_flies((0.0, 0.0, math.pi / 2), segs, pc, rng)   # looking at it
    assert len(pts) > 100 and len(fit) == len(pts)
    assert np.abs(pts[:, 1] - 3.0).max() < 0.15                        # on the wall, within noise
    bearing = np.arctan2(pts[:, 1], pts[:, 0]) - math.pi / 2
    assert np.abs(bearing).max() <= pc.fov_rad / 2 + 0.05


def test_robot_reaches_the_target_in_at_least_9_of_10_seeded_worlds():
    t0 = time.perf_counter()
    results = []
    for seed in range(10):
        sc = make_scenario(seed)
        res = run_closed_loop(sc.segments, sc.start, sc.target, sc.bounds, seed=seed)
        results.append(res)
        print(f"seed {seed} {sc.name:9s} reached={res.reached} collided={res.collided} reason={res.reason!r} "
              f"time={res.time_s:.1f}s min_clearance={res.min_clearance_m:.3f} m")
        if res.reached:
            end = res.path[-1, :2]
            assert math.hypot(*(end - sc.target[:2])) <= sc.target[2] + 1e-9
    ok = sum(r.reached and not r.collided for r in results)
    min_clear = min(r.min_clearance_m for r in results)
    print(f"closed loop: {ok}/10 reached without touching an obstacle, minimum clearance {min_clear:.3f} m "
          f"({time.perf_counter() - t0:.1f} s)")
    assert ok >= 9
    assert not any(r.collided for r in results)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["obstacles_boxes", "obstacles_doorway", "obstacles_dead_end"])
def test_robot_reaches_the_target_in_the_simulator_planner_scenarios(name):
    sim_scenario = pytest.importorskip("common.sim.scenario")
    sim_world = pytest.importorskip("common.sim.world")
    sc = sim_scenario.load_scenario(sim_scenario.scenario_path(name))
    segs = np.asarray(sim_world.World(sc).obstacle_segments(0.05, 1.0))
    bounds = (segs[..., 0].min(), segs[..., 1].min(), segs[..., 0].max(), segs[..., 1].max())
    res = run_closed_loop(segs, sc.start, (*sc.target, 0.3), bounds, seed=0, timeout_s=120)
    print(f"{name}: reached={res.reached} collided={res.collided} reason={res.reason!r} "
          f"time={res.time_s:.1f}s min_clearance={res.min_clearance_m:.3f} m")
    assert res.reached and not res.collided
