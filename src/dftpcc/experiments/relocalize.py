"""Can a rover still localize against a compressed map? Registration of simulated scans, and the cutoff that keeps it.

Scans are cast from the terrain itself (:mod:`dftpcc.experiments.rover`) at
poses drawn with a fixed seed, each registered with small_gicp's GICP from an
initial guess :data:`OFFSET_M` and :data:`OFFSET_DEG` off the truth against a
map: the original one or one rebuilt by dftpcc. A scan succeeds when it ends
within :data:`SUCCESS_M` and :data:`SUCCESS_DEG` of the truth (coarse:
:data:`COARSE_M`, :data:`COARSE_DEG`). :func:`recommend` finds the smallest
file whose rebuilt map still relocalizes scans within a given error.

GICP (plane-to-plane, covariances from :attr:`Gicp.neighbours` neighbours)
is the registration: point-to-plane and point-to-point ICP barely move from
the initial guess on gentle terrain, whose points mostly constrain height,
pitch and roll (docs/relocalization.md measures them). Maps and scans are
registered in a local frame (a map's own coordinates minus their rounded
mean): small_gicp's voxel grid keys hold 21 bits per axis, so points at
UTM-size coordinates are dropped ("voxel coord is out of range").
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from ..format import restate
from ..dem import DEM
from ..encoder import encode_dem
from .._optional import import_optional, install_hint
from ..errors import InvalidInputError
from ..files import check_compressed_output, read_dem
from ..io import atomic_write
from ..mapfile import open as open_map
from ..params import Params, tile_size_for
from .rover import LIDARS, Lidar, Surface, check_map_size, scan_at, sensor_pose

__all__ = ["Gicp", "MapTarget", "Scan", "Outcome", "Recommendation", "simulate_scans", "perturb", "pose_error",
           "relocalize", "relocalize_map", "recommend", "recommend_file", "compress_file_reloc", "check_target_reloc",
           "require_small_gicp", "with_reloc_stats", "surface_dem", "SLAM_INSTALL_HINT",
           "OFFSET_M", "OFFSET_DEG", "SUCCESS_M", "SUCCESS_DEG", "COARSE_M", "COARSE_DEG", "RECOMMEND_CUTOFFS",
           "RECOMMEND_FRACTION", "RECOMMEND_LIDAR"]

SLAM_INSTALL_HINT = install_hint("slam")
#: Initial guesses are this far off the true pose: translation (metres, random
#: direction in 3-D) and rotation (degrees, about a random axis).
OFFSET_M = 0.5
OFFSET_DEG = 5.0
#: A relocalized scan within both of these of the truth is a success ...
SUCCESS_M = 0.10
SUCCESS_DEG = 1.0
#: ... and within these a coarse success (the right basin, not yet precise).
COARSE_M = 2.0
COARSE_DEG = 5.0
#: Scans are drawn at least this fraction of the lidar range inside the map's border.
BORDER_FRACTION = 0.2
#: Draws per wanted pose before giving up on a map with too little valid ground.
DRAWS_PER_POSE = 200
#: A rate-control recommendation tries these cutoffs, smallest file first.
RECOMMEND_CUTOFFS: tuple[float, ...] = tuple(round(0.05 * i, 2) for i in range(19, -1, -1))
#: A candidate meets ``target_reloc`` when at least this fraction of scans end
#: within the target translation error and :data:`SUCCESS_DEG`.
RECOMMEND_FRACTION = 0.95
#: The sensor recommend simulates: a VLP-16 with a 50 m range, so maps from 50 m up can be checked.
RECOMMEND_LIDAR = Lidar(16, -15.0, 15.0, 0.4, 50.0, 0.5, 0.03)


def require_small_gicp() -> Any:
    """small_gicp, or :class:`~dftpcc.errors.MissingDependencyError` with the install hint."""
    return import_optional("small_gicp", "slam", needed_for="relocalization")


@dataclass(frozen=True)
class Gicp:
    """Registration settings (small_gicp GICP).

    Attributes
    ----------
    voxel : float
        Scans and maps are voxel-downsampled to this size before
        registration, metres (denser maps are thinned to it, sparser ones kept).
    neighbours : int
        Points per local covariance.
    correspondence : tuple of float
        Largest point-pair distance of each successive round, metres: coarse
        first (an initial guess 5 degrees off moves points 50 m away by 4 m),
        then fine.
    iterations : int
        Gauss-Newton iterations per round at most.
    """

    voxel: float = 0.25
    neighbours: int = 20
    correspondence: tuple[float, ...] = (5.0, 2.0, 1.0)
    iterations: int = 30


class MapTarget:
    """A map prepared once for many registrations: local frame, downsampled, covariances, k-d tree.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        The map, metres, in the frame the scan poses are given in.
    gicp : Gicp
    """

    def __init__(self, points: np.ndarray, gicp: Gicp = Gicp()):
        sg = require_small_gicp()
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] < gicp.neighbours:
            raise InvalidInputError(f"a map needs at least {gicp.neighbours} points of 3 coordinates, "
                                    f"got shape {points.shape}")
        # Rounded to a metre so the shift itself is exact in float64.
        self.origin = np.round(points.mean(axis=0))
        self.gicp = gicp
        self.cloud, self.tree = sg.preprocess_points(points - self.origin, downsampling_resolution=gicp.voxel,
                                                     num_neighbors=gicp.neighbours)
        self.size = int(self.cloud.size())

    def register(self, scan: np.ndarray, guess: np.ndarray) -> np.ndarray:
        """The pose (map <- sensor, 4 x 4, map frame) that aligns ``scan`` (sensor frame) to the map from ``guess``."""
        sg = require_small_gicp()
        source, _ = sg.preprocess_points(np.asarray(scan, dtype=np.float64), downsampling_resolution=self.gicp.voxel,
                                         num_neighbors=self.gicp.neighbours)
        shift = np.eye(4)
        shift[:3, 3] = self.origin
        T = np.linalg.solve(shift, guess)  # the guess in the local frame
        for distance in self.gicp.correspondence:
            result = sg.align(self.cloud, source, self.tree, init_T_target_source=T, registration_type="GICP",
                              max_correspondence_distance=distance, max_iterations=self.gicp.iterations)
            T = result.T_target_source
        return shift @ T


@dataclass(frozen=True)
class Scan:
    """A simulated scan: ``points`` (sensor frame, metres) cast from ``pose`` (map <- sensor, 4 x 4)."""

    pose: np.ndarray
    points: np.ndarray


def simulate_scans(surface: Surface, count: int, *, lidar: Lidar = LIDARS["vlp16"], seed: int = 0,
                   window: tuple[float, float, float, float] | None = None) -> list[Scan]:
    """``count`` scans at random poses (fixed ``seed``) over valid ground of ``surface``.

    Positions are drawn uniformly in ``window`` (x_lo, x_hi, y_lo, y_hi, local
    metres; default the map less :data:`BORDER_FRACTION` of the lidar range
    on each side), headings uniformly; a draw whose rover footprint has no data
    is drawn again.

    Raises
    ------
    InvalidInputError
        A map smaller than the lidar's range, a window outside it, or too little
        valid ground to place ``count`` rovers (after :data:`DRAWS_PER_POSE` draws each).
    """
    if count < 1:
        raise InvalidInputError(f"scan count must be at least 1, got {count}")
    check_map_size(surface, lidar)
    rng = np.random.default_rng(seed)
    if window is None:
        lo = 0.5 * surface.spacing + BORDER_FRACTION * lidar.max_range
        w, d = surface.extent
        window = (lo, lo + w - 2 * BORDER_FRACTION * lidar.max_range, lo, lo + d - 2 * BORDER_FRACTION * lidar.max_range)
    x_lo, x_hi, y_lo, y_hi = window
    if not (x_hi > x_lo and y_hi > y_lo):
        raise InvalidInputError(f"empty window for the scan poses: {window}")
    scans: list[Scan] = []
    for _ in range(count * DRAWS_PER_POSE):
        x, y, yaw = rng.uniform(x_lo, x_hi), rng.uniform(y_lo, y_hi), rng.uniform(-math.pi, math.pi)
        try:
            pose = sensor_pose(surface, x, y, yaw, mount_height=lidar.mount_height)
            points = scan_at(surface, pose, lidar, rng)
        except InvalidInputError:
            continue  # no ground there, or none in the sensor's sight: draw again
        scans.append(Scan(pose, points))
        if len(scans) == count:
            return scans
    empty = 1.0 - float(np.isfinite(surface.heights).mean())
    raise InvalidInputError(f"too little ground for the simulated rover: {len(scans)} of {count} scans placed on "
                            f"ground in local window x {x_lo:.1f}..{x_hi:.1f} m, y {y_lo:.1f}..{y_hi:.1f} m "
                            f"after {count * DRAWS_PER_POSE} draws; {100 * empty:.0f} % of the map's cells are empty")


def _rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def perturb(pose: np.ndarray, rng: np.random.Generator, *, offset_m: float = OFFSET_M,
            offset_deg: float = OFFSET_DEG) -> np.ndarray:
    """An initial guess ``offset_m`` metres (random direction) and ``offset_deg`` degrees (random axis) off ``pose``."""
    guess = pose.copy()
    direction = rng.normal(size=3)
    guess[:3, 3] += offset_m * direction / np.linalg.norm(direction)
    guess[:3, :3] = _rotation_about(rng.normal(size=3), math.radians(offset_deg)) @ pose[:3, :3]
    return guess


def pose_error(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Translation (metres) and rotation (degrees) between two poses."""
    dt = float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]))
    cos = (np.trace(truth[:3, :3].T @ estimate[:3, :3]) - 1.0) / 2.0
    return dt, math.degrees(math.acos(min(1.0, max(-1.0, cos))))


