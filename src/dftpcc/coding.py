"""Encode stage: quantize coefficients and entropy-code them and the mask.

Coefficients arrive ordered from low to high frequency. They are cut into
chunks of geometrically growing length, each coded on its own, so any prefix
of whole chunks decodes to a coarser map (progressive decoding). The
occupancy mask is bit-packed and zstd-compressed.
"""

from __future__ import annotations

import math
import struct
import zlib

import numpy as np
import zstandard

from .errors import CorruptFileError

__all__ = [
    "quantize",
    "dequantize",
    "choose_step",
    "encode_coefficients",
    "decode_coefficients",
    "encode_mask",
    "decode_mask",
]

#: zstd level for coefficient chunks and the mask: high ratio, still fast on small inputs.
ZSTD_LEVEL = 19
#: Length of the first coefficient chunk; each next chunk is CHUNK_GROWTH times longer.
FIRST_CHUNK = 256
CHUNK_GROWTH = 2
#: Chunk header: coefficient count, payload bytes, CRC-32 of the payload.
_CHUNK = struct.Struct("<IIII")  # count, nbytes, crc32, element kind
#: Element kinds inside a chunk.
KIND_INT = 0
KIND_COMPLEX64 = 1
#: A chunk never holds more coefficients than this (guards allocation on decode).
MAX_CHUNK_COEFS = 1 << 28


def quantize(values: np.ndarray, step: float, deadzone: float) -> np.ndarray:
    """Dead-zone uniform quantizer: integers ``sign(c) * floor(|c|/step + 0.5 - deadzone)``.

    Parameters
    ----------
    values : ndarray of float
        Real coefficients, metres (orthonormal transform).
    step : float
        Quantizer step in metres.
    deadzone : float
        Rounding offset in steps, in [0, 0.5).
    """
    q = np.floor(np.abs(values) / step + (0.5 - deadzone))
    return (np.sign(values) * q).astype(np.int64)


def dequantize(q: np.ndarray, step: float) -> np.ndarray:
    """Reconstruction of :func:`quantize`: ``q * step`` (metres)."""
    return q.astype(np.float64) * step


def choose_step(values: np.ndarray, *, target_rmse: float, n_cells: int, deadzone: float) -> float:
    """Largest step whose quantization error is at most ``target_rmse`` metres.

    The error is measured exactly in the coefficient domain (Parseval holds
    for the orthonormal transform) as the RMS over all ``n_cells`` cells of
    the grid. Found by bisection on a log scale.
    """
    budget = target_rmse * target_rmse * n_cells
    values = np.asarray(values, dtype=np.float64)

    def sq_error(step: float) -> float:
        err = values - dequantize(quantize(values, step, deadzone), step)
        return float(np.dot(err, err))

    lo, hi = target_rmse * 1e-3, max(target_rmse * math.sqrt(12.0 * n_cells), 1e-12)
    if sq_error(hi) <= budget:
        return hi
    for _ in range(40):
        mid = math.sqrt(lo * hi)
        if sq_error(mid) <= budget:
            lo = mid
        else:
            hi = mid
        if hi / lo < 1.01:
            break
    return lo


def _chunk_bounds(count: int) -> list[tuple[int, int]]:
    bounds, start, size = [], 0, FIRST_CHUNK
    while start < count:
        stop = min(count, start + size)
        bounds.append((start, stop))
        start, size = stop, size * CHUNK_GROWTH
    return bounds


def _zigzag(q: np.ndarray) -> np.ndarray:
    return ((q << 1) ^ (q >> 63)).astype(np.uint64)


def _unzigzag(u: np.ndarray) -> np.ndarray:
    return (u >> np.uint64(1)).astype(np.int64) ^ -(u & np.uint64(1)).astype(np.int64)


