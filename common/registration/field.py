"""Fast pseudo-distance: B's field on a grid by FFT convolution plus an exact near-field correction.

Why this design (measured, see bench/registration.py): the kernel 1/(ε + r) decays so slowly that the
far flies carry most of S_B(x) = Σⱼ 1/(ε + |x − bⱼ|), so nearest-neighbour truncation is wrong, and the
exact sum is n·p kernel evaluations (25 M for 5,000 flies each: tens of ms even in parallel numba).
The kernel is split, as in particle-particle/particle-mesh (P³M) solvers, into

* a smooth far part K_far(r) = K(r) for r ≥ r_c and a quadratic in r² inside (value and slope matched
  at r_c), convolved with B's triangular-shaped-cloud (TSC) deposit by one real FFT, sampled on a grid
  of spacing h and read back by tricubic (Catmull-Rom) interpolation, value and analytic gradient;
* a compact near part K − K_far (zero beyond r_c = near_cells·h), summed exactly over the neighbours
  of each query point found through a 3-D cell list of B (cells.py).

Defaults: a TSC deposit (quadratic B-spline, window sinc³, deconvolved), near_cells=1,
max_cells=360,000 for a prebuilt field (h ≈ 0.6 m); the registration, which rebuilds the field for
every call, uses max_cells=120,000. bench/registration.py measures the cost and the error against the
exact sum; docs/design/registration.md says why this split.

Grid extent: the grid covers B and the `bounds` the caller will evaluate at (for registration, every
place A's points can reach under the search window), padded by r_c.  A point outside the grid is
still answered, by the exact sum over all of B, so coverage only affects speed, never correctness.
Resolution: h = (grid volume / max_cells)^(1/3); the near radius follows h, so the accuracy of the
split does not depend on ε (ε only enters the kernels, exactly).
"""
from __future__ import annotations

import functools

import numpy as np
import scipy.fft

from . import _kernels
from .cells import CellList
from .pseudo_distance import PopulationError, as_population, as_weights, check_eps


DEPOSITS = {"tsc": (_kernels.tsc_deposit, 3), "cic": (_kernels.cic_deposit, 2)}  # (kernel, window power)


def _deposit_window(fft_shape, power) -> np.ndarray:
    """Fourier transfer function of the deposit (sinc^power per axis: 2 for CIC, 3 for TSC), rfftn layout."""
    f0 = np.fft.fftfreq(fft_shape[0])[:, None, None]
    f1 = np.fft.fftfreq(fft_shape[1])[None, :, None]
    f2 = np.fft.rfftfreq(fft_shape[2])[None, None, :]
    return (np.sinc(f0) * np.sinc(f1) * np.sinc(f2)) ** power


@functools.lru_cache(maxsize=8)
def _far_kernel_spectrum(fft_shape, h, eps, rc, deconvolve, power=2):
    """rfftn of K_far on the circular offset layout (float32), divided by the deposit's window.

    Cached: successive frames of the same scene usually reuse the grid shape and spacing (the
    spacing is rounded to a ladder of 2^(1/8) steps for that reason), which saves one of three FFTs.
    """
    kern = _kernels.far_kernel_grid(*fft_shape, h, eps, rc).astype(np.float32)
    khat = scipy.fft.rfftn(kern, workers=1)
    if deconvolve:
        khat /= _deposit_window(fft_shape, power).astype(np.float32)
    khat.setflags(write=False)
    return khat


def _convolve_zero_padded(rho, khat, fft_shape) -> np.ndarray:
    """Linear convolution of rho (s0, s1, s2) with the kernel whose rfftn is khat, cropped to rho's
    shape, as float64.

    rfftn/irfftn axis by axis, skipping the zero padding: the forward transforms along z and y run
    only over rho's rows (¼ and ½ of the padded volume) and the inverse ones only over the rows that
    are kept.  Same result as irfftn(rfftn(rho, fft_shape) · khat)[:s0, :s1, :s2], ≈40 % less work.
    One thread: on the shared machine two FFT threads measured slower in wall time (and ≈10 % more
    CPU) than one.
    """
    s0, s1, s2 = rho.shape
    F0, F1, F2 = fft_shape
    a = scipy.fft.rfft(rho, n=F2, axis=2, workers=1)
    a = scipy.fft.fft(a, n=F1, axis=1, workers=1, overwrite_x=True)
    a = scipy.fft.fft(a, n=F0, axis=0, workers=1, overwrite_x=True)
    a *= khat
    a = scipy.fft.ifft(a, axis=0, workers=1, overwrite_x=True)[:s0]
    a = scipy.fft.ifft(a, axis=1, workers=1)[:, :s1]
    out = scipy.fft.irfft(a, n=F2, axis=2, workers=1)[:, :, :s2]
    return np.ascontiguousarray(out, dtype=np.float64)


