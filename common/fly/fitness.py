"""Image fitness of flies: how well the N×N neighbourhoods at a fly's two projections agree.

    fitness = G · F / (SSD_mean + F)

* SSD_mean — mean over colours and the (optionally Gaussian-weighted) N×N window of (L − R)², sampled
  bilinearly at the left and right projections (or at the nearest pixel when ``subpixel`` is off);
* F — a floor tied to the image noise (``ssd_floor_scale · 2σ²``).  With only a tiny constant there,
  flies pile up wherever the SSD is near zero (saturated or identical patches) instead of on surfaces;
* G ∈ [0, 1) — a saturating normaliser ``g²/(g² + g_sat²)`` of the window's RMS image gradient ``g``
  in the left image: uniform regions (where any depth matches) score low, while strong edges do not
  dominate the ranking the way a raw gradient sum would.

This is ``G / (SSD + floor)`` of the Fly-algorithm literature scaled by the constant F, so fitness lies
in [0, 1) and plug-in terms from other sensors can be weighted against it.  Flies whose window leaves
either image (or that are behind the camera) get ``OUTSIDE_FITNESS`` (−inf), lower than any other.

The kernel is a numba ``prange`` loop over flies; ``prepare_frame`` does the per-frame work once
(``prepare_images``, its share that depends on the images alone, can be done ahead in another thread).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from common.camera import CalibrationError, StereoCalibration
from common.numba_cache import cache_twin

OUTSIDE_FITNESS = np.float32(-np.inf)


class ImageError(ValueError):
    """Images that cannot be used as a stereo pair (shape, dtype, size or channel mismatch)."""


@dataclass
class PreparedFrame:
    """One stereo frame ready for the fitness kernel (computed once per frame by ``prepare_frame``)."""
    left: np.ndarray        # H×W×C float32, C-contiguous
    right: np.ndarray       # H×W×C float32
    gradient_norm: np.ndarray  # H×W float32, G in [0, 1) for the window centred at each left pixel
    noise_sigma: float      # grey-level noise std used for the floor
    inv_floor: float        # 1 / F
    weights: np.ndarray     # N×N float32 window weights, summing to 1 / C


def _as_float_image(img: np.ndarray, which: str) -> np.ndarray:
    a = np.asarray(img)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 3):
        raise ImageError(f"{which} image must be H×W mono or H×W×3 RGB, got shape {np.shape(img)}")
    if a.dtype == np.uint8:
        return np.ascontiguousarray(a, dtype=np.float32)
    if np.issubdtype(a.dtype, np.floating):
        if not np.all(np.isfinite(a)):
            raise ImageError(f"{which} image has non-finite values")
        return np.ascontiguousarray(a, dtype=np.float32)
    raise ImageError(f"{which} image must be uint8 (or float in 0..255), got {a.dtype}")


def estimate_noise_sigma(grey: np.ndarray, flat_fraction: float = 0.3) -> float:
    """Noise std (grey levels) of a grey image: Immerkær's Laplacian-difference estimator restricted to
    the ``flat_fraction`` of pixels with the weakest gradient, so texture is not mistaken for noise.

    Evaluated at every other row and column (a quarter of the pixels: plenty for two statistics)."""
    g = np.asarray(grey, dtype=np.float32)
    if g.shape[0] < 3 or g.shape[1] < 3:
        raise ImageError(f"image {g.shape} too small to estimate noise")
    lap, grad = _laplacian_and_gradient_quarter(np.ascontiguousarray(g))
    lap, grad = lap.ravel(), grad.ravel()
    k = max(int(flat_fraction * grad.size) - 1, 0)
    flat = grad <= np.partition(grad, k)[k]
    return float(np.sqrt(np.pi / 2) * lap[flat].mean(dtype=np.float64) / 6.0)


@numba.njit(cache=True, nogil=True)
def _laplacian_and_gradient_quarter(g):
    """|Immerkær Laplacian difference| and |Sobel x| + |Sobel y| at odd rows and columns (interior)."""
    H, W = g.shape
    h, w = (H - 1) // 2, (W - 1) // 2
    lap = np.empty((h, w), np.float32)
    grad = np.empty((h, w), np.float32)
    for i in range(h):
        y = 2 * i + 1
        for j in range(w):
            x = 2 * j + 1
            a0, a1, a2 = g[y - 1, x - 1], g[y - 1, x], g[y - 1, x + 1]
            b0, b1, b2 = g[y, x - 1], g[y, x], g[y, x + 1]
            c0, c1, c2 = g[y + 1, x - 1], g[y + 1, x], g[y + 1, x + 1]
            lap[i, j] = abs((a0 - 2 * a1 + a2) - 2 * (b0 - 2 * b1 + b2) + (c0 - 2 * c1 + c2))
            grad[i, j] = (abs((a2 - a0) + 2 * (b2 - b0) + (c2 - c0))
                          + abs((c0 + 2 * c1 + c2) - (a0 + 2 * a1 + a2)))
    return lap, grad


def window_weights(n: int, channels: int, sigma: float | None) -> np.ndarray:
    """N×N weights summing to 1/channels, so the kernel's weighted sum is a mean over window and colours."""
    r = np.arange(n, dtype=np.float64) - n // 2
    if sigma is None:
        w = np.ones((n, n))
    else:
        g = np.exp(-0.5 * (r / sigma) ** 2)
        w = np.outer(g, g)
    return (w / (w.sum() * channels)).astype(np.float32)


