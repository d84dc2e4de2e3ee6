"""Take ``.dftpc`` bytes apart and put them back together with valid checksums.

Used to craft lying headers (a field changed, every CRC made to match) for
the corrupt-file corpus and the fuzz harness: checksums stop damage, not a
deliberately crafted file, so the checks behind them must hold on their own.
Only the container layout (docs/format.md) is assumed here, not the coding
of the MASK and COEF sections.
"""

from __future__ import annotations

import json
import struct
import zlib

import numpy as np

from dftpcc import format as fmt

PREAMBLE = struct.Struct("<8sBBHI")  # magic, major, minor, flags, section count
CRC = struct.Struct("<I")
GEOM = struct.Struct("<ddddIIdQQddd")
GEOM_FIELDS = ("x0", "y0", "z0", "resolution", "rows", "cols", "angle",
               "point_count", "cell_count", "plane_a", "plane_b", "plane_c")

assert PREAMBLE.size == fmt.sections.PREAMBLE.size and GEOM.size == fmt.header.GEOM.size


#: Unsigned LEB128, as the container writes it.
leb128 = fmt.sections.leb128


def _read_leb128(data: bytes, pos: int) -> tuple[int, int] | None:
    """``(value, end)``, or None where the reader would refuse the integer (cut short, over 64 bits)."""
    try:
        value, end = fmt.sections.read_leb128_at(memoryview(data), pos)
    except fmt.sections.TooWide:
        return None
    return None if value is None else (value, end)


def entry(tag: bytes, tile: int, length: int, crc: int) -> bytes:
    """One section table entry: tag, LEB128 tile, LEB128 length, u32 CRC-32."""
    return tag + leb128(tile) + leb128(length) + CRC.pack(crc)


def _parse(data: bytes) -> tuple[list[tuple[bytes, int, int, int, int]], int] | None:
    """``([(tag, tile, length, crc, crc_pos), ...], table_end)`` as far as ``data`` holds a table, else None."""
    if len(data) < PREAMBLE.size:
        return None
    _magic, _major, minor, _flags, count = PREAMBLE.unpack_from(data, 0)
    if count > (fmt.sections.MAX_SECTIONS if minor == 0 else fmt.sections.MAX_SECTIONS_TILED):
        return None
    entries, pos = [], PREAMBLE.size
    for _ in range(count):
        tag = data[pos:pos + 4]
        tile = _read_leb128(data, pos + 4)
        length = tile and _read_leb128(data, tile[1])
        if length is None or length[1] + CRC.size > len(data):
            return None
        pos = length[1]
        entries.append((tag, tile[0], length[0], CRC.unpack_from(data, pos)[0], pos))
        pos += CRC.size
    return entries, pos


def _parsed(data: bytes) -> tuple[list[tuple[bytes, int, int, int, int]], int]:
    parsed = _parse(data)
    if parsed is None:
        raise struct.error("no complete section table")
    return parsed


def table(data: bytes) -> list[tuple[bytes, int, int, int, int]]:
    """Section table entries ``(tag, tile, offset, length, crc)`` of a well-formed file (offsets derived).

    Raises struct.error when ``data`` holds no complete table (as unpacking it would).
    """
    entries, end = _parsed(data)
    offset, out = end + CRC.size, []
    for tag, tile, length, crc, _pos in entries:
        out.append((tag, tile, offset, length, crc))
        offset += length
    return out


def head_size(data: bytes) -> int:
    """Bytes of preamble, table and table CRC: where the first payload starts."""
    return _parsed(data)[1] + CRC.size


def split(data: bytes) -> list[tuple[bytes, bytes]]:
    """``[(tag, payload), ...]`` in table order (tile numbers dropped: see :func:`split_tiled`)."""
    return [(tag, data[off:off + length]) for tag, _tile, off, length, _crc in table(data)]


def split_tiled(data: bytes) -> list[tuple[bytes, int, bytes]]:
    """``[(tag, tile, payload), ...]`` in table order."""
    return [(tag, tile, data[off:off + length]) for tag, tile, off, length, _crc in table(data)]


def version_of(data: bytes) -> tuple[int, int]:
    """(major, minor) of the preamble."""
    _magic, major, minor, _flags, _count = PREAMBLE.unpack_from(data, 0)
    return major, minor


