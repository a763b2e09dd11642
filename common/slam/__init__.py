"""Fly-based SLAM: the localiser (registration of each population against a map of keyframe
populations) and what it is built from.

The names below are loaded on first use (PEP 562), so that ``common.slam.config`` imports without the
numba, SciPy and GTSAM code of the localiser (a restarted localiser service publishes before that
code has loaded)."""
from __future__ import annotations

import importlib

_EXPORTS = {"Estimate": "localiser", "FlyLocaliser": "localiser", "Keyframe": "localiser",
            "LocaliserError": "localiser", "voxel_thin": "localiser", "LocaliserConfig": "config"}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'common.slam' has no attribute {name!r}")
    return getattr(importlib.import_module(f"common.slam.{_EXPORTS[name]}"), name)