def gradient_energy(sq_grad: np.ndarray, n: int, min_half_window: bool) -> np.ndarray:
    """Mean squared gradient over the n×n window at each pixel — or, with ``min_half_window``, the least
    of the four half-windows (left, right, top, bottom; each including the centre line).

    The half-window minimum is what makes G well-behaved at depth edges: a window whose texture is all
    on one side (a strong foreground edge beside a flat background) is the one that a fly at the wrong
    depth matches well, and it gets a low G instead of the highest.
    """
    if not min_half_window or n < 3:
        return cv2.boxFilter(sq_grad, cv2.CV_32F, (n, n), borderType=cv2.BORDER_REPLICATE)
    h = n // 2
    sq = np.ascontiguousarray(sq_grad, dtype=np.float32)
    padded = cv2.copyMakeBorder(sq, h, h, h, h, cv2.BORDER_REPLICATE)
    return _min_half_window_mean(padded, h, np.empty(sq.shape, np.float32))


@numba.njit(cache=True, nogil=True, fastmath=True)
def _min_half_window_mean(padded, h, out):
    """``out`` (H×W) = per pixel, the least mean of the image over its four (2h+1)×(h+1) half-windows;
    ``padded`` is the image with h replicated pixels on every side.  Horizontal (2h+1)-sums of every
    padded row first, then one pass down the rows with vertical running sums: every inner loop runs
    along a row without a branch, so it vectorises."""
    Hp, Wp = padded.shape
    H, W = Hp - 2 * h, Wp - 2 * h
    rows = np.zeros((Hp, W), np.float32)        # rows[y, x] = sum of padded[y, x .. x+2h]
    for y in range(Hp):
        r, p = rows[y], padded[y]
        for i in range(2 * h + 1):
            for x in range(W):
                r[x] += p[x + i]
    cols = np.zeros(Wp, np.float32)             # cols[x] = sum of padded[y .. y+2h, x] at output row y
    top = np.zeros(W, np.float32)               # sum of rows[y .. y+h]: rows y-h..y of the image
    bottom = np.zeros(W, np.float32)            # sum of rows[y+h .. y+2h]: rows y..y+h
    for j in range(2 * h + 1):
        for x in range(Wp):
            cols[x] += padded[j, x]
    for j in range(h + 1):
        for x in range(W):
            top[x] += rows[j, x]
            bottom[x] += rows[h + j, x]
    side = np.empty(W + h, np.float32)          # side[x] = sum of cols[x .. x+h]: left at x, right at x+h
    scale = np.float32(1.0 / ((h + 1) * (2 * h + 1)))
    for y in range(H):
        if y > 0:
            for x in range(Wp):
                cols[x] += padded[y + 2 * h, x] - padded[y - 1, x]
            for x in range(W):
                top[x] += rows[y + h, x] - rows[y - 1, x]
                bottom[x] += rows[y + 2 * h, x] - rows[y + h - 1, x]
        for x in range(W + h):
            side[x] = cols[x]
        for i in range(1, h + 1):
            for x in range(W + h):
                side[x] += cols[x + i]
        for x in range(W):
            out[y, x] = min(min(side[x], side[x + h]), min(top[x], bottom[x])) * scale
    return out


