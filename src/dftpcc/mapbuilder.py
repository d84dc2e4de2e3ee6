"""A map that grows scan by scan: per-cell sums kept per tile, only the tiles a scan changed re-coded.

The grid stage for a rover: :class:`MapBuilder` keeps, for every tile of a
fixed lattice that has points, the sum of heights and the count of points of
each cell, and codes a tiled (1.1) file with no base layer (``TIDX`` base
reach 0) and a zero plane, so each tile's bytes depend on the cells of its
own coded window only (:func:`dftpcc.tiles.code_tile`). After a scan, only
the tiles whose window holds a changed cell are coded again; every other
tile keeps its bytes, which is what makes a delta (:mod:`dftpcc.delta`) small.

What is kept, and why (the state file, ``MAP.state`` beside ``MAP``, an ``.npz``):

* per held tile, per cell: the **sum** of the heights above the map's ``z0``
  as int64 micrometres (:data:`HEIGHT_QUANTUM_M`), the **count** of points,
  and the **sum of squares** (float64, m²). Integer sums are exact, so a
  cell's mean, hence every tile's bytes, does not depend on the order in
  which scans were added: a map grown by updates equals the map of all its
  points added at once. The sum of squares only feeds the stated gridding
  error (``STAT``), where float64 rounding is far below the float32 it is
  written as.
* per tile, the figures of its last coding (cells, squared error, largest
  error, point-weighted squared error), so the file's statistics are exact
  without decoding the tiles that are not coded again (``TIDX`` keeps them
  only as float32).
* the settings (resolution, tile size, cutoff, step, lattice origin, CRS),
  the number of points added, and the SHA-256 of the map the state belongs
  to, of the map it was updated from and of the scans that update added:
  an update refuses a state of another map, and repairs a map left one
  update behind its state (the state is written first, then the map; an
  interruption between the two).

The state file's layout and checks are :mod:`dftpcc.mapstate`'s (docs/growing-maps.md).

Memory is 20 bytes per cell of the held tiles (4 for the count).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import warnings
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from . import coding, kernels
from .format import VERSION, Header, MapWriter, Source, read_tile, unpack_source
from .dem import Grid, TileGrid, as_points
from .encoder import check_heights
from .errors import CorruptFileError, DftpccError, DftpccWarning, InvalidInputError
from .io.atomic import atomic_write_all, check_distinct, check_output
from .io.lock import lock_path, locked
from .mapstate import FIGURES as _FIGURES, STATE_VERSION, read_state, write_state
from .params import DEFAULT_CUTOFF, MAX_COORDINATE_M, TILE_SIZES, Params, check_cutoff, make_params
from .tiles import TILE_OVERLAP, TileCode, TileJob, code_tile

__all__ = ["MapBuilder", "UpdateResult", "update_file", "state_path", "is_growing", "same_crs",
           "HEIGHT_QUANTUM_M", "Z0_QUANTUM_M", "DEFAULT_STEP_M", "DEFAULT_GROWING_TILE_SIZE", "STATE_SUFFIX",
           "STATE_VERSION", "StateRecoveredWarning"]

#: Heights are summed as whole multiples of this (metres): exact integer sums, whatever the order of the adds.
HEIGHT_QUANTUM_M = 1e-6
#: The map's projection height z0 is the first scan's mean height rounded to this (metres).
Z0_QUANTUM_M = 1.0
#: Quantizer step of a growing map unless given (metres): fixed, since rate control would
#: choose another step as the map grows and so re-code every tile.
DEFAULT_STEP_M = 0.01
#: Tile side of a growing map unless given, cells: a tile is what one update re-codes at least.
DEFAULT_GROWING_TILE_SIZE = 256
#: The state file of ``MAP`` is ``MAP`` + this.
STATE_SUFFIX = ".state"
#: Points a cell may collect: counts are int32.
MAX_CELL_POINTS = 2**31 - 1
#: A scan's points in a tile are sorted into cells (np.unique) when fewer than the tile's cells over
#: this, else counted in a histogram of them: the same cells and order, whichever is cheaper.
HISTOGRAM_SHARE = 8


class StateRecoveredWarning(DftpccWarning):
    """The map was older than its state (an update interrupted between the two writes); rebuilt from the state."""


@dataclass
class _Cells:
    """One held tile's accumulators, T x T each."""

    sum: np.ndarray  # int64, micrometres above z0
    sumsq: np.ndarray  # float64, m²
    count: np.ndarray  # int32, points

    @classmethod
    def empty(cls, size: int) -> "_Cells":
        return cls(np.zeros((size, size), np.int64), np.zeros((size, size)), np.zeros((size, size), np.int32))


def state_path(map_path: str | os.PathLike[str]) -> Path:
    """The state file of a growing map: ``MAP.state`` beside it."""
    return Path(f"{os.fspath(map_path)}{STATE_SUFFIX}")


def is_growing(header: Header) -> bool:
    """Whether a map's header is that of a growing map: tiled, no base layer, a zero plane, the
    tiles' own masks (no map mask: a tile's sections are all a scan may rewrite)."""
    return (header.tiles is not None and header.tiles.base_cycles == 0 and not any(header.plane)
            and not header.tiles.map_mask)


def same_crs(a: dict[str, Any] | None, b: dict[str, Any] | None) -> bool:
    """Whether two CRS dicts (``{"wkt": ..., "las_vlrs": [...]}``) say the same; an empty one is no CRS."""
    a, b = a or {}, b or {}
    if not a or not b:
        return not a and not b
    if a.get("wkt") and b.get("wkt"):
        if a["wkt"] == b["wkt"]:
            return True
        try:  # the same CRS written two ways
            from rasterio.crs import CRS

            return bool(CRS.from_wkt(a["wkt"]) == CRS.from_wkt(b["wkt"]))
        except Exception:  # noqa: BLE001 - unparsable WKT: the texts differ, so do the CRSs
            return False
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


