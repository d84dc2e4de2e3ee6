"""The data the pipeline passes between stages: point arrays, the grid and the DEM.

A point cloud is an (N, 3) float64 array checked here once (:func:`as_points`);
a :class:`Grid` says where each cell lies; a :class:`DEM` holds one height per
cell, which cells had points, and what gridding lost (:class:`HeightSpread`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import InvalidInputError, advice

__all__ = ["Grid", "TileGrid", "DEM", "RasterSource", "HeightSpread", "as_points", "drop_nonfinite", "nonfinite_error",
           "MULTI_HEIGHT_TOLERANCE_CELLS"]

#: A point farther than this many cell sizes (vertically) from its cell's
#: height is one the DEM cannot represent: a wall, an overhang, a tree.
#: Even a 45 degree slope stays within 0.71 cells of a cell's mean height.
MULTI_HEIGHT_TOLERANCE_CELLS = 1.0

@dataclass(frozen=True)
class Grid:
    """Geometry of a DEM: where cell (row, col) lies in the original frame.

    A point ``p`` has local coordinates ``R(-angle) @ (p.xy - origin)``;
    column ``floor(u / resolution)``, row ``floor(v / dy)``. Row 0 is
    at the smallest local v (south for an axis-aligned grid). Heights in the
    DEM are relative to ``z0``, the centroid height of the cloud (the paper's
    projection plane).

    Attributes
    ----------
    x0, y0 : float
        Origin (corner of cell (0, 0)) in the input's horizontal unit (metres).
    z0 : float
        Height of the projection plane, metres.
    resolution : float
        Cell size, metres (along u; along v too unless ``resolution_y``).
    rows, cols : int
        Shape of the DEM.
    angle : float
        Rotation of the grid's u axis from the x axis, radians.
    resolution_y : float, optional
        Cell size along v in metres when cells are not square (GeoTIFF DEMs
        on a latitude/longitude grid); None for square cells.
    """

    x0: float
    y0: float
    z0: float
    resolution: float
    rows: int
    cols: int
    angle: float = 0.0
    resolution_y: float | None = None

    @property
    def dy(self) -> float:
        """Cell size along v (rows), metres."""
        return self.resolution if self.resolution_y is None else self.resolution_y

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.cols)

    @property
    def size(self) -> int:
        return self.rows * self.cols

    def _rotation(self) -> tuple[float, float]:
        return math.cos(self.angle), math.sin(self.angle)

    def to_local(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Local (u, v) coordinates in metres of points ``xy`` of shape (N, 2+)."""
        dx = xy[:, 0] - self.x0
        dy = xy[:, 1] - self.y0
        if self.angle == 0.0:
            return dx, dy
        c, s = self._rotation()
        return c * dx + s * dy, -s * dx + c * dy

    def cell_of(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row and column (int64) of each point; may fall outside the grid."""
        u, v = self.to_local(xy)
        return np.floor(v * (1.0 / self.dy)).astype(np.int64), np.floor(u * (1.0 / self.resolution)).astype(np.int64)

    def flat_index(self, xy: np.ndarray) -> np.ndarray:
        """Row-major cell index of each point, -1 where it lies outside the grid."""
        # The hot loop of gridding: in-place float arithmetic, one conversion,
        # as few passes over millions of points as numpy allows.
        u, v = self.to_local(xy)
        u = np.multiply(u, 1.0 / self.resolution)
        v = np.multiply(v, 1.0 / self.dy)
        np.floor(u, out=u)
        np.floor(v, out=v)
        outside = (u < 0) | (u >= self.cols) | (v < 0) | (v >= self.rows)
        v *= self.cols
        v += u  # exact: cell counts are far below 2**53
        idx = v.astype(np.int64)
        if outside.any():
            idx[outside] = -1
        return idx

    def centres(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World x, y of the centres of cells ``(rows, cols)``."""
        u = (cols + 0.5) * self.resolution
        v = (rows + 0.5) * self.dy
        if self.angle == 0.0:
            return self.x0 + u, self.y0 + v
        c, s = self._rotation()
        return self.x0 + c * u - s * v, self.y0 + s * u + c * v

    def window(self, row: int, col: int, rows: int, cols: int) -> "Grid":
        """The grid of the ``rows`` x ``cols`` cells starting at cell (``row``, ``col``) of this one."""
        u, v = col * self.resolution, row * self.dy
        c, s = self._rotation()
        return Grid(x0=self.x0 + c * u - s * v, y0=self.y0 + s * u + c * v, z0=self.z0,
                    resolution=self.resolution, rows=rows, cols=cols, angle=self.angle,
                    resolution_y=self.resolution_y)


@dataclass(frozen=True)
class TileGrid:
    """A rows x cols grid cut into square tiles of ``size`` cells (docs/format.md, *Tiles*).

    Tile ``k`` (0-based, row-major; number ``k + 1`` in a file) covers rows
    ``i*size`` to ``min(rows, (i+1)*size)`` and likewise columns, with
    ``i, j = divmod(k, tile_cols)``.
    """

    rows: int
    cols: int
    size: int

    @property
    def tile_rows(self) -> int:
        return -(-self.rows // self.size)

    @property
    def tile_cols(self) -> int:
        return -(-self.cols // self.size)

    @property
    def count(self) -> int:
        return self.tile_rows * self.tile_cols

    def bounds(self, k: int) -> tuple[int, int, int, int]:
        """``(row_start, row_stop, col_start, col_stop)`` of tile ``k``, cells."""
        i, j = divmod(k, self.tile_cols)
        s = self.size
        return i * s, min(self.rows, (i + 1) * s), j * s, min(self.cols, (j + 1) * s)

    def shape(self, k: int) -> tuple[int, int]:
        r0, r1, c0, c1 = self.bounds(k)
        return r1 - r0, c1 - c0

    def touching(self, rows: tuple[int, int], cols: tuple[int, int]) -> list[int]:
        """Tiles holding any cell of rows ``[rows[0], rows[1])`` and cols ``[cols[0], cols[1])``."""
        s = self.size
        ti = range(rows[0] // s, -(-rows[1] // s))
        tj = range(cols[0] // s, -(-cols[1] // s))
        return [i * self.tile_cols + j for i in ti for j in tj]


@dataclass(frozen=True)
class HeightSpread:
    """How far a cloud is from having one height per cell.

    A DEM keeps one height per cell; points far above or below it (a
    vertical wall, an overhang, vegetation over ground) are flattened.

    Attributes
    ----------
    tolerance_m : float
        A point farther than this from its cell's height (metres) is counted
        as unrepresented (:data:`MULTI_HEIGHT_TOLERANCE_CELLS` cell sizes).
    points : int
        Points gridded.
    unrepresented_points : int
        Points farther than ``tolerance_m`` from their cell's height.
    unrepresented_cells : int
        Cells holding at least one such point.
    unrepresented_rmse_m : float
        RMS distance of those points to their cell's height, metres (0 if none).
    max_distance_m : float
        Largest distance of any point to its cell's height, metres.
    """

    tolerance_m: float
    points: int
    unrepresented_points: int
    unrepresented_cells: int
    unrepresented_rmse_m: float
    max_distance_m: float

    @property
    def fraction(self) -> float:
        """Fraction of the points the DEM cannot represent, in [0, 1]."""
        return self.unrepresented_points / self.points if self.points else 0.0

    def as_stats(self) -> dict[str, float | int]:
        """The figures as flat JSON-ready fields, for a file's STAT section."""
        return {
            "unrepresented_fraction": self.fraction,
            "unrepresented_points": self.unrepresented_points,
            "unrepresented_cells": self.unrepresented_cells,
            "unrepresented_rmse_m": self.unrepresented_rmse_m,
            "unrepresented_tolerance_m": self.tolerance_m,
            "max_point_distance_m": self.max_distance_m,
        }

    def describe(self) -> str:
        """One sentence for a warning or a summary line."""
        return (f"{100 * self.fraction:.2f} % of the points ({self.unrepresented_points:,} of "
                f"{self.points:,}, in {self.unrepresented_cells:,} cell(s)) lie more than "
                f"{self.tolerance_m:g} m ({MULTI_HEIGHT_TOLERANCE_CELLS:g} cell) above or below their cell's height, by "
                f"{self.unrepresented_rmse_m:.3g} m RMS and up to {self.max_distance_m:.3g} m: a DEM "
                f"keeps one height per cell, so walls, overhangs and vegetation are flattened "
                f"(keep ground points only, e.g. LAS class 2, or use finer cells)")


@dataclass(frozen=True)
class RasterSource:
    """The sample type and nodata value of the raster a DEM was read from, kept so that a
    decoder can write it back the same way (``STAT`` fields ``source_dtype``, ``source_nodata``).

    Attributes
    ----------
    dtype : str
        NumPy name of the raster's sample type (``int16``, ``float32``, ...).
    nodata : float, optional
        Its nodata value, in the raster's height unit; None when it declares none.
    """

    dtype: str
    nodata: float | None = None

    def as_stats(self) -> dict[str, Any]:
        """The ``STAT`` records of this source (docs/format.md): none for float32 (a decoder's default),
        the nodata value only when a float32 holds it exactly."""
        code = RASTER_DTYPE_CODES.get(self.dtype)
        if code is None or self.dtype == "float32":
            return {}
        stats: dict[str, Any] = {"source_dtype": code}
        if self.nodata is not None and math.isfinite(self.nodata) and float(np.float32(self.nodata)) == self.nodata:
            stats["source_nodata"] = float(self.nodata)
        return stats

    @classmethod
    def from_stats(cls, stats: dict[str, Any]) -> "RasterSource | None":
        """The source a file's ``STAT`` records, or None (a point cloud, a float32 raster, an unknown code)."""
        dtype = RASTER_DTYPES.get(stats.get("source_dtype", 0))
        return None if dtype is None else cls(dtype, stats.get("source_nodata"))


#: ``STAT`` ``source_dtype`` codes (docs/format.md).
RASTER_DTYPE_CODES = {"uint8": 1, "int8": 2, "uint16": 3, "int16": 4, "uint32": 5, "int32": 6, "float32": 7,
                      "float64": 8}
RASTER_DTYPES = {code: name for name, code in RASTER_DTYPE_CODES.items()}


@dataclass
class DEM:
    """A gridded map: heights relative to ``grid.z0`` plus which cells had points.

    Attributes
    ----------
    grid : Grid
    heights : ndarray, shape (rows, cols), float64
        Height above the projection plane in metres; empty cells hold 0
        until :func:`fill_empty` is applied.
    mask : ndarray, shape (rows, cols), bool
        True where at least one point fell.
    counts : ndarray, shape (rows, cols), int, optional
        Points per cell (known when the DEM was gridded from points).
    gridding_rmse : float, optional
        RMS vertical distance in metres of the points to their cell's height:
        with ``mean`` cells, the floor no codec storing this DEM goes below.
    spread : HeightSpread, optional
        Points the DEM cannot represent (known when gridded from points).
    source : RasterSource, optional
        The raster it is the own grid of (known when read from a GeoTIFF on its pixels).
    """

    grid: Grid
    heights: np.ndarray
    mask: np.ndarray
    counts: np.ndarray | None = None
    gridding_rmse: float | None = None
    spread: HeightSpread | None = None
    source: RasterSource | None = None


#: How many offending row numbers an error message lists.
_ROWS_SHOWN = 5

def _as_xyz(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise InvalidInputError(f"points must have shape (N, 3), got {points.shape}")
    if points.dtype.kind not in "biuf":
        raise InvalidInputError(f"points must be real numbers, got dtype {points.dtype}")
    return np.asarray(points[:, :3], dtype=np.float64)


def as_points(points: np.ndarray, *, finite: bool = True) -> np.ndarray:
    """``points`` as a finite (N, 3) float64 array with at least one row, or a clear error
    (``finite=False``: not checked for NaN and infinities, for a caller whose own pass checks them)."""
    points = _as_xyz(points)
    if points.shape[0] == 0:
        raise InvalidInputError("the point cloud is empty")
    if not finite:
        return points
    # One sum is finite exactly when every value is (or when a huge value
    # overflowed it): the exact row-wise check runs only then.
    if np.isfinite(points.sum()):
        return points
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        raise nonfinite_error(np.flatnonzero(~finite), points.shape[0])
    return points


def nonfinite_error(bad_rows: np.ndarray, total: int | str) -> InvalidInputError:
    """The error for NaN or infinite coordinates in ``bad_rows`` of ``total`` points."""
    shown = ", ".join(str(int(i)) for i in bad_rows[:_ROWS_SHOWN]) + (", ..." if bad_rows.size > _ROWS_SHOWN else "")
    return InvalidInputError(
        f"{bad_rows.size} of {total} point(s) have NaN or infinite coordinates (rows {shown}); "
        f"drop them first ({advice('dftpcc.grid.drop_nonfinite, or read(..., drop_nonfinite=True)', '--drop-nonfinite')})")


def drop_nonfinite(points: np.ndarray) -> tuple[np.ndarray, int]:
    """The rows of ``points`` whose x, y and z are all finite.

    Compression refuses NaN or infinite coordinates, since silently losing
    points hides a broken sensor or reader; this is the explicit opt-in.

    Parameters
    ----------
    points : array_like, shape (N, 3)

    Returns
    -------
    points : ndarray, shape (M, 3), float64
        The finite rows, in their order.
    dropped : int
        ``N - M``.
    """
    points = _as_xyz(points)
    finite = np.isfinite(points).all(axis=1)
    return points[finite], int(points.shape[0] - finite.sum())

