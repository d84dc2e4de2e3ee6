"""Quantize stage: the dead-zone uniform quantizer of the coefficients, and the step a target asks for.

A file states its step in a few significant digits (:func:`short_step`); the integers it codes
stay below 2**63 (:data:`QUANT_LIMIT`), or the quantizer refuses (:func:`finest_step` names the
smallest workable step).
"""

from __future__ import annotations

import math

import numpy as np

from . import kernels
from .errors import InvalidInputError
from .params import MAX_COORDINATE_M
from .sums import dot

__all__ = ["quantize", "dequantize", "finest_step", "round_up", "short_step", "choose_step", "quantization_sq_error",
           "QUANT_LIMIT"]


#: choose_step stops when the step is known to within this factor.
STEP_TOLERANCE = 1.02


#: choose_step evaluates at most about this many coefficients per try.
STEP_SAMPLE = 32768


#: Quantized coefficients are int64: zstd chunks (kind 0) hold any of them,
#: zigzag-mapped in up to 8 byte planes, and an ANS chunk whose values exceed
#: MAX_ANS_SYMBOL falls back to kind 0. So the real limit is the quantizer's
#: own cast: ``|c| / step`` must stay below 2**63, or the integers wrap.
QUANT_LIMIT = 2.0**63


#: Significant digits of a smallest workable step or target, as a message states it (rounded up).
SUGGESTED_DIGITS = 3


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

    Raises
    ------
    InvalidInputError
        ``step`` is so fine that an integer would pass :data:`QUANT_LIMIT`
        (see :func:`finest_step`): the quantizer refuses rather than wrap.
    """
    with np.errstate(over="ignore"):
        q = np.floor(np.abs(values) / step + (0.5 - deadzone))
    if q.size and not q.max() < QUANT_LIMIT:  # also inf and NaN
        raise InvalidInputError(
            f"quantizer step {step:g} m is too fine for coefficients up to {float(np.abs(values).max()):g} m: "
            f"their integers would pass 2**63 and wrap; the smallest workable step is {finest_step(values):g} m")
    return (np.sign(values) * q).astype(np.int64)


def finest_step(values: np.ndarray) -> float:
    """The smallest quantizer step (metres, :data:`SUGGESTED_DIGITS` significant digits)
    at which :func:`quantize` takes ``values`` (metres) without passing :data:`QUANT_LIMIT`,
    whatever the dead zone; 0 when every value is 0."""
    peak = float(np.abs(values).max(initial=0.0))
    if peak == 0.0:
        return 0.0
    # A hair above peak / 2**63, so that |c| / step + 0.5 rounds below 2**63.
    return round_up(max(peak / QUANT_LIMIT * (1 + 1e-9), math.ulp(0.0)))


def round_up(value: float, digits: int = SUGGESTED_DIGITS) -> float:
    """``value`` (> 0) rounded up to ``digits`` significant digits, to state in a message."""
    short = float(f"{value:.{digits - 1}e}")
    if short < value:
        short = float(f"{short + 10.0 ** (math.floor(math.log10(short)) - digits + 1):.{digits - 1}e}")
    return max(short, value)


#: Significant digits of a quantizer step as the file states it.
STEP_DIGITS = 6


def short_step(step: float) -> float:
    """The largest step a file can state that is not above ``step``: at most
    :data:`~dftpcc.params.MAX_COORDINATE_M`, in :data:`STEP_DIGITS` significant
    digits. The file states it in a few characters, and a finer step only
    lowers the error (rate control may search steps beyond the limit for a
    huge target; they are held at it)."""
    if not (math.isfinite(step) and step > 0.0):
        return step
    step = min(step, MAX_COORDINATE_M)
    short = float(f"{step:.{STEP_DIGITS}g}")
    while short > step:
        short = float(f"{short - 10.0 ** (math.floor(math.log10(short)) - STEP_DIGITS + 1):.{STEP_DIGITS}g}")
    return short


def dequantize(q: np.ndarray, step: float) -> np.ndarray:
    """Reconstruction of :func:`quantize`: ``q * step`` (metres)."""
    return q.astype(np.float64) * step


@kernels.kernel("dequantize_into")
def dequantize_into(shape: tuple[int, int], where: np.ndarray, q: np.ndarray, step: float) -> np.ndarray:
    """A float64 array of ``shape``, zero but at the flat positions ``where``, which hold
    ``dequantize(q, step)`` (a decoder's coefficient block: the compiled twin writes each value
    where it goes instead of making the values, then scattering them)."""
    out = np.zeros(shape)
    out.ravel()[where] = dequantize(q, step)
    return out


def choose_step(values: np.ndarray, *, target_rmse: float, n_cells: int, deadzone: float) -> float:
    """Largest step whose quantization error is at most ``target_rmse`` metres.

    The error is measured exactly in the coefficient domain (Parseval holds
    for the orthonormal transform) as the RMS over all ``n_cells`` cells of
    the grid. Found by bisection on a log scale.
    """
    values = np.asarray(values, dtype=np.float64)
    finest = finest_step(values)  # of every value, not only the sample's
    # On long streams an evenly strided sample predicts the error well and
    # costs a fraction of the time (the file states the true error anyway).
    stride = max(1, values.size // STEP_SAMPLE)
    budget = target_rmse * target_rmse * n_cells / stride
    values = values[::stride]

    def sq_error(step: float) -> float:
        return quantization_sq_error(values, step, deadzone)

    lo = max(target_rmse * 1e-3, finest)
    hi = max(target_rmse * math.sqrt(12.0 * n_cells), 1e-12, lo)
    if sq_error(hi) <= budget:
        return hi
    for _ in range(40):
        mid = math.sqrt(lo * hi)
        if sq_error(mid) <= budget:
            lo = mid
        else:
            hi = mid
        if hi / lo < STEP_TOLERANCE:
            break
    return lo


@kernels.kernel("quantization_sq_error")
def quantization_sq_error(values: np.ndarray, step: float, deadzone: float) -> float:
    """The sum of squares (m²) of ``values - dequantize(quantize(values, step, deadzone), step)``."""
    err = values - dequantize(quantize(values, step, deadzone), step)
    return dot(err, err)

