"""Harmonic field: log-space solution vs the textbook relaxation, exactness, warm start, evidence."""
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from common.planning import HarmonicPlanner, PlannerConfig, PlannerInputError
from common.planning import harmonic as hk


def wall_flies(x0, x1, y, z=0.5, step=0.02):
    xs = np.arange(x0, x1, step)
    return np.stack([xs, np.full_like(xs, y), np.full_like(xs, z)], axis=1)


def corridor_planner(length=20.5):
    """A 1.2 m wide, ``length`` m long corridor made of fly walls, target at the x = 0 end."""
    pl = HarmonicPlanner(PlannerConfig(resolution=0.05, size_m=(length, 1.5), origin=(0.0, 0.0)))
    walls = np.vstack([wall_flies(0, length, 0.15), wall_flies(0, length, 1.35)])
    pl.update_flies(walls, np.ones(len(walls)), 0)
    pl.set_target(0.5, 0.75, 0.2)
    return pl


def padded_psi(pl):
    psi = np.full(pl._state.shape, -np.inf)
    psi[1:-1, 1:-1] = pl.log_phi
    return psi


def test_plain_relaxation_has_zero_gradient_far_down_a_corridor_but_log_field_does_not():
    pl = corridor_planner()
    rep = pl.solve()
    assert rep.converged
    state = pl._state
    far = np.zeros(state.shape, dtype=bool)
    far[:, -150:] = True                      # the last 7.5 m of the corridor
    far &= state == hk.ACTIVE
    assert far.sum() > 1000

    for dtype, tol, sweeps in ((np.float64, 1e-13, 20000), (np.float32, 1e-6, 3000)):
        u = hk.plain_potential(state, dtype, tol=tol, max_sweeps=sweeps)
        # converged, yet every far cell is exactly 1: 1 - u (~1e-40 there) is below the precision
        assert np.all(u[far] == 1.0), dtype
        ok = hk.reaches_target(hk.descent_successor(-u.astype(float), state))
        print(f"plain {np.dtype(dtype).name}: descent reaches the target from {ok[state == hk.ACTIVE].mean():.1%} "
              f"of free cells, {ok[far].mean():.1%} of far cells")
        assert ok[far].mean() == 0.0

    psi = padded_psi(pl)
    assert np.all(np.isfinite(psi[far]))
    assert psi[far].min() < -80               # phi = exp(psi) < 1e-35: beyond float32, 1 - phi == 1 in float64
    ok = hk.reaches_target(hk.descent_successor(psi, state))
    print(f"log field: descent reaches the target from {ok[state == hk.ACTIVE].mean():.1%} of free cells")
    assert ok[state == hk.ACTIVE].all()
    # and the controller far down the corridor actually drives towards the target (-x)
    cmd = pl.command((19.0, 0.75, np.pi))
    assert not cmd.stop and cmd.v > 0.2 and abs(cmd.omega) < 0.2


def direct_log_phi(state):
    """log phi by a sparse direct float64 solve of the 5-point Laplace system (reference)."""
    idx = -np.ones(state.shape, dtype=np.int64)
    act = np.argwhere(state == hk.ACTIVE)
    idx[tuple(act.T)] = np.arange(len(act))
    rows, cols, vals = [], [], []
    b = np.zeros(len(act))
    for k, (y, x) in enumerate(act):
        rows.append(k), cols.append(k), vals.append(4.0)
        for ny, nx in ((y, x + 1), (y, x - 1), (y + 1, x), (y - 1, x)):
            if state[ny, nx] == hk.ACTIVE:
                rows.append(k), cols.append(idx[ny, nx]), vals.append(-1.0)
            elif state[ny, nx] == hk.TARGET:
                b[k] += 1.0
    A = sp.csc_matrix((vals, (rows, cols)), shape=(len(act), len(act)))
    phi = spla.spsolve(A, b)
    out = np.full(state.shape, -np.inf)
    out[tuple(act.T)] = np.log(phi)
    return out


def random_obstacle_planner(seed, n_blobs=12):
    rng = np.random.default_rng(seed)
    pl = HarmonicPlanner(PlannerConfig(resolution=0.1, size_m=(4.0, 3.0), origin=(0.0, 0.0),
                                       robot_radius=0.1, safety_margin=0.0, tolerance=1e-7))
    centres = rng.uniform([0.5, 0.3], [3.5, 2.7], size=(n_blobs, 2))
    pts = np.repeat(centres, 20, axis=0) + rng.normal(0, 0.03, (20 * n_blobs, 2))
    pl.update_flies(np.column_stack([pts, np.full(len(pts), 0.5)]), np.ones(len(pts)), 0)
    pl.set_target(0.3, 1.5, 0.15)
    return pl


