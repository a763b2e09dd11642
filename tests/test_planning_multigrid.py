"""The log-space multigrid (common/planning/multigrid.py) on its own: small maps solved directly, and
solvers built on the previous solver's buffers give exactly a fresh solver's field."""
import numpy as np
import pytest

from common.planning import harmonic as hk
from common.planning.multigrid import LogFieldSolver, _band_solve, fine_scales, pad_rows4
from common.planning.multigrid_hierarchy import BAND_MAX, band_order, interp_table
from tests.test_planning_solver import direct_log_phi


def room(h, w, boxes=()):
    """Padded state of an h x w room, target in the top-left corner, BLOCKED boxes (y0, y1, x0, x1) in
    padded coordinates."""
    state = np.full((h + 2, w + 2), hk.BLOCKED, dtype=np.int8)
    state[1:-1, 1:-1] = hk.ACTIVE
    for y0, y1, x0, x1 in boxes:
        state[y0:y1, x0:x1] = hk.BLOCKED
    state[1:3, 1:3] = hk.TARGET
    return state


def cold_scale(state):
    s = np.zeros(state.shape)
    hk.extend_scale(s, np.zeros(state.shape, dtype=bool), state, 0.3)
    return s


def solve(solver, tol=1e-12, cap=80):
    for cycles in range(1, cap + 1):
        if solver.cycle(2.0, 1, 99) < tol:
            return cycles
    return cap


def log_phi(solver, shape):
    psi = np.full(shape, -np.inf)
    psi.ravel()[solver.cells] = solver.s + np.log(solver.x)
    return psi


def test_a_map_smaller_than_the_coarsest_level_is_solved_exactly_in_one_cycle():
    state = room(5, 7, boxes=[(3, 5, 4, 5)])
    solver = LogFieldSolver(state, cold_scale(state), coarsest=48)
    assert solver.hier.levels == 1                      # no coarse level: one dense solve
    solver.cycle(2.0, 1, 99)
    act = state == hk.ACTIVE
    ref = direct_log_phi(state)
    assert np.abs(log_phi(solver, state.shape)[act] - ref[act]).max() < 1e-12
    assert solver.cycle(2.0, 1, 99) < 1e-12             # and the next cycle changes nothing


def test_a_solver_built_on_the_previous_solvers_buffers_gives_the_fresh_solvers_field():
    """A map change reuses the old solver's work buffers; nothing of the old map may leak into the new
    field (the new map has more cells, so the buffers also have to be big enough)."""
    before = room(40, 50, boxes=[(10, 30, 20, 24), (25, 27, 5, 45)])
    after = room(40, 50, boxes=[(10, 30, 20, 24)])     # a wall removed: more cells, another field
    old = LogFieldSolver(before, cold_scale(before), coarsest=16)
    solve(old)
    fresh = LogFieldSolver(after, cold_scale(after), coarsest=16)
    reused = LogFieldSolver(after, cold_scale(after), coarsest=16, recycle=old)
    assert solve(fresh) == solve(reused)
    assert np.array_equal(log_phi(fresh, after.shape), log_phi(reused, after.shape))
    act = after == hk.ACTIVE
    assert np.abs(log_phi(reused, after.shape)[act] - direct_log_phi(after)[act]).max() < 1e-8


def test_cells_blocked_in_a_solved_system_give_the_new_maps_exact_field():
    """``block`` keeps the old hierarchy (whose aggregates now straddle the new walls) but the live
    cells' equations are the new map's: converged, the field is the direct solve of the new map, also
    for a pocket the new wall cuts off (its cells are blocked too, as the planner's connectivity does)."""
    before = room(30, 40, boxes=[(8, 24, 12, 14)])
    solver = LogFieldSolver(before, cold_scale(before), coarsest=16)
    solve(solver)
    after = before.copy()
    after[14:20, 25:33] = hk.BLOCKED                   # an object in the open room
    after[24:31, 12:16] = hk.BLOCKED                   # the wall extended to the border and thickened
    after[20:22, 30:41] = hk.BLOCKED                   # walls closing off the bottom-right corner ...
    after[20:31, 30:32] = hk.BLOCKED
    after[22:31, 32:41] = hk.BLOCKED                   # ... whose cells are then unreachable
    gone = np.flatnonzero((before == hk.ACTIVE) & (after == hk.BLOCKED))
    solver.block(gone)
    # the level-0 scales kept across the change are the ones computed afresh for the new log scale
    n1 = solver.hier.n[1]
    E2, S = fine_scales(solver.s, solver.hier.agg[:solver.size], n1)
    assert np.array_equal(solver._scales[1], S) and np.allclose(solver._scales[0], E2, rtol=1e-14, atol=0)
    assert solver.live_size == solver.size - gone.size
    cycles = solve(solver)
    assert cycles < 40
    act = after == hk.ACTIVE
    ref = direct_log_phi(after)
    assert np.abs(log_phi(solver, after.shape)[act] - ref[act]).max() < 1e-8
    solver.block(gone[:5])                             # blocking again changes nothing
    assert solver.live_size == solver.size - gone.size
    assert solver.cycle(2.0, 1, 99) < 1e-10


def test_blocking_a_cell_the_solver_does_not_have_is_refused():
    state = room(10, 12)
    solver = LogFieldSolver(state, cold_scale(state), coarsest=16)
    with pytest.raises(ValueError, match="block"):
        solver.block(np.array([0]))                    # a border cell