@dataclass(frozen=True)
class Outcome:
    """Registration errors of a set of scans against one map.

    Attributes
    ----------
    translation : ndarray
        Metres, per scan.
    rotation : ndarray
        Degrees, per scan.
    """

    translation: np.ndarray
    rotation: np.ndarray

    def success(self, metres: float = SUCCESS_M, degrees: float = SUCCESS_DEG) -> float:
        """Fraction of scans within ``metres`` and ``degrees`` of the truth."""
        return float(np.mean((self.translation <= metres) & (self.rotation <= degrees)))

    @property
    def coarse(self) -> float:
        return self.success(COARSE_M, COARSE_DEG)

    @property
    def median_m(self) -> float:
        return float(np.median(self.translation))

    @property
    def median_deg(self) -> float:
        return float(np.median(self.rotation))

    def summary(self) -> dict[str, float]:
        return {"success": self.success(), "coarse": self.coarse, "median_m": self.median_m,
                "median_deg": self.median_deg, "p95_m": float(np.percentile(self.translation, 95))}


def relocalize(target: MapTarget, scans: Sequence[Scan], *, seed: int = 0, offset_m: float = OFFSET_M,
               offset_deg: float = OFFSET_DEG) -> Outcome:
    """Register every scan against ``target`` from a perturbed guess (fixed ``seed``: the same guesses for every map)."""
    rng = np.random.default_rng(seed)
    errors = [pose_error(target.register(s.points, perturb(s.pose, rng, offset_m=offset_m, offset_deg=offset_deg)),
                         s.pose) for s in scans]
    t, r = (np.array(e) for e in zip(*errors))
    return Outcome(t, r)


