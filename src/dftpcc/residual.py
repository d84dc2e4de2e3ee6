"""The residual layer: what brings every occupied cell within a promised maximum error.

After the low-passed, quantized spectrum, each rebuilt cell's remaining error
is quantized with a step of twice the bound (so rounding leaves at most the
bound) and coded as one integer per rebuilt cell, row-major, in the RESD
section. Interpolated (footprint) cells have no measured height and get 0.

Two layouts (docs/format.md, ``RESD``): the values in chunks, as coefficients
are; or, where most are 0, one *sparse* chunk: which cells are not 0, as a
picture coded with the occupancy mask's context model (the corrections cluster
where the terrain is rough), then their magnitudes and signs. The smaller wins.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from . import coding, occupancy
from .errors import CorruptFileError

__all__ = ["GUARANTEE_MARGIN", "residual_step", "residual", "encode_residual", "decode_residual"]

#: The residual layer aims this much inside the promised bound, so float
#: round-off in the decoder's inverse transform cannot break the guarantee.
GUARANTEE_MARGIN = 1e-6


def residual_step(bound: float) -> float:
    """Quantizer step (metres) of the residual layer that keeps every cell within ``bound``."""
    return 2.0 * bound * (1.0 - GUARANTEE_MARGIN)


def residual(target: np.ndarray, rebuilt: np.ndarray, measured: np.ndarray, kept: np.ndarray,
             bound: float) -> tuple[np.ndarray, np.ndarray]:
    """Integers that bring every measured cell of ``rebuilt`` within ``bound`` metres of ``target``.

    Parameters
    ----------
    target, rebuilt : ndarray, shape (rows, cols)
        Gridded and rebuilt heights, metres.
    measured : ndarray of bool
        Cells that held points (their error counts).
    kept : ndarray of bool
        Cells the file rebuilds (``measured``, or its footprint).
    bound : float
        Largest error allowed, metres.

    Returns
    -------
    q : ndarray of int64, one per kept cell (row-major)
    heights : ndarray, the corrected ``rebuilt``
    """
    step = residual_step(bound)
    err = np.where(measured, target - rebuilt, 0.0)[kept]
    q = np.round(err / step).astype(np.int64)
    heights = rebuilt.copy()
    heights[kept] += q * step
    return q, heights


def encode_residual(q: np.ndarray, coder: str, kept: np.ndarray) -> bytes:
    """The RESD section of ``q``, one integer per ``True`` cell of ``kept`` (row-major): the
    chunked layout, or the sparse one where at least half the values are 0 and it is shorter."""
    flat = np.zeros(q.size)  # one band per chunk: the residual has no frequency
    # Every band layout puts all values in band 0, so there is no layout to choose.
    chunked = coding.encode_coefficients(q, radius=flat, angle=flat, coder=coder, exhaustive=False)
    # At a coarse bound most values are 0, which kind 3 codes at 0.07 bits or more each (its scale
    # floor, MIN_SCALE), however they cluster: the sparse layout codes where they are not.
    if 2 * np.count_nonzero(q) > q.size:
        return chunked
    sparse = _encode_sparse(q, coder, kept)
    return sparse if len(sparse) < len(chunked) else chunked


_LENGTH = struct.Struct("<I")
#: Largest magnitude a sparse chunk may state (so that magnitude + 1 stays an int64).
MAX_SPARSE_MAGNITUDE = 1 << 62


def _encode_sparse(q: np.ndarray, coder: str, kept: np.ndarray) -> bytes:
    nonzero = q != 0
    picture = np.zeros(kept.shape, dtype=bool)
    picture[kept] = nonzero
    where = occupancy.encode_mask(picture)
    values = q[nonzero]
    flat = np.zeros(values.size)
    sizes = coding.encode_coefficients(np.abs(values) - 1, radius=flat, angle=flat, coder=coder, exhaustive=False,
                                       progressive=False)
    signs = np.packbits(values < 0).tobytes()
    return coding.one_chunk(q.size, _LENGTH.pack(len(where)) + where + sizes + signs, coding.KIND_SPARSE_RESIDUAL)


def _decode_sparse(payload: bytes, kept: np.ndarray) -> np.ndarray:
    what = "sparse residual layer"
    if len(payload) < _LENGTH.size:
        raise CorruptFileError(f"{what} is truncated")
    (length,) = _LENGTH.unpack_from(payload, 0)
    if _LENGTH.size + length > len(payload):
        raise CorruptFileError(f"{what}: its map of nonzero cells runs past the chunk")
    picture = occupancy.decode_mask(payload[_LENGTH.size:_LENGTH.size + length], kept.shape)
    if (picture & ~kept).any():
        raise CorruptFileError(f"{what} corrects a cell that is not rebuilt")
    nonzero = picture[kept]
    n = int(nonzero.sum())
    sign_at = len(payload) - (n + 7) // 8
    if sign_at < _LENGTH.size + length:
        raise CorruptFileError(f"{what} is too short for the signs of its {n} nonzero values")
    flat = np.zeros(n)
    sizes = coding.decode_coefficients(payload[_LENGTH.size + length:sign_at], n, radius=flat, angle=flat,
                                       progressive=False, exact=True)
    if sizes.dtype.kind != "i" or sizes.size != n or (n and (sizes.min() < 0 or sizes.max() > MAX_SPARSE_MAGNITUDE)):
        raise CorruptFileError(f"{what} has magnitudes outside 0..2**62")
    packed = np.frombuffer(payload, dtype=np.uint8, offset=sign_at)
    negative = np.unpackbits(packed)
    if negative[n:].any():
        raise CorruptFileError(f"{what} has a stray sign bit")
    magnitude = sizes + 1
    q = np.zeros(nonzero.size, dtype=np.int64)
    q[nonzero] = np.where(negative[:n].astype(bool), -magnitude, magnitude)
    return q


def decode_residual(blob: Any, kept: np.ndarray) -> np.ndarray:
    """The integers of a RESD section, one per ``True`` cell of ``kept``."""
    count = int(kept.sum())
    flat = np.zeros(count)
    q = coding.decode_coefficients(blob, count, radius=flat, angle=flat,
                                   whole={coding.KIND_SPARSE_RESIDUAL: lambda p: _decode_sparse(p, kept)})
    if q.dtype.kind != "i" or q.size != count:
        raise CorruptFileError("residual layer is not one integer per rebuilt cell")
    return q