@numba.njit(cache=True, nogil=True)
def _minus(img, mean, remove, out):
    """``out`` (float32, img's shape) = ``img − mean`` (both uint8, same shape), or just ``img``."""
    a = img.ravel()
    b = mean.ravel()
    o = out.reshape(-1)     # a view (ravel would copy a non-contiguous ``out`` and drop the writes)
    if remove:
        for i in range(a.size):
            o[i] = np.float32(a[i]) - np.float32(b[i])
    else:
        for i in range(a.size):
            o[i] = np.float32(a[i])
    return out


@numba.njit(cache=True, nogil=True)
def _grey(img):
    """Channel mean of an H×W×C uint8 image, as float32 (the sum of a pixel's integers is exact in
    float32, so the order of the channels does not change the result)."""
    H, W, C = img.shape
    flat = img.reshape(H * W * C)
    out = np.empty(H * W, np.float32)
    inv_c = np.float32(1.0 / C)
    if C == 3:      # unrolled: the general loop's inner channel loop does not vectorise
        for i in range(H * W):
            out[i] = (np.float32(flat[3 * i]) + np.float32(flat[3 * i + 1]) + np.float32(flat[3 * i + 2])) * inv_c
        return out.reshape(H, W)
    for i in range(H * W):
        acc = np.float32(0.0)
        for c in range(C):
            acc += np.float32(flat[i * C + c])
        out[i] = acc * inv_c
    return out.reshape(H, W)


@dataclass
class FrameImages:
    """The part of a :class:`PreparedFrame` that depends on the images and the settings in ``key`` alone,
    not on the noise estimate (the evolver's state), so it can be computed ahead in another thread
    (common.lockstep does, while the evolver works on the frame before).  ``sources`` are the images
    it was computed from: ``prepare_frame`` uses it only for those very arrays."""
    left: np.ndarray        # H×W×C float32, local mean removed when asked
    right: np.ndarray
    grey: np.ndarray        # H×W float32 left image (channel mean)
    energy: np.ndarray      # H×W float32 gradient energy of ``grey`` over the window
    key: tuple
    sources: tuple


def _images_key(neighbourhood, mean_removal_px, gradient_window, min_half_window, epipolar_gradient) -> tuple:
    return (int(neighbourhood), int(mean_removal_px or 0), int(gradient_window or neighbourhood),
            bool(min_half_window), bool(epipolar_gradient))