class MapBuilder:
    """A tiled map grown by adding scans, re-coding only the tiles they change.

    The tile lattice is anchored at ``origin`` (default: the first scan's
    mean x and y snapped down to a multiple of the tile's width, and its
    mean height rounded to :data:`Z0_QUANTUM_M`); it grows by whole tiles in
    any direction as scans reach new ground. The file's grid is the
    bounding box of the held tiles plus one empty tile on every side, so no
    held tile's coded window is ever cut by the map's edge: growing never
    changes the window, hence the bytes, of a tile whose cells did not
    change. Empty tiles cost 4 bytes of the tile index each, before zstd.

    Parameters
    ----------
    resolution : float
        Cell size, metres.
    tile_size : int
        Tile side, cells (at least 16).
    cutoff : float
        f_c in [0, 1), fixed for every tile and update.
    step : float
        Quantizer step, metres, fixed (no rate control of the step: a target would choose
        another step as the map grows, and every tile would be coded again). A maximum
        error is kept by residual layers instead (:meth:`encode`).
    crs : dict, optional
        The map frame's CRS (``{"wkt": ..., "las_vlrs": [...]}``).
    origin : (x, y, z), optional
        Lattice origin in metres (x, y: the corner of lattice cell (0, 0);
        z: the projection height the heights are summed above).
    jit : bool
        Load the compiled kernels (:mod:`dftpcc.kernels`; numba, the ``fast``
        extra) when installed: a builder codes tiles scan after scan, so their
        one-time load (about 0.3 s) is paid back within a few scans. The bytes
        are the same either way; ``DFTPCC_JIT=0`` keeps numpy whatever this says.
    """

    def __init__(self, resolution: float, *, tile_size: int = DEFAULT_GROWING_TILE_SIZE, cutoff: float = DEFAULT_CUTOFF,
                 step: float = DEFAULT_STEP_M, crs: dict[str, Any] | None = None,
                 origin: Sequence[float] | None = None, jit: bool = True):
        if not (isinstance(tile_size, (int, np.integer)) and not isinstance(tile_size, bool)
                and max(TILE_SIZES[0], 2 * TILE_OVERLAP) <= tile_size <= TILE_SIZES[1]):
            raise InvalidInputError(f"tile_size must be a whole number of cells from {TILE_SIZES[0]} to "
                                    f"{TILE_SIZES[1]}, got {tile_size!r}")
        if not (isinstance(step, (int, float)) and 0 < step <= MAX_COORDINATE_M):
            raise InvalidInputError(f"step must be a positive number of metres, got {step!r}")
        self.params: Params = make_params(resolution=resolution, cutoff=check_cutoff(cutoff),
                                          step=coding.short_step(float(step)), tile_size=int(tile_size))
        self.resolution = float(self.params.resolution)
        self.tile_size = int(tile_size)
        self.crs: dict[str, Any] = dict(crs or {})
        self.origin: tuple[float, float, float] | None = None
        if origin is not None:
            self.origin = _check_origin(origin)
        self.point_count = 0
        self._tiles: dict[tuple[int, int], _Cells] = {}
        self._codes: dict[tuple[int, int], TileCode] = {}
        self._gridding: dict[tuple[int, int], float] = {}  # squared distance of points to their cell's mean, m²
        self._dirty: set[tuple[int, int]] = set()  # tiles whose coded window holds a cell whose mean changed
        self._mask_dirty: set[tuple[int, int]] = set()  # tiles that gained occupied cells
        self._recount: set[tuple[int, int]] = set()  # tiles with cells seen again at the same mean
        #: During :meth:`encode`: the tiles it codes, and the (heights, occupied) of those computed yet.
        self._coding: dict[tuple[int, int], tuple[np.ndarray, np.ndarray] | None] = {}
        #: The minor version the held tiles' sections were coded for (a map resumed from a 1.1 file
        #: holds them in the legacy coefficient order until they are coded again).
        self._minor = VERSION[1]
        self._file_sha256: str | None = None  # of the map file this builder was read from or last saved as
        #: SHA-256 of the scans of the update that gave this map (:func:`update_file`, docs/growing-maps.md);
        #: None once anything else was added.
        self.update_sha256: str | None = None
        self._previous_sha256: str | None = None  # of the map the update that gave this one started from
        if jit:
            kernels.load()

    # -- growing -------------------------------------------------------------------------------

    @property
    def span(self) -> float:
        """Width of one tile, metres."""
        return self.tile_size * self.resolution

    @property
    def tiles(self) -> list[tuple[int, int]]:
        """The held tiles' lattice indices (row, column), sorted."""
        return sorted(self._tiles)

    def add(self, points: np.ndarray, pose: tuple[np.ndarray, np.ndarray] | None = None) -> "MapBuilder":
        """Add a scan.

        Parameters
        ----------
        points : array_like, shape (N, 3)
            Metres: in the map frame, or in the sensor frame with ``pose``.
        pose : (rotation (3, 3), translation (3,)), optional
            The sensor's pose: a point becomes ``rotation @ p + translation``.

        Returns
        -------
        MapBuilder
            ``self``, so adds chain.
        """
        pts = as_points(points)
        if pose is not None:
            rotation, translation = (np.asarray(v, dtype=np.float64) for v in pose)
            if rotation.shape != (3, 3) or translation.shape != (3,) or not (
                    np.isfinite(rotation).all() and np.isfinite(translation).all()):
                raise InvalidInputError("a pose is a finite (3, 3) rotation and a (3,) translation")
            pts = pts @ rotation.T + translation
        self.update_sha256 = None
        check_heights(float(pts[:, 2].min()), float(pts[:, 2].max()))
        if float(np.abs(pts[:, :2]).max()) > MAX_COORDINATE_M:
            raise InvalidInputError(f"points beyond ±{MAX_COORDINATE_M:g} m")
        if self.origin is None:
            mean = pts.mean(axis=0)
            self.origin = (math.floor(mean[0] / self.span) * self.span, math.floor(mean[1] / self.span) * self.span,
                           round(mean[2] / Z0_QUANTUM_M) * Z0_QUANTUM_M)
        ox, oy, oz = self.origin
        size = self.tile_size
        col = np.floor((pts[:, 0] - ox) * (1.0 / self.resolution)).astype(np.int64)
        row = np.floor((pts[:, 1] - oy) * (1.0 / self.resolution)).astype(np.int64)
        micro = np.rint((pts[:, 2] - oz) * (1.0 / HEIGHT_QUANTUM_M))  # whole micrometres, exact in float64
        rel = micro * HEIGHT_QUANTUM_M  # the heights summed, so squares and sums agree
        ti, tj = row // size, col // size
        local = (row - ti * size) * size + (col - tj * size)
        keys = (ti - ti.min()) * (int(tj.max() - tj.min()) + 1) + (tj - tj.min())
        order = np.argsort(keys, kind="stable")
        bounds = np.flatnonzero(np.diff(keys[order])) + 1
        for group in np.split(order, bounds):
            tile = (int(ti[group[0]]), int(tj[group[0]]))
            self._add_to(tile, local[group], micro[group], rel[group])
        self.point_count += int(pts.shape[0])
        return self

    def _add_to(self, tile: tuple[int, int], local: np.ndarray, micro: np.ndarray, rel: np.ndarray) -> None:
        size = self.tile_size
        cells = self._tiles.get(tile)
        if cells is None:
            cells = self._tiles[tile] = _Cells.empty(size)
        # A scan sees a few percent of a tile's cells: sum per cell seen, and update only those.
        if local.size >= size * size // HISTOGRAM_SHARE:
            # The cells seen, ascending, and each point's index among them (np.unique's, without
            # its sort): a histogram of the tile's cells, cheaper than sorting many points.
            seen = np.flatnonzero(np.bincount(local, minlength=size * size))
            rank = np.empty(size * size, dtype=np.intp)
            rank[seen] = np.arange(seen.size)
            where = rank[local]
        else:
            seen, where = np.unique(local, return_inverse=True)
        added = np.bincount(where, minlength=seen.size)
        total, sums, sumsq = cells.count.reshape(-1), cells.sum.reshape(-1), cells.sumsq.reshape(-1)
        before, before_sum = total[seen], sums[seen]
        if int(before.max(initial=0)) + int(added.max()) > MAX_CELL_POINTS:
            raise InvalidInputError(f"a cell would hold more than {MAX_CELL_POINTS:,} points")
        # A float64 sum of whole numbers is exact below 2**53 micrometres (9,000 km) per scan and cell.
        after_sum = before_sum + np.bincount(where, weights=micro, minlength=seen.size).astype(np.int64)
        after = before + added.astype(np.int32)
        sums[seen], total[seen] = after_sum, after
        sumsq[seen] += np.bincount(where, weights=rel * rel, minlength=seen.size)
        # A cell's height in every window is its mean (see _heights): a cell seen again whose mean
        # came out the same leaves every section as it was, only the tile's point-weighted error moves.
        new = before == 0
        moved = new | (np.divide(before_sum, before, out=np.zeros(seen.size), where=~new)
                       != np.divide(after_sum, after))
        if new.any():
            self._mask_dirty.add(tile)
        if moved.any():
            self._mark(tile, *np.divmod(seen[moved], size))
        if not moved.all():
            self._recount.add(tile)

    def _mark(self, tile: tuple[int, int], rows: np.ndarray, cols: np.ndarray) -> None:
        """Mark ``tile`` and every neighbour whose coded window holds a changed cell (at ``rows``, ``cols``
        of the tile, some at least): those within the overlap of an edge or corner."""
        m, size = TILE_OVERLAP, self.tile_size
        side = {-1: lambda v: v < m, 0: lambda v: np.ones(v.shape, bool), 1: lambda v: v >= size - m}
        i, j = tile
        for di in (-1, 0, 1):
            near_row = side[di](rows)
            if not near_row.any():
                continue
            for dj in (-1, 0, 1):
                if (near_row & side[dj](cols)).any():
                    self._dirty.add((i + di, j + dj))

    def changed_tiles(self) -> list[tuple[int, int]]:
        """Held tiles whose coded window holds a cell changed since the last :meth:`encode` (lattice indices, sorted).

        A cell changes when it is new or its mean height does (points added
        to a cell at exactly its mean change no section, only the tile's
        point-weighted error, which :meth:`encode` updates without coding the
        tile again). A cell within :data:`~dftpcc.tiles.TILE_OVERLAP` cells of
        a tile's edge lies in the neighbour's window too, so it changes both.
        """
        return sorted(k for k in self._tiles if k in self._dirty or k not in self._codes)

    # -- coding --------------------------------------------------------------------------------

    def _heights(self, cells: _Cells) -> tuple[np.ndarray, np.ndarray]:
        occupied = cells.count > 0
        # An empty cell's sum is 0: 0 / 1 gives its 0, and the others the same quotient as a
        # division masked to them, without the mask's cost.
        mean = cells.sum / np.maximum(cells.count, 1)
        return mean * HEIGHT_QUANTUM_M, occupied

    def _job(self, tile: tuple[int, int]) -> TileJob:
        """The tile's coded window: its cells and :data:`TILE_OVERLAP` of its neighbours' on each side."""
        size, m = self.tile_size, TILE_OVERLAP
        width = size + 2 * m
        rest, mask = np.zeros((width, width)), np.zeros((width, width), bool)
        # Per offset: the neighbour's cells taken, and where they go in the window.
        take = {-1: (slice(size - m, size), slice(0, m)), 0: (slice(0, size), slice(m, m + size)),
                1: (slice(0, m), slice(m + size, width))}
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                near = (tile[0] + di, tile[1] + dj)
                cells = self._tiles.get(near)
                if cells is None:
                    continue
                (sr, wr), (sc, wc) = take[di], take[dj]
                whole = self._coding.get(near)
                if whole is None and near in self._coding:  # coded in this encode too: its heights once
                    whole = self._coding[near] = self._heights(cells)
                if whole is not None:
                    rest[wr, wc], mask[wr, wc] = whole[0][sr, sc], whole[1][sr, sc]
                else:
                    part = _Cells(cells.sum[sr, sc], cells.sumsq[sr, sc], cells.count[sr, sc])
                    rest[wr, wc], mask[wr, wc] = self._heights(part)
        own = self._tiles[tile]
        return TileJob(0, rest, mask, (m, m + size, m, m + size), np.zeros((size, size)), own.count)

    def _code(self, tile: tuple[int, int], *, sections_kept: bool = False) -> None:
        """Code ``tile`` again; ``sections_kept``: its cells kept their means, so only its errors are measured."""
        job = self._job(tile)
        known = self._codes.get(tile)
        if known is not None and (sections_kept or tile not in self._mask_dirty):
            job.mask_code = known.mask  # no cell of the tile became occupied: the same mask
        if known is not None and sections_kept:
            job.coef_code = known.coef
        self._codes[tile] = code_tile(job, self.params)
        cells = self._tiles[tile]
        occupied = cells.count > 0
        if occupied.all():  # the occupied cells in row-major order are every cell: no copies
            total, sums, sumsq = cells.count.ravel(), cells.sum.ravel(), cells.sumsq.ravel()
        else:
            total, sums, sumsq = cells.count[occupied], cells.sum[occupied], cells.sumsq[occupied]
        mean_sum = sums * HEIGHT_QUANTUM_M
        spread = sumsq - mean_sum * mean_sum / total
        self._gridding[tile] = float(np.maximum(spread, 0.0).sum())

    def encode(self, *, target_max_error: float | None = None) -> bytes:
        """The map as a tiled (1.1) ``.dftpc`` file, re-coding only :meth:`changed_tiles`.

        Parameters
        ----------
        target_max_error : float, optional
            Largest error (metres) of any occupied cell, from this update on: every tile coded
            gets a residual layer that keeps its cells within it (0: none). The file states one
            bound for all its tiles, so a bound other than the map's last one codes every tile
            again; None keeps the map's (the cutoff and step stay fixed, as without a target).

        Raises
        ------
        InvalidInputError
            Nothing was added yet, or a bound that is not a number of metres.
        """
        if not self._tiles:
            raise InvalidInputError("the map is empty: add a scan first")
        if target_max_error is not None:
            if isinstance(target_max_error, bool) or not (isinstance(target_max_error, (int, float)) and
                                                          0.0 <= target_max_error <= MAX_COORDINATE_M):
                raise InvalidInputError(f"target_max_error must be a number of metres from 0 (none) to "
                                        f"{MAX_COORDINATE_M:g}, got {target_max_error!r}")
            if float(target_max_error) != self.params.target_max_error:
                self.params = self.params.replace(target_max_error=float(target_max_error))
                self._dirty.update(self._tiles)  # every tile's residual is in steps of the one bound
        changed = self.changed_tiles()
        recount = sorted(self._recount.difference(changed))
        # The tiles coded now, with their cells' heights once computed (a tile's window takes
        # the edges of its neighbours', often coded now as well).
        self._coding = dict.fromkeys(changed + recount)
        try:
            for tile in changed:
                self._code(tile)
            for tile in recount:
                self._code(tile, sections_kept=True)
        finally:
            self._coding = {}
        self._dirty.clear()
        self._mask_dirty.clear()
        self._recount.clear()
        return self._write()

    def _write(self) -> bytes:
        """The map's bytes through the one writer: the held tiles and an empty tile around them, no base
        layer, no plane."""
        size = self.tile_size
        held = self.tiles
        i0, j0 = min(i for i, _ in held) - 1, min(j for _, j in held) - 1  # one empty tile around
        tile_rows = max(i for i, _ in held) - i0 + 2
        tile_cols = max(j for _, j in held) - j0 + 2
        tiling = TileGrid(tile_rows * size, tile_cols * size, size)
        ox, oy, oz = self.origin  # type: ignore[misc]
        grid = Grid(x0=ox + j0 * self.span, y0=oy + i0 * self.span, z0=oz, resolution=self.resolution,
                    rows=tiling.rows, cols=tiling.cols)
        writer = MapWriter(grid, self.params, point_count=self.point_count, crs=self.crs, tiling=tiling,
                           overlap=TILE_OVERLAP, base_cycles=0, minor=self._minor)
        for tile in held:  # sorted: ascending tile numbers
            writer.add_code(dataclasses.replace(self._codes[tile], k=(tile[0] - i0) * tile_cols + (tile[1] - j0)))
        floor = math.sqrt(sum(self._gridding[t] for t in held) / self.point_count)
        stats = writer.stats(gridding_rmse=floor, vertical_points=self.point_count)
        base = coding.encode_coefficients(np.zeros(0, dtype=np.int64), radius=np.zeros(0), angle=np.zeros(0),
                                          coder=self.params.coder, progressive=False)
        return writer.finish(stats, coef_count=0, base=base)

    # -- files ---------------------------------------------------------------------------------

    def save(self, path: str | os.PathLike[str], *, state: str | os.PathLike[str] | None = None,
             data: bytes | None = None, before: Sequence[tuple[Path, bytes]] = ()) -> bytes:
        """Write the map and its state (``state``, default :func:`state_path`) in one transaction.

        Both are written to temporaries first (:func:`~dftpcc.io.atomic.atomic_write_all`),
        then renamed: the state first, naming the map's SHA-256, then the map.
        A process killed between the two renames leaves a state ahead of its
        map, which :meth:`from_file` recognises and repairs by coding the map again.

        Parameters
        ----------
        before : list of (path, bytes)
            Other files of the same transaction, renamed before the state
            (:func:`update_file`'s delta: present whenever the state moved on).

        Returns
        -------
        bytes
            The map written (``data`` when given: the bytes of :meth:`encode`).
        """
        data = self.encode() if data is None else data
        digest = hashlib.sha256(data).hexdigest()
        settings, arrays = self._state(digest, self._file_sha256)
        atomic_write_all([*((target, _bytes_writer(content)) for target, content in before),
                          (state_path(path) if state is None else Path(state),
                           lambda tmp: write_state(tmp, settings, arrays)),
                          (Path(path), _bytes_writer(data))])
        self._file_sha256 = digest
        return data

    def _state(self, digest: str, previous: str | None) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The settings and arrays of the state file (:mod:`dftpcc.mapstate`) of the map whose SHA-256 is ``digest``."""
        held = self.tiles
        size = self.tile_size
        settings = dict(resolution=self.resolution, tile_size=size, cutoff=self.params.cutoff, step=self.params.step,
                        origin=list(self.origin or ()), crs=self.crs, point_count=self.point_count,
                        map_sha256=digest, previous_sha256=previous, update_sha256=self.update_sha256)
        figures = np.array([[c.cells, c.squared_error, c.max_error, c.weighted_squared_error]
                            for c in (self._codes[t] for t in held)]).reshape(-1, _FIGURES)
        return settings, dict(tiles=np.array(held, dtype=np.int64).reshape(-1, 2),
                    sum=np.stack([self._tiles[t].sum for t in held]) if held else np.zeros((0, size, size), np.int64),
                    sumsq=np.stack([self._tiles[t].sumsq for t in held]) if held else np.zeros((0, size, size)),
                    count=np.stack([self._tiles[t].count for t in held]) if held else np.zeros((0, size, size),
                                                                                              np.int32),
                    figures=figures,
                    gridding=np.array([self._gridding[t] for t in held]))

    @classmethod
    def from_file(cls, path: str | os.PathLike[str], state: str | os.PathLike[str] | None = None) -> "MapBuilder":
        """Resume a growing map from its file and its state (default :func:`state_path`).

        Untouched tiles keep the bytes they have in the file; the next
        :meth:`encode` codes only the tiles later adds change.

        Raises
        ------
        InvalidInputError
            The map is no growing map (tiled with base reach 0, zero plane),
            it has no state file, or the state belongs to another map or
            disagrees with its settings.
        CorruptFileError
            A damaged map or state file.
        """
        path = Path(path)
        state = state_path(path) if state is None else Path(state)
        data = path.read_bytes()
        source = Source(data)
        header, _ = unpack_source(source, max_cells=None)
        if not is_growing(header):
            why = ("it is not tiled" if header.tiles is None else
                   f"its base layer reaches {header.tiles.base_cycles} cycle(s) per tile" if header.tiles.base_cycles
                   else "it has a detrending plane" if any(header.plane) else "its mask is the whole map's")
            raise InvalidInputError(f"{path}: not a growing map ({why}); a map made by 'dftpcc compress' can be "
                                    f"updated when made with --growable (or start one with 'dftpcc update "
                                    f"NEW.dftpc SCANS --resolution R')")
        if not state.is_file():
            raise InvalidInputError(f"{path}: not a growing map: its state file {state} is missing (a growing map "
                                    f"keeps its cells' sums there; without them it cannot be updated)")
        arrays, settings = read_state(state)
        try:
            builder = cls(settings["resolution"], tile_size=settings["tile_size"], cutoff=settings["cutoff"],
                          step=settings["step"], crs=settings["crs"], origin=settings["origin"])
        except InvalidInputError as exc:
            raise CorruptFileError(f"{state}: the map state's settings are refused: {exc}") from None
        # The residual layers the tiles keep are in steps of the bound the file states.
        builder.params = builder.params.replace(target_max_error=header.params.target_max_error)
        builder.point_count = int(settings["point_count"])
        builder.update_sha256 = settings.get("update_sha256")
        builder._previous_sha256 = settings["previous_sha256"]
        tiles = [tuple(int(v) for v in t) for t in arrays["tiles"]]
        for n, tile in enumerate(tiles):
            builder._tiles[tile] = _Cells(arrays["sum"][n].astype(np.int64), arrays["sumsq"][n].astype(np.float64),
                                          arrays["count"][n].astype(np.int32))
            builder._gridding[tile] = float(arrays["gridding"][n])
        digest = hashlib.sha256(data).hexdigest()
        if digest != settings["map_sha256"]:
            if digest != settings.get("previous_sha256"):
                raise InvalidInputError(f"{path}: its state file {state} belongs to another map (it names the map "
                                        f"{str(settings['map_sha256'])[:16]}..., this one is {digest[:16]}...); give "
                                        f"the state written with this map")
            return builder._recovered(path, state, settings["map_sha256"], on_disk=digest)
        builder._file_sha256 = digest
        builder._check_header(path, header, tiles)
        i0, j0 = min(i for i, _ in tiles) - 1, min(j for _, j in tiles) - 1
        tile_cols = header.tiles.tiling.tile_cols  # type: ignore[union-attr]
        for n, tile in enumerate(tiles):
            k = (tile[0] - i0) * tile_cols + (tile[1] - j0)
            blobs = read_tile(source, header, k)
            cells, squared, largest, weighted = arrays["figures"][n]
            builder._codes[tile] = TileCode(k, bytes(blobs.get(b"MASK", b"")), bytes(blobs.get(b"COEF", b"")),
                                            bytes(blobs.get(b"RESD", b"")), int(cells), float(squared),
                                            float(largest), float(weighted))
        # The map the state lays out again (head, index, statistics from the state; sections from the
        # file) must be the file: an edited state that passes its checksum cannot give another map.
        builder._minor = header.minor
        if builder._write() != data:
            raise InvalidInputError(f"{path}: its state file {state} does not give this map (an edited state, or "
                                    f"one of another version of it); give the state written with this map")
        if header.legacy_order:  # a 1.1 map: its tiles are coded again, in the integer order, at the next encode
            builder._dirty.update(builder._tiles)
            builder._minor = VERSION[1]
        return builder

    def _recovered(self, path: Path, state: Path, expected: str, *, on_disk: str) -> "MapBuilder":
        """A state one update ahead of its map (the map was not written after it): code the map again from it."""
        data = self.encode()
        if hashlib.sha256(data).hexdigest() != expected:
            raise CorruptFileError(f"{state}: the map state does not give the map it names (damaged state)")
        # The next state names the map still on disk as the one it started from (as its delta does):
        # were that update interrupted too, the map on disk is still the one the state knows.
        self._file_sha256 = on_disk
        warnings.warn(f"{path} is older than its state {state} (an update was interrupted before the map was "
                      f"written); the map was coded again from the state", StateRecoveredWarning, stacklevel=3)
        return self

    def _check_header(self, path: Path, header: Header, tiles: list[tuple[int, int]]) -> None:
        """The file agrees with the state: settings, extent and cells."""
        g, p, index = header.grid, header.params, header.tiles
        assert index is not None
        i0, j0 = min(i for i, _ in tiles) - 1, min(j for _, j in tiles) - 1
        ox, oy, oz = self.origin  # type: ignore[misc]
        agree = (math.isclose(g.resolution, self.resolution, rel_tol=1e-12) and index.tiling.size == self.tile_size
                 and p.cutoff == self.params.cutoff and p.step == self.params.step
                 and math.isclose(g.x0, ox + j0 * self.span, abs_tol=1e-6) and
                 math.isclose(g.y0, oy + i0 * self.span, abs_tol=1e-6) and g.z0 == oz
                 and g.angle == 0.0 and header.point_count == self.point_count
                 and header.tiles.tiling.tile_rows == max(i for i, _ in tiles) - i0 + 2
                 and header.tiles.tiling.tile_cols == max(j for _, j in tiles) - j0 + 2)
        if not agree:
            raise InvalidInputError(f"{path}: the map disagrees with its state file (settings or extent); give the "
                                    f"state written with this map")
        cols = index.tiling.tile_cols
        for n, (i, j) in enumerate(tiles):
            if int(index.cells[(i - i0) * cols + (j - j0)]) != int(np.count_nonzero(self._tiles[(i, j)].count)):
                raise InvalidInputError(f"{path}: the map's tile ({i}, {j}) has other occupied cells than its state "
                                        f"file says; give the state written with this map")


def _bytes_writer(content: bytes) -> Callable[[Path], None]:
    return lambda tmp: Path(tmp).write_bytes(content)  # type: ignore[func-returns-value]


class GrowingMap:
    """A growing map opened to add scans: ``dftpcc.open(path, "a")`` resumes one, ``"w"`` starts one.

    Like laspy's appender: :meth:`add` scans (in the map frame, or in the sensor frame with their
    pose), and on :meth:`close` (or leaving ``with``) the map and its state are written, in one
    transaction, if anything was added. An exception inside ``with`` writes nothing. It holds the
    map's lock (``MAP.lock``, as ``dftpcc update`` does) from opening to closing, so an update of
    the same map waits for it. The :class:`MapBuilder` it holds is :attr:`builder`.
    """

    def __init__(self, path: str | os.PathLike[str], builder: MapBuilder, lock: Any = None):
        self.path, self.builder = Path(path), builder
        self._added = False
        self._lock = lock  # an entered ExitStack holding the map's lock

    def _release(self) -> None:
        if self._lock is not None:
            self._lock.close()
            self._lock = None

    def add(self, points: np.ndarray, pose: tuple[np.ndarray, np.ndarray] | None = None) -> "GrowingMap":
        """Add a scan (see :meth:`MapBuilder.add`)."""
        self.builder.add(points, pose)
        self._added = True
        return self

    def close(self) -> None:
        """Write the map and its state if a scan was added since opening, and release the map's lock."""
        try:
            if self._added:
                self.builder.save(self.path)
                self._added = False
        finally:
            self._release()

    def __enter__(self) -> "GrowingMap":
        return self

    def __exit__(self, kind: type | None, *_exc: Any) -> None:
        if kind is None:
            self.close()
        else:
            self._release()

    def __repr__(self) -> str:
        return f"GrowingMap({str(self.path)!r}, {len(self.builder.tiles)} tiles, {self.builder.point_count:,} points)"


