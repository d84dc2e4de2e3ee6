"""Grid stage: a point cloud becomes a Digital Elevation Model (DEM).

As in the paper, points are projected on a horizontal plane at the height of
their centroid, inside the minimum bounding rectangle (axis-aligned, or
optionally rotated to minimum area); each cell of ``resolution`` metres holds
one height. Cells no point fell in are recorded in an occupancy mask and
filled smoothly so the transform sees no artificial cliff.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np
from scipy import ndimage

from .errors import InvalidInputError, MultiHeightWarning

__all__ = [
    "Grid",
    "DEM",
    "HeightSpread",
    "MAX_CELLS",
    "drop_nonfinite",
    "fit_grid",
    "rasterize",
    "rasterize_chunks",
    "fill_empty",
    "fit_plane",
    "auto_resolution",
    "CloudSummary",
    "cell_limit",
    "gridding_rmse",
]

#: Largest grid dftpcc builds in memory (cells). A float64 DEM this size is
#: 800 MB and the transform needs a few such arrays.
MAX_CELLS = 100_000_000

#: Peak memory of compressing one cell, bytes: the DEM, its mask, counts,
#: fill, transform and synthesis arrays (about 90 B measured for the
#: compact profile, 120 B for the paper's complex DFT), rounded up.
ENCODE_BYTES_PER_CELL = 128

#: Float64 resolves a coordinate ``x`` to about ``x * 2**-52``; a grid needs
#: that to be below this fraction of a cell, or cells blur into each other.
COORDINATE_PRECISION_CELLS = 1e-3

#: A point farther than this many cell sizes (vertically) from its cell's
#: height is one the DEM cannot represent: a wall, an overhang, a tree.
#: Even a 45 degree slope stays within 0.71 cells of a cell's mean height.
MULTI_HEIGHT_TOLERANCE_CELLS = 1.0

#: Warn (:class:`~dftpcc.errors.MultiHeightWarning`) when at least this
#: fraction of the points cannot be represented.
MULTI_HEIGHT_WARN_FRACTION = 0.01

#: An extent within this many cells below a whole number of cells counts as whole.
LATTICE_TOLERANCE = 1e-6

#: Margin, in cells, around a rotated grid (see fit_grid).
ROTATED_MARGIN = 1e-6

#: ``auto`` resolution aims at this many points per occupied cell.
AUTO_POINTS_PER_CELL = 4.0


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
    """

    grid: Grid
    heights: np.ndarray
    mask: np.ndarray
    counts: np.ndarray | None = None
    gridding_rmse: float | None = None
    spread: HeightSpread | None = None


#: How many offending row numbers an error message lists.
_ROWS_SHOWN = 5


def _as_xyz(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise InvalidInputError(f"points must have shape (N, 3), got {points.shape}")
    if points.dtype.kind not in "biuf":
        raise InvalidInputError(f"points must be real numbers, got dtype {points.dtype}")
    return np.asarray(points[:, :3], dtype=np.float64)


def _check_points(points: np.ndarray) -> np.ndarray:
    points = _as_xyz(points)
    if points.shape[0] == 0:
        raise InvalidInputError("the point cloud is empty")
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
        f"drop them first (dftpcc.grid.drop_nonfinite, or read(..., drop_nonfinite=True))")


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


def _min_area_angle(xy: np.ndarray) -> float:
    """Angle of the minimum-area bounding rectangle (rotating calipers on the hull)."""
    from scipy.spatial import ConvexHull, QhullError

    # The hull of the cloud is the hull of its extreme points; thin it first.
    centred = xy - xy.mean(axis=0)
    try:
        hull = centred[ConvexHull(centred).vertices]
    except (QhullError, ValueError):
        return 0.0
    edges = np.diff(np.vstack([hull, hull[:1]]), axis=0)
    angles = np.unique(np.mod(np.arctan2(edges[:, 1], edges[:, 0]), math.pi / 2))
    c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
    u = c * hull[:, 0] + s * hull[:, 1]
    v = -s * hull[:, 0] + c * hull[:, 1]
    areas = np.ptp(u, axis=1) * np.ptp(v, axis=1)
    return float(angles[int(np.argmin(areas))])