def join_tiled(sections: list[tuple[bytes, int, bytes]], *, version: tuple[int, int] = fmt.sections.VERSION,
               flags: int = 0, count: int | None = None) -> bytes:
    """Bytes of a file holding ``(tag, tile, payload)`` sections, every checksum correct (``count`` may lie)."""
    entries = [entry(tag, tile, len(payload), zlib.crc32(payload)) for tag, tile, payload in sections]
    n = len(sections) if count is None else count
    head = PREAMBLE.pack(fmt.sections.MAGIC, version[0], version[1], flags, n) + b"".join(entries)
    return head + CRC.pack(zlib.crc32(head)) + b"".join(p for _, _, p in sections)


def join(sections: list[tuple[bytes, bytes]], *, version: tuple[int, int] = fmt.sections.VERSION,
         flags: int = 0, count: int | None = None) -> bytes:
    """Bytes of a file holding ``sections``, every checksum correct.

    ``count`` overrides the section count in the preamble (a lying header).
    """
    entries = [entry(tag, 0, len(payload), zlib.crc32(payload)) for tag, payload in sections]
    n = len(sections) if count is None else count
    head = PREAMBLE.pack(fmt.sections.MAGIC, version[0], version[1], flags, n) + b"".join(entries)
    return head + CRC.pack(zlib.crc32(head)) + b"".join(p for _, p in sections)


def replace_section(data: bytes, tag: bytes, payload: bytes | None, *, tile: int = 0) -> bytes:
    """The file with section ``tag`` of ``tile`` replaced (or removed when ``payload`` is None), CRCs fixed.

    Other tiles' sections and the version are kept.
    """
    out = []
    for t, k, p in split_tiled(data):
        if t == tag and k == tile:
            if payload is not None:
                out.append((t, k, payload))
        else:
            out.append((t, k, p))
    return join_tiled(out, version=version_of(data))


def section(data: bytes, tag: bytes, *, tile: int = 0) -> bytes:
    """The payload of the first section ``tag`` of ``tile`` (KeyError when there is none)."""
    for t, k, p in split_tiled(data):
        if t == tag and k == tile:
            return p
    raise KeyError((tag, tile))


def json_of(data: bytes, tag: bytes):
    """The JSON value of section ``tag`` (stored as text, or zstd-compressed text); for STAT,
    which is binary, the fields it stores (:func:`stat_of`)."""
    if tag == b"STAT":
        return stat_of(data)
    return json.loads(fmt.sections.json_text(memoryview(section(data, tag)), tag.decode()))


def with_json(data: bytes, tag: bytes, value) -> bytes:
    """The file with section ``tag`` holding ``value`` as plain JSON text (which readers accept
    for PARM and CRS), CRCs fixed."""
    return replace_section(data, tag, json.dumps(value).encode())


def stat_of(data: bytes) -> dict:
    """The fields the binary STAT section stores (not those the reader derives from the table)."""
    return fmt.header.unpack_stats(memoryview(section(data, b"STAT")))


def with_stat(data: bytes, **changes: float | int | None) -> bytes:
    """The file with some STAT fields changed (None removes one), CRCs fixed.

    Records are laid out as format.md says (marker byte, then id and value, ids ascending),
    without the writer's checks, so a lie can be told: integer fields take any unsigned
    value (wider than 64 bits too), float fields any float, NaN and infinities included.
    """
    ids = {name: i for i, name in fmt.header.STAT_FIELDS.items()}
    fields = stat_of(data)
    fields.update(changes)
    out = bytearray([fmt.header.STAT_BINARY])
    for name, value in sorted(fields.items(), key=lambda kv: ids[kv[0]]):
        if value is None:
            continue
        i = ids[name]
        out.append(i)
        with np.errstate(over="ignore"):  # a lie may overflow float32: it becomes inf, as meant
            out += leb128(int(value)) if i >= 128 else np.float32(value).astype("<f4").tobytes()
    return replace_section(data, b"STAT", bytes(out))


def geom(data: bytes) -> dict[str, float | int]:
    return dict(zip(GEOM_FIELDS, GEOM.unpack(section(data, b"GEOM")[:GEOM.size])))


def with_geom(data: bytes, **changes: float | int) -> bytes:
    """The file with some geometry fields changed (later fields kept as they are), CRCs fixed."""
    fields = geom(data)
    unknown = set(changes) - set(fields)
    if unknown:
        raise KeyError(unknown)
    fields.update(changes)
    tail = section(data, b"GEOM")[GEOM.size:]
    return replace_section(data, b"GEOM", GEOM.pack(*(fields[k] for k in GEOM_FIELDS)) + tail)


