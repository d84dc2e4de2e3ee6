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

from dftpcc import container

PREAMBLE = struct.Struct("<8sBBHI")  # magic, major, minor, flags, section count
CRC = struct.Struct("<I")
GEOM = struct.Struct("<ddddIIdQQddd")
GEOM_FIELDS = ("x0", "y0", "z0", "resolution", "rows", "cols", "angle",
               "point_count", "cell_count", "plane_a", "plane_b", "plane_c")

assert PREAMBLE.size == container._PREAMBLE.size and GEOM.size == container._GEOM.size


#: Unsigned LEB128, as the container writes it.
leb128 = container._leb128


def _read_leb128(data: bytes, pos: int) -> tuple[int, int] | None:
    """``(value, end)``, or None where the reader would refuse the integer (cut short, over 64 bits)."""
    try:
        value, end = container._read_leb128(memoryview(data), pos)
    except container._TooWide:
        return None
    return None if value is None else (value, end)


def entry(tag: bytes, tile: int, length: int, crc: int) -> bytes:
    """One section table entry: tag, LEB128 tile, LEB128 length, u32 CRC-32."""
    return tag + leb128(tile) + leb128(length) + CRC.pack(crc)


def _parse(data: bytes) -> tuple[list[tuple[bytes, int, int, int, int]], int] | None:
    """``([(tag, tile, length, crc, crc_pos), ...], table_end)`` as far as ``data`` holds a table, else None."""
    if len(data) < PREAMBLE.size:
        return None
    count = PREAMBLE.unpack_from(data, 0)[4]
    if count > container.MAX_SECTIONS:
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
    """``[(tag, payload), ...]`` in table order."""
    return [(tag, data[off:off + length]) for tag, _tile, off, length, _crc in table(data)]


def join(sections: list[tuple[bytes, bytes]], *, version: tuple[int, int] = container.VERSION,
         flags: int = 0, count: int | None = None) -> bytes:
    """Bytes of a file holding ``sections``, every checksum correct.

    ``count`` overrides the section count in the preamble (a lying header).
    """
    entries = [entry(tag, 0, len(payload), zlib.crc32(payload)) for tag, payload in sections]
    n = len(sections) if count is None else count
    head = PREAMBLE.pack(container.MAGIC, version[0], version[1], flags, n) + b"".join(entries)
    return head + CRC.pack(zlib.crc32(head)) + b"".join(p for _, p in sections)


def replace_section(data: bytes, tag: bytes, payload: bytes | None) -> bytes:
    """The file with section ``tag`` replaced (or removed when ``payload`` is None), CRCs fixed."""
    out = []
    for t, p in split(data):
        if t == tag:
            if payload is not None:
                out.append((t, payload))
        else:
            out.append((t, p))
    return join(out)


def section(data: bytes, tag: bytes) -> bytes:
    return dict(split(data))[tag]


def json_of(data: bytes, tag: bytes):
    """The JSON value of section ``tag`` (stored as text, or zstd-compressed text); for STAT,
    which is binary, the fields it stores (:func:`stat_of`)."""
    if tag == b"STAT":
        return stat_of(data)
    return json.loads(container._json_text(memoryview(section(data, tag)), tag.decode()))


def with_json(data: bytes, tag: bytes, value) -> bytes:
    """The file with section ``tag`` holding ``value`` as plain JSON text (which readers accept
    for PARM and CRS), CRCs fixed."""
    return replace_section(data, tag, json.dumps(value).encode())


def stat_of(data: bytes) -> dict:
    """The fields the binary STAT section stores (not those the reader derives from the table)."""
    return container._unpack_stats(memoryview(section(data, b"STAT")))


def with_stat(data: bytes, **changes: float | int | None) -> bytes:
    """The file with some STAT fields changed (None removes one), CRCs fixed.

    Records are laid out as format.md says (marker byte, then id and value, ids ascending),
    without the writer's checks, so a lie can be told: integer fields take any unsigned
    value (wider than 64 bits too), float fields any float, NaN and infinities included.
    """
    ids = {name: i for i, name in container.STAT_FIELDS.items()}
    fields = stat_of(data)
    fields.update(changes)
    out = bytearray([container.STAT_BINARY])
    for name, value in sorted(fields.items(), key=lambda kv: ids[kv[0]]):
        if value is None:
            continue
        i = ids[name]
        out.append(i)
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
