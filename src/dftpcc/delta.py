"""Deltas between two versions of a tiled map: what a rover sends after an update (docs/format.md, *Deltas*).

A delta describes the new file as pieces: byte ranges copied from the old
one (the tiles an update did not code again, which keep their bytes) and
new bytes (the file's head, the re-coded tiles). It names the SHA-256 of
the map it applies to and of the map it gives, so applying it to another
map, twice, or out of order is refused before anything is written, and a
damaged delta cannot give a wrong map.
"""

from __future__ import annotations

import hashlib
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import zstandard

from .container import Source, leb128, read_leb128, unpack_source
from .errors import CorruptFileError, InvalidInputError, MissingFileError
from .io.atomic import atomic_write, check_output

__all__ = ["MAGIC", "VERSION", "make_delta", "apply_delta", "read_delta", "Delta", "patch_file",
           "COPY", "DATA", "MAX_COPY_FACTOR"]

#: The first bytes of a delta (a high byte and CR LF, like a map's, and D for delta).
MAGIC = b"\x89DFTPD\r\n"
#: Major and minor version of the delta layout.
VERSION = (1, 0)
#: Piece kinds: bytes of the base map, or the next bytes of the delta's new data.
COPY, DATA = 0, 1
#: The copies of a delta add up to at most this many times the base map (a tile is copied once, or a
#: few times when tiles share bytes): a crafted delta must not make a few bytes cost gigabytes.
MAX_COPY_FACTOR = 4
#: zstd level of the new data (the head's table and index compress; coded tiles hardly do).
ZSTD_LEVEL = 19
_HEAD = struct.Struct("<8sBBH32s32s")  # magic, major, minor, flags, base SHA-256, result SHA-256
_CRC = struct.Struct("<I")


@dataclass(frozen=True)
class Delta:
    """A parsed delta.

    Attributes
    ----------
    base_sha256, result_sha256 : bytes
        SHA-256 of the map it applies to and of the map it gives (32 bytes each).
    result_size : int
        Bytes of the resulting map.
    pieces : list of (kind, a, b)
        ``(COPY, offset, length)`` of the base, or ``(DATA, start, length)`` of ``data``.
    data : bytes
        The new bytes (decompressed).
    """

    base_sha256: bytes
    result_sha256: bytes
    result_size: int
    pieces: list[tuple[int, int, int]]
    data: bytes

    @property
    def copied(self) -> int:
        """Bytes the result takes from the base map."""
        return sum(n for kind, _, n in self.pieces if kind == COPY)


def _tile_payloads(data: bytes) -> list[tuple[int, int]]:
    """(offset, length) of every tile section payload of a tiled map (empty for any other bytes)."""
    if not data:
        return []
    header, _ = unpack_source(Source(data))
    if header.tiles is None:
        return []
    return sorted((start, length) for sections in header.tiles.sections.values()
                  for start, length, _crc in sections.values())


def make_delta(base: bytes, result: bytes) -> bytes:
    """The delta that turns the map ``base`` into the map ``result``.

    Every tile section of ``result`` found byte for byte in ``base`` (by
    length and content) becomes a copy; the rest (the head, re-coded tiles)
    is new data. Adjacent copies of adjacent base bytes merge into one.
    ``base`` may be empty (the first version of a map): the delta then holds it all.
    """
    found: dict[tuple[int, int], int] = {}
    for start, length in _tile_payloads(base):
        found.setdefault((length, zlib.crc32(base[start:start + length])), start)
    pieces: list[tuple[int, int, int]] = []  # (kind, offset in base or in result, length)
    pos = 0

    def put(kind: int, offset: int, length: int) -> None:
        if length == 0:
            return
        if pieces and pieces[-1][0] == kind:
            last_kind, last_offset, last_length = pieces[-1]
            # new data runs on in the result; a copy merges only when it runs on in the base too
            if kind == DATA or last_offset + last_length == offset:
                pieces[-1] = (kind, last_offset, last_length + length)
                return
        pieces.append((kind, offset, length))

    for start, length in _tile_payloads(result):
        payload = result[start:start + length]
        at = found.get((length, zlib.crc32(payload)))
        if at is None or base[at:at + length] != payload:
            continue
        put(DATA, pos, start - pos)
        put(COPY, at, length)
        pos = start + length
    put(DATA, pos, len(result) - pos)
    new = b"".join(result[offset:offset + length] for kind, offset, length in pieces if kind == DATA)
    body = bytearray(_HEAD.pack(MAGIC, *VERSION, 0, hashlib.sha256(base).digest(), hashlib.sha256(result).digest()))
    body += leb128(len(result)) + leb128(len(pieces))
    for kind, offset, length in pieces:
        body += bytes([kind]) + (leb128(offset) if kind == COPY else b"") + leb128(length)
    body += zstandard.ZstdCompressor(level=ZSTD_LEVEL, write_content_size=True).compress(new)
    return bytes(body + _CRC.pack(zlib.crc32(body)))


