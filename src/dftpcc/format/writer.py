"""The one writer of ``.dftpc`` bytes (docs/format.md): the header, the tile index and the
section table are built here, and every map (whole, band by band, growing, re-stated) is
written through it.
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import tempfile
import warnings
import zlib
from typing import Any, BinaryIO

import numpy as np

from ..dem import Grid, TileGrid
from ..errors import CorruptFileError, InvalidInputError, LargeGridWarning
from ..limits import cell_budget
from ..params import Params
from .header import DERIVED_STATS, Header, check_header, header_sections
from .index import TileIndex, check_map_resid, pack_index, tile_needs
from .reader import read_tile, unpack_source
from .sections import MAX_SECTIONS_TILED, VERSION, head, names
from .source import Source
from .validate import as_writer, check_tiled_params


def pack(header: Header, mask_blob: bytes, coef_blob: bytes, resid_blob: bytes = b"") -> bytes:
    """An untiled map's bytes from its header and coded sections (what :class:`MapWriter` writes of
    the one-tile case).

    ``resid_blob`` is the optional residual layer (max-error guarantee); it
    follows the coefficients, so a prefix of the file still decodes.

    Raises
    ------
    InvalidInputError
        A header the reader would refuse (:func:`check_header`), or
        statistics or JSON sections it could not take: nothing is written
        that dftpcc cannot read.
    """
    payloads = [(b"MASK", mask_blob), (b"COEF", coef_blob)] + ([(b"RESD", resid_blob)] if resid_blob else [])
    data = _untiled_head(header, [(0, tag, len(p), zlib.crc32(p)) for tag, p in payloads]) + \
        b"".join(p for _, p in payloads)
    _warn_large(header.grid, len(data))
    return data


def _untiled_head(header: Header, entries: list[tuple[int, bytes, int, int]]) -> bytes:
    """Preamble, table and header sections of an untiled (1.0) map whose MASK, COEF and RESD
    ``(0, tag, length, crc)`` follow; the checks run first."""
    check_header(header)
    sections = header_sections(header)
    table = [(tag, 0, len(p), zlib.crc32(p)) for tag, p in sections] + [(tag, 0, n, crc) for _, tag, n, crc in entries]
    return head(table, (VERSION[0], header.minor)) + b"".join(p for _, p in sections)


def _warn_large(g: Grid, size: int) -> None:
    if g.size > cell_budget(size):
        warnings.warn(
            f"this map is a {g.rows} x {g.cols} grid ({g.size:,} cells) in only {size:,} bytes; readers "
            f"refuse such a file by default as a possible decompression bomb: open it with "
            f"dftpcc.open(..., max_cells={g.size})", LargeGridWarning, stacklevel=3)


def pack_tiled(header: Header, base_blob: bytes, tiles: list[tuple[int, bytes, bytes, bytes]],
               map_mask: bytes = b"", map_resid: bytes = b"") -> bytes:
    """Serialise a tiled map (version 1.1, docs/format.md *Tiles*).

    Parameters
    ----------
    header : Header
        With ``tiles`` holding the index (cells and errors per tile; its
        ``sections`` are ignored: the writer lays them out).
    base_blob : bytes
        The BASE section.
    tiles : list of (k, mask, coef, resid)
        Each occupied tile (0-based ``k``, ascending) and its sections
        (``resid`` empty without a maximum-error target or with a map residual; ``mask`` empty
        with a map mask).
    map_mask, map_resid : bytes
        The whole grid's MASK and RESD payloads, at tile 0 (empty: the tiles hold their own; a map
        residual needs the map mask).
    """
    return b"".join(tiled_parts(header, base_blob, tiles, map_mask, map_resid))


def tiled_parts(header: Header, base_blob: bytes, tiles: list[tuple[int, bytes, bytes, bytes]],
                map_mask: bytes = b"", map_resid: bytes = b"") -> list[bytes]:
    """:func:`pack_tiled`'s bytes in pieces: the head (preamble, table, tile 0), then each payload."""
    entries, payloads = [], []
    for k, mask_blob, coef_blob, resid_blob in tiles:
        for tag, blob in ((b"MASK", mask_blob), (b"COEF", coef_blob), (b"RESD", resid_blob)):
            if not blob:  # no residual layer; a full tile's mask; all-zero coefficients (format.md, TIDX)
                continue
            entries.append((k, tag, len(blob), zlib.crc32(blob)))
            payloads.append(blob)
    return [tiled_head(header, base_blob, entries, map_mask, map_resid)] + payloads


