"""Fly-population registration (Louchet et al., "Flies open a door to SLAM")."""
from .pseudo_distance import PopulationError, field_exact, pseudo_distance_exact
from .field import PseudoDistanceField

__all__ = ["PopulationError", "field_exact", "pseudo_distance_exact", "PseudoDistanceField"]
from .register import RegistrationResult, register_6dof, register_planar

__all__ += ["RegistrationResult", "register_6dof", "register_planar"]
