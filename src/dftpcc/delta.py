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
import io
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import zstandard

from .format import Header, Source, leb128, read_leb128, tile_sections, unpack_source
from .errors import CorruptFileError, DftpccError, InvalidInputError, MissingFileError
from .io.atomic import atomic_write, check_distinct, check_output
from .io.lock import lock_path, locked

__all__ = ["MAGIC", "VERSION", "make_delta", "apply_delta", "read_delta", "Delta", "patch_file",
           "COPY", "DATA", "MAX_COPY_FACTOR", "MAX_DATA_FACTOR"]

#: The first bytes of a delta (a high byte and CR LF, like a map's, and D for delta).
MAGIC = b"\x89DFTPD\r\n"
#: Major and minor version of the delta layout.
VERSION = (1, 0)
#: Piece kinds: bytes of the base map, or the next bytes of the delta's new data.
COPY, DATA = 0, 1
#: The copies of a delta add up to at most this many times the base map (a tile is copied once, or a
#: few times when tiles share bytes): a crafted delta must not make a few bytes cost gigabytes.
MAX_COPY_FACTOR = 4
#: The new data adds up to at most this many times its zstd frame, plus DATA_ALLOWANCE bytes: it is
#: coded tiles and a head, which zstd hardly shrinks (1.1 to 1.6 times on growing maps), whereas a
#: 131 KB frame of zeros declares 4 GB.
MAX_DATA_FACTOR = 64
#: Bytes of new data any frame may give, however small (a tiny delta's frame overhead exceeds its data).
DATA_ALLOWANCE = 1 << 16
#: Bytes of the result's head decompressed at most to tell another map from another version of this one.
HEAD_LIMIT = 4 << 20
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
    return sorted((start, length) for sections in tile_sections(data).values()
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


def _checked_head(delta: bytes) -> tuple[bytes, bytes]:
    """Magic, CRC and version of a delta (format.md, *Applying*, step 1): its base and result SHA-256."""
    if len(delta) < _HEAD.size + _CRC.size or not delta.startswith(MAGIC):
        raise CorruptFileError("not a dftpcc delta (no delta magic)")
    if zlib.crc32(delta[:-_CRC.size]) != _CRC.unpack_from(delta, len(delta) - _CRC.size)[0]:
        raise CorruptFileError("delta fails its checksum (damaged or truncated)")
    _, major, minor, flags, base_sha, result_sha = _HEAD.unpack_from(delta, 0)
    if (major, minor) != VERSION or flags:
        raise CorruptFileError(f"delta version {major}.{minor} (flags {flags}) is not {VERSION[0]}.{VERSION[1]}")
    return base_sha, result_sha


def _pieces(delta: bytes, base_size: int | None) -> tuple[int, list[tuple[int, int, int]], int, bytes]:
    """The result size, pieces, new data bytes and zstd frame of a checked delta (step 3), every
    size checked against the base and the frame before anything is decompressed."""
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
    if data_bytes > MAX_DATA_FACTOR * len(frame) + DATA_ALLOWANCE:
        raise CorruptFileError(f"delta's {len(frame):,} bytes of compressed data claim to give {data_bytes:,}, more than "
                               f"{MAX_DATA_FACTOR} times as many (crafted?)")
    try:
        declared = zstandard.frame_content_size(frame)
    except zstandard.ZstdError as exc:
        raise CorruptFileError(f"delta's new data does not decompress: {exc}") from None
    if declared != data_bytes:
        raise CorruptFileError(f"delta's new data declares {declared} bytes, its pieces {data_bytes:,}")
    return result_size, pieces, data_bytes, frame


def read_delta(delta: bytes, *, base_size: int | None = None) -> Delta:
    """Parse and check a delta (its magic, version, CRC and pieces) and decompress its new data.

    ``base_size``: bytes of the map it will apply to, so copies beyond it are refused here.
    Every size is checked before the new data is decompressed (format.md, *Applying*).

    Raises
    ------
    CorruptFileError
        Not a delta, another version, a damaged or inconsistent one.
    """
    delta = bytes(delta)
    base_sha, result_sha = _checked_head(delta)
    result_size, pieces, data_bytes, frame = _pieces(delta, base_size)
    try:
        data = zstandard.ZstdDecompressor().decompress(frame, max_output_size=data_bytes) if data_bytes else b""
    except zstandard.ZstdError as exc:
        raise CorruptFileError(f"delta's new data does not decompress: {exc}") from None
    if len(data) != data_bytes:
        raise CorruptFileError("delta's new data is shorter than it declares")
    return Delta(base_sha, result_sha, result_size, pieces, data)


def _result_head(delta: bytes) -> Header | None:
    """The header of the map a delta gives, from at most HEAD_LIMIT bytes of its new data, or None
    when the delta does not start its result with new data or that head does not parse."""
    try:
        result_size, pieces, data_bytes, frame = _pieces(delta, None)
        if not pieces or pieces[0][0] != DATA:
            return None
        with zstandard.ZstdDecompressor().stream_reader(io.BytesIO(frame)) as reader:
            head = reader.read(min(pieces[0][2], HEAD_LIMIT))
        header, _ = unpack_source(Source(file=io.BytesIO(head), size=result_size))
    except (DftpccError, zstandard.ZstdError):
        return None
    return header


def _tiles_in_space(header: Header, shift: tuple[int, int]) -> dict[tuple[int, int], tuple[int, set]]:
    """Occupied cells and the (tag, length, CRC-32) of the sections of every tile, keyed by tile row
    and column plus ``shift`` (tiles), so that two versions of a map key a tile at one place alike."""
    assert header.tiles is not None
    columns, sections = header.tiles.tiling.tile_cols, header.tiles.sections
    return {(shift[0] + k // columns, shift[1] + k % columns):
            (int(n), {(tag, length, crc) for tag, (_, length, crc) in sections.get(k, {}).items()})
            for k, n in enumerate(header.tiles.cells) if n}


def _same_map(base: Header, result: Header) -> bool | None:
    """Whether two maps look like two versions of one growing map (format.md, *Applying*, step 2);
    None where this cannot tell (a map that is no growing map, or a rotated one)."""
    a, b = base.grid, result.grid
    if not (base.growing and result.growing) or a.angle or b.angle:
        return None
    size = base.tiles.tiling.size
    if (size, a.resolution, a.dy, a.z0, base.params, base.crs) != (
            result.tiles.tiling.size, b.resolution, b.dy, b.z0, result.params, result.crs):
        return False
    shift = []
    for d, cell in ((b.y0 - a.y0, a.dy), (b.x0 - a.x0, a.resolution)):
        tiles = d / (size * cell)
        if abs(tiles - round(tiles)) > 1e-6:
            return False
        shift.append(round(tiles))
    old, new = _tiles_in_space(base, (0, 0)), _tiles_in_space(result, (shift[0], shift[1]))
    # A growing map's cells only grow, and the tiles an update did not touch keep their bytes.
    nested = (all(n <= new.get(k, (0,))[0] for k, (n, _) in old.items())
              or all(n <= old.get(k, (0,))[0] for k, (n, _) in new.items()))
    return nested and any(found & new[k][1] for k, (_, found) in old.items() if k in new)


def _refuse_another_base(base: bytes, have: bytes, delta: bytes, base_sha: bytes, result_sha: bytes) -> None:
    """Why ``base`` is not the map the delta applies to (format.md, *Applying*, step 2): always raises."""
    def v(sha: bytes) -> str:
        return sha.hex()[:16] + "..."
    if have == result_sha:
        raise InvalidInputError(f"this delta was applied already: the map is the map it gives (SHA-256 {v(have)})")
    try:
        mine = unpack_source(Source(base))[0] if base else None
    except DftpccError:
        mine = None
    theirs = _result_head(delta)
    same = None if mine is None or theirs is None else _same_map(mine, theirs)
    if same is not None:
        if same:
            raise InvalidInputError(
                f"this delta was made for another version of this map: it turns version {v(base_sha)} into "
                f"{v(result_sha)}, and this file is version {v(have)}; deltas apply in order (one was not applied "
                f"yet, or this map changed since)")
        raise InvalidInputError(
            f"this delta was made for another map (its result's grid, settings or ground is not this map's): "
            f"it turns {v(base_sha)} into {v(result_sha)}; this file is {v(have)}")
    raise InvalidInputError(
        f"this delta applies to the map whose SHA-256 is {v(base_sha)}, not to this one ({v(have)}): another "
        f"map, or another version of this one (deltas apply in order)")


def apply_delta(base: bytes, delta: bytes) -> bytes:
    """The map ``delta`` makes of ``base``, checked against the SHA-256 the delta states.

    The checks run in the order of format.md, *Applying*: the base first, then every size before
    anything is decompressed, and the result's SHA-256 before the result is assembled.

    Raises
    ------
    InvalidInputError
        ``base`` is not the map the delta was made from: another map, the
        delta's own result (applied twice), or another version of this map
        (a delta not applied yet: out of order).
    CorruptFileError
        A damaged delta, or one whose result is not the map it names.
    """
    delta = bytes(delta)
    base_sha, result_sha = _checked_head(delta)
    have = hashlib.sha256(base).digest()
    if have != base_sha:
        _refuse_another_base(base, have, delta, base_sha, result_sha)
    parsed = read_delta(delta, base_size=len(base))
    view, data = memoryview(base), memoryview(parsed.data)
    parts = [view[a:a + n] if kind == COPY else data[a:a + n] for kind, a, n in parsed.pieces]
    digest = hashlib.sha256()
    for part in parts:
        digest.update(part)
    if digest.digest() != parsed.result_sha256:
        raise CorruptFileError("the delta's result is not the map it names (a damaged delta)")
    return b"".join(parts)


def patch_file(map_path: str | os.PathLike[str], delta_path: str | os.PathLike[str], *,
               output: str | os.PathLike[str] | None = None, force: bool = False) -> int:
    """Apply a delta file to a map file (``dftpcc patch``), in place without ``output``; atomic.

    Returns
    -------
    int
        Bytes of the map written.
    """
    out = Path(map_path) if output is None else Path(output)
    read = {f"the map {map_path}": map_path, f"the delta {delta_path}": delta_path,
            f"the map's lock {lock_path(map_path)}": lock_path(map_path)}
    if output is not None:
        check_distinct({f"-o {out}": out}, read)
    check_output(out, force=force)
    for path in (map_path, delta_path):
        if not Path(path).is_file():
            raise MissingFileError(path)
    # In place, the map is read, patched and written back: an update of it meanwhile would be lost.
    with locked([map_path, out]):
        result = apply_delta(Path(map_path).read_bytes(), Path(delta_path).read_bytes())
        atomic_write(out, result)
    return len(result)
