"""Planner commands: stop reasons, speed and turn limits, slowing near obstacles and the target."""
import math

import numpy as np

from common.planning import HarmonicPlanner, PlannerConfig


def room(**kw):
    """A 6 m x 4 m grid, target at (5, 2)."""
    cfg = PlannerConfig(resolution=0.05, size_m=(6.0, 4.0), origin=(0.0, 0.0), **kw)
    pl = HarmonicPlanner(cfg)
    pl.set_target(5.0, 2.0, 0.3)
    return pl


def ring_flies(cx, cy, radius, n=400, z=0.5):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.column_stack([cx + radius * np.cos(a), cy + radius * np.sin(a), np.full(n, z)])


def test_stop_reasons():
    pl = HarmonicPlanner(PlannerConfig(size_m=(6.0, 4.0), origin=(0.0, 0.0)))
    assert pl.command((1.0, 1.0, 0.0)) == pl.command((1.0, 1.0, 0.0))
    assert pl.command((1.0, 1.0, 0.0)).reason == "no target"
    assert pl.command((1.0, 1.0, 0.0)).stop
    pl.set_target(5.0, 2.0, 0.3)
    assert pl.command((1.0, 1.0, 0.0)).reason == "not solved"
    pl.solve()
    assert pl.command((4.9, 2.1, 0.0)).reason == "target reached"
    assert pl.command((-3.0, 1.0, 0.0)).reason == "outside grid"
    moving = pl.command((1.0, 1.0, 0.0))
    assert not moving.stop and moving.reason == "following field"

    # robot enclosed by a ring of flies: free where it stands, but no way out
    pl.update_flies(ring_flies(1.5, 2.0, 0.8), np.ones(400), 0)
    pl.solve()
    cmd = pl.command((1.5, 2.0, 0.0))
    assert cmd.stop and cmd.reason == "no path" and cmd.v == 0 and cmd.omega == 0

    # the target itself walled in
    pl2 = room()
    pl2.update_flies(ring_flies(5.0, 2.0, 0.2), np.ones(400), 0)
    pl2.solve()
    assert pl2.command((1.0, 1.0, 0.0)).reason == "target blocked"
    pl2.clear_target()
    assert pl2.command((1.0, 1.0, 0.0)).reason == "no target"
    pl2.set_target(50.0, 2.0, 0.3)                   # beyond the fixed map extent
    assert pl2.solve().status == "target outside grid"
    assert pl2.command((1.0, 1.0, 0.0)).reason == "target outside grid"


def test_limits_and_turning_on_the_spot():
    pl = room(v_max=0.4, omega_max=1.0)
    pl.solve()
    for yaw in np.linspace(-math.pi, math.pi, 13):
        cmd = pl.command((1.0, 2.0, yaw))
        assert 0.0 <= cmd.v <= 0.4 + 1e-12 and abs(cmd.omega) <= 1.0 + 1e-12
    facing = pl.command((1.0, 2.0, 0.0))
    assert facing.v > 0.35 and abs(facing.omega) < 0.05          # straight at the target: full speed
    away = pl.command((1.0, 2.0, math.pi))
    assert away.v == 0.0 and abs(away.omega) == 1.0               # facing away: turn in place
    left = pl.command((1.0, 2.0, 0.5))
    assert left.omega < 0                                          # target to the right: turn right


def aligned_command(pl, x, y):
    """Command for a robot at (x, y) already facing along the field (turn until omega ~ 0)."""
    yaw = 0.0
    for _ in range(50):
        cmd = pl.command((x, y, yaw))
        yaw += cmd.omega / pl.cfg.heading_gain
    assert abs(cmd.omega) < 1e-3
    return cmd


def test_slows_near_obstacles_and_at_the_target():
    pl = room()
    wall = np.column_stack([np.linspace(0.0, 6.0, 300), np.full(300, 1.0), np.full(300, 0.5)])
    pl.update_flies(wall, np.ones(300), 0)
    pl.solve()
    near_wall = aligned_command(pl, 2.0, 1.35)      # 0.35 m from the wall (inflation 0.25)
    open_space = aligned_command(pl, 2.0, 2.5)
    assert 0 < near_wall.v < 0.5 * open_space.v
    near_target = aligned_command(pl, 4.55, 2.0)    # 0.15 m short of the target disc
    assert 0 < near_target.v < 0.5 * open_space.v


def test_escapes_when_inside_the_inflated_obstacles():
    pl = room()
    wall = np.column_stack([np.linspace(0.0, 6.0, 300), np.full(300, 1.0), np.full(300, 0.5)])
    pl.update_flies(wall, np.ones(300), 0)
    pl.solve()
    cmd = pl.command((2.0, 1.15, math.pi / 2))      # 15 cm from the wall, facing away from it
    assert not cmd.stop and cmd.reason == "escaping obstacle" and 0 < cmd.v <= pl.cfg.escape_speed


def test_path_from_descends_to_the_target_around_an_obstacle():
    pl = room()
    # a wall across the direct line, leaving a gap at the top
    wall = np.column_stack([np.full(300, 3.0), np.linspace(0.0, 3.0, 300), np.full(300, 0.5)])
    pl.update_flies(wall, np.ones(300), 0)
    pl.solve()
    path = pl.path_from(1.0, 1.0)
    assert np.hypot(*(path[-1] - [5.0, 2.0])) <= 0.3 + pl.resolution
    field = pl.field
    rows = np.floor((path[:, 1] - pl.grid_origin[1]) / pl.resolution).astype(int)
    cols = np.floor((path[:, 0] - pl.grid_origin[0]) / pl.resolution).astype(int)
    assert np.all(np.diff(field[rows, cols]) < 0)
    assert path[:, 1].max() > 3.0 + pl.cfg.inflation_m - pl.resolution  # it goes through the gap
    assert pl.path_from(-5.0, 0.0).shape == (0, 2)