def fit_grid(points: np.ndarray, resolution: float, *, frame: str = "axis") -> Grid:
    """The grid that encloses ``points`` at ``resolution`` metres per cell.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Coordinates in metres (float64 keeps UTM-size coordinates exact).
    resolution : float
        Cell size in metres.
    frame : {'axis', 'oriented'}
        Axis-aligned or minimum-area rotated bounding rectangle.

    Raises
    ------
    InvalidInputError
        Empty or non-finite cloud, a bad resolution, a grid over
        :func:`cell_limit` cells (:data:`MAX_CELLS`, or what the available
        memory holds; the message gives the numbers and the coarsest
        resolution that fits), or coordinates too large for float64 to
        resolve cells of ``resolution``.
    """
    points = _check_points(points)
    _check_resolution(resolution)
    angle = _min_area_angle(points[:, :2]) if frame == "oriented" else 0.0
    # Each extreme once, column by column: over millions of strided values every pass counts.
    x_lo, x_hi, y_lo, y_hi = (float(f(points[:, k])) for k in (0, 1) for f in (np.min, np.max))
    if angle:
        c, s = math.cos(angle), math.sin(angle)
        u = c * points[:, 0] + s * points[:, 1]
        v = -s * points[:, 0] + c * points[:, 1]
        local = (float(u.min()), float(u.max()), float(v.min()), float(v.max()))
    else:  # the paper's frame: no arithmetic over millions of points
        local = (x_lo, x_hi, y_lo, y_hi)
    return _grid_around((x_lo, x_hi, y_lo, y_hi), local, angle, float(points[:, 2].mean()), resolution)


def _check_resolution(resolution: float) -> None:
    if not (math.isfinite(resolution) and resolution > 0):
        raise InvalidInputError(f"resolution must be a positive number of metres, got {resolution!r}")


def _grid_around(xy_extremes: tuple[float, float, float, float], local: tuple[float, float, float, float],
                 angle: float, z0: float, resolution: float) -> Grid:
    """The grid of ``resolution`` cells covering ``local`` = (umin, umax, vmin, vmax) in the frame
    rotated by ``angle``; ``xy_extremes`` = (x_lo, x_hi, y_lo, y_hi) for the precision check."""
    c, s = math.cos(angle), math.sin(angle)
    # A rotated frame recomputes local coordinates from a rotated origin; a
    # margin of a millionth of a cell keeps round-off from pushing the
    # extreme points outside the grid.
    margin = ROTATED_MARGIN * resolution if angle else 0.0
    umin, umax, vmin, vmax = local
    umin, vmin, umax, vmax = umin - margin, vmin - margin, umax + margin, vmax + margin
    # Sizes in floats first: a tiny resolution or a huge extent must give a
    # clear refusal, not an overflow or an attempt to allocate.
    with np.errstate(over="ignore", invalid="ignore"):
        # An extent a hair short of whole cells (round-off on lattice data)
        # counts as whole, so the last lattice point gets its own cell.
        cols_f = float(np.floor((umax - umin) / resolution + LATTICE_TOLERANCE)) + 1.0
        rows_f = float(np.floor((vmax - vmin) / resolution + LATTICE_TOLERANCE)) + 1.0
    _check_grid_size(rows_f, cols_f, resolution)
    _check_precision(max(abs(e) for e in xy_extremes), resolution)
    rows, cols = int(rows_f), int(cols_f)
    # Whole cells overhang the points' extent; split the overhang evenly on
    # both sides. Points on a lattice of the cell size (a DEM's pixel
    # centres, a voxelised SLAM map) then sit mid-cell, not on cell edges
    # where round-off would drop some into their neighbour.
    umin -= (cols * resolution - (umax - umin)) / 2.0
    vmin -= (rows * resolution - (vmax - vmin)) / 2.0
    x0, y0 = c * umin - s * vmin, s * umin + c * vmin
    return Grid(x0=x0, y0=y0, z0=z0, resolution=float(resolution), rows=rows, cols=cols, angle=angle)


