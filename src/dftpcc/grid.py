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
    "fill_empty",
    "fit_plane",
    "auto_resolution",
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
        bad = np.flatnonzero(~finite)
        shown = ", ".join(str(int(i)) for i in bad[:_ROWS_SHOWN]) + (", ..." if bad.size > _ROWS_SHOWN else "")
        raise InvalidInputError(
            f"{bad.size} of {points.shape[0]} point(s) have NaN or infinite coordinates (rows {shown}); "
            f"drop them first (dftpcc.grid.drop_nonfinite, or read(..., drop_nonfinite=True))")
    return points


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
    if not (math.isfinite(resolution) and resolution > 0):
        raise InvalidInputError(f"resolution must be a positive number of metres, got {resolution!r}")
    angle = _min_area_angle(points[:, :2]) if frame == "oriented" else 0.0
    c, s = math.cos(angle), math.sin(angle)
    if angle:
        u = c * points[:, 0] + s * points[:, 1]
        v = -s * points[:, 0] + c * points[:, 1]
    else:  # the paper's frame: no arithmetic over millions of points
        u, v = points[:, 0], points[:, 1]
    # A rotated frame recomputes local coordinates from a rotated origin; a
    # margin of a millionth of a cell keeps round-off from pushing the
    # extreme points outside the grid.
    margin = ROTATED_MARGIN * resolution if angle else 0.0
    # Each extreme once, column by column: over millions of strided values every pass counts.
    x_lo, x_hi, y_lo, y_hi = (float(f(points[:, k])) for k in (0, 1) for f in (np.min, np.max))
    if angle:
        umin, umax, vmin, vmax = float(u.min()), float(u.max()), float(v.min()), float(v.max())
    else:
        umin, umax, vmin, vmax = x_lo, x_hi, y_lo, y_hi
    umin, vmin, umax, vmax = umin - margin, vmin - margin, umax + margin, vmax + margin
    # Sizes in floats first: a tiny resolution or a huge extent must give a
    # clear refusal, not an overflow or an attempt to allocate.
    with np.errstate(over="ignore", invalid="ignore"):
        # An extent a hair short of whole cells (round-off on lattice data)
        # counts as whole, so the last lattice point gets its own cell.
        cols_f = float(np.floor((umax - umin) / resolution + LATTICE_TOLERANCE)) + 1.0
        rows_f = float(np.floor((vmax - vmin) / resolution + LATTICE_TOLERANCE)) + 1.0
    _check_grid_size(rows_f, cols_f, resolution)
    _check_precision(max(abs(x_lo), abs(x_hi), abs(y_lo), abs(y_hi)), resolution)
    rows, cols = int(rows_f), int(cols_f)
    # Whole cells overhang the points' extent; split the overhang evenly on
    # both sides. Points on a lattice of the cell size (a DEM's pixel
    # centres, a voxelised SLAM map) then sit mid-cell, not on cell edges
    # where round-off would drop some into their neighbour.
    umin -= (cols * resolution - (umax - umin)) / 2.0
    vmin -= (rows * resolution - (vmax - vmin)) / 2.0
    x0, y0 = c * umin - s * vmin, s * umin + c * vmin
    return Grid(x0=x0, y0=y0, z0=float(points[:, 2].mean()), resolution=float(resolution),
                rows=rows, cols=cols, angle=angle)


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
    idx = grid.flat_index(points)
    keep = idx >= 0
    if not keep.all():
        idx, points = idx[keep], points[keep]
    z = points[:, 2] - grid.z0
    count = np.bincount(idx, minlength=grid.size)
    mask = count > 0
    if aggregate == "mean":
        total = np.bincount(idx, weights=z, minlength=grid.size)
        heights = np.divide(total, count, out=np.zeros(grid.size), where=mask)
    elif aggregate in ("min", "max"):
        heights = np.full(grid.size, np.inf if aggregate == "min" else -np.inf)
        (np.minimum if aggregate == "min" else np.maximum).at(heights, idx, z)
        heights[~mask] = 0.0
    elif aggregate == "median":
        heights = np.zeros(grid.size)
        labels = np.flatnonzero(mask)
        heights[labels] = ndimage.median(z, labels=idx, index=labels)
    else:
        raise InvalidInputError(f"aggregate must be mean, median, min or max; got {aggregate!r}")
    dz = z - heights[idx]
    sq = np.multiply(dz, dz, out=dz)  # squared distances: all that is needed from here on
    spread = _height_spread(sq, idx, grid.resolution)
    if spread.fraction >= MULTI_HEIGHT_WARN_FRACTION:
        warnings.warn(spread.describe(), MultiHeightWarning, stacklevel=2)
    return DEM(grid=grid, heights=heights.reshape(grid.shape), mask=mask.reshape(grid.shape),
               counts=count.reshape(grid.shape), gridding_rmse=float(np.sqrt(np.mean(sq))),
               spread=spread)


def _height_spread(sq: np.ndarray, idx: np.ndarray, resolution: float) -> HeightSpread:
    """``sq``: squared vertical distance of each point to its cell's height."""
    tolerance = MULTI_HEIGHT_TOLERANCE_CELLS * resolution
    far = sq > tolerance * tolerance
    n_far = int(np.count_nonzero(far))
    return HeightSpread(
        tolerance_m=tolerance,
        points=int(sq.size),
        unrepresented_points=n_far,
        # bincount, not unique: O(n) instead of a sort over millions of points
        unrepresented_cells=int(np.count_nonzero(np.bincount(idx[far]))) if n_far else 0,
        unrepresented_rmse_m=math.sqrt(float(np.sum(sq, where=far)) / n_far) if n_far else 0.0,
        max_distance_m=math.sqrt(float(sq.max())) if sq.size else 0.0,
    )


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
    xy = points[:, :2]
    extent = np.ptp(xy, axis=0)
    area = float(extent[0] * extent[1])
    if not math.isfinite(area):
        raise InvalidInputError(f"cannot choose a resolution automatically: the points span "
                                f"{extent[0]:.3g} x {extent[1]:.3g} m; give a resolution in metres")
    if float(extent.max()) <= 0:
        raise InvalidInputError(
            f"cannot choose a resolution automatically: all {points.shape[0]:,} point(s) lie at one x, y "
            f"position; give a resolution in metres (the map is then a single cell)")
    if area <= 0:
        # A line along x or y (a transect): density along its length.
        spacing = float(extent.max()) / (points.shape[0] - 1)
        return AUTO_POINTS_PER_CELL * spacing
    trial = math.sqrt(area / points.shape[0])
    cols = np.floor((xy[:, 0] - xy[:, 0].min()) / trial).astype(np.int64)
    rows = np.floor((xy[:, 1] - xy[:, 1].min()) / trial).astype(np.int64)
    occupied = np.unique(rows * (int(cols.max()) + 1) + cols).size
    density = points.shape[0] / (occupied * trial * trial)
    return float(math.sqrt(AUTO_POINTS_PER_CELL / density))
