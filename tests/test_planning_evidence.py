"""Evidence memory: what a sensor no longer sees is remembered; what it sees and finds empty is forgotten."""
import math

import numpy as np
import pytest

from common.planning import HarmonicPlanner, PlannerConfig, PlannerInputError, SensorView


def wall(x0, x1, y, z=0.5, n=200):
    xs = np.linspace(x0, x1, n)
    return np.stack([xs, np.full_like(xs, y), np.full_like(xs, z)], axis=1)


def corridor_planner():
    """A 1.6 m wide corridor along x (walls at y = -0.8 and +0.8) in an open 10 m x 6 m map, target at
    (8.5, 0).  Around the walls the map is open: a gap in a wall is a way out of the corridor."""
    pl = HarmonicPlanner(PlannerConfig(resolution=0.05, size_m=(10.0, 6.0), origin=(0.0, -3.0),
                                       robot_radius=0.2, evidence_half_life_s=1.0, unseen_half_life_s=60.0))
    pl.set_target(8.5, 0.0, 0.3)
    return pl


def forward_view(x, range_m=3.0):
    """A camera at (x, 0) looking along +x with a 70 degree field of view."""
    return SensorView(x, 0.0, 0.0, math.radians(35.0), range_m, 0.3)


def test_walls_that_left_the_camera_view_still_block():
    pl = corridor_planner()
    walls = np.vstack([wall(1.0, 4.0, -0.8), wall(1.0, 4.0, 0.8)])
    for k in range(10):                    # seen from x = 0 for 1 s
        pl.update_flies(walls, np.ones(len(walls)), k * 100_000_000, view=forward_view(0.0))
    # The robot drove on: now at x = 3.5 looking ahead, the walls at 1..3 m are beside and behind it.
    # 10 s pass with flies only on the walls ahead (4..6.5 m).
    ahead = np.vstack([wall(4.0, 6.5, -0.8), wall(4.0, 6.5, 0.8)])
    for k in range(10, 110):
        pl.update_flies(ahead, np.ones(len(ahead)), k * 100_000_000, view=forward_view(3.5))
    pl.solve()
    col = pl.cell_of(2.0, 0.8)[1]
    rows_wall = [pl.cell_of(2.0, y)[0] for y in (-0.8, 0.8)]
    assert not pl.passable[rows_wall, col].any(), "walls behind the camera were forgotten"
    # ... so the path from x = 1.5 follows the corridor instead of leaving it through a forgotten wall.
    path = pl.path_from(1.5, 0.0)
    assert len(path) > 0 and np.abs(path[:, 1]).max() < 0.8


def test_without_a_view_walls_out_of_sight_fade_as_before():
    pl = corridor_planner()
    walls = np.vstack([wall(1.0, 4.0, -0.8), wall(1.0, 4.0, 0.8)])
    for k in range(10):
        pl.update_flies(walls, np.ones(len(walls)), k * 100_000_000)
    ahead = np.vstack([wall(4.0, 6.5, -0.8), wall(4.0, 6.5, 0.8)])
    for k in range(10, 110):
        pl.update_flies(ahead, np.ones(len(ahead)), k * 100_000_000)
    pl.solve()
    assert pl.passable[pl.cell_of(2.0, 0.8)]


def test_a_phantom_in_view_is_forgotten_once_no_fly_renews_it():
    pl = corridor_planner()
    phantom = np.column_stack([np.full(100, 2.5), np.linspace(-0.3, 0.3, 100), np.full(100, 0.5)])
    for k in range(10):
        pl.update_flies(phantom, np.ones(100), k * 100_000_000, view=forward_view(0.0))
    pl.solve()
    assert not pl.passable[pl.cell_of(2.5, 0.0)]
    other = wall(1.0, 4.0, 0.8)            # later populations: flies on a wall only, phantom in view
    for k in range(10, 60):
        pl.update_flies(other, np.ones(len(other)), k * 100_000_000, view=forward_view(0.0))
    pl.solve()
    assert pl.passable[pl.cell_of(2.5, 0.0)]


def test_sonar_echoes_are_kept_after_the_robot_moved_away():
    pl = corridor_planner()
    echo = np.column_stack([np.linspace(2.0, 3.0, 20), np.full(20, -0.8)])
    for k in range(5):                      # robot at (2.5, 0): the wall 0.8 m to its right echoes
        pl.update_sonar(echo, k * 100_000_000, view=SensorView(2.5, 0.0, 0.0, math.pi, 1.3))
    for k in range(5, 105):                 # 10 s later the robot is at x = 6, nothing within 1.3 m
        pl.update_sonar(np.zeros((0, 2)), k * 100_000_000, view=SensorView(6.0, 0.0, 0.0, math.pi, 1.3))
    pl.solve()
    assert not pl.passable[pl.cell_of(2.5, -0.8)]
    for k in range(105, 135):               # back at (2.5, 0): no echo there any more -> freed
        pl.update_sonar(np.zeros((0, 2)), k * 100_000_000, view=SensorView(2.5, 0.0, 0.0, math.pi, 1.3))
    pl.solve()
    assert pl.passable[pl.cell_of(2.5, -0.8)]


def test_sensor_view_rejects_bad_values():
    with pytest.raises(PlannerInputError, match="half_fov_rad"):
        SensorView(0.0, 0.0, 0.0, 0.0, 3.0)
    with pytest.raises(PlannerInputError, match="near_m < range_m"):
        SensorView(0.0, 0.0, 0.0, 1.0, 3.0, near_m=4.0)
    with pytest.raises(PlannerInputError, match="finite"):
        SensorView(float("nan"), 0.0, 0.0, 1.0, 3.0)
    pl = corridor_planner()
    with pytest.raises(PlannerInputError, match="SensorView"):
        pl.update_flies(wall(1, 2, 0.5), np.ones(200), 0, view=(0.0, 0.0, 0.0))
    with pytest.raises(PlannerInputError, match="unseen_half_life_s"):
        PlannerConfig(unseen_half_life_s=0.0)


def test_the_service_turns_to_look_again_when_there_is_no_path():
    from services.planner import velocity_command
    from common.planning import Command
    pl = corridor_planner()
    across = np.column_stack([np.full(200, 3.0), np.linspace(-3.0, 3.0, 200), np.full(200, 0.5)])
    for k in range(10):                     # a wall across the whole map, seen once
        pl.update_flies(across, np.ones(200), k * 100_000_000, view=forward_view(0.0))
    pl.solve()
    c = pl.command((1.0, 0.0, 0.0))
    assert c.reason == "no path"
    look = velocity_command(c, 0.3)
    assert not look.stop and look.linear_mps == 0.0 and look.angular_radps == 0.3
    assert velocity_command(c, 0.0).stop
    moving = velocity_command(Command(0.2, -0.1, False, "following field"), 0.3)
    assert (moving.linear_mps, moving.angular_radps, moving.reason) == (0.2, -0.1, "following field")