def open_growing(path: str | os.PathLike[str], mode: str, **settings: Any) -> GrowingMap:
    """``dftpcc.open(path, "a")``: resume the growing map ``path`` (and its state); ``"w"``: start one there,
    with ``settings`` (``resolution`` required; ``tile_size``, ``cutoff``, ``step``, ``crs``, ``origin``).

    Raises
    ------
    InvalidInputError
        ``"a"`` of a file that is no growing map or has no state, or with settings (they are the
        map's); ``"w"`` without a resolution, or over a write-protected file.
    """
    path = Path(path)
    if mode == "a":
        if settings:
            raise InvalidInputError(f"opening {path} to append takes no settings (they are the map's): "
                                    f"{', '.join(sorted(settings))}")
        if not path.is_file():
            raise InvalidInputError(f"{path}: no such file (open it with mode 'w' to start a growing map)")
    elif "resolution" not in settings:
        raise InvalidInputError("a new growing map needs its cell size: dftpcc.open(path, 'w', resolution=R)")
    else:
        for target in (path, state_path(path)):
            check_output(target, force=True)
    stack = ExitStack()
    stack.enter_context(locked([path]))
    try:
        builder = MapBuilder.from_file(path) if mode == "a" else MapBuilder(settings.pop("resolution"), **settings)
    except BaseException:
        stack.close()
        raise
    return GrowingMap(path, builder, stack)


