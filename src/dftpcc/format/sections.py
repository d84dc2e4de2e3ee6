"""The ``.dftpc`` bytes at their lowest level (docs/format.md, *Layout*): the preamble, the section
table with its CRC-32s, LEB128 integers, float32 rounding that keeps a stated error an upper bound,
and JSON payloads. Everything above (header, tile index, reader, writer) is made of these.
"""

from __future__ import annotations

import json
import struct
import zlib
from typing import TYPE_CHECKING, Any

import numpy as np
import zstandard

from ..errors import CorruptFileError, InvalidInputError, UnsupportedFormatError

if TYPE_CHECKING:
    from .source import Source

MAGIC = b"\x89DFTPC\r\n"
#: (major, minor). A reader refuses another major; a newer minor may add
#: sections and JSON fields, which an older reader skips.
#: What the writer writes, a tiled map or not: 1.2 orders coefficients by exact integers
#: (docs/format.md, *Which coefficient is which*).
VERSION = (1, 2)
#: The first version with tiled maps (docs/format.md, *Tiles*).
VERSION_TILED = (1, 1)
#: The first minor version with the integer coefficient order; earlier ones keep the legacy
#: order by the C library's ``hypot``.
INTEGER_ORDER_MINOR = 2


def legacy_order(minor: int) -> bool:
    """Whether a file of this minor version orders its coefficients by the legacy ``hypot`` rule."""
    return minor < INTEGER_ORDER_MINOR
PREAMBLE = struct.Struct("<8sBBHI")  # magic, major, minor, flags, section count
# A section table entry: 4-byte tag, LEB128 tile, LEB128 payload length, u32 CRC-32.
CRC = struct.Struct("<I")
MAX_SECTIONS = 1024
#: Sections of a tiled (1.1) file: tile 0's and three per tile.
MAX_SECTIONS_TILED = 1 << 24

#: An unsigned LEB128 integer holds at most 64 bits: ten groups of 7 bits, the
#: tenth byte holding only bit 63 (0 or 1) and ending the value.
LEB128_MAX_BYTES = 10
U64_LIMIT = 1 << 64


class TooWide(Exception):
    """A LEB128 integer of more than 64 bits (callers name where it was)."""


def read_leb128_at(data: memoryview, pos: int) -> tuple[int | None, int]:
    """An unsigned LEB128 integer at ``pos`` and the position after it; None when the data ends inside it.

    Raises :class:`TooWide` for more than :data:`LEB128_MAX_BYTES` bytes or a
    value of 2**64 or more (docs/format.md: a reader refuses those).
    """
    value, shift, end = 0, 0, min(len(data), pos + LEB128_MAX_BYTES)
    while pos < end:
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if not byte & 0x80:
            if value >= U64_LIMIT:
                raise TooWide()
            return value, pos
    if shift >= 7 * LEB128_MAX_BYTES:  # ten bytes, all saying more follows
        raise TooWide()
    return None, pos


def read_leb128(data: bytes | memoryview, pos: int, what: str) -> tuple[int, int]:
    """An unsigned LEB128 integer of at most 64 bits at ``pos`` of ``data`` and the position after it
    (docs/format.md); ``what`` names the data in the CorruptFileError a cut or too wide one raises."""
    try:
        value, end = read_leb128_at(memoryview(data), pos)
    except TooWide:
        raise CorruptFileError(f"{what} holds a number wider than 64 bits") from None
    if value is None:
        raise CorruptFileError(f"{what} is truncated (inside a number)")
    return value, end


def leb128(value: int) -> bytes:
    """``value`` (unsigned) as LEB128: 7 bits a byte, least significant first."""
    out = bytearray()
    while True:
        byte, value = value & 0x7F, value >> 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)


def head(entries: list[tuple[bytes, int, int, int]], version: tuple[int, int]) -> bytes:
    """Preamble, section table and the table's CRC for (tag, tile, length, crc) entries."""
    # Payloads follow the table in its order, so an entry needs no offset.
    rows = [tag + leb128(tile) + leb128(length) + CRC.pack(crc) for tag, tile, length, crc in entries]
    start = PREAMBLE.pack(MAGIC, *version, 0, len(entries)) + b"".join(rows)
    return start + CRC.pack(zlib.crc32(start))


def entry_bytes(tile: int, length: int) -> int:
    """Bytes of the section table entry of a payload of ``length`` bytes at ``tile``."""
    return 4 + len(leb128(tile)) + len(leb128(length)) + CRC.size


#: Bytes of a section table entry, at most: tag, two 10-byte LEB128 integers, CRC.
_ENTRY_MAX_BYTES = 4 + 2 * 10 + 4
#: ... and of a typical one (a tile number and a length of up to 3 LEB128 bytes each).
_ENTRY_TYPICAL_BYTES = 4 + 3 + 3 + 4


def table_of(source: Source) -> tuple[list[tuple[bytes, int, int, int]], int, int]:
    """The section table of ``source``, where the payloads start, and the minor version."""
    pre = source.read(0, PREAMBLE.size)
    if len(pre) < PREAMBLE.size:
        return (*table(pre), 0)  # refused as too short
    count = min(PREAMBLE.unpack_from(pre, 0)[4], MAX_SECTIONS_TILED + 1)
    # Most entries are far shorter than the longest: read for a typical one first, then for the longest.
    for per_entry in (_ENTRY_TYPICAL_BYTES, _ENTRY_MAX_BYTES):
        prefix = source.read(0, PREAMBLE.size + count * per_entry + CRC.size)
        try:
            entries, start = table(prefix)
            break
        except CorruptFileError:
            if len(prefix) == source.size or per_entry == _ENTRY_MAX_BYTES:
                raise
    return entries, start, PREAMBLE.unpack_from(pre, 0)[2]