class PseudoDistanceField:
    """B's field S_B, prebuilt for fast δ(A, B) and its gradient with respect to A's points.

    Parameters
    ----------
    B : (p, 3) population whose field is built.
    eps : the ε of the pseudo-distance, metres (> 0).
    weights_b : optional (p,) non-negative weights of B's flies (δ_w of pseudo_distance.py).
    bounds : optional ((3,), (3,)) lower/upper corners of the region where the field will be
        evaluated; the grid covers it and B.  Default: B's bounding box.
    spacing : grid spacing h in metres; default from `max_cells`.
    max_cells : grid-size budget when `spacing` is None (memory ≈ 4·8 bytes per cell, FFT ≈ 8× cells).
    near_cells : near-field radius r_c in grid spacings.  1 (default, with the TSC deposit): δ within
        ≈0.2 % of exact on the deep street scene, the per-point gradient within ≈3.5 % (median);
        1.5: δ within ≈0.06 %, gradient ≈2 %, ≈1.5× slower; 2: δ within ≈0.03 %, gradient ≈1.2 %,
        ≈1.8× slower (8× the neighbours).
    parallel_min : evaluate in parallel threads only for at least this many points (threads are a
        loss on small batches, and 10× slower when another process holds a core).
    deconvolve : divide the kernel spectrum by the deposit's window (removes its smoothing bias).
    deposit : "tsc" (default: 27-node quadratic B-spline) or "cic" (8-node trilinear, the deposit
        before the TSC change, kept so the bench can show both).
    cells_per_radius : x-y column width of the near-field cell list is r_c / cells_per_radius (0.35
        measured fastest at near_cells=1, 0.5 at 2: few columns per query, each one long
        contiguous run).
    """

    def __init__(self, B, eps, weights_b=None, bounds=None, spacing=None, max_cells: int = 360_000,
                 near_cells: float = 1.0, deconvolve: bool = True, parallel_min: int = 50_000,
                 cells_per_radius: float = 0.35, deposit: str = "tsc"):
        self.B = as_population(B, "B")
        self.eps = check_eps(eps)
        self.parallel_min = int(parallel_min)
        self.wb = as_weights(weights_b, len(self.B), "weights_b")
        if max_cells < 64:
            raise PopulationError(f"max_cells must be at least 64, got {max_cells}")
        if deposit not in DEPOSITS:
            raise PopulationError(f"deposit must be one of {sorted(DEPOSITS)}, got {deposit!r}")
        if near_cells <= 0:
            raise PopulationError(f"near_cells must be positive, got {near_cells}")
        lo = self.B.min(0)
        hi = self.B.max(0)
        if bounds is not None:
            blo, bhi = (np.asarray(b, dtype=float).reshape(3) for b in bounds)
            if not (np.all(np.isfinite(blo)) and np.all(np.isfinite(bhi)) and np.all(bhi >= blo)):
                raise PopulationError(f"bounds must be finite (lo, hi) corners with hi >= lo, got {bounds}")
            lo = np.minimum(lo, blo)
            hi = np.maximum(hi, bhi)
        ext = hi - lo
        if spacing is None:
            floor = max(ext.max() / 50.0, 1e-3)
            vol = np.prod(np.maximum(ext, floor))
            h = float((vol / max_cells) ** (1.0 / 3.0))
            h = float(2.0 ** (np.ceil(8 * np.log2(h)) / 8))  # ladder of 2^(1/8): kernel cache hits
        else:
            h = float(spacing)
            if not np.isfinite(h) or h <= 0:
                raise PopulationError(f"spacing must be a positive distance, got {spacing}")
        self.h = h
        self.rc = float(near_cells * h)
        pad = self.rc + 2 * h
        self.lo = lo - pad
        shape = np.ceil((ext + 2 * pad) / h).astype(np.int64) + 1
        self.shape = tuple(int(s) for s in shape)
        if spacing is not None and np.prod(shape) > 50_000_000:
            raise PopulationError(f"spacing {h} m gives a {self.shape} grid, too large")

        # Far field: deposit ⊛ K_far by zero-padded FFT (linear, not circular, convolution).
        deposit_kernel, power = DEPOSITS[deposit]
        rho = deposit_kernel(self.B, self.wb, self.lo, h, shape)
        fft_shape = tuple(scipy.fft.next_fast_len(2 * s - 1, real=True) for s in self.shape)
        khat = _far_kernel_spectrum(fft_shape, h, self.eps, self.rc, bool(deconvolve), power)
        self.grid = _convolve_zero_padded(rho.astype(np.float32), khat, fft_shape)

        # Near field: 3-D cell list of B (cells of side r_c / cells_per_radius).
        self.cells = CellList(self.B, self.wb, self.rc, cells_per_radius)
        self.weight_sum = float(self.wb.sum())
        self.last_outside = 0

    # ------------------------------------------------------------------------------------ queries
    @property
    def upper(self) -> np.ndarray:
        """Upper corner of the grid (points beyond it fall back to the exact sum)."""
        return self.lo + (np.asarray(self.shape) - 1) * self.h

    def covers(self, Q) -> np.ndarray:
        """Boolean (n,) mask of the rows of Q inside the grid."""
        Q = np.asarray(Q, dtype=float)
        return np.all((Q >= self.lo) & (Q <= self.upper), axis=1)

    def _args(self, near: bool):
        return (self.grid, self.lo, self.h, self.B, self.wb, self.eps, self.rc, *self.cells.args(), near)

    def field(self, Q, with_grad: bool = False, near: bool = True):
        """S_B at the rows of Q (and ∇S_B, (n, 3), when `with_grad`).

        ``near=False`` returns the far part alone: B's field smoothed within r_c, the coarse level of
        the registration's coarse-to-fine search.
        """
        S, G = self._field(as_population(Q, "Q", allow_empty=True), with_grad, near)
        return (S, G) if with_grad else S

    def _field(self, Q, with_grad: bool, near: bool):
        """(S, G or None) at the rows of Q, a validated (n, 3) float64 C array (no checks: the
        registration's inner loop calls this some 100 times per registration)."""
        if not with_grad and len(Q) < self.parallel_min:
            S, out = _kernels.fast_values(Q, *self._args(near))
            self.last_outside = int(out)
            return S, None
        kern = _kernels.fast_field if len(Q) >= self.parallel_min else _kernels.fast_field_serial
        S, G, out = kern(Q, *self._args(near), with_grad)
        self.last_outside = int(out)
        return S, (G if with_grad else None)

    def delta(self, A, weights_a=None) -> float:
        """δ(A, B) (δ_w with weights), fast."""
        A = as_population(A, "A")
        S = self._field(A, False, True)[0]
        if weights_a is None:
            return self.weight_sum / len(A) * float((1.0 / S).sum())
        wa = as_weights(weights_a, len(A), "weights_a")
        return self.weight_sum / wa.sum() * float((wa / S).sum())

    def delta_and_grad(self, A, weights_a=None):
        """(δ(A, B), ∂δ/∂aᵢ as an (n, 3) array), fast."""
        A = as_population(A, "A")
        wa = as_weights(weights_a, len(A), "weights_a")
        S, G = self.field(A, with_grad=True)
        scale = self.weight_sum / wa.sum()
        delta = scale * float((wa / S).sum())
        grad = (-scale * wa / (S * S))[:, None] * G
        return delta, grad

    def batch_sums(self, A, wa, Rs, ts, near: bool = True) -> np.ndarray:
        """Σᵢ wa_i / S_B(Rₖᵀ(aᵢ − tₖ)) for each candidate k (arrays already validated).

        Multiply by weight_sum / wa.sum() to get δ(A, fₖ(B)) with fₖ = (Rₖ, tₖ).
        """
        return _kernels.batch_delta(A, wa, np.ascontiguousarray(Rs, dtype=float),
                                    np.ascontiguousarray(ts, dtype=float), *self._args(near))
