"""HarmonicPlanner: occupancy from flies and sonar, a log-space harmonic field kept up to date by warm
restarts, and a differential-drive command down its gradient.

Usage (the planner service)::

    pl = HarmonicPlanner(PlannerConfig(resolution=0.05, size_m=(20, 20), origin=(-10, -10)))
    pl.set_target(x, y, radius)
    pl.update_flies(points_map, fitness, stamp_ns, view=None)  # (N, 3) map frame, (N,), SensorView
    pl.update_sonar(points_xy, stamp_ns, view=None)   # (M, 2) map frame
    pl.solve(max_ms=20)                               # warm-started multigrid, returns a SolveReport
    cmd = pl.command((x, y, yaw))                     # Command(v, omega, stop, reason)
    pl.field, pl.grid_origin, pl.resolution, pl.path_from(x, y)

Grid convention: ``field[row, col]`` is the cell whose centre is
``grid_origin + ((col + 0.5) * resolution, (row + 0.5) * resolution)`` in the map frame.
"""
from __future__ import annotations

import logging
import math
import time

import numpy as np

from . import harmonic as hk
from .config import SensorView, Command, PlannerConfig, PlannerInputError, SolveReport
from .controller import heading_command
from .multigrid import LogFieldSolver
from .occupancy import EvidenceGrid

log = logging.getLogger("flyslam.planner")

# Largest share of a solver's cells that map changes may cut out of it before the system and its
# multigrid hierarchy are rebuilt for the current map (see HarmonicPlanner._block_only).
BLOCK_REUSE_FRACTION = 0.1