def table(data: memoryview) -> tuple[list[tuple[bytes, int, int, int]], int]:
    """The section table as (tag, tile, length, crc) entries, and where the payloads start.

    Checks the preamble and the table's checksum, not the payloads.
    """
    if len(data) < PREAMBLE.size + CRC.size:
        raise CorruptFileError(f"not a .dftpc file: only {len(data)} bytes")
    magic, major, minor, _flags, count = PREAMBLE.unpack_from(data, 0)
    if magic != MAGIC:
        raise CorruptFileError("not a .dftpc file (bad magic bytes)")
    if major != VERSION[0]:
        raise UnsupportedFormatError(
            f".dftpc format version {major}.{minor} is not supported (this reader: {VERSION[0]}.x)")
    allowed = MAX_SECTIONS if minor == 0 else MAX_SECTIONS_TILED
    if count > allowed:
        raise CorruptFileError(f"section table claims {count} sections, more than the {allowed} allowed")
    entries, pos = [], PREAMBLE.size
    for index in range(count):
        tile = length = None
        try:
            if pos + 4 <= len(data):
                tag = bytes(data[pos:pos + 4])
                tile, pos = read_leb128_at(data, pos + 4)
            if tile is not None:
                length, pos = read_leb128_at(data, pos)
        except TooWide:
            raise CorruptFileError(f"section table entry {index} holds an integer wider than 64 bits") from None
        if length is None or pos + CRC.size > len(data):
            raise CorruptFileError("file is truncated inside its section table")
        (crc,) = CRC.unpack_from(data, pos)
        pos += CRC.size
        entries.append((tag, tile, length, crc))
    if len(data) < pos + CRC.size:
        raise CorruptFileError("file is truncated inside its section table")
    (crc,) = CRC.unpack_from(data, pos)
    if zlib.crc32(data[:pos]) != crc:
        raise CorruptFileError("section table fails its checksum")
    return entries, pos + CRC.size


def checked(source: Source, start: int, length: int, crc: int, what: str) -> memoryview:
    """A payload read from ``source`` and checked against the file's end and its CRC."""
    if start + length > source.size:
        raise CorruptFileError(f"{what}: file is truncated (it needs bytes up to {start + length}, the file has "
                               f"{source.size})")
    payload = source.read(start, length)
    if zlib.crc32(payload) != crc:
        raise CorruptFileError(f"{what} fails its checksum (damaged file)")
    return payload


#: A JSON section may be stored as one zstd frame (it starts with these bytes,
#: which no JSON text does) when that is smaller: a map of a few hundred
#: points should not pay a kilobyte for its metadata.
_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
#: Largest decompressed JSON section a reader accepts (bytes).
MAX_JSON_BYTES = 1 << 20

def pack_json(obj: Any, name: str) -> bytes:
    raw = json.dumps(obj, sort_keys=True, separators=(",", ":")).encode("utf-8")
    if len(raw) > MAX_JSON_BYTES:  # the reader's limit on a decompressed JSON section
        raise InvalidInputError(f"cannot write this map: section {name} would hold {len(raw):,} bytes of JSON, "
                                f"more than the {MAX_JSON_BYTES} bytes a reader accepts")
    packed = zstandard.ZstdCompressor(level=19).compress(raw)
    return packed if len(packed) < len(raw) else raw


def json_text(payload: memoryview, name: str) -> str:
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


def read_json(payload: memoryview, name: str) -> Any:
    try:
        return json.loads(json_text(payload, name)) if len(payload) else {}
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CorruptFileError(f"section {name} is not valid JSON: {exc}") from None
    except RecursionError:  # deeply nested arrays: crafted, never written by dftpcc
        raise CorruptFileError(f"section {name} nests JSON too deeply") from None


F32 = struct.Struct("<f")


def f32_up(value: float) -> bytes:
    """``value`` as the nearest float32 not below it (finite values stay finite)."""
    f = np.float32(value)
    if float(f) < value:
        f = np.nextafter(f, np.float32(np.inf))
    return F32.pack(f)


def f32_coarse_up(values: np.ndarray, low_bits: int) -> np.ndarray:
    """Finite ``values`` >= 0 as float32 not below them whose ``low_bits`` low mantissa bits are 0
    (a carry into the exponent is the next power of two, still not below): zstd shortens those."""
    values = np.asarray(values, dtype=np.float64)
    f = values.astype(np.float32)
    f = np.where(f < values, np.nextafter(f, np.float32(np.inf)), f).astype(np.float32)
    step = np.uint32(1 << low_bits) if low_bits else np.uint32(1)
    bits = f.view(np.uint32)
    coarse = ((bits + (step - np.uint32(1))) & ~(step - np.uint32(1))).view(np.float32)
    return np.where(np.isfinite(coarse), coarse, f).astype(np.float32)


def names(tags: set[bytes]) -> str:
    return ", ".join(t.decode().strip() for t in sorted(tags)) or "none"