def with_table_entry(data: bytes, index: int, **changes: int | bytes) -> bytes:
    """The file with one section table entry changed (tag, tile, length or crc) and the table CRC fixed.

    The payloads stay where they were, so a changed length moves where the
    reader looks for every later section: the lie a crafted file tells.
    """
    entries, end = _parsed(data)
    names = ("tag", "tile", "length", "crc")
    unknown = set(changes) - set(names)
    if unknown:
        raise KeyError(unknown)
    rows = [dict(zip(names, e[:4])) for e in entries]
    rows[index].update(changes)
    head = data[:PREAMBLE.size] + b"".join(entry(**r) for r in rows)
    return head + CRC.pack(zlib.crc32(head)) + data[end + CRC.size:]


def fix_table_crc(data: bytes) -> bytes:
    """Recompute the section-table CRC (as far as the file holds a table)."""
    parsed = _parse(data)
    if parsed is None or len(data) < parsed[1] + CRC.size:
        return data
    end = parsed[1]
    buf = bytearray(data)
    CRC.pack_into(buf, end, zlib.crc32(data[:end]))
    return bytes(buf)


def fix_crcs(data: bytes) -> bytes:
    """Every section CRC and then the table CRC recomputed, best effort, for any bytes.

    Lets a fuzzer's mutation reach the checks behind the checksums: a
    mutated field then looks like a crafted lie, not damage.
    """
    parsed = _parse(data)
    if parsed is None:
        return data
    entries, end = parsed
    buf = bytearray(data)
    offset = end + CRC.size
    for _tag, _tile, length, _crc, crc_pos in entries:
        if offset + length <= len(buf):
            CRC.pack_into(buf, crc_pos, zlib.crc32(bytes(buf[offset:offset + length])))
        offset += length
    return fix_table_crc(bytes(buf))


def with_chunk_kind(data: bytes, tag: bytes, kind: int) -> bytes:
    """The file with every chunk header of the COEF-like section ``tag`` stating ``kind``
    (payloads unchanged; a chunk's CRC covers its payload only), CRCs fixed."""
    payload = bytearray(section(data, tag))
    (count,), pos = struct.unpack_from("<I", payload, 0), 4
    for _ in range(count):
        nbytes = struct.unpack_from("<I", payload, pos + 4)[0]
        struct.pack_into("<I", payload, pos + 12, kind)
        pos += 16 + nbytes
    return replace_section(data, tag, bytes(payload))


# --- the tiled layout (format 1.1) -------------------------------------------------------------------

TIDX_HEAD = struct.Struct("<BIHB")  # coding, tile size T, overlap M, base reach K


