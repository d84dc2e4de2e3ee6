"""An independent `.dftpc` decoder written from docs/format.md alone.

It does not import dftpcc: it exists to show whether the format document is enough to read a file,
version 1.0 and the tiled version 1.1.
``decode(data)`` returns the rebuilt points, shape (N, 3), float64.

Written by a helper that read only docs/format.md. When the section table lost its offsets
(entries of tag, LEB128 tile and length, CRC), ``_sections`` was updated to the new table by the
library's author, from the same document. Later, from the document's new rules: LEB128 of at most
64 bits (``_uleb``), no bytes after the last section (``_sections``), and only binary STAT and
COEF kind 3 for ANS (the drafts' JSON STAT and kind 2 refused). The rest is as the helper wrote it.

The tiled layout (version 1.1: ``_table``, ``_by_tile`` and the "tiles" part at the end) was added
by another helper from docs/format.md's section "Tiles: version 1.1" alone, without reading the
library's tiles, decoder or container modules.

The link frames (``link_frame``, ``link_plan``, ``link_rebuild`` at the end) were written field by
field from docs/format.md's section "Link frames", sharing no code with dftpcc/link.py; by the same
helper who wrote that module, so a weaker check than a reader who never saw it.
"""

from __future__ import annotations

import decimal
import fractions
import json
import math
import struct
import zlib

import constriction
import numpy as np
import zstandard
from scipy import fft as sfft

MAGIC = b"\x89DFTPC\r\n"
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
MAX_SECTIONS = 1024
MAX_SECTIONS_TILED = 1 << 24  # in a 1.1 file
ENTRY_MIN_BYTES = 10  # tag, one-byte tile, one-byte length, CRC
MAX_JSON_BYTES = 1 << 20

# PARM fields left out take these (frozen for all 1.x files).
V1_DEFAULTS = {
    "cutoff": 0.8, "profile": "compact", "aggregate": "mean", "frame": "axis",
    "transform": "dct", "detrend": "plane", "fill": "consistent", "storage": "quantized",
    "step": 0.0, "deadzone": 0.1, "coder": "ans", "mask": "exact", "target_rmse": 0.0,
    "target_max_error": 0.0, "target_bpp": 0.0,
}

STAT_FLOAT_IDS = {0: "dem_rmse_m", 1: "dem_max_error_m", 2: "gridding_rmse_m",
                  3: "vertical_rmse_m", 4: "unrepresented_fraction", 5: "unrepresented_rmse_m",
                  6: "reloc_success_fraction", 7: "target_rmse_m", 8: "source_nodata"}
STAT_INT_IDS = {128: "coef_count", 129: "cells_interpolated", 130: "source_dtype"}

BAND_LAYOUTS = [(4, 1), (8, 1), (8, 4), (8, 16)]  # (ring width, angular sectors)


# --------------------------------------------------------------------------- helpers

def _zstd(frame: bytes, limit: int) -> bytes:
    """One zstd frame, refused if it declares (or yields) more than ``limit`` bytes."""
    try:
        declared = zstandard.get_frame_parameters(frame).content_size
        if declared != zstandard.CONTENTSIZE_UNKNOWN and declared > limit:
            raise ValueError(f"zstd frame declares {declared} bytes, more than {limit}")
        return zstandard.ZstdDecompressor().decompress(frame, max_output_size=max(limit, 1))
    except zstandard.ZstdError as exc:
        raise ValueError(f"zstd frame does not decompress: {exc}") from exc


def _json(payload: bytes) -> dict:
    if payload[:4] == ZSTD_MAGIC:
        payload = _zstd(payload, MAX_JSON_BYTES)
    obj = json.loads(payload.decode("utf-8"))
    if not isinstance(obj, dict):
        raise ValueError("JSON section is not an object")
    return obj


def _words(buf: bytes) -> np.ndarray:
    if len(buf) % 4:
        raise ValueError("ANS data is not whole 32-bit words")
    return np.frombuffer(buf, dtype="<u4").astype(np.uint32)


# --------------------------------------------------------------------------- container

def _uleb(data: bytes, pos: int, where: str = "section table") -> tuple[int, int]:
    """Unsigned LEB128 at ``pos`` and the position after it.

    format.md: at most 10 bytes and a value below 2**64 (a tenth byte is 0 or 1 and ends it);
    anything wider is refused, never reduced.
    """
    value = 0
    for k in range(10):
        if pos + k >= len(data):
            raise ValueError(f"{where} is truncated")
        byte = data[pos + k]
        value |= (byte & 0x7F) << (7 * k)
        if not byte & 0x80:
            if value >= 1 << 64:
                break
            return value, pos + k + 1
    raise ValueError(f"{where} holds an integer wider than 64 bits")


def _table(data: bytes) -> tuple[int, list[tuple[bytes, int, int, int, int]]]:
    """The minor version and the table: ``(tag, tile, offset, length, crc)`` per entry.

    format.md: at most 1024 entries (2**24 in a 1.1 file), every entry read before any is used;
    offsets follow from the lengths; the file ends where its last payload ends.
    """
    if len(data) < 20:
        raise ValueError("not a .dftpc file: too short")
    if data[:8] != MAGIC:
        raise ValueError("bad magic bytes")
    major, minor, _flags, count = struct.unpack_from("<BBHI", data, 8)
    if major != 1:
        raise ValueError(f"unsupported major version {major}")
    if count > (MAX_SECTIONS if minor == 0 else MAX_SECTIONS_TILED):
        raise ValueError("too many sections")
    if 16 + ENTRY_MIN_BYTES * count + 4 > len(data):  # a count the file's bytes cannot hold
        raise ValueError("truncated section table")
    raw, pos = [], 16
    for _ in range(count):
        if pos + 4 > len(data):
            raise ValueError("truncated section table")
        tag = data[pos:pos + 4]
        tile, pos = _uleb(data, pos + 4)
        length, pos = _uleb(data, pos)
        if pos + 4 > len(data):
            raise ValueError("truncated section table")
        raw.append((tag, tile, length, struct.unpack_from("<I", data, pos)[0]))
        pos += 4
    table_end = pos
    if table_end + 4 > len(data):
        raise ValueError("truncated section table")
    if zlib.crc32(data[:table_end]) != struct.unpack_from("<I", data, table_end)[0]:
        raise ValueError("section table fails its checksum")
    # The file ends where its last payload ends: bytes after it are refused.
    end = table_end + 4 + sum(length for _tag, _tile, length, _crc in raw)
    if len(data) > end:
        raise ValueError(f"{len(data) - end} bytes after the last section")
    entries, offset = [], table_end + 4  # payloads follow the table in its order
    for tag, tile, length, crc in raw:
        entries.append((tag, tile, offset, length, crc))
        offset += length
    return minor, entries


def _by_tile(entries) -> dict[int, dict[bytes, tuple[int, int, int]]]:
    """tile -> tag -> (offset, length, crc), the first entry of a tag in each tile (repeats ignored)."""
    tiles: dict[int, dict[bytes, tuple[int, int, int]]] = {}
    for tag, tile, offset, length, crc in entries:
        tiles.setdefault(tile, {}).setdefault(tag, (offset, length, crc))
    return tiles


