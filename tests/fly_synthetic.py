"""Kept for tests that import it from here: the generator lives in common.fly.synthetic."""
from common.fly.synthetic import textured_plane_pair  # noqa: F401