def relocalize_map(points: np.ndarray, scans: Sequence[Scan], *, gicp: Gicp = Gicp(), seed: int = 0) -> Outcome:
    """:func:`relocalize` against a map given as points (prepared here)."""
    return relocalize(MapTarget(points, gicp), scans, seed=seed)


def ground_dem(dem: DEM) -> DEM:
    """The ground the simulated rover drives and scans: the map's occupied cells and the gaps they
    enclose (its footprint, as ``mask='footprint'`` keeps), the gaps filled smoothly.

    A sparse cloud gridded finely (a few points per square metre at 0.5 m) leaves most cells empty
    between its points: the lidar's rays would fall through those holes and return nothing.
    """
    from ..fill import fill_empty, footprint

    ground = footprint(dem.mask)
    if ground.sum() == dem.mask.sum():
        return dem
    heights = np.where(ground, fill_empty(np.where(dem.mask, dem.heights, 0.0), dem.mask, method="smooth"), 0.0)
    return DEM(grid=dem.grid, heights=heights, mask=ground)


def surface_dem(dem: DEM, *, scale: float = 1.0) -> tuple[Surface, np.ndarray]:
    """The rover's surface of ``dem`` (:func:`ground_dem`: its gaps filled) and the 4 x 4 transform from
    its local frame to the DEM's map frame.

    A map point is ``T @ [x, y, z, 1]`` of a local point; with ``scale`` the
    local frame is also ``scale`` times the map's size.
    """
    g = dem.grid
    surface = Surface.from_dem(ground_dem(dem), scale=scale)
    T = np.diag([1.0 / scale] * 3 + [1.0])
    T[:3, 3] = (g.x0, g.y0, g.z0)
    return surface, T