def _check_origin(origin: Sequence[float]) -> tuple[float, float, float]:
    values = tuple(float(v) for v in origin)
    if len(values) != 3 or not all(math.isfinite(v) and abs(v) <= MAX_COORDINATE_M for v in values):
        raise InvalidInputError(f"origin must be three finite coordinates (x, y, z) in metres, got {origin!r}")
    return values  # type: ignore[return-value]


# -- the update of a map file: what `dftpcc update` runs ------------------------------------------------


@dataclass
class UpdateResult:
    """What :func:`update_file` did.

    Attributes
    ----------
    path : Path
        The map written.
    size : int
        Its bytes.
    scans : int
        Scans (or point files) added.
    points : int
        Points added.
    tiles : int
        Tiles the map holds.
    recoded : int
        Tiles coded again.
    delta_size : int or None
        Bytes of the delta written, if one was asked for.
    created : bool
        Whether the map was started by this update.
    """

    path: Path
    size: int
    scans: int
    points: int
    tiles: int
    recoded: int
    delta_size: int | None
    created: bool
    repeated: bool = False
    """The scans were the map's last update already (a rerun of an update): none was added again."""


def _scans(inputs: Iterable[str | os.PathLike[str]], points_topic: str | None, pose_topic: str | None,
           map_frame: str | None = None
           ) -> Iterable[tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None, dict[str, Any]]]:
    """(points, pose, CRS) of every scan: a bag's scans through their poses, a point file whole, in the map frame."""
    from .io import format_of, read

    for path in inputs:
        if format_of(path) == "rosbag":
            from .io.rosbag import posed_scans

            for scan in posed_scans(path, points_topic, pose_topic or "/odom", map_frame=map_frame):
                yield scan.points, (scan.rotation, scan.translation), {}
        else:
            cloud = read(path)
            yield cloud.points, None, cloud.crs or {}


