"""An independent `.dftpc` decoder written from docs/format.md alone.

It does not import dftpcc: it exists to show whether the format document is enough to read a file.
``decode(data)`` returns the rebuilt points, shape (N, 3), float64.

Written by a helper that read only docs/format.md. When the section table lost its offsets
(entries of tag, LEB128 tile and length, CRC), ``_sections`` was updated to the new table by the
library's author, from the same document. Later, from the document's new rules: LEB128 of at most
64 bits (``_uleb``), no bytes after the last section (``_sections``), and only binary STAT and
COEF kind 3 for ANS (the drafts' JSON STAT and kind 2 refused). The rest is as the helper wrote it.
"""

from __future__ import annotations

import decimal
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
MAX_JSON_BYTES = 1 << 20

# PARM fields left out take these (frozen for all 1.x files).
V1_DEFAULTS = {
    "cutoff": 0.8, "profile": "compact", "aggregate": "mean", "frame": "axis",
    "transform": "dct", "detrend": "plane", "fill": "consistent", "storage": "quantized",
    "step": 0.0, "deadzone": 0.1, "coder": "ans", "mask": "exact", "target_rmse": 0.0,
    "target_max_error": 0.0, "target_bpp": 0.0,
}

STAT_FLOAT_IDS = {0: "dem_rmse_m", 1: "dem_max_error_m", 2: "gridding_rmse_m",
                  3: "vertical_rmse_m", 4: "unrepresented_fraction", 5: "unrepresented_rmse_m"}
STAT_INT_IDS = {128: "coef_count", 129: "cells_interpolated"}

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


def _sections(data: bytes) -> dict[bytes, bytes]:
    if len(data) < 20:
        raise ValueError("not a .dftpc file: too short")
    if data[:8] != MAGIC:
        raise ValueError("bad magic bytes")
    major, _minor, _flags, count = struct.unpack_from("<BBHI", data, 8)
    if major != 1:
        raise ValueError(f"unsupported major version {major}")
    if count > MAX_SECTIONS:
        raise ValueError("too many sections")
    entries, pos = [], 16
    for _ in range(count):
        if pos + 4 > len(data):
            raise ValueError("truncated section table")
        tag = data[pos:pos + 4]
        tile, pos = _uleb(data, pos + 4)
        length, pos = _uleb(data, pos)
        if pos + 4 > len(data):
            raise ValueError("truncated section table")
        entries.append((tag, tile, length, struct.unpack_from("<I", data, pos)[0]))
        pos += 4
    table_end = pos
    if table_end + 4 > len(data):
        raise ValueError("truncated section table")
    if zlib.crc32(data[:table_end]) != struct.unpack_from("<I", data, table_end)[0]:
        raise ValueError("section table fails its checksum")
    # The file ends where its last payload ends: bytes after it are refused.
    end = table_end + 4 + sum(length for _tag, _tile, length, _crc in entries)
    if len(data) > end:
        raise ValueError(f"{len(data) - end} bytes after the last section")
    sections: dict[bytes, bytes] = {}
    offset = table_end + 4  # payloads follow the table in its order
    for tag, tile, length, crc in entries:
        start, offset = offset, offset + length
        if tile != 0 or tag in sections:  # other tiles and repeated tags are skipped
            continue
        if offset > len(data):
            raise ValueError(f"section {tag!r} is truncated")
        payload = data[start:offset]
        if zlib.crc32(payload) != crc:
            raise ValueError(f"section {tag!r} fails its checksum")
        sections[tag] = payload
    for tag in (b"GEOM", b"PARM", b"MASK", b"COEF"):
        if tag not in sections:
            raise ValueError(f"section {tag!r} is missing")
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


