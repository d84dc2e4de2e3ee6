"""A simulated rover on real terrain: a spinning lidar ray-cast over a DEM, written as a ROS 2 bag.

The terrain is a :class:`Surface`: the bilinear interpolation of a DEM's
cells, in a *local* frame (metres): x, y from the corner of the DEM's cell
(0, 0), z relative to the DEM's projection plane (its ``grid.z0``), all
optionally multiplied by one ``scale`` (a 48 m lunar DEM at ``scale=1/48``
becomes a rover-sized terrain of 1 m cells with the same slopes). Every
coordinate this module produces (poses, bag messages) is in that local frame,
so numbers stay small and registration keeps its precision; divide by
``scale`` and add the DEM's grid origin (``x0``, ``y0``, ``z0``) to go back to
the map's own coordinates (:func:`dftpcc.experiments.relocalize.surface_dem`
returns that transform).

:func:`cast_scan` marches every ray of a scan at once over the surface and
refines each crossing by bisection; :func:`drive` turns waypoints into timed
poses (the sensor rides ``mount_height`` above the ground, rolled and pitched
with the terrain); :func:`write_bag` writes the scans and odometry. Scans are
instantaneous (no motion distortion within a sweep). Bag conventions:
``/points`` ``sensor_msgs/msg/PointCloud2`` in frame ``lidar`` (x, y, z
float32, unorganized, dense), ``/odom`` ``nav_msgs/msg/Odometry`` ground truth
(frame ``map``, child ``lidar``: a map point is ``R @ p_lidar + t``),
``/odom_noisy`` the same with drifting wheel-odometry noise, ``/tf`` the
ground-truth ``map -> lidar`` transform; odometry at :data:`ODOM_RATE_HZ`.
"""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..dem import DEM
from .._optional import import_optional, install_hint
from ..errors import InvalidInputError, MissingDependencyError

__all__ = ["Surface", "Lidar", "LIDARS", "Drive", "drive", "loop_waypoints", "sensor_pose", "cast_scan",
           "scan_at", "odometry_noise", "write_bag", "check_map_size", "main", "ODOM_RATE_HZ", "SCAN_RATE_HZ", "ROS_INSTALL_HINT"]

#: Odometry messages per second in a bag.
ODOM_RATE_HZ = 50.0
#: Lidar revolutions (scans) per second.
SCAN_RATE_HZ = 10.0
#: Rover speed in metres per second (a fast planetary rover, a slow field robot).
ROVER_SPEED = 0.5
#: March step along a ray near the ground, in cells: where the slope bound
#: would allow less, the ray steps this far and a crossing is found by the
#: change of sign, so only crests thinner than half a cell can be jumped over.
MARCH_STEP_CELLS = 0.5
#: Radii (cells) of the height ceilings a ray may skip over in one step when it
#: is above the highest ground that near: coarse first, 32 cells, then 8, then 2.
CEILING_CELLS = (32, 8, 2)
#: Bisection steps refining each crossing: the bracket shrinks from half a
#: cell to 2**-BISECTIONS of it (under 0.1 mm on 1 m cells) before a last
#: linear interpolation.
BISECTIONS = 14
#: Half the wheelbase, metres: the ground under the rover is sampled this far
#: ahead, behind and to the sides to set roll and pitch.
HALF_WHEELBASE = 0.5
#: Wheel-odometry noise of ``/odom_noisy``: translation error per metre driven
#: (1 sigma, as a fraction) and heading error per square-root metre (radians).
ODOM_TRANSLATION_NOISE = 0.02
ODOM_HEADING_NOISE = math.radians(0.5)
#: Cells whose sides differ by less than this fraction are taken as square
#: (Kepler's are 47.679 x 47.682 m: 0.05 cells of drift across its 804 rows).
SQUARE_CELL_TOLERANCE = 1e-3
ROS_INSTALL_HINT = install_hint("ros")
#: Nanoseconds per second (ROS stamps).
NS = 1_000_000_000