def update_file(map_path: str | os.PathLike[str], inputs: Sequence[str | os.PathLike[str]], *,
                output: str | os.PathLike[str] | None = None, delta: str | os.PathLike[str] | None = None,
                points_topic: str | None = None, pose_topic: str | None = None, resolution: float | None = None,
                tile_size: int | None = None, cutoff: float | None = None, step: float | None = None,
                force: bool = False, map_frame: str | None = None, new: bool = False,
                waiting: Callable[[Path], None] | None = None,
                on_stage: Callable[..., None] | None = None) -> UpdateResult:
    """Add scans to a growing map and write it with its state (``dftpcc update``).

    ``on_stage`` is called with each stage's name as it starts (``read``: the scans, then
    ``code``, ``write``), as :func:`dftpcc.compress_file` calls it.

    Without ``output`` the map is updated in place. The map and its state
    are written only once every scan was read and added: a failing input
    (a truncated bag) leaves everything as it was. A map that does not
    exist yet is started, with ``resolution`` (required) and the other
    settings.

    Two updates of one map at once are serialised: each holds the map's
    lock (``MAP.lock``, :func:`dftpcc.io.lock.locked`; and the output's
    with ``output``) from before it reads the map until its files are
    written, so the second waits, then reads the map the first wrote: both
    runs' scans end up in the map.

    Parameters
    ----------
    map_path : path
        The growing map (and ``MAP.state`` beside it).
    inputs : sequence of path
        ROS bags (scans placed by the poses of ``pose_topic``, default
        ``/odom``; ``/tf``: the TF tree, up to ``map_frame`` or its root) or
        point files (LAS, LAZ, PLY, ...) in the map frame.
    output : path, optional
        Write the new map (and its state) here instead.
    delta : path, optional
        Also write the delta from the old map to the new one (:mod:`dftpcc.delta`).
    resolution, tile_size, cutoff, step : optional
        Settings of a new map; for an existing one they must be its own.
    new : bool
        Start a new map even where ``map_path`` exists (``dftpcc compress --growable``; replacing a
        file needs ``force``).
    waiting : callable, optional
        Called with the lock file's path when another update holds it, before waiting for it.

    Raises
    ------
    InvalidInputError
        Settings or a CRS other than the map's, a map that is no growing map
        or has no state, an unreadable input; nothing is written.
    """
    map_path = Path(map_path)
    out = Path(output) if output is not None else map_path
    read = {f"the map {map_path}": map_path, f"its state {state_path(map_path)}": state_path(map_path),
            f"its lock {lock_path(map_path)}": lock_path(map_path),
            **{f"the input {path}": path for path in inputs}}
    written = {}
    if output is not None:
        read[f"the lock {lock_path(out)}"] = lock_path(out)
        written.update({f"-o {out}": out, f"the new state {state_path(out)}": state_path(out)})
    if delta is not None:
        written[f"--delta {delta}"] = delta
    check_distinct(written, read)
    for target in [out, state_path(out)] + ([Path(delta)] if delta is not None else []):
        check_output(target, force=force)
    with locked([map_path, out], waiting=waiting):
        return _update_locked(map_path, out, inputs, delta=delta, points_topic=points_topic, pose_topic=pose_topic,
                              resolution=resolution, tile_size=tile_size, cutoff=cutoff, step=step,
                              map_frame=map_frame, new=new, stage=on_stage or (lambda *_: None))


