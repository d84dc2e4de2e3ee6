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

Which coefficients are kept, and their order, is decided in exact integers
(docs/format.md, *Which coefficient is which*): by the key ``du² + dv²`` (times
4 for the DCT, whose frequencies are half-integers), so that no ``hypot`` of
one C library or another can split a tie. Files of format 1.0 and 1.1 follow
the legacy rule, ordered by numpy's (glibc's) ``hypot``: ``legacy=True``.
"""

from __future__ import annotations

import contextlib
import functools
import math
import threading
from fractions import Fraction
from typing import Any, Callable, Iterator

import numpy as np
import scipy.fft as sfft

__all__ = [
    "Layout",
    "layout",
    "radius_limit",
    "forward",
    "inverse",
    "fft_workers",
    "corner",
    "kept_order",
    "kept_count",
    "values_per_coefficient",
    "mse_per_squared_error",
]

#: Worker threads for scipy.fft; -1 uses every core.
FFT_WORKERS = -1

#: This thread's worker count while :func:`fft_workers` holds one.
_this_thread = threading.local()


@contextlib.contextmanager
def fft_workers(workers: int | Callable[[], int | None] | None) -> Iterator[None]:
    """Run this thread's transforms on ``workers`` threads (None: :data:`FFT_WORKERS`) inside the block;
    a callable is asked before each transform.

    For a stage of the same map running beside them on another core (:meth:`dftpcc.kernels.Side.cores_left`):
    the transforms then take the cores it leaves while it runs. The coefficients' bits do not depend
    on it (each 1-D line is transformed whole by one thread).
    """
    before = getattr(_this_thread, "workers", None)
    _this_thread.workers = workers
    try:
        yield
    finally:
        _this_thread.workers = before


def _fft_workers() -> int:
    workers = getattr(_this_thread, "workers", None)
    if callable(workers):
        workers = workers()
    return FFT_WORKERS if workers is None else workers


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
    legacy : bool
        The legacy order by ``hypot`` (format 1.0 and 1.1), else the integer order.
    key : ndarray of int64, shape coef_shape, or None
        The integer order's key ``i² + j²`` (DCT) or ``di² + dj²`` (DFT), a property; None for the
        legacy order.

    See :meth:`angle_of` for the direction of a coefficient's frequency.
    """

    def __init__(self, kind: str, shape: tuple[int, int], *, legacy: bool = False):
        self.kind = kind
        self.shape = shape
        self.legacy = legacy
        n, m = shape
        if kind == "full":
            iu, iv = np.arange(n) - n // 2, np.arange(m) - m // 2
        elif kind == "half":
            # Signed integer row frequencies (fftfreq's order), computed exactly:
            # fftfreq(n, 1/n) is off by an ulp for some n, which reorders ties.
            k = np.arange(n)
            iu, iv = np.where(k < (n + 1) // 2, k, k - n), np.arange(m // 2 + 1)
        elif kind == "dct":
            iu, iv = np.arange(n), np.arange(m)
        else:
            raise ValueError(f"unknown layout {kind!r}")
        half = 0.5 if kind == "dct" else 1.0  # DCT index k is DFT frequency k/2
        du, dv = iu.astype(float) * half, iv.astype(float) * half
        self.coef_shape = (du.size, dv.size)
        self._du, self._dv = du, dv
        self._iu, self._iv = iu.astype(np.int64), iv.astype(np.int64)
        if legacy:
            self.radius = np.hypot(du[:, None], dv[None, :])
        else:
            # sqrt is correctly rounded everywhere: equal keys, equal radii (the bands need no more).
            self.radius = np.sqrt(self.key.astype(float)) * half

    @property
    def key(self) -> np.ndarray | None:
        """The integer order's key per coefficient (int64, coef_shape), made when asked (a large grid's
        layout holds its radii already); None for the legacy order."""
        if self.legacy:
            return None
        return self._iu[:, None] * self._iu[:, None] + self._iv[None, :] * self._iv[None, :]

    def angle_of(self, flat: np.ndarray) -> np.ndarray:
        """Direction of the frequencies at flat indices ``flat``, scaled to [0, 1]
        over the half-plane (``full``, ``half``) or quadrant (``dct``) the layout covers."""
        span = {"full": 2 * math.pi, "half": math.pi, "dct": math.pi / 2}[self.kind]
        start = {"full": -math.pi, "half": -math.pi / 2, "dct": 0.0}[self.kind]
        rows, cols = np.divmod(flat, self.coef_shape[1])
        return np.clip((np.arctan2(self._du[rows], self._dv[cols]) - start) / span, 0.0, 1.0)


@functools.lru_cache(maxsize=8)
def layout(transform: str, storage: str, shape: tuple[int, int], *, legacy: bool = False) -> Layout:
    """The coefficient layout used by a transform/storage pair (cached: treat it as read-only);
    ``legacy``: a 1.0 or 1.1 file's order."""
    if transform == "dct":
        return Layout("dct", shape, legacy=legacy)
    return Layout("full" if storage == "complex64" else "half", shape, legacy=legacy)


def radius_limit(shape: tuple[int, int], cutoff: float) -> float:
    """Radius ``r = (1 - f_c) * r_M`` of the low-pass circle in frequency pixels."""
    n, m = shape
    return (1.0 - cutoff) * math.hypot(n / 2.0, m / 2.0)


#: Coefficient orders and their corners, by layout and cutoff (:func:`_cached`): eight of each.
_ORDER_CACHE: dict[tuple, Any] = {}
_ORDER_CACHE_SIZE = 16
#: The cache is shared by threads (zarr codes chunks in threads).
_ORDER_LOCK = threading.Lock()


#: The circle's relative slack: a coefficient a cutoff's circle runs through (0.8 on a square
#: grid, although 1 - 0.8 rounds below 0.2) is kept.
SLACK = 1 + 1e-12


def key_limit(shape: tuple[int, int], cutoff: float, *, dct: bool) -> int:
    """The largest integer key inside the circle of ``cutoff`` (docs/format.md: ``c q <= A² S² (rows² +
    cols²)``, ``A = 1 - cutoff`` and ``S`` :data:`SLACK` as binary64 numbers, the rest exact).

    Exact rationals, not floats: a last bit of a float radius or limit would decide, on one
    machine or another, whether a coefficient on the circle is in the stream.
    """
    n, m = shape
    bound = Fraction(1.0 - cutoff) ** 2 * Fraction(SLACK) ** 2 * (n * n + m * m)
    return math.floor(bound if dct else bound / 4)


def key_radius(key: int, *, dct: bool) -> float:
    """The radius (frequency pixels) of an integer key: a limit on :attr:`Layout.radius` that keeps
    exactly the keys up to ``key`` (the radii of distinct keys differ below 2^51)."""
    return math.sqrt(float(key)) * (0.5 if dct else 1.0)


def _limit(lay: Layout, cutoff: float) -> float:
    if lay.legacy:
        # A hair of slack so a coefficient exactly on the circle is kept on every platform.
        return radius_limit(lay.shape, cutoff) * SLACK
    n, m = lay.shape
    # Beyond every key the grid has: then its radius stays where distinct keys' radii are distinct.
    return key_radius(min(key_limit(lay.shape, cutoff, dct=lay.kind == "dct"), n * n + m * m),
                      dct=lay.kind == "dct")


def kept_order(lay: Layout, cutoff: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The coefficients inside the circle of ``cutoff``, from low to high radius.

    Returns flat indices, their radii and their angles. The order is
    deterministic (stable sort on radius, ties by index), so the encoder and
    decoder derive it from the shape alone; the stream for a larger cutoff
    is a prefix of this one (progressive decoding). Only the coefficients
    inside the circle are sorted, and results are cached per shape and
    cutoff: sweeps and rate control ask many times.
    """
    def make() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        flat_radius = lay.radius.ravel()
        if lay.legacy:
            inside = np.flatnonzero(flat_radius <= _limit(lay, cutoff)) if cutoff > 0 else np.arange(flat_radius.size)
            order = inside[np.argsort(flat_radius[inside], kind="stable")]
        else:
            flat_key = lay.key.ravel()
            n, m = lay.shape
            limit = min(key_limit(lay.shape, cutoff, dct=lay.kind == "dct"), n * n + m * m)  # an int64
            inside = np.flatnonzero(flat_key <= limit) if cutoff > 0 else np.arange(flat_key.size)
            order = inside[np.argsort(flat_key[inside], kind="stable")]  # ties in row-major order
        return order, flat_radius[order], lay.angle_of(order)

    return _cached(("order", lay.kind, lay.shape, lay.legacy, cutoff), make)


def kept_corner(lay: Layout, cutoff: float) -> tuple[tuple[int, int], np.ndarray]:
    """:func:`corner` of all of :func:`kept_order`'s coefficients, cached as it is: what a
    decoder scatters a whole stream into."""
    return _cached(("corner", lay.kind, lay.shape, lay.legacy, cutoff),
                   lambda: corner(lay, kept_order(lay, cutoff)[0]))


def _cached(key: tuple, make: Callable[[], Any]) -> Any:
    """``make()``, kept for ``key`` among the last few (read-only arrays: callers share them)."""
    with _ORDER_LOCK:
        found = _ORDER_CACHE.get(key)
    if found is not None:
        return found
    found = make()
    with _ORDER_LOCK:
        while len(_ORDER_CACHE) >= _ORDER_CACHE_SIZE:
            _ORDER_CACHE.pop(next(iter(_ORDER_CACHE)))
        _ORDER_CACHE[key] = found
    return found


def kept_count(lay: Layout, cutoff: float, sorted_radii: np.ndarray | None = None) -> int:
    """How many coefficients lie inside the circle of ``cutoff``.

    ``sorted_radii``: the radii of :func:`kept_order` for a smaller cutoff,
    if the caller has them (a binary search instead of a pass over the grid).
    """
    if sorted_radii is not None:
        return int(np.searchsorted(sorted_radii, _limit(lay, cutoff), side="right"))
    return int(np.count_nonzero(lay.radius <= _limit(lay, cutoff)))


def values_per_coefficient(lay: Layout, storage: str) -> int:
    """Reals stored per coefficient: 2 for the quantized half spectrum (real and
    imaginary parts interleaved, each with its coefficient's frequency), else 1."""
    return 2 if lay.kind == "half" and storage == "quantized" else 1


def mse_per_squared_error(lay: Layout) -> float:
    """Parseval: mean squared height error per cell (m^2) per unit of summed squared
    coefficient error, for the stored values of ``lay``.

    ``dct`` and ``half`` are orthonormal (``half`` counts each stored
    coefficient for its conjugate twin too); ``full`` is the paper's
    unnormalised DFT, whose inverse divides by N*M.
    """
    n = lay.shape[0] * lay.shape[1]
    return {"dct": 1.0 / n, "half": 2.0 / n, "full": 1.0 / (n * n)}[lay.kind]


def forward(values: np.ndarray, lay: Layout, *, overwrite: bool = False,
            corner: tuple[int, int] | None = None) -> np.ndarray:
    """Transform a DEM (rows, cols) to coefficients of ``lay.coef_shape``.

    ``overwrite``: ``values`` (float64, C-contiguous) may be overwritten: the DCT's first pass
    then runs in place, the same bits without a second grid.

    ``corner``: for ``dct``, ``(kr, kc)``: only the coefficients ``[:kr, :kc]`` (a file at a fixed
    cutoff keeps a small low-frequency corner). The DCT runs along the longer axis first, then
    along the shorter one on the corner's lines alone (its ``kr`` rows of a tall grid, its ``kc``
    columns of a wide one), so the part of the second pass that makes no coefficient a file keeps
    is skipped. The order depends on the grid's shape only: a coefficient has the same bits
    whatever corner is asked.
    """
    if lay.kind == "full":
        return sfft.fftshift(sfft.fft2(values, workers=_fft_workers()))
    if lay.kind == "half":
        return sfft.rfft2(values, norm="ortho", workers=_fft_workers())
    kr, kc = lay.coef_shape if corner is None else corner
    rows, cols = lay.shape

    def dct(x: np.ndarray, axis: int, **kw) -> np.ndarray:
        return sfft.dct(x, type=2, axis=axis, norm="ortho", workers=_fft_workers(), **kw)

    if rows > cols:
        return dct(dct(values, 0, overwrite_x=overwrite)[:kr], 1)[:, :kc]
    return dct(dct(values, 1, overwrite_x=overwrite)[:, :kc], 0)[:kr]


def inverse(coefs: np.ndarray, lay: Layout, *, first_axis: int | None = None, overwrite: bool = False) -> np.ndarray:
    """Back from coefficients to a real DEM of ``lay.shape`` (float64).

    For ``dct`` the coefficients may be just the low-frequency corner
    ``[:kr, :kc]`` of the layout (the rest zero): the inverse then runs
    first along the axis that has fewer non-zero lines, about 40 % less
    work at f_c = 0.8. ``first_axis`` (0 or 1) imposes the order instead:
    the heights are the same either way up to float round-off, and a fixed
    order gives the same bits as the whole zero-padded array in that order.
    ``overwrite``: ``coefs`` may be destroyed (the caller's own scratch). The second pass
    always works in place in the first's output: pocketfft then allocates no second grid,
    about a quarter of a 1.6 M-cell inverse's time, with the same bits.
    """
    if lay.kind == "full":
        return sfft.ifft2(sfft.ifftshift(coefs), workers=_fft_workers()).real
    if lay.kind == "half":
        return sfft.irfft2(coefs, s=lay.shape, norm="ortho", workers=_fft_workers())
    (n, m), (kr, kc) = lay.shape, coefs.shape

    def idct(x: np.ndarray, size: int, axis: int, mine: bool) -> np.ndarray:  # zero-pads x to size
        return sfft.idct(x, type=2, n=size, axis=axis, norm="ortho", workers=_fft_workers(), overwrite_x=mine)

    if first_axis is None:
        first_axis = 1 if kr * m <= n * kc else 0
    if first_axis == 1:
        return idct(idct(coefs, m, 1, overwrite), n, 0, True)
    return idct(idct(coefs, n, 0, overwrite), m, 1, True)


def corner(lay: Layout, flat: np.ndarray) -> tuple[tuple[int, int], np.ndarray]:
    """The smallest top-left block of the coefficient array holding the
    flat indices ``flat``, and their flat indices within that block."""
    m = lay.coef_shape[1]
    rows, cols = np.divmod(flat, m)
    shape = (int(rows.max(initial=0)) + 1, int(cols.max(initial=0)) + 1)
    return shape, rows * shape[1] + cols
