"""Harmonic-function planner: occupancy from the fly population and sonar, a log-space harmonic field kept
up to date by warm-started multigrid, and a differential-drive command down its gradient.

API (what the planner service calls)::

    from common.planning import HarmonicPlanner, PlannerConfig
    pl = HarmonicPlanner(PlannerConfig(resolution=0.05, size_m=(20.0, 20.0), origin=(-10.0, -10.0),
                                       robot_radius=0.2))
    pl.set_target(x, y, radius)                        # map frame; clear_target() to drop it
    pl.update_flies(points_map, fitness, stamp_ns, view=None)  # (N, 3) map frame, (N,) fitness, int ns;
                                                       # view=SensorView(x, y, yaw, half_fov_rad, range_m, near_m):
                                                       # evidence is forgotten fast only inside the camera's view
    pl.update_sonar(points_xy, stamp_ns, view=None)    # (M, 2) map-frame echo points (M may be 0)
    rep = pl.solve(max_ms=None, max_cycles=None)       # SolveReport(cycles, converged, ..., status)
    cmd = pl.command((x, y, yaw))                      # Command(v, omega, stop, reason)
    pl.field          # (H, W) -log(1 - u): 0 on the target, +inf on obstacles / unreachable cells
    pl.log_phi        # (H, W) log(1 - u) (= -field)
    pl.grid_origin, pl.resolution, pl.shape            # field[row, col] centre = origin + (col+.5, row+.5)*res
    pl.passable, pl.clearance                          # inflated free space, distance to obstacles (m)
    pl.path_from(x, y)                                 # (K, 2) map-frame descent path to the target

Stop reasons: 'target reached', 'no path', 'no target', 'target blocked', 'target outside grid',
'not solved', 'outside grid', 'robot in obstacle'; while moving the reason is 'following field' or 'escaping obstacle'.
Bad input raises ``PlannerInputError`` (a ValueError).

Modules: ``config`` (PlannerConfig, Command, SolveReport), ``occupancy`` (evidence grid), ``harmonic``
(grid kernels), ``multigrid`` (the log-space solver), ``controller`` (heading -> (v, omega)),
``planner`` (HarmonicPlanner), ``closed_loop`` (kinematic harness), ``scenarios`` (seeded worlds).
"""
from .config import SensorView, Command, PlannerConfig, PlannerInputError, SolveReport
from .planner import HarmonicPlanner

__all__ = ["SensorView", "Command", "HarmonicPlanner", "PlannerConfig", "PlannerInputError", "SolveReport"]