@pytest.mark.parametrize("seed", [0, 1])
def test_field_matches_a_direct_solve_of_laplace(seed):
    pl = random_obstacle_planner(seed)
    assert pl.solve().converged
    ref = direct_log_phi(pl._state)
    psi = padded_psi(pl)
    act = pl._state == hk.ACTIVE
    assert np.array_equal(np.isfinite(ref), np.isfinite(psi) & (pl._state != hk.TARGET))
    assert np.abs(psi[act] - ref[act]).max() < 1e-4


def test_warm_update_reuses_the_last_solution_and_matches_a_cold_solve():
    blob = np.column_stack([np.full(30, 2.0), np.linspace(1.3, 1.5, 30), np.full(30, 0.5)])
    pl = random_obstacle_planner(3)
    pl.solve()
    before = pl.field.copy()
    pl.update_flies(blob, np.ones(30), 1)
    # reference: a fresh planner fed the same evidence, solved from scratch to convergence
    ref = random_obstacle_planner(3)
    ref.update_flies(blob, np.ones(30), 1)
    ref.solve()
    fin = np.isfinite(ref.field)
    assert np.abs(before[fin] - ref.field[fin]).max() > 0.05          # the blob changed the field
    # with the same small budget, the warm start is far closer to the answer than a cold start
    cold = random_obstacle_planner(3)
    cold.update_flies(blob, np.ones(30), 1)
    cold.solve(max_cycles=2)
    pl.solve(max_cycles=2)
    warm_err = np.abs(pl.field[fin] - ref.field[fin]).max()
    cold_err = np.abs(cold.field[fin] - ref.field[fin]).max()
    print(f"after 2 cycles: warm error {warm_err:.3g}, cold error {cold_err:.3g} (log phi)")
    assert warm_err < cold_err / 5
    assert pl.solve().converged
    assert np.array_equal(np.isfinite(ref.field), np.isfinite(pl.field))
    assert np.abs(pl.field[fin] - ref.field[fin]).max() < 1e-3


def test_time_budget_stops_early_and_the_next_call_continues():
    pl = corridor_planner()
    first = pl.solve(max_cycles=2)
    assert not first.converged and first.cycles == 2
    rest = pl.solve()
    assert rest.converged and rest.cycles > 0
    again = pl.solve()                        # nothing changed: no work, still converged
    assert again.converged and again.cycles == 0
    assert hk.usable_fraction(padded_psi(pl), pl._state) == 1.0


def test_inflation_blocks_cells_within_robot_radius_plus_margin_only():
    cfg = PlannerConfig(resolution=0.05, size_m=(4.0, 4.0), origin=(-2.0, -2.0), robot_radius=0.2,
                        safety_margin=0.05)
    pl = HarmonicPlanner(cfg)
    post = np.tile([[0.0, 0.0, 0.5]], (10, 1))
    pl.update_flies(post, np.ones(10), 0)
    pl.set_target(1.5, 1.5, 0.2)
    pl.solve()
    centres = pl.cell_centres(*np.indices(cfg.shape))
    obstacle_centre = pl.cell_centres(*pl.cell_of(0.0, 0.0))
    d = np.linalg.norm(centres - obstacle_centre, axis=-1)
    assert not pl.passable[d <= 0.25 - 1e-9].any()
    assert pl.passable[d > 0.25 + 1e-9].all()


def test_flies_outside_the_robot_height_band_do_not_block():
    pl = HarmonicPlanner(PlannerConfig(resolution=0.05, size_m=(4.0, 4.0), origin=(-2.0, -2.0)))
    floor = np.column_stack([np.zeros(50), np.zeros(50), np.full(50, 0.01)])
    ceiling = np.column_stack([np.zeros(50), np.zeros(50), np.full(50, 2.4)])
    assert pl.update_flies(np.vstack([floor, ceiling]), np.ones(100), 0) == 0
    pl.set_target(1.5, 0.0, 0.2)
    pl.solve()
    assert pl.passable.all()


