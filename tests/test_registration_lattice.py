"""The coarse lattice sized to the search window (lattice_step): same answer, less work."""
import numpy as np
import pytest

from common.geometry import make_transform, rot_y
from common.registration import PopulationError, StereoModel, register_planar


def test_window_sized_lattice_finds_the_full_lattices_answer_with_fewer_evaluations(deep_street_views):
    rig, truth, A, B = deep_street_views
    prior = make_transform(rot_y(0.0), [-0.1, 0.0, 0.8])         # odometry, a little off
    window = (0.25, 0.25, np.deg2rad(8.0))                         # the localiser's usual window
    full = register_planar(A, B, prior=prior, window=window, stereo=StereoModel(rig, lattice_step=None))
    sized = register_planar(A, B, prior=prior, window=window, stereo=StereoModel(rig))
    assert full.ok and sized.ok, (full.reason, sized.reason)
    np.testing.assert_allclose(sized.params, full.params, atol=0.01)
    assert np.hypot(*(sized.params[:2] - truth[:2])) < 0.3          # as in test_registration_deep
    assert sized.evaluations < 0.7 * full.evaluations


def test_a_pinned_parameter_stays_at_the_prior(deep_street_views):
    rig, truth, A, B = deep_street_views
    prior = make_transform(rot_y(truth[2]), [truth[0], 0.0, 0.8])
    res = register_planar(A, B, prior=prior, window=(0.0, 0.3, 0.0), stereo=StereoModel(rig))
    assert res.params[0] == truth[0] and res.params[2] == pytest.approx(truth[2])
    assert abs(res.params[1] - truth[1]) < 0.2


def test_lattice_step_must_be_a_positive_distance(deep_street_views):
    rig, _, A, B = deep_street_views
    with pytest.raises(PopulationError, match="lattice_step"):
        register_planar(A, B, lattice_step=-1.0)
