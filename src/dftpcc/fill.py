"""Conditioning before the transform: remove the trend, fill the empty cells.

Part of the spectrum stage: the transform sees the DEM minus a least-squares
plane (:func:`fit_plane`), with empty cells filled smoothly (:func:`fill_empty`)
so it meets no artificial cliff; :func:`footprint` says which empty cells a
``mask='footprint'`` map rebuilds.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from . import kernels
from .dem import DEM
from .errors import InvalidInputError
from .sums import dot

__all__ = ["fit_plane", "plane_from_moments", "PlaneSums", "plane_values", "add_plane", "fill_empty", "footprint"]


def fit_plane(dem: DEM) -> tuple[float, float, float]:
    """Least-squares plane ``a + b*col + c*row`` (metres) through the occupied cells."""
    mask = dem.mask
    occupied = int(np.count_nonzero(mask))
    if occupied < 3:
        z = dem.heights[mask]
        return (float(z.mean()) if z.size else 0.0, 0.0, 0.0)
    # Normal equations on centred coordinates: 3 x 3, well conditioned, and
    # a few passes over the cells instead of a least-squares solve on them.
    return plane_from_moments(*_plane_sums(dem.heights, mask))


def plane_from_moments(mx: float, my: float, mz: float, xx: float, xy: float, yy: float, xz: float,
                       yz: float) -> tuple[float, float, float]:
    """The plane ``a + b*col + c*row`` of :func:`fit_plane` from the means of the cells' column, row and
    height and the (equally scaled) sums of products of their centred values: the normal equations."""
    normal = np.array([[xx, xy], [xy, yy]])
    rhs = np.array([xz, yz])
    try:
        b, c = np.linalg.solve(normal, rhs)
    except np.linalg.LinAlgError:  # all cells on one line: fit along it only
        b, c = np.linalg.lstsq(normal, rhs, rcond=None)[0]
    return float(mz - b * mx - c * my), float(b), float(c)


class PlaneSums:
    """:func:`fit_plane` for a map read in pieces: the sums of one pass over its occupied cells.

    Heights are summed about ``ref`` (metres; the first piece's mean is a good choice), so that the
    raw second moments keep their precision over a map too large to centre in memory first.
    """

    def __init__(self, ref: float):
        self.ref = ref
        self.moments = np.zeros(9)  # n, z, x, y, xx, xy, yy, xz, yz

    def add(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> None:
        """Occupied cells at columns ``x`` and rows ``y`` (float, of the whole map) with heights ``z`` (metres)."""
        z = z - self.ref
        self.moments += [z.size, z.sum(), x.sum(), y.sum(), dot(x, x), dot(x, y), dot(y, y), dot(x, z), dot(y, z)]

    @property
    def count(self) -> int:
        return int(self.moments[0])

    def mean(self) -> float:
        """The cells' mean height, metres."""
        return self.ref + self.moments[1] / self.moments[0]

    def plane(self, z0: float) -> tuple[float, float, float]:
        """The least-squares plane through the cells' heights about ``z0`` (metres)."""
        n, sz, sx, sy, sxx, sxy, syy, sxz, syz = self.moments
        mx, my, mz = sx / n, sy / n, sz / n
        a, b, c = plane_from_moments(mx, my, mz, sxx / n - mx * mx, sxy / n - mx * my, syy / n - my * my,
                                     sxz / n - mx * mz, syz / n - my * mz)
        return a - (z0 - self.ref), b, c


@kernels.kernel("plane_sums")
def _plane_sums(heights: np.ndarray, mask: np.ndarray) -> tuple[float, float, float, float, float, float, float, float]:
    """The means of the column, row and height (metres) of the cells set in ``mask`` (at least one),
    and the sums of products xx, xy, yy, xz, yz of the centred values."""
    # Column and row of each occupied cell, row-major (np.nonzero's order),
    # made as floats directly: cheaper than two index arrays and a 2-D gather.
    z = heights[mask]
    n_rows, n_cols = mask.shape
    x = np.broadcast_to(np.arange(n_cols, dtype=float), mask.shape)[mask]
    y = np.repeat(np.arange(n_rows, dtype=float), np.count_nonzero(mask, axis=1))
    mx, my, mz = x.mean(), y.mean(), z.mean()
    x -= mx
    y -= my
    z -= mz
    # The five sums of products (dftpcc.sums.dot's arithmetic), written into one
    # scratch array: fresh products for each would cost more than the sums.
    scratch = np.empty_like(z)

    def dot_(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.sum(np.multiply(a, b, out=scratch)))

    return mx, my, mz, dot_(x, x), dot_(x, y), dot_(y, y), dot_(x, z), dot_(y, z)


def plane_values(plane: tuple[float, float, float], shape: tuple[int, int]) -> np.ndarray:
    """The plane of :func:`fit_plane` evaluated on a grid of ``shape``."""
    a, b, c = plane
    rows = np.arange(shape[0], dtype=float)[:, None]
    cols = np.arange(shape[1], dtype=float)[None, :]
    return a + b * cols + c * rows


@kernels.kernel("add_plane")
def add_plane(heights: np.ndarray, plane: tuple[float, float, float]) -> None:
    """``heights += plane_values(plane, heights.shape)``, in place (float64 heights; compiled: without
    the plane's grid)."""
    heights += plane_values(plane, heights.shape)


def fill_empty(heights: np.ndarray, mask: np.ndarray, *, method: str = "smooth") -> np.ndarray:
    """Heights with empty cells filled, occupied cells untouched.

    ``zero`` leaves 0 (the projection plane). ``smooth`` is push-pull
    interpolation: occupied cells are averaged down a pyramid, and each
    level's empty cells take the bilinearly upsampled coarser level, so a
    hole is bridged by a smooth surface and adds little high-frequency
    energy to the spectrum.

    Parameters
    ----------
    heights : ndarray, shape (rows, cols)
    mask : ndarray of bool, same shape
    method : {'smooth', 'zero'}
    """
    out = np.where(mask, heights, 0.0)
    if method == "zero" or mask.all() or not mask.any():
        return out
    if method != "smooth":
        raise InvalidInputError(f"fill must be 'smooth' or 'zero', got {method!r}")
    return _push_pull(out, np.ascontiguousarray(mask, dtype=bool))


#: Levels of fewer cells take numpy's own 2x2 block sums (see :func:`_pairs`).
SMALL_LEVEL_CELLS = 4096


def _pairs(a: np.ndarray) -> np.ndarray:
    """Sums of the 2x2 blocks of ``a``, zero-padded to even sizes, added as
    ``reshape(...).sum(axis=(1, 3))`` adds them: each row's pair, then the two rows;
    in ``a``'s dtype (uint8 counts of known cells, or float64 values).

    Only the odd last row or column is padded, not a copy of the whole level.
    """
    def blocks(x: np.ndarray) -> np.ndarray:
        return (x[0::2, 0::2] + x[0::2, 1::2]) + (x[1::2, 0::2] + x[1::2, 1::2])

    r, c = a.shape
    if c <= 2 or a.size < SMALL_LEVEL_CELLS:
        # numpy's reduction adds the four in another order when the coarse level is
        # one cell wide; small levels cost nothing either way.
        if r % 2 or c % 2:  # zero-padded by hand: np.pad costs more than the sums on a small level
            p = np.zeros((r + r % 2, c + c % 2), dtype=a.dtype)
            p[:r, :c] = a
        else:
            p = a
        return p.reshape(p.shape[0] // 2, 2, p.shape[1] // 2, 2).sum(axis=(1, 3), dtype=a.dtype)
    if r % 2 == 0 and c % 2 == 0:
        return blocks(a)
    re, ce = r - r % 2, c - c % 2
    out = np.empty(((r + 1) // 2, (c + 1) // 2), dtype=a.dtype)
    out[:re // 2, :ce // 2] = blocks(a[:re, :ce])
    if r % 2:
        out[-1:, :] = blocks(np.pad(a[re:], ((0, 1), (0, c % 2))))
    if c % 2:
        out[:re // 2, -1:] = blocks(np.pad(a[:re, ce:], ((0, 0), (0, 1))))
    return out


#: Bilinear 2x upsampling with cell-centred samples: an output takes this much of
#: the coarse sample it lies in and the rest of the neighbour on its side.
NEAR_WEIGHT, FAR_WEIGHT = 0.75, 0.25


def _sides(index: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """The coarse sample each output ``index`` lies in, and the neighbour it leans on (edges clamped)."""
    own = index >> 1
    # Even outputs lean on the coarse sample before theirs, odd ones on the one after.
    return own, np.clip(np.where(index & 1, own + 1, own - 1), 0, size - 1)


def _upsampled_at(coarse: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Cells (rows, cols) of the 2x bilinear upsampling of ``coarse``, edges clamped: along
    the rows first, then along the columns, each as ``0.75 * own + 0.25 * neighbour``."""
    k, kn = _sides(rows, coarse.shape[0])
    p, pn = _sides(cols, coarse.shape[1])
    width = coarse.shape[1]
    flat = coarse.ravel()

    def along_rows(col: np.ndarray) -> np.ndarray:
        return NEAR_WEIGHT * flat[k * width + col] + FAR_WEIGHT * flat[kn * width + col]

    return NEAR_WEIGHT * along_rows(p) + FAR_WEIGHT * along_rows(pn)


def _upsampled(coarse: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """:func:`_upsampled_at` of every cell of a ``shape`` level, the same arithmetic in the same
    order (so the same bits), by whole rows and columns instead of one gather per cell."""
    return _doubled(_doubled(coarse, shape[0], 0), shape[1], 1)


def _doubled(coarse: np.ndarray, n: int, axis: int) -> np.ndarray:
    """``coarse`` upsampled 2x along ``axis`` (0 or 1) to ``n`` samples as :func:`_sides` pairs them:
    output 2i is ``0.75 * c[i] + 0.25 * c[i - 1]``, output 2i + 1 ``0.75 * c[i] + 0.25 * c[i + 1]``,
    edges clamped; by strided slices rather than gathers (the same products and sums)."""
    m = coarse.shape[axis]
    half = (n + 1) // 2  # coarse samples the outputs lie in: n <= 2 m

    def at(a: int, b: int) -> tuple[slice, ...]:
        return (slice(a, b),) if axis == 0 else (slice(None), slice(a, b))

    def every(start: int, stop: int | None) -> tuple[slice, ...]:
        return (slice(start, stop, 2),) if axis == 0 else (slice(None), slice(start, stop, 2))

    shape = (2 * half, coarse.shape[1]) if axis == 0 else (coarse.shape[0], 2 * half)
    out = np.empty(shape)
    own = NEAR_WEIGHT * coarse[at(0, half)]
    far = FAR_WEIGHT * coarse[at(0, min(half + 1, m))]  # 0.25 c[j] for every j a neighbour may be
    out[every(0, 1)] = own[at(0, 1)] + far[at(0, 1)]  # output 0 leans on c[0] itself
    out[every(2, None)] = own[at(1, half)] + far[at(0, half - 1)]
    if half < m:
        out[every(1, None)] = own + far[at(1, half + 1)]
    else:  # the last odd output leans on the last sample itself
        out[every(1, 2 * half - 2)] = own[at(0, half - 1)] + far[at(1, half)]
        out[every(2 * half - 1, None)] = own[at(half - 1, half)] + far[at(m - 1, m)]
    return out[at(0, n)]


#: A level whose cells to fill are more than this share of it is upsampled and blended whole
#: (sparse scans leave most cells of a fine grid empty); fewer are upsampled one by one.
DENSE_UPSAMPLING_SHARE = 0.25


def _push_pull(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """``known``: True where ``values`` is known, False elsewhere (where ``values`` is 0).

    The weights of push-pull are 1 at known cells and 0 elsewhere at every level (a
    coarse cell is known when any of its four is), so they are kept as booleans and
    counted in bytes; where the arithmetic needs them they are the floats 0 and 1.
    """
    if known.all():
        return values  # nothing to fill at this level (coarse levels of a dense map)
    if min(values.shape) <= 1 and values.size <= 2:
        weights = known.astype(np.float64)
        total = weights.sum()
        mean = (values * weights).sum() / total if total else 0.0
        return np.where(known, values, mean)
    return _push(values, known, _push_pull(*_pull(values, known)))


def _pull_compiled(values: np.ndarray, known: np.ndarray) -> tuple[np.ndarray, np.ndarray] | Any:
    # The compiled pull adds each block as _pairs adds a large level's; a small one's sums are numpy's.
    if values.shape[1] <= 2 or values.size < SMALL_LEVEL_CELLS:
        return NotImplemented
    return kernels.compiled_module().pull(values, known)


@kernels.kernel(_pull_compiled)
def _pull(values: np.ndarray, known: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Push-pull's coarser level: the mean of the known values of each 2x2 block (zeros past odd
    edges), and whether any of the four is known."""
    # The weights are 0 or 1 and the unknown values 0, so values * weights is values itself; the
    # counts are whole, the same in any dtype.
    counts, vsum = _pairs(known.view(np.uint8)), _pairs(values)
    coarse_known = counts > 0
    return np.divide(vsum, counts, out=np.zeros_like(vsum), where=coarse_known), coarse_known


@kernels.kernel("push")
def _push(values: np.ndarray, known: np.ndarray, coarse: np.ndarray) -> np.ndarray:
    """Push-pull's blend of a level with the 2x bilinear upsampling of the filled ``coarse`` level:
    the known cells keep their values, the others take the upsampling."""
    # Push: the blend w * values + (1 - w) * up with the bilinear upsampling
    # ``up`` of the filled coarse level. With 0/1 weights it is ``values`` at
    # known cells; ``up`` is needed only at the unknown ones, and at known
    # zeros, whose sign the blend decides.
    # The unknown cells alone often decide that a level is blended whole (a sparse scan's).
    unknown = ~known
    needed = None
    if values.size - np.count_nonzero(known) <= DENSE_UPSAMPLING_SHARE * values.size:
        needed = unknown | (values == 0.0)
        count = np.count_nonzero(needed)
    if needed is None or count > DENSE_UPSAMPLING_SHARE * values.size:  # the same blend, on whole rows
        # w * values + (1 - w) * up with w 1 or 0 is values + 0 * up (known) or 0 + up (unknown,
        # where values is +0): values + (1 - w) * up, the same bits, and at the cells not needed
        # (known, nonzero) values itself.
        up = _upsampled(coarse, values.shape)
        np.multiply(up, unknown, out=up)
        up += values
        return up
    out = values.copy()
    if count:
        need = np.flatnonzero(needed)
        w = known.ravel()[need].astype(np.float64)
        out.ravel()[need] = w * values.ravel()[need] + (1.0 - w) * _upsampled_at(
            coarse, *np.divmod(need, values.shape[1]))
    return out


def footprint(mask: np.ndarray) -> np.ndarray:
    """Occupied cells plus the empty ones the map encloses (one-cell gaps closed, holes filled)."""
    from scipy import ndimage  # here, not at import: only a footprint mask needs it (30-60 ms to load)

    closed = ndimage.binary_closing(mask, structure=np.ones((3, 3), bool), border_value=0) | mask
    return ndimage.binary_fill_holes(closed)
