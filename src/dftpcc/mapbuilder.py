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
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from . import coding, kernels, quantizer
from .format import VERSION, Header, MapWriter, Source, read_tile, unpack_source
from .dem import Grid, TileGrid, as_points
from .grid import HEIGHT_QUANTUM_M, CellSums, lattice_cells
from .encoder import check_heights
from .errors import CorruptFileError, DftpccWarning, InvalidInputError
from .io.atomic import atomic_write_all
from .mapstate import FIGURES as _FIGURES, STATE_VERSION, read_state, write_state
from .params import DEFAULT_CUTOFF, MAX_COORDINATE_M, TILE_SIZES, Params, check_cutoff, make_params
from .tiles import TILE_OVERLAP, TileCode, TileJob, code_tile

__all__ = ["MapBuilder", "state_path", "is_growing", "same_crs",
           "HEIGHT_QUANTUM_M", "Z0_QUANTUM_M", "DEFAULT_STEP_M", "DEFAULT_GROWING_TILE_SIZE", "STATE_SUFFIX",
           "STATE_VERSION", "StateRecoveredWarning"]

#: The map's projection height z0 is the first scan's mean height rounded to this (metres).
Z0_QUANTUM_M = 1.0
#: Quantizer step of a growing map unless given (metres): fixed, since rate control would
#: choose another step as the map grows and so re-code every tile.
DEFAULT_STEP_M = 0.01
#: Tile side of a growing map unless given, cells: a tile is what one update re-codes at least.
DEFAULT_GROWING_TILE_SIZE = 256
#: The state file of ``MAP`` is ``MAP`` + this.
STATE_SUFFIX = ".state"
#: A preview's cell is a block of this many cells a side (:meth:`MapBuilder.preview`).
PREVIEW_BLOCK = 8
#: A preview's quantizer step, metres: a preview is for the eye, coarse in height too.
PREVIEW_STEP_M = 0.05


class StateRecoveredWarning(DftpccWarning):
    """The map was older than its state (an update interrupted between the two writes); rebuilt from the state."""


def state_path(map_path: str | os.PathLike[str]) -> Path:
    """The state file of a growing map: ``MAP.state`` beside it."""
    return Path(f"{os.fspath(map_path)}{STATE_SUFFIX}")


def is_growing(header: Header) -> bool:
    """Whether a map's header is that of a growing map (:attr:`Header.growing`)."""
    return header.growing


def same_crs(a: dict[str, Any] | None, b: dict[str, Any] | None) -> bool:
    """Whether two CRS dicts (``{"wkt": ..., "las_vlrs": [...]}``) say the same; an empty one is no CRS."""
    a, b = a or {}, b or {}
    if not a or not b:
        return not a and not b
    if a.get("wkt") and b.get("wkt"):
        if a["wkt"] == b["wkt"]:
            return True
        try:  # the same CRS written two ways: equal definitions, or one authority code (EPSG:2154 as
            # WKT1 "RGF93 v1 / Lambert-93" from one LAS file and WKT2 "RGF93 / Lambert-93" from another)
            from rasterio.crs import CRS

            first, second = CRS.from_wkt(a["wkt"]), CRS.from_wkt(b["wkt"])
            if first == second:
                return True
            code = first.to_authority(confidence_threshold=100)
            return code is not None and code == second.to_authority(confidence_threshold=100)
        except Exception:  # noqa: BLE001 - unparsable WKT: the texts differ, so do the CRSs
            return False
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)