def tiled_head(header: Header, base_blob: bytes, entries: list[tuple[int, bytes, int, int]],
               map_mask: bytes = b"", map_resid: bytes = b"") -> bytes:
    """The start of a tiled file: preamble, section table and tile 0's payloads, for tile sections
    ``(k, tag, length, crc)`` whose payloads follow it in that order.

    Every check runs here, before anything is written, so a writer that streams the tiles'
    payloads after this head writes a file a reader accepts or nothing (a map coded band by band
    keeps its payloads aside until the table is known).
    """
    check_header(header)
    if header.tiles is None:
        raise ValueError("a tiled header needs its tile index")
    index = dataclasses.replace(header.tiles, map_mask=bool(map_mask), map_resid=bool(map_resid))
    with as_writer():
        check_tiled_params(header.params, header.grid, index.tiling.size)
        check_map_resid(index, header.params)
        # The reader's rule, on the sections written (an occupied tile may have none at all: full,
        # without a residual layer, every coefficient 0).
        written: dict[int, set[bytes]] = {}
        for k, tag, *_ in entries:
            written.setdefault(k, set()).add(tag)
        for k in sorted(set(written) | set(np.flatnonzero(index.cells).tolist())):
            tags = written.get(k, set())
            if tags != tile_needs(index, header.params, k, tags):
                raise CorruptFileError(f"tile {k + 1} is written with sections {names(tags)}")
        if int(index.cells.sum()) != header.cell_count:
            raise CorruptFileError("tile cells do not add up to the map's")
    sections = header_sections(header) + [(b"TIDX", pack_index(index)), (b"BASE", base_blob)]
    sections += [(tag, blob) for tag, blob in ((b"MASK", map_mask), (b"RESD", map_resid)) if blob]
    table = [(tag, 0, len(p), zlib.crc32(p)) for tag, p in sections]
    table += [(tag, k + 1, length, crc) for k, tag, length, crc in entries]
    if len(table) > MAX_SECTIONS_TILED:
        raise InvalidInputError(f"cannot write this map: {len(table):,} sections, more than the "
                                f"{MAX_SECTIONS_TILED:,} a tiled file holds; choose a larger tile size")
    return head(table, (VERSION[0], header.minor)) + b"".join(p for _, p in sections)


#: Statistics of the points one height per cell could not hold (walls, vegetation) a file states,
#: of :meth:`dftpcc.dem.Spread.as_stats`: two figures; the rest would cost a small map more header
#: than its coefficients.
SPREAD_STATS = ("unrepresented_fraction", "unrepresented_rmse_m")


