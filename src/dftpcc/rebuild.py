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
    grid, mask = dem.grid, dem.mask
    if grid.angle == 0.0:
        # Axis-aligned: one x per column and one y per row, picked by the mask
        # itself (rows come in order, so y is each row's y repeated): no flat
        # indices to divide, no gathers.
        xs, _ = grid.centres(np.zeros(grid.cols), np.arange(grid.cols))
        _, ys = grid.centres(np.arange(grid.rows), np.zeros(grid.rows))
        x = np.broadcast_to(xs, mask.shape)[mask]
        out = np.empty((x.size, 3))
        out[:, 0] = x
        out[:, 1] = np.repeat(ys, np.count_nonzero(mask, axis=1))
        z = dem.heights[mask]
    else:
        flat = np.flatnonzero(mask)
        out = np.empty((flat.size, 3))
        rows, cols = np.divmod(flat, grid.cols)
        out[:, 0], out[:, 1] = grid.centres(rows, cols)
        z = dem.heights.ravel().take(flat)
    z += grid.z0
    out[:, 2] = z
    return out
