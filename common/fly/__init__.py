"""The Fly algorithm: a population of 3-D points evolved to lie on the surfaces a stereo rig sees.

Public API: ``EvolverConfig``, ``FlyEvolver`` (see ``common.fly.evolver``), and the accuracy measure
``inlier_fraction`` (``common.fly.metrics``) shared by tests, benches and services.

Threading: the fitness kernel is a numba ``prange`` loop.  numba's OpenMP layer busy-waits between
parallel regions by default, which on a small machine shared with other busy processes turns a
sub-millisecond evaluation into several milliseconds (the spinning thread waits for a descheduled
peer).  Importing this package sets ``OMP_WAIT_POLICY=PASSIVE`` unless the environment already chose a
policy; it only takes effect when no OpenMP parallel region has run yet in the process.
"""
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from common.fly.config import EvolverConfig, EvolverConfigError  # noqa: E402
from common.fly.evolver import FitnessTermError, FlyEvolver, NoImagesError  # noqa: E402
from common.fly.fitness import OUTSIDE_FITNESS, ImageError  # noqa: E402
from common.fly.metrics import InlierStats, inlier_fraction, inlier_stats  # noqa: E402

__all__ = ["EvolverConfig", "EvolverConfigError", "FlyEvolver", "FitnessTermError", "NoImagesError",
           "OUTSIDE_FITNESS", "ImageError", "InlierStats", "inlier_fraction", "inlier_stats"]