def check_bound(target_max_error: float | None) -> float | None:
    """A growing map's maximum-error bound as given (metres, 0: none; None: the map's own), checked.

    Raises
    ------
    InvalidInputError
        Not a number of metres from 0 to :data:`~dftpcc.params.MAX_COORDINATE_M`.
    """
    if target_max_error is None:
        return None
    if isinstance(target_max_error, bool) or not (isinstance(target_max_error, (int, float)) and
                                                  0.0 <= target_max_error <= MAX_COORDINATE_M):
        raise InvalidInputError(f"target_max_error must be a number of metres from 0 (none) to "
                                f"{MAX_COORDINATE_M:g}, got {target_max_error!r}")
    return float(target_max_error)

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
                                          step=quantizer.short_step(float(step)), tile_size=int(tile_size))
        self.resolution = float(self.params.resolution)
        self.tile_size = int(tile_size)
        self.crs: dict[str, Any] = dict(crs or {})
        self.origin: tuple[float, float, float] | None = None
        if origin is not None:
            self.origin = _check_origin(origin)
        self.point_count = 0
        self._tiles: dict[tuple[int, int], CellSums] = {}
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
            # Term by term, not ``pts @ rotation.T``: BLAS's product rounds by the machine's kernel (FMA
            # or not), so a point on a cell's edge could fall in another cell on another machine; and on
            # a rover pinned to one core its threads cost ten times the arithmetic.
            pts = (pts[:, 0:1] * rotation[:, 0] + pts[:, 1:2] * rotation[:, 1] + pts[:, 2:3] * rotation[:, 2]
                   + translation)
        self.update_sha256 = None
        check_heights(float(pts[:, 2].min()), float(pts[:, 2].max()))
        if float(np.abs(pts[:, :2]).max()) > MAX_COORDINATE_M:
            raise InvalidInputError(f"points beyond ±{MAX_COORDINATE_M:g} m")
        if self.origin is None:
            mean = pts.mean(axis=0)
            self.origin = (math.floor(mean[0] / self.span) * self.span, math.floor(mean[1] / self.span) * self.span,
                           round(mean[2] / Z0_QUANTUM_M) * Z0_QUANTUM_M)
        size = self.tile_size
        row, col, quanta = lattice_cells(pts, self.origin, self.resolution)
        ti, tj = row // size, col // size
        local = (row - ti * size) * size + (col - tj * size)
        keys = (ti - ti.min()) * (int(tj.max() - tj.min()) + 1) + (tj - tj.min())
        order = np.argsort(keys, kind="stable")
        bounds = np.flatnonzero(np.diff(keys[order])) + 1
        for group in np.split(order, bounds):
            tile = (int(ti[group[0]]), int(tj[group[0]]))
            self._add_to(tile, local[group], quanta[group])
        self.point_count += int(pts.shape[0])
        return self

    def _add_to(self, tile: tuple[int, int], local: np.ndarray, quanta: np.ndarray) -> None:
        size = self.tile_size
        cells = self._tiles.get(tile)
        if cells is None:
            cells = self._tiles[tile] = CellSums.empty((size, size))
        seen, new, moved = cells.add(local, quanta)
        # A cell's height in every window is its mean: a cell seen again whose mean came out the
        # same leaves every section as it was, only the tile's point-weighted error moves.
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

    def preview(self, *, block: int = PREVIEW_BLOCK, step: float = PREVIEW_STEP_M) -> bytes:
        """The map at a coarser cell: a small ``.dftpc`` file a slow link carries ahead of the tiles' detail.

        Every occupied ``block`` x ``block`` block of the lattice (from its origin) gives one point
        at the block's centre at the mean height of the block's points (from the exact sums, so
        the same map gives the same preview whatever the order of its scans), compressed with a
        cell of the block's side (metres: ``block`` times the resolution), the map's cutoff and
        ``step`` (metres). docs/format.md, *Link frames*, the preview.

        Raises
        ------
        InvalidInputError
            Nothing was added yet.
        """
        from .encoder import compress

        if not self._tiles:
            raise InvalidInputError("the map is empty: add a scan first")
        size = self.tile_size
        rows, cols, sums, counts = [], [], [], []
        for (i, j), cells in self._tiles.items():
            r, c = np.nonzero(cells.count)
            rows.append((i * size + r) // block)
            cols.append((j * size + c) // block)
            sums.append(cells.sum[r, c])
            counts.append(cells.count[r, c])
        row, col = np.concatenate(rows), np.concatenate(cols)
        r0, c0 = int(row.min()), int(col.min())
        width = int(col.max()) - c0 + 1
        keys, where = np.unique((row - r0) * width + (col - c0), return_inverse=True)
        # int64 sums of int64 quanta: exact, as the cells' own means are.
        total = np.zeros(keys.size, np.int64)
        np.add.at(total, where, np.concatenate(sums))
        count = np.bincount(where, weights=np.concatenate(counts), minlength=keys.size)
        ox, oy, oz = self.origin  # type: ignore[misc]
        side = block * self.resolution
        br, bc = np.divmod(keys, width)
        points = np.c_[ox + (bc + c0 + 0.5) * side, oy + (br + r0 + 0.5) * side,
                       oz + total / count * HEIGHT_QUANTUM_M]
        return compress(points, resolution=side, cutoff=self.params.cutoff, step=step, crs=self.crs or None)

    # -- coding --------------------------------------------------------------------------------

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
                    whole = self._coding[near] = cells.heights()
                if whole is not None:
                    rest[wr, wc], mask[wr, wc] = whole[0][sr, sc], whole[1][sr, sc]
                else:
                    rest[wr, wc], mask[wr, wc] = cells.part(sr, sc).heights()
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
        self._gridding[tile] = self._tiles[tile].squared_spread()

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
        target_max_error = check_bound(target_max_error)
        if target_max_error is not None:
            if target_max_error != self.params.target_max_error:
                self.params = self.params.replace(target_max_error=target_max_error)
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
        atomic_write_all([*((target, content) for target, content in before),
                          (state_path(path) if state is None else Path(state),
                           lambda tmp: write_state(tmp, settings, arrays)),
                          (Path(path), data)])
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
    def from_file(cls, path: str | os.PathLike[str], state: str | os.PathLike[str] | None = None, *,
                  target_max_error: float | None = None) -> "MapBuilder":
        """Resume a growing map from its file and its state (default :func:`state_path`).

        Untouched tiles keep the bytes they have in the file; the next
        :meth:`encode` codes only the tiles later adds change.

        Parameters
        ----------
        target_max_error : float, optional
            Metres: the bound the update being resumed asked for. Only used to repair a map left
            one update behind its state (the state was written, the map not) when that update
            changed the bound: the state does not record it, the file states the old one.

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
        why = header.why_not_growing()
        if why:
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
            builder._tiles[tile] = CellSums(arrays["sum"][n].astype(np.int64), arrays["sumsq"][n].astype(np.float64),
                                          arrays["count"][n].astype(np.int32))
            builder._gridding[tile] = float(arrays["gridding"][n])
        digest = hashlib.sha256(data).hexdigest()
        if digest != settings["map_sha256"]:
            if digest != settings.get("previous_sha256"):
                raise InvalidInputError(f"{path}: its state file {state} belongs to another map (it names the map "
                                        f"{str(settings['map_sha256'])[:16]}..., this one is {digest[:16]}...); give "
                                        f"the state written with this map")
            return builder._recovered(path, state, settings["map_sha256"], on_disk=digest, bound=target_max_error)
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

    def _recovered(self, path: Path, state: Path, expected: str, *, on_disk: str,
                   bound: float | None = None) -> "MapBuilder":
        """A state one update ahead of its map (the map was not written after it): code the map again from it,
        with the bound the file states (the builder's now), or else ``bound`` (that update's)."""
        bounds = [self.params.target_max_error] + ([float(bound)] if bound is not None else [])
        for tried in dict.fromkeys(bounds):
            data = self.encode(target_max_error=tried)
            if hashlib.sha256(data).hexdigest() == expected:
                break
        else:
            raise CorruptFileError(f"{state}: the map state does not give the map it names with a maximum error of "
                                   f"{' or '.join(f'{b:g} m' for b in dict.fromkeys(bounds))} (a damaged state, or "
                                   f"the interrupted update changed --target-max-error: run it again with it)")
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




def _check_origin(origin: Sequence[float]) -> tuple[float, float, float]:
    values = tuple(float(v) for v in origin)
    if len(values) != 3 or not all(math.isfinite(v) and abs(v) <= MAX_COORDINATE_M for v in values):
        raise InvalidInputError(f"origin must be three finite coordinates (x, y, z) in metres, got {origin!r}")
    return values  # type: ignore[return-value]
