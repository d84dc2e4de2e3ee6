"""The residual layer: what brings every occupied cell within a promised maximum error.

After the low-passed, quantized spectrum, each rebuilt cell's remaining error
is quantized with a step of twice the bound (so rounding leaves at most the
bound) and coded as one integer per rebuilt cell, row-major, in the RESD
section. Interpolated (footprint) cells have no measured height and get 0.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from . import coding
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


def encode_residual(q: np.ndarray, coder: str) -> bytes:
    """The RESD section of ``q``."""
    flat = np.zeros(q.size)  # one band per chunk: the residual has no frequency
    # Every band layout puts all values in band 0, so there is no layout to choose. At a coarse
    # bound most values are 0, which the ANS model (its scale at least MIN_SCALE) codes at
    # 0.07 bits or more each: zstd takes the chunks where it is shorter.
    return coding.encode_coefficients(q, radius=flat, angle=flat, coder=coder, exhaustive=False, smallest=True)


def decode_residual(blob: Any, count: int) -> np.ndarray:
    """The ``count`` integers of a RESD section."""
    flat = np.zeros(count)
    q = coding.decode_coefficients(blob, count, radius=flat, angle=flat)
    if q.dtype.kind != "i" or q.size != count:
        raise CorruptFileError("residual layer is not one integer per rebuilt cell")
    return q