def prepare_images(calib: StereoCalibration, left: np.ndarray, right: np.ndarray, neighbourhood: int,
                   mean_removal_px: int | None = None, gradient_window: int | None = None,
                   min_half_window: bool = True, epipolar_gradient: bool = True) -> FrameImages:
    """The images' share of ``prepare_frame`` (float images, grey, gradient energy); thread-safe."""
    for img, which in ((left, "left"), (right, "right")):
        try:
            calib.check_image(np.asarray(img), which)
        except CalibrationError as e:
            raise ImageError(str(e)) from e
    la, ra = np.asarray(left), np.asarray(right)
    if la.shape != ra.shape:
        raise ImageError(f"left {la.shape} and right {ra.shape} images differ")
    k = (int(mean_removal_px or 1), int(mean_removal_px or 1))
    if la.dtype == np.uint8 and ra.dtype == np.uint8 and la.ndim in (2, 3):
        la3 = la.reshape(la.shape[0], la.shape[1], -1)
        ra3 = ra.reshape(ra.shape[0], ra.shape[1], -1)
        if la3.shape[2] not in (1, 3):
            raise ImageError(f"left image must be H×W mono or H×W×3 RGB, got shape {la.shape}")
        bl = cv2.blur(la3, k, borderType=cv2.BORDER_REPLICATE).reshape(la3.shape) if mean_removal_px else la3
        br = cv2.blur(ra3, k, borderType=cv2.BORDER_REPLICATE).reshape(ra3.shape) if mean_removal_px else ra3
        # outputs allocated by numpy, which asks the kernel for huge pages for large arrays: a new
        # frame's images then cost a few page faults instead of thousands
        L = _minus(np.ascontiguousarray(la3), np.ascontiguousarray(bl), bool(mean_removal_px),
                   np.empty(la3.shape, np.float32))
        R = _minus(np.ascontiguousarray(ra3), np.ascontiguousarray(br), bool(mean_removal_px),
                   np.empty(ra3.shape, np.float32))
        grey = _grey(np.ascontiguousarray(la3))
    else:
        L, R = _as_float_image(left, "left"), _as_float_image(right, "right")
        C = L.shape[2]
        grey = L[:, :, 0].copy() if C == 1 else cv2.transform(L, np.full((1, C), 1.0 / C, np.float32))
        if mean_removal_px:
            L = L - cv2.blur(L, k, borderType=cv2.BORDER_REPLICATE).reshape(L.shape)
            R = R - cv2.blur(R, k, borderType=cv2.BORDER_REPLICATE).reshape(R.shape)
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
    gy = None if epipolar_gradient else cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
    # Only the gradient along the epipolar lines (x) constrains disparity: a horizontal edge has strong
    # vertical gradient but matches at every disparity along it (aperture problem).
    sq = cv2.multiply(gx, gx) if epipolar_gradient else cv2.add(cv2.multiply(gx, gx), cv2.multiply(gy, gy))
    energy = gradient_energy(sq, int(gradient_window or neighbourhood), min_half_window)
    return FrameImages(np.ascontiguousarray(L), np.ascontiguousarray(R), grey, energy,
                       _images_key(neighbourhood, mean_removal_px, gradient_window, min_half_window,
                                   epipolar_gradient), (left, right))


def prepare_frame(calib: StereoCalibration, left: np.ndarray, right: np.ndarray, neighbourhood: int,
                  noise_sigma: float | None, ssd_floor_scale: float, gradient_saturation: float,
                  window_sigma: float | None, mean_removal_px: int | None = None,
                  gradient_window: int | None = None, min_half_window: bool = True,
                  epipolar_gradient: bool = True, images: FrameImages | None = None) -> PreparedFrame:
    """Convert a stereo pair once per frame: float images, noise floor and the gradient normaliser map.

    ``mean_removal_px`` (odd) subtracts each image's local mean over that box before matching, which makes
    the SSD insensitive to exposure/gain differences between the two cameras (a cheap zero-mean SSD).
    ``images``: ``prepare_images`` of these very arrays with these settings, computed ahead; anything
    else is computed here.
    """
    key = _images_key(neighbourhood, mean_removal_px, gradient_window, min_half_window, epipolar_gradient)
    if (images is None or images.key != key or images.sources[0] is not left
            or images.sources[1] is not right):
        images = prepare_images(calib, left, right, neighbourhood, mean_removal_px, gradient_window,
                                min_half_window, epipolar_gradient)
    C = images.left.shape[2]
    sigma = float(noise_sigma) if noise_sigma is not None else estimate_noise_sigma(images.grey)
    sigma = max(sigma, 0.5)  # quantisation alone is ~0.3 grey levels; never trust a zero estimate
    floor = max(ssd_floor_scale, 1e-6) * 2.0 * sigma ** 2
    energy = images.energy
    sat2 = np.float32((gradient_saturation * sigma) ** 2)
    G = cv2.divide(energy, energy + sat2) if sat2 > 0 else np.ones_like(energy)
    return PreparedFrame(images.left, images.right, np.ascontiguousarray(G), sigma,
                         1.0 / floor, window_weights(neighbourhood, C, window_sigma))


