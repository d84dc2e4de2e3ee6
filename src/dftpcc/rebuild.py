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
    flat = np.flatnonzero(dem.mask)
    rows, cols = np.divmod(flat, dem.grid.cols)
    out = np.empty((flat.size, 3))
    if dem.grid.angle == 0.0:
        # Axis-aligned: centres are one x per column and one y per row, gathered.
        xs, _ = dem.grid.centres(np.zeros(dem.grid.cols), np.arange(dem.grid.cols))
        _, ys = dem.grid.centres(np.arange(dem.grid.rows), np.zeros(dem.grid.rows))
        np.take(xs, cols, out=out[:, 0])
        np.take(ys, rows, out=out[:, 1])
    else:
        out[:, 0], out[:, 1] = dem.grid.centres(rows, cols)
    np.take(dem.heights.ravel(), flat, out=out[:, 2])
    out[:, 2] += dem.grid.z0
    return out
