"""Spectrum stage: the DEM's 2D transform and the paper's circular low-pass.

Conventions (stated once, here):

* ``dft`` (the paper): ``F = fftshift(fft2(f))`` with the paper's eq. 1 sign
  and scaling (``exp(-2j*pi*...)``, no normalisation on the forward
  transform, ``1/(N*M)`` on the inverse, eq. 3). Low frequencies are centred:
  frequency (0, 0) sits at index ``(N//2, M//2)``.
* ``dft`` with quantized storage keeps only the Hermitian half,
  ``rfft2(f, norm='ortho')``: a real DEM's spectrum is conjugate-symmetric.
* ``dct``: orthonormal DCT-II (``scipy.fft.dctn(norm='ortho')``). It equals
  the DFT of the DEM mirrored about its borders, so the transform sees no
  wrap-around jump; index ``k`` of the DCT is DFT frequency ``k/2`` of the
  mirrored grid.

Cutoff (paper eq. 2): ``f_c = 1 - r / r_M``. We read ``r_M`` as half the
diagonal of the centred spectrum in frequency pixels,
``sqrt((N/2)**2 + (M/2)**2)``: the distance from the centre (DC) to a corner,
so ``f_c = 0`` keeps every coefficient. A coefficient at frequency
``(du, dv)`` (in DFT pixels) is kept when ``hypot(du, dv) <= r``. The DCT
uses the same circle in the same units, so a cutoff removes the same spatial
frequencies whichever transform is used.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.fft as sfft

__all__ = [
    "Layout",
    "layout",
    "radius_limit",
    "forward",
    "inverse",
    "kept_order",
]

#: Worker threads for scipy.fft; -1 uses every core.
FFT_WORKERS = -1


class Layout:
    """Where each stored coefficient of a transform sits and how far from DC.

    Attributes
    ----------
    kind : str
        ``full`` (centred complex DFT), ``half`` (rfft2) or ``dct``.
    shape : tuple of int
        Shape of the DEM (rows, cols).
    coef_shape : tuple of int
        Shape of the coefficient array.
    radius : ndarray, shape coef_shape
        Distance of each coefficient from DC in DFT frequency pixels.
    """

    def __init__(self, kind: str, shape: tuple[int, int]):
        self.kind = kind
        self.shape = shape
        n, m = shape
        if kind == "full":
            du = np.arange(n, dtype=float) - n // 2
            dv = np.arange(m, dtype=float) - m // 2
        elif kind == "half":
            du = sfft.fftfreq(n, 1.0 / n)
            dv = np.arange(m // 2 + 1, dtype=float)
        elif kind == "dct":
            du = np.arange(n, dtype=float) / 2.0
            dv = np.arange(m, dtype=float) / 2.0
        else:
            raise ValueError(f"unknown layout {kind!r}")
        self.coef_shape = (du.size, dv.size)
        self.radius = np.hypot(du[:, None], dv[None, :])


def layout(transform: str, storage: str, shape: tuple[int, int]) -> Layout:
    """The coefficient layout used by a transform/storage pair."""
    if transform == "dct":
        return Layout("dct", shape)
    return Layout("full" if storage == "complex64" else "half", shape)


def radius_limit(shape: tuple[int, int], cutoff: float) -> float:
    """Radius ``r = (1 - f_c) * r_M`` of the low-pass circle in frequency pixels."""
    n, m = shape
    return (1.0 - cutoff) * math.hypot(n / 2.0, m / 2.0)


def kept_order(lay: Layout, cutoff: float) -> np.ndarray:
    """Flat indices of the coefficients inside the circle, from low to high radius.

    The order is deterministic (stable sort on radius, ties by index), so the
    encoder and decoder derive it from the shape alone, and any prefix of the
    stream is a smaller circle: the basis of progressive decoding.
    """
    r = radius_limit(lay.shape, cutoff)
    flat_radius = lay.radius.ravel()
    # A hair of slack so a coefficient exactly on the circle is kept on every platform.
    inside = np.flatnonzero(flat_radius <= r * (1 + 1e-12))
    return inside[np.argsort(flat_radius[inside], kind="stable")]


def forward(values: np.ndarray, lay: Layout) -> np.ndarray:
    """Transform a DEM (rows, cols) to coefficients of ``lay.coef_shape``."""
    if lay.kind == "full":
        return sfft.fftshift(sfft.fft2(values, workers=FFT_WORKERS))
    if lay.kind == "half":
        return sfft.rfft2(values, norm="ortho", workers=FFT_WORKERS)
    return sfft.dctn(values, type=2, norm="ortho", workers=FFT_WORKERS)


def inverse(coefs: np.ndarray, lay: Layout) -> np.ndarray:
    """Back from coefficients to a real DEM of ``lay.shape`` (float64)."""
    if lay.kind == "full":
        return sfft.ifft2(sfft.ifftshift(coefs), workers=FFT_WORKERS).real
    if lay.kind == "half":
        return sfft.irfft2(coefs, s=lay.shape, norm="ortho", workers=FFT_WORKERS)
    return sfft.idctn(coefs, type=2, norm="ortho", workers=FFT_WORKERS)