@dataclass(frozen=True)
class Surface:
    """A terrain: the bilinear interpolation of a grid of heights, in a local frame (metres).

    Attributes
    ----------
    heights : ndarray, shape (rows, cols), float64
        Height of each node, metres; NaN where the DEM has no data. Node
        (i, j) lies at x = (j + 0.5) * spacing, y = (i + 0.5) * spacing (row 0
        south), so nodes are the DEM's cell centres.
    spacing : float
        Distance between nodes, metres.
    """

    heights: np.ndarray
    spacing: float
    slope: float = field(init=False, repr=False)
    ceilings: tuple[np.ndarray, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        h = np.asarray(self.heights, dtype=np.float64)
        if h.ndim != 2 or min(h.shape) < 2:
            raise InvalidInputError(f"a surface needs at least 2 x 2 nodes, got shape {h.shape}")
        if not (math.isfinite(self.spacing) and self.spacing > 0):
            raise InvalidInputError(f"node spacing must be a positive number of metres, got {self.spacing!r}")
        if not np.isfinite(h).any():
            raise InvalidInputError("the surface has no valid height")
        object.__setattr__(self, "heights", h)
        # A bilinear patch is steepest at a corner, where its gradient is made
        # of its edge differences: the largest of them bounds every slope,
        # which bounds how far a ray may march without passing the ground.
        with np.errstate(invalid="ignore"):
            gx = np.nanmax(np.abs(np.diff(h, axis=1)), initial=0.0) / self.spacing
            gy = np.nanmax(np.abs(np.diff(h, axis=0)), initial=0.0) / self.spacing
        object.__setattr__(self, "slope", float(math.hypot(gx, gy)))
        # Highest node within CEILING_CELLS[k] + 1 nodes of each node: no point of the surface within
        # CEILING_CELLS[k] cells of a node lies above it (a bilinear patch stays below its corners).
        from scipy import ndimage

        top = np.where(np.isfinite(h), h, -np.inf)
        object.__setattr__(self, "ceilings", tuple(
            ndimage.maximum_filter(top, size=2 * (r + 1) + 1, mode="nearest") for r in CEILING_CELLS))

    @classmethod
    def from_dem(cls, dem: DEM, *, scale: float = 1.0) -> "Surface":
        """The surface of a DEM's occupied cells, heights about ``grid.z0``, every length times ``scale``.

        Raises
        ------
        InvalidInputError
            A rotated grid or cells whose sides differ by more than
            :data:`SQUARE_CELL_TOLERANCE` (not supported), or a bad scale.
            Nearly square cells take the x spacing.
        """
        g = dem.grid
        if g.angle != 0.0 or (g.resolution_y is not None
                              and not math.isclose(g.resolution_y, g.resolution, rel_tol=SQUARE_CELL_TOLERANCE)):
            raise InvalidInputError("the simulated rover needs a DEM with square, axis-aligned cells")
        if not (math.isfinite(scale) and scale > 0):
            raise InvalidInputError(f"scale must be a positive number, got {scale!r}")
        heights = np.where(dem.mask, dem.heights, np.nan) * scale
        return cls(heights, g.resolution * scale)

    @property
    def shape(self) -> tuple[int, int]:
        return self.heights.shape  # type: ignore[return-value]

    @property
    def extent(self) -> tuple[float, float]:
        """Width (x) and depth (y) of the region covered by nodes, metres."""
        rows, cols = self.shape
        return (cols - 1) * self.spacing, (rows - 1) * self.spacing

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Whether points lie between the outer nodes (where :meth:`height` is defined)."""
        lo = 0.5 * self.spacing
        w, d = self.extent
        return (x >= lo) & (x <= lo + w) & (y >= lo) & (y <= lo + d)

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear height at (x, y), metres; NaN outside the nodes or next to a node without data."""
        rows, cols = self.shape
        u = np.asarray(x, dtype=np.float64) * (1.0 / self.spacing) - 0.5
        v = np.asarray(y, dtype=np.float64) * (1.0 / self.spacing) - 0.5
        outside = ~((u >= 0) & (u <= cols - 1) & (v >= 0) & (v <= rows - 1))  # NaN coordinates too
        # The last node belongs to the last patch; clipped indices keep the gather in bounds
        # (points outside are NaN below).
        j = np.clip(np.floor(u), 0, cols - 2)
        i = np.clip(np.floor(v), 0, rows - 2)
        fu = u - j
        fv = v - i
        idx = i.astype(np.int64) * cols + j.astype(np.int64)
        flat = self.heights.ravel()
        h00 = flat.take(idx)
        h01 = flat.take(idx + 1)
        h10 = flat.take(idx + cols)
        h11 = flat.take(idx + cols + 1)
        low = h00 + fu * (h01 - h00)
        high = h10 + fu * (h11 - h10)
        out = low + fv * (high - low)
        if outside.any():
            out = np.where(outside, np.nan, out)
        return out

    def points(self) -> np.ndarray:
        """The nodes with data as points, shape (n, 3), local metres: the DEM's own cells as a map."""
        i, j = np.nonzero(np.isfinite(self.heights))
        return np.column_stack([(j + 0.5) * self.spacing, (i + 0.5) * self.spacing, self.heights[i, j]])

    def sample(self, spacing: float, *, window: tuple[float, float, float, float] | None = None) -> np.ndarray:
        """The surface sampled on a square lattice of ``spacing`` metres: shape (n, 3), local metres.

        ``window`` (x_lo, x_hi, y_lo, y_hi) limits the samples to a region; samples
        where the surface is undefined are left out.
        """
        lo = 0.5 * self.spacing
        w, d = self.extent
        x_lo, x_hi, y_lo, y_hi = window if window is not None else (lo, lo + w, lo, lo + d)
        # Samples sit at the centres of a lattice of `spacing` cells inside the window.
        xs = np.arange(x_lo + 0.5 * spacing, x_hi, spacing)
        ys = np.arange(y_lo + 0.5 * spacing, y_hi, spacing)
        gx, gy = np.meshgrid(xs, ys)
        z = self.height(gx.ravel(), gy.ravel())
        keep = np.isfinite(z)
        return np.column_stack([gx.ravel()[keep], gy.ravel()[keep], z[keep]])


@dataclass(frozen=True)
class Lidar:
    """A spinning multi-beam lidar.

    Attributes
    ----------
    beams : int
        Lasers, evenly spread from ``elevation_min_deg`` to ``elevation_max_deg``.
    elevation_min_deg, elevation_max_deg : float
        Vertical field of view, degrees above the sensor's horizontal plane.
    azimuth_step_deg : float
        Horizontal angle between two firings, degrees.
    max_range, min_range : float
        Returns beyond or before these ranges are dropped, metres.
    range_noise : float
        Standard deviation of the Gaussian range noise, metres.
    mount_height : float
        Height of the sensor above the ground under the rover, metres.
    """

    beams: int = 16
    elevation_min_deg: float = -15.0
    elevation_max_deg: float = 15.0
    azimuth_step_deg: float = 0.2
    max_range: float = 100.0
    min_range: float = 0.5
    range_noise: float = 0.02
    mount_height: float = 1.5

    def directions(self) -> np.ndarray:
        """Unit ray directions in the sensor frame, shape (beams * firings, 3), beam-major."""
        elev = np.radians(np.linspace(self.elevation_min_deg, self.elevation_max_deg, self.beams))
        az = np.radians(np.arange(0.0, 360.0, self.azimuth_step_deg))
        e, a = np.meshgrid(elev, az, indexing="ij")
        return np.column_stack([(np.cos(e) * np.cos(a)).ravel(), (np.cos(e) * np.sin(a)).ravel(), np.sin(e).ravel()])


#: Sensors by name: beams, field of view, firing step and range noise of the
#: Velodyne VLP-16, HDL-32E and HDL-64E data sheets (at 10 Hz).
LIDARS: dict[str, Lidar] = {
    "vlp16": Lidar(16, -15.0, 15.0, 0.2, 100.0, 0.5, 0.03),
    "hdl32": Lidar(32, -30.67, 10.67, 0.16, 100.0, 0.5, 0.02),
    "hdl64": Lidar(64, -24.9, 2.0, 0.17, 120.0, 0.5, 0.02),
}


def _rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll): sensor axes in the map frame."""
    cr, sr, cp, sp, cy, sy = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def sensor_pose(surface: Surface, x: float, y: float, yaw: float, *, mount_height: float = 1.5) -> np.ndarray:
    """The 4 x 4 pose (map <- lidar) of a rover at (x, y) heading ``yaw`` (radians).

    The rover's attitude follows the ground: pitch and roll from the heights
    :data:`HALF_WHEELBASE` ahead, behind and to each side; the sensor sits
    ``mount_height`` metres above the ground along the rover's up axis.

    Raises
    ------
    InvalidInputError
        The ground under the rover has no data (NaN) or lies outside the map.
    """
    c, s = math.cos(yaw), math.sin(yaw)
    d = HALF_WHEELBASE
    px = np.array([x, x + d * c, x - d * c, x - d * s, x + d * s])
    py = np.array([y, y + d * s, y - d * s, y + d * c, y - d * c])
    h = surface.height(px, py)
    if not np.isfinite(h).all():
        raise InvalidInputError(f"no valid ground under the rover at local ({x:.2f}, {y:.2f}) m: the trajectory "
                                f"crosses cells without data or leaves the map")
    pitch = -math.atan2(h[1] - h[2], 2 * d)  # nose up is a negative rotation about y
    roll = math.atan2(h[3] - h[4], 2 * d)
    pose = np.eye(4)
    pose[:3, :3] = _rotation(roll, pitch, yaw)
    pose[:3, 3] = (x, y, h[0])
    pose[:3, 3] += pose[:3, 2] * mount_height
    return pose


def cast_scan(surface: Surface, pose: np.ndarray, lidar: Lidar, *,
              rng: np.random.Generator | None = None) -> np.ndarray:
    """Ray-cast one lidar revolution from ``pose`` over ``surface``: the returns in the sensor frame.

    Every ray marches at once: a ray above the ground advances by the
    largest step that cannot pass under it (its height above the ground over
    the surface's slope bound, or :data:`CEILING_CELLS` when it flies above the
    highest ground that near), but at least :data:`MARCH_STEP_CELLS` cells; the
    first step that ends below the ground brackets the crossing, which
    :data:`BISECTIONS` halvings and a linear interpolation refine. Rays that
    climb faster than the steepest slope, leave the map, meet a cell without
    data or reach ``lidar.max_range`` return nothing.

    Parameters
    ----------
    surface : Surface
    pose : ndarray, shape (4, 4)
        Map <- lidar transform, local metres.
    lidar : Lidar
    rng : numpy.random.Generator, optional
        Draws the range noise (``lidar.range_noise``); None: noise-free ranges.

    Returns
    -------
    ndarray, shape (n, 3), float64
        Returns in the sensor frame, metres, in firing order.
    """
    dirs_s = lidar.directions()
    rot, origin = pose[:3, :3], pose[:3, 3]
    dirs = dirs_s @ rot.T
    n = dirs.shape[0]
    horiz = np.hypot(dirs[:, 0], dirs[:, 1])
    # How fast the ray's height above the ground can fall per metre along it.
    closing = surface.slope * horiz - dirs[:, 2]
    min_step = MARCH_STEP_CELLS * surface.spacing
    t_hit = np.full(n, np.nan)
    active = np.flatnonzero(closing > 0)
    t = np.full(active.size, lidar.min_range)
    gap = origin[2] + t * dirs[active, 2] - surface.height(origin[0] + t * dirs[active, 0],
                                                           origin[1] + t * dirs[active, 1])
    found: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    # A ray starting below the ground (a sensor inside a cliff) returns nothing.
    ok = np.isfinite(gap) & (gap > 0)
    active, t, gap = active[ok], t[ok], gap[ok]
    rows, cols = surface.shape
    ceilings = [c.ravel() for c in surface.ceilings]
    while active.size:
        d = dirs[active]
        # The slope bound makes gap / closing a step that cannot pass under the
        # ground; near it (a grazing ray), a fixed step and the sign test take over.
        step = np.maximum(gap / closing[active], min_step)
        # A ray above the highest ground within R cells (and still above it after
        # descending for R cells of horizontal travel) skips those R cells at once.
        x, y, z = origin[0] + t * d[:, 0], origin[1] + t * d[:, 1], origin[2] + t * d[:, 2]
        node = (np.clip(np.rint(y * (1.0 / surface.spacing) - 0.5), 0, rows - 1).astype(np.int64) * cols
                + np.clip(np.rint(x * (1.0 / surface.spacing) - 0.5), 0, cols - 1).astype(np.int64))
        flat = np.maximum(horiz[active], 1e-9)
        fall = np.maximum(-d[:, 2], 0.0)
        for radius, ceiling in zip(CEILING_CELLS, ceilings):
            reach = radius * surface.spacing / flat
            safe = z - fall * reach > ceiling.take(node)
            step = np.where(safe & (reach > step), reach, step)
        t_new = t + step
        gap_new = origin[2] + t_new * d[:, 2] - surface.height(origin[0] + t_new * d[:, 0], origin[1] + t_new * d[:, 1])
        hit = gap_new <= 0
        if hit.any():
            found.append((active[hit], t[hit], t_new[hit]))
        # NaN gaps (off the map, or no data) and rays past the range end here.
        keep = ~hit & np.isfinite(gap_new) & (t_new < lidar.max_range)
        active, t, gap = active[keep], t_new[keep], gap_new[keep]
    if found:
        rays = np.concatenate([f[0] for f in found])
        lo_t = np.concatenate([f[1] for f in found])
        hi_t = np.concatenate([f[2] for f in found])
        d = dirs[rays]

        def gap_at(tt: np.ndarray) -> np.ndarray:
            return origin[2] + tt * d[:, 2] - surface.height(origin[0] + tt * d[:, 0], origin[1] + tt * d[:, 1])

        for _ in range(BISECTIONS):
            mid = 0.5 * (lo_t + hi_t)
            g = gap_at(mid)
            below = ~(g > 0)  # NaN (a data gap inside the bracket) counts as ground
            hi_t = np.where(below, mid, hi_t)
            lo_t = np.where(below, lo_t, mid)
        g_lo, g_hi = gap_at(lo_t), gap_at(hi_t)
        with np.errstate(invalid="ignore", divide="ignore"):
            frac = np.where(np.isfinite(g_hi) & (g_lo - g_hi > 0), g_lo / (g_lo - g_hi), 0.5)
        t_hit[rays] = lo_t + np.clip(frac, 0.0, 1.0) * (hi_t - lo_t)
    ranges = t_hit
    if rng is not None and lidar.range_noise > 0:
        ranges = ranges + rng.normal(0.0, lidar.range_noise, n)
    keep = np.isfinite(ranges) & (ranges >= lidar.min_range) & (ranges <= lidar.max_range)
    return dirs_s[keep] * ranges[keep, None]


@dataclass(frozen=True)
class Drive:
    """Timed poses of a drive.

    Attributes
    ----------
    times : ndarray, shape (k,)
        Seconds from the start.
    poses : ndarray, shape (k, 4, 4)
        Map <- lidar transforms, local metres.
    distance : float
        Metres driven.
    clipped : bool
        True when the drive was cut where the waypoints left the map.
    """

    times: np.ndarray
    poses: np.ndarray
    distance: float
    clipped: bool = False


def loop_waypoints(surface: Surface, *, radius: float | None = None, points: int = 72,
                   centre: tuple[float, float] | None = None) -> np.ndarray:
    """Waypoints of a closed circle, local metres, shape (points + 1, 2).

    Default: centred on the map, radius a quarter of its smaller side.
    """
    w, d = surface.extent
    lo = 0.5 * surface.spacing
    cx, cy = centre if centre is not None else (lo + 0.5 * w, lo + 0.5 * d)
    r = 0.25 * min(w, d) if radius is None else radius
    a = np.linspace(0.0, 2 * math.pi, points + 1)
    return np.column_stack([cx + r * np.cos(a), cy + r * np.sin(a)])


def drive(surface: Surface, waypoints: Sequence[Sequence[float]] | np.ndarray, *, speed: float = ROVER_SPEED,
          rate: float = ODOM_RATE_HZ, lidar: Lidar | None = None, clip: bool = False) -> Drive:
    """Poses along the polyline ``waypoints`` at ``speed`` m/s, ``rate`` poses per second.

    The rover faces along the segment it drives (yaw), rides the ground (roll,
    pitch: :func:`sensor_pose`) with the sensor ``lidar.mount_height`` above it.

    Parameters
    ----------
    clip : bool
        A drive that leaves the map (or crosses cells without data) is refused;
        with ``clip`` it is cut at the last pose on valid ground instead
        (:attr:`Drive.clipped` says so).

    Raises
    ------
    InvalidInputError
        Fewer than two distinct waypoints, a bad speed or rate, the map
        smaller than the sensor's range, a drive that leaves the map (unless
        ``clip``), or no valid ground at its start.
    """
    lidar = lidar or LIDARS["vlp16"]
    wp = np.asarray(waypoints, dtype=np.float64)
    if wp.ndim != 2 or wp.shape[1] != 2 or wp.shape[0] < 2 or not np.isfinite(wp).all():
        raise InvalidInputError(f"waypoints must be an (n >= 2, 2) array of finite local metres, got shape {wp.shape}")
    for name, value in (("speed", speed), ("rate", rate)):
        if not (math.isfinite(value) and value > 0):
            raise InvalidInputError(f"{name} must be a positive number, got {value!r}")
    check_map_size(surface, lidar)
    seg = np.diff(wp, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    keep = length > 0
    seg, length, starts = seg[keep], length[keep], wp[:-1][keep]
    if not length.size:
        raise InvalidInputError("the waypoints do not move: give at least two distinct points")
    total = float(length.sum())
    s = np.arange(0.0, total + 1e-9, speed / rate)
    cum = np.concatenate([[0.0], np.cumsum(length)])
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, length.size - 1)
    frac = (s - cum[k]) / length[k]
    xy = starts[k] + frac[:, None] * seg[k]
    yaw = np.arctan2(seg[k, 1], seg[k, 0])
    # The ground the wheels touch must exist: the rover's footprint, not only its centre.
    r = HALF_WHEELBASE
    ok = np.ones(s.size, bool)
    for dx, dy in ((0, 0), (r, 0), (-r, 0), (0, r), (0, -r)):
        ok &= np.isfinite(surface.height(xy[:, 0] + dx, xy[:, 1] + dy))
    clipped = False
    if not ok.all():
        first_bad = int(np.argmin(ok))
        where = xy[first_bad]
        if not clip or first_bad == 0:
            what = "starts" if first_bad == 0 else "leaves the map or crosses cells without data"
            raise InvalidInputError(
                f"the trajectory {what} at local ({where[0]:.1f}, {where[1]:.1f}) m after {s[first_bad]:.1f} m "
                f"(map: {surface.extent[0]:.1f} x {surface.extent[1]:.1f} m)"
                + ("" if first_bad == 0 else "; clip=True (--clip) stops the drive there instead"))
        xy, yaw, s = xy[:first_bad], yaw[:first_bad], s[:first_bad]
        clipped = True
    poses = np.stack([sensor_pose(surface, float(x), float(y), float(a), mount_height=lidar.mount_height)
                      for (x, y), a in zip(xy, yaw)])
    return Drive(times=s / speed, poses=poses, distance=float(s[-1]) if s.size else 0.0, clipped=clipped)


def check_map_size(surface: Surface, lidar: Lidar) -> None:
    """Refuse a map smaller than the sensor's range: most of its rays would leave it.

    Raises
    ------
    InvalidInputError
        The map's smaller side is shorter than ``lidar.max_range``.
    """
    side = min(surface.extent)
    if side < lidar.max_range:
        raise InvalidInputError(
            f"the map ({surface.extent[0]:.1f} x {surface.extent[1]:.1f} m) is smaller than the simulated lidar's "
            f"range of {lidar.max_range:g} m: most rays would leave it; use a larger map, a shorter-range sensor "
            f"(max_range) or scale the DEM up")


def scan_at(surface: Surface, pose: np.ndarray, lidar: Lidar, rng: np.random.Generator) -> np.ndarray:
    """:func:`cast_scan` with noise; refuses a pose from which no ray reaches the ground.

    Raises
    ------
    InvalidInputError
        The scan is empty.
    """
    pts = cast_scan(surface, pose, lidar, rng=rng)
    if not pts.shape[0]:
        raise InvalidInputError(f"no lidar return at local ({pose[0, 3]:.1f}, {pose[1, 3]:.1f}) m: no valid "
                                f"ground within {lidar.max_range:g} m")
    return pts


def _exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w`` (radians), Rodrigues' formula."""
    theta = float(np.linalg.norm(w))
    if theta < 1e-12:
        return np.eye(3)
    k = w / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * kx + (1 - math.cos(theta)) * kx @ kx