class HarmonicPlanner:
    def __init__(self, config: PlannerConfig | None = None):
        self.cfg = config or PlannerConfig()
        self.grid = EvidenceGrid(self.cfg)
        h, w = self.cfg.shape
        self._target: tuple[float, float, float] | None = None
        self._target_version = 0
        # Padded (H+2, W+2) solver state: phi = exp(s) * r on ACTIVE cells.
        self._state = np.zeros((h + 2, w + 2), dtype=np.int8)
        self._s = np.zeros((h + 2, w + 2))
        self._r = np.zeros((h + 2, w + 2))
        self._r_is_one = False            # whether r is 1 on every non-BLOCKED cell (s alone holds phi)
        self._target_cells: tuple | None = None     # (target, mask) cache of _target_mask
        self._solved_key: tuple | None = None
        self._solver: LogFieldSolver | None = None
        self._converged = False
        self._has_solution = False
        self._status = "no target"
        self._clearance = np.full((h, w), np.float32(1e6))
        self._passable = np.ones((h, w), dtype=bool)

    # -- inputs --------------------------------------------------------------------------------------
    def set_target(self, x: float, y: float, radius: float) -> None:
        """Target region: a disc in the map frame.  Its cells are the 0-potential Dirichlet boundary."""
        vals = (x, y, radius)
        if not all(isinstance(v, (int, float, np.floating)) and math.isfinite(v) for v in vals) or radius <= 0:
            raise PlannerInputError(f"set_target needs finite x, y and a positive radius, got {vals!r}")
        self._target = (float(x), float(y), float(radius))
        self._target_version += 1

    def clear_target(self) -> None:
        self._target = None
        self._target_version += 1

    def update_flies(self, points_map, fitness, stamp_ns: int, view: SensorView | None = None,
                     weight: float = 1.0, cell_cap: float | None = None) -> int:
        """Fold a fly population ((N, 3) map-frame points, (N,) fitness) into the occupancy evidence.
        ``view`` (where the camera looked, map frame): old evidence is forgotten quickly only inside it,
        slowly elsewhere (see occupancy.py); without it, everywhere at the same rate.  ``weight`` scales
        the population's evidence; ``cell_cap`` bounds what it adds to one cell (see EvidenceGrid.add_flies)."""
        return self.grid.add_flies(points_map, fitness, stamp_ns, view, weight, cell_cap)

    def update_sonar(self, points_xy, stamp_ns: int, view: SensorView | None = None) -> None:
        """Fold sonar echoes ((M, 2) map-frame x, y; M may be 0) into the occupancy evidence.  ``view``: the
        region the scan observed (e.g. SensorView(x, y, 0, pi, range) around the robot)."""
        self.grid.add_sonar(points_xy, stamp_ns, view)

    # -- grid helpers --------------------------------------------------------------------------------
    @property
    def resolution(self) -> float:
        return self.cfg.resolution

    @property
    def grid_origin(self) -> tuple[float, float]:
        return self.cfg.origin

    @property
    def shape(self) -> tuple[int, int]:
        return self.cfg.shape

    def cell_of(self, x: float, y: float) -> tuple[int, int] | None:
        """(row, col) of a map point, or None outside the grid."""
        col = math.floor((x - self.cfg.origin[0]) / self.cfg.resolution)
        row = math.floor((y - self.cfg.origin[1]) / self.cfg.resolution)
        h, w = self.shape
        if 0 <= row < h and 0 <= col < w:
            return row, col
        return None

    def cell_centres(self, rows, cols) -> np.ndarray:
        res = self.cfg.resolution
        return np.stack([self.cfg.origin[0] + (np.asarray(cols) + 0.5) * res,
                         self.cfg.origin[1] + (np.asarray(rows) + 0.5) * res], axis=-1)

    # -- solving -------------------------------------------------------------------------------------
    def _target_mask(self) -> np.ndarray:
        if self._target_cells is not None and self._target_cells[0] == self._target:
            return self._target_cells[1]
        h, w = self.shape
        tx, ty, tr = self._target
        xs = self.cfg.origin[0] + (np.arange(w) + 0.5) * self.cfg.resolution
        ys = self.cfg.origin[1] + (np.arange(h) + 0.5) * self.cfg.resolution
        mask = (xs[None, :] - tx) ** 2 + (ys[:, None] - ty) ** 2 <= tr * tr
        if not mask.any():          # a target smaller than a cell still gets its cell
            cell = self.cell_of(tx, ty)
            if cell is not None:
                mask[cell] = True
        self._target_cells = (self._target, mask)
        return mask

    def _rebuild_state(self) -> None:
        """Re-derive obstacles, inflation and the connected region; carry the old solution over."""
        occupied = self.grid.occupied()
        self._clearance = self.grid.clearance_m(occupied)
        self._passable = self._clearance > self.cfg.inflation_m
        h, w = self.shape
        passable = np.zeros((h + 2, w + 2), dtype=bool)
        passable[1:-1, 1:-1] = self._passable
        target = np.zeros_like(passable)
        target[1:-1, 1:-1] = self._target_mask()
        outside = not target.any()
        target &= passable
        if not target.any():
            self._status = "target outside grid" if outside else "target blocked"
            self._state[:] = hk.BLOCKED
            self._has_solution = False
            return
        dist = hk.flood_from_target(passable, target)
        new_state = np.full(passable.shape, hk.BLOCKED, dtype=np.int8)
        new_state[dist >= 0] = hk.ACTIVE
        new_state[target] = hk.TARGET
        if self._has_solution and np.array_equal(new_state, self._state):
            return      # evidence changed but no cell changed side: keep solution, weights and factors
        if self._block_only(new_state):
            return
        active = new_state == hk.ACTIVE
        # Warm start: keep phi = exp(s) r wherever the cell was already solved; fold r into s (r is 1
        # everywhere after a completed solve, which stores its factors in s: nothing to fold then).
        known = active & (self._state == hk.ACTIVE) if self._has_solution else np.zeros_like(active)
        s = self._s
        if not self._r_is_one:
            s[known] += np.log(self._r[known])
        s[~known] = 0.0             # target cells (phi = 1), blocked ones, and new cells before their guess
        # New cells: a BFS guess 0.3 (in log phi) lower per cell than their parent.
        if (active & ~known).any():
            hk.extend_scale(s, known, new_state, 0.3)
        self._r = np.where(new_state != hk.BLOCKED, 1.0, 0.0)
        self._r_is_one = True
        self._state = new_state
        # The system of the new map around the warm start, with its multigrid hierarchy (multigrid.py).
        self._solver = LogFieldSolver(new_state, s, self.cfg.mg_coarsest, recycle=self._solver)
        self._converged = False
        self._status = "ok"
        self._has_solution = True

    def _block_only(self, new_state: np.ndarray) -> bool:
        """A change that only turned ACTIVE cells BLOCKED (an object appeared, or cells it cut off):
        take them out of the current solver (``LogFieldSolver.block``) instead of building a new system
        and hierarchy (most of a warm update's set-up).  Not done once the removed cells exceed
        ``BLOCK_REUSE_FRACTION`` of the solver's cells (the old coarse spaces fit the map less and less)."""
        sv = self._solver
        if not self._has_solution or sv is None:
            return False
        changed = new_state != self._state
        gone = changed & (self._state == hk.ACTIVE) & (new_state == hk.BLOCKED)
        if not np.array_equal(changed, gone):
            return False
        flat = np.flatnonzero(gone)
        if sv.dead + flat.size > BLOCK_REUSE_FRACTION * sv.size:
            return False
        sv.block(flat)
        self._state = new_state
        self._converged = False
        self._status = "ok"
        return True

    def _store_solution(self) -> None:
        """Copy the solver's log phi to the padded grid (r = 1).  The solver itself is not rebased: its
        level-0 scales stay valid for the next warm update; ``solve`` rebases when the factors drift far
        from 1."""
        sv = self._solver
        self._s.ravel()[sv.cells] = sv.log_phi()
        self._r.ravel()[sv.cells] = 1.0
        self._r_is_one = True

    def solve(self, max_ms: float | None = None, max_cycles: int | None = None) -> SolveReport:
        """Bring the field up to date: rebuild obstacles if the evidence or target changed, then run
        multigrid cycles (multigrid.py) from the previous solution until the largest relative change of
        phi made by one cycle is below ``tolerance``, ``max_cycles`` ran, or ``max_ms`` elapsed (checked
        after every cycle; the next call continues where this one stopped).  ``max_cycles`` overrides
        the configured cap for this call (a reproducible budget, unlike ``max_ms``).  A converged field
        whose map has not changed costs nothing."""
        t0 = time.perf_counter()
        if self._target is None:
            self._status = "no target"
            self._has_solution = False
            return SolveReport(0, False, float("nan"), 0.0, 0, "no target")
        key = (self.grid.version, self._target_version)
        if key != self._solved_key or self._solver is None:
            self._rebuild_state()
            self._solved_key = key
        if self._status != "ok":
            return SolveReport(0, False, float("nan"), (time.perf_counter() - t0) * 1e3, 0, self._status)
        cfg = self.cfg
        sv = self._solver
        cap = cfg.max_cycles if max_cycles is None else int(max_cycles)
        cycles = 0
        change = 0.0 if self._converged else float("inf")
        while change >= cfg.tolerance and cycles < cap:
            change = sv.cycle(cfg.mg_over_correction, cfg.mg_smoothing_sweeps, cfg.mg_krylov_levels)
            cycles += 1
            if not math.isfinite(change):
                return self._discard_solver(cycles, t0)
            if max_ms is not None and (time.perf_counter() - t0) * 1e3 >= max_ms:
                break
            if sv.drift() > 30.0:
                sv.rebase()             # keep x near 1 so exp(s) x never leaves float64's range
        if cycles:
            self._store_solution()
        self._converged = change < cfg.tolerance
        return SolveReport(cycles, self._converged, float(change), (time.perf_counter() - t0) * 1e3,
                           sv.live_size, "ok")

    def _discard_solver(self, cycles: int, t0: float) -> SolveReport:
        """A cycle produced a non-finite field (a numerical failure the solver should never have; the
        multigrid's factors are clipped to keep float64 in range): keep nothing of it.  The planner says
        so, commands stop ("not solved"), and the next ``solve`` starts the field from scratch."""
        log.error("harmonic field became non-finite after %d cycles: discarded, restarting from scratch",
                  cycles)
        self._solver = None
        self._has_solution = False
        self._converged = False
        self._solved_key = None
        self._s[:] = 0.0
        self._r[:] = 1.0
        self._status = "solver failed: field restarted"
        return SolveReport(cycles, False, float("nan"), (time.perf_counter() - t0) * 1e3, 0, self._status)

    # -- outputs -------------------------------------------------------------------------------------
    @property
    def log_phi(self) -> np.ndarray:
        """(H, W) log of the complementary potential phi = 1 - u: 0 on the target, decreasing away from
        it, -inf on obstacles and wherever the target cannot be reached.  Steering ascends it."""
        psi = np.where(self._state != hk.BLOCKED, self._s + np.log(np.maximum(self._r, 1e-300)), -np.inf)
        psi[self._state == hk.TARGET] = 0.0
        return psi[1:-1, 1:-1]

    @property
    def field(self) -> np.ndarray:
        """(H, W) potential to descend, ``-log(1 - u)``: 0 on the target, growing away from it, +inf on
        (inflated) obstacles and unreachable cells.  Finite and with a usable gradient everywhere the
        target is reachable, however far (the harmonic u itself would round to 1 there)."""
        return -self.log_phi

    @property
    def passable(self) -> np.ndarray:
        """(H, W) bool: cells outside the inflated obstacles."""
        return self._passable

    @property
    def clearance(self) -> np.ndarray:
        """(H, W) distance (m) to the nearest occupied cell."""
        return self._clearance

    @property
    def status(self) -> str:
        return self._status

    def path_from(self, x: float, y: float, max_steps: int | None = None) -> np.ndarray:
        """(K, 2) map-frame cell centres of the discrete steepest descent from (x, y) to the target
        (empty if (x, y) is outside the grid or not connected to the target)."""
        cell = self.cell_of(x, y)
        if cell is None or not self._has_solution or self._state[cell[0] + 1, cell[1] + 1] == hk.BLOCKED:
            return np.zeros((0, 2))
        psi = np.full(self._state.shape, -np.inf)
        psi[1:-1, 1:-1] = self.log_phi
        steps = max_steps or int(4 * sum(self.shape))
        cells = hk.descent_path(psi, self._state, cell[0] + 1, cell[1] + 1, steps)
        return self.cell_centres(cells[:, 0] - 1, cells[:, 1] - 1)

    def _psi_patch(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """log phi over padded rows r0:r1, cols c0:c1 (clipped to the padded grid, -inf outside)."""
        hp, wp = self._state.shape
        out = np.full((r1 - r0, c1 - c0), -np.inf)
        ra, rb, ca, cb = max(r0, 0), min(r1, hp), max(c0, 0), min(c1, wp)
        st = self._state[ra:rb, ca:cb]
        with np.errstate(divide="ignore"):
            val = self._s[ra:rb, ca:cb] + np.log(self._r[ra:rb, ca:cb])
        val = np.where(st == hk.BLOCKED, -np.inf, np.where(st == hk.TARGET, 0.0, val))
        out[ra - r0:rb - r0, ca - c0:cb - c0] = val
        return out

    def _descent_direction(self, x: float, y: float) -> tuple[float, float] | None:
        """Gradient of log phi at (x, y), bilinear over the four surrounding cell-centre gradients
        (computed on a 4 x 4 patch, so a command costs the same on any grid size)."""
        res = self.cfg.resolution
        fx = (x - self.cfg.origin[0]) / res - 0.5 + 1      # padded continuous column
        fy = (y - self.cfg.origin[1]) / res - 0.5 + 1
        c0, r0 = int(math.floor(fx)), int(math.floor(fy))
        psi = self._psi_patch(r0 - 1, r0 + 3, c0 - 1, c0 + 3)
        gx = gy = wsum = 0.0
        for dr in (0, 1):
            for dc in (0, 1):
                if not np.isfinite(psi[1 + dr, 1 + dc]):
                    continue
                wgt = (1 - abs(fx - (c0 + dc))) * (1 - abs(fy - (r0 + dr)))
                g = _cell_gradient(psi, 1 + dr, 1 + dc)
                gx += wgt * g[0]
                gy += wgt * g[1]
                wsum += wgt
        if wsum == 0 or gx * gx + gy * gy == 0:
            return None
        return gx, gy

    def command(self, robot_pose_xyyaw) -> Command:
        """Differential-drive command for a robot at (x, y, yaw) in the map frame."""
        x, y, yaw = (float(v) for v in robot_pose_xyyaw)
        if not all(math.isfinite(v) for v in (x, y, yaw)):
            raise PlannerInputError(f"robot pose must be finite (x, y, yaw), got {robot_pose_xyyaw!r}")
        if self._target is None:
            return Command(0.0, 0.0, True, "no target")
        tx, ty, tr = self._target
        dist_target = math.hypot(tx - x, ty - y)
        if dist_target <= tr:
            return Command(0.0, 0.0, True, "target reached")
        if self._status in ("target blocked", "target outside grid"):
            return Command(0.0, 0.0, True, self._status)
        if not self._has_solution:
            return Command(0.0, 0.0, True, "not solved")
        cell = self.cell_of(x, y)
        if cell is None:
            return Command(0.0, 0.0, True, "outside grid")
        clearance = float(self._clearance[cell])
        state = self._state[cell[0] + 1, cell[1] + 1]
        if state == hk.BLOCKED:
            if self._passable[cell]:
                return Command(0.0, 0.0, True, "no path")
            # Inside the inflated obstacles (noise, or an obstacle seen late): back away from the nearest
            # obstacle along the clearance gradient, slowly, until the field takes over again.
            g = _cell_gradient(self._clearance, cell[0], cell[1])
            if g[0] == 0 and g[1] == 0:
                return Command(0.0, 0.0, True, "robot in obstacle")
            v, w = heading_command(math.atan2(g[1], g[0]), yaw, self.cfg, speed_limit=self.cfg.escape_speed)
            return Command(v, w, False, "escaping obstacle")
        direction = self._descent_direction(x, y)
        if direction is None:
            return Command(0.0, 0.0, True, "no path")
        slow_c = (clearance - self.cfg.inflation_m) / self.cfg.slow_clearance_m
        slow_t = (dist_target - tr) / self.cfg.slow_target_m
        frac = min(1.0, max(self.cfg.min_speed_fraction, min(slow_c, slow_t)))
        v, w = heading_command(math.atan2(direction[1], direction[0]), yaw, self.cfg,
                               speed_limit=self.cfg.v_max * frac)
        return Command(v, w, False, "following field")


def _cell_gradient(a: np.ndarray, r: int, c: int) -> tuple[float, float]:
    """(d/dx, d/dy) of ``a`` at [r, c]: central differences where both neighbours are finite, one-sided
    where only one is (obstacles are -inf in log phi)."""
    out = []
    for (ra, ca), (rb, cb) in (((r, c + 1), (r, c - 1)), ((r + 1, c), (r - 1, c))):
        hi = a[ra, ca] if 0 <= ra < a.shape[0] and 0 <= ca < a.shape[1] else -np.inf
        lo = a[rb, cb] if 0 <= rb < a.shape[0] and 0 <= cb < a.shape[1] else -np.inf
        centre = a[r, c]
        if np.isfinite(hi) and np.isfinite(lo):
            out.append(0.5 * (hi - lo))
        elif np.isfinite(hi):
            out.append(hi - centre)
        elif np.isfinite(lo):
            out.append(centre - lo)
        else:
            out.append(0.0)
    return float(out[0]), float(out[1])
