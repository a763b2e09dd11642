"""Configuration, command and report types of the harmonic planner."""
from __future__ import annotations

import math
from dataclasses import dataclass, field


class PlannerInputError(ValueError):
    """Bad input to the planner (wrong shape, non-finite value, impossible configuration)."""


@dataclass(frozen=True)
class PlannerConfig:
    """Everything the harmonic planner needs to know, in SI units and the map frame (x, y; z up).

    The grid is a *fixed map-frame extent* (``origin`` = map coordinates of its lower-left corner,
    ``size_m`` = (width along x, height along y)), not a window that follows the robot: the flies and the
    target live in the map frame, a fixed grid keeps the warm start valid cell for cell (a scrolling grid
    would have to shift the field and invent values on the entering edge every cycle), and a target
    outside a robot-centred window would have to be projected onto its border, which creates false
    goals.  At 5 cm a 20 m x 20 m map is only 400 x 400 cells.

    Occupancy evidence per cell is a decaying sum of fly weights (fitness scaled so that the mean positive
    fitness of an update counts 1) and sonar hits, capped at ``evidence_cap`` so that a cell whose flies
    moved away is freed at most ``half_life * log2(cap / occupied_weight)`` later.  Evidence given with a
    SensorView decays at ``evidence_half_life_s`` inside that view, where the sensor would renew it, and
    at ``unseen_half_life_s`` elsewhere, so walls beside and behind a forward camera are not forgotten.
    """

    resolution: float = 0.1
    size_m: tuple[float, float] = (10.0, 10.0)
    origin: tuple[float, float] = (-5.0, -5.0)
    robot_radius: float = 0.22
    safety_margin: float = 0.05          # added to the robot radius when inflating obstacles
    fly_z_min: float = 0.05              # flies between fly_z_min and fly_z_max (map z) are obstacles
    fly_z_max: float = 1.0               # above it: overhead, not an obstacle for a ground robot
    occupied_weight: float = 2.0         # evidence at which a cell is an obstacle
    evidence_cap: float = 8.0            # evidence is capped here (bounds how long a vacated cell stays occupied)
    evidence_half_life_s: float = 2.0    # evidence half-life inside the view that can renew it
    unseen_half_life_s: float = 60.0     # evidence half-life outside the current view
    sonar_weight: float = 2.0            # evidence per sonar echo
    # Solver (multigrid.py).
    tolerance: float = 1e-4              # converged when one cycle changes no cell's phi by more than this, relatively
    mg_over_correction: float = 2.0      # exponent of the fine level's coarse factor (see multigrid.py)
    mg_smoothing_sweeps: int = 1         # Gauss-Seidel sweeps before and after each coarse correction
    mg_krylov_levels: int = 1            # coarse levels 1..k use K-cycles, deeper ones V-cycles
    mg_coarsest: int = 48                # most unknowns of the directly solved coarsest level
    max_cycles: int = 200
    # Controller.
    v_max: float = 0.4
    omega_max: float = 1.0
    heading_gain: float = 2.0
    turn_in_place_rad: float = math.radians(60.0)
    slow_clearance_m: float = 0.25       # free space beyond the inflated obstacles under which to slow down
    slow_target_m: float = 0.8           # distance to the target region under which to slow down
    min_speed_fraction: float = 0.2
    escape_speed: float = 0.08           # speed used to back out of inflated obstacles

    def __post_init__(self):
        positive = ["resolution", "robot_radius", "evidence_half_life_s", "unseen_half_life_s", "occupied_weight",
                    "evidence_cap", "tolerance", "v_max", "omega_max", "heading_gain"]
        for name in positive:
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise PlannerInputError(f"PlannerConfig.{name} must be a finite positive number, got {v!r}")
        if len(self.size_m) != 2 or min(self.size_m) < 4 * self.resolution:
            raise PlannerInputError(f"PlannerConfig.size_m must be (width, height) of at least 4 cells, "
                                    f"got {self.size_m!r}")
        if len(self.origin) != 2 or not all(math.isfinite(o) for o in self.origin):
            raise PlannerInputError(f"PlannerConfig.origin must be a finite (x, y), got {self.origin!r}")
        if not (isinstance(self.mg_over_correction, (int, float)) and 1.0 <= self.mg_over_correction <= 2.5):
            raise PlannerInputError(f"PlannerConfig.mg_over_correction must be in [1, 2.5], "
                                    f"got {self.mg_over_correction!r}")
        if self.evidence_cap < self.occupied_weight:
            raise PlannerInputError("PlannerConfig.evidence_cap must be >= occupied_weight")
        if self.fly_z_max <= self.fly_z_min:
            raise PlannerInputError("PlannerConfig.fly_z_max must be above fly_z_min")
        if self.safety_margin < 0 or self.mg_smoothing_sweeps < 1 or self.max_cycles < 1 or self.mg_coarsest < 1:
            raise PlannerInputError("PlannerConfig: safety_margin >= 0, mg_smoothing_sweeps >= 1, "
                                    "mg_coarsest >= 1 and max_cycles >= 1 required")

    @property
    def inflation_m(self) -> float:
        return self.robot_radius + self.safety_margin

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) = (cells along y, cells along x)."""
        return (int(round(self.size_m[1] / self.resolution)), int(round(self.size_m[0] / self.resolution)))


@dataclass(frozen=True)
class SensorView:
    """What a sensor observed with one reading, on the ground plane (map frame): a wedge from (x, y) around
    heading ``yaw`` (rad), ``half_fov_rad`` either side (pi: all around, e.g. a sonar ring), between
    ``near_m`` and ``range_m``.  For a camera: its position, optical-axis heading, half its horizontal
    field of view and the depth band inside which its flies are trusted.  Cells inside are *observed*:
    evidence there that the reading does not renew is forgotten at the normal rate."""

    x: float
    y: float
    yaw: float
    half_fov_rad: float
    range_m: float
    near_m: float = 0.0

    def __post_init__(self):
        vals = (self.x, self.y, self.yaw, self.half_fov_rad, self.range_m, self.near_m)
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in vals):
            raise PlannerInputError(f"SensorView needs finite numbers, got {vals!r}")
        if not 0.0 < self.half_fov_rad <= math.pi or not 0.0 <= self.near_m < self.range_m:
            raise PlannerInputError(f"SensorView needs 0 < half_fov_rad <= pi and 0 <= near_m < range_m, got "
                                    f"half_fov_rad={self.half_fov_rad}, near_m={self.near_m}, range_m={self.range_m}")


@dataclass(frozen=True)
class Command:
    """Differential-drive command.  ``stop`` True means v = omega = 0 and ``reason`` says why
    ('target reached', 'no path', 'no target', 'target blocked', 'target outside grid', 'not solved',
    'outside grid', 'robot in obstacle'); while moving ``reason`` is 'following field' or 'escaping obstacle'."""

    v: float
    omega: float
    stop: bool
    reason: str


@dataclass(frozen=True)
class SolveReport:
    """What one ``HarmonicPlanner.solve`` call did: multigrid cycles run, whether the last cycle's largest
    relative change of phi is below the tolerance, that change, wall time, ACTIVE cells, status."""
    cycles: int
    converged: bool
    max_rel_change: float
    elapsed_ms: float
    active_cells: int
    status: str = field(default="ok")   # 'ok', 'no target', 'target blocked', 'target outside grid'