def _payload(data: bytes, tag: bytes, where: tuple[int, int, int], name: str = "") -> bytes:
    """A section's payload, checked against its CRC (``name`` says which tile, if any)."""
    offset, length, crc = where
    if offset + length > len(data):
        raise ValueError(f"{name}section {tag!r} is truncated")
    payload = data[offset:offset + length]
    if zlib.crc32(payload) != crc:
        raise ValueError(f"{name}section {tag!r} fails its checksum")
    return payload


def _is_tiled(minor: int, tile0: dict) -> bool:
    # A 1.1 file is the tiled layout; a later minor version is tiled when it has a tile index.
    return minor == 1 or (minor > 1 and b"TIDX" in tile0)


def _sections(data: bytes) -> dict[bytes, bytes]:
    """The payloads of tile 0 (the whole map's sections), each checked against its CRC."""
    minor, entries = _table(data)
    tiles = _by_tile(entries)
    tile0 = tiles.get(0, {})
    tiled = _is_tiled(minor, tile0)
    sections = {tag: _payload(data, tag, where) for tag, where in tile0.items()}
    required = (b"GEOM", b"PARM", b"STAT", b"TIDX", b"BASE") if tiled else (b"GEOM", b"PARM", b"MASK", b"COEF")
    for tag in required:
        if tag not in sections:
            raise ValueError(f"section {tag!r} is missing")
    if tiled:
        if b"COEF" in sections:  # a MASK at tile 0 is the map mask, a RESD the map residual
            raise ValueError("tile 0 of a tiled file holds a b'COEF' section")
        if b"RESD" in sections and b"MASK" not in sections:
            raise ValueError("tile 0 holds a map residual without the map mask")
    return sections


def _geom(p: bytes) -> dict:
    if len(p) < 88:
        raise ValueError("geometry section is too short")
    x0, y0, z0, res = struct.unpack_from("<4d", p, 0)
    rows, cols = struct.unpack_from("<II", p, 32)
    (angle,) = struct.unpack_from("<d", p, 40)
    points, cells = struct.unpack_from("<QQ", p, 48)
    plane = struct.unpack_from("<3d", p, 64)
    dy = struct.unpack_from("<d", p, 88)[0] if len(p) >= 96 else 0.0
    values = (x0, y0, z0, res, angle, *plane, dy)
    if not all(math.isfinite(v) for v in values) or res <= 0 or dy < 0:
        raise ValueError("geometry section holds non-finite or non-positive values")
    if res < 1e-9 or 0 < dy < 1e-9:
        raise ValueError("geometry section states a cell size below 1e-9")
    if rows < 1 or cols < 1 or not 1 <= cells <= rows * cols:
        raise ValueError("implausible grid")
    return dict(x0=x0, y0=y0, z0=z0, res=res, rows=rows, cols=cols, angle=angle,
                points=points, cells=cells, plane=plane, dy=dy if dy > 0 else res)


def _stat(p: bytes) -> dict:
    if not p:
        raise ValueError("section STAT is empty")
    if p[0] != 1:  # binary is the only coding
        raise ValueError(f"section STAT has unknown coding {p[0]}")
    stats, i = {}, 1
    while i < len(p):
        fid = p[i]
        i += 1
        if fid < 128:
            if i + 4 > len(p):
                raise ValueError("section STAT is truncated")
            (v,) = struct.unpack_from("<f", p, i)
            i += 4
            if not math.isfinite(v):
                raise ValueError(f"section STAT: field {fid} is not finite")
            if fid in STAT_FLOAT_IDS:
                stats[STAT_FLOAT_IDS[fid]] = float(v)
        else:
            v, i = _uleb(p, i, "section STAT")
            if fid in STAT_INT_IDS:
                stats[STAT_INT_IDS[fid]] = v
    return stats


# --------------------------------------------------------------------------- mask

def _seed_lines(frame: bytes, count: int, w: int) -> list[np.ndarray]:
    if count == 0:
        if frame:
            raise ValueError("occupancy mask has seed lines it does not need")
        return []
    raw = _zstd(frame, 4 * (w + 2) * count)
    if len(raw) % 4:
        raise ValueError("seed lines have a wrong length")
    m = len(raw) // 4
    planes = np.frombuffer(raw, np.uint8).reshape(4, m).astype(np.uint64)
    values = planes[0] | planes[1] << 8 | planes[2] << 16 | planes[3] << 24
    lines, i = [], 0
    for _ in range(count):
        if i >= m:
            raise ValueError("seed lines are truncated")
        k = int(values[i])
        runs = values[i + 1:i + 1 + k].astype(np.int64)
        i += 1 + k
        if k < 1 or len(runs) != k or runs.sum() != w:
            raise ValueError(f"seed line does not add up to {w} cells")
        bits = np.repeat(np.arange(k) % 2, runs).astype(np.uint8)
        lines.append(bits)
    if i != m:
        raise ValueError("seed lines have trailing data")
    return lines


