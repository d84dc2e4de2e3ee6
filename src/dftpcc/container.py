"""Container stage: the ``.dftpc`` byte layout (see docs/format.md).

A file is a fixed preamble, a table of sections (tag, tile, length, CRC-32;
the payloads follow in table order) protected by its own CRC, then the
section payloads. Every section is
checked against its CRC before use, and every size is checked against the
file length before anything is allocated; the grid a header asks for must
also fit a decoding budget that grows with the file's size, so a small
crafted file cannot demand gigabytes (docs/format-validation.md lists every
check). Tile 0 is the whole map; the tile field lets a later tiled layout
add independently coded tiles behind an index without changing this
structure.
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import json
import math
import struct
import warnings
import zlib
from dataclasses import dataclass, field
from typing import Any, BinaryIO

import numpy as np
import zstandard

from .errors import (
    CorruptFileError,
    InvalidInputError,
    LargeGridWarning,
    ResourceLimitError,
    UnsupportedFormatError,
)
from .dem import Grid, TileGrid
from .limits import DECODE_BYTES_PER_CELL, MAX_CELLS, cell_budget
from .params import MAX_COORDINATE_M, Params

__all__ = [
    "MAGIC",
    "VERSION",
    "VERSION_TILED",
    "Header",
    "TileIndex",
    "Source",
    "pack",
    "pack_tiled",
    "tiled_head",
    "unpack",
    "unpack_source",
    "read_tile",
    "leb128",
    "read_leb128",
    "cells_allowed",
    "check_grid",
    "check_header",
    "check_max_bytes",
]

MAGIC = b"\x89DFTPC\r\n"
#: (major, minor). A reader refuses another major; a newer minor may add
#: sections and JSON fields, which an older reader skips.
VERSION = (1, 0)
#: A tiled map (docs/format.md, *Tiles*).
VERSION_TILED = (1, 1)
_PREAMBLE = struct.Struct("<8sBBHI")  # magic, major, minor, flags, section count
# A section table entry: 4-byte tag, LEB128 tile, LEB128 payload length, u32 CRC-32.
_CRC = struct.Struct("<I")
MAX_SECTIONS = 1024
#: Sections of a tiled (1.1) file: tile 0's and three per tile.
MAX_SECTIONS_TILED = 1 << 24
#: Tiles of a 1.1 file, at most, and at most this many per byte of the file.
MAX_TILES = 1 << 20
TILES_PER_FILE_BYTE = 64
#: rows x cols of a tiled map, at most (MAX_CELLS applies to each tile).
MAX_TILED_CELLS = 1 << 36
#: The tile index's coding byte: 1, its errors one after another (read only); 2, in byte planes.
TIDX_CODING = 2
TIDX_CODINGS = (1, 2)
#: The low mantissa bits the writer rounds the tile index's errors up to 0 (format.md, TIDX).
TIDX_ERROR_LOW_BITS = 8
_TIDX_HEAD = struct.Struct("<BIHB")
#: Sections of tile 0 a tiled file must hold, and the sections a tile holds.
REQUIRED_TILED = (b"GEOM", b"PARM", b"STAT", b"TIDX", b"BASE")
TILE_TAGS = (b"MASK", b"COEF", b"RESD")
#: Geometry section: origin x, y, projection-plane z, resolution, rows, cols,
#: angle, original point count, occupied cells, plane a, b, c; then the row
#: spacing (0 for square cells).
_GEOM = struct.Struct("<ddddIIdQQddd")
_GEOM_Y = struct.Struct("<d")
#: Sections the reader needs; unknown tags are skipped.
REQUIRED = (b"GEOM", b"PARM", b"MASK", b"COEF")
#: MAX_COORDINATE_M (from params, which checks steps and targets against it):
#: the largest coordinate, height, grid extent or quantizer step a header may state.
#: Largest plane term ``|a| + |b|*cols + |c|*rows`` a header may state, metres.
MAX_PLANE_M = 1e18
#: LAS variable-length records: 16-bit record id and length, 32-byte description.
_VLR_MAX_ID = 0xFFFF
_VLR_MAX_BYTES = 0xFFFF
_VLR_DESCRIPTION = 32



@dataclass
class Header:
    """Everything about a compressed map except its coefficients and mask.

    Attributes
    ----------
    grid : Grid
    params : Params
        With ``step`` set to the quantizer step actually used (metres).
    point_count : int
        Points in the original cloud.
    cell_count : int
        Occupied cells (= points rebuilt).
    plane : tuple of float
        Detrending plane ``a + b*col + c*row`` in metres (zeros if none).
    crs : dict
        ``{"wkt": str | None, "las_vlrs": [...]}`` as read from the input.
    stats : dict
        Figures measured at compression time (metres, bytes).
    coef_count : int
        Coefficients stored (of a tiled map: its base layer's).
    tiles : TileIndex, optional
        The tile index of a tiled (version 1.1) map.
    """

    grid: Grid
    params: Params
    point_count: int
    cell_count: int
    plane: tuple[float, float, float] = (0.0, 0.0, 0.0)
    crs: dict[str, Any] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)
    coef_count: int = 0
    tiles: "TileIndex | None" = None


@dataclass
class TileIndex:
    """What a tiled file says of its tiles (docs/format.md, ``TIDX``).

    Attributes
    ----------
    tiling : TileGrid
    overlap : int
        Cells of its neighbours a tile's transform also spans on each side.
    base_cycles : int
        Reach of the base layer, cycles per tile (0: none).
    cells : ndarray of int64, shape (n,)
        Rebuilt cells per tile (0: the tile has no sections).
    rmse, max_error : ndarray of float, shape (n,)
        DEM error per tile measured at compression, metres (NaN for empty tiles).
    sections : dict
        Tile (0-based) -> tag -> (offset, length, CRC-32) of its payloads in the file.
    map_mask : bool
        Whether tile 0 holds the map mask (format.md, *Tile sections*): then no tile holds a MASK,
        and a tile's mask is the map mask's cells of it.
    map_resid : bool
        Whether tile 0 holds the map residual (only beside the map mask): then no tile holds a
        RESD, and a tile's residual integers are the map residual's at its cells.
    """

    tiling: TileGrid
    overlap: int
    base_cycles: int
    cells: np.ndarray
    rmse: np.ndarray
    max_error: np.ndarray
    sections: dict[int, dict[bytes, tuple[int, int, int]]] = field(default_factory=dict)
    map_mask: bool = False
    map_resid: bool = False

    def tile_bytes(self, k: int) -> int:
        """Bytes of tile ``k``'s payloads."""
        return sum(length for _, length, _ in self.sections.get(k, {}).values())


def check_grid(grid: Grid, *, point_count: int, cell_count: int, params: Params,
               plane: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
    """Refuse, before any work, a map whose geometry the reader would refuse.

    The reader's checks on GEOM (origin, extent, plane, cells, points,
    row spacing; not the decoding budget, which a writer only warns about),
    run on what the writer is about to state.

    Raises
    ------
    InvalidInputError
        "cannot write this map: <what the reader would say>".
    """
    with _as_writer():
        _check_grid(grid, point_count, cell_count, params, plane)


def check_header(header: Header) -> None:
    """Refuse a header :func:`unpack` would refuse, so no file is written that dftpcc cannot read.

    The reader's checks on geometry, parameters, coefficient count and CRS;
    :func:`pack` runs them first, and also refuses statistics or JSON sections
    the reader could not take.

    Raises
    ------
    InvalidInputError
        "cannot write this map: <what the reader would say>".
    """
    g = header.grid
    with _as_writer():
        if header.tiles is None and header.params.tile_size not in (0, "auto"):
            raise CorruptFileError(f"an untiled map states tiles of {header.params.tile_size} cells")
        _check_grid(g, header.point_count, header.cell_count, header.params, header.plane, header.tiles is not None)
        _check_params(header.params, g.resolution)
        _check_coef_count(header.coef_count, g.size)
        _check_crs(header.crs)


def _check_grid(grid: Grid, point_count: int, cell_count: int, params: Params,
                plane: tuple[float, float, float], tiled: bool = False) -> None:
    if not (_is_count(point_count) and point_count < _U64_LIMIT):
        raise CorruptFileError(f"point count {point_count!r} does not fit the header's 64 bits")
    fields = (grid.x0, grid.y0, grid.z0, grid.resolution, grid.rows, grid.cols, grid.angle,
              point_count, cell_count, *plane)
    # The budget is the reader's default, not a limit of the format: a writer warns (see pack).
    # A tiled map is read tile by tile: its limit is the reader's (unpack_tiled), not the whole-grid budget.
    limit = MAX_TILED_CELLS if tiled else MAX_CELLS
    _check_geometry(fields, limit, 0, limit=limit)
    _check_points(params, point_count, cell_count)
    _check_row_spacing(grid.resolution_y or 0.0, grid.rows)


class _as_writer:
    """Turn the reader's refusal (CorruptFileError) into the writer's (InvalidInputError)."""

    def __enter__(self) -> None:
        return None

    def __exit__(self, kind: type | None, exc: BaseException | None, _tb: Any) -> None:
        if isinstance(exc, CorruptFileError):
            raise InvalidInputError(f"cannot write this map: a reader would refuse the file: {exc}") from None


def pack(header: Header, mask_blob: bytes, coef_blob: bytes, resid_blob: bytes = b"") -> bytes:
    """Serialise a map into ``.dftpc`` bytes.

    ``resid_blob`` is the optional residual layer (max-error guarantee); it
    follows the coefficients, so a prefix of the file still decodes.

    Raises
    ------
    InvalidInputError
        A header the reader would refuse (:func:`check_header`), or
        statistics or JSON sections it could not take: nothing is written
        that dftpcc cannot read.
    """
    check_header(header)
    g = header.grid
    sections = _map_sections(header) + [
        (b"MASK", mask_blob),
        (b"COEF", coef_blob),  # late, so a prefix of the file carries the low frequencies
    ] + ([(b"RESD", resid_blob)] if resid_blob else [])
    data = _assemble([(tag, 0, payload) for tag, payload in sections], VERSION)
    if g.size > cell_budget(len(data)):
        warnings.warn(
            f"this map is a {g.rows} x {g.cols} grid ({g.size:,} cells) in only {len(data):,} bytes; readers "
            f"refuse such a file by default as a possible decompression bomb: open it with "
            f"dftpcc.open(..., max_cells={g.size})", LargeGridWarning, stacklevel=2)
    return data


def _map_sections(header: Header) -> list[tuple[bytes, bytes]]:
    """GEOM, PARM, CRS and STAT: what every file holds at tile 0."""
    g = header.grid
    geom = _GEOM.pack(g.x0, g.y0, g.z0, g.resolution, g.rows, g.cols, g.angle,
                      header.point_count, header.cell_count, *header.plane)
    if g.resolution_y:  # square cells leave the row spacing out
        geom += _GEOM_Y.pack(g.resolution_y)
    info = dict(header.stats, coef_count=header.coef_count)
    return [
        (b"GEOM", geom),
        (b"PARM", _pack_json(_params_for_file(header.params), "PARM")),
    ] + ([(b"CRS ", _pack_json(_crs_for_file(header.crs), "CRS"))] if header.crs else []) + [
        (b"STAT", _pack_stats({k: v for k, v in info.items()
                               if k not in _DERIVED_STATS and not (k in _OPTIONAL_STATS and v == 0)})),
    ]


def _head(entries: list[tuple[bytes, int, int, int]], version: tuple[int, int]) -> bytes:
    """Preamble, section table and the table's CRC for (tag, tile, length, crc) entries."""
    # Payloads follow the table in its order, so an entry needs no offset.
    table = [tag + _leb128(tile) + _leb128(length) + _CRC.pack(crc) for tag, tile, length, crc in entries]
    head = _PREAMBLE.pack(MAGIC, *version, 0, len(entries)) + b"".join(table)
    return head + _CRC.pack(zlib.crc32(head))


def _assemble(sections: list[tuple[bytes, int, bytes]], version: tuple[int, int]) -> bytes:
    head = _head([(tag, tile, len(p), zlib.crc32(p)) for tag, tile, p in sections], version)
    return head + b"".join(p for _, _, p in sections)


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


def entry_bytes(tile: int, length: int) -> int:
    """Bytes of the section table entry of a payload of ``length`` bytes at ``tile``."""
    return 4 + len(_leb128(tile)) + len(_leb128(length)) + _CRC.size


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
    with _as_writer():
        _check_tiled_params(header.params, header.grid, index.tiling.size)
        _check_map_resid(index, header.params)
        # The reader's rule, on the sections written (an occupied tile may have none at all: full,
        # without a residual layer, every coefficient 0).
        written: dict[int, set[bytes]] = {}
        for k, tag, *_ in entries:
            written.setdefault(k, set()).add(tag)
        for k in sorted(set(written) | set(np.flatnonzero(index.cells).tolist())):
            tags = written.get(k, set())
            if tags != _tile_needs(index, header.params, k, tags):
                raise CorruptFileError(f"tile {k + 1} is written with sections {_names(tags)}")
        if int(index.cells.sum()) != header.cell_count:
            raise CorruptFileError("tile cells do not add up to the map's")
    sections = _map_sections(header) + [(b"TIDX", _pack_index(index)), (b"BASE", base_blob)]
    sections += [(tag, blob) for tag, blob in ((b"MASK", map_mask), (b"RESD", map_resid)) if blob]
    table = [(tag, 0, len(p), zlib.crc32(p)) for tag, p in sections]
    table += [(tag, k + 1, length, crc) for k, tag, length, crc in entries]
    if len(table) > MAX_SECTIONS_TILED:
        raise InvalidInputError(f"cannot write this map: {len(table):,} sections, more than the "
                                f"{MAX_SECTIONS_TILED:,} a tiled file holds; choose a larger tile size")
    return _head(table, VERSION_TILED) + b"".join(p for _, p in sections)


def _pack_index(index: TileIndex) -> bytes:
    cells = index.cells.astype("<u4")
    occupied = index.cells > 0
    rmse, max_error = (_f32_coarse_up(values[occupied]) for values in (index.rmse, index.max_error))
    if max_error.size:  # no tile states more than the map's maximum error (their maximum, in STAT)
        max_error = np.minimum(max_error, _f32_coarse_up(index.max_error[occupied].max(keepdims=True), 0))
    errors = np.concatenate([rmse, max_error]).astype("<f4")
    body = b"".join(a.view(np.uint8).reshape(-1, 4).T.tobytes() for a in (cells, errors))
    frame = zstandard.ZstdCompressor(level=19, write_content_size=True).compress(body)
    return _TIDX_HEAD.pack(TIDX_CODING, index.tiling.size, index.overlap, index.base_cycles) + frame


class Source:
    """The bytes of a ``.dftpc`` file: in memory, or an open file read by offset (random access).

    ``read(offset, length)`` returns up to ``length`` bytes (fewer at the
    end); a tiled map opened from a path reads its header and then only the
    tiles asked for.
    """

    def __init__(self, data: bytes | memoryview | None = None, *, file: BinaryIO | None = None,
                 size: int | None = None):
        self._data = memoryview(data) if data is not None else None
        self._file = file
        self.size = len(self._data) if self._data is not None else int(size or 0)
        #: Bytes read so far (the random-access benchmark reports it).
        self.bytes_read = 0

    def read(self, offset: int, length: int) -> memoryview:
        length = max(0, min(length, self.size - offset))
        self.bytes_read += length
        if self._data is not None:
            return self._data[offset:offset + length]
        assert self._file is not None
        self._file.seek(offset)
        return memoryview(self._file.read(length))

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
        self._data = None


#: Bytes of a section table entry, at most: tag, two 10-byte LEB128 integers, CRC.
_ENTRY_MAX_BYTES = 4 + 2 * 10 + 4
#: ... and of a typical one (a tile number and a length of up to 3 LEB128 bytes each).
_ENTRY_TYPICAL_BYTES = 4 + 3 + 3 + 4


def _table_of(source: Source) -> tuple[list[tuple[bytes, int, int, int]], int, int]:
    """The section table of ``source``, where the payloads start, and the minor version."""
    pre = source.read(0, _PREAMBLE.size)
    if len(pre) < _PREAMBLE.size:
        return (*_table(pre), 0)  # refused as too short
    count = min(_PREAMBLE.unpack_from(pre, 0)[4], MAX_SECTIONS_TILED + 1)
    # Most entries are far shorter than the longest: read for a typical one first, then for the longest.
    for per_entry in (_ENTRY_TYPICAL_BYTES, _ENTRY_MAX_BYTES):
        prefix = source.read(0, _PREAMBLE.size + count * per_entry + _CRC.size)
        try:
            entries, start = _table(prefix)
            break
        except CorruptFileError:
            if len(prefix) == source.size or per_entry == _ENTRY_MAX_BYTES:
                raise
    return entries, start, _PREAMBLE.unpack_from(pre, 0)[2]


def _table(data: memoryview) -> tuple[list[tuple[bytes, int, int, int]], int]:
    """The section table as (tag, tile, length, crc) entries, and where the payloads start.

    Checks the preamble and the table's checksum, not the payloads.
    """
    if len(data) < _PREAMBLE.size + _CRC.size:
        raise CorruptFileError(f"not a .dftpc file: only {len(data)} bytes")
    magic, major, minor, _flags, count = _PREAMBLE.unpack_from(data, 0)
    if magic != MAGIC:
        raise CorruptFileError("not a .dftpc file (bad magic bytes)")
    if major != VERSION[0]:
        raise UnsupportedFormatError(
            f".dftpc format version {major}.{minor} is not supported (this reader: {VERSION[0]}.x)")
    allowed = MAX_SECTIONS if minor == 0 else MAX_SECTIONS_TILED
    if count > allowed:
        raise CorruptFileError(f"section table claims {count} sections, more than the {allowed} allowed")
    entries, pos = [], _PREAMBLE.size
    for index in range(count):
        tile = length = None
        try:
            if pos + 4 <= len(data):
                tag = bytes(data[pos:pos + 4])
                tile, pos = _read_leb128(data, pos + 4)
            if tile is not None:
                length, pos = _read_leb128(data, pos)
        except _TooWide:
            raise CorruptFileError(f"section table entry {index} holds an integer wider than 64 bits") from None
        if length is None or pos + _CRC.size > len(data):
            raise CorruptFileError("file is truncated inside its section table")
        (crc,) = _CRC.unpack_from(data, pos)
        pos += _CRC.size
        entries.append((tag, tile, length, crc))
    if len(data) < pos + _CRC.size:
        raise CorruptFileError("file is truncated inside its section table")
    (crc,) = _CRC.unpack_from(data, pos)
    if zlib.crc32(data[:pos]) != crc:
        raise CorruptFileError("section table fails its checksum")
    return entries, pos + _CRC.size


#: An unsigned LEB128 integer holds at most 64 bits: ten groups of 7 bits, the
#: tenth byte holding only bit 63 (0 or 1) and ending the value.
LEB128_MAX_BYTES = 10
_U64_LIMIT = 1 << 64


class _TooWide(Exception):
    """A LEB128 integer of more than 64 bits (callers name where it was)."""


def _read_leb128(data: memoryview, pos: int) -> tuple[int | None, int]:
    """An unsigned LEB128 integer at ``pos`` and the position after it; None when the data ends inside it.

    Raises :class:`_TooWide` for more than :data:`LEB128_MAX_BYTES` bytes or a
    value of 2**64 or more (docs/format.md: a reader refuses those).
    """
    value, shift, end = 0, 0, min(len(data), pos + LEB128_MAX_BYTES)
    while pos < end:
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if not byte & 0x80:
            if value >= _U64_LIMIT:
                raise _TooWide()
            return value, pos
    if shift >= 7 * LEB128_MAX_BYTES:  # ten bytes, all saying more follows
        raise _TooWide()
    return None, pos


def _sections(data: memoryview, *, allow_truncated_coef: bool) -> tuple[dict[bytes, memoryview], dict[bytes, int]]:
    """The checked payload of each tile-0 section, and the length the table declares for it."""
    entries, offset = _table(data)
    # The file ends where its last payload ends (format.md): bytes after it are no
    # part of this map, and reading on silently would hide them. A prefix read on
    # purpose ends earlier, so it passes; one past the end is the whole file.
    end = offset + sum(length for _tag, _tile, length, _crc in entries)
    if len(data) > end:
        raise CorruptFileError(
            f"{len(data) - end:,} trailing byte(s) after the last section, which ends at byte {end:,} "
            f"(two files joined, or data appended in transfer?)")
    found: dict[bytes, memoryview] = {}
    declared: dict[bytes, int] = {}
    for tag, tile, length, crc in entries:
        start, end = offset, offset + length
        offset = end
        name = tag.decode("latin-1").strip()
        if tile != 0 or tag in declared:
            continue  # tiles beyond 0 belong to a later layout; duplicates keep the first
        declared[tag] = length
        if end > len(data):
            if tag == b"COEF" and allow_truncated_coef:
                found[tag] = data[start:] if start <= len(data) else data[0:0]
                continue
            if tag == b"RESD" and allow_truncated_coef:
                continue
            if allow_truncated_coef:  # a prefix asked for on purpose: say how much is needed
                raise CorruptFileError(
                    f"the first {len(data)} bytes end inside section {name}: a partial decode needs "
                    f"at least the first {end} bytes")
            raise CorruptFileError(f"file is truncated: section {name} needs bytes up to {end}, file has {len(data)}")
        payload = data[start:end]
        if zlib.crc32(payload) != crc:
            raise CorruptFileError(f"section {name} fails its checksum (damaged file)")
        found[tag] = payload
    for tag in REQUIRED:
        if tag not in found:
            raise CorruptFileError(f"section {tag.decode().strip()} is missing")
    return found, declared


#: A JSON section may be stored as one zstd frame (it starts with these bytes,
#: which no JSON text does) when that is smaller: a map of a few hundred
#: points should not pay a kilobyte for its metadata.
_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
#: Largest decompressed JSON section a reader accepts (bytes).
MAX_JSON_BYTES = 1 << 20


#: Parameter values a version-1 file leaves out. Frozen here, apart from the
#: library's defaults, so that changing a default later cannot change what
#: an existing file means.
V1_PARAM_DEFAULTS: dict[str, Any] = {
    "cutoff": 0.8, "profile": "compact", "aggregate": "mean", "frame": "axis", "transform": "dct",
    "detrend": "plane", "fill": "consistent", "storage": "quantized", "step": 0.0, "deadzone": 0.1,
    "coder": "ans", "mask": "exact", "target_rmse": 0.0, "target_max_error": 0.0, "target_bpp": 0.0,
    "tile_size": 0,
    "target_reloc": 0.0,
}
#: Statistics the reader derives from the section table instead of storing them.
_DERIVED_STATS = {"mask_bytes": b"MASK", "coef_bytes": b"COEF", "residual_bytes": b"RESD"}
#: Statistics left out when zero.
_OPTIONAL_STATS = ("cells_interpolated",)


def _params_for_file(params: Params) -> dict[str, Any]:
    full = json.loads(params.to_json())
    if full.get("tile_size") == "auto":  # a file states what it is: 'auto' that did not tile is 0
        full["tile_size"] = 0
    # The resolution is GEOM's cell width; a reader takes it from there.
    return {k: v for k, v in full.items()
            if k != "resolution" and (k not in V1_PARAM_DEFAULTS or V1_PARAM_DEFAULTS[k] != v)}


def _params_from_file(text: str, resolution: float) -> Params:
    stored = json.loads(text)
    if not isinstance(stored, dict):
        raise InvalidInputError("parameters must be a JSON object")
    return Params.from_json(json.dumps(V1_PARAM_DEFAULTS | {"resolution": resolution} | stored))


#: Binary STAT: a marker byte, then records of a u8 field id and its value:
#: ids below 128 hold a float32 (errors rounded up to the next float32, so a
#: stated error stays an upper bound), ids from 128 an unsigned LEB128 integer.
#: A reader skips ids it does not know. The first byte is the coding: binary
#: is the only one (a reader refuses another).
STAT_BINARY = 0x01
STAT_FIELDS: dict[int, str] = {
    0: "dem_rmse_m", 1: "dem_max_error_m", 2: "gridding_rmse_m", 3: "vertical_rmse_m",
    4: "unrepresented_fraction", 5: "unrepresented_rmse_m", 6: "reloc_success_fraction",
    7: "target_rmse_m", 8: "source_nodata", 128: "coef_count", 129: "cells_interpolated", 130: "source_dtype",
}
_STAT_IDS = {name: i for i, name in STAT_FIELDS.items()}
_F32 = struct.Struct("<f")


def read_leb128(data: bytes | memoryview, pos: int, what: str) -> tuple[int, int]:
    """An unsigned LEB128 integer of at most 64 bits at ``pos`` of ``data`` and the position after it
    (docs/format.md); ``what`` names the data in the CorruptFileError a cut or too wide one raises."""
    try:
        value, end = _read_leb128(memoryview(data), pos)
    except _TooWide:
        raise CorruptFileError(f"{what} holds a number wider than 64 bits") from None
    if value is None:
        raise CorruptFileError(f"{what} is truncated (inside a number)")
    return value, end


def leb128(value: int) -> bytes:
    """``value`` (unsigned) as LEB128: 7 bits a byte, least significant first."""
    return _leb128(value)


def _leb128(value: int) -> bytes:
    out = bytearray()
    while True:
        byte, value = value & 0x7F, value >> 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)


def _f32_up(value: float) -> bytes:
    """``value`` as the nearest float32 not below it (finite values stay finite)."""
    f = np.float32(value)
    if float(f) < value:
        f = np.nextafter(f, np.float32(np.inf))
    return _F32.pack(f)


def _f32_coarse_up(values: np.ndarray, low_bits: int = TIDX_ERROR_LOW_BITS) -> np.ndarray:
    """Finite ``values`` >= 0 as float32 not below them whose ``low_bits`` low mantissa bits are 0
    (a carry into the exponent is the next power of two, still not below): zstd shortens those."""
    values = np.asarray(values, dtype=np.float64)
    f = values.astype(np.float32)
    f = np.where(f < values, np.nextafter(f, np.float32(np.inf)), f).astype(np.float32)
    step = np.uint32(1 << low_bits) if low_bits else np.uint32(1)
    bits = f.view(np.uint32)
    coarse = ((bits + (step - np.uint32(1))) & ~(step - np.uint32(1))).view(np.float32)
    return np.where(np.isfinite(coarse), coarse, f).astype(np.float32)


def _pack_stats(stats: dict[str, Any]) -> bytes:
    out = bytearray([STAT_BINARY])
    for name, value in sorted(stats.items(), key=lambda kv: _STAT_IDS.get(kv[0], 256)):
        i = _STAT_IDS.get(name)
        if i is None:
            raise ValueError(f"statistic {name!r} has no STAT field id")
        out.append(i)
        if i >= 128:
            out += _leb128(int(value))
            continue
        packed = _f32_up(float(value))
        if not math.isfinite(_F32.unpack(packed)[0]):  # the reader refuses NaN and infinities
            raise InvalidInputError(f"cannot write this map: statistic {name} = {value!r} is not a finite float32")
        out += packed
    return bytes(out)


def _unpack_stats(payload: memoryview) -> dict[str, Any]:
    raw = bytes(payload)
    if not raw:
        raise CorruptFileError("section STAT is empty")
    if raw[0] != STAT_BINARY:
        raise CorruptFileError(f"section STAT has unknown coding {raw[0]:#04x} (binary STAT starts with "
                               f"{STAT_BINARY:#04x})")
    stats: dict[str, Any] = {}
    pos = 1
    while pos < len(raw):
        i = raw[pos]
        pos += 1
        if i < 128:
            if pos + _F32.size > len(raw):
                raise CorruptFileError("section STAT is truncated")
            (value,) = _F32.unpack_from(raw, pos)
            pos += _F32.size
            if not math.isfinite(value):
                raise CorruptFileError(f"section STAT: field {i} is not finite")
        else:
            try:
                value, pos = _read_leb128(memoryview(raw), pos)
            except _TooWide:
                raise CorruptFileError("section STAT holds an integer wider than 64 bits") from None
            if value is None:
                raise CorruptFileError("section STAT is truncated")
        if i in STAT_FIELDS:
            stats[STAT_FIELDS[i]] = value
    return stats


def _pack_json(obj: Any, name: str) -> bytes:
    raw = json.dumps(obj, sort_keys=True, separators=(",", ":")).encode("utf-8")
    if len(raw) > MAX_JSON_BYTES:  # the reader's limit on a decompressed JSON section
        raise InvalidInputError(f"cannot write this map: section {name} would hold {len(raw):,} bytes of JSON, "
                                f"more than the {MAX_JSON_BYTES} bytes a reader accepts")
    packed = zstandard.ZstdCompressor(level=19).compress(raw)
    return packed if len(packed) < len(raw) else raw


def _json_text(payload: memoryview, name: str) -> str:
    raw = bytes(payload)
    if raw[:4] == _ZSTD_MAGIC:
        try:
            if zstandard.frame_content_size(raw) > MAX_JSON_BYTES:
                raise CorruptFileError(f"section {name} declares more than {MAX_JSON_BYTES} bytes of JSON")
            raw = zstandard.ZstdDecompressor().decompress(raw, max_output_size=MAX_JSON_BYTES)
        except zstandard.ZstdError as exc:
            raise CorruptFileError(f"section {name} does not decompress: {exc}") from None
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise CorruptFileError(f"section {name} is not UTF-8: {exc}") from None


def _crs_for_file(crs: dict[str, Any]) -> dict[str, Any]:
    """The CRS as stored: LAS records that are text travel as text, so the WKT
    (often present twice, as ``wkt`` and as its LAS record) compresses to once."""
    out = dict(crs)
    vlrs = []
    for vlr in crs.get("las_vlrs", []):
        data = base64.b64decode(vlr["data"])
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError:
            vlrs.append(vlr)
            continue
        if text.encode("utf-8") == data:
            vlrs.append({k: v for k, v in vlr.items() if k != "data"} | {"text": text})
        else:
            vlrs.append(vlr)
    if vlrs:
        out["las_vlrs"] = vlrs
    return out


def _crs_from_file(crs: Any) -> Any:
    """Inverse of :func:`_crs_for_file`: every LAS record back to base64 ``data``."""
    if not isinstance(crs, dict) or not isinstance(crs.get("las_vlrs"), list):
        return crs
    vlrs = []
    for vlr in crs["las_vlrs"]:
        if isinstance(vlr, dict) and "data" not in vlr and isinstance(vlr.get("text"), str):
            data = base64.b64encode(vlr["text"].encode("utf-8")).decode("ascii")
            vlr = {k: v for k, v in vlr.items() if k != "text"} | {"data": data}
        vlrs.append(vlr)
    return dict(crs, las_vlrs=vlrs)


def _json(payload: memoryview, name: str) -> Any:
    try:
        return json.loads(_json_text(payload, name)) if len(payload) else {}
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CorruptFileError(f"section {name} is not valid JSON: {exc}") from None
    except RecursionError:  # deeply nested arrays: crafted, never written by dftpcc
        raise CorruptFileError(f"section {name} nests JSON too deeply") from None


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _is_count(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _check_geometry(geom: tuple, budget: int, file_size: int, *, limit: int = MAX_CELLS) -> None:
    """Geometry fields against sane limits and the decoding budget (see the constants above);
    ``limit``: the format's largest grid (:data:`MAX_TILED_CELLS` for a tiled map)."""
    (x0, y0, z0, res, rows, cols, angle, npoints, ncells, pa, pb, pc) = geom
    if not all(math.isfinite(v) for v in (x0, y0, z0, res, angle, pa, pb, pc)) or res <= 0:
        raise CorruptFileError("geometry section holds non-finite or non-positive values")
    if max(abs(x0), abs(y0), abs(z0)) > MAX_COORDINATE_M:
        raise CorruptFileError(f"geometry section states an origin beyond {MAX_COORDINATE_M:g} m")
    if rows == 0 or cols == 0:
        raise CorruptFileError(f"implausible grid {rows} x {cols}")
    if res * max(rows, cols) > MAX_COORDINATE_M:
        raise CorruptFileError(f"grid {rows} x {cols} of {res:g} m cells extends beyond {MAX_COORDINATE_M:g} m")
    if abs(pa) + abs(pb) * cols + abs(pc) * rows > MAX_PLANE_M:
        raise CorruptFileError(f"detrending plane ({pa:g}, {pb:g}, {pc:g}) leaves the map by more than {MAX_PLANE_M:g} m")
    cells = rows * cols
    if cells > budget:
        asks = (f"refusing to decode: the header asks for a {rows:,} x {cols:,} grid ({cells:,} cells, about "
                f"{cells * DECODE_BYTES_PER_CELL / 1e9:,.1f} GB to decode)")
        if cells > limit:
            raise ResourceLimitError(f"{asks}, more than the {limit:,}-cell limit of the format")
        raise ResourceLimitError(
            f"{asks}, more than the {budget:,} cells allowed for a {file_size:,}-byte file; if you trust "
            f"this file, open it with max_cells={cells} (command line: --max-cells {cells})")
    if not 1 <= ncells <= cells:
        raise CorruptFileError(f"implausible grid {rows} x {cols} with {ncells} occupied cells")


def _check_params(params: Params, res: float) -> None:
    # Params may leave these open for the encoder to choose ('auto', None); a file states them.
    if params.cutoff is None:
        raise CorruptFileError("parameter section states no cutoff")
    if not _is_number(params.resolution) or not math.isclose(params.resolution, res, rel_tol=1e-9):
        raise CorruptFileError(f"parameter resolution {params.resolution!r} m disagrees with the grid's {res!r} m")
    if params.storage == "quantized" and not 0.0 < params.step <= MAX_COORDINATE_M:
        raise CorruptFileError(f"quantizer step {params.step!r} m is not in (0, {MAX_COORDINATE_M:g}]")


def _check_points(params: Params, npoints: int, ncells: int) -> None:
    # Every rebuilt cell of an exact mask held a point; a footprint mask also
    # rebuilds enclosed empty cells, so it may have more cells than points.
    if params.mask == "exact" and npoints < ncells:
        raise CorruptFileError(f"header states {npoints} original points for {ncells} occupied cells")


def _check_coef_count(coef_count: Any, cells: int) -> None:
    if not _is_count(coef_count) or coef_count > cells:
        raise CorruptFileError("coefficient count is missing or implausible")


def _check_row_spacing(res_y: float, rows: int) -> None:
    """The optional GEOM row spacing (0 for square cells)."""
    if not (math.isfinite(res_y) and res_y >= 0):
        raise CorruptFileError(f"geometry holds an invalid row spacing {res_y!r}")
    if res_y * rows > MAX_COORDINATE_M:
        raise CorruptFileError(f"grid {rows} rows of {res_y:g} m extend beyond {MAX_COORDINATE_M:g} m")


def _check_crs(crs: Any) -> None:
    """The CRS is written back into LAS, PLY and GeoTIFF outputs, so its shape must be right."""
    if not isinstance(crs, dict):
        raise CorruptFileError("section CRS must be a JSON object")
    wkt = crs.get("wkt")
    if wkt is not None and not isinstance(wkt, str):
        raise CorruptFileError("section CRS: wkt must be a string")
    vlrs = crs.get("las_vlrs", [])
    if not isinstance(vlrs, list):
        raise CorruptFileError("section CRS: las_vlrs must be a list")
    for i, vlr in enumerate(vlrs):
        ok = (isinstance(vlr, dict)
              and isinstance(vlr.get("record_id"), int) and not isinstance(vlr.get("record_id"), bool)
              and 0 <= vlr["record_id"] <= _VLR_MAX_ID
              and isinstance(vlr.get("description", ""), str)
              and len(vlr.get("description", "").encode("utf-8")) <= _VLR_DESCRIPTION
              and isinstance(vlr.get("data"), str))
        if ok:
            try:
                ok = len(base64.b64decode(vlr["data"], validate=True)) <= _VLR_MAX_BYTES
            except (binascii.Error, ValueError):
                ok = False
        if not ok:
            raise CorruptFileError(f"section CRS: LAS record {i} is malformed")


def _grid_and_crs(fields: tuple, geom: memoryview, crs_payload: memoryview | None) -> tuple[Grid, dict[str, Any]]:
    """The grid of checked GEOM ``fields`` (and its optional row spacing), and the checked CRS."""
    crs = _crs_from_file(_json(crs_payload, "CRS")) if crs_payload is not None else {}
    _check_crs(crs)
    (x0, y0, z0, res, rows, cols, angle, *_rest) = fields
    res_y = _GEOM_Y.unpack_from(geom, _GEOM.size)[0] if len(geom) >= _GEOM.size + _GEOM_Y.size else 0.0
    _check_row_spacing(res_y, rows)
    return Grid(x0=x0, y0=y0, z0=z0, resolution=res, rows=rows, cols=cols, angle=angle,
                resolution_y=res_y or None), crs


def _parse_params(payload: memoryview, res: float) -> Params:
    """The PARM section, checked (a file states its cutoff, resolution and step)."""
    try:
        params = _params_from_file(_json_text(payload, "PARM"), res)
    except CorruptFileError as exc:
        raise CorruptFileError(f"parameter section is invalid: {exc}") from None
    except (InvalidInputError, TypeError, UnicodeDecodeError, ValueError, OverflowError) as exc:
        raise CorruptFileError(f"parameter section is invalid: {exc}") from None
    except RecursionError:
        raise CorruptFileError("parameter section nests JSON too deeply") from None
    _check_params(params, res)
    return params


def unpack(data: bytes | memoryview, *, allow_truncated_coef: bool = False,
           max_cells: int | None = None) -> tuple[Header, dict[bytes, memoryview]]:
    """Parse and check ``.dftpc`` bytes.

    Parameters
    ----------
    data : bytes
    allow_truncated_coef : bool
        Accept a COEF section cut short (progressive decoding of a prefix).
    max_cells : int, optional
        Largest grid (rows x cols) to accept; default :func:`cell_budget`
        of ``len(data)``. Never more than :data:`~dftpcc.grid.MAX_CELLS`.

    Returns
    -------
    header : Header
    blobs : dict
        Payloads of the coded sections by tag (``b"MASK"``, ``b"COEF"``,
        ``b"RESD"`` when present), not yet decoded. With
        ``allow_truncated_coef`` a cut-short COEF is returned as far as it
        goes and a missing or cut RESD is left out.

    Raises
    ------
    CorruptFileError
        Bad magic, a failed checksum, a size that does not fit the file, or
        an implausible geometry, parameter or statistics field.
    ResourceLimitError
        The grid is larger than ``max_cells`` (a possible decompression bomb).
    UnsupportedFormatError
        Another major version of the format.
    """
    data = memoryview(data)
    if _is_tiled(_table(data)[0]):
        return unpack_source(Source(data), allow_truncated_coef=allow_truncated_coef, max_cells=max_cells)
    budget = cells_allowed(len(data), max_cells)
    found, declared = _sections(data, allow_truncated_coef=allow_truncated_coef)
    geom = found[b"GEOM"]
    if len(geom) < _GEOM.size:
        raise CorruptFileError("geometry section is too short")
    fields = _GEOM.unpack_from(geom, 0)
    _check_geometry(fields, budget, len(data))
    (x0, y0, z0, res, rows, cols, angle, npoints, ncells, pa, pb, pc) = fields
    params = _parse_params(found[b"PARM"], res)
    if params.tile_size:
        raise CorruptFileError(f"parameters state tiles of {params.tile_size} cells in an untiled (1.0) map")
    _check_points(params, npoints, ncells)
    stats = _unpack_stats(found[b"STAT"]) if b"STAT" in found else {}
    for key, tag in _DERIVED_STATS.items():
        stats.setdefault(key, declared.get(tag, 0))
    coef_count = stats.get("coef_count")
    _check_coef_count(coef_count, rows * cols)
    grid, crs = _grid_and_crs(fields, geom, found.get(b"CRS "))
    header = Header(grid=grid, params=params, point_count=npoints, cell_count=ncells,
                    plane=(pa, pb, pc), crs=crs, stats=stats, coef_count=coef_count)
    return header, {tag: found[tag] for tag in (b"MASK", b"COEF", b"RESD") if tag in found}


def cells_allowed(file_size: int, max_cells: int | None) -> int:
    """The largest grid a file of ``file_size`` bytes may ask for: ``max_cells`` if given
    (never over :data:`~dftpcc.limits.MAX_CELLS`), else :func:`~dftpcc.limits.cell_budget`."""
    check_max_cells(max_cells)
    if max_cells is None:
        return cell_budget(file_size)
    return min(max_cells, MAX_CELLS)


def check_max_cells(max_cells: Any) -> None:
    """Refuse a ``max_cells`` argument that is not None or a positive whole number."""
    if max_cells is not None and (not _is_count(max_cells) or max_cells == 0):
        raise InvalidInputError(f"max_cells must be a positive whole number, got {max_cells!r}")


def check_max_bytes(max_bytes: Any) -> None:
    """Refuse a ``max_bytes`` argument that is not None or a positive whole number of bytes."""
    if max_bytes is not None and (not _is_count(max_bytes) or max_bytes == 0):
        raise InvalidInputError(f"max_bytes must be a positive whole number of bytes, got {max_bytes!r}")


def unpack_source(source: Source, *, allow_truncated_coef: bool = False,
                  max_cells: int | None = None) -> tuple[Header, dict[bytes, memoryview]]:
    """:func:`unpack` from a :class:`Source`: a tiled map reads its table and tile 0 only.

    An untiled map is read whole and parsed as by :func:`unpack`. A tiled
    one returns a header whose ``tiles`` says where each tile's sections lie
    (read them with :func:`read_tile`) and the blobs ``b"BASE"`` and, if tile 0 holds the map mask,
    ``b"MASK"``.
    """
    entries, offset, minor = _table_of(source)
    if not _is_tiled(entries):
        return unpack(source.read(0, source.size), allow_truncated_coef=allow_truncated_coef, max_cells=max_cells)
    if minor < VERSION_TILED[1]:  # format.md: a 1.0 file has no sections of tiles, a tiled map is 1.1
        raise CorruptFileError(f"a version 1.{minor} file holds a tile index (TIDX): a tiled map is version "
                               f"{VERSION_TILED[0]}.{VERSION_TILED[1]}")
    if allow_truncated_coef:
        raise InvalidInputError("a tiled map (format 1.1) has no progressive decoding: read it whole, or a "
                                "region of it with bbox=")
    end = offset + sum(length for _tag, _tile, length, _crc in entries)
    if source.size > end:
        raise CorruptFileError(
            f"{source.size - end:,} trailing byte(s) after the last section, which ends at byte {end:,} "
            f"(two files joined, or data appended in transfer?)")
    found: dict[bytes, tuple[int, int, int]] = {}
    tiles: dict[int, dict[bytes, tuple[int, int, int]]] = {}
    for tag, tile, length, crc in entries:
        start, offset = offset, offset + length
        if tile == 0:
            if tag == b"COEF":  # a MASK there is the map mask, a RESD the map residual
                raise CorruptFileError(f"a tiled map holds no section {tag.decode().strip()} at tile 0")
            found.setdefault(tag, (start, length, crc))
        elif tag in TILE_TAGS:
            tiles.setdefault(tile - 1, {}).setdefault(tag, (start, length, crc))
    payloads: dict[bytes, memoryview] = {}
    for tag in REQUIRED_TILED + (b"CRS ", b"MASK", b"RESD"):
        if tag not in found:
            if tag in (b"CRS ", b"MASK", b"RESD"):
                continue
            raise CorruptFileError(f"section {tag.decode().strip()} is missing")
        start, length, crc = found[tag]
        payloads[tag] = _checked(source, start, length, crc, f"section {tag.decode().strip()}")
    geom = payloads[b"GEOM"]
    if len(geom) < _GEOM.size:
        raise CorruptFileError("geometry section is too short")
    fields = _GEOM.unpack_from(geom, 0)
    _check_geometry(fields, MAX_TILED_CELLS, source.size, limit=MAX_TILED_CELLS)
    (x0, y0, z0, res, rows, cols, angle, npoints, ncells, pa, pb, pc) = fields
    params = _parse_params(payloads[b"PARM"], res)
    _check_points(params, npoints, ncells)
    stats = _unpack_stats(payloads[b"STAT"])
    coef_count = stats.get("coef_count")
    _check_coef_count(coef_count, rows * cols)
    grid, crs = _grid_and_crs(fields, geom, payloads.get(b"CRS "))
    index = _unpack_index(payloads[b"TIDX"], grid, params, ncells, source.size)
    index.map_mask, index.map_resid = b"MASK" in payloads, b"RESD" in payloads
    _check_map_resid(index, params)
    # Any tag: format.md refuses tile numbers above the count, not only those of MASK, COEF, RESD.
    last = max(tile for _tag, tile, _length, _crc in entries)
    if last > index.tiling.count:
        raise CorruptFileError(f"section table names tile {last}, but the map has {index.tiling.count} tiles")
    # Only tiles with cells or with sections can disagree: a loop over all 2**20 tiles a small
    # file may name would cost a second in Python.
    for k in sorted(set(tiles) | set(np.flatnonzero(index.cells).tolist())):
        have = set(tiles.get(k, {}))
        need = _tile_needs(index, params, k, have)
        if have != need:
            raise CorruptFileError(f"tile {k + 1} has sections {_names(have)} where its index entry needs "
                                   f"{_names(need)}")
    index.sections = tiles
    for key, tag in _DERIVED_STATS.items():  # the tiles' sections, and tile 0's BASE, map mask and residual
        stats.setdefault(key, sum(t.get(tag, (0, 0, 0))[1] for t in tiles.values())
                         + found.get(b"BASE" if tag == b"COEF" else tag, (0, 0, 0))[1])
    header = Header(grid=grid, params=params, point_count=npoints, cell_count=ncells,
                    plane=(pa, pb, pc), crs=crs, stats=stats, coef_count=coef_count, tiles=index)
    return header, {tag: payloads[tag] for tag in (b"BASE", b"MASK", b"RESD") if tag in payloads}


def _is_tiled(entries: list[tuple[bytes, int, int, int]]) -> bool:
    """Whether a file's table holds a tile index: the tiled layout (format 1.1)."""
    return any(tag == b"TIDX" and tile == 0 for tag, tile, _, _ in entries)


def _names(tags: set[bytes]) -> str:
    return ", ".join(t.decode().strip() for t in sorted(tags)) or "none"


def _checked(source: Source, start: int, length: int, crc: int, what: str) -> memoryview:
    """A payload read from ``source`` and checked against the file's end and its CRC."""
    if start + length > source.size:
        raise CorruptFileError(f"{what}: file is truncated (it needs bytes up to {start + length}, the file has "
                               f"{source.size})")
    payload = source.read(start, length)
    if zlib.crc32(payload) != crc:
        raise CorruptFileError(f"{what} fails its checksum (damaged file)")
    return payload


def read_tile(source: Source, header: Header, k: int) -> dict[bytes, memoryview]:
    """The checked sections of tile ``k`` (0-based) of a tiled map.

    Raises
    ------
    CorruptFileError
        Naming the tile, when one of its sections is cut or fails its checksum.
    """
    assert header.tiles is not None
    i, j = divmod(k, header.tiles.tiling.tile_cols)
    out = {}
    for tag, (start, length, crc) in header.tiles.sections.get(k, {}).items():
        out[tag] = _checked(source, start, length, crc,
                            f"tile {k + 1} (tile row {i}, column {j}): section {tag.decode().strip()}")
    return out


def _tile_needs(index: TileIndex, params: Params, k: int, have: set[bytes]) -> set[bytes]:
    """The sections tile ``k`` (0-based) must hold, given those it has (format.md, TIDX): MASK and
    COEF, and RESD with a maximum-error target, when it has cells; a full tile may leave its MASK
    out (every cell), any tile its COEF (every coefficient 0); no tile has a MASK with a map mask,
    nor a RESD with a map residual."""
    if not index.cells[k]:
        return set()
    need = {b"MASK", b"COEF"} | ({b"RESD"} if params.target_max_error > 0 and not index.map_resid else set())
    if index.map_mask or (index.cells[k] == math.prod(index.tiling.shape(k)) and b"MASK" not in have):
        need.discard(b"MASK")
    if b"COEF" not in have:
        need.discard(b"COEF")
    return need


def _check_map_resid(index: TileIndex, params: Params) -> None:
    """A RESD at tile 0 is the map residual: it needs the map mask (its cells) and a bound."""
    if index.map_resid and not index.map_mask:
        raise CorruptFileError("a map residual (RESD at tile 0) needs the map mask (MASK at tile 0)")
    if index.map_resid and not params.target_max_error > 0:
        raise CorruptFileError("a map residual (RESD at tile 0) in a file without a maximum-error target")


def _check_tiled_params(params: Params, grid: Grid, size: Any) -> None:
    if not (isinstance(size, int) and 16 <= size <= 65536):
        raise CorruptFileError(f"tile size {size!r} is not in [16, 65536]")
    if params.tile_size != size:
        raise CorruptFileError(f"the tile index says tiles of {size} cells, the parameters {params.tile_size!r}")
    if max(grid.rows, grid.cols) <= size:
        raise CorruptFileError(f"a {grid.rows} x {grid.cols} grid fits one tile of {size} cells: it is no tiled map")
    wrong = {k: v for k, v in (("transform", params.transform), ("storage", params.storage),
                               ("detrend", params.detrend), ("mask", params.mask))
             if v != {"transform": "dct", "storage": "quantized", "detrend": "plane", "mask": "exact"}[k]}
    if wrong:
        raise CorruptFileError(f"a tiled map is coded with the DCT, quantized, a plane and an exact mask, not "
                               f"{', '.join(f'{k}={v}' for k, v in wrong.items())}")
    count = -(-grid.rows // size) * -(-grid.cols // size)
    if count > MAX_TILES:
        raise CorruptFileError(f"{count:,} tiles of {size} cells, more than the {MAX_TILES:,} a file may hold")


def _unpack_index(payload: memoryview, grid: Grid, params: Params, ncells: int, file_size: int) -> TileIndex:
    raw = bytes(payload)
    if len(raw) < _TIDX_HEAD.size:
        raise CorruptFileError("tile index is too short")
    coding, size, overlap, base_cycles = _TIDX_HEAD.unpack_from(raw, 0)
    if coding not in TIDX_CODINGS:
        raise CorruptFileError(f"tile index has unknown coding {coding}")
    _check_tiled_params(params, grid, size)
    if overlap > size // 2:
        raise CorruptFileError(f"tile overlap {overlap} is more than half the tile size {size}")
    tiling = TileGrid(grid.rows, grid.cols, size)
    n = tiling.count
    if n > TILES_PER_FILE_BYTE * file_size:
        raise CorruptFileError(f"{n:,} tiles in a {file_size:,}-byte file: more than {TILES_PER_FILE_BYTE} "
                               f"a byte (crafted?)")
    frame = raw[_TIDX_HEAD.size:]
    try:
        declared = zstandard.frame_content_size(frame)
    except zstandard.ZstdError as exc:
        raise CorruptFileError(f"tile index does not decompress: {exc}") from None
    if declared < 0:  # zstandard's CONTENTSIZE_UNKNOWN: format.md requires the size be stated
        raise CorruptFileError("tile index's zstd frame does not state its content size")
    if declared < 4 * n or declared > 12 * n:
        raise CorruptFileError(f"tile index declares {declared} bytes, not 4 per tile and 8 per occupied tile "
                               f"of {n} tiles")
    try:
        body = zstandard.ZstdDecompressor().decompress(frame, max_output_size=declared)
    except zstandard.ZstdError as exc:
        raise CorruptFileError(f"tile index does not decompress: {exc}") from None
    if len(body) != declared:
        raise CorruptFileError("tile index is shorter than it declares")
    cells = np.frombuffer(body[: 4 * n], dtype=np.uint8).reshape(4, n).T.copy().view("<u4").ravel().astype(np.int64)
    occupied = np.flatnonzero(cells)
    if declared != 4 * n + 8 * occupied.size:
        raise CorruptFileError(f"tile index holds {declared} bytes where {n} tiles, {occupied.size} occupied, "
                               f"need {4 * n + 8 * occupied.size}")
    for k in occupied:
        h, w = tiling.shape(int(k))
        if cells[k] > h * w:
            raise CorruptFileError(f"tile {k + 1} claims {cells[k]} cells in a {h} x {w} tile")
    if int(cells.sum()) != ncells:
        raise CorruptFileError(f"the tiles' cells add up to {int(cells.sum())}, the map states {ncells}")
    errors = np.frombuffer(body[4 * n:], dtype=np.uint8)
    if coding == 2:  # byte planes
        errors = errors.reshape(4, -1).T.copy()
    errors = errors.view("<f4").ravel().astype(np.float64)
    if not (np.isfinite(errors).all() and (errors >= 0).all()):
        raise CorruptFileError("tile index holds a negative or non-finite error")
    rmse, max_error = np.full(n, np.nan), np.full(n, np.nan)
    rmse[occupied], max_error[occupied] = errors[: occupied.size], errors[occupied.size:]
    return TileIndex(tiling=tiling, overlap=overlap, base_cycles=base_cycles, cells=cells, rmse=rmse,
                     max_error=max_error)
