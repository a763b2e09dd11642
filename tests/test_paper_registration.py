"""The paper's registration experiments on the simulated trolley (bench/paper.py), in miniature.

One stereo pair from each of two trolley pauses, 5,000 flies evolved for 120 generations (the
evolver's inlier fraction has levelled off by then: see the bench's convergence trace).  Registration
is the bench's co-visible recipe with ε = 0.03 m (its headline at 150 generations; the full bench now
evolves 400 and its selection round picks ε = 0.02): δ over all flies, from the wheel-odometry prior,
then a second pass on the flies both rigs could hold (co-visibility that accounts for the stereo overlap).
"""
from __future__ import annotations

import numpy as np
import pytest

from bench.paper import (PAPER_VARIANT, Variant, evolve, odometry_displacement, optical_params,
                         render_pauses, true_displacement)

FLIES, GENERATIONS = 5000, 120
POSE_A, POSE_B = 0, 3          # trolley pauses: 0.2 m forward, 0.1 m sideways and 5° of yaw apart
RECIPE = Variant("δ ε=0.03, all flies, co-visible ×2", covis_passes=1,
                 options=dict(max_points=1_000_000, eps=0.03))


@pytest.fixture(scope="module")
def trolley():
    views = render_pauses(pauses=(POSE_A, POSE_B))
    pops = {(p, s): evolve(views, p, s, FLIES, GENERATIONS)[:2] for p, s in
            ((POSE_A, 0), (POSE_A, 1), (POSE_B, 2))}
    return views, pops


def test_equivalent_populations_register_to_identity(trolley):
    views, pops = trolley
    (A, fa), (B, fb) = pops[(POSE_A, 0)], pops[(POSE_A, 1)]
    for variant in (RECIPE, PAPER_VARIANT):
        x, z, th = variant.register(A, fa, B, fb, views.calib).params
        assert abs(x) < 0.05 and abs(z) < 0.05, (variant.name, x, z)
        assert abs(np.rad2deg(th)) < 0.5, (variant.name, np.rad2deg(th))


def test_trolley_displacement_is_recovered(trolley):
    # Tolerance, measured (bench/paper.py full run, 300 registrations of independent populations):
    # errors x 4.1 ± 3.0 mm (max 16), z −0.2 ± 9.8 mm (99th percentile 25, max 66), θ −0.05 ± 0.06°
    # (max 0.31°).  3 cm, 8 cm and 0.5° hold every one of those 300 and are still well below the
    # 0.2 m forward move that the paper's plain δ misses here (it returns z ≈ 0, see bench/paper.py).
    views, pops = trolley
    (A, fa), (B, fb) = pops[(POSE_A, 0)], pops[(POSE_B, 2)]
    truth = optical_params(true_displacement(views, POSE_A, POSE_B))
    odo = odometry_displacement(views, POSE_A, POSE_B)
    err = RECIPE.register(A, fa, B, fb, views.calib, prior=odo).params - truth
    assert abs(err[0]) < 0.03 and abs(err[1]) < 0.08, err
    assert abs(np.rad2deg(err[2])) < 0.5, np.rad2deg(err[2])
    # The odometry prior alone is not the answer: it misses the 0.1 m sideways step entirely.
    assert abs(optical_params(odo)[0] - truth[0]) > 0.08