@dataclass(frozen=True)
class Recommendation:
    """What :func:`recommend` chose and measured.

    Attributes
    ----------
    params : Params
        The chosen parameters (``cutoff`` set).
    data : bytes
        The chosen file, its statistics holding ``reloc_success_fraction``.
    success : float
        Fraction of scans within the target translation error and :data:`SUCCESS_DEG`.
    p95_m : float
        95th percentile of the translation error, metres.
    bits_per_point : float
    tried : list of dict
        Every candidate measured: cutoff, bytes, bits per point, success, p95_m, median_m.
    notes : dict
        What the file records beside its parameters: ``target_reloc``, metres.
    """

    params: Params
    data: bytes
    success: float
    p95_m: float
    bits_per_point: float
    tried: list[dict[str, Any]] = field(default_factory=list)
    notes: dict[str, Any] = field(default_factory=dict)


def _bytes_of(size: int) -> str:
    return f"{size:,} bytes"


def recommend(dem: DEM, target_reloc: float, params: Params | None = None, *, point_count: int | None = None,
              crs: dict[str, Any] | None = None, scans: int = 20, seed: int = 0, lidar: Lidar = RECOMMEND_LIDAR,
              gicp: Gicp = Gicp(), cutoffs: Iterable[float] = RECOMMEND_CUTOFFS,
              on_candidate: Callable[[dict[str, Any]], None] | None = None,
              on_stage: Callable[..., None] | None = None) -> Recommendation:
    """The smallest file whose rebuilt map still relocalizes scans cast on the map itself within ``target_reloc``.

    ``scans`` scans are cast (fixed ``seed``) on the bilinear surface of
    ``dem`` (its own cells, in the DEM's frame less its origin), and for each
    cutoff, smallest file first, the map rebuilt from the file is tried:
    the first where at least :data:`RECOMMEND_FRACTION` of the scans end within
    ``target_reloc`` metres and :data:`SUCCESS_DEG` degrees is chosen.

    Parameters
    ----------
    dem : DEM
        The map's DEM (as :func:`dftpcc.files.read_dem` gives it).
    target_reloc : float
        Largest translation error, metres.
    params : Params, optional
        Everything but the cutoff (and the rate-control targets, which it replaces).

    Raises
    ------
    InvalidInputError
        A bad target, a map too small for the sensor or without valid ground,
        a rotated or non-square grid (``frame='oriented'``, a latitude/longitude
        raster), a cutoff or a rate-control target given too, or no cutoff
        meets the target (the message gives the best error reached and at what size).
    MissingDependencyError
        small_gicp is not installed.
    """
    params = check_target_reloc(target_reloc, params)
    if tile_size_for(params, dem.grid.shape):
        raise InvalidInputError(f"target_reloc measures maps coded whole; a {dem.grid.rows:,} x {dem.grid.cols:,} "
                                f"grid would be tiled (tile_size {params.tile_size!r}): give tile_size=0, or a "
                                f"coarser resolution")
    stage = on_stage or (lambda *_: None)
    stage("simulate")
    surface, to_map = surface_dem(dem)
    cast = simulate_scans(surface, scans, lidar=lidar, seed=seed)
    # Scans live in the surface's local frame; rebuilt maps come in the DEM's
    # frame, so they are moved by the inverse of the DEM's origin.
    shift = -to_map[:3, 3]
    candidates = []
    cutoffs = tuple(cutoffs)
    stage("encode")
    for k, cutoff in enumerate(cutoffs):
        stage("encode", k / max(len(cutoffs), 1))
        # The file records the target beside its parameters (a PARM note), as every candidate is sized.
        data = restate(encode_dem(dem, params.replace(cutoff=cutoff), point_count=point_count, crs=crs),
                       notes={"target_reloc": float(target_reloc)})
        candidates.append((len(data), cutoff, data))
    if not candidates:
        raise InvalidInputError("no cutoff to try")
    candidates.sort(key=lambda c: (c[0], -c[1]))
    count = point_count or int(dem.mask.sum())
    best: dict[str, Any] | None = None
    tried: list[dict[str, Any]] = []
    stage("relocalize")
    for k, (size, cutoff, data) in enumerate(candidates):
        stage("relocalize", k / len(candidates))
        with open_map(data) as cmap:
            points = cmap.read_points() + shift
        outcome = relocalize_map(points, cast, gicp=gicp, seed=seed)
        row = {"cutoff": cutoff, "bytes": size, "bits_per_point": 8.0 * size / count,
               "success": outcome.success(target_reloc), "p95_m": float(np.percentile(outcome.translation, 95)),
               "median_m": outcome.median_m,
               # Each criterion alone, so a failure can say which one held the scans back.
               "within_m": float(np.mean(outcome.translation <= target_reloc)),
               "within_deg": float(np.mean(outcome.rotation <= SUCCESS_DEG)),
               "p95_deg": float(np.percentile(outcome.rotation, 95))}
        tried.append(row)
        if on_candidate is not None:
            on_candidate(row)
        if best is None or row["p95_m"] < best["p95_m"]:
            best = row
        if row["success"] >= RECOMMEND_FRACTION:
            chosen = with_reloc_stats(data, row["success"])
            with open_map(chosen) as cmap:
                chosen_params, notes = cmap.params, cmap.header.notes
            return Recommendation(chosen_params, chosen, row["success"], row["p95_m"],
                                  8.0 * len(chosen) / count, tried, notes)
    assert best is not None  # at least one candidate was measured
    raise InvalidInputError(
        f"target_reloc {target_reloc:g} m cannot be met: a scan counts when within {target_reloc:g} m and "
        f"{SUCCESS_DEG:g} degree of the truth, and {100 * RECOMMEND_FRACTION:.0f} % must; the best map, at cutoff "
        f"{best['cutoff']:g} ({_bytes_of(best['bytes'])}, {best['bits_per_point']:.3g} bits/point), had "
        f"{100 * best['success']:.0f} % of {scans} scans: {100 * best['within_m']:.0f} % within {target_reloc:g} m "
        f"(95th percentile {best['p95_m']:.3g} m), {100 * best['within_deg']:.0f} % within {SUCCESS_DEG:g} degree "
        f"(95th percentile {best['p95_deg']:.3g} degrees)")