def odometry_noise(poses: np.ndarray, rng: np.random.Generator, *,
                   translation: float = ODOM_TRANSLATION_NOISE, heading: float = ODOM_HEADING_NOISE) -> np.ndarray:
    """Dead-reckoned poses: the true increments between poses, each perturbed, chained from the first pose.

    Each increment's translation gets Gaussian noise of ``translation`` times
    its length (per axis) and its rotation a heading error of ``heading``
    radians times the root of its length, so the error grows like a random walk.

    Returns
    -------
    ndarray, shape (k, 4, 4)
    """
    out = np.empty_like(poses)
    out[0] = poses[0]
    for k in range(1, poses.shape[0]):
        inc = np.linalg.solve(poses[k - 1], poses[k])
        step = float(np.linalg.norm(inc[:3, 3]))
        noisy = inc.copy()
        noisy[:3, 3] += rng.normal(0.0, translation * step, 3)
        noisy[:3, :3] = _exp_so3(np.array([0.0, 0.0, rng.normal(0.0, heading * math.sqrt(step))])) @ inc[:3, :3]
        out[k] = out[k - 1] @ noisy
    return out


def _quaternion(rot: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(rot).as_quat()
    return float(x), float(y), float(z), float(w)


def _rosbags() -> tuple[type, object]:
    rosbag2 = import_optional("rosbags.rosbag2", "ros", needed_for="writing ROS bags")
    typesys = import_optional("rosbags.typesys", "ros", needed_for="writing ROS bags")
    return rosbag2.Writer, typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)


