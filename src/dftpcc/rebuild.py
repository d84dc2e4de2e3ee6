"""Rebuild stage: a decoded DEM becomes a point cloud again.

One point per occupied cell, at the cell centre, with the rebuilt height,
in the original coordinate frame (float64, so UTM-size coordinates stay exact).
"""

from __future__ import annotations

import numpy as np

from .grid import DEM

__all__ = ["dem_to_points"]


def dem_to_points(dem: DEM) -> np.ndarray:
    """Points of the occupied cells of ``dem``.

    Returns
    -------
    ndarray, shape (cells, 3), float64
        x, y of the cell centres and z = ``grid.z0`` + height, metres;
        cells in row-major order.
    """
    rows, cols = np.nonzero(dem.mask)
    x, y = dem.grid.centres(rows, cols)
    out = np.empty((rows.size, 3))
    out[:, 0] = x
    out[:, 1] = y
    out[:, 2] = dem.heights[rows, cols] + dem.grid.z0
    return out