def test_cells_are_freed_after_their_flies_move_away():
    cfg = PlannerConfig(resolution=0.05, size_m=(4.0, 2.0), origin=(0.0, 0.0), evidence_half_life_s=0.5)
    pl = HarmonicPlanner(cfg)
    pl.set_target(3.5, 1.0, 0.2)
    wall = np.column_stack([np.full(200, 2.0), np.linspace(0.0, 2.0, 200), np.full(200, 0.5)])
    for k in range(10):                                    # a wall across the room for 1 s at 10 Hz
        pl.update_flies(wall, np.ones(200), k * 100_000_000)
    pl.solve()
    assert pl.command((0.5, 1.0, 0.0)).reason == "no path"
    moved = wall + [0.0, 0.0, 0.0]
    moved[:, 0] = 3.9                                      # the flies now sit by the far wall
    for k in range(10, 40):                                # 3 s later: 6 half-lives, cap/threshold = 4
        pl.update_flies(moved[::2], np.ones(100), k * 100_000_000)
    pl.solve()
    cmd = pl.command((0.5, 1.0, 0.0))
    assert not cmd.stop and cmd.v > 0
    assert pl.passable[:, int(2.0 / 0.05)].all()


def test_bad_inputs_raise_clear_errors():
    pl = HarmonicPlanner(PlannerConfig(size_m=(4.0, 4.0), origin=(0.0, 0.0)))
    with pytest.raises(PlannerInputError, match=r"\(N, 3\)"):
        pl.update_flies(np.zeros((5, 2)), np.ones(5), 0)
    with pytest.raises(PlannerInputError, match="fitness"):
        pl.update_flies(np.zeros((5, 3)), np.ones(4), 0)
    with pytest.raises(PlannerInputError, match=r"\(M, 2\)"):
        pl.update_sonar(np.zeros((5, 3)), 0)
    with pytest.raises(PlannerInputError, match="radius"):
        pl.set_target(1.0, 1.0, 0.0)
    with pytest.raises(PlannerInputError, match="finite"):
        pl.set_target(float("nan"), 1.0, 0.3)
    with pytest.raises(PlannerInputError, match="pose"):
        pl.command((np.nan, 0.0, 0.0))
    with pytest.raises(PlannerInputError, match="mg_over_correction"):
        PlannerConfig(mg_over_correction=3.0)
    with pytest.raises(ValueError, match="resolution"):
        PlannerConfig(resolution=-0.05)


def serpentine_planner(size=10.0, spacing=1.6):
    """Walls 1.6 m apart with 1.5 m gaps at alternate ends: one long winding corridor; target at its
    start (bottom left)."""
    pl = HarmonicPlanner(PlannerConfig(resolution=0.05, size_m=(size, size), origin=(0.0, 0.0)))
    walls = []
    for k, y in enumerate(np.arange(spacing, size - 0.2, spacing)):
        x0, x1 = (0.0, size - 1.5) if k % 2 == 0 else (1.5, size)
        walls.append(wall_flies(x0, x1, y))
    walls = np.vstack(walls)
    pl.update_flies(walls, np.ones(len(walls)), 0)
    pl.set_target(0.5, 0.5, 0.25)
    return pl, walls


def test_a_narrowing_far_along_a_winding_corridor_is_absorbed_in_a_few_cycles():
    """A small object just past a turn lowers phi everywhere beyond it by a large common factor (here
    more than e^2).  Relaxation carries such a factor along the corridor slowly (hundreds of sweeps);
    the multigrid's coarse levels move whole regions at once: a handful of cycles, and the result is
    the same field as a cold solve of the new map."""
    rng = np.random.default_rng(0)
    obstacle = np.column_stack([1.43 + rng.uniform(-0.07, 0.07, 40), 4.03 + rng.uniform(-0.07, 0.07, 40),
                                np.full(40, 0.5)])
    pl, walls = serpentine_planner()
    assert pl.solve().converged
    before = pl.field.copy()
    pl.update_flies(obstacle, np.ones(40), 1)
    rep = pl.solve()
    print(f"warm update: {rep.cycles} cycles, {rep.elapsed_ms:.1f} ms")
    assert rep.converged and rep.cycles <= 15
    fin = np.isfinite(pl.field)
    assert np.median(pl.field[fin] - before[fin]) > 2.0      # the narrowing matters far away
    assert hk.usable_fraction(padded_psi(pl), pl._state) == 1.0
    cold, _ = serpentine_planner()
    cold.update_flies(obstacle, np.ones(40), 1)
    assert cold.solve().converged
    assert np.array_equal(np.isfinite(cold.field), fin)
    assert np.abs(cold.field[fin] - pl.field[fin]).max() < 1e-3


