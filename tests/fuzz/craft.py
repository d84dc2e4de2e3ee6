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

from dftpcc import container

PREAMBLE = struct.Struct("<8sBBHI")  # magic, major, minor, flags, section count
ENTRY = struct.Struct("<4sIQQI")  # tag, tile, offset, length, crc32
CRC = struct.Struct("<I")
GEOM = struct.Struct("<ddddIIdQQddd")
GEOM_FIELDS = ("x0", "y0", "z0", "resolution", "rows", "cols", "angle",
               "point_count", "cell_count", "plane_a", "plane_b", "plane_c")

assert PREAMBLE.size == container._PREAMBLE.size and ENTRY.size == container._ENTRY.size
assert GEOM.size == container._GEOM.size


def table(data: bytes) -> list[tuple[bytes, int, int, int, int]]:
    """Section table entries ``(tag, tile, offset, length, crc)`` of a well-formed file."""
    count = PREAMBLE.unpack_from(data, 0)[4]
    return [ENTRY.unpack_from(data, PREAMBLE.size + i * ENTRY.size) for i in range(count)]


def split(data: bytes) -> list[tuple[bytes, bytes]]:
    """``[(tag, payload), ...]`` in table order."""
    return [(tag, data[off:off + length]) for tag, _tile, off, length, _crc in table(data)]


def join(sections: list[tuple[bytes, bytes]], *, version: tuple[int, int] = container.VERSION,
         flags: int = 0, count: int | None = None) -> bytes:
    """Bytes of a file holding ``sections``, every checksum correct.

    ``count`` overrides the section count in the preamble (a lying header).
    """
    offset = PREAMBLE.size + len(sections) * ENTRY.size + CRC.size
    entries = []
    for tag, payload in sections:
        entries.append(ENTRY.pack(tag, 0, offset, len(payload), zlib.crc32(payload)))
        offset += len(payload)
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
    """The JSON value of section ``tag`` (stored as text, or zstd-compressed text; STAT may be binary)."""
    if tag == b"STAT":
        return container._unpack_stats(memoryview(section(data, tag)))
    return json.loads(container._json_text(memoryview(section(data, tag)), tag.decode()))


def with_json(data: bytes, tag: bytes, value) -> bytes:
    """The file with section ``tag`` holding ``value`` as plain JSON text (which readers accept), CRCs fixed."""
    return replace_section(data, tag, json.dumps(value).encode())


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
    """The file with one section table entry changed and the table CRC fixed (payload CRCs not)."""
    entries = table(data)
    names = ("tag", "tile", "offset", "length", "crc")
    entry = dict(zip(names, entries[index]))
    entry.update(changes)
    buf = bytearray(data)
    ENTRY.pack_into(buf, PREAMBLE.size + index * ENTRY.size, *(entry[k] for k in names))
    return fix_table_crc(bytes(buf))


def fix_table_crc(data: bytes) -> bytes:
    """Recompute the section-table CRC (as far as the file holds a table)."""
    if len(data) < PREAMBLE.size:
        return data
    count = PREAMBLE.unpack_from(data, 0)[4]
    end = PREAMBLE.size + count * ENTRY.size
    if count > container.MAX_SECTIONS or len(data) < end + CRC.size:
        return data
    buf = bytearray(data)
    CRC.pack_into(buf, end, zlib.crc32(data[:end]))
    return bytes(buf)


def fix_crcs(data: bytes) -> bytes:
    """Every section CRC and then the table CRC recomputed, best effort, for any bytes.

    Lets a fuzzer's mutation reach the checks behind the checksums: a
    mutated field then looks like a crafted lie, not damage.
    """
    if len(data) < PREAMBLE.size:
        return data
    count = PREAMBLE.unpack_from(data, 0)[4]
    if count > container.MAX_SECTIONS or len(data) < PREAMBLE.size + count * ENTRY.size:
        return data
    buf = bytearray(data)
    for i in range(count):
        pos = PREAMBLE.size + i * ENTRY.size
        tag, tile, off, length, _crc = ENTRY.unpack_from(buf, pos)
        if off + length <= len(buf):
            ENTRY.pack_into(buf, pos, tag, tile, off, length, zlib.crc32(bytes(buf[off:off + length])))
    return fix_table_crc(bytes(buf))