def _pack_ints(q: np.ndarray) -> bytes:
    # Byte planes (low bytes of all values, then the next bytes...) let zstd
    # see the long runs of zero high bytes that small coefficients leave.
    u = _zigzag(q)
    width = max(1, (int(u.max()).bit_length() + 7) // 8) if u.size else 1
    planes = u.astype("<u8").view(np.uint8).reshape(-1, 8)[:, :width].T
    return bytes([width]) + np.ascontiguousarray(planes).tobytes()


def _unpack_ints(raw: bytes, count: int) -> np.ndarray:
    if not raw:
        raise CorruptFileError("coefficient chunk is empty")
    width = raw[0]
    if not 1 <= width <= 8 or len(raw) != 1 + width * count:
        raise CorruptFileError("coefficient chunk has an inconsistent length")
    planes = np.frombuffer(raw, dtype=np.uint8, offset=1).reshape(width, count)
    full = np.zeros((count, 8), dtype=np.uint8)
    full[:, :width] = planes.T
    return _unzigzag(full.view("<u8").ravel())


def _unzstd(dctx: zstandard.ZstdDecompressor, payload: bytes, limit: int, what: str) -> bytes:
    """Decompress one zstd frame that must expand to at most ``limit`` bytes.

    The frame's declared size is checked before anything is allocated, so a
    crafted frame cannot ask for more memory than the header allows.
    """
    try:
        declared = zstandard.frame_content_size(payload)
        if declared > limit:
            raise CorruptFileError(f"{what} declares {declared} bytes, more than the {limit} it can hold")
        return dctx.decompress(payload, max_output_size=limit)
    except zstandard.ZstdError as exc:
        raise CorruptFileError(f"{what} does not decompress: {exc}") from None


def encode_coefficients(values: np.ndarray) -> bytes:
    """Code an ordered coefficient stream as self-checking chunks.

    ``values`` is either int64 (quantized, zstd-coded) or complex64 (the
    paper's raw storage, stored as is: real and imaginary float32, little
    endian).
    """
    out = [struct.pack("<I", len(_chunk_bounds(values.size)))]
    complex_kind = np.iscomplexobj(values)
    cctx = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
    for start, stop in _chunk_bounds(values.size):
        part = values[start:stop]
        if complex_kind:
            payload, kind = part.astype("<c8").tobytes(), KIND_COMPLEX64
        else:
            payload, kind = cctx.compress(_pack_ints(part)), KIND_INT
        out.append(_CHUNK.pack(stop - start, len(payload), zlib.crc32(payload), kind))
        out.append(payload)
    return b"".join(out)


def decode_coefficients(blob: bytes | memoryview, expected: int, *, allow_partial: bool = False) -> np.ndarray:
    """Inverse of :func:`encode_coefficients`.

    Parameters
    ----------
    blob : bytes
        The coefficient section (possibly truncated when ``allow_partial``).
    expected : int
        Number of coefficients the header announces.
    allow_partial : bool
        Return the coefficients of the whole chunks present instead of
        raising when the section is cut short (progressive decoding).

    Returns
    -------
    ndarray
        int64 or complex128 coefficients, at most ``expected`` of them.
    """
    blob = memoryview(blob)
    if len(blob) < 4:
        if allow_partial:
            return np.zeros(0, dtype=np.int64)
        raise CorruptFileError("coefficient section is truncated")
    (nchunks,) = struct.unpack_from("<I", blob, 0)
    bounds = _chunk_bounds(expected)
    if nchunks != len(bounds):
        raise CorruptFileError(f"coefficient section has {nchunks} chunks, header implies {len(bounds)}")
    pos, parts = 4, []
    dctx = zstandard.ZstdDecompressor()
    for index, (start, stop) in enumerate(bounds):
        if pos + _CHUNK.size > len(blob):
            if allow_partial:
                break
            raise CorruptFileError(f"coefficient chunk {index} is truncated")
        count, nbytes, crc, kind = _CHUNK.unpack_from(blob, pos)
        pos += _CHUNK.size
        if count != stop - start or count > MAX_CHUNK_COEFS:
            raise CorruptFileError(f"coefficient chunk {index} holds {count} values, expected {stop - start}")
        if pos + nbytes > len(blob):
            if allow_partial:
                break
            raise CorruptFileError(f"coefficient chunk {index} is truncated")
        payload = bytes(blob[pos:pos + nbytes])
        pos += nbytes
        if zlib.crc32(payload) != crc:
            raise CorruptFileError(f"coefficient chunk {index} fails its checksum")
        if kind == KIND_COMPLEX64:
            if nbytes != 8 * count:
                raise CorruptFileError(f"coefficient chunk {index} has a wrong length")
            parts.append(np.frombuffer(payload, dtype="<c8").astype(np.complex128))
        elif kind == KIND_INT:
            raw = _unzstd(dctx, payload, 1 + 8 * count, f"coefficient chunk {index}")
            parts.append(_unpack_ints(raw, count))
        else:
            raise CorruptFileError(f"coefficient chunk {index} has unknown kind {kind}")
    if not parts:
        return np.zeros(0, dtype=np.int64)
    if len({p.dtype for p in parts}) != 1:
        raise CorruptFileError("coefficient chunks mix kinds")
    return np.concatenate(parts)


def encode_mask(mask: np.ndarray) -> bytes:
    """Bit-packed occupancy (row-major), zstd-compressed."""
    return zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress(np.packbits(mask.ravel()).tobytes())


def decode_mask(blob: bytes | memoryview, shape: tuple[int, int]) -> np.ndarray:
    """Inverse of :func:`encode_mask`; checks the size against ``shape``."""
    nbytes = (shape[0] * shape[1] + 7) // 8
    raw = _unzstd(zstandard.ZstdDecompressor(), bytes(blob), nbytes, "occupancy mask")
    if len(raw) != nbytes:
        raise CorruptFileError("occupancy mask has the wrong size for the grid")
    bits = np.unpackbits(np.frombuffer(raw, dtype=np.uint8), count=shape[0] * shape[1])
    return bits.astype(bool).reshape(shape)
