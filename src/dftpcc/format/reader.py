"""The one reader of ``.dftpc`` bytes: the table, then the header (:func:`dftpcc.format.header.parse_header`),
then the coded sections; a tiled map's tiles are read on demand (:func:`read_tile`).
"""

from __future__ import annotations

import zlib

import numpy as np

from ..errors import CorruptFileError, InvalidInputError
from .header import DERIVED_STATS, Header, parse_header
from .index import check_map_resid, tile_needs, unpack_index
from .sections import VERSION_TILED, checked, names, table, table_of  # noqa: F401 (table: read by tests)
from .source import Source
from .validate import MAX_TILED_CELLS, cells_allowed

#: Sections of tile 0 a tiled file must hold, and the sections a tile holds.
REQUIRED_TILED = (b"GEOM", b"PARM", b"STAT", b"TIDX", b"BASE")
TILE_TAGS = (b"MASK", b"COEF", b"RESD")
#: Sections the reader needs; unknown tags are skipped.
REQUIRED = (b"GEOM", b"PARM", b"MASK", b"COEF")


def _sections(data: memoryview, *, allow_truncated_coef: bool) -> tuple[dict[bytes, memoryview], dict[bytes, int]]:
    """The checked payload of each tile-0 section, and the length the table declares for it."""
    entries, offset = table(data)
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
    if is_tiled(table(data)[0]):
        return unpack_source(Source(data), allow_truncated_coef=allow_truncated_coef, max_cells=max_cells)
    budget = cells_allowed(len(data), max_cells)
    found, declared = _sections(data, allow_truncated_coef=allow_truncated_coef)
    header = parse_header(found, budget=budget, file_size=len(data))
    header.minor = int(data[9])  # the preamble's minor version (table() checked the preamble is there)
    for key, tag in DERIVED_STATS.items():
        header.stats.setdefault(key, declared.get(tag, 0))
    return header, {tag: found[tag] for tag in (b"MASK", b"COEF", b"RESD") if tag in found}


def unpack_source(source: Source, *, allow_truncated_coef: bool = False,
                  max_cells: int | None = None) -> tuple[Header, dict[bytes, memoryview]]:
    """:func:`unpack` from a :class:`Source`: a tiled map reads its table and tile 0 only.

    An untiled map is read whole and parsed as by :func:`unpack`. A tiled
    one returns a header whose ``tiles`` says where each tile's sections lie
    (read them with :func:`read_tile`) and the blobs ``b"BASE"`` and, if tile 0 holds the map mask,
    ``b"MASK"``.
    """
    entries, offset, minor = table_of(source)
    if not is_tiled(entries):
        return unpack(source.read(0, source.size), allow_truncated_coef=allow_truncated_coef, max_cells=max_cells)
    if minor < VERSION_TILED[1]:  # format.md: a 1.0 file has no sections of tiles, a tiled map is 1.1 or later
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
        payloads[tag] = checked(source, start, length, crc, f"section {tag.decode().strip()}")
    header = parse_header(payloads, budget=MAX_TILED_CELLS, file_size=source.size, limit=MAX_TILED_CELLS, tiled=True)
    header.minor = minor
    grid, params, stats = header.grid, header.params, header.stats
    index = unpack_index(payloads[b"TIDX"], grid, params, header.cell_count, source.size)
    index.map_mask, index.map_resid = b"MASK" in payloads, b"RESD" in payloads
    check_map_resid(index, params)
    # Any tag: format.md refuses tile numbers above the count, not only those of MASK, COEF, RESD.
    last = max(tile for _tag, tile, _length, _crc in entries)
    if last > index.tiling.count:
        raise CorruptFileError(f"section table names tile {last}, but the map has {index.tiling.count} tiles")
    # Only tiles with cells or with sections can disagree: a loop over all 2**20 tiles a small
    # file may name would cost a second in Python.
    for k in sorted(set(tiles) | set(np.flatnonzero(index.cells).tolist())):
        have = set(tiles.get(k, {}))
        need = tile_needs(index, params, k, have)
        if have != need:
            raise CorruptFileError(f"tile {k + 1} has sections {names(have)} where its index entry needs "
                                   f"{names(need)}")
    index.sections = tiles
    for key, tag in DERIVED_STATS.items():  # the tiles' sections, and tile 0's BASE, map mask and residual
        stats.setdefault(key, sum(t.get(tag, (0, 0, 0))[1] for t in tiles.values())
                         + found.get(b"BASE" if tag == b"COEF" else tag, (0, 0, 0))[1])
    header.tiles = index
    return header, {tag: payloads[tag] for tag in (b"BASE", b"MASK", b"RESD") if tag in payloads}


def is_tiled(entries: list[tuple[bytes, int, int, int]]) -> bool:
    """Whether a file's table holds a tile index: the tiled layout (format 1.1)."""
    return any(tag == b"TIDX" and tile == 0 for tag, tile, _, _ in entries)


def tile_sections(data: bytes) -> dict[int, dict[bytes, tuple[int, int, int]]]:
    """Where the sections of each tile of the map ``data`` lie: by tile number (0-based), by tag,
    (start, length, CRC-32); nothing for no bytes or an untiled map (its sections are the map's).

    What a delta or a link frame copies from one version of a map to the next.

    Raises
    ------
    DftpccError
        As :func:`unpack_source`: ``data`` is no map this reader reads.
    """
    if not data:
        return {}
    header, _ = unpack_source(Source(data))
    return {} if header.tiles is None else header.tiles.sections


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
        out[tag] = checked(source, start, length, crc,
                            f"tile {k + 1} (tile row {i}, column {j}): section {tag.decode().strip()}")
    return out
