"""3-D cell list of a fly population, for the exact short-range sums of field.py and local.py.

The flies are sorted by cell (x-major, then y, then z) and stored as float32 structure-of-arrays
relative to the list's corner; see `_kernels.build_cells` and `_kernels.near_accumulate`.  Cells are
wide in x-y (a query visits few columns, each one contiguous run) and fine in z (the run hugs the
sphere's chord).  Measured on the deep street (5,000 flies, r_c = 1.8 m): x-y columns of 2 r_c and
z cells of r_c / 4 were the fastest of the shapes tried.
"""
from __future__ import annotations

import numpy as np

from . import _kernels

MAX_CELLS = 2_000_000  # start offsets: 8 MB of int32 at most; beyond that the cells grow


class CellList:
    """B and its weights sorted into cells of radius / xy_per_radius (x, y) by radius / z_per_radius (z)."""

    def __init__(self, B: np.ndarray, wb: np.ndarray, radius: float, xy_per_radius: float = 0.5,
                 z_per_radius: float = 4.0):
        self.lo = B.min(0)
        span = B.max(0) - self.lo
        cell = float(radius) / np.array([xy_per_radius, xy_per_radius, z_per_radius], dtype=float)
        while np.prod(np.floor(span / cell) + 1) > MAX_CELLS:
            cell *= 1.25
        self.cell = cell
        self.dims = (np.floor(span / cell) + 1).astype(np.int64)
        self.B_sorted, self.wb_sorted, self.start = _kernels.build_cells(B, wb, self.lo, cell, self.dims)

    def args(self):
        """(Bs, wbs, start, lo, cell, dims): the cell-list arguments of the numba kernels."""
        return self.B_sorted, self.wb_sorted, self.start, self.lo, self.cell, self.dims