def tile_index(data: bytes) -> dict:
    """What TIDX says: ``coding``, ``size`` T, ``overlap`` M, ``cells`` per tile (n), ``figures``
    (the f32 RMSE then maximum error of each occupied tile, as read)."""
    import zstandard

    raw = section(data, b"TIDX")
    coding, size, overlap, reach = TIDX_HEAD.unpack_from(raw, 0)
    if size == 0:
        raise ValueError("tile index states tiles of 0 cells")
    g = geom(data)
    n = -(-g["rows"] // size) * -(-g["cols"] // size)
    body = zstandard.ZstdDecompressor().decompress(raw[TIDX_HEAD.size:])
    cells = np.frombuffer(body[:4 * n], np.uint8).reshape(4, n).T.copy().view("<u4").ravel().astype(np.int64)
    figures = np.frombuffer(body[4 * n:], np.uint8)
    if coding == 2:  # the figures in 4 byte planes too
        figures = figures[: figures.size - figures.size % 4].reshape(4, -1).T.copy()
    with np.errstate(invalid="ignore"):  # a mutated file's figures may be signalling NaNs
        figures = figures.view("<f4").ravel().astype(np.float64)
    return {"coding": coding, "size": size, "overlap": overlap, "reach": reach, "cells": cells,
            "figures": figures}


def pack_tile_index(cells, *, size: int, overlap: int, coding: int = 1, figures=None,
                    content_size: bool = True, reach: int = 1) -> bytes:
    """A TIDX payload: u32 cells per tile as 4 byte planes, then the f32 figures (0.01 m each
    by default: an RMSE and a maximum error per occupied tile; one after another with coding 1, in
    byte planes with coding 2), in one zstd frame."""
    import zstandard

    cells = np.asarray(cells, dtype=np.int64)
    planes = cells.astype("<u4").view(np.uint8).reshape(-1, 4).T.tobytes()
    if figures is None:
        figures = np.full(2 * int(np.count_nonzero(cells)), 0.01)
    figures = np.asarray(figures, "<f4")
    body = planes + (figures.view(np.uint8).reshape(-1, 4).T.tobytes() if coding == 2 else figures.tobytes())
    frame = zstandard.ZstdCompressor(write_content_size=content_size).compress(body)
    return TIDX_HEAD.pack(coding, size, overlap, reach) + frame


def with_tile_index(data: bytes, **changes) -> bytes:
    """The file with TIDX re-coded with some of its fields changed (``cells``, ``size``,
    ``overlap``, ``coding``, ``figures``), CRCs fixed."""
    if "cells" in changes:  # the old counts may not fit the grid any more: read the head only
        coding, size, overlap, reach = TIDX_HEAD.unpack_from(section(data, b"TIDX"), 0)
        index = {"coding": coding, "size": size, "overlap": overlap, "reach": reach, "figures": None}
    else:
        index = tile_index(data)
    index.update(changes)
    return replace_section(data, b"TIDX", pack_tile_index(index["cells"], size=index["size"],
                                                          overlap=index["overlap"], coding=index["coding"],
                                                          figures=index["figures"], reach=index["reach"]))


def tiled_file(rows: int, cols: int, size: int, occupied: dict[int, int], *, overlap: int = 8,
               cutoff: float = 0.8, step: float = 0.01, pad: int = 0, reach: int = 1) -> bytes:
    """A tiled (1.1) map built from nothing: a flat grid of ``rows`` x ``cols`` 1 m cells in tiles of
    ``size``, where tile k (1-based) of ``occupied`` has its first ``occupied[k]`` cells (row-major)
    set, every coefficient 0. ``pad`` bytes of an unknown tile-0 section make the file larger
    (limits that grow with the file's size); ``reach``: the base layer's cycles per tile (TIDX).
    Every checksum is correct, every count consistent:
    the map is sound, only perhaps costly (the corpus's bombs)."""
    from dftpcc import coding, occupancy, spectrum, tiles
    from dftpcc.dem import TileGrid

    tiling = TileGrid(rows, cols, size)
    cells = np.zeros(tiling.count, np.int64)
    sections = []
    for k, count in sorted(occupied.items()):
        h, w = tiling.shape(k - 1)
        mask = np.zeros(h * w, bool)
        mask[:count] = True
        cells[k - 1] = count
        w0, w1, v0, v1 = tiles.coded_window(tiling, k - 1, overlap)
        lay = spectrum.layout("dct", "quantized", (w1 - w0, v1 - v0))
        _order, radii, angles = spectrum.kept_order(lay, cutoff)
        mask_blob = occupancy.encode_mask(mask.reshape(h, w))
        coef_blob = coding.encode_coefficients(np.zeros(radii.size, np.int64), radius=radii, angle=angles,
                                              progressive=False)
        sections += [(b"MASK", k, mask_blob), (b"COEF", k, coef_blob)]
    i, _j, radius, angle = tiles.base_order((rows, cols), size, cutoff, reach)
    base = coding.encode_coefficients(np.zeros(i.size, np.int64), radius=radius, angle=angle, progressive=False)
    total = int(cells.sum())
    geom_blob = GEOM.pack(0.0, 0.0, 0.0, 1.0, rows, cols, 0.0, total, total, 0.0, 0.0, 0.0)
    parm = json.dumps({"step": step, "tile_size": size, "cutoff": cutoff}).encode()
    stat = bytes([fmt.header.STAT_BINARY, 128]) + leb128(int(i.size))
    head = [(b"GEOM", 0, geom_blob), (b"PARM", 0, parm), (b"STAT", 0, stat),
            (b"TIDX", 0, pack_tile_index(cells, size=size, overlap=overlap, reach=reach)),
            (b"BASE", 0, base)]
    if pad:
        head.append((b"XTRA", 0, bytes(pad)))
    return join_tiled(head + sections)
