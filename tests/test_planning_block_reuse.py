"""A map change that only blocks cells (an object appeared) is absorbed by the current solver
(``LogFieldSolver.block``) instead of a new system and hierarchy; the field must be the one a fresh
planner computes for the same evidence, and any other change must still rebuild."""
import numpy as np

from common.planning import planner as planner_mod
from common.planning import harmonic as hk
from tests.test_planning_solver import serpentine_planner


def blob(x, y, n=40, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack([x + rng.uniform(-0.07, 0.07, n), y + rng.uniform(-0.07, 0.07, n), np.full(n, 0.5)])


def test_an_object_appearing_reuses_the_solver_and_gives_the_fresh_planners_field():
    pl, _ = serpentine_planner(size=6.0)
    assert pl.solve().converged
    solver = pl._solver
    obj = blob(1.43, 2.43)
    pl.update_flies(obj, np.ones(len(obj)), 1)
    rep = pl.solve()
    assert pl._solver is solver and solver.dead > 0
    fresh, _ = serpentine_planner(size=6.0)
    fresh.update_flies(obj, np.ones(len(obj)), 1)
    ref = fresh.solve()
    assert rep.converged and ref.converged
    assert rep.active_cells == ref.active_cells                 # cut-out cells are not counted
    fin = np.isfinite(fresh.field)
    assert np.array_equal(np.isfinite(pl.field), fin)
    assert np.abs(pl.field[fin] - fresh.field[fin]).max() < 1e-3
    assert hk.usable_fraction(np.pad(pl.log_phi, 1, constant_values=-np.inf), pl._state) == 1.0


def test_freed_cells_or_too_many_blocked_cells_rebuild_the_solver(monkeypatch):
    pl, walls = serpentine_planner(size=6.0)
    pl.solve()
    solver = pl._solver
    # too many removed cells for the configured share: a new system for the new map
    monkeypatch.setattr(planner_mod, "BLOCK_REUSE_FRACTION", 1e-4)
    obj = blob(3.0, 0.8)
    pl.update_flies(obj, np.ones(len(obj)), 1)
    assert pl.solve().converged
    assert pl._solver is not solver and pl._solver.dead == 0
    monkeypatch.setattr(planner_mod, "BLOCK_REUSE_FRACTION", 0.1)
    solver = pl._solver
    # the walls are seen again and again, the object no more: its evidence decays and its cells are freed
    for k in range(60):
        pl.update_flies(walls, np.ones(len(walls)), (2 + k) * 1_000_000_000)
        if pl._solver is not solver:
            break
        pl.solve()
    assert pl.solve().converged
    assert pl._solver is not solver, "freeing cells must rebuild the system"