def write_bag(path: str | os.PathLike[str], surface: Surface, route: Drive, lidar: Lidar, *,
              scan_rate: float = SCAN_RATE_HZ, seed: int = 0, on_scan: Callable[[int], None] | None = None) -> dict[str, float]:
    """Write a ROS 2 bag (sqlite3) of the drive: scans on ``/points``, odometry and ``/tf``.

    Odometry (``/odom`` true, ``/odom_noisy`` dead-reckoned with
    :func:`odometry_noise`) at every pose of ``route`` (its rate), with ``/tf``;
    a scan every ``1 / scan_rate`` seconds, stamped with the time of the
    pose it was cast from. Stamps start at 0 s. The bag is written to a
    temporary folder and moved to ``path`` only when complete.

    Returns
    -------
    dict
        ``scans``, ``points`` (total returns), ``cast_s`` (seconds spent ray-casting).

    Raises
    ------
    InvalidInputError
        ``path`` exists, or a bad scan rate.
    MissingDependencyError
        rosbags is not installed.
    """
    import time

    Writer, ts = _rosbags()
    path = Path(path)
    if path.exists():
        raise InvalidInputError(f"{path}: exists; a ROS 2 bag is a new folder")
    if not (math.isfinite(scan_rate) and scan_rate > 0):
        raise InvalidInputError(f"scan rate must be a positive number of hertz, got {scan_rate!r}")
    if not route.times.size:
        raise InvalidInputError("the drive has no pose")
    rng = np.random.default_rng(seed)
    noisy = odometry_noise(route.poses, rng)
    T = ts.types
    Time = T["builtin_interfaces/msg/Time"]
    Header = T["std_msgs/msg/Header"]
    PointField = T["sensor_msgs/msg/PointField"]
    fields = [PointField(name=c, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, c in enumerate("xyz")]

    def stamp(t: float) -> object:
        ns = int(round(t * NS))
        return Time(sec=ns // NS, nanosec=ns % NS)

    def pose_msg(pose: np.ndarray) -> object:
        qx, qy, qz, qw = _quaternion(pose[:3, :3])
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=float(pose[0, 3]), y=float(pose[1, 3]), z=float(pose[2, 3])),
            orientation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw))

    def odom(t: float, pose: np.ndarray) -> object:
        zero3 = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        return T["nav_msgs/msg/Odometry"](
            header=Header(stamp=stamp(t), frame_id="map"), child_frame_id="lidar",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose_msg(pose), covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=zero3, angular=zero3), covariance=np.zeros(36)))

    def tf(t: float, pose: np.ndarray) -> object:
        p = pose_msg(pose)
        transform = T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=p.position.x, y=p.position.y, z=p.position.z),
            rotation=p.orientation)
        return T["tf2_msgs/msg/TFMessage"](transforms=[T["geometry_msgs/msg/TransformStamped"](
            header=Header(stamp=stamp(t), frame_id="map"), child_frame_id="lidar", transform=transform)])

    period = 1.0 / scan_rate
    scans = points = 0
    cast_s = 0.0
    next_scan = 0.0
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".dftpcc-bag-", dir=path.parent) as tmp:
        part = Path(tmp) / "bag"
        with Writer(part, version=9) as writer:
            c_pts = writer.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
            c_odom = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
            c_noisy = writer.add_connection("/odom_noisy", "nav_msgs/msg/Odometry", typestore=ts)
            c_tf = writer.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=ts)
            for k, (t, pose) in enumerate(zip(route.times, route.poses)):
                ns = int(round(float(t) * NS))
                writer.write(c_odom, ns, ts.serialize_cdr(odom(float(t), pose), "nav_msgs/msg/Odometry"))
                writer.write(c_noisy, ns, ts.serialize_cdr(odom(float(t), noisy[k]), "nav_msgs/msg/Odometry"))
                writer.write(c_tf, ns, ts.serialize_cdr(tf(float(t), pose), "tf2_msgs/msg/TFMessage"))
                if t + 1e-9 < next_scan:
                    continue
                next_scan += period
                t0 = time.perf_counter()
                pts = cast_scan(surface, pose, lidar, rng=rng).astype(np.float32)
                cast_s += time.perf_counter() - t0
                msg = T["sensor_msgs/msg/PointCloud2"](
                    header=Header(stamp=stamp(float(t)), frame_id="lidar"), height=1, width=pts.shape[0],
                    fields=fields, is_bigendian=False, point_step=12, row_step=12 * pts.shape[0],
                    data=np.frombuffer(pts.tobytes(), dtype=np.uint8), is_dense=True)
                writer.write(c_pts, ns, ts.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
                scans += 1
                points += pts.shape[0]
                if on_scan is not None:
                    on_scan(scans)
        if path.exists():  # made by someone else while we wrote
            raise InvalidInputError(f"{path}: appeared while the bag was written; not replaced")
        os.replace(part, path)
    return {"scans": scans, "points": points, "cast_s": cast_s}



def _waypoints(text: str) -> np.ndarray:
    try:
        return np.array([[float(v) for v in pair.split(",")] for pair in text.split(";") if pair.strip()])
    except ValueError:
        raise InvalidInputError(f"waypoints are 'x,y;x,y;...' in local metres, got {text!r}") from None


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m dftpcc.experiments.rover MAP BAG``: drive a simulated rover over a map, write a ROS 2 bag.

    MAP is a GeoTIFF DEM (its own cells) or any point cloud dftpcc reads
    (gridded at ``--resolution``). The drive is a loop around the map's middle
    unless ``--waypoints`` are given (local metres, see the module docstring).
    """
    import argparse
    import sys
    import time

    from ..files import read_dem
    from ..params import Params

    parser = argparse.ArgumentParser(prog="python -m dftpcc.experiments.rover", description=main.__doc__.splitlines()[0])
    parser.add_argument("map", help="GeoTIFF DEM or point cloud")
    parser.add_argument("bag", help="the ROS 2 bag folder to write (must not exist)")
    parser.add_argument("--lidar", choices=tuple(LIDARS), default="vlp16")
    parser.add_argument("--resolution", type=float, help="grid a point cloud at this cell size, metres (default 1)")
    parser.add_argument("--classes", help="LAS/LAZ classes to keep, e.g. 2")
    parser.add_argument("--scale", type=float, default=1.0,
                        help="multiply every length of the map (e.g. 0.1 makes a 10 m DEM rover-sized); default 1")
    parser.add_argument("--waypoints", type=_waypoints, help="'x,y;x,y;...' in local metres (default: a loop)")
    parser.add_argument("--radius", type=float, help="radius of the default loop, metres (default: a quarter of the map)")
    parser.add_argument("--speed", type=float, default=ROVER_SPEED, help=f"m/s (default {ROVER_SPEED})")
    parser.add_argument("--duration", type=float, help="stop after this many seconds of driving")
    parser.add_argument("--scan-rate", type=float, default=SCAN_RATE_HZ, help=f"scans per second (default {SCAN_RATE_HZ:g})")
    parser.add_argument("--clip", action="store_true", help="cut a drive that leaves the map instead of refusing it")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    try:
        classes = [int(c) for c in args.classes.split(",")] if args.classes else None
        # A raster keeps its own cells unless a resolution is given; a cloud is gridded at 1 m by default.
        raster = args.map.lower().endswith((".tif", ".tiff"))
        resolution = args.resolution or ("auto" if raster else 1.0)
        dem, _, _ = read_dem(args.map, Params(resolution=resolution), classes=classes)
        surface = Surface.from_dem(dem, scale=args.scale)
        lidar = LIDARS[args.lidar]
        waypoints = args.waypoints if args.waypoints is not None else loop_waypoints(surface, radius=args.radius)
        route = drive(surface, waypoints, speed=args.speed, lidar=lidar, clip=args.clip)
        if args.duration is not None:
            keep = route.times <= args.duration
            route = Drive(route.times[keep], route.poses[keep], float(route.times[keep][-1] * args.speed), route.clipped)
        t0 = time.perf_counter()
        info = write_bag(args.bag, surface, route, lidar, scan_rate=args.scan_rate, seed=args.seed)
    except (InvalidInputError, MissingDependencyError) as exc:
        print(f"rover: error: {exc}", file=sys.stderr)
        return 6 if isinstance(exc, MissingDependencyError) else 3
    print(f"{args.bag}: {info['scans']} scans ({info['points']:,} returns), {route.distance:.1f} m in "
          f"{route.times[-1]:.1f} s{' (clipped at the map edge)' if route.clipped else ''}; ray-casting "
          f"{1000 * info['cast_s'] / max(info['scans'], 1):.0f} ms per scan, {time.perf_counter() - t0:.1f} s in all")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
