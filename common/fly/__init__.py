"""The Fly algorithm: a population of 3-D points evolved to lie on the surfaces a stereo rig sees.

Public API: ``EvolverConfig``, ``FlyEvolver`` (see ``common.fly.evolver``), and the accuracy measure
``inlier_fraction`` (``common.fly.metrics``) shared by tests, benches and services.
"""
from common.fly.config import EvolverConfig, EvolverConfigError
from common.fly.evolver import FitnessTermError, FlyEvolver, NoImagesError
from common.fly.fitness import OUTSIDE_FITNESS, ImageError
from common.fly.metrics import InlierStats, inlier_fraction, inlier_stats

__all__ = ["EvolverConfig", "EvolverConfigError", "FlyEvolver", "FitnessTermError", "NoImagesError",
           "OUTSIDE_FITNESS", "ImageError", "InlierStats", "inlier_fraction", "inlier_stats"]
