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
    grid = dem.grid
    out = np.empty((flat.size, 3))
    # Each column of `out` is computed contiguously, then written once: a
    # strided gather or in-place add costs twice as much.
    if grid.angle == 0.0:
        # Axis-aligned: one x per column and one y per row. Rows come in
        # order, so y is each row's y repeated; 32-bit division is several
        # times faster than 64-bit.
        xs, _ = grid.centres(np.zeros(grid.cols), np.arange(grid.cols))
        _, ys = grid.centres(np.arange(grid.rows), np.zeros(grid.rows))
        index = flat.astype(np.int32) if grid.size < 2**31 else flat
        out[:, 0] = xs.take(index % index.dtype.type(grid.cols))
        out[:, 1] = np.repeat(ys, np.count_nonzero(dem.mask, axis=1))
    else:
        rows, cols = np.divmod(flat, grid.cols)
        out[:, 0], out[:, 1] = grid.centres(rows, cols)
    z = dem.heights.ravel().take(flat)
    z += grid.z0
    out[:, 2] = z
    return out
