"""Grid stage: a point cloud becomes a Digital Elevation Model (DEM).

As in the paper, points are projected on a horizontal plane at the height of
their centroid, inside the minimum bounding rectangle (axis-aligned, or
optionally rotated to minimum area); each cell of ``resolution`` metres holds
one height. Cells no point fell in are recorded in an occupancy mask and
filled smoothly so the transform sees no artificial cliff.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .errors import InvalidInputError

__all__ = [
    "Grid",
    "DEM",
    "MAX_CELLS",
    "fit_grid",
    "rasterize",
    "fill_empty",
    "fit_plane",
    "auto_resolution",
    "gridding_rmse",
]

#: Largest grid dftpcc builds in memory (cells). A float64 DEM this size is
#: 800 MB and the transform needs a few such arrays.
MAX_CELLS = 100_000_000

#: Margin, in cells, around a rotated grid (see fit_grid).
ROTATED_MARGIN = 1e-6

#: ``auto`` resolution aims at this many points per occupied cell.
AUTO_POINTS_PER_CELL = 4.0


@dataclass(frozen=True)
class Grid:
    """Geometry of a DEM: where cell (row, col) lies in the original frame.

    A point ``p`` has local coordinates ``R(-angle) @ (p.xy - origin)``;
    column ``floor(u / resolution)``, row ``floor(v / resolution)``. Row 0 is
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
        Cell size, metres.
    rows, cols : int
        Shape of the DEM.
    angle : float
        Rotation of the grid's u axis from the x axis, radians.
    """

    x0: float
    y0: float
    z0: float
    resolution: float
    rows: int
    cols: int
    angle: float = 0.0

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
        inv = 1.0 / self.resolution
        return np.floor(v * inv).astype(np.int64), np.floor(u * inv).astype(np.int64)

    def flat_index(self, xy: np.ndarray) -> np.ndarray:
        """Row-major cell index of each point, -1 where it lies outside the grid."""
        r, c = self.cell_of(xy)
        inside = (r >= 0) & (r < self.rows) & (c >= 0) & (c < self.cols)
        return np.where(inside, r * self.cols + c, -1)

    def centres(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World x, y of the centres of cells ``(rows, cols)``."""
        u = (cols + 0.5) * self.resolution
        v = (rows + 0.5) * self.resolution
        if self.angle == 0.0:
            return self.x0 + u, self.y0 + v
        c, s = self._rotation()
        return self.x0 + c * u - s * v, self.y0 + s * u + c * v


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
    """

    grid: Grid
    heights: np.ndarray
    mask: np.ndarray
    counts: np.ndarray | None = None
    gridding_rmse: float | None = None


def _check_points(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise InvalidInputError(f"points must have shape (N, 3), got {points.shape}")
    if points.shape[0] == 0:
        raise InvalidInputError("the point cloud is empty")
    points = np.asarray(points[:, :3], dtype=np.float64)
    if not np.isfinite(points).all():
        bad = int((~np.isfinite(points).all(axis=1)).sum())
        raise InvalidInputError(f"{bad} point(s) have NaN or infinite coordinates; drop them first")
    return points


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
        Empty or non-finite cloud, a bad resolution, or a grid over
        :data:`MAX_CELLS` cells.
    """
    points = _check_points(points)
    if not (math.isfinite(resolution) and resolution > 0):
        raise InvalidInputError(f"resolution must be a positive number of metres, got {resolution!r}")
    angle = _min_area_angle(points[:, :2]) if frame == "oriented" else 0.0
    c, s = math.cos(angle), math.sin(angle)
    u = c * points[:, 0] + s * points[:, 1]
    v = -s * points[:, 0] + c * points[:, 1]
    # A rotated frame recomputes local coordinates from a rotated origin; a
    # margin of a millionth of a cell keeps round-off from pushing the
    # extreme points outside the grid.
    margin = ROTATED_MARGIN * resolution if angle else 0.0
    umin, vmin = float(u.min()) - margin, float(v.min()) - margin
    cols = int(math.floor((float(u.max()) + margin - umin) / resolution)) + 1
    rows = int(math.floor((float(v.max()) + margin - vmin) / resolution)) + 1
    if rows * cols > MAX_CELLS:
        raise InvalidInputError(
            f"a {rows} x {cols} grid ({rows * cols:,} cells) at {resolution} m exceeds the "
            f"{MAX_CELLS:,}-cell limit; use a coarser resolution"
        )
    x0, y0 = c * umin - s * vmin, s * umin + c * vmin
    return Grid(x0=x0, y0=y0, z0=float(points[:, 2].mean()), resolution=float(resolution),
                rows=rows, cols=cols, angle=angle)


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
    return DEM(grid=grid, heights=heights.reshape(grid.shape), mask=mask.reshape(grid.shape),
               counts=count.reshape(grid.shape), gridding_rmse=float(np.sqrt(np.mean(dz * dz))))


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
    design = np.column_stack([np.ones(rows.size), cols.astype(float), rows.astype(float)])
    coef, *_ = np.linalg.lstsq(design, dem.heights[rows, cols], rcond=None)
    return float(coef[0]), float(coef[1]), float(coef[2])


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


def _push_pull(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
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
    up = ndimage.zoom(coarse, 2, order=1, mode="nearest", grid_mode=True)[:r, :c]
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
    if area <= 0 or points.shape[0] < 2:
        raise InvalidInputError("cannot choose a resolution automatically: the points span no area")
    trial = math.sqrt(area / points.shape[0])
    cols = np.floor((xy[:, 0] - xy[:, 0].min()) / trial).astype(np.int64)
    rows = np.floor((xy[:, 1] - xy[:, 1].min()) / trial).astype(np.int64)
    occupied = np.unique(rows * (int(cols.max()) + 1) + cols).size
    density = points.shape[0] / (occupied * trial * trial)
    return float(math.sqrt(AUTO_POINTS_PER_CELL / density))