_BLOCK = 64  # flies per parallel work item (one scratch buffer each)


def _fitness_kernel_py(L, R, G, pos, fx, fy, cxl, cxr, cy, baseline, half, C, subpixel, vertical, inv_floor,
                       wexp, out):
    """L, R: H×(W·C) float32 (rows of interleaved colours); wexp: nw×(nw·C) per-sample weights."""
    H = L.shape[0]
    W = L.shape[1] // C
    n = pos.shape[0]
    nw = 2 * half + 1
    rowlen = nw * C
    nblocks = (n + _BLOCK - 1) // _BLOCK
    for b in numba.prange(nblocks):
        # One window row after vertical interpolation: (nw + 1) columns × C, left and right.
        lrow = np.empty(rowlen + C, dtype=np.float32)
        rrow = np.empty(rowlen + C, dtype=np.float32)
        for k in range(b * _BLOCK, min(n, (b + 1) * _BLOCK)):
            z = np.float64(pos[k, 2])
            if not z > 0.0:
                out[k] = -np.inf
                continue
            iz = 1.0 / z
            ul = fx * pos[k, 0] * iz + cxl
            ur = fx * (pos[k, 0] - baseline) * iz + cxr
            v = fy * pos[k, 1] * iz + cy
            if not (abs(ul) < 1e9 and abs(ur) < 1e9 and abs(v) < 1e9):
                out[k] = -np.inf
                continue
            acc = np.float32(0.0)
            if subpixel:
                xl0 = int(np.floor(ul))
                xr0 = int(np.floor(ur))
                y0 = int(np.floor(v))
                if (xl0 < half or xl0 > W - 2 - half or xr0 < half or xr0 > W - 2 - half
                        or y0 < half or y0 > H - 2 - half):
                    out[k] = -np.inf
                    continue
                ax = np.float32(ul - xl0)
                bx = np.float32(ur - xr0)
                ay = np.float32(v - y0)
                ol = (xl0 - half) * C
                orr = (xr0 - half) * C
                if vertical:
                    uol = np.uint64(ol)
                    uor = np.uint64(orr)
                    uc = np.uint64(C)
                    for j in range(nw):
                        L0 = L[np.uint64(y0 + j - half)]
                        L1 = L[np.uint64(y0 + j - half + 1)]
                        R0 = R[np.uint64(y0 + j - half)]
                        R1 = R[np.uint64(y0 + j - half + 1)]
                        wrow = wexp[j]
                        for p in range(rowlen + C):
                            up = np.uint64(p)
                            a0 = L0[uol + up]
                            lrow[up] = a0 + ay * (L1[uol + up] - a0)
                            b0 = R0[uor + up]
                            rrow[up] = b0 + ay * (R1[uor + up] - b0)
                        for p in range(rowlen):
                            up = np.uint64(p)
                            d = ((lrow[up] + ax * (lrow[up + uc] - lrow[up]))
                                 - (rrow[up] + bx * (rrow[up + uc] - rrow[up])))
                            acc += wrow[up] * d * d
                else:
                    # Rectified rig: sample the left window at the nearest pixel and the right one at
                    # the same place minus the fly's exact (sub-pixel) disparity, interpolating along
                    # the epipolar line.  One interpolation per sample instead of four.
                    xn = int(np.floor(ul + 0.5))
                    xs = ur - (ul - xn)
                    xr0 = int(np.floor(xs))
                    if xn > W - 1 - half or xr0 < half or xr0 > W - 2 - half:
                        out[k] = -np.inf
                        continue
                    bx = np.float32(xs - xr0)
                    ol = (xn - half) * C
                    orr = (xr0 - half) * C
                    yr = int(np.floor(v + 0.5)) - half
                    if yr + nw > H:
                        out[k] = -np.inf
                        continue
                    # Unsigned indices: numba then skips its negative-index wraparound test, and the
                    # inner loop vectorises.
                    uol = np.uint64(ol)
                    uor = np.uint64(orr)
                    uc = np.uint64(C)
                    for j in range(nw):
                        Lrow = L[np.uint64(yr + j)]
                        Rrow = R[np.uint64(yr + j)]
                        wrow = wexp[j]
                        for p in range(rowlen):
                            up = np.uint64(p)
                            b0 = Rrow[uor + up]
                            d = Lrow[uol + up] - (b0 + bx * (Rrow[uor + up + uc] - b0))
                            acc += wrow[up] * d * d
                g = G[int(np.floor(v + 0.5)), int(np.floor(ul + 0.5))]
            else:
                xl0 = int(np.floor(ul + 0.5))
                xr0 = int(np.floor(ur + 0.5))
                y0 = int(np.floor(v + 0.5))
                if (xl0 < half or xl0 > W - 1 - half or xr0 < half or xr0 > W - 1 - half
                        or y0 < half or y0 > H - 1 - half):
                    out[k] = -np.inf
                    continue
                ol = (xl0 - half) * C
                orr = (xr0 - half) * C
                uol = np.uint64(ol)
                uor = np.uint64(orr)
                for j in range(nw):
                    Lrow = L[np.uint64(y0 + j - half)]
                    Rrow = R[np.uint64(y0 + j - half)]
                    wrow = wexp[j]
                    for p in range(rowlen):
                        up = np.uint64(p)
                        d = Lrow[uol + up] - Rrow[uor + up]
                        acc += wrow[up] * d * d
                g = G[y0, xl0]
            out[k] = g / (np.float32(1.0) + acc * inv_floor)


