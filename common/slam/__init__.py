"""Fly-based SLAM: the localiser (registration of each population against a map of keyframe
populations) and what it is built from."""
from .localiser import Estimate, FlyLocaliser, Keyframe, LocaliserConfig, LocaliserError, voxel_thin

__all__ = ["Estimate", "FlyLocaliser", "Keyframe", "LocaliserConfig", "LocaliserError", "voxel_thin"]