def read_delta(delta: bytes, *, base_size: int | None = None) -> Delta:
    """Parse and check a delta (its magic, version, CRC and pieces).

    ``base_size``: bytes of the map it will apply to, so copies beyond it are refused here.

    Raises
    ------
    CorruptFileError
        Not a delta, another version, a damaged or inconsistent one.
    """
    delta = bytes(delta)
    if len(delta) < _HEAD.size + _CRC.size or not delta.startswith(MAGIC):
        raise CorruptFileError("not a dftpcc delta (no delta magic)")
    if zlib.crc32(delta[:-_CRC.size]) != _CRC.unpack_from(delta, len(delta) - _CRC.size)[0]:
        raise CorruptFileError("delta fails its checksum (damaged or truncated)")
    _, major, minor, flags, base_sha, result_sha = _HEAD.unpack_from(delta, 0)
    if (major, minor) != VERSION or flags:
        raise CorruptFileError(f"delta version {major}.{minor} (flags {flags}) is not {VERSION[0]}.{VERSION[1]}")
    end = len(delta) - _CRC.size
    result_size, pos = read_leb128(delta, _HEAD.size, "delta")
    count, pos = read_leb128(delta, pos, "delta")
    if count > end - pos:  # each piece takes at least two bytes
        raise CorruptFileError(f"delta claims {count:,} pieces in {end - pos:,} bytes")
    pieces, total, copied, data_bytes = [], 0, 0, 0
    for _ in range(count):
        if pos >= end:
            raise CorruptFileError("delta is truncated (in its pieces)")
        kind = delta[pos]
        pos += 1
        if kind == COPY:
            offset, pos = read_leb128(delta, pos, "delta")
            length, pos = read_leb128(delta, pos, "delta")
            if base_size is not None and offset + length > base_size:
                raise CorruptFileError(f"delta copies bytes {offset:,} to {offset + length:,} of a {base_size:,}-byte map")
            copied += length
            pieces.append((COPY, offset, length))
        elif kind == DATA:
            length, pos = read_leb128(delta, pos, "delta")
            pieces.append((DATA, data_bytes, length))
            data_bytes += length
        else:
            raise CorruptFileError(f"delta piece of unknown kind {kind}")
        total += length
    if total != result_size:
        raise CorruptFileError(f"delta pieces add up to {total:,} bytes, not the {result_size:,} it states")
    if base_size is not None and copied > MAX_COPY_FACTOR * base_size:
        raise CorruptFileError(f"delta copies {copied:,} bytes of a {base_size:,}-byte map (crafted?)")
    frame = delta[pos:end]
    try:
        declared = zstandard.frame_content_size(frame)
        if declared != data_bytes:
            raise CorruptFileError(f"delta's new data declares {declared} bytes, its pieces {data_bytes:,}")
        data = zstandard.ZstdDecompressor().decompress(frame, max_output_size=data_bytes) if data_bytes else b""
    except zstandard.ZstdError as exc:
        raise CorruptFileError(f"delta's new data does not decompress: {exc}") from None
    if len(data) != data_bytes:
        raise CorruptFileError("delta's new data is shorter than it declares")
    return Delta(base_sha, result_sha, result_size, pieces, data)


def apply_delta(base: bytes, delta: bytes) -> bytes:
    """The map ``delta`` makes of ``base``, checked against the SHA-256 the delta states.

    Raises
    ------
    InvalidInputError
        ``base`` is not the map the delta was made from: another map, the
        delta's own result (applied twice), or a map a previous delta was
        not applied to yet (out of order).
    CorruptFileError
        A damaged delta, or one whose result is not the map it names.
    """
    parsed = read_delta(delta, base_size=len(base))
    have = hashlib.sha256(base).digest()
    if have != parsed.base_sha256:
        if have == parsed.result_sha256:
            raise InvalidInputError("this delta was applied already: the map is the map it gives "
                                    f"(SHA-256 {have.hex()[:16]}...)")
        raise InvalidInputError(
            f"this delta applies to the map whose SHA-256 is {parsed.base_sha256.hex()[:16]}..., not to this one "
            f"({have.hex()[:16]}...): the wrong map, or an earlier delta not applied yet (deltas apply in order)")
    out = b"".join(base[a:a + n] if kind == COPY else parsed.data[a:a + n] for kind, a, n in parsed.pieces)
    if hashlib.sha256(out).digest() != parsed.result_sha256:
        raise CorruptFileError("the delta's result is not the map it names (a damaged delta)")
    return out


def patch_file(map_path: str | os.PathLike[str], delta_path: str | os.PathLike[str], *,
               output: str | os.PathLike[str] | None = None, force: bool = False) -> int:
    """Apply a delta file to a map file (``dftpcc patch``), in place without ``output``; atomic.

    Returns
    -------
    int
        Bytes of the map written.
    """
    out = Path(map_path) if output is None else Path(output)
    check_output(out, force=force)
    for path in (map_path, delta_path):
        if not Path(path).is_file():
            raise MissingFileError(path)
    result = apply_delta(Path(map_path).read_bytes(), Path(delta_path).read_bytes())
    atomic_write(out, lambda tmp: Path(tmp).write_bytes(result))
    return len(result)