def test_multigrid_matches_a_direct_solve_across_one_cell_walls():
    """Two-cell-wide corridors separated by walls one cell thick, joined at alternate ends: from the
    second level on, every block of the coarsening straddles a wall, so an aggregation that ignored
    connectivity would tie together cells whose phi differs by orders of magnitude.  The multigrid (cold
    start, then to convergence) gives the direct solve's log phi."""
    from common.planning.multigrid import LogFieldSolver
    h, w = 23, 40
    state = np.full((h + 2, w + 2), hk.BLOCKED, dtype=np.int8)
    state[1:-1, 1:-1] = hk.ACTIVE
    for k, row in enumerate(range(3, h + 1, 3)):             # walls on rows 3, 6, ...; gaps alternate
        state[row, 1:-1] = hk.BLOCKED
        state[row, (w if k % 2 == 0 else 1)] = hk.ACTIVE
    state[1:3, 1:3] = hk.TARGET
    s = np.zeros(state.shape)
    hk.extend_scale(s, np.zeros(state.shape, dtype=bool), state, 0.3)
    solver = LogFieldSolver(state, s)
    for cycles in range(1, 60):
        if solver.cycle(2.0, 1, 99) < 1e-12:
            break
    ref = direct_log_phi(state)
    psi = np.full(state.shape, -np.inf)
    psi.ravel()[solver.cells] = solver.s + np.log(solver.x)
    act = state == hk.ACTIVE
    print(f"{cycles} cycles, log phi down to {ref[act].min():.0f}")
    assert cycles < 40
    assert ref[act].min() < -40                                # a wide range of phi across the walls
    assert np.abs(psi[act] - ref[act]).max() < 1e-6


def test_a_narrow_serpentine_solved_cold_gives_a_finite_field_that_matches_a_direct_solve():
    """Walls 0.7 m apart with 0.6 m doorways: the hierarchy's banded coarsest level is a long chain whose
    exact solve asks for factors far below float64's range on a cold start (they once came back as NaN
    or a division by zero).  The default planner converges, and to the right field."""
    pl = HarmonicPlanner(PlannerConfig(resolution=0.05, size_m=(10.0, 10.0), origin=(0.0, 0.0)))
    walls = []
    for k, y in enumerate(np.arange(0.7, 9.8, 0.7)):
        x0, x1 = (0.0, 9.4) if k % 2 == 0 else (0.6, 10.0)
        walls.append(wall_flies(x0, x1, y))
    walls = np.vstack(walls)
    pl.update_flies(walls, np.ones(len(walls)), 0)
    pl.set_target(0.5, 0.5, 0.25)
    rep = pl.solve()
    assert rep.converged and rep.cycles < 60 and np.isfinite(rep.max_rel_change)
    act = pl._state == hk.ACTIVE
    psi = np.full(pl._state.shape, -np.inf)
    psi[1:-1, 1:-1] = pl.log_phi
    assert np.isfinite(psi[act]).all() and psi[act].min() < -300      # deep, and nowhere NaN
    with np.errstate(divide="ignore"):
        ref = direct_log_phi(pl._state)
    near = act & (ref > -600)                          # where float64's phi does not underflow
    assert np.abs(psi[near] - ref[near]).max() < 1e-3


def test_a_field_that_turns_non_finite_is_discarded_commands_stop_and_the_next_solve_starts_afresh(monkeypatch):
    from common.planning.multigrid import LogFieldSolver
    pl = corridor_planner(6.0)
    assert pl.solve().converged
    monkeypatch.setattr(LogFieldSolver, "cycle", lambda self, *a, **k: float("nan"))
    obj = wall_flies(3.0, 3.2, 0.75)                   # a small object: a change, so the solver runs
    pl.update_flies(obj, np.ones(len(obj)), 1)
    rep = pl.solve()
    assert not rep.converged and rep.status.startswith("solver failed")
    cmd = pl.command((4.0, 0.75, 0.0))
    assert cmd.stop and cmd.v == 0.0 and cmd.omega == 0.0 and cmd.reason == "not solved"
    monkeypatch.undo()
    rep = pl.solve()
    assert rep.converged and pl.status == "ok" and np.isfinite(pl.log_phi[pl.passable]).all()
    assert not pl.command((4.0, 0.75, 0.0)).stop
    # also when the non-finite cycle is the one that uses up a time budget
    monkeypatch.setattr(LogFieldSolver, "cycle", lambda self, *a, **k: float("nan"))
    obj = wall_flies(4.5, 4.7, 0.75)
    pl.update_flies(obj, np.ones(len(obj)), 2)
    assert pl.solve(max_ms=0.0).status.startswith("solver failed") and pl.command((4.0, 0.75, 0.0)).stop
    monkeypatch.undo()
