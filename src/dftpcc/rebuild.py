"""Rebuild stage: a decoded DEM becomes a point cloud again.

One point per occupied cell, at the cell centre, with the rebuilt height,
in the original coordinate frame (float64, so UTM-size coordinates stay exact);
or, :func:`dem_to_dense_points`, ``factor**2`` samples of the rebuilt surface per cell.
"""

from __future__ import annotations

from typing import Iterator

import numpy as np

from . import kernels
from .errors import InvalidInputError
from .grid import DEM

__all__ = ["dem_to_points", "dem_to_point_chunks", "dem_to_dense_points"]


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
        return _cell_points(mask, xs, ys, dem.heights, grid.z0)
    flat = np.flatnonzero(mask)
    out = np.empty((flat.size, 3))
    rows, cols = np.divmod(flat, grid.cols)
    out[:, 0], out[:, 1] = grid.centres(rows, cols)
    z = dem.heights.ravel().take(flat)
    z += grid.z0
    out[:, 2] = z
    return out


def dem_to_point_chunks(dem: DEM, cells: int) -> Iterator[np.ndarray]:
    """:func:`dem_to_points` in parts of whole rows, about ``cells`` grid cells each (at least a row):
    the same points in the same order and bits, without the whole array of them (a band of a
    20,000-column map is 20 M points).

    Yields
    ------
    ndarray, shape (n, 3), float64
    """
    grid, mask = dem.grid, dem.mask
    if grid.angle != 0.0:
        yield dem_to_points(dem)
        return
    xs, _ = grid.centres(np.zeros(grid.cols), np.arange(grid.cols))
    _, ys = grid.centres(np.arange(grid.rows), np.zeros(grid.rows))
    rows = max(1, cells // max(grid.cols, 1))
    for r0 in range(0, grid.rows, rows):
        r1 = min(grid.rows, r0 + rows)
        yield _cell_points(mask[r0:r1], xs, ys[r0:r1], dem.heights[r0:r1], grid.z0)


@kernels.kernel("cell_points")
def _cell_points(mask: np.ndarray, xs: np.ndarray, ys: np.ndarray, heights: np.ndarray, z0: float) -> np.ndarray:
    """``(xs[col], ys[row], heights + z0)`` of every cell set in ``mask`` (rows, cols), row-major, metres;
    ``xs`` one x per column, ``ys`` one y per row."""
    x = np.broadcast_to(xs, mask.shape)[mask]
    out = np.empty((x.size, 3))
    out[:, 0] = x
    out[:, 1] = np.repeat(ys, np.count_nonzero(mask, axis=1))
    z = heights[mask]
    z += z0
    out[:, 2] = z
    return out


def dem_to_dense_points(dem: DEM, factor: int) -> np.ndarray:
    """``factor`` x ``factor`` samples of the rebuilt surface per occupied cell.

    The samples sit at the centres of a ``factor`` times finer lattice of each
    cell, with heights interpolated bilinearly between the centres of the
    cell and its neighbours; an empty neighbour (or one beyond the grid) has
    no weight, the others share it, so the map's border is not pulled towards
    the codec's fill. A registration that pairs points with the map (GICP)
    gets a surface rather than one point per cell (docs/relocalization.md).
    ``factor=1`` is :func:`dem_to_points`.

    Parameters
    ----------
    dem : DEM
    factor : int
        Samples per cell side, at least 1.

    Returns
    -------
    ndarray, shape (cells * factor**2, 3), float64
        x, y, z in metres, original frame; cell by cell in row-major order.

    Raises
    ------
    InvalidInputError
        ``factor`` is not a positive whole number.
    """
    if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
        raise InvalidInputError(f"densify factor must be a whole number >= 1, got {factor!r}")
    if factor == 1:
        return dem_to_points(dem)
    grid = dem.grid
    rows, cols = np.nonzero(dem.mask)
    offsets = (np.arange(factor) + 0.5) / factor - 0.5  # sub-sample positions from the cell centre, in cells
    dv, du = (a.ravel() for a in np.meshgrid(offsets, offsets, indexing="ij"))
    # Fractional cell coordinates of every sample, in units where centres are integers.
    u = (cols[:, None] + du[None, :]).ravel()
    v = (rows[:, None] + dv[None, :]).ravel()
    j0 = np.floor(u).astype(np.int64)
    i0 = np.floor(v).astype(np.int64)
    fu, fv = u - j0, v - i0
    total = np.zeros(u.size)
    weight = np.zeros(u.size)
    for di, dj, w in ((0, 0, (1 - fv) * (1 - fu)), (0, 1, (1 - fv) * fu), (1, 0, fv * (1 - fu)), (1, 1, fv * fu)):
        i, j = i0 + di, j0 + dj
        inside = (i >= 0) & (i < grid.rows) & (j >= 0) & (j < grid.cols)
        ic, jc = np.clip(i, 0, grid.rows - 1), np.clip(j, 0, grid.cols - 1)
        w = np.where(inside & dem.mask[ic, jc], w, 0.0)
        total += w * dem.heights[ic, jc]
        weight += w
    # A sample lies within its own cell, whose weight is at least 1/4: never zero.
    out = np.empty((u.size, 3))
    out[:, 0], out[:, 1] = grid.centres(v, u)
    out[:, 2] = total / weight + grid.z0
    return out
