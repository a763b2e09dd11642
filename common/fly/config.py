"""Configuration of the Fly algorithm evolver (one dataclass, validated on construction)."""
from __future__ import annotations

import math
from dataclasses import dataclass


class EvolverConfigError(ValueError):
    """An EvolverConfig field is out of range or inconsistent with another."""


@dataclass
class EvolverConfig:
    """Everything that tunes the evolver.  Defaults are the ones that reach ≥ 90 % inliers on the
    Middlebury motorcycle pair (see tests/test_fly_accuracy.py and bench/evolver.py).

    Depths are metres along the left optical axis; pixel quantities are in pixels of the calibrated
    (rectified) images.

    Each offspring is made by exactly one operator (``*_rate``; the rest, 1 − sum, is mutation in
    (u_left, v, disparity) space, i.e. scaled to stereo depth uncertainty).  In steady state a mutated
    or exchanged child competes with its own parent (deterministic crowding, every fly keeps its image
    niche; local children come from every fly once per generation); other children replace the loser
    of a reverse tournament.  Fitness is G·F / (SSD_mean + F) (see common.fly.fitness).
    """
    population: int = 5000
    neighbourhood: int = 7            # N of the N×N window compared between left and right (odd, 3..15)
    # Flies are drawn with 1/z uniform in [1/depth_max, 1/depth_min] (metres; depth_max may be inf).
    depth_min: float | None = None    # None: where the disparity is a quarter of the image width, f·B/(W/4)
    depth_max: float | None = None    # None: where it is one pixel, f·B/1 px (farther is not resolved)
    mode: str = "steady"              # 'steady' | 'generational'
    selection: str = "tournament"     # 'tournament' | 'elitist'
    tournament_size: int = 2
    elite_fraction: float = 0.1       # elitist ranking: parents drawn from this top fraction; elites kept
    crossover2_rate: float = 0.1      # 2-parent barycentric crossover (children on the parents' line)
    crossover3_rate: float = 0.1      # 3-parent barycentric crossover (children in the parents' plane)
    immigration_rate: float = 0.02    # fresh flies drawn like the initialisation
    exchange_rate: float = 0.6        # depth exchange: parent's pixel, an image neighbour's disparity
    mutation_sigma_px: float = 0.7    # image-plane step (pixels) of the left projection
    mutation_sigma_disparity: float = 4.0   # initial disparity step (pixels)
    adaptive_mutation: bool = True    # per-fly disparity step: ×1.5 / ×0.85 after a win / loss (steady state)
    mutation_sigma_disparity_min: float = 0.05
    crowding: bool = True             # steady state: a mutated or exchanged child competes with its parent
    batch_fraction: float = 1.0       # steady state: offspring per batch (evaluated together), fraction of N
    sharing_radius_px: float | None = None   # 2-D sharing cell size in the left image; None = sqrt(W·H / N)
    sharing_strength: float = 1.0            # 0 disables sharing
    subpixel: bool = True             # right window interpolated along the epipolar line; else nearest pixels
    subpixel_vertical: bool = False   # full bilinear sampling of both windows (slower, same disparity)
    noise_sigma: float | None = None  # grey-level noise std; None = estimated (Immerkær) every 30 frames
    ssd_floor_scale: float = 2.0      # F = ssd_floor_scale · 2·σ²  (2σ² = variance of a noisy difference)
    gradient_saturation: float = 6.0  # k in G = g²/(g² + (k·σ)²), g² the mean squared gradient
    window_sigma: float | None = 1.2  # Gaussian window weighting (px), favours the centre; None = flat
    mean_removal_px: int | None = 15  # local-mean box (odd px) subtracted before matching; None = raw images
    gradient_window: int | None = None  # box (px) over which G averages gradient energy; None = N
    gradient_min_half: bool = True    # G from the least textured half-window (see fitness.gradient_energy)
    gradient_epipolar: bool = True    # G from the x gradient only (what constrains disparity); else |∇|²

    parallel: bool | str = "auto"     # fitness kernel: True all cores, False calling thread, 'auto' (threads.py)
    parallel_min_flies: int = 20000   # with parallel='auto' and the chooser not yet informed: threshold

    def __post_init__(self):
        self.validate()

    def validate(self) -> None:
        def bad(msg):
            raise EvolverConfigError(f"EvolverConfig: {msg}")
        if int(self.population) != self.population or self.population < 4:
            bad(f"population must be an integer ≥ 4, got {self.population}")
        if self.neighbourhood % 2 != 1 or not 1 <= self.neighbourhood <= 15:
            bad(f"neighbourhood must be odd in 1..15, got {self.neighbourhood}")
        if self.depth_min is not None and not (self.depth_min > 0 and math.isfinite(self.depth_min)):
            bad(f"depth_min must be positive and finite, got {self.depth_min}")
        if self.depth_max is not None and not self.depth_max > (self.depth_min or 0.0):
            bad(f"depth_max ({self.depth_max}) must exceed depth_min ({self.depth_min})")
        if self.mode not in ("steady", "generational"):
            bad(f"mode must be 'steady' or 'generational', got {self.mode!r}")
        if self.selection not in ("tournament", "elitist"):
            bad(f"selection must be 'tournament' or 'elitist', got {self.selection!r}")
        if self.tournament_size < 1:
            bad(f"tournament_size must be ≥ 1, got {self.tournament_size}")
        if not 0 < self.elite_fraction < 1:
            bad(f"elite_fraction must be in (0, 1), got {self.elite_fraction}")
        rates = (self.crossover2_rate, self.crossover3_rate, self.immigration_rate, self.exchange_rate)
        if min(rates) < 0 or sum(rates) > 1:
            bad(f"crossover, exchange and immigration rates must be ≥ 0 and sum to ≤ 1, got {rates}")
        for name in ("mutation_sigma_px", "mutation_sigma_disparity", "mutation_sigma_disparity_min",
                     "ssd_floor_scale", "gradient_saturation"):
            v = getattr(self, name)
            if not (v >= 0 and math.isfinite(v)):
                bad(f"{name} must be finite and ≥ 0, got {v}")
        if not 0 < self.batch_fraction <= 1:
            bad(f"batch_fraction must be in (0, 1], got {self.batch_fraction}")
        if self.parallel not in (True, False, "auto"):
            bad(f"parallel must be True, False or 'auto', got {self.parallel!r}")
        if int(self.parallel_min_flies) != self.parallel_min_flies or self.parallel_min_flies < 1:
            bad(f"parallel_min_flies must be a positive integer, got {self.parallel_min_flies}")
        if self.sharing_radius_px is not None and not self.sharing_radius_px > 0:
            bad(f"sharing_radius_px must be positive or None, got {self.sharing_radius_px}")
        if self.sharing_strength < 0:
            bad(f"sharing_strength must be ≥ 0, got {self.sharing_strength}")
        if self.noise_sigma is not None and not self.noise_sigma > 0:
            bad(f"noise_sigma must be positive or None, got {self.noise_sigma}")
        for name in ("mean_removal_px", "gradient_window"):
            v = getattr(self, name)
            if v is not None and (int(v) != v or v < 1 or v % 2 != 1):
                bad(f"{name} must be an odd positive integer or None, got {v}")
        if self.window_sigma is not None and not self.window_sigma > 0:
            bad(f"window_sigma must be positive or None, got {self.window_sigma}")

    def depth_range(self, calib) -> tuple[float, float]:
        """(depth_min, depth_max) in metres for a rig, the unset ends derived from its f·B and width."""
        fb = calib.fx * calib.baseline
        lo = self.depth_min if self.depth_min is not None else fb / (0.25 * calib.width)
        hi = self.depth_max if self.depth_max is not None else fb / 1.0
        if not hi > lo:
            raise EvolverConfigError(f"EvolverConfig: depth range [{lo:.3g}, {hi:.3g}] m is empty for a rig "
                                     f"with f·B = {fb:.3g} px·m")
        return lo, hi