class MapWriter:
    """The one writer of a map: its header fields up front, its tiles added as they are coded, and
    the statistics, the tile index, the header and the section table built once, by :meth:`finish`.

    An untiled (1.0) map is the one-tile case (``tiling=None``, one :meth:`add` at ``k=0``); a
    tiled (1.1) map takes its occupied tiles in ascending order, with its base layer and, if tile 0
    holds them, the map mask and residual at :meth:`finish`. With ``spool=True`` the tiles'
    payloads wait in a temporary file, not in memory, until the table is known (a map coded band
    by band), and :meth:`write_to` streams the file out.

    Parameters
    ----------
    grid : Grid
    params : Params
        As the file states them (cutoff and step chosen).
    point_count : int
        Points of the original cloud (valid pixels of a raster).
    plane : tuple of float
        The detrending plane ``a + b*col + c*row``, metres.
    crs : dict, optional
    tiling : TileGrid, optional
        A tiled map's tiles; ``overlap`` and ``base_cycles`` as in :class:`TileIndex`.
    notes : dict, optional
        PARM fields beside the parameters (:attr:`Header.notes`).
    minor : int
        The minor version to write: the coefficient order the sections follow (:func:`restate` keeps a
        1.0 or 1.1 file's legacy order, and says so).
    """

    def __init__(self, grid: Grid, params: Params, *, point_count: int, plane: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 crs: dict[str, Any] | None = None, tiling: TileGrid | None = None, overlap: int = 0,
                 base_cycles: int = 0, spool: bool = False, notes: dict[str, Any] | None = None,
                 minor: int = VERSION[1]):
        self.grid, self.params, self.point_count, self.plane, self.crs = grid, params, point_count, plane, crs or {}
        self.notes = dict(notes or {})
        self.minor = minor
        self.tiling, self.overlap, self.base_cycles = tiling, overlap, base_cycles
        n = tiling.count if tiling is not None else 1
        self.cells = np.zeros(n, dtype=np.int64)
        self.rmse, self.max_error = np.full(n, np.nan), np.full(n, np.nan)
        self.squared = self.weighted = self.worst = 0.0
        self.entries: list[tuple[int, bytes, int, int]] = []
        self._payloads: list[bytes] = []
        self._spool: BinaryIO | None = tempfile.TemporaryFile(prefix="dftpcc-tiles-") if spool else None

    def add(self, k: int, mask: bytes, coef: bytes, resid: bytes = b"", *, cells: int, squared_error: float,
            max_error: float, weighted_squared_error: float = 0.0) -> None:
        """Tile ``k`` (0-based; 0 of an untiled map) with its sections (empty: none written, as
        docs/format.md allows), its rebuilt cells and the errors it leaves (sums of squares, metres²)."""
        self.add_sections(k, {b"MASK": mask, b"COEF": coef, b"RESD": resid})
        self.cells[k] = cells
        self.rmse[k], self.max_error[k] = math.sqrt(squared_error / cells) if cells else math.nan, max_error
        self.squared += squared_error
        self.weighted += weighted_squared_error
        self.worst = max(self.worst, max_error)

    def add_sections(self, k: int, sections: dict[bytes, Any]) -> None:
        """Tile ``k``'s coded sections alone, in the file's order (an untiled map always has a MASK
        and a COEF; a tile leaves out what it does not need, docs/format.md TIDX)."""
        for tag in (b"MASK", b"COEF", b"RESD"):
            blob = bytes(sections.get(tag, b""))
            if not blob and not (self.tiling is None and tag != b"RESD"):
                continue
            self.entries.append((k, tag, len(blob), zlib.crc32(blob)))
            if self._spool is not None:
                self._spool.write(blob)
            else:
                self._payloads.append(blob)

    def add_code(self, code: Any) -> None:
        """:meth:`add` of a :class:`~dftpcc.tiles.TileCode`."""
        self.add(code.k, code.mask, code.coef, code.resid, cells=code.cells, squared_error=code.squared_error,
                 max_error=code.max_error, weighted_squared_error=code.weighted_squared_error)

    def stats(self, *, gridding_rmse: float, spread: dict[str, Any] | None = None,
              vertical_points: int | None = None, rmse: float | None = None, max_error: float | None = None,
              **extra: Any) -> dict[str, Any]:
        """The figures the file states (docs/format.md, STAT), from the tiles added.

        Parameters
        ----------
        gridding_rmse : float
            The gridding floor, metres.
        spread : dict, optional
            :meth:`~dftpcc.dem.Spread.as_stats` when some points were not represented.
        vertical_points : int, optional
            The points the per-cell weighted errors are averaged over, for ``vertical_rmse_m``
            (points scatter about their cell's mean, so the errors add in quadrature); None: no
            such figure (a raster, or another aggregate than the mean).
        rmse, max_error : float, optional
            The DEM's errors as its coder measured them, metres (an untiled map's, over its
            occupied cells); default from the tiles'.
        extra
            Further STAT fields (``cells_interpolated``, ``target_rmse_m``, ``reloc_success_fraction``).
        """
        occupied = int(self.cells.sum())
        stats: dict[str, Any] = {
            "dem_rmse_m": math.sqrt(self.squared / occupied) if rmse is None else rmse,
            "dem_max_error_m": self.worst if max_error is None else max_error,
            "gridding_rmse_m": gridding_rmse,
        }
        if spread is not None:
            stats.update({key: spread[key] for key in SPREAD_STATS})
        if vertical_points is not None:
            stats["vertical_rmse_m"] = math.sqrt(gridding_rmse * gridding_rmse + self.weighted / vertical_points)
        stats.update(extra)
        return stats

    def header(self, stats: dict[str, Any], *, coef_count: int) -> Header:
        """The header :meth:`finish` writes (``coef_count``: the coefficients an untiled map keeps, or a
        tiled map's base layer's)."""
        index = None
        if self.tiling is not None:
            index = TileIndex(tiling=self.tiling, overlap=self.overlap, base_cycles=self.base_cycles,
                              cells=self.cells, rmse=self.rmse, max_error=self.max_error)
        return Header(grid=self.grid, params=self.params, point_count=self.point_count,
                      cell_count=int(self.cells.sum()), plane=self.plane, crs=self.crs, stats=stats,
                      coef_count=coef_count, tiles=index, notes=self.notes, minor=self.minor)

    def head(self, stats: dict[str, Any], *, coef_count: int, base: bytes = b"", map_mask: bytes = b"",
             map_resid: bytes = b"") -> bytes:
        """The file's start: preamble, section table and tile 0's sections; its tiles' payloads follow
        in the order they were added. Every check runs here, before anything is written."""
        header = self.header(stats, coef_count=coef_count)
        if self.tiling is None:
            return _untiled_head(header, self.entries)
        return tiled_head(header, base, self.entries, map_mask, map_resid)

    def finish(self, stats: dict[str, Any], *, coef_count: int, base: bytes = b"", map_mask: bytes = b"",
               map_resid: bytes = b"") -> bytes:
        """The whole file in memory."""
        start = self.head(stats, coef_count=coef_count, base=base, map_mask=map_mask, map_resid=map_resid)
        if self._spool is not None:
            self._spool.seek(0)
            return start + self._spool.read()
        data = start + b"".join(self._payloads)
        if self.tiling is None:
            _warn_large(self.grid, len(data))
        return data

    def write_payloads(self, out: BinaryIO) -> None:
        """The tiles' payloads, in the order added, after :meth:`head` was written to ``out``
        (spooled ones copied across a megabyte at a time: memory stays flat)."""
        if self._spool is not None:
            self._spool.seek(0)
            shutil.copyfileobj(self._spool, out, 1 << 20)
        else:
            for blob in self._payloads:
                out.write(blob)

    def close(self) -> None:
        """Drop the spooled payloads."""
        if self._spool is not None:
            self._spool.close()
            self._spool = None

    def __enter__(self) -> "MapWriter":
        return self

    def __exit__(self, *_exc: Any) -> None:
        self.close()


