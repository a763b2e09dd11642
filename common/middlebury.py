"""Loading the Middlebury 2014 "Motorcycle" reference pair shipped in ``../shared/data``.

Used by accuracy tests and benchmarks of the fly evolver: images, ground-truth disparity and the
calibration given in that folder's README.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from common.camera import StereoCalibration

# Calibration from shared/data/middlebury-motorcycle/README.md (quarter-size images).
MOTORCYCLE = dict(f=994.978, cx_left=311.193, cy=254.877, doffs=31.086, baseline_m=0.193001)


@dataclass
class ReferencePair:
    left: np.ndarray        # H×W×3 uint8, RGB
    right: np.ndarray       # H×W×3 uint8, RGB
    disparity: np.ndarray   # H×W float32 left-view disparity, +inf where unknown
    calibration: StereoCalibration


def default_motorcycle_dir() -> Path:
    return Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "middlebury-motorcycle"


def load_motorcycle(folder: str | Path | None = None) -> ReferencePair:
    folder = Path(folder) if folder else default_motorcycle_dir()
    left_path, right_path = folder / "motorcycle_left.png", folder / "motorcycle_right.png"
    disp_path = folder / "motorcycle_disp.npz"
    for p in (left_path, right_path, disp_path):
        if not p.exists():
            raise FileNotFoundError(f"Middlebury motorcycle pair: missing {p}")
    left = cv2.cvtColor(cv2.imread(str(left_path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    right = cv2.cvtColor(cv2.imread(str(right_path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    disparity = np.load(disp_path)["arr_0"].astype(np.float32)
    h, w = left.shape[:2]
    calib = StereoCalibration.from_middlebury(width=w, height=h, **MOTORCYCLE)
    return ReferencePair(left, right, disparity, calib)
