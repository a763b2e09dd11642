"""A folder of image files read like a video: what a stereo capture script or a dataset leaves behind.

A sequence is named by a glob pattern (``cap/left_*.png``) or a folder (every image file in it), and
read in natural order, numbers by value (``img2.png`` before ``img10.png``; zero-padded frame numbers
and nanosecond stamps sort as they should). :class:`ImageSequence` offers the part of
``cv2.VideoCapture`` that flyslam's camera driver uses, so the driver treats it as one more video file.
A sequence has no frame rate of its own (``get(CAP_PROP_FPS)`` is 0): whoever plays it says the rate.
"""
from __future__ import annotations

import glob
import re
from pathlib import Path

import cv2
import numpy as np

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")
_GLOB_CHARS = re.compile(r"[*?\[]")


class ImageSequenceError(ValueError):
    """An image of the sequence that cannot be read."""


def is_image_sequence(spec: str) -> bool:
    """Whether ``spec`` names an image sequence (a glob pattern or a folder) rather than a file or device."""
    return bool(_GLOB_CHARS.search(spec)) or Path(spec).is_dir()


def _natural_key(path: str) -> list:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path)]


def sequence_files(spec: str) -> list[str]:
    """The image files ``spec`` names, in natural order (empty when there are none)."""
    names = glob.glob(str(Path(spec) / "*")) if Path(spec).is_dir() else glob.glob(spec)
    return sorted((n for n in names if Path(n).suffix.lower() in IMAGE_SUFFIXES and Path(n).is_file()),
                  key=_natural_key)


class ImageSequence:
    """Images of a sequence one at a time, as 8-bit BGR (colour files) or grey (single-channel files)."""

    def __init__(self, spec: str):
        self.spec = spec
        self.files = sequence_files(spec)
        self._next = 0           # index of the image the next grab() moves to
        self._current = -1

    def isOpened(self) -> bool:  # noqa: N802 - cv2.VideoCapture's name
        return bool(self.files)

    def grab(self) -> bool:
        if self._next >= len(self.files):
            return False
        self._current, self._next = self._next, self._next + 1
        return True

    def retrieve(self) -> tuple[bool, np.ndarray | None]:
        if self._current < 0:
            return False, None
        path = self.files[self._current]
        img = cv2.imread(path, cv2.IMREAD_ANYCOLOR)      # 8-bit whatever the file's depth
        if img is None:
            raise ImageSequenceError(f"image {path} cannot be read (corrupt, or not an image)")
        if img.ndim == 3 and img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        return True, img

    def set(self, prop: int, value: float) -> bool:
        if prop != cv2.CAP_PROP_POS_FRAMES:
            return False
        self._next, self._current = int(value), -1
        return True

    def get(self, prop: int) -> float:
        return 0.0                 # CAP_PROP_FPS, the only one asked: no rate of its own

    def release(self) -> None:
        self.files = []