def available_memory() -> int | None:
    """Bytes of memory the system can still give this process (Linux), else ``None``."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def cell_limit() -> int:
    """Largest grid (cells) compression will build here: :data:`MAX_CELLS`, or less
    when the available memory cannot hold :data:`ENCODE_BYTES_PER_CELL` per cell."""
    memory = available_memory()
    return MAX_CELLS if memory is None else max(1, min(MAX_CELLS, memory // ENCODE_BYTES_PER_CELL))


def _size(nbytes: float) -> str:
    for unit, scale in (("PB", 1e15), ("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if nbytes >= scale:
            return f"{nbytes / scale:,.1f} {unit}"
    return f"{nbytes / 1e3:,.1f} kB"


def _count(n: float) -> str:
    return f"{n:,.0f}" if n < 1e15 else f"{n:.3g}"


#: Headroom on a suggested resolution for the extra row and column a grid takes.
ROUNDING_MARGIN = 0.01


def _round_up(value: float, digits: int = 2) -> float:
    """``value`` rounded up to ``digits`` significant digits (a resolution to suggest)."""
    scale = 10.0 ** (math.floor(math.log10(value)) - digits + 1)
    return float(f"{math.ceil(value / scale) * scale:.{digits}g}")


def _check_grid_size(rows: float, cols: float, resolution: float) -> None:
    cells = rows * cols
    limit = cell_limit()
    if math.isfinite(cells) and cells <= limit:
        return
    if not math.isfinite(cells):
        raise InvalidInputError(
            f"the points span about {_count((cols - 1) * resolution)} x {_count((rows - 1) * resolution)} m: "
            f"at {resolution:g} m that is more cells than can be counted; use a coarser resolution")
    why = (f"the {MAX_CELLS:,}-cell limit" if limit == MAX_CELLS else
           f"the {limit:,} cells that the available memory ({_size(available_memory() or 0)}) holds")
    # Cells scale with 1/resolution**2: the coarsest step that fits, rounded up.
    need = resolution * math.sqrt(cells / limit) * (1 + ROUNDING_MARGIN)
    hint = f"use a resolution of at least {_round_up(need):g} m"
    raise InvalidInputError(
        f"a {_count(rows)} x {_count(cols)} grid ({_count(cells)} cells) at {resolution:g} m would need "
        f"about {_size(cells * ENCODE_BYTES_PER_CELL)} of memory and exceeds {why}; {hint}")


def _check_precision(largest: float, resolution: float) -> None:
    """``largest``: the largest |x| or |y| of the cloud, metres."""
    ulp = largest * 2.0**-52
    if ulp > COORDINATE_PRECISION_CELLS * resolution:
        raise InvalidInputError(
            f"coordinates up to {largest:.3g} m are resolved only to {ulp:.2g} m in float64, too coarse for "
            f"{resolution:g} m cells; subtract an offset from x and y first")


def rasterize(points: np.ndarray, grid: Grid, *, aggregate: str = "mean") -> DEM:
    """Height of every cell from the points in it.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
    grid : Grid
    aggregate : {'mean', 'median', 'min', 'max'}

    Returns
    -------
    DEM
        Heights relative to ``grid.z0`` in metres; 0 in empty cells.
    """
    points = _check_points(points)
    idx, z = _cells_of(points, grid)
    if aggregate == "median":
        count = np.bincount(idx, minlength=grid.size)
        mask = count > 0
        heights = np.zeros(grid.size)
        labels = np.flatnonzero(mask)
        heights[labels] = ndimage.median(z, labels=idx, index=labels)
    else:
        cells = _CellHeights(grid.size, aggregate)
        cells.add(idx, z)
        count, heights, mask = cells.count, cells.heights(), cells.count > 0
    spread = _SpreadCounter(grid)
    spread.add(idx, z, heights)
    return spread.dem(heights, mask, count)


def rasterize_chunks(chunks: Callable[[], Iterable[np.ndarray]], grid: Grid, *, aggregate: str = "mean") -> DEM:
    """:func:`rasterize` for a cloud read chunk by chunk, in two passes.

    Memory holds the grid's per-cell arrays and one chunk, not the cloud.

    Parameters
    ----------
    chunks : callable
        Each call starts a new pass: an iterable of finite (n, 3) float64
        arrays that together are the cloud.
    grid : Grid
    aggregate : {'mean', 'min', 'max'}
        A median needs all of a cell's points at once, so it is refused.
    """
    check_chunked_aggregate(aggregate)
    cells = _CellHeights(grid.size, aggregate)
    for points in chunks():
        cells.add(*_cells_of(points, grid))
    heights, mask = cells.heights(), cells.count > 0
    # Second pass: each point against its cell's final height.
    spread = _SpreadCounter(grid)
    for points in chunks():
        spread.add(*_cells_of(points, grid), heights)
    return spread.dem(heights, mask, cells.count)


def check_chunked_aggregate(aggregate: str) -> None:
    """Refuse an aggregate that cannot be gathered chunk by chunk (the median)."""
    if aggregate == "median":
        raise InvalidInputError("aggregate 'median' needs all of a cell's points at once; "
                                "a cloud read in chunks can use mean, min or max")


def _cells_of(points: np.ndarray, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """Flat cell index and height above ``grid.z0`` of the points inside ``grid``."""
    idx = grid.flat_index(points)
    keep = idx >= 0
    if not keep.all():
        idx, points = idx[keep], points[keep]
    return idx, points[:, 2] - grid.z0


class _CellHeights:
    """Count and mean, minimum or maximum height per cell, accumulated over chunks of points."""

    def __init__(self, size: int, aggregate: str):
        if aggregate not in ("mean", "min", "max"):
            raise InvalidInputError(f"aggregate must be mean, median, min or max; got {aggregate!r}")
        self.aggregate, self.size = aggregate, size
        self.count = np.zeros(size, dtype=np.int64)
        fill = {"mean": 0.0, "min": np.inf, "max": -np.inf}[aggregate]
        self.acc = np.full(size, fill)

    def add(self, idx: np.ndarray, z: np.ndarray) -> None:
        self.count += np.bincount(idx, minlength=self.size)
        if self.aggregate == "mean":
            self.acc += np.bincount(idx, weights=z, minlength=self.size)
        else:
            (np.minimum if self.aggregate == "min" else np.maximum).at(self.acc, idx, z)

    def heights(self) -> np.ndarray:
        mask = self.count > 0
        if self.aggregate == "mean":
            return np.divide(self.acc, self.count, out=np.zeros(self.size), where=mask)
        return np.where(mask, self.acc, 0.0)


class _SpreadCounter:
    """How far points lie from their cell's height, accumulated over chunks: the gridding RMSE
    and the :class:`HeightSpread`."""

    def __init__(self, grid: Grid):
        self.grid = grid
        self.tolerance = MULTI_HEIGHT_TOLERANCE_CELLS * grid.resolution
        self.points = self.far_points = 0
        self.sq_sum = self.far_sq_sum = self.max_sq = 0.0
        self.far_cells: np.ndarray | None = None  # allocated at the first far point

    def add(self, idx: np.ndarray, z: np.ndarray, heights: np.ndarray) -> None:
        dz = z - heights[idx]
        sq = np.multiply(dz, dz, out=dz)  # squared distances: all that is needed from here on
        self.points += sq.size
        self.sq_sum += float(sq.sum())
        if sq.size:
            self.max_sq = max(self.max_sq, float(sq.max()))
        far = sq > self.tolerance * self.tolerance
        n_far = int(np.count_nonzero(far))
        if n_far:
            self.far_points += n_far
            self.far_sq_sum += float(np.sum(sq, where=far))
            if self.far_cells is None:
                self.far_cells = np.zeros(self.grid.size, dtype=bool)
            self.far_cells[idx[far]] = True

    def dem(self, heights: np.ndarray, mask: np.ndarray, count: np.ndarray) -> DEM:
        """The DEM, with its gridding RMSE and spread; warns when the spread is large."""
        spread = HeightSpread(
            tolerance_m=self.tolerance,
            points=self.points,
            unrepresented_points=self.far_points,
            unrepresented_cells=int(np.count_nonzero(self.far_cells)) if self.far_cells is not None else 0,
            unrepresented_rmse_m=math.sqrt(self.far_sq_sum / self.far_points) if self.far_points else 0.0,
            max_distance_m=math.sqrt(self.max_sq),
        )
        if spread.fraction >= MULTI_HEIGHT_WARN_FRACTION:
            warnings.warn(spread.describe(), MultiHeightWarning, stacklevel=3)
        shape = self.grid.shape
        return DEM(grid=self.grid, heights=heights.reshape(shape), mask=mask.reshape(shape),
                   counts=count.reshape(shape), gridding_rmse=math.sqrt(self.sq_sum / self.points) if self.points
                   else 0.0, spread=spread)


def gridding_rmse(points: np.ndarray, dem: DEM) -> float:
    """RMS vertical distance in metres of each point to its own cell's height.

    With ``aggregate='mean'`` this is the floor: the error no codec that
    stores this DEM can go below. Points outside the grid are ignored.
    """
    points = _check_points(points)
    idx = dem.grid.flat_index(points)
    keep = idx >= 0
    dz = points[keep, 2] - dem.grid.z0 - dem.heights.ravel()[idx[keep]]
    return float(np.sqrt(np.mean(dz * dz))) if dz.size else 0.0


def fit_plane(dem: DEM) -> tuple[float, float, float]:
    """Least-squares plane ``a + b*col + c*row`` (metres) through the occupied cells."""
    rows, cols = np.nonzero(dem.mask)
    if rows.size < 3:
        return (float(dem.heights[dem.mask].mean()) if rows.size else 0.0, 0.0, 0.0)
    # Normal equations on centred coordinates: 3 x 3, well conditioned, and
    # a few passes over the cells instead of a least-squares solve on them.
    x, y, z = cols.astype(float), rows.astype(float), dem.heights[rows, cols]
    mx, my, mz = x.mean(), y.mean(), z.mean()
    x -= mx
    y -= my
    z = z - mz
    normal = np.array([[x @ x, x @ y], [x @ y, y @ y]])
    rhs = np.array([x @ z, y @ z])
    try:
        b, c = np.linalg.solve(normal, rhs)
    except np.linalg.LinAlgError:  # all cells on one line: fit along it only
        b, c = np.linalg.lstsq(normal, rhs, rcond=None)[0]
    return float(mz - b * mx - c * my), float(b), float(c)


def plane_values(plane: tuple[float, float, float], shape: tuple[int, int]) -> np.ndarray:
    """The plane of :func:`fit_plane` evaluated on a grid of ``shape``."""
    a, b, c = plane
    rows = np.arange(shape[0], dtype=float)[:, None]
    cols = np.arange(shape[1], dtype=float)[None, :]
    return a + b * cols + c * rows


def fill_empty(heights: np.ndarray, mask: np.ndarray, *, method: str = "smooth") -> np.ndarray:
    """Heights with empty cells filled, occupied cells untouched.

    ``zero`` leaves 0 (the projection plane). ``smooth`` is push-pull
    interpolation: occupied cells are averaged down a pyramid, and each
    level's empty cells take the bilinearly upsampled coarser level, so a
    hole is bridged by a smooth surface and adds little high-frequency
    energy to the spectrum.

    Parameters
    ----------
    heights : ndarray, shape (rows, cols)
    mask : ndarray of bool, same shape
    method : {'smooth', 'zero'}
    """
    out = np.where(mask, heights, 0.0)
    if method == "zero" or mask.all() or not mask.any():
        return out
    if method != "smooth":
        raise InvalidInputError(f"fill must be 'smooth' or 'zero', got {method!r}")
    return _push_pull(out, mask.astype(np.float64))


def _upsample2(a: np.ndarray, axis: int) -> np.ndarray:
    """Linear 2x upsampling along ``axis`` with cell-centred samples, edges clamped."""
    a = np.moveaxis(a, axis, 0)
    before = np.concatenate([a[:1], a[:-1]])
    after = np.concatenate([a[1:], a[-1:]])
    out = np.empty((2 * a.shape[0],) + a.shape[1:])
    out[0::2] = 0.75 * a + 0.25 * before
    out[1::2] = 0.75 * a + 0.25 * after
    return np.moveaxis(out, 0, axis)


def _push_pull(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    if weights.min() >= 1.0:
        return values  # nothing to fill at this level (coarse levels of a dense map)
    if min(values.shape) <= 1 and values.size <= 2:
        total = weights.sum()
        mean = (values * weights).sum() / total if total else 0.0
        return np.where(weights > 0, values, mean)
    # Pull: average the known values over 2x2 blocks (pad odd sizes by edge).
    r, c = values.shape
    pr, pc = r % 2, c % 2
    v = np.pad(values * weights, ((0, pr), (0, pc)))
    w = np.pad(weights, ((0, pr), (0, pc)))
    wsum = w.reshape(v.shape[0] // 2, 2, v.shape[1] // 2, 2).sum(axis=(1, 3))
    vsum = v.reshape(v.shape[0] // 2, 2, v.shape[1] // 2, 2).sum(axis=(1, 3))
    coarse_v = np.divide(vsum, wsum, out=np.zeros_like(vsum), where=wsum > 0)
    coarse = _push_pull(coarse_v, np.minimum(wsum, 1.0))
    # Push: bilinear upsampling of the filled coarse level back to this size.
    up = _upsample2(_upsample2(coarse, 0), 1)[:r, :c]
    wc = np.minimum(weights, 1.0)
    return wc * values + (1.0 - wc) * up


def auto_resolution(points: np.ndarray) -> float:
    """A cell size in metres giving about :data:`AUTO_POINTS_PER_CELL` points per occupied cell.

    The density is measured on the occupied area (a trial grid at the mean
    spacing), so an irregular footprint does not bias it.
    """
    points = _check_points(points)
    summary = CloudSummary()
    summary.add(points)
    return summary.auto_resolution(lambda: (points,))


def _auto_trial(extent: np.ndarray, n: int) -> tuple[float, bool]:
    """The trial cell size for :func:`auto_resolution`, or (resolution, True) for a line of points."""
    area = float(extent[0] * extent[1])
    if not math.isfinite(area):
        raise InvalidInputError(f"cannot choose a resolution automatically: the points span "
                                f"{extent[0]:.3g} x {extent[1]:.3g} m; give a resolution in metres")
    if float(extent.max()) <= 0:
        raise InvalidInputError(
            f"cannot choose a resolution automatically: all {n:,} point(s) lie at one x, y "
            f"position; give a resolution in metres (the map is then a single cell)")
    if area <= 0:
        # A line along x or y (a transect): density along its length.
        spacing = float(extent.max()) / (n - 1)
        return AUTO_POINTS_PER_CELL * spacing, True
    return math.sqrt(area / n), False


class CloudSummary:
    """What fitting a grid needs to know of a cloud read in chunks, gathered in one pass.

    Attributes
    ----------
    count : int
        Points seen.
    z_sum : float
        Sum of their heights (the projection plane is their mean).
    extremes : list of float
        x_lo, x_hi, y_lo, y_hi.
    hull : ndarray, shape (k, 2), or None
        With ``hull=True``: the vertices of the convex hull of x, y so far
        (an oriented frame is fitted to them).
    """

    def __init__(self, *, hull: bool = False):
        self.count, self.z_sum = 0, 0.0
        self.extremes = [math.inf, -math.inf, math.inf, -math.inf]
        self.hull: np.ndarray | None = np.zeros((0, 2)) if hull else None

    def add(self, points: np.ndarray) -> None:
        if not points.shape[0]:
            return
        self.count += points.shape[0]
        self.z_sum += float(points[:, 2].sum())
        lo = [float(points[:, k].min()) for k in (0, 1)]
        hi = [float(points[:, k].max()) for k in (0, 1)]
        e = self.extremes
        self.extremes = [min(e[0], lo[0]), max(e[1], hi[0]), min(e[2], lo[1]), max(e[3], hi[1])]
        if self.hull is not None:
            self.hull = _hull_vertices(np.vstack([self.hull, points[:, :2]]))

    def fit_grid(self, resolution: float, *, frame: str = "axis") -> Grid:
        """:func:`fit_grid` for the cloud summarised here (same grid, up to float round-off)."""
        if not self.count:
            raise InvalidInputError("the point cloud is empty")
        _check_resolution(resolution)
        x_lo, x_hi, y_lo, y_hi = self.extremes
        angle = 0.0
        local = (x_lo, x_hi, y_lo, y_hi)
        if frame == "oriented":
            if self.hull is None:
                raise ValueError("an oriented frame needs CloudSummary(hull=True)")
            angle = _min_area_angle(self.hull)
            if angle:  # a linear function is extreme at the hull's vertices
                c, s = math.cos(angle), math.sin(angle)
                u = c * self.hull[:, 0] + s * self.hull[:, 1]
                v = -s * self.hull[:, 0] + c * self.hull[:, 1]
                local = (float(u.min()), float(u.max()), float(v.min()), float(v.max()))
        return _grid_around((x_lo, x_hi, y_lo, y_hi), local, angle, self.z_sum / self.count, resolution)

    def auto_resolution(self, chunks: Callable[[], Iterable[np.ndarray]]) -> float:
        """:func:`auto_resolution` for the cloud summarised here; one more pass over ``chunks``."""
        if not self.count:
            raise InvalidInputError("the point cloud is empty")
        x_lo, x_hi, y_lo, y_hi = self.extremes
        trial, line = _auto_trial(np.array([x_hi - x_lo, y_hi - y_lo]), self.count)
        if line:
            return trial
        cols = int(np.floor((x_hi - x_lo) / trial)) + 1
        rows = int(np.floor((y_hi - y_lo) / trial)) + 1
        # A bitmap of the trial cells (about one byte per point); a thin footprint far
        # off the axes spans many more cells than points, so there the ids are kept.
        bitmap = rows * cols <= 4 * self.count + 1024
        occupied = np.zeros(rows * cols if bitmap else 0, dtype=bool if bitmap else np.int64)
        for points in chunks():
            c = np.floor((points[:, 0] - x_lo) / trial).astype(np.int64)
            r = np.floor((points[:, 1] - y_lo) / trial).astype(np.int64)
            if bitmap:
                occupied[r * cols + c] = True
            else:
                occupied = np.union1d(occupied, r * cols + c)
        n_occupied = int(np.count_nonzero(occupied)) if bitmap else occupied.size
        density = self.count / (n_occupied * trial * trial)
        return float(math.sqrt(AUTO_POINTS_PER_CELL / density))


def _hull_vertices(xy: np.ndarray) -> np.ndarray:
    """The points of ``xy`` on its convex hull (all of them when the hull is degenerate and small)."""
    from scipy.spatial import ConvexHull, QhullError

    if xy.shape[0] <= 3:
        return xy
    try:
        return xy[ConvexHull(xy - xy.mean(axis=0)).vertices]
    except (QhullError, ValueError):
        # Collinear points: the two ends of the line are what any frame needs.
        order = np.lexsort((xy[:, 1], xy[:, 0]))
        return xy[[order[0], order[-1]]]