def _mask_context(p: bytes, rows: int, cols: int, transposed: int) -> np.ndarray:
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
    for s, bits in enumerate(_seed_lines(p[10:10 + seed_bytes], n_stripes - 1, w), start=1):
        lines[s * L] = bits
    coder = constriction.stream.stack.AnsCoder(_words(p[10 + seed_bytes:]))
    popcount = np.array([bin(c).count("1") for c in range(256)], float)
    p_c = (popcount + 0.5) / 9
    n1 = np.zeros(256)
    nn = np.zeros(256)
    zeros = np.zeros(w, np.uint8)
    bern = constriction.stream.model.Bernoulli
    for t in range(L):
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
    if kind == 2:
        return _mask_context(p, rows, cols, transposed).astype(bool)
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


def _stream(p: bytes, total: int, radius: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """The values of a COEF-style section: int64 (quantized) or complex128 (complex64 chunks)."""
    bounds = _chunk_bounds(total)
    if len(p) < 4 or struct.unpack_from("<I", p, 0)[0] != len(bounds):
        raise ValueError("coefficient section has the wrong chunk count")
    values, kinds, pos = [], set(), 4
    for start, stop in bounds:
        if pos + 16 > len(p):
            raise ValueError("coefficient chunk is truncated")
        count, nbytes, crc, kind = struct.unpack_from("<4I", p, pos)
        body = p[pos + 16:pos + 16 + nbytes]
        pos += 16 + nbytes
        if count != stop - start or len(body) != nbytes or zlib.crc32(body) != crc:
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
    if len(kinds) > 1:
        raise ValueError("coefficient chunks mix kinds")
    if not values:
        return np.zeros(0, np.int64)
    return np.concatenate(values)


def _layout(rows: int, cols: int, transform: str, storage: str):
    """Coefficient array shape, and per coefficient (row-major): radius, angle in [0, 1]."""
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


# --------------------------------------------------------------------------- decode

def decode(data: bytes) -> np.ndarray:
    data = bytes(data)
    sec = _sections(data)
    g = _geom(sec[b"GEOM"])
    rows, cols = g["rows"], g["cols"]
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
    transform, storage = params["transform"], params["storage"]
    if not 0 <= cutoff < 1:
        raise ValueError("cutoff must be in [0, 1)")
    if storage not in ("quantized", "complex64") or params["detrend"] not in ("none", "plane"):
        raise ValueError("parameter section is invalid")
    step = float(params["step"])
    if storage == "quantized" and not 0 < step <= 1e12:
        raise ValueError("quantizer step is not in (0, 1e12]")

    mask = _mask(sec[b"MASK"], rows, cols)
    if int(mask.sum()) != g["cells"]:
        raise ValueError("occupancy mask disagrees with the header's cell count")

    # Which coefficient is which: stable sort by radius, keep the prefix inside the circle.
    shape, radius, angle = _layout(rows, cols, transform, storage)
    order = np.argsort(radius.ravel(), kind="stable")
    r_sorted = radius.ravel()[order]
    limit = (1 - cutoff) * math.hypot(rows / 2, cols / 2) * (1 + 1e-12)
    kept = int(np.searchsorted(r_sorted, limit, side="right"))
    coef_count = stats.get("coef_count")
    if not isinstance(coef_count, int) or isinstance(coef_count, bool) or coef_count != kept:
        raise ValueError("coefficient count is missing or disagrees with the grid and cutoff")
    pos, r_kept, a_kept = order[:kept], r_sorted[:kept], angle.ravel()[order[:kept]]
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
        q = _stream(sec[b"RESD"], len(r), np.zeros(len(r)), np.zeros(len(r)))
        h = h + q * 2 * e * (1 - 1e-6)
    if not np.all(np.isfinite(h)):
        raise ValueError("coefficients decode to non-finite heights")

    u = (col + 0.5) * g["res"]
    v = (r + 0.5) * g["dy"]
    ca, sa = math.cos(g["angle"]), math.sin(g["angle"])
    x = g["x0"] + ca * u - sa * v
    y = g["y0"] + sa * u + ca * v
    return np.column_stack([x, y, g["z0"] + h]).astype(np.float64)