def _contexts(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w = len(a)
    ap = np.pad(a.astype(np.int64), 2)
    bp = np.pad(b.astype(np.int64), 2)
    return (ap[0:w] + 2 * ap[1:w + 1] + 4 * ap[2:w + 2] + 8 * ap[3:w + 3] + 16 * ap[4:w + 4]
            + 32 * bp[1:w + 1] + 64 * bp[2:w + 2] + 128 * bp[3:w + 3])


def _mask_context(p: bytes, rows: int, cols: int, transposed: int, first_seed: bool) -> np.ndarray:
    # Kind 2, or kind 3 (first_seed): line 0 of the first stripe is a seed too, step 0 codes nothing.
    # The lines run along the longer axis: transposed is 1 exactly when rows > cols.
    if transposed != int(rows > cols):
        raise ValueError("occupancy mask runs along the wrong axis")
    n, w = (cols, rows) if transposed else (rows, cols)
    if len(p) < 10:
        raise ValueError("occupancy mask is truncated")
    stripe, seed_bytes = struct.unpack_from("<II", p, 2)
    if stripe < 1 or 10 + seed_bytes > len(p):
        raise ValueError("occupancy mask has a wrong length")
    L = min(stripe, n)
    n_stripes = -(-n // L)
    lines = np.zeros((n, w), np.uint8)
    first = int(first_seed)
    for s, bits in enumerate(_seed_lines(p[10:10 + seed_bytes], n_stripes - 1 + first, w), start=1 - first):
        lines[s * L] = bits
    coder = constriction.stream.stack.AnsCoder(_words(p[10 + seed_bytes:]))
    popcount = np.array([bin(c).count("1") for c in range(256)], float)
    p_c = (popcount + 0.5) / 9
    n1 = np.zeros(256)
    nn = np.zeros(256)
    zeros = np.zeros(w, np.uint8)
    bern = constriction.stream.model.Bernoulli
    for t in range(first, L):
        idx = [s * L + t for s in range(n_stripes if t else 1) if s * L + t < n]
        ctx = []
        for i in idx:
            if t == 0:
                a = b = zeros
            else:
                a = lines[i - 1]
                b = lines[i - 2] if t >= 2 else a
            ctx.append(_contexts(a, b))
        ctx = np.concatenate(ctx)
        prob = (n1 + p_c) / (nn + 1)
        bits = np.zeros(len(ctx), np.int64)
        for c in (0, 255):
            sel = np.flatnonzero(ctx == c)
            if len(sel):
                bits[sel] = coder.decode(bern(float(prob[c]), perfect=False), len(sel))
        sel = np.flatnonzero((ctx != 0) & (ctx != 255))
        if len(sel):
            bits[sel] = coder.decode(bern(perfect=False), prob[ctx[sel]])
        for k, i in enumerate(idx):
            lines[i] = bits[k * w:(k + 1) * w]
        n1 += np.bincount(ctx, weights=bits, minlength=256)
        nn += np.bincount(ctx, minlength=256)
    return lines.T if transposed else lines


def _mask(p: bytes, rows: int, cols: int) -> np.ndarray:
    if len(p) < 2:
        raise ValueError("occupancy mask is truncated")
    kind, transposed = p[0], p[1]
    if kind == 0:
        nbytes = -(-rows * cols // 8)
        raw = _zstd(p[2:], nbytes)
        if len(raw) != nbytes:
            raise ValueError("occupancy mask has the wrong size for the grid")
        bits = np.unpackbits(np.frombuffer(raw, np.uint8), count=rows * cols)
        return bits.reshape(rows, cols).astype(bool)
    if kind in (2, 3):
        return _mask_context(p, rows, cols, transposed, kind == 3).astype(bool)
    raise ValueError(f"occupancy mask has unknown coding {kind}")


# --------------------------------------------------------------------------- coefficients

def _chunk_bounds(total: int) -> list[tuple[int, int]]:
    bounds, start, length = [], 0, 256
    while start < total:
        bounds.append((start, min(start + length, total)))
        start += length
        length *= 2
    return bounds


def _table_model(max_abs: int, code: int):
    """COEF kind 3: the Categorical model of a band, from integers (format.md, steps 1-4)."""
    with decimal.localcontext() as ctx:
        ctx.prec = 50
        b = max(decimal.Decimal(2) ** (decimal.Decimal(code - 128) / 8), decimal.Decimal("0.05"))
        r = int(((1 + b * b).sqrt() - 1) / b * 65536)
    w = [1 << 32]
    for _ in range(max_abs):
        w.append((w[-1] * r) >> 16)
    n = 2 * max_abs + 1
    weights = [w[abs(q)] for q in range(-max_abs, max_abs + 1)]
    total = sum(weights)
    f = [1 + (x * ((1 << 24) - n)) // total for x in weights]
    f[max_abs] += (1 << 24) - sum(f)
    return constriction.stream.model.Categorical(np.array(f, dtype=np.float64) / (1 << 24), perfect=False)


def _ans_chunk(p: bytes, count: int, radius: np.ndarray, angle: np.ndarray) -> np.ndarray:
    if len(p) < 9:
        raise ValueError("ANS chunk is truncated")
    layout, max_abs, side = struct.unpack_from("<BII", p, 0)
    if layout >= len(BAND_LAYOUTS) or 9 + side > len(p):
        raise ValueError("ANS chunk has an implausible header")
    width, sectors = BAND_LAYOUTS[layout]
    band = (np.floor(radius / width).astype(np.int64) * sectors
            + np.minimum(np.floor(angle * sectors).astype(np.int64), sectors - 1))
    lo, hi = int(band.min()), int(band.max())
    nbands = hi - lo + 1
    if side == nbands:  # few codes are stored raw
        codes = np.frombuffer(p[9:9 + side], np.uint8)
    elif side > nbands:
        raise ValueError("ANS chunk has too many bytes of band scales")
    else:
        codes = np.frombuffer(_zstd(p[9:9 + side], nbands), np.uint8)
    if len(codes) != hi - lo + 1:
        raise ValueError("ANS chunk has a wrong number of band scales")
    code = codes[band - lo].astype(np.int64)
    coder = constriction.stream.stack.AnsCoder(_words(p[9 + side:]))
    out = np.zeros(count, np.int64)
    for c in np.unique(code[code > 0]):
        sel = np.flatnonzero(code == c)
        out[sel] = coder.decode(_table_model(max_abs, int(c)), len(sel)) - max_abs
    return out


def _zstd_chunk(p: bytes, count: int) -> np.ndarray:
    raw = _zstd(p, 1 + 8 * count)
    w = raw[0] if raw else 0
    if not 1 <= w <= 8 or len(raw) != 1 + w * count:
        raise ValueError("zstd chunk has an inconsistent length")
    planes = np.frombuffer(raw[1:], np.uint8).reshape(w, count).astype(np.uint64)
    z = np.zeros(count, np.uint64)
    for k in range(w):
        z |= planes[k] << np.uint64(8 * k)
    return ((z >> np.uint64(1)) ^ (np.uint64(0) - (z & np.uint64(1)))).view(np.int64)


def _stream(p: bytes, total: int, radius: np.ndarray, angle: np.ndarray, *, free: bool = False) -> np.ndarray:
    """The values of a COEF-style section: int64 (quantized) or complex128 (complex64 chunks);
    ``free``: 1.1's BASE or tile COEF, whose chunk lengths are the writer's choice."""
    if len(p) < 4:
        raise ValueError("coefficient section has the wrong chunk count")
    (nchunks,) = struct.unpack_from("<I", p, 0)
    bounds = _chunk_bounds(total)
    if (nchunks > total) if free else (nchunks != len(bounds)):
        raise ValueError("coefficient section has the wrong chunk count")
    values, kinds, pos, stop = [], set(), 4, 0
    for k in range(nchunks):
        if pos + 16 > len(p):
            raise ValueError("coefficient chunk is truncated")
        count, nbytes, crc, kind = struct.unpack_from("<4I", p, pos)
        start, stop = (stop, stop + count) if free else bounds[k]
        body = p[pos + 16:pos + 16 + nbytes]
        pos += 16 + nbytes
        if count != stop - start or count == 0 or stop > total or len(body) != nbytes or zlib.crc32(body) != crc:
            raise ValueError("coefficient chunk is damaged")
        kinds.add(kind)
        if kind == 1:
            if nbytes != 8 * count:
                raise ValueError("coefficient chunk has a wrong length")
            values.append(np.frombuffer(body, "<c8").astype(np.complex128))
        elif kind == 0:
            values.append(_zstd_chunk(body, count))
        elif kind == 3:
            values.append(_ans_chunk(body, count, radius[start:stop], angle[start:stop]))
        else:
            raise ValueError(f"coefficient chunk has unknown kind {kind}")
    if stop != total:
        raise ValueError("coefficient chunks do not hold the stream")
    if 1 in kinds and len(kinds) > 1:  # integer kinds (0, 3) may alternate; complex ones stand alone
        raise ValueError("coefficient chunks mix complex and integer kinds")
    if not values:
        return np.zeros(0, np.int64)
    return np.concatenate(values)


def _predicted_residual(body: bytes, mask: np.ndarray) -> np.ndarray:
    """RESD kind 5 (format.md, *Kind 5, predicted residual*), cell by cell in wavefront order."""
    if len(body) < 29:
        raise ValueError("predicted residual has a wrong length")
    a = struct.unpack_from("<7i", body, 0)
    listed = body[28]
    if max(abs(x) for x in a) >= 1 << 24 or not 1 <= listed <= 64 or len(body) < 29 + listed:
        raise ValueError("predicted residual has an implausible header")
    codes = list(body[29:29 + listed]) + [0] * (64 - listed)
    coded = [k for k in range(64) if codes[k]]
    at = 29 + listed + 2 * len(coded)
    if len(body) < at or (len(body) - at) % 4:
        raise ValueError("predicted residual has a wrong length")
    widths = [0] * 64
    for k, m in zip(coded, struct.unpack_from(f"<{len(coded)}H", body, 29 + listed)):
        widths[k] = m
    if max(widths) > 1 << 15:
        raise ValueError("predicted residual has an implausible header")
    if sum(2 * widths[k] + 1 for k in coded) > 16 * int(mask.sum()) + (1 << 19):
        raise ValueError("predicted residual asks for too large tables")
    rows, cols = mask.shape
    coder = constriction.stream.stack.AnsCoder(_words(body[at:]))
    v = [[0] * cols for _ in range(rows)]
    e = [[0] * cols for _ in range(rows)]

    def at(grid, r, c, up, left):  # a neighbour under rules 1-4
        if r == 0 and c == 0:
            return 0
        if up and r == 0:
            return grid[0][c - 1]
        if not up and c == 0:
            return grid[r - 1][0]
        return grid[max(r - up, 0)][min(max(c - left, 0), cols - 1)]

    offsets = ((0, 1), (1, 0), (1, 1), (1, -1), (0, 2), (2, 0), (2, -1))
    for k in range(2 * (rows - 1) + cols):
        cells = [(r, k - 2 * r) for r in range(rows) if 0 <= k - 2 * r < cols]
        classes = {}
        for r, c in cells:
            if mask[r, c]:
                act = sum(m * abs(at(e, r, c, up, left)) for m, (up, left) in zip((2, 2, 1, 1, 1, 1, 0), offsets))
                b = act.bit_length()
                cls = 0 if act == 0 else min(63, 2 * b - 1 + ((act >> (b - 2)) & 1 if b >= 2 else 0))
                classes.setdefault(cls, []).append((r, c))
        for cls in sorted(classes):
            if codes[cls]:
                got = coder.decode(_table_model(widths[cls], codes[cls]), len(classes[cls]))
                for (r, c), sym in zip(classes[cls], got.tolist()):
                    e[r][c] = sym - widths[cls]
        for r, c in cells:
            if mask[r, c]:
                total = sum(w * at(v, r, c, up, left) for w, (up, left) in zip(a, offsets))
                v[r][c] = ((total + (1 << 15)) >> 16) + e[r][c]
            else:
                v[r][c] = at(v, r, c, 0, 1)
            if abs(v[r][c]) >= 1 << 31:
                raise ValueError("predicted residual value out of range")
    return np.array([v[r][c] for r in range(rows) for c in range(cols) if mask[r, c]], dtype=np.int64)


def _residual(p: bytes, mask: np.ndarray) -> np.ndarray:
    """A RESD section: chunks as COEF's (radius and angle 0), or one chunk of kind 4 (sparse) or
    kind 5 (predicted)."""
    total = int(mask.sum())
    if len(p) >= 20 and struct.unpack_from("<I", p, 16)[0] == 5:
        nchunks, = struct.unpack_from("<I", p, 0)
        count, nbytes, crc, _kind = struct.unpack_from("<4I", p, 4)
        body = p[20:20 + nbytes]
        if nchunks != 1 or count != total or 20 + nbytes != len(p) or zlib.crc32(body) != crc:
            raise ValueError("predicted residual chunk is not the section's one whole chunk")
        return _predicted_residual(body, mask)
    if len(p) >= 20 and struct.unpack_from("<I", p, 16)[0] == 4:  # chunk 0's kind (its header: count, bytes, crc, kind)
        nchunks, = struct.unpack_from("<I", p, 0)
        count, nbytes, crc, _kind = struct.unpack_from("<4I", p, 4)
        body = p[20:20 + nbytes]
        if nchunks != 1 or count != total or 20 + nbytes != len(p) or zlib.crc32(body) != crc:
            raise ValueError("sparse residual chunk is not the section's one whole chunk")
        if len(body) < 4:
            raise ValueError("sparse residual chunk is truncated")
        (length,) = struct.unpack_from("<I", body, 0)
        if 4 + length > len(body):
            raise ValueError("sparse residual map runs past the chunk")
        picture = _mask(body[4:4 + length], *mask.shape)
        if (picture & ~mask).any():
            raise ValueError("sparse residual sets a cell that is not rebuilt")
        nonzero = picture[mask]  # row-major over the rebuilt cells
        n = int(nonzero.sum())
        signs_at = len(body) - (n + 7) // 8
        if signs_at < 4 + length:
            raise ValueError("sparse residual has no room for its signs")
        region = body[4 + length:signs_at]
        sizes = _stream(region, n, np.zeros(n), np.zeros(n), free=True)
        # The magnitudes' structure must end where the signs start.
        end = 4
        for _ in range(struct.unpack_from("<I", region, 0)[0]):
            end += 16 + struct.unpack_from("<4I", region, end)[1]
        if end != len(region):
            raise ValueError("sparse residual magnitudes do not end where the signs start")
        if np.iscomplexobj(sizes) or (n and (sizes.min() < 0 or sizes.max() > 1 << 62)):
            raise ValueError("sparse residual magnitudes out of range")
        bits = np.unpackbits(np.frombuffer(body[signs_at:], np.uint8))
        if bits[n:].any():
            raise ValueError("sparse residual has a stray sign bit")
        q = np.zeros(total, np.int64)
        q[nonzero] = np.where(bits[:n] == 1, -(sizes + 1), sizes + 1)
        return q
    return _stream(p, total, np.zeros(total), np.zeros(total))


def _layout(rows: int, cols: int, transform: str, storage: str):
    """Coefficient array shape, and per coefficient (row-major): the legacy radius (hypot), angle in [0, 1]."""
    if transform == "dft" and storage == "complex64":
        i, j = np.meshgrid(np.arange(rows) - rows // 2, np.arange(cols) - cols // 2,
                           indexing="ij")
        return (rows, cols), np.hypot(i, j), (np.arctan2(i, j) + np.pi) / (2 * np.pi)
    if transform == "dft":
        # Exact signed integer row frequencies: the last bits decide the order of tied radii.
        k = np.arange(rows)
        di = np.where(k < (rows + 1) // 2, k, k - rows).astype(float)
        i, j = np.meshgrid(di, np.arange(cols // 2 + 1), indexing="ij")
        return (rows, cols // 2 + 1), np.hypot(i, j), (np.arctan2(i, j) + np.pi / 2) / np.pi
    if transform == "dct":
        i, j = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
        return (rows, cols), np.hypot(i / 2, j / 2), np.arctan2(i, j) / (np.pi / 2)
    raise ValueError(f"unknown transform {transform!r}")


def _keys(rows: int, cols: int, transform: str, storage: str) -> tuple[np.ndarray, float]:
    """Version 1.2: the integer key q of each coefficient (row-major), and the radius's scale (sqrt(q) times it)."""
    if transform == "dft" and storage == "complex64":
        i, j = np.meshgrid(np.arange(rows) - rows // 2, np.arange(cols) - cols // 2, indexing="ij")
        return (i * i + j * j).ravel(), 1.0
    if transform == "dft":
        k = np.arange(rows)
        di = np.where(k < (rows + 1) // 2, k, k - rows)
        i, j = np.meshgrid(di, np.arange(cols // 2 + 1), indexing="ij")
        return (i * i + j * j).ravel(), 1.0
    i, j = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    return (i * i + j * j).ravel(), 0.5


S_SLACK = float.fromhex("0x1.0000000001198p+0")


def _bound(rows: int, cols: int, cutoff: float) -> fractions.Fraction:
    """A² S² (rows² + cols²), exactly, with A = 1 - cutoff in binary64."""
    a = fractions.Fraction(1.0 - cutoff)
    return a * a * fractions.Fraction(S_SLACK) ** 2 * (rows * rows + cols * cols)


def _order(rows: int, cols: int, transform: str, storage: str, cutoff: float, legacy: bool):
    """Which coefficient is which: (coefficient array shape, flat positions kept in stream order,
    their radii and angles)."""
    shape, radius, angle = _layout(rows, cols, transform, storage)
    if legacy:  # 1.0, 1.1: stable sort by the hypot radius, the prefix inside the circle
        order = np.argsort(radius.ravel(), kind="stable")
        r_sorted = radius.ravel()[order]
        limit = (1 - cutoff) * math.hypot(rows / 2, cols / 2) * (1 + 1e-12)
        kept = int(np.searchsorted(r_sorted, limit, side="right"))
        pos = order[:kept]
        return shape, pos, r_sorted[:kept], angle.ravel()[pos]
    q, scale = _keys(rows, cols, transform, storage)
    c = 1 if transform == "dct" else 4
    # c q <= bound exactly: q <= floor(bound / c) (q and the floor are integers).
    q_max = math.floor(_bound(rows, cols, cutoff) / c)
    inside = np.flatnonzero(q <= min(q_max, rows * rows + cols * cols))
    pos = inside[np.lexsort((inside, q[inside]))]  # by q, ties by row-major index
    return shape, pos, np.sqrt(q[pos].astype(float)) * scale, angle.ravel()[pos]


# --------------------------------------------------------------------------- decode

def _header(sec: dict[bytes, bytes]) -> tuple[dict, dict, dict]:
    """GEOM, PARM (defaults filled in) and STAT of tile 0, with the checks both layouts share."""
    g = _geom(sec[b"GEOM"])
    params = dict(V1_DEFAULTS)
    params.update(_json(sec[b"PARM"]))
    stats = _stat(sec[b"STAT"]) if b"STAT" in sec else {}
    # Each occupied cell had a point. With mask="footprint" the rebuilt cells include the
    # interpolated empty ones, which may outnumber the points: compare the occupied cells only.
    if g["points"] < g["cells"] - stats.get("cells_interpolated", 0):
        raise ValueError("header states fewer original points than occupied cells")
    if "resolution" in params and not math.isclose(params["resolution"], g["res"], rel_tol=1e-9):
        raise ValueError("parameter resolution disagrees with the grid's")
    cutoff = float(params["cutoff"])
    if not 0 <= cutoff < 1:
        raise ValueError("cutoff must be in [0, 1)")
    if params["storage"] not in ("quantized", "complex64") or params["detrend"] not in ("none", "plane"):
        raise ValueError("parameter section is invalid")
    step = float(params["step"])
    if params["storage"] == "quantized" and not 0 < step <= 1e12:
        raise ValueError("quantizer step is not in (0, 1e12]")
    return g, params, stats


def _points(g: dict, r: np.ndarray, col: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Points at the centres of cells (r, col) of the map with heights h above z0."""
    if not np.all(np.isfinite(h)):
        raise ValueError("coefficients decode to non-finite heights")
    u = (col + 0.5) * g["res"]
    v = (r + 0.5) * g["dy"]
    ca, sa = math.cos(g["angle"]), math.sin(g["angle"])
    x = g["x0"] + ca * u - sa * v
    y = g["y0"] + sa * u + ca * v
    return np.column_stack([x, y, g["z0"] + h]).astype(np.float64)


def decode(data: bytes) -> np.ndarray:
    data = bytes(data)
    minor, entries = _table(data)
    sec = _sections(data)
    g, params, stats = _header(sec)
    if _is_tiled(minor, _by_tile(entries).get(0, {})):
        return _decode_tiled(data, entries, sec, g, params, stats)
    if params.get("tile_size", 0) != 0:
        raise ValueError("a 1.0 file states a tile size")
    rows, cols = g["rows"], g["cols"]
    cutoff, step = float(params["cutoff"]), float(params["step"])
    transform, storage = params["transform"], params["storage"]

    mask = _mask(sec[b"MASK"], rows, cols)
    if int(mask.sum()) != g["cells"]:
        raise ValueError("occupancy mask disagrees with the header's cell count")

    # Which coefficient is which: the integer order (1.2) or the legacy one (1.0).
    shape, pos, r_kept, a_kept = _order(rows, cols, transform, storage, cutoff, minor < 2)
    kept = pos.size
    coef_count = stats.get("coef_count")
    if not isinstance(coef_count, int) or isinstance(coef_count, bool) or coef_count != kept:
        raise ValueError("coefficient count is missing or disagrees with the grid and cutoff")
    pairs = transform == "dft" and storage == "quantized"
    per = 2 if pairs else 1
    values = _stream(sec[b"COEF"], per * kept, np.repeat(r_kept, per), np.repeat(a_kept, per))
    if storage == "quantized":
        if np.iscomplexobj(values):
            raise ValueError("quantized file holds float coefficients")
        values = values * step
        if pairs:
            values = values[0::2] + 1j * values[1::2]
    elif not np.iscomplexobj(values) and kept:
        raise ValueError("complex64 file holds integer coefficients")

    if transform == "dct":
        coefs = np.zeros(rows * cols)
        coefs[pos] = values.real if np.iscomplexobj(values) else values
        height = sfft.idctn(coefs.reshape(shape), type=2, norm="ortho")
    elif storage == "complex64":
        coefs = np.zeros(rows * cols, np.complex128)
        coefs[pos] = values
        height = np.fft.ifft2(np.fft.ifftshift(coefs.reshape(shape))).real
    else:
        coefs = np.zeros(shape[0] * shape[1], np.complex128)
        coefs[pos] = values
        height = np.fft.irfft2(coefs.reshape(shape), s=(rows, cols), norm="ortho")

    if params["detrend"] == "plane":
        a, b, c = g["plane"]
        height = height + (a + b * np.arange(cols)[None, :] + c * np.arange(rows)[:, None])

    r, col = np.nonzero(mask)  # rebuilt cells, row-major
    h = height[r, col]
    if b"RESD" in sec:
        e = float(params["target_max_error"])
        if not e > 0:
            raise ValueError("residual layer without target_max_error")
        q = _residual(sec[b"RESD"], mask)
        h = h + q * 2 * e * (1 - 1e-6)
    return _points(g, r, col, h)


# --------------------------------------------------------------------------- tiles (1.1)

TILE_MIN, TILE_MAX = 16, 65536  # T, cells
MAX_GRID_CELLS_TILED = 1 << 36
MAX_TILES = 1 << 20
TILES_PER_FILE_BYTE = 64
TIDX_CODINGS = (1, 2)  # 2: the errors in byte planes
TIDX_HEAD = struct.Struct("<BIHB")  # coding, T, overlap M, base reach K
# A 1.1 file fixes these parameters (format.md, "What changes in a 1.1 file").
TILED_PARAMS = {"transform": "dct", "storage": "quantized", "detrend": "plane", "mask": "exact"}


def _tile_box(k: int, rows: int, cols: int, size: int, tx: int) -> tuple[int, int, int, int]:
    """Rows r0..r1-1 and columns c0..c1-1 of tile number k (1-based, row-major)."""
    i, j = divmod(k - 1, tx)
    return i * size, min(rows, (i + 1) * size), j * size, min(cols, (j + 1) * size)


def _tile_index(p: bytes, n: int, size: int) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """TIDX: overlap M, base reach K, cells rebuilt per tile (n), DEM RMSE and max error of the m tiles with cells."""
    if len(p) < TIDX_HEAD.size:
        raise ValueError("tile index is truncated")
    coding, t, overlap, reach = TIDX_HEAD.unpack_from(p, 0)
    if coding not in TIDX_CODINGS:
        raise ValueError(f"tile index has unknown coding {coding}")
    if t != size:
        raise ValueError("tile index states another tile size than PARM")
    if 2 * overlap > size:
        raise ValueError("tile overlap is more than half a tile")
    frame = p[TIDX_HEAD.size:]
    try:
        declared = zstandard.get_frame_parameters(frame).content_size
    except zstandard.ZstdError as exc:
        raise ValueError(f"tile index is not a zstd frame: {exc}") from exc
    # Its size is 4n + 8m with 0 <= m <= n: checked before anything is allocated.
    if declared == zstandard.CONTENTSIZE_UNKNOWN:
        raise ValueError("tile index does not state its size")
    if not 4 * n <= declared <= 12 * n or (declared - 4 * n) % 8:
        raise ValueError(f"tile index declares {declared} bytes for {n} tiles")
    m = (declared - 4 * n) // 8
    try:
        unpacker = zstandard.ZstdDecompressor().decompressobj()
        raw = unpacker.decompress(frame)
        rest = unpacker.unused_data
    except zstandard.ZstdError as exc:
        raise ValueError(f"tile index does not decompress: {exc}") from exc
    if len(raw) != declared or rest:
        raise ValueError("tile index is not one frame of its declared size")
    planes = np.frombuffer(raw[:4 * n], np.uint8).reshape(4, n).astype(np.uint64)
    cells = (planes[0] | planes[1] << 8 | planes[2] << 16 | planes[3] << 24).astype(np.int64)
    if int(np.count_nonzero(cells)) != m:
        raise ValueError("tile index holds figures for another number of tiles than have cells")
    figure_bytes = np.frombuffer(raw[4 * n:], np.uint8)
    if coding == 2:  # 4 byte planes of the 2m values
        figure_bytes = figure_bytes.reshape(4, 2 * m).T.copy()
    figures = figure_bytes.view("<f4").reshape(-1).astype(np.float64)
    rmse, max_error = figures[:m], figures[m:]
    if not (np.all(np.isfinite(figures)) and np.all(figures >= 0)):
        raise ValueError("tile index holds a negative or non-finite error")
    return overlap, reach, cells, rmse, max_error


def _dct_prefix(h: int, w: int, cutoff: float, legacy: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row-major positions, radii and angles of the kept DCT coefficients of an h x w array."""
    _shape, pos, radius, angle = _order(h, w, "dct", "quantized", cutoff, legacy)
    return pos, radius, angle


def _base_layer(p: bytes, rows: int, cols: int, size: int, cutoff: float, step: float,
                coef_count, reach: int, legacy: bool) -> np.ndarray:
    """BASE: the whole grid's lowest DCT coefficients as a dense (ni, nj) array g(i, j), metres."""
    radius_max = min(reach * max(rows, cols) / size, (1 - cutoff) * math.hypot(rows / 2, cols / 2)) * (1 + 1e-12)
    if reach == 0:  # no base layer: not even the DC
        if coef_count != 0:
            raise ValueError("coefficient count is missing or disagrees with the base layer")
        _stream(p, 0, np.zeros(0), np.zeros(0), free=True)
        return np.zeros((1, 1))
    # hypot(i/2, j/2) <= radius_max needs i, j <= 2 radius_max: only that corner is enumerated.
    ni, nj = min(rows, int(2 * radius_max) + 1), min(cols, int(2 * radius_max) + 1)
    i, j = np.meshgrid(np.arange(ni), np.arange(nj), indexing="ij")
    angle = (np.arctan2(i, j) / (np.pi / 2)).ravel()
    if legacy:
        radius = np.hypot(i / 2, j / 2).ravel()
        order = np.argsort(radius, kind="stable")  # ties in row-major order of (i, j)
        kept = int(np.searchsorted(radius[order], radius_max, side="right"))
    else:  # q <= A² S² (rows² + cols²) and q T² <= 4 S² (K max(rows, cols))², exactly
        q = (i * i + j * j).ravel()
        q_max = min(math.floor(_bound(rows, cols, cutoff)),
                    math.floor(4 * fractions.Fraction(S_SLACK) ** 2 * (reach * max(rows, cols)) ** 2 / (size * size)))
        inside = np.flatnonzero(q <= q_max)
        order = inside[np.lexsort((inside, q[inside]))]
        kept = order.size
        radius = np.sqrt(q.astype(float)) * 0.5
    if not isinstance(coef_count, int) or isinstance(coef_count, bool) or coef_count != kept:
        raise ValueError("coefficient count is missing or disagrees with the base layer")
    pos = order[:kept]
    values = _stream(p, kept, radius[pos], angle[pos], free=True)
    if np.iscomplexobj(values):
        raise ValueError("base layer holds float coefficients")
    g = np.zeros(ni * nj)
    g[pos] = values * step
    return g.reshape(ni, nj)


def _phi(n: int, k: int, cells: np.ndarray) -> np.ndarray:
    """DCT-II orthonormal basis phi_N(k, n) for k in 0..k-1 at the given cells: shape (k, len(cells))."""
    kk = np.arange(k)[:, None]
    out = np.sqrt(2 / n) * np.cos(np.pi * kk * (2 * cells[None, :] + 1) / (2 * n))
    out[0] = 1 / math.sqrt(n)
    return out


def _decode_tile(data: bytes, k: int, secs: dict, g: dict, params: dict, size: int, overlap: int,
                 count: int, base: np.ndarray, tx: int,
                 map_mask: np.ndarray | None = None,
                 map_resid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows, columns (map indices, row-major within the tile) and heights above z0 of tile k."""
    rows, cols = g["rows"], g["cols"]
    r0, r1, c0, c1 = _tile_box(k, rows, cols, size, tx)
    h, w = r1 - r0, c1 - c0
    name = f"tile {k}: "
    if map_mask is not None:  # the map mask's cells of the tile
        mask = map_mask[r0:r1, c0:c1]
    elif b"MASK" in secs:
        mask = _mask(_payload(data, b"MASK", secs[b"MASK"], name), h, w)
    else:  # a full tile without MASK: every cell
        mask = np.ones((h, w), bool)
    if int(mask.sum()) != count:
        raise ValueError(f"{name}occupancy mask disagrees with the tile index")
    # The coded window: the tile and M cells around it, within the map.
    wr0, wr1 = max(0, r0 - overlap), min(rows, r1 + overlap)
    wc0, wc1 = max(0, c0 - overlap), min(cols, c1 + overlap)
    hh, ww = wr1 - wr0, wc1 - wc0
    pos, radius, angle = _dct_prefix(hh, ww, float(params["cutoff"]), data[9] < 2)  # 1.1: legacy order
    coefs = np.zeros(hh * ww)
    if b"COEF" in secs:  # none: every coefficient 0
        values = _stream(_payload(data, b"COEF", secs[b"COEF"], name), len(pos), radius, angle, free=True)
        if np.iscomplexobj(values):
            raise ValueError(f"{name}holds float coefficients")
        coefs[pos] = values * float(params["step"])
    window = sfft.idctn(coefs.reshape(hh, ww), type=2, norm="ortho")
    height = window[r0 - wr0:r1 - wr0, c0 - wc0:c1 - wc0]
    # The base layer and the plane on the tile's own cells of the map.
    rr, cc = np.arange(r0, r1), np.arange(c0, c1)
    height = height + _phi(rows, base.shape[0], rr).T @ base @ _phi(cols, base.shape[1], cc)
    a, b, c = g["plane"]
    height = height + (a + b * cc[None, :] + c * rr[:, None])
    r, col = np.nonzero(mask)  # row-major within the tile
    hv = height[r, col]
    e = float(params["target_max_error"])
    if map_resid is not None:  # the map residual's integers at the tile's cells
        hv = hv + map_resid[r0:r1, c0:c1][r, col] * 2 * e * (1 - 1e-6)
    elif e > 0:
        q = _residual(_payload(data, b"RESD", secs[b"RESD"], name), mask)
        if np.iscomplexobj(q):
            raise ValueError(f"{name}residual layer holds float values")
        hv = hv + q * 2 * e * (1 - 1e-6)
    return r + r0, col + c0, hv


def decode_grid(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """A tiled (1.1) file's whole grid: the mask (rows, cols) bool and the heights above z0 (metres,
    0 where the mask is not set)."""
    data = bytes(data)
    minor, entries = _table(data)
    sec = _sections(data)
    if not _is_tiled(minor, _by_tile(entries).get(0, {})):
        raise ValueError("not a tiled file")
    return _tiled_grid(data, entries, sec, *_header(sec))


def _decode_tiled(data: bytes, entries, sec: dict, g: dict, params: dict, stats: dict) -> np.ndarray:
    """A 1.1 file, whole: points in row-major order of the map."""
    mask, heights = _tiled_grid(data, entries, sec, g, params, stats)
    r, col = np.nonzero(mask)  # the map's rows in row-major order
    return _points(g, r, col, heights[r, col])


def _tiled_grid(data: bytes, entries, sec: dict, g: dict, params: dict,
                stats: dict) -> tuple[np.ndarray, np.ndarray]:
    """Every tile in tile number order, into the map's mask and heights."""
    rows, cols = g["rows"], g["cols"]
    for key, value in TILED_PARAMS.items():
        if params[key] != value:
            raise ValueError(f"a tiled file has {key} {params[key]!r}")
    size = params.get("tile_size", 0)
    if not isinstance(size, int) or isinstance(size, bool) or not TILE_MIN <= size <= TILE_MAX:
        raise ValueError("tile size is missing or out of range")
    if rows <= size and cols <= size:
        raise ValueError("a tiled file's grid fits in one tile")
    if rows * cols > MAX_GRID_CELLS_TILED:
        raise ValueError("grid has more cells than a tiled file may")
    ty, tx = -(-rows // size), -(-cols // size)
    n = ty * tx
    if n > MAX_TILES or n > TILES_PER_FILE_BYTE * len(data):
        raise ValueError(f"{n} tiles: more than the file can hold")
    e = float(params["target_max_error"])
    overlap, reach, cells, _rmse, _max_error = _tile_index(sec[b"TIDX"], n, size)
    for k in range(1, n + 1):
        r0, r1, c0, c1 = _tile_box(k, rows, cols, size, tx)
        if cells[k - 1] > (r1 - r0) * (c1 - c0):
            raise ValueError(f"tile {k}: more cells than the tile has")
    if int(cells.sum()) != g["cells"]:
        raise ValueError("tile index disagrees with the header's cell count")
    tiles = _by_tile(entries)
    if max(tiles) > n:
        raise ValueError(f"section of tile {max(tiles)}, beyond the {n} tiles")
    coded = (b"MASK", b"COEF", b"RESD") if e > 0 else (b"MASK", b"COEF")
    map_mask = None
    if b"MASK" in sec:  # the map mask: no tile holds a MASK
        coded = tuple(t for t in coded if t != b"MASK")
        map_mask = _mask(sec[b"MASK"], rows, cols)
    map_resid = None
    if b"RESD" in sec:  # the map residual (only beside the map mask): no tile holds a RESD
        if e <= 0:
            raise ValueError("a map residual in a file without a maximum-error target")
        coded = tuple(t for t in coded if t != b"RESD")
        q = _residual(sec[b"RESD"], map_mask)
        if np.iscomplexobj(q):
            raise ValueError("map residual holds float values")
        map_resid = np.zeros((rows, cols), np.int64)
        map_resid[map_mask] = q
    for k in range(1, n + 1):
        have = tiles.get(k, {})
        r0, r1, c0, c1 = _tile_box(k, rows, cols, size, tx)
        full = cells[k - 1] == (r1 - r0) * (c1 - c0)
        for tag in (b"MASK", b"COEF", b"RESD"):
            wanted = cells[k - 1] > 0 and tag in coded
            if tag == b"MASK" and full and tag not in have and map_mask is None:
                continue  # a full tile may leave its mask out
            if tag == b"COEF" and tag not in have:
                continue  # and any tile its coefficients, all 0 then
            if (tag in have) != wanted:
                raise ValueError(f"tile {k}: section {tag!r} " + ("is missing" if wanted else "is not expected"))
    base = _base_layer(sec[b"BASE"], rows, cols, size, float(params["cutoff"]), float(params["step"]),
                       stats.get("coef_count"), reach, data[9] < 2)  # the preamble's minor version: 1.1's legacy order
    heights = np.zeros((rows, cols))
    mask = np.zeros((rows, cols), bool)
    for k in range(1, n + 1):
        if cells[k - 1]:
            r, col, h = _decode_tile(data, k, tiles.get(k, {}), g, params, size, overlap, int(cells[k - 1]), base, tx,
                                     map_mask, map_resid)
            heights[r, col] = h
            mask[r, col] = True
    return mask, heights


# --------------------------------------------------------------------------- link frames
# Written from docs/format.md's section "Link frames" alone (not from dftpcc/link.py): a data frame or
# an acknowledgement parsed into a dict, a change's plan, and a change's target rebuilt from its frames.

LINK_MAGIC = b"\x89DL"
LINK_MAX_MAP = 1 << 30


def link_frame(data: bytes) -> dict:
    """A frame's fields; ValueError for anything the document refuses."""
    if len(data) < 13 + 4:
        raise ValueError("frame shorter than its head and CRC")
    if zlib.crc32(data[:-4]) != struct.unpack("<I", data[-4:])[0]:
        raise ValueError("frame CRC")
    if data[:3] != LINK_MAGIC or data[3] != 1:
        raise ValueError("frame magic or layout")
    kind = data[4]
    (map_id,) = struct.unpack_from("<Q", data, 5)
    body = data[13:-4]
    if kind == 1:
        if len(body) < 24:
            raise ValueError("data frame head cut")
        base_v, target_v = struct.unpack_from("<II", body, 0)
        check = body[8:16]
        item, part, parts = struct.unpack_from("<IHH", body, 16)
        if map_id == 0 or target_v < 1 or target_v <= base_v or parts < 1 or part >= parts:
            raise ValueError("data frame fields")
        return {"kind": "data", "map_id": map_id, "base_version": base_v, "target_version": target_v,
                "base_check": check, "item": item, "part": part, "parts": parts, "payload": body[24:]}
    if kind == 2:
        if len(body) < 52 + 1:
            raise ValueError("acknowledgement head cut")
        epoch, seq, version = struct.unpack_from("<III", body, 0)
        sha = body[12:44]
        base_v, target_v = struct.unpack_from("<II", body, 44)
        count, pos = _uleb(body, 52, "acknowledgement")
        reports = {}
        for _ in range(count):
            item, pos = _uleb(body, pos, "acknowledgement")
            n, pos = _uleb(body, pos, "acknowledgement")
            if pos >= len(body):
                raise ValueError("report cut")
            mode = body[pos]
            pos += 1
            if mode == 0:
                held = set(range(n))
            elif mode == 1:
                width = (n + 7) // 8
                if pos + width > len(body):
                    raise ValueError("bitmap cut")
                held = {i for i in range(n) if body[pos + i // 8] >> (i % 8) & 1}
                pos += width
            else:
                raise ValueError("report mode")
            reports[item] = (n, held)
        if pos != len(body):
            raise ValueError("bytes after the reports")
        return {"kind": "ack", "map_id": map_id, "epoch": epoch, "sequence": seq, "version": version,
                "sha256": sha, "base_version": base_v, "target_version": target_v, "reports": reports}
    raise ValueError(f"frame kind {kind}")


def link_plan(plan: bytes, base_size: int) -> dict:
    """A plan: target size and SHA-256, pieces [(kind, a, n)], the rest bytes."""
    declared = zstandard.get_frame_parameters(plan).content_size
    if declared == zstandard.CONTENTSIZE_UNKNOWN:
        raise ValueError("plan's content size not stated")
    if declared > LINK_MAX_MAP + 64 or declared > max(1 << 20, 1024 * len(plan)):
        raise ValueError("plan declares more than it may")
    body = _zstd(plan, declared)
    if len(body) != declared:
        raise ValueError("plan shorter than declared")
    size, pos = _uleb(body, 0, "plan")
    sha = body[pos:pos + 32]
    count, pos = _uleb(body, pos + 32, "plan")
    pieces, seen, rest_total = [], set(), 0
    for _ in range(count):
        kind = body[pos]
        pos += 1
        if kind == 1:
            n, pos = _uleb(body, pos, "plan")
            pieces.append((1, rest_total, n))
            rest_total += n
        elif kind in (0, 2):
            a, pos = _uleb(body, pos, "plan")
            n, pos = _uleb(body, pos, "plan")
            if kind == 0 and a + n > base_size:
                raise ValueError("copy past the base")
            if kind == 2 and (a == 0 or a == 2**32 - 1 or a in seen):
                raise ValueError("tile item 0, the preview's or twice")
            seen.add(a)
            pieces.append((kind, a, n))
        else:
            raise ValueError("piece kind")
    rest = body[pos:]
    if rest_total != len(rest) or sum(n for _, _, n in pieces) != size:
        raise ValueError("pieces do not add up")
    return {"size": size, "sha256": sha, "pieces": pieces, "rest": rest}


#: The item of a change's preview (not part of the target; the plan never names it).
LINK_PREVIEW_ITEM = 2**32 - 1


def link_preview(frames: list[bytes]) -> bytes:
    """The preview of one change (item 2^32 - 1, its parts joined in part order): a ``.dftpc`` file."""
    parts: dict[int, bytes] = {}
    count = None
    for raw in frames:
        f = link_frame(raw)
        if f["kind"] != "data" or f["item"] != LINK_PREVIEW_ITEM:
            continue
        if count is not None and count != f["parts"]:
            raise ValueError("part counts disagree")
        count = f["parts"]
        parts[f["part"]] = f["payload"]
    if count is None or len(parts) != count:
        raise ValueError("no whole preview")
    return b"".join(parts[i] for i in range(count))


def link_rebuild(base: bytes, frames: list[bytes]) -> bytes:
    """The target of one change from its data frames (any order, repeats allowed), checked by its SHA-256."""
    import hashlib

    items: dict[int, dict[int, bytes]] = {}
    counts: dict[int, int] = {}
    change = None
    for raw in frames:
        f = link_frame(raw)
        key = (f["map_id"], f["base_version"], f["target_version"], f["base_check"])
        if change is None:
            change = key
            if f["base_version"] and hashlib.sha256(base).digest()[:8] != f["base_check"]:
                raise ValueError("base check is not this base")
        elif key != change:
            raise ValueError("frames of two changes")
        if counts.setdefault(f["item"], f["parts"]) != f["parts"]:
            raise ValueError("part counts disagree")
        items.setdefault(f["item"], {})[f["part"]] = f["payload"]
    if change is None:
        raise ValueError("no frame")
    base = base if change[1] else b""

    def joined(item: int) -> bytes:
        if len(items.get(item, {})) != counts.get(item, -1):
            raise ValueError(f"item {item} incomplete")
        return b"".join(items[item][i] for i in range(counts[item]))

    plan = link_plan(joined(0), len(base))
    out = bytearray()
    for kind, a, n in plan["pieces"]:
        if kind == 0:
            out += base[a:a + n]
        elif kind == 1:
            out += plan["rest"][a:a + n]
        else:
            tile = joined(a)
            if len(tile) != n:
                raise ValueError("tile item length")
            out += tile
    if hashlib.sha256(out).digest() != plan["sha256"]:
        raise ValueError("result SHA-256")
    return bytes(out)