def test_rows_padded_to_four_entries_keep_every_coupling_and_where_the_finer_level_adds_to_it():
    cptr = np.array([0, 2, 3, 7, 8, 9])
    cind = np.array([1, 2, 0, 0, 1, 3, 4, 2, 2])       # row 2 already has 4 entries
    emap = np.array([-1, 0, 1, 2, -1, 8, 3, 6])        # finer-level entries -> these entries
    ip4, ind4, emap4 = pad_rows4(cptr, cind, emap)
    assert np.array_equal(ip4, [0, 4, 8, 12, 16, 20])
    for row in range(5):
        real = cind[cptr[row]:cptr[row + 1]]
        padded = ind4[4 * row:4 * row + 4]
        assert list(padded[:real.size]) == list(real) and np.all(padded[real.size:] == row)
    # every finer entry still lands on the same neighbour
    for e, k in enumerate(emap):
        assert (emap4[e] < 0) if k < 0 else (ind4[emap4[e]] == cind[k])


def test_more_level0_sweeps_converge_to_the_same_field_in_fewer_cycles():
    state = room(40, 50, boxes=[(10, 30, 20, 24), (25, 27, 5, 45)])
    act = state == hk.ACTIVE
    ref = direct_log_phi(state)
    cycles = {}
    for sweeps in (1, 2):
        solver = LogFieldSolver(state, cold_scale(state), coarsest=16)
        for k in range(1, 81):
            if solver.cycle(2.0, 1, 99, fine_sweeps=sweeps) < 1e-10:
                break
        cycles[sweeps] = k
        assert np.abs(log_phi(solver, state.shape)[act] - ref[act]).max() < 1e-8
    assert cycles[2] < cycles[1]


def serpentine_state(h=60, w=64, width=6):
    """Padded state of one long winding corridor: walls every ``width + 1`` rows, open at alternate ends."""
    state = room(h, w)
    for k, y in enumerate(range(width + 1, h, width + 1)):
        x0, x1 = (1, w - 3) if k % 2 == 0 else (4, w + 1)
        state[y, x0:x1] = hk.BLOCKED
    return state


def test_a_corridor_maps_hierarchy_stops_at_a_narrow_banded_level_and_still_solves_exactly():
    """A winding corridor's coarse levels are chains: the hierarchy stops at the first one whose
    couplings fit a narrow band (well before the 16-unknown floor) and solves it exactly, and the
    planner's cycle (K-cycles on level 1 only) converges to the direct solve of the map."""
    state = serpentine_state()
    solver = LogFieldSolver(state, cold_scale(state), coarsest=16)
    assert solver.hier.levels > 1 and solver.hier.n[-1] > 16
    assert solver.hier.band <= BAND_MAX
    for cycles in range(1, 61):
        if solver.cycle(2.0, 1, 1) < 1e-11:
            break
    assert cycles < 40
    act = state == hk.ACTIVE
    assert np.abs(log_phi(solver, state.shape)[act] - direct_log_phi(state)[act]).max() < 1e-8


def test_banded_elimination_in_the_bandwidth_order_matches_a_dense_solve():
    """The coarsest level's solve: a chain-like M-matrix given in a scrambled node order."""
    rng = np.random.default_rng(3)
    n = 60
    perm = rng.permutation(n)                          # node perm[k] is the k-th along a 2-wide ladder
    rows = [[] for _ in range(n)]
    for k in range(n):
        for dk in (1, 2):
            if k + dk < n:
                a, b = perm[k], perm[k + dk]
                rows[a].append(b), rows[b].append(a)
    ip = np.concatenate([[0], np.cumsum([len(r) for r in rows])]).astype(np.int64)
    ind = np.concatenate([np.array(sorted(r), np.int64) for r in rows])
    vals = rng.uniform(0.1, 1.0, ind.size)
    dg = np.array([vals[ip[i]:ip[i + 1]].sum() for i in range(n)]) * rng.uniform(1.0, 1.5, n) + 1e-3
    f = rng.uniform(0.0, 1.0, n)
    rank, b = band_order(ip, ind)
    assert b <= 4                                      # the ladder's order is found again
    out = np.empty(n)
    _band_solve(dg, ip, ind, vals, f, rank, b, np.empty((n, 2 * b + 1)), np.empty(n), out)
    A = np.diag(dg)
    for i in range(n):
        A[i, ind[ip[i]:ip[i + 1]]] -= vals[ip[i]:ip[i + 1]]
    assert np.allclose(out, np.linalg.solve(A, f), rtol=1e-12, atol=0)


def test_interpolated_coarse_factors_never_reach_across_a_wall_and_follow_blocked_cells():
    """Level 0's bilinear prolongation reads the neighbouring 2 x 2 blocks' factors only through live
    couplings: never from the other side of a one-cell wall, and, once ``block`` has cut an object's
    cells out, exactly as a table built afresh for the new couplings."""
    state = room(20, 21, boxes=[(1, 17, 10, 11)])      # a wall at padded column 10, open at the bottom
    solver = LogFieldSolver(state, cold_scale(state), coarsest=8)
    agg = solver.hier.agg[:solver.size]
    cx = solver.cells % state.shape[1]
    cy = solver.cells // state.shape[1]
    upper = cy < 17                                    # where the wall separates the two sides
    side = np.where(cx < 10, 0, 1)
    for i in np.flatnonzero(upper):
        for a in solver._interp[i]:
            members = agg == a
            assert np.all(side[members & upper] == side[i]), f"cell {i} reads a factor across the wall"
    obj = [(y, x) for y in range(4, 8) for x in range(4, 8)]
    flat = np.array(sorted(y * state.shape[1] + x for y, x in obj))
    solver.block(flat)
    assert np.array_equal(solver._interp, interp_table(solver.nb, solver.w4, cy, cx, agg))
    for y, x in ((12, 4), (13, 15)):                  # single cells: their four neighbours touch no other
        solver.block(np.array([y * state.shape[1] + x]))
        assert np.array_equal(solver._interp, interp_table(solver.nb, solver.w4, cy, cx, agg))