def _update_locked(map_path: Path, out: Path, inputs: Sequence[str | os.PathLike[str]], *,
                   delta: str | os.PathLike[str] | None, points_topic: str | None, pose_topic: str | None,
                   resolution: float | None, tile_size: int | None, cutoff: float | None, step: float | None,
                   map_frame: str | None, new: bool = False,
                   stage: Callable[..., None] = lambda *_: None) -> UpdateResult:
    """:func:`update_file` once the map is locked and the outputs checked."""
    from .delta import make_delta

    created = new or not map_path.exists()
    if created:
        if resolution is None:
            raise InvalidInputError(f"{map_path} does not exist: give --resolution (and --step, --cutoff, "
                                    f"--tile-size if not the defaults) to start a growing map")
        if delta is not None:
            raise InvalidInputError("a delta needs a map to start from: the first update of a map writes none")
        base = b""
        builder = MapBuilder(resolution, tile_size=DEFAULT_GROWING_TILE_SIZE if tile_size is None else tile_size,
                             cutoff=DEFAULT_CUTOFF if cutoff is None else cutoff, step=DEFAULT_STEP_M if step is None else step)
    else:
        base = map_path.read_bytes()
        builder = MapBuilder.from_file(map_path)
        _check_settings(map_path, builder, resolution, tile_size, cutoff, step)
    last_update = builder.update_sha256
    stage("read")
    scans = points = 0
    record = hashlib.sha256()
    for pts, pose, crs in _scans(inputs, points_topic, pose_topic, map_frame):
        if crs:
            if created and scans == 0:
                builder.crs = dict(crs)
            elif not same_crs(crs, builder.crs):
                raise InvalidInputError(f"the scans' CRS is not the map's ({_crs_name(crs)} against "
                                        f"{_crs_name(builder.crs)}): reproject them to the map's CRS first")
        builder.add(pts, pose)
        _record_scan(record, pts, pose)
        scans += 1
        points += int(pts.shape[0])
    if scans == 0:
        raise InvalidInputError("no scan to add")
    if not created and out == map_path and record.hexdigest() == last_update:
        with warnings.catch_warnings():  # the map was recovered from its state once already, and said so
            warnings.simplefilter("ignore", StateRecoveredWarning)
            again = MapBuilder.from_file(map_path)
        return _finish_update(map_path, base, again, delta, scans, points)
    builder.update_sha256 = record.hexdigest()
    recoded = len(builder.changed_tiles())
    stage("code")
    data = builder.encode()
    patch = make_delta(base, data) if delta is not None else None
    stage("write")
    # One transaction, renamed delta first: a kill after it leaves the old map and state (a rerun
    # writes the same delta again) or the new state (a rerun finishes the update: _finish_update).
    builder.save(out, data=data, before=[] if patch is None or delta is None else [(Path(delta), patch)])
    return UpdateResult(out, len(data), scans, points, len(builder.tiles), recoded,
                        None if patch is None else len(patch), created)


