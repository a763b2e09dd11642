"""Procedural, seeded surface textures for the simulated world, with mip pyramids.

Every texture is an RGB float32 albedo image in [0, 1] built with numpy from a seed, so a scenario renders
identically on every machine.  Kinds:

* ``brick``    running-bond bricks with mortar joints and per-brick colour variation (tiles)
* ``wood``     planks with grain along the width (tiles) — floors, doors
* ``noise``    multi-scale 1/f noise around a base colour (concrete, carpet, grass, asphalt) (tiles)
* ``paint``    painted plaster: a flat colour with very low contrast (±1–2 grey levels) (tiles)
* ``tiles``    square floor/ceiling tiles with grout (tiles)
* ``facade``   building front with a grid of windows (tiles)
* ``checker``  a two-colour checkerboard (tiles) — calibration and tests
* ``poster``   a framed sheet of random shapes and rows of letter-like blobs (stretched over its quad)
* ``door``     a panelled wooden door with a handle (stretched over its quad)
* ``light``    a bright ceiling light panel (stretched; rendered unshaded)

Tiling kinds repeat every ``size_m`` metres along the surface; stretched kinds cover their quad exactly.
Mip levels (each half the size of the previous, box-filtered) let the renderer pick a level by pixel
footprint so distant or oblique surfaces do not alias (shimmer) as the camera moves.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

TILING_KINDS = ("brick", "wood", "noise", "paint", "tiles", "facade", "checker")
STRETCHED_KINDS = ("poster", "door", "light")
KINDS = TILING_KINDS + STRETCHED_KINDS

_DEFAULT_COLOR = {
    "brick": (150, 72, 52), "wood": (140, 98, 60), "noise": (128, 128, 128), "paint": (205, 200, 188),
    "tiles": (180, 178, 170), "facade": (170, 160, 145), "checker": (220, 220, 220),
    "poster": (235, 232, 220), "door": (120, 80, 50), "light": (255, 252, 240),
}
_DEFAULT_SIZE_M = {
    "brick": (1.0, 0.5), "wood": (1.2, 1.2), "noise": (2.0, 2.0), "paint": (4.0, 4.0),
    "tiles": (1.2, 1.2), "facade": (6.0, 6.0), "checker": (0.4, 0.4),
}


class TextureError(ValueError):
    """A texture specification that cannot be built."""


@dataclass(frozen=True)
class TextureSpec:
    """What a surface looks like. ``size_m`` is the repeat period (tiling kinds only)."""
    kind: str
    seed: int = 0
    color: tuple[int, int, int] | None = None
    size_m: tuple[float, float] | None = None
    contrast: float = 1.0
    resolution: int = 256

    def __post_init__(self):
        if self.kind not in KINDS:
            raise TextureError(f"unknown texture kind {self.kind!r}; expected one of {', '.join(KINDS)}")
        if self.color is not None and (len(self.color) != 3 or not all(0 <= c <= 255 for c in self.color)):
            raise TextureError(f"texture colour must be 3 values in 0..255, got {self.color}")
        if self.size_m is not None and (len(self.size_m) != 2 or min(self.size_m) <= 0):
            raise TextureError(f"texture size_m must be two positive lengths, got {self.size_m}")
        if not (self.resolution >= 16 and (self.resolution & (self.resolution - 1)) == 0):
            raise TextureError(f"texture resolution must be a power of two ≥ 16, got {self.resolution}")
        if not 0 <= self.contrast <= 10:
            raise TextureError(f"texture contrast must be in 0..10, got {self.contrast}")

    @property
    def tiles(self) -> bool:
        return self.kind in TILING_KINDS

    @property
    def base_color(self) -> np.ndarray:
        return np.asarray(self.color if self.color is not None else _DEFAULT_COLOR[self.kind], np.float32) / 255

    @property
    def period_m(self) -> tuple[float, float]:
        if self.size_m is not None:
            return tuple(float(s) for s in self.size_m)
        return _DEFAULT_SIZE_M.get(self.kind, (1.0, 1.0))


# -------------------------------------------------------------------------------------- building blocks
def periodic_noise(rng: np.random.Generator, h: int, w: int, beta: float = 2.0, min_freq: float = 1.0) -> np.ndarray:
    """Zero-mean unit-variance noise with a 1/f^beta power spectrum that tiles seamlessly (FFT-built)."""
    white = rng.standard_normal((h, w))
    fy = np.fft.fftfreq(h)[:, None] * h
    fx = np.fft.rfftfreq(w)[None, :] * w
    f = np.sqrt(fx ** 2 + fy ** 2)
    amp = np.where(f >= min_freq, 1.0 / np.maximum(f, 1e-9) ** (beta / 2), 0.0)
    out = np.fft.irfft2(np.fft.rfft2(white) * amp, s=(h, w))
    out -= out.mean()
    s = out.std()
    return (out / s if s > 0 else out).astype(np.float32)


def _rgb(base: np.ndarray, shade: np.ndarray) -> np.ndarray:
    """Colour image base × shade (shade H×W, around 1)."""
    return np.clip(shade[..., None] * base[None, None, :], 0, 1).astype(np.float32)


def _brick(spec: TextureSpec, rng) -> np.ndarray:
    n = spec.resolution
    h, w = n // 2, n  # period is 1.0 × 0.5 m by default: keep texels square
    rows, cols = 8, 4  # 8 courses of 4 bricks per period: ~25 × 6 cm bricks at the default size
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    course = (yy * rows / h).astype(int)
    xs = xx * cols / w + 0.5 * (course % 2)
    brick_id = course * (cols + 1) + np.floor(xs).astype(int) % cols
    mortar = (np.abs(yy * rows / h - np.round(yy * rows / h)) * h / rows < 1.2) | \
             (np.abs(xs - np.round(xs)) * w / cols < 1.2)
    per_brick = 1 + 0.18 * spec.contrast * rng.standard_normal(rows * (cols + 1))
    hue = 1 + 0.06 * spec.contrast * rng.standard_normal((rows * (cols + 1), 3))
    grain = 1 + 0.08 * spec.contrast * periodic_noise(rng, h, w, beta=1.0)
    img = spec.base_color[None, None, :] * (per_brick[brick_id] * grain)[..., None] * hue[brick_id]
    img[mortar] = np.array([0.72, 0.70, 0.66]) * (1 + 0.05 * grain[mortar, None])
    return np.clip(img, 0, 1).astype(np.float32)


def _wood(spec: TextureSpec, rng) -> np.ndarray:
    n = spec.resolution
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32)
    planks = 6
    pid = (yy * planks / n).astype(int)
    warp = 6 * periodic_noise(rng, n, n, beta=3.0)
    phase = rng.uniform(0, 2 * np.pi, planks)
    rings = np.sin(2 * np.pi * (yy * planks / n * 5 + warp * 0.15) + phase[pid] + 0.02 * xx * 2 * np.pi / n * 3)
    fine = periodic_noise(rng, n, n, beta=1.2)
    shade = 1 + spec.contrast * (0.12 * rings + 0.06 * fine + 0.12 * rng.standard_normal(planks)[pid])
    seam = np.abs(yy * planks / n - np.round(yy * planks / n)) * n / planks < 0.8
    shade[seam] *= 0.55
    return _rgb(spec.base_color, shade)


def _noise(spec: TextureSpec, rng) -> np.ndarray:
    n = spec.resolution
    shade = 1 + spec.contrast * (0.14 * periodic_noise(rng, n, n, beta=2.0) + 0.10 * periodic_noise(rng, n, n, beta=0.6))
    tint = 1 + 0.015 * spec.contrast * np.stack([periodic_noise(rng, n, n, beta=2.5) for _ in range(3)], -1)
    return np.clip(_rgb(spec.base_color, shade) * tint, 0, 1).astype(np.float32)


def _paint(spec: TextureSpec, rng) -> np.ndarray:
    # Roller-painted plaster: ±0.5 % low-frequency mottling and a faint fine stipple — about one grey
    # level of contrast, which is what makes such walls hard for stereo matching.
    n = spec.resolution
    shade = 1 + spec.contrast * (0.006 * periodic_noise(rng, n, n, beta=2.5) + 0.004 * periodic_noise(rng, n, n, beta=0.3))
    return _rgb(spec.base_color, shade)


def _tiles(spec: TextureSpec, rng) -> np.ndarray:
    n = spec.resolution
    k = 4  # 4 × 4 tiles per period: 30 cm tiles at the default size
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32)
    tid = (yy * k / n).astype(int) * k + (xx * k / n).astype(int)
    grout = (np.abs(yy * k / n - np.round(yy * k / n)) * n / k < 1.0) | \
            (np.abs(xx * k / n - np.round(xx * k / n)) * n / k < 1.0)
    shade = 1 + spec.contrast * (0.07 * rng.standard_normal(k * k)[tid] + 0.05 * periodic_noise(rng, n, n, beta=1.0))
    shade[grout] = 0.6
    return _rgb(spec.base_color, shade)


def _facade(spec: TextureSpec, rng) -> np.ndarray:
    n = spec.resolution
    k = 4  # 4 × 4 windows per period
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32)
    fy, fx = (yy * k / n) % 1, (xx * k / n) % 1
    win = (fx > 0.2) & (fx < 0.8) & (fy > 0.25) & (fy < 0.8)
    wid = (yy * k / n).astype(int) * k + (xx * k / n).astype(int)
    shade = 1 + spec.contrast * 0.08 * periodic_noise(rng, n, n, beta=1.5)
    img = _rgb(spec.base_color, shade)
    glass = np.array([0.25, 0.3, 0.38], np.float32) * (1 + 0.5 * rng.random(k * k)[wid][win])[:, None]
    img[win] = np.clip(glass, 0, 1)
    return img


def _checker(spec: TextureSpec, rng) -> np.ndarray:
    n = spec.resolution
    yy, xx = np.mgrid[0:n, 0:n]
    c = ((yy * 2 // n + xx * 2 // n) % 2).astype(np.float32)
    return _rgb(spec.base_color, 0.15 + 0.85 * c)


def _poster(spec: TextureSpec, rng) -> np.ndarray:
    n = spec.resolution
    img = np.empty((n, n, 3), np.float32)
    img[:] = spec.base_color
    palette = rng.uniform(0.05, 0.95, (8, 3)).astype(np.float32)
    img_u8 = (img * 255).astype(np.uint8)
    for _ in range(rng.integers(3, 7)):  # large coloured shapes in the upper part
        col = tuple(int(c) for c in (palette[rng.integers(8)] * 255))
        kind = rng.integers(3)
        cx, cy = int(rng.uniform(0.15, 0.85) * n), int(rng.uniform(0.1, 0.55) * n)
        r = int(rng.uniform(0.06, 0.2) * n)
        if kind == 0:
            cv2.circle(img_u8, (cx, cy), r, col, -1, cv2.LINE_AA)
        elif kind == 1:
            cv2.rectangle(img_u8, (cx - r, cy - r // 2), (cx + r, cy + r // 2), col, -1, cv2.LINE_AA)
        else:
            pts = np.array([[cx, cy - r], [cx - r, cy + r], [cx + r, cy + r]], np.int32)
            cv2.fillPoly(img_u8, [pts], col, cv2.LINE_AA)
    # "Text": rows of letter-like blobs (short strokes and dots) in the lower part.
    ink = tuple(int(c) for c in (rng.uniform(0, 0.25, 3) * 255))
    y = int(0.65 * n)
    while y < 0.92 * n:
        x = int(0.08 * n)
        size = max(2, int(rng.uniform(0.025, 0.04) * n))
        while x < 0.9 * n:
            word = rng.integers(2, 7)
            for _ in range(word):
                g = rng.integers(4)
                if g == 0:
                    cv2.line(img_u8, (x, y), (x, y - size), ink, max(1, size // 4), cv2.LINE_AA)
                elif g == 1:
                    cv2.circle(img_u8, (x + size // 3, y - size // 3), max(1, size // 3), ink, max(1, size // 5), cv2.LINE_AA)
                elif g == 2:
                    cv2.line(img_u8, (x, y), (x + size // 2, y - size), ink, max(1, size // 4), cv2.LINE_AA)
                else:
                    cv2.rectangle(img_u8, (x, y - size // 2), (x + size // 2, y), ink, max(1, size // 5))
                x += int(size * 0.8)
            x += size
        y += int(size * 2.0)
    cv2.rectangle(img_u8, (0, 0), (n - 1, n - 1), (30, 30, 30), max(2, n // 64))  # frame
    return img_u8.astype(np.float32) / 255


def _door(spec: TextureSpec, rng) -> np.ndarray:
    n = spec.resolution
    wood = _wood(TextureSpec("wood", seed=spec.seed, color=spec.color or _DEFAULT_COLOR["door"],
                             contrast=0.6 * spec.contrast, resolution=n), rng)
    img = np.ascontiguousarray(np.rot90(wood))  # grain runs vertically on a door
    u8 = (img * 255).astype(np.uint8)
    dark = (0.7 * u8.reshape(-1, 3).mean(0)).astype(int).tolist()
    for (x0, y0, x1, y1) in ((0.15, 0.08, 0.85, 0.45), (0.15, 0.55, 0.85, 0.92)):  # two panels
        cv2.rectangle(u8, (int(x0 * n), int(y0 * n)), (int(x1 * n), int(y1 * n)), dark, max(1, n // 64))
    cv2.rectangle(u8, (0, 0), (n - 1, n - 1), (60, 55, 50), max(2, n // 40))  # frame
    cv2.circle(u8, (int(0.85 * n), int(0.5 * n)), max(2, n // 40), (200, 200, 190), -1, cv2.LINE_AA)  # handle
    return u8.astype(np.float32) / 255


def _light(spec: TextureSpec, rng) -> np.ndarray:
    n = spec.resolution
    img = np.empty((n, n, 3), np.float32)
    img[:] = spec.base_color
    yy, xx = np.mgrid[0:n, 0:n]
    border = (np.minimum(np.minimum(xx, n - 1 - xx), np.minimum(yy, n - 1 - yy)) < n // 16)
    img[border] *= 0.55
    return img


_BUILDERS = {"brick": _brick, "wood": _wood, "noise": _noise, "paint": _paint, "tiles": _tiles,
             "facade": _facade, "checker": _checker, "poster": _poster, "door": _door, "light": _light}


def build_texture(spec: TextureSpec) -> np.ndarray:
    """The level-0 albedo image (H×W×3 float32 in [0, 1]) of a texture spec; deterministic in its seed."""
    kind_salt = KINDS.index(spec.kind)
    rng = np.random.default_rng([spec.seed, kind_salt, 0x5EED])
    return np.ascontiguousarray(_BUILDERS[spec.kind](spec, rng), dtype=np.float32)


def mip_pyramid(img: np.ndarray, min_size: int = 1) -> list[np.ndarray]:
    """Mip levels of an image: level k is the 2^k box-filtered reduction (dimensions stay ≥ min_size)."""
    levels = [img]
    while min(levels[-1].shape[:2]) >= 2 * min_size and levels[-1].shape[0] % 2 == 0 and levels[-1].shape[1] % 2 == 0:
        a = levels[-1]
        levels.append(0.25 * (a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2]))
    return levels


@dataclass
class TextureAtlas:
    """All textures of a world, every mip level flattened into one array the numba renderer can index.

    ``texels`` is (total, 3) float32; texture ``i`` level ``k`` starts at ``offset[i, k]`` and is
    ``height[i, k]`` × ``width[i, k]`` row-major.  ``period_m[i]`` is the repeat size in metres of tiling
    textures (stretched ones get −1: their quad's size is used), ``emissive[i]`` marks unshaded lights.
    """
    texels: np.ndarray
    offset: np.ndarray
    width: np.ndarray
    height: np.ndarray
    n_levels: np.ndarray
    period_m: np.ndarray
    emissive: np.ndarray
    specs: list[TextureSpec] = field(default_factory=list)

    @classmethod
    def build(cls, specs: list[TextureSpec]) -> "TextureAtlas":
        pyramids = [mip_pyramid(build_texture(s)) for s in specs]
        max_levels = max((len(p) for p in pyramids), default=1)
        n = len(specs)
        offset = np.zeros((max(n, 1), max_levels), np.int64)
        width = np.ones((max(n, 1), max_levels), np.int64)
        height = np.ones((max(n, 1), max_levels), np.int64)
        n_levels = np.ones(max(n, 1), np.int64)
        chunks, cursor = [], 0
        for i, pyr in enumerate(pyramids):
            n_levels[i] = len(pyr)
            for k in range(max_levels):
                lvl = pyr[min(k, len(pyr) - 1)]
                if k < len(pyr):
                    chunks.append(lvl.reshape(-1, 3))
                    offset[i, k] = cursor
                    cursor += lvl.shape[0] * lvl.shape[1]
                else:
                    offset[i, k] = offset[i, len(pyr) - 1]
                height[i, k], width[i, k] = lvl.shape[:2]
        texels = np.concatenate(chunks) if chunks else np.zeros((1, 3), np.float32)
        period = np.array([s.period_m if s.tiles else (-1.0, -1.0) for s in specs] or [(1.0, 1.0)], np.float64)
        emissive = np.array([s.kind == "light" for s in specs] or [False], np.bool_)
        return cls(np.ascontiguousarray(texels, np.float32), offset, width, height, n_levels, period, emissive,
                   list(specs))