def restate(data: bytes, *, notes: dict[str, Any] | None = None, **stats: Any) -> bytes:
    """``data`` with further STAT fields (e.g. ``reloc_success_fraction``) and PARM notes (e.g.
    ``target_reloc``), the map itself unchanged: the same sections, tiles included, re-written
    through :class:`MapWriter`."""
    source = Source(data)
    header, shared = unpack_source(source, max_cells=None)
    writer = MapWriter(header.grid, header.params, point_count=header.point_count, plane=header.plane,
                       crs=header.crs, tiling=header.tiles.tiling if header.tiles else None,
                       overlap=header.tiles.overlap if header.tiles else 0,
                       base_cycles=header.tiles.base_cycles if header.tiles else 0,
                       notes=header.notes | (notes or {}), minor=header.minor)  # the sections' order stays theirs
    if header.tiles is None:
        writer.cells[0] = header.cell_count
        writer.add_sections(0, shared)
    else:
        index = header.tiles
        writer.cells, writer.rmse, writer.max_error = index.cells, index.rmse, index.max_error
        for k in sorted(index.sections):
            writer.add_sections(k, read_tile(source, header, k))
    kept = {k: v for k, v in header.stats.items() if k not in DERIVED_STATS}
    return writer.finish(kept | stats, coef_count=header.coef_count, base=bytes(shared.get(b"BASE", b"")),
                         map_mask=bytes(shared[b"MASK"]) if header.tiles is not None and b"MASK" in shared else b"",
                         map_resid=bytes(shared[b"RESD"]) if header.tiles is not None and b"RESD" in shared else b"")