def _finish_update(map_path: Path, base: bytes, builder: MapBuilder, delta: str | os.PathLike[str] | None,
                   scans: int, points: int) -> UpdateResult:
    """The scans of an in-place update are the map's last update already: write what that update did not.

    Its state was written; the map too unless it was killed before (then
    ``builder`` recovered it from the state, and ``base`` is the older map).
    The delta was renamed before the state, so it is on disk already unless
    this run asks for it under another name.
    """
    from .delta import make_delta, read_delta

    data = builder.encode()
    digest = hashlib.sha256(data).hexdigest()
    written = hashlib.sha256(base).hexdigest() == digest
    files: list[tuple[Path, Callable[[Path], None]]] = []
    patch = None
    if delta is not None:
        start = base if not written else None
        try:
            known = read_delta(Path(delta).read_bytes())
            if known.result_sha256.hex() == digest and known.base_sha256.hex() == (
                    hashlib.sha256(start).hexdigest() if start is not None else builder._previous_sha256):
                patch = Path(delta).read_bytes()
        except (OSError, DftpccError):
            pass
        if patch is None:
            if start is None:
                raise InvalidInputError(f"{map_path}: its last update added these very scans (nothing added again), "
                                        f"and its delta can no longer be made: the map it started from is gone. "
                                        f"Send the delta that update wrote")
            patch = make_delta(start, data)
            files.append((Path(delta), _bytes_writer(patch)))
    if not written:
        files.append((map_path, _bytes_writer(data)))
    atomic_write_all(files)
    return UpdateResult(map_path, len(data), scans, points, len(builder.tiles), 0,
                        None if patch is None else len(patch), False, repeated=True)


