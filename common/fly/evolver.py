"""The Fly algorithm evolver: a population of 3-D points that evolves to lie on visible surfaces.

Usage (the service layer wraps exactly this)::

    ev = FlyEvolver(calib, EvolverConfig(), seed=0)
    ev.set_images(left, right)        # once per frame; re-scores the population
    ev.step(10)                       # 10 generations; call in a loop, the population is always usable
    ev.positions, ev.fitness          # (N, 3) float32 left-optical points, (N,) float32
    ev.move_flies(T_new_old)          # proprioceptive fusion between frames (robot motion)
    ev.add_fitness_term("sonar", fn, weight)   # fn(positions (N,3) float32) -> (N,) float32

Steady state (default): one *generation* is N offspring (N = population size), made in batches of
``batch_fraction·N`` (default one batch) and inserted one at a time.  Each offspring comes from one
operator (see ``common.fly.operators``): Gaussian mutation in (u, v, disparity), depth exchange (the
parent's pixel with the disparity of the fittest of a few image neighbours — PatchMatch-like
propagation), 2- or 3-parent barycentric crossover, or immigration.  Mutation and exchange children come
from every fly once per generation and compete with their own parent (deterministic crowding: each fly
keeps its image niche and refines its depth); crossover children come from tournament or elitist parents
and replace the loser of a reverse tournament when they are fitter; immigrants replace that loser
unconditionally (they are how new objects get noticed).  Comparisons use the shared fitness (2-D sharing,
``SharingGrid``).

Generational: every generation builds a whole new population from selected parents; with 'elitist'
selection the top ``elite_fraction`` survives unchanged.

Population arrays are kept ordered by sharing cell (row-major over the left image), which makes
fitness evaluation cache-friendly and lets the operators pick mates among image neighbours.  The order of
flies is therefore not stable across ``step`` calls (``move_flies``/``set_images`` keep it).

Randomness comes from one numpy Generator seeded by ``seed``: a run is reproducible.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from common.camera import StereoCalibration
from common.fly.config import EvolverConfig
from common.fly.fitness import (OUTSIDE_FITNESS, FrameImages, PreparedFrame, image_fitness, prepare_frame,
                                prepare_images)
from common.fly.operators import (CROSSOVER2, CROSSOVER3, EXCHANGE, IMMIGRANT, MUTATION, SharingGrid,
                                  camera_vector, cell_order, insert_offspring, make_offspring,
                                  permuted, plan_batch, project_uvd)
from common.fly.sampling import disparity_bounds, sample_flies
from common.fly.threads import KernelChooser

FitnessTerm = Callable[[np.ndarray], np.ndarray]

_MATE_REACH = 8          # crossover mates are within this many places in the cell-ordered population
_EXCHANGE_BEST_OF = 8    # depth exchange copies the fittest of this many such neighbours
_NOISE_REFRESH_FRAMES = 30
_AUTO_MIN_FLIES = 1000   # below this a parallel region is never worth it
# What each kernel costs depends on the machine and its load, not on the evolver: one chooser per process.
_KERNEL_CHOOSER = KernelChooser()
_STEP_UP, _STEP_DOWN = 1.5, 0.85   # adaptive mutation: disparity step after a success / a failure


class FitnessTermError(ValueError):
    """A plug-in fitness term was malformed or returned something other than (N,) finite numbers."""


class NoImagesError(RuntimeError):
    """step() was called before set_images()."""


def images_ahead(calib: StereoCalibration, config: EvolverConfig, left: np.ndarray,
                 right: np.ndarray) -> FrameImages:
    """The share of ``FlyEvolver.set_images``'s work that depends on the images alone, for ``config``:
    thread-safe, so the next frame can be prepared while the evolver works on this one."""
    c = config
    return prepare_images(calib, left, right, c.neighbourhood, c.mean_removal_px, c.gradient_window,
                          c.gradient_min_half, c.gradient_epipolar)


class FlyEvolver:
    def __init__(self, calib: StereoCalibration, config: EvolverConfig | None = None, seed: int = 0):
        self.calib = calib
        self.config = config = config if config is not None else EvolverConfig()
        config.validate()
        self.rng = np.random.default_rng(seed)
        self._half = config.neighbourhood // 2
        self._margin = self._half + 1.0
        self.depth_min, self.depth_max = config.depth_range(calib)
        self._d_range = disparity_bounds(calib, self.depth_min, self.depth_max)
        span = calib.width - 1 - 2 * self._margin
        fb = calib.fx * calib.baseline
        d_far = fb / (1e6 * self.depth_min) - calib.doffs   # keep mutated flies at finite depth
        self._d_range = (max(self._d_range[0], -span, d_far), min(self._d_range[1], span))
        self._sigma_max = max((self._d_range[1] - self._d_range[0]) / 2, config.mutation_sigma_disparity_min)
        cell = config.sharing_radius_px or float(np.sqrt(calib.width * calib.height / config.population))
        self.sharing = SharingGrid(calib.width, calib.height, cell, config.sharing_strength)
        self._terms: dict[str, tuple[FitnessTerm, float]] = {}
        self._cam = camera_vector(calib)
        self._chooser = _KERNEL_CHOOSER
        self._frame: PreparedFrame | None = None
        self._noise_sigma: float | None = None
        self._frames_since_noise = 0
        self.generation = 0
        n = config.population
        self._pos = sample_flies(calib, n, self.depth_min, self.depth_max, self.rng, self._margin)
        self._sigma_d = np.full(n, config.mutation_sigma_disparity, np.float32)
        self._fit = np.full(n, OUTSIDE_FITNESS, np.float32)
        self._cells = np.full(n, -1, np.int64)
        self._reorder()

    # ------------------------------------------------------------------------------ public state
    @property
    def positions(self) -> np.ndarray:
        """(N, 3) float32 fly positions in the left optical frame (read-only view; copy to keep)."""
        v = self._pos.view()
        v.flags.writeable = False
        return v

    @property
    def fitness(self) -> np.ndarray:
        """(N,) float32 fitness: image term in [0, 1) plus weighted plug-in terms; −inf outside an image
        or before the first set_images()."""
        v = self._fit.view()
        v.flags.writeable = False
        return v

    def shared_fitness(self) -> np.ndarray:
        """(N,) float32 fitness after 2-D sharing — what selection and replacement compare."""
        return SharingGrid.apply(self._fit, self.sharing.factor(self._cells))

    @property
    def mutation_sigma_disparity(self) -> np.ndarray:
        """(N,) float32 per-fly disparity mutation step (pixels), adapted when adaptive_mutation is on."""
        return self._sigma_d.copy()

    @property
    def frame(self) -> PreparedFrame | None:
        return self._frame

    # ------------------------------------------------------------------------------- inputs
    def set_images(self, left: np.ndarray, right: np.ndarray, images: FrameImages | None = None) -> None:
        """Load a new rectified stereo frame (H×W×3 uint8 RGB or H×W mono) and re-score the population.

        With ``noise_sigma=None`` the image noise is estimated on the first frame and re-estimated every
        ``_NOISE_REFRESH_FRAMES`` frames (a camera's noise changes slowly; the estimate costs a few ms).
        ``images``: :func:`images_ahead` of these arrays, computed beforehand (e.g. in another thread).
        """
        c = self.config
        sigma = c.noise_sigma
        if sigma is None and self._noise_sigma is not None and self._frames_since_noise < _NOISE_REFRESH_FRAMES:
            sigma = self._noise_sigma
            self._frames_since_noise += 1
        frame = prepare_frame(self.calib, left, right, c.neighbourhood, sigma, c.ssd_floor_scale,
                              c.gradient_saturation, c.window_sigma, c.mean_removal_px, c.gradient_window,
                              c.gradient_min_half, c.gradient_epipolar, images)
        if c.noise_sigma is None and sigma is None:
            self._noise_sigma, self._frames_since_noise = frame.noise_sigma, 1
        self._frame = frame
        self._rescore()

    def move_flies(self, T_new_old: np.ndarray, rescore: bool = True) -> None:
        """Proprioceptive fusion: move every fly by the robot's motion, ``p_new = T_new_old · p_old``
        (4×4 rigid transform between the left optical frames of two frames), then re-score.

        ``rescore=False`` when the new frame's images follow at once (``set_images`` re-scores): scoring
        the moved flies on the old images would only be thrown away."""
        T = np.asarray(T_new_old, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"T_new_old must be a finite 4×4 matrix, got shape {T.shape}")
        R = T[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or not np.allclose(T[3], [0, 0, 0, 1]):
            raise ValueError("T_new_old must be a rigid transform (orthonormal rotation, last row 0 0 0 1)")
        with np.errstate(invalid="ignore", over="ignore"):
            self._pos = (self._pos.astype(np.float64) @ R.T + T[:3, 3]).astype(np.float32)
        if rescore:
            self._rescore()

    def add_fitness_term(self, name: str, fn: FitnessTerm, weight: float = 1.0) -> None:
        """Add (or replace) a plug-in fitness term: ``fn(positions (N,3) float32) -> (N,) float32``,
        added as ``weight · fn(positions)`` to the image fitness of every fly evaluated from now on."""
        if not callable(fn):
            raise FitnessTermError(f"fitness term {name!r} is not callable")
        if not np.isfinite(weight):
            raise FitnessTermError(f"fitness term {name!r} weight must be finite, got {weight}")
        self._terms[str(name)] = (fn, float(weight))
        self._rescore()

    def remove_fitness_term(self, name: str) -> None:
        if name not in self._terms:
            raise KeyError(f"no fitness term named {name!r}; have {sorted(self._terms)}")
        del self._terms[name]
        self._rescore()

    # ------------------------------------------------------------------------------ evaluation
    def evaluate(self, positions: np.ndarray) -> np.ndarray:
        """(N,) float32 total fitness of arbitrary points on the current frame (image + plug-in terms)."""
        if self._frame is None:
            raise NoImagesError("no images yet: call set_images() first")
        pos = np.ascontiguousarray(positions, dtype=np.float32)
        c = self.config
        frame, calib = self._frame, self.calib

        def kernel(parallel: bool) -> np.ndarray:
            return image_fitness(frame, calib, pos, subpixel=c.subpixel, vertical=c.subpixel_vertical,
                                 parallel=parallel)

        if c.parallel == "auto" and len(pos) >= _AUTO_MIN_FLIES:
            fit = self._chooser.run(kernel, len(pos))
        else:
            fit = kernel(c.parallel is True or (c.parallel == "auto" and len(pos) >= c.parallel_min_flies))
        for name, (fn, w) in self._terms.items():
            t = np.asarray(fn(pos), dtype=np.float32)
            if t.shape != (len(pos),) or not np.all(np.isfinite(t)):
                raise FitnessTermError(
                    f"fitness term {name!r} must return ({len(pos)},) finite values, got shape {t.shape}")
            fit += np.float32(w) * t
        return fit

    def _rescore(self) -> None:
        """Re-evaluate every fly (new frame, moved flies, new terms); fly order is kept."""
        if self._frame is not None:
            self._fit = self.evaluate(self._pos)
        u, v, _ = project_uvd(self.calib, self._pos)
        self._cells = self.sharing.cells(u, v)
        self.sharing.update(self._cells)

    def _reorder(self, cells_current: bool = False) -> None:
        """Sort the population by sharing cell (cache locality, local mates).  ``cells_current``: every
        fly's cell is already up to date (steady-state insertion keeps them), else they are recomputed."""
        cells = self._cells
        if not cells_current:
            u, v, _ = project_uvd(self.calib, self._pos)
            cells = self.sharing.cells(u, v)
        order = cell_order(cells, self.sharing.cols * self.sharing.rows)
        self._pos, self._fit, self._sigma_d, self._cells = permuted(order, self._pos, self._fit, self._sigma_d,
                                                                    cells)
        self.sharing.update(self._cells)

    # ------------------------------------------------------------------------------- evolution
    def step(self, n: int = 1) -> None:
        """Run ``n`` generations on the current frame."""
        if self._frame is None:
            raise NoImagesError("no images yet: call set_images() first")
        if int(n) != n or n < 0:
            raise ValueError(f"step(n) needs a non-negative integer, got {n}")
        for _ in range(int(n)):
            if self.config.mode == "steady":
                self._steady_generation()
            else:
                self._generational_generation()
            self.generation += 1

    def _plan(self, shared: np.ndarray, m: int, own_for_local: bool) -> tuple[np.ndarray, np.ndarray]:
        """(operators, parents) of a batch of ``m`` children, sorted by parent (operators.plan_batch)."""
        c = self.config
        rates = np.zeros(5)
        rates[[CROSSOVER2, CROSSOVER3, IMMIGRANT, EXCHANGE]] = (c.crossover2_rate, c.crossover3_rate,
                                                                c.immigration_rate, c.exchange_rate)
        rates[MUTATION] = max(0.0, 1.0 - rates.sum())
        if c.selection == "tournament":
            size, pool = int(c.tournament_size), np.zeros(0, np.int64)
        else:
            k = max(1, int(round(c.elite_fraction * len(shared))))
            size, pool = 0, np.argpartition(-shared, k - 1)[:k].astype(np.int64)
        ops, parents = np.empty(m, np.int64), np.empty(m, np.int64)
        plan_batch(np.cumsum(rates / rates.sum()), np.ascontiguousarray(shared, np.float32), size, pool,
                   bool(own_for_local), int(self.rng.integers(2 ** 62)), ops, parents)
        return ops, parents

    def _make_offspring(self, parents: np.ndarray, ops: np.ndarray, parent_sigma: np.ndarray):
        """Children positions and disparity steps (one numba loop over the batch, see operators)."""
        c, rng = self.config, self.rng
        m = len(parents)
        n_imm = int(np.count_nonzero(ops == IMMIGRANT))
        immigrants = (sample_flies(self.calib, n_imm, self.depth_min, self.depth_max, rng, self._margin) if n_imm
                      else np.zeros((0, 3), np.float32))
        child = np.empty((m, 3), np.float32)
        sigma = np.empty(m, np.float32)
        none = np.zeros(0, np.int64)
        make_offspring(ops, parents, none, none, self._pos, self._fit, parent_sigma, immigrants, self._cam,
                       float(c.mutation_sigma_px), float(self._d_range[0]), float(self._d_range[1]),
                       float(c.mutation_sigma_disparity_min), float(c.mutation_sigma_disparity), _MATE_REACH,
                       _EXCHANGE_BEST_OF, int(rng.integers(2 ** 62)), child, sigma)
        return child, sigma

    def _steady_generation(self) -> None:
        c, rng = self.config, self.rng
        n = len(self._pos)
        batch = max(1, int(round(c.batch_fraction * n)))
        done = 0
        while done < n:
            m = min(batch, n - done)
            done += m
            # With crowding over the whole population, local operators (mutation, depth exchange) refine
            # the parent in its own niche: every fly gets its turn once per generation instead of the
            # fittest getting most of them.  Parents come in population (cell) order: children land near
            # them, so the batch is evaluated in image order too (cache-friendly).
            ops, parents = self._plan(self.shared_fitness(), m, own_for_local=c.crowding and m == n)
            child, sigma = self._make_offspring(parents, ops, self._sigma_d[parents])
            fit = self.evaluate(child)
            g = self.sharing
            insert_offspring(ops, parents, max(2, c.tournament_size), int(rng.integers(2 ** 62)), child, sigma,
                             fit, self._pos, self._fit, self._sigma_d, self._cells, g.counts,
                             float(g.expected), float(g.strength), float(g.cell), g.cols, g.rows, self._cam,
                             bool(c.crowding), bool(c.adaptive_mutation), _STEP_UP, _STEP_DOWN,
                             float(c.mutation_sigma_disparity_min), float(self._sigma_max))
        self._reorder(cells_current=True)

    def _generational_generation(self) -> None:
        c, rng = self.config, self.rng
        n = len(self._pos)
        shared = self.shared_fitness()
        n_elite = int(round(c.elite_fraction * n)) if c.selection == "elitist" else 0
        elite = np.argpartition(-shared, n_elite - 1)[:n_elite] if n_elite else np.zeros(0, np.int64)
        m = n - n_elite
        ops, parents = self._plan(shared, m, own_for_local=False)
        sigma = self._sigma_d[parents]
        if c.adaptive_mutation:
            # Log-normal self-adaptation: a mutated child carries its own step, selection keeps good ones.
            mut = ops == MUTATION
            sigma = sigma.copy()
            sigma[mut] *= np.exp(0.6 * rng.standard_normal(int(mut.sum()))).astype(np.float32)
            np.clip(sigma, c.mutation_sigma_disparity_min, self._sigma_max, out=sigma)
        child, sigma = self._make_offspring(parents, ops, sigma)
        fit = self.evaluate(child)
        self._pos = np.concatenate([self._pos[elite], child])
        self._fit = np.concatenate([self._fit[elite], fit])
        self._sigma_d = np.concatenate([self._sigma_d[elite], sigma])
        self._reorder()