def check_target_reloc(target_reloc: float, params: Params | None = None) -> Params:
    """Refuse, before any work, a relocalization target that is not a positive length or comes with a
    cutoff or another rate-control target; the parameters to use (default :class:`Params`).

    Raises
    ------
    InvalidInputError
    MissingDependencyError
        small_gicp is not installed.
    """
    if isinstance(target_reloc, bool) or not (isinstance(target_reloc, (int, float)) and math.isfinite(target_reloc)
                                               and target_reloc > 0):
        raise InvalidInputError(f"target_reloc must be a positive number of metres, got {target_reloc!r}")
    params = params or Params()
    if params.has_target:
        raise InvalidInputError("give target_reloc alone: it chooses the cutoff, as the other targets would")
    if params.cutoff is not None:
        raise InvalidInputError("target_reloc chooses the cutoff: do not give one")
    require_small_gicp()
    return params


def recommend_file(src: str | os.PathLike[str], target_reloc: float, params: Params | None = None, *,
                   format: str | None = None, classes: Sequence[int] | None = None,  # noqa: A002
                   topic: str | None = None, pose_topic: str | None = None, **options: Any) -> Recommendation:
    """:func:`recommend` for the map in a file (any input :func:`dftpcc.compress_file` reads, a ROS bag
    of scans with their ``pose_topic`` included), gridded as it would be."""
    params = check_target_reloc(target_reloc, params)
    if options.get("on_stage") is not None:
        options["on_stage"]("read")
    dem, count, crs = read_dem(src, params, format=format, classes=classes, topic=topic, pose_topic=pose_topic)
    return recommend(dem, target_reloc, params, point_count=count, crs=crs, **options)


def compress_file_reloc(src: str | os.PathLike[str], dst: str | os.PathLike[str], target_reloc: float,
                        params: Params | None = None, *, force: bool = False, **options: Any) -> Recommendation:
    """Write the file :func:`recommend_file` chooses to ``dst`` (``.dftpc``; checked before any work, written whole or not at all)."""
    params = check_target_reloc(target_reloc, params)
    check_compressed_output(dst, force=force)
    chosen = recommend_file(src, target_reloc, params, **options)
    atomic_write(dst, lambda tmp: Path(tmp).write_bytes(chosen.data))
    return chosen


def with_reloc_stats(data: bytes, success: float) -> bytes:
    """``data`` with ``reloc_success_fraction`` added to its statistics (the map itself unchanged, tiles
    included)."""
    return restate(data, reloc_success_fraction=float(success))
