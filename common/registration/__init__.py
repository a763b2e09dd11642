"""Fly-population registration (Louchet et al., "Flies open a door to SLAM")."""
from .pseudo_distance import PopulationError, field_exact, pseudo_distance_exact
from .field import PseudoDistanceField

__all__ = ["PopulationError", "field_exact", "pseudo_distance_exact", "PseudoDistanceField"]
from .register import RegistrationResult, StereoModel, register_6dof, register_planar
from .local import LocalCorrelationField
from .weights import covisible_masks, depth_sigma, depth_weights, footprint_weights, visible_mask

__all__ += ["RegistrationResult", "StereoModel", "register_6dof", "register_planar", "covisible_masks",
            "depth_sigma", "depth_weights", "footprint_weights", "visible_mask", "LocalCorrelationField"]