# The same loop compiled twice: across all cores, and on the calling thread only.  On a small machine
# shared with other busy processes a parallel region can stall for a scheduler time slice (milliseconds)
# waiting for a descheduled worker, so modest batches are better evaluated serially.
_fitness_kernel_parallel = numba.njit(parallel=True, cache=True, nogil=True, fastmath=True)(_fitness_kernel_py)
_fitness_kernel_serial = numba.njit(parallel=False, cache=True, nogil=True, fastmath=True)(cache_twin(_fitness_kernel_py, "serial"))


def image_fitness(frame: PreparedFrame, calib: StereoCalibration, positions: np.ndarray,
                  subpixel: bool = True, vertical: bool = False, out: np.ndarray | None = None,
                  parallel: bool = True) -> np.ndarray:
    """(N,) float32 image fitness of (N, 3) left-optical positions on a prepared frame.

    ``subpixel``: right window sampled at the exact disparity (linear along the epipolar line), left at
    the nearest pixel; ``vertical`` additionally interpolates both windows bilinearly; neither: nearest
    pixels.
    ``parallel``: use all cores (numba prange) or only the calling thread.
    """
    pos = np.ascontiguousarray(positions, dtype=np.float32)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions must be (N, 3), got {np.shape(positions)}")
    if out is None:
        out = np.empty(len(pos), dtype=np.float32)
    H, W, C = frame.left.shape
    half = frame.weights.shape[0] // 2
    wexp = np.ascontiguousarray(np.repeat(frame.weights, C, axis=1))
    kernel = _fitness_kernel_parallel if parallel else _fitness_kernel_serial
    kernel(frame.left.reshape(H, W * C), frame.right.reshape(H, W * C), frame.gradient_norm,
                    pos, calib.fx, calib.fy, calib.cx_left, calib.cx_right, calib.cy,
                    calib.baseline, half, C, bool(subpixel), bool(vertical), np.float32(frame.inv_floor),
                    wexp, out)
    return out