def _record_scan(record: Any, points: np.ndarray, pose: tuple[np.ndarray, np.ndarray] | None) -> None:
    """Add a scan to the SHA-256 of an update's scans (docs/growing-maps.md, *The update's record*)."""
    record.update(np.ascontiguousarray(points, dtype="<f8").tobytes())
    if pose is None:
        record.update(b"none")
    else:
        record.update(np.ascontiguousarray(pose[0], dtype="<f8").tobytes()
                      + np.ascontiguousarray(pose[1], dtype="<f8").tobytes())


def _crs_name(crs: dict[str, Any]) -> str:
    if not crs:
        return "none"
    wkt = crs.get("wkt") or ""
    return (wkt.split('"')[1] if wkt.count('"') >= 2 else "a LAS CRS record") if wkt or crs.get("las_vlrs") else "none"


def _check_settings(path: Path, builder: MapBuilder, resolution: float | None, tile_size: int | None,
                    cutoff: float | None, step: float | None) -> None:
    """Refuse an update asking for other settings than the map's: a growing map keeps its own."""
    asked = {"resolution": (resolution, builder.resolution), "tile size": (tile_size, builder.tile_size),
             "cutoff": (cutoff, builder.params.cutoff), "step": (step, builder.params.step)}
    for name, (want, have) in asked.items():
        if want is not None and not math.isclose(float(want), float(have), rel_tol=1e-9):
            raise InvalidInputError(f"{path}: the map's {name} is {have:g}, not {want:g}: a growing map keeps the "
                                    f"settings it was started with (start another map for another {name})")
