"""Grid stage: a point cloud becomes a Digital Elevation Model (DEM).

One per-cell accumulator for every way a cloud arrives: whole (:func:`rasterize`), in chunks
(:func:`rasterize_chunks`, :class:`CloudSummary` for the grid), band by band on disk for a grid
larger than memory (:func:`rasterize_bands`, :class:`GriddedBands`), and scan by scan into the tiles
of a growing map (:class:`CellSums`, exact integer sums, so the order of the scans does not matter).

As in the paper, points are projected on a horizontal plane at the height of
their centroid, inside the minimum bounding rectangle (axis-aligned, or
optionally rotated to minimum area); each cell of ``resolution`` metres holds
one height. Cells no point fell in are recorded in the occupancy mask; filling
them for the transform is the spectrum stage's job (:mod:`dftpcc.fill`).
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator, NamedTuple

import numpy as np

from . import kernels
from .dem import DEM, MULTI_HEIGHT_TOLERANCE_CELLS, Grid, HeightSpread, as_points
from .errors import InvalidInputError, MultiHeightWarning
from .limits import check_grid_size

#: Refuses a grid of (rows, cols) cells of a resolution (metres) that cannot be built here.
SizeCheck = Callable[[float, float, float], None]

__all__ = [
    "fit_grid",
    "extremes",
    "survey",
    "Survey",
    "rasterize",
    "rasterize_chunks",
    "rasterize_bands",
    "GriddedBands",
    "check_chunked_aggregate",
    "auto_resolution",
    "CloudSummary",
    "CellSums",
    "lattice_cells",
    "HEIGHT_QUANTUM_M",
]

#: Float64 resolves a coordinate ``x`` to about ``x * 2**-52``; a grid needs
#: that to be below this fraction of a cell, or cells blur into each other.
COORDINATE_PRECISION_CELLS = 1e-3

#: Warn (:class:`~dftpcc.errors.MultiHeightWarning`) when at least this
#: fraction of the points cannot be represented.
MULTI_HEIGHT_WARN_FRACTION = 0.01

#: An extent within this many cells below a whole number of cells counts as whole.
LATTICE_TOLERANCE = 1e-6

#: Margin, in cells, around a rotated grid (see fit_grid).
ROTATED_MARGIN = 1e-6

#: Minimum-area rectangles whose areas differ by less than this fraction are a tie (oriented
#: frame), broken by the smallest angle.
ANGLE_TIE_TOLERANCE = 1e-9

#: ``auto`` resolution aims at this many points per occupied cell.
AUTO_POINTS_PER_CELL = 4.0

#: Points handled at once by the passes over a whole cloud: a block's columns and
#: scratch arrays stay in the core's cache, so a cloud is read from memory once per
#: pass instead of once per column and operation (2x faster on 2.8 M points).
BLOCK_POINTS = 16384


class Survey(NamedTuple):
    """What one pass over a cloud tells the grid: its extremes, and its mean height (the grid's z0)."""

    x_lo: float
    x_hi: float
    y_lo: float
    y_hi: float
    z_lo: float
    z_hi: float
    z_mean: float


def survey(points: np.ndarray) -> tuple[np.ndarray, Survey]:
    """:func:`~dftpcc.dem.as_points` of ``points``, and their :class:`Survey`.

    On the compiled backend, the check for NaN and infinities, the extremes and the sum of the
    heights are one pass over the cloud instead of four, to the same bits as numpy's reductions
    (``points[:, 2].mean()``); a cloud that fails the check is refused by
    :func:`~dftpcc.dem.as_points`, with its message.
    """
    xyz = as_points(points, finite=False)
    return xyz, Survey(*_survey_values(xyz))


@kernels.kernel("survey")
def _survey_values(xyz: np.ndarray) -> tuple[float, float, float, float, float, float, float]:
    """x_lo, x_hi, y_lo, y_hi, z_lo, z_hi and the mean height of (N, 3) float64 points, N > 0, or the
    error of :func:`~dftpcc.dem.as_points` for a coordinate that is not finite."""
    z = as_points(xyz)[:, 2]
    return (*_xy_extremes(xyz), float(z.min()), float(z.max()), float(z.mean()))


def extremes(points: np.ndarray) -> tuple[float, float, float, float, float, float]:
    """x_lo, x_hi, y_lo, y_hi, z_lo, z_hi of ``points`` (N, 3+), N > 0 (see :func:`survey`)."""
    return tuple(survey(points)[1])[:6]  # type: ignore[return-value]


def _xy_extremes(points: np.ndarray) -> tuple[float, float, float, float]:
    """x_lo, x_hi, y_lo, y_hi of ``points`` (N, 3+), in one pass over the cloud."""
    x_lo = y_lo = math.inf
    x_hi = y_hi = -math.inf
    for start in range(0, points.shape[0], BLOCK_POINTS):
        block = points[start:start + BLOCK_POINTS]
        x, y = block[:, 0], block[:, 1]
        x_lo, x_hi = min(x_lo, float(x.min())), max(x_hi, float(x.max()))
        y_lo, y_hi = min(y_lo, float(y.min())), max(y_hi, float(y.max()))
    return x_lo, x_hi, y_lo, y_hi


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
    # Rectangles of equal area (a tie in exact arithmetic) differ in their last bits with the
    # points' centre: the hull of a whole cloud and of its chunks must choose the same one.
    tied = areas <= areas.min() * (1.0 + ANGLE_TIE_TOLERANCE)
    return float(angles[int(np.argmax(tied))])  # the smallest angle of the tie


def fit_grid(points: np.ndarray, resolution: float, *, frame: str = "axis", known: Survey | None = None,
             checked: bool = False) -> Grid:
    """The grid that encloses ``points`` at ``resolution`` metres per cell.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Coordinates in metres (float64 keeps UTM-size coordinates exact).
    resolution : float
        Cell size in metres.
    frame : {'axis', 'oriented'}
        Axis-aligned or minimum-area rotated bounding rectangle.
    known : Survey, optional
        The points' :func:`survey`, if the caller made it (their extremes and mean are not taken again).
    checked : bool
        The points were checked by :func:`~dftpcc.dem.as_points` already (an encoder's own call).

    Raises
    ------
    InvalidInputError
        Empty or non-finite cloud, a bad resolution, a grid over
        :func:`cell_limit` cells (:data:`MAX_CELLS`, or what the available
        memory holds; the message gives the numbers and the coarsest
        resolution that fits), or coordinates too large for float64 to
        resolve cells of ``resolution``.
    """
    points = points if checked else as_points(points)
    _check_resolution(resolution)
    angle = _min_area_angle(points[:, :2]) if frame == "oriented" else 0.0
    x_lo, x_hi, y_lo, y_hi = _xy_extremes(points) if known is None else known[:4]
    if angle:
        c, s = math.cos(angle), math.sin(angle)
        u = c * points[:, 0] + s * points[:, 1]
        v = -s * points[:, 0] + c * points[:, 1]
        local = (float(u.min()), float(u.max()), float(v.min()), float(v.max()))
    else:  # the paper's frame: no arithmetic over millions of points
        local = (x_lo, x_hi, y_lo, y_hi)
    z0 = float(points[:, 2].mean()) if known is None else known.z_mean
    return _grid_around((x_lo, x_hi, y_lo, y_hi), local, angle, z0, resolution)


def _check_resolution(resolution: float) -> None:
    if not (math.isfinite(resolution) and resolution > 0):
        raise InvalidInputError(f"resolution must be a positive number of metres, got {resolution!r}")


def _grid_around(xy_extremes: tuple[float, float, float, float], local: tuple[float, float, float, float],
                 angle: float, z0: float, resolution: float, check_size: SizeCheck = check_grid_size) -> Grid:
    """The grid of ``resolution`` cells covering ``local`` = (umin, umax, vmin, vmax) in the frame
    rotated by ``angle``; ``xy_extremes`` = (x_lo, x_hi, y_lo, y_hi) for the precision check;
    ``check_size`` refuses a grid too large to build (the limit of a grid held whole by default)."""
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
    check_size(rows_f, cols_f, resolution)
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


def _check_precision(largest: float, resolution: float) -> None:
    """``largest``: the largest |x| or |y| of the cloud, metres."""
    ulp = largest * 2.0**-52
    if ulp > COORDINATE_PRECISION_CELLS * resolution:
        raise InvalidInputError(
            f"coordinates up to {largest:.3g} m are resolved only to {ulp:.2g} m in float64, too coarse for "
            f"{resolution:g} m cells; subtract an offset from x and y first")


def rasterize(points: np.ndarray, grid: Grid, *, aggregate: str = "mean", checked: bool = False) -> DEM:
    """Height of every cell from the points in it.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
    grid : Grid
    aggregate : {'mean', 'median', 'min', 'max'}
    checked : bool
        The points were checked by :func:`~dftpcc.dem.as_points` already.

    Returns
    -------
    DEM
        Heights relative to ``grid.z0`` in metres; 0 in empty cells.
    """
    points = points if checked else as_points(points)
    idx, z = _cells_of(points, grid)
    if aggregate == "median":
        count, heights, mask = _median_heights(idx, z, grid.size)
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


def _median_heights(idx: np.ndarray, z: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points per cell, the median height of each (0 where empty) and the occupancy, of ``size`` cells."""
    from scipy import ndimage  # here, not at import: only the median needs it (30-60 ms to load)

    count = np.bincount(idx, minlength=size)
    mask = count > 0
    heights = np.zeros(size)
    labels = np.flatnonzero(mask)
    heights[labels] = ndimage.median(z, labels=idx, index=labels)
    return count, heights, mask


def check_chunked_aggregate(aggregate: str) -> None:
    """Refuse an aggregate that cannot be gathered chunk by chunk (the median)."""
    if aggregate == "median":
        raise InvalidInputError("aggregate 'median' needs all of a cell's points at once; "
                                "a cloud read in chunks can use mean, min or max")


# -- a grid larger than memory: a cloud gridded band by band on disk -------------------------------

#: Files of :func:`rasterize_bands` in its folder: the map's heights (float64, metres above the grid's
#: z0, 0 where empty), occupancy (bool) and points per cell (int64), row-major, and per band its
#: points' cells (band-local flat index) and heights, then their squared distances to the cell's height.
_HEIGHTS, _MASK, _COUNTS = "heights.f8", "mask.b1", "counts.i8"


@dataclass(frozen=True)
class GriddedBands:
    """A cloud's grid written to ``folder`` by :func:`rasterize_bands`, read back by windows.

    Small and made of paths: a dask worker reads its own windows from the files.

    Attributes
    ----------
    folder : str
    grid : Grid
    counted : int
        Points gridded (the counts' sum).
    gridding_rmse : float
        RMS distance of the points to their cell's height, metres (as a whole grid's ``DEM.gridding_rmse``).
    spread : HeightSpread
    """

    folder: str
    grid: Grid
    counted: int
    gridding_rmse: float
    spread: HeightSpread

    def _window(self, name: str, dtype: type, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        # Mapped for the copy only: the pages read leave this process's memory with the mapping.
        mapped = np.memmap(Path(self.folder) / name, dtype=dtype, mode="r", shape=self.grid.shape)
        try:
            return np.array(mapped[r0:r1, c0:c1])
        finally:
            del mapped

    def heights(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """Heights (metres above ``grid.z0``, 0 where empty) of rows ``r0:r1`` and columns ``c0:c1``."""
        return self._window(_HEIGHTS, np.float64, r0, r1, c0, c1)

    def mask(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """Occupancy (bool) of rows ``r0:r1`` and columns ``c0:c1``."""
        return self._window(_MASK, np.bool_, r0, r1, c0, c1)

    def counts(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """Points (int64) per cell of rows ``r0:r1`` and columns ``c0:c1``."""
        return self._window(_COUNTS, np.int64, r0, r1, c0, c1)


def _smallest_uint(largest: int) -> type:
    return next(t for t in (np.uint8, np.uint16, np.uint32, np.uint64) if largest <= np.iinfo(t).max)


def rasterize_bands(segments: Iterable[Iterable[np.ndarray]], grid: Grid, folder: str | os.PathLike[str], *,
                    band_rows: int, aggregate: str = "mean",
                    on_stage: Callable[..., None] | None = None) -> GriddedBands:
    """:func:`rasterize` (one segment) or :func:`rasterize_chunks` (a segment per chunk) of a grid larger
    than memory, band of ``band_rows`` rows by band, into files in ``folder``: the same heights,
    counts, gridding RMSE and spread, to the bit.

    One pass over the points spills each point's cell and height to its band's files (and its
    band to a file in the points' order); each band is then gridded alone, adding its points
    segment by segment as the whole grid adds chunk by chunk, and written out; last, each
    segment's squared distances are put back in its points' order and summed as the whole
    grid sums them. Memory holds a band's cells and a piece of points (a segment's, for the
    median, which needs a cell's points together and is refused in chunks), not the map; the
    folder holds about 24 bytes a point and 17 a cell (:func:`~dftpcc.limits.check_spill_space`).

    Parameters
    ----------
    segments : iterable of iterables of ndarray (n, 3)
        The points, finite float64, in pieces; each segment is a chunk of :func:`rasterize_chunks`
        (one segment: :func:`rasterize` of them all), whatever its pieces.
    grid : Grid
    folder : path
        An empty folder for the files; the caller removes it.
    band_rows : int
        Rows of a band (a band of tile rows of the coded map).
    aggregate : {'mean', 'median', 'min', 'max'}
    on_stage : callable, optional
        ``on_stage("grid", done)`` as the bands are gridded.
    """
    if aggregate not in ("mean", "median", "min", "max"):
        raise InvalidInputError(f"aggregate must be mean, median, min or max; got {aggregate!r}")
    report = on_stage or (lambda *_: None)
    folder = Path(folder)
    rows, cols = grid.shape
    band_cells = band_rows * cols
    nbands = -(-rows // band_rows)
    cell_type = np.int32 if band_cells <= np.iinfo(np.int32).max else np.int64
    band_type = _smallest_uint(nbands - 1)
    table = []  # points per band, one row per segment
    with open(folder / "bands", "wb") as order_out:
        for segment in segments:
            per_band = np.zeros(nbands, dtype=np.int64)
            for points in segment:
                idx, z = _cells_of(points, grid)
                band = (idx // band_cells).astype(band_type)
                order_out.write(band.tobytes())
                order = np.argsort(band, kind="stable")  # each band's points keep their order
                counts = np.bincount(band, minlength=nbands)
                ends = np.cumsum(counts)
                idx, z, band = idx[order], z[order], band[order]
                idx -= band.astype(np.int64) * band_cells
                for b in np.flatnonzero(counts):
                    part = slice(int(ends[b] - counts[b]), int(ends[b]))
                    with open(folder / f"cells{b}", "ab") as out:
                        out.write(idx[part].astype(cell_type).tobytes())
                    with open(folder / f"z{b}", "ab") as out:
                        out.write(z[part].tobytes())
                per_band += counts
                del idx, z, band, order
            table.append(per_band)
    segment_counts = np.array(table, dtype=np.int64).reshape(len(table), nbands)
    for name in (_HEIGHTS, _MASK, _COUNTS):
        with open(folder / name, "wb") as out:
            out.truncate(grid.size * {_HEIGHTS: 8, _MASK: 1, _COUNTS: 8}[name])
    tolerance_sq = (MULTI_HEIGHT_TOLERANCE_CELLS * grid.resolution) ** 2
    counted = far_cells = 0
    for b in range(nbands):
        report("grid", b / nbands)
        r0, r1 = b * band_rows, min(rows, (b + 1) * band_rows)
        size = (r1 - r0) * cols
        count, heights, mask = _grid_band(folder, b, segment_counts[:, b], size, aggregate, cell_type)
        offset = r0 * cols
        for name, values, width in ((_HEIGHTS, heights, 8), (_MASK, mask, 1), (_COUNTS, count, 8)):
            with open(folder / name, "r+b") as out:
                out.seek(offset * width)
                out.write(np.ascontiguousarray(values).tobytes())
        counted += int(count.sum())
        del count, mask
        far_cells += _band_squares(folder, b, segment_counts[:, b], heights, tolerance_sq, cell_type)
    spread = _SpreadCounter(grid)
    _add_segment_squares(folder, segment_counts, band_type, spread)
    rmse, height_spread = spread.result(far_cells, stacklevel=2)
    report("grid", 1.0)
    return GriddedBands(str(folder), grid, counted, rmse, height_spread)


def _band_points(folder: Path, b: int, counts: np.ndarray, cell_type: type) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Band ``b``'s spilled cells (int64) and heights, one segment at a time (``counts`` points each)."""
    if not counts.any():
        return
    with open(folder / f"cells{b}", "rb") as cells, open(folder / f"z{b}", "rb") as heights:
        for n in counts:
            if n:
                yield (np.fromfile(cells, dtype=cell_type, count=int(n)).astype(np.int64),
                       np.fromfile(heights, dtype=np.float64, count=int(n)))


def _grid_band(folder: Path, b: int, counts: np.ndarray, size: int, aggregate: str,
               cell_type: type) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points per cell, heights and occupancy of band ``b``'s ``size`` cells."""
    if aggregate == "median":  # one segment (refused in chunks): the band's points together
        parts = list(_band_points(folder, b, counts, cell_type))
        if not parts:
            return np.zeros(size, dtype=np.int64), np.zeros(size), np.zeros(size, dtype=bool)
        return _median_heights(parts[0][0], parts[0][1], size)
    cells = _CellHeights(size, aggregate)
    # A segment without points of this band adds zeros to its cells in the whole grid: nothing to add.
    for idx, z in _band_points(folder, b, counts, cell_type):
        cells.add(idx, z)
    return cells.count, cells.heights(), cells.count > 0


def _band_squares(folder: Path, b: int, counts: np.ndarray, heights: np.ndarray, tolerance_sq: float,
                  cell_type: type) -> int:
    """Write band ``b``'s points' squared distances to their cell's height (m², :func:`_distance_sums`'
    arithmetic) in the band's order, drop its spilled points; the cells holding a far point."""
    far = np.zeros(heights.size, dtype=bool)
    with open(folder / f"sq{b}", "wb") as out:
        for idx, z in _band_points(folder, b, counts, cell_type):
            dz = z - heights[idx]
            dz *= dz
            out.write(dz.tobytes())
            far[idx[dz > tolerance_sq]] = True
    for name in (f"cells{b}", f"z{b}"):
        (folder / name).unlink(missing_ok=True)
    return int(np.count_nonzero(far))


def _add_segment_squares(folder: Path, segment_counts: np.ndarray, band_type: type, spread: _SpreadCounter) -> None:
    """Each segment's squared distances back in its points' order (their bands, spilled in that order,
    say from which band file each comes), added to ``spread`` as the whole grid adds a chunk's."""
    taken = np.zeros(segment_counts.shape[1], dtype=np.int64)  # squares read from each band's file
    with open(folder / "bands", "rb") as order_in:
        for per_band in segment_counts:
            band = np.fromfile(order_in, dtype=band_type, count=int(per_band.sum()))
            sq = np.empty(band.size)
            parts = [np.fromfile(folder / f"sq{b}", dtype=np.float64, count=int(per_band[b]), offset=int(taken[b]) * 8)
                     for b in np.flatnonzero(per_band)]
            if parts:
                sq[np.argsort(band, kind="stable")] = np.concatenate(parts)
            taken += per_band
            spread.add_squares(sq)


def _cells_of(points: np.ndarray, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """Flat cell index and height above ``grid.z0`` of the points inside ``grid``."""
    if grid.angle == 0.0:
        found = _axis_cells(points, grid)
        if found is not None:
            return found
    idx = grid.flat_index(points)
    keep = idx >= 0
    if not keep.all():
        idx, points = idx[keep], points[keep]
    return idx, points[:, 2] - grid.z0


@kernels.kernel("axis_cells")
def _axis_cells(points: np.ndarray, grid: Grid) -> tuple[np.ndarray, np.ndarray] | None:
    """:meth:`Grid.flat_index` and the heights above ``grid.z0`` for an axis-aligned grid, block by
    block (the same arithmetic, so the same cells); None when a point lies outside the grid."""
    n = points.shape[0]
    inv_u, inv_v, cols, rows = 1.0 / grid.resolution, 1.0 / grid.dy, grid.cols, grid.rows
    idx, z = np.empty(n, dtype=np.int64), np.empty(n)
    u, v = np.empty(min(n, BLOCK_POINTS)), np.empty(min(n, BLOCK_POINTS))
    for start in range(0, n, BLOCK_POINTS):
        block = points[start:start + BLOCK_POINTS]
        m = block.shape[0]
        bu, bv = u[:m], v[:m]
        np.subtract(block[:, 0], grid.x0, out=bu)
        np.multiply(bu, inv_u, out=bu)
        np.floor(bu, out=bu)
        np.subtract(block[:, 1], grid.y0, out=bv)
        np.multiply(bv, inv_v, out=bv)
        np.floor(bv, out=bv)
        # Four reductions of a cached block instead of four comparisons of the cloud.
        if not (bu.min() >= 0 and bu.max() < cols and bv.min() >= 0 and bv.max() < rows):
            return None
        bv *= cols
        bv += bu  # exact: cell counts are far below 2**53
        idx[start:start + m] = bv
        np.subtract(block[:, 2], grid.z0, out=z[start:start + m])
    return idx, z


class _CellHeights:
    """Count and mean, minimum or maximum height per cell, accumulated over chunks of points."""

    def __init__(self, size: int, aggregate: str):
        if aggregate not in ("mean", "min", "max"):
            raise InvalidInputError(f"aggregate must be mean, median, min or max; got {aggregate!r}")
        self.aggregate, self.size = aggregate, size
        self.count = np.zeros(size, dtype=np.int64)
        fill = {"mean": 0.0, "min": np.inf, "max": -np.inf}[aggregate]
        self.acc = np.full(size, fill)
        self.empty = True  # no point added yet: count and acc hold their starting values

    def add(self, idx: np.ndarray, z: np.ndarray) -> None:
        if self.aggregate == "mean":
            count, total = _cell_sums(idx, z, self.size)
            if self.empty:  # the sums themselves (0 + x is x: a bin's sum is never -0.0), nothing to add
                self.count, self.acc = count, total
            else:
                self.count += count
                self.acc += total
        else:
            self.count += np.bincount(idx, minlength=self.size)
            (np.minimum if self.aggregate == "min" else np.maximum).at(self.acc, idx, z)
        self.empty = False

    def heights(self) -> np.ndarray:
        mask = self.count > 0
        if self.aggregate == "mean":
            return np.divide(self.acc, self.count, out=np.zeros(self.size), where=mask)
        return np.where(mask, self.acc, 0.0)


@kernels.kernel("cell_sums")
def _cell_sums(idx: np.ndarray, z: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Points (int64) and the sum of their heights (float64, metres) in each of ``size`` cells."""
    return np.bincount(idx, minlength=size), np.bincount(idx, weights=z, minlength=size)


class _SpreadCounter:
    """How far points lie from their cell's height, accumulated over chunks: the gridding RMSE
    and the :class:`HeightSpread`."""

    def __init__(self, grid: Grid):
        self.grid = grid
        self.tolerance = MULTI_HEIGHT_TOLERANCE_CELLS * grid.resolution
        self.points = self.far_points = 0
        self.sq_sum = self.far_sq_sum = self.max_sq = 0.0
        self.far_cells: np.ndarray | None = None  # allocated at the first far point (or kernel call)

    def add(self, idx: np.ndarray, z: np.ndarray, heights: np.ndarray) -> None:
        sq_sum, largest, far, far_sum, self.far_cells = _distance_sums(
            idx, z, heights, self.tolerance * self.tolerance, self.far_cells)
        self.points += idx.size
        self.sq_sum += sq_sum
        self.max_sq = max(self.max_sq, largest)
        self.far_points += far
        self.far_sq_sum += far_sum

    def add_squares(self, sq: np.ndarray) -> None:
        """:meth:`add` of one chunk's squared distances ``sq`` (m², in the chunk's order), already taken:
        the same sums, to the bit (a chunk gridded band by band, :mod:`dftpcc.bandgrid`)."""
        far_sq = sq[sq > self.tolerance * self.tolerance]
        self.points += sq.size
        self.sq_sum += float(sq.sum())
        self.max_sq = max(self.max_sq, float(sq.max()) if sq.size else 0.0)
        self.far_points += far_sq.size
        self.far_sq_sum += float(far_sq.sum())

    def result(self, far_cells: int | None = None, stacklevel: int = 3) -> tuple[float, HeightSpread]:
        """The gridding RMSE (metres) and the :class:`HeightSpread`; warns when the spread is large.
        ``far_cells``: the cells holding a far point, when counted elsewhere (band by band)."""
        if far_cells is None:
            far_cells = int(np.count_nonzero(self.far_cells)) if self.far_cells is not None else 0
        spread = HeightSpread(
            tolerance_m=self.tolerance,
            points=self.points,
            unrepresented_points=self.far_points,
            unrepresented_cells=far_cells,
            unrepresented_rmse_m=math.sqrt(self.far_sq_sum / self.far_points) if self.far_points else 0.0,
            max_distance_m=math.sqrt(self.max_sq),
        )
        if spread.fraction >= MULTI_HEIGHT_WARN_FRACTION:
            warnings.warn(spread.describe(), MultiHeightWarning, stacklevel=stacklevel + 1)
        return math.sqrt(self.sq_sum / self.points) if self.points else 0.0, spread

    def dem(self, heights: np.ndarray, mask: np.ndarray, count: np.ndarray) -> DEM:
        """The DEM, with its gridding RMSE and spread; warns when the spread is large."""
        rmse, spread = self.result()
        shape = self.grid.shape
        return DEM(grid=self.grid, heights=heights.reshape(shape), mask=mask.reshape(shape),
                   counts=count.reshape(shape), gridding_rmse=rmse, spread=spread)


@kernels.kernel("distance_sums")
def _distance_sums(idx: np.ndarray, z: np.ndarray, heights: np.ndarray, tolerance_sq: float,
                   far_cells: np.ndarray | None) -> tuple[float, float, int, float, np.ndarray | None]:
    """With ``sq = (z - heights[idx])**2`` (m²): ``sq.sum()``, its maximum (0 for no points), how many
    exceed ``tolerance_sq`` and their sum; and ``far_cells`` (bool per cell, allocated at the first far
    point) with the far points' cells set. numpy's pairwise sums (of the far squares in the points'
    order): their bits reach the file."""
    # Squared distances block by block, so the gathered heights and the differences stay
    # in cache; the sums run over the whole arrays, adding in the same order as one pass would.
    sq = np.empty(idx.size)
    for start in range(0, idx.size, BLOCK_POINTS):
        dz = sq[start:start + BLOCK_POINTS]
        np.subtract(z[start:start + BLOCK_POINTS], heights[idx[start:start + BLOCK_POINTS]], out=dz)
        np.multiply(dz, dz, out=dz)
    largest = float(sq.max()) if sq.size else 0.0
    is_far = sq > tolerance_sq
    far_sq = sq[is_far]
    if far_sq.size:
        if far_cells is None:
            far_cells = np.zeros(heights.size, dtype=bool)
        far_cells[idx[is_far]] = True
    return float(sq.sum()), largest, far_sq.size, float(far_sq.sum()), far_cells


def auto_resolution(points: np.ndarray) -> float:
    """A cell size in metres giving about :data:`AUTO_POINTS_PER_CELL` points per occupied cell.

    The density is measured on the occupied area (a trial grid at the mean
    spacing), so an irregular footprint does not bias it.
    """
    points = as_points(points)
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
        x_lo, x_hi, y_lo, y_hi = _xy_extremes(points)
        e = self.extremes
        self.extremes = [min(e[0], x_lo), max(e[1], x_hi), min(e[2], y_lo), max(e[3], y_hi)]
        if self.hull is not None:
            self.hull = _hull_vertices(np.vstack([self.hull, points[:, :2]]))

    def fit_grid(self, resolution: float, *, frame: str = "axis", check_size: SizeCheck = check_grid_size) -> Grid:
        """:func:`fit_grid` for the cloud summarised here (same grid, up to float round-off); ``check_size``
        refuses a grid too large (default: :func:`~dftpcc.limits.check_grid_size`, a grid held whole)."""
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
        return _grid_around((x_lo, x_hi, y_lo, y_hi), local, angle, self.z_sum / self.count, resolution,
                            check_size)

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



# -- exact sums: the cells of a map that grows -----------------------------------------------------

#: Heights are summed as whole multiples of this (metres) by :class:`CellSums`: exact integer sums,
#: whatever the order of the adds.
HEIGHT_QUANTUM_M = 1e-6
#: Points a cell of :class:`CellSums` may collect: counts are int32.
MAX_CELL_POINTS = 2**31 - 1
#: :meth:`CellSums.add` sorts a scan's points into cells (np.unique) when fewer than the block's cells
#: over this, else counts them in a histogram of the cells: the same cells and order, whichever is cheaper.
HISTOGRAM_SHARE = 8


def lattice_cells(points: np.ndarray, origin: tuple[float, float, float], resolution: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row and column (int64) of each point's cell of a lattice anchored at ``origin`` (x, y: the corner
    of cell (0, 0)), and its height above ``origin[2]`` in whole :data:`HEIGHT_QUANTUM_M` (float64,
    exact: a whole number below 2**53), what :class:`CellSums` adds."""
    ox, oy, oz = origin
    col = np.floor((points[:, 0] - ox) * (1.0 / resolution)).astype(np.int64)
    row = np.floor((points[:, 1] - oy) * (1.0 / resolution)).astype(np.int64)
    quanta = np.rint((points[:, 2] - oz) * (1.0 / HEIGHT_QUANTUM_M))
    return row, col, quanta


@dataclass
class CellSums:
    """Exact per-cell sums over a block of cells, added to scan by scan: the gridder of a growing map.

    :func:`rasterize` sums float heights in the cloud's order; a map grown by scans must not
    depend on their order (a map grown by updates equals the map of all its points added at
    once), so here a cell's heights are summed as int64 multiples of :data:`HEIGHT_QUANTUM_M`,
    exact whatever the order. The sum of squares (float64, m²) only feeds the stated gridding
    error, where float64 rounding is far below the float32 it is written as.
    """

    sum: np.ndarray  # int64, quanta above the lattice's z
    sumsq: np.ndarray  # float64, m²
    count: np.ndarray  # int32, points

    @classmethod
    def empty(cls, shape: tuple[int, int]) -> "CellSums":
        return cls(np.zeros(shape, np.int64), np.zeros(shape), np.zeros(shape, np.int32))

    def part(self, rows: slice, cols: slice) -> "CellSums":
        """A view of some of the cells."""
        return CellSums(self.sum[rows, cols], self.sumsq[rows, cols], self.count[rows, cols])

    def add(self, cells: np.ndarray, quanta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Add points at flat cell indices ``cells`` with heights ``quanta`` (see :func:`lattice_cells`).

        Returns
        -------
        seen : ndarray of int
            The flat cells the points fell in, ascending.
        new : ndarray of bool
            Which of them were empty before.
        moved : ndarray of bool
            Which of them changed their mean height (the new ones included).
        """
        size = self.count.size
        # A scan sees a few percent of a block's cells: sum per cell seen, and update only those.
        if cells.size >= size // HISTOGRAM_SHARE:
            # The cells seen, ascending, and each point's index among them (np.unique's, without
            # its sort): a histogram of the block's cells, cheaper than sorting many points.
            seen = np.flatnonzero(np.bincount(cells, minlength=size))
            rank = np.empty(size, dtype=np.intp)
            rank[seen] = np.arange(seen.size)
            where = rank[cells]
        else:
            seen, where = np.unique(cells, return_inverse=True)
        added = np.bincount(where, minlength=seen.size)
        total, sums, sumsq = self.count.reshape(-1), self.sum.reshape(-1), self.sumsq.reshape(-1)
        before, before_sum = total[seen], sums[seen]
        if int(before.max(initial=0)) + int(added.max()) > MAX_CELL_POINTS:
            raise InvalidInputError(f"a cell would hold more than {MAX_CELL_POINTS:,} points")
        # A float64 sum of whole numbers is exact below 2**53 quanta (9,000 km) per scan and cell.
        after_sum = before_sum + np.bincount(where, weights=quanta, minlength=seen.size).astype(np.int64)
        after = before + added.astype(np.int32)
        sums[seen], total[seen] = after_sum, after
        metres = quanta * HEIGHT_QUANTUM_M  # the heights summed, so squares and sums agree
        sumsq[seen] += np.bincount(where, weights=metres * metres, minlength=seen.size)
        new = before == 0
        moved = new | (np.divide(before_sum, before, out=np.zeros(seen.size), where=~new)
                       != np.divide(after_sum, after))
        return seen, new, moved

    def heights(self) -> tuple[np.ndarray, np.ndarray]:
        """Each cell's mean height (metres above the lattice's z; 0 where empty) and whether it is occupied."""
        occupied = self.count > 0
        # An empty cell's sum is 0: 0 / 1 gives its 0, and the others the same quotient as a
        # division masked to them, without the mask's cost.
        mean = self.sum / np.maximum(self.count, 1)
        return mean * HEIGHT_QUANTUM_M, occupied

    def squared_spread(self) -> float:
        """Sum over the points of the squared distance to their cell's mean height, m²."""
        occupied = self.count > 0
        if occupied.all():  # the occupied cells in row-major order are every cell: no copies
            total, sums, sumsq = self.count.ravel(), self.sum.ravel(), self.sumsq.ravel()
        else:
            total, sums, sumsq = self.count[occupied], self.sum[occupied], self.sumsq[occupied]
        mean_sum = sums * HEIGHT_QUANTUM_M
        return float(np.maximum(sumsq - mean_sum * mean_sum / total, 0.0).sum())
