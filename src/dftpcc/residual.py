"""The residual layer: what brings every occupied cell within a promised maximum error.

After the low-passed, quantized spectrum, each rebuilt cell's remaining error
is quantized with a step of twice the bound (so rounding leaves at most the
bound) and coded as one integer per rebuilt cell, row-major, in the RESD
section. Interpolated (footprint) cells have no measured height and get 0.

Three layouts (docs/format.md, ``RESD``): the values in chunks, as coefficients
are; where most are 0, one *sparse* chunk: which cells are not 0, as a
picture coded with the occupancy mask's context model (the corrections cluster
where the terrain is rough), then their magnitudes and signs; or one
*predicted* chunk, where the residual is the map itself (rough terrain): each
value predicted from seven decoded neighbours with least-squares weights, and
the prediction's error coded given the neighbours' errors, as lossless image
coders do. The smallest wins.
"""

from __future__ import annotations

import math
import struct
import threading
import weakref
from fractions import Fraction
from typing import Any

import constriction
import numpy as np

from . import coding, geometric, kernels, occupancy, quantizer
from .errors import CorruptFileError, InvalidInputError

__all__ = ["GUARANTEE_MARGIN", "residual_step", "residual", "residual_integers", "encode_residual", "decode_residual", "layout_of",
           "predicted_residual", "estimated_size", "sampled_predicted_size", "sampled_rows"]

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
    q = residual_integers(target, rebuilt, measured, kept, bound)
    heights = rebuilt.copy()
    heights[kept] += q * residual_step(bound)
    return q, heights


def residual_integers(target: np.ndarray, rebuilt: np.ndarray, measured: np.ndarray, kept: np.ndarray,
                      bound: float) -> np.ndarray:
    """The integers of :func:`residual` without the corrected map: rate control sizes many
    layers and rebuilds none of them."""
    step = residual_step(bound)
    err = np.where(measured, target - rebuilt, 0.0)[kept]
    with np.errstate(over="ignore", invalid="ignore"):
        r = np.round(err / step)
    # As quantizer.quantize: refuse rather than let the cast wrap (the encoder's checks make this a last guard).
    if r.size and not np.abs(r).max() < quantizer.QUANT_LIMIT:  # also inf and NaN
        worst = float(np.abs(err).max())
        raise InvalidInputError(
            f"target maximum error {bound:g} m is too fine for residuals up to {worst:g} m: their integers would "
            f"pass 2**63 and wrap; the smallest workable target is "
            f"{quantizer.round_up(quantizer.finest_step(err) / (2.0 * (1.0 - GUARANTEE_MARGIN))):g} m")
    return r.astype(np.int64)


#: :func:`encode_residual` codes only the layouts whose estimated bytes are within this fraction
#: of the smallest (estimates are within 0.2 % of the coded chunked and predicted layouts and 2 %
#: of the sparse one on ../shared/data): the layout it keeps is the one coding every layout would.
LAYOUT_SLACK = 0.05
#: The predicted layout codes real maps in at least about this share of the median predictor's
#: bytes (:func:`median_predicted_size`; 0.56 the least measured): where that share of them cannot
#: come within :data:`LAYOUT_SLACK` of another layout, its fit and contexts are not worth their time.
PREDICTED_SHARE = 0.45


def encode_residual(q: np.ndarray, coder: str, kept: np.ndarray, *, predicted: bool = True) -> bytes:
    """The RESD section of ``q``, one integer per ``True`` cell of ``kept`` (row-major): the
    chunked layout; the sparse one where at least half the values are 0 and it is shorter; the
    predicted one (``predicted``, ANS files) where it is shorter than both. Rate control sizes
    its many candidates without the predicted layout, the slowest to code, and tries it on the
    few that may win (:func:`dftpcc.ratecontrol.for_max_error`). A layout whose estimate
    (:func:`estimated_size`'s) passes another's by more than :data:`LAYOUT_SLACK` is not coded."""
    flat = np.zeros(q.size)  # one band per chunk: the residual has no frequency
    chunked = coding.estimated_size(q, radius=flat, angle=flat, coder=coder, exhaustive=False)
    # At a coarse bound most values are 0, which kind 3 codes at 0.07 bits or more each (its scale
    # floor, MIN_SCALE), however they cluster: the sparse layout codes where they are not.
    sparse = _estimated_sparse(q, coder, kept) if 2 * np.count_nonzero(q) <= q.size else math.inf
    smallest = min(chunked, sparse)
    layer = None
    # The layout is coded where its estimate comes within the slack. Its model (fit, errors,
    # contexts) is about two thirds of coding it and is kept for the coding, so where rate control
    # has not made it, the median predictor's floor of the layout's bytes is looked at first: where
    # even that cannot come within the slack, the model is not made at all.
    if predicted and coder == "ans" and q.size and (
            _known_model(q, kept) is not None
            or PREDICTED_SHARE * median_predicted_size(q, kept) < (1.0 + LAYOUT_SLACK) * smallest) \
            and _estimated_predicted(q, kept) < (1.0 + LAYOUT_SLACK) * smallest:
        layer = predicted_residual(q, coder, kept)
        smallest = min(smallest, math.inf if layer is None else len(layer))
    reach = (1.0 + LAYOUT_SLACK) * smallest
    # In the order the layouts are preferred on a tie: chunked, sparse, predicted.
    best = None
    if chunked <= reach:
        # Every band layout puts all values in band 0, so there is no layout to choose.
        best = coding.encode_coefficients(q, radius=flat, angle=flat, coder=coder, exhaustive=False)
    if sparse <= reach:
        other = _encode_sparse(q, coder, kept)
        best = other if best is None or len(other) < len(best) else best
    if layer is not None and (best is None or len(layer) < len(best)):
        best = layer
    if best is None:  # every estimate missed its layout by more than the slack: code the chunked one
        best = coding.encode_coefficients(q, radius=flat, angle=flat, coder=coder, exhaustive=False)
    return best


def predicted_residual(q: np.ndarray, coder: str, kept: np.ndarray) -> bytes | None:
    """The RESD section of ``q`` in the predicted layout (one kind-5 chunk), or None where it does
    not apply: a zstd file, no values, or values and errors past the layout's limits."""
    if coder != "ans" or not q.size:
        return None
    payload = _encode_predicted(q, kept)
    return None if payload is None else coding.one_chunk(q.size, payload, coding.KIND_PREDICTED_RESIDUAL)


def estimated_size(q: np.ndarray, coder: str, kept: np.ndarray, *, predicted: bool = True) -> float:
    """Bytes :func:`encode_residual` would code ``q`` in, without coding it: each layout's size
    from its model's probabilities (:func:`dftpcc.coding.estimated_size`,
    :func:`dftpcc.occupancy.estimated_size`), the smallest; within a few % of the coded layer,
    for rate control to rank its candidates (:mod:`dftpcc.ratemodel`)."""
    flat = np.zeros(q.size)
    best = coding.estimated_size(q, radius=flat, angle=flat, coder=coder, exhaustive=False)
    if 2 * np.count_nonzero(q) <= q.size:
        best = min(best, _estimated_sparse(q, coder, kept))
    if predicted and coder == "ans" and q.size:
        best = min(best, _estimated_predicted(q, kept))
    return best


def _estimated_sparse(q: np.ndarray, coder: str, kept: np.ndarray) -> float:
    """Bytes of :func:`_encode_sparse` of ``q``, from its models' probabilities."""
    nonzero = q != 0
    picture = np.zeros(kept.shape, dtype=bool)
    picture[kept] = nonzero
    values = q[nonzero]
    zero = np.zeros(values.size)
    return (4.0 + coding.CHUNK_HEAD.size + _LENGTH.size + occupancy.estimated_size(picture)
            + coding.estimated_size(np.abs(values) - 1, radius=zero, angle=zero, coder=coder,
                                    exhaustive=False, progressive=False) + (values.size + 7) // 8)


def median_predicted_size(q: np.ndarray, kept: np.ndarray) -> float:
    """Bytes of ``q``'s errors from the median predictor of its W, N and NW neighbours (LOCO-I's),
    one scale for all: a few array passes against the predicted layout's fit and contexts, which
    code real maps in 0.56-1.1 times this (measured on ../shared/data at 1.3 and 4 times the
    gridding floor). Rate control's cheap look at whether that layout can win at all."""
    e = _median_errors(_filled(q, kept), kept)
    flat = np.zeros(e.size)
    return coding.estimated_size(e, radius=flat, angle=flat, exhaustive=False)


@kernels.kernel("median_errors")
def _median_errors(grid: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """Each kept cell's value in the filled ``grid`` less the median of its W, N and NW (row-major)."""
    w, n, nw = _kept_neighbours(grid, kept, ((0, 1), (1, 0), (1, 1)))
    return grid[kept] - np.clip(w + n - nw, np.minimum(w, n), np.maximum(w, n))


def _estimated_predicted(q: np.ndarray, kept: np.ndarray) -> float:
    """Bytes of :func:`predicted_residual` of ``q``, from its model's probabilities (inf where the
    layout does not apply)."""
    return _model_bytes(_shared_model(q, kept))


#: :func:`sampled_predicted_size` models bands of this many rows, one in every :data:`SAMPLE_EVERY`,
#: and counts the bits of their rows after the first :data:`SAMPLE_SKIP` (which the band before
#: predicts and classifies) ...
SAMPLE_ROWS = 16
SAMPLE_EVERY = 4
SAMPLE_SKIP = 2
#: ... on a grid of at least this many bands.
SAMPLE_BANDS = 4


def sampled_predicted_size(q: np.ndarray, kept: np.ndarray) -> float | None:
    """:func:`_estimated_predicted` of ``q`` from a quarter of its rows, scaled to all of them:
    bands of :data:`SAMPLE_ROWS` rows, one in every :data:`SAMPLE_EVERY`, modelled as one grid.
    For rate control to pass over the layout where even that comes nowhere near another file, in
    a quarter of the time (0.43-1.15 times the whole grid's estimate on ../shared/data); None on a
    grid of too few bands to sample (its model is cheap anyway), or where a band has no model."""
    rows = kept.shape[0]
    starts = _sample_starts(rows)
    if starts is None or not q.size:
        return None
    offsets = np.concatenate(([0], np.cumsum(np.count_nonzero(kept, axis=1))))
    bits = cells = 0.0
    for start in starts:
        stop = min(start + SAMPLE_ROWS, rows)
        part = kept[start:stop]
        counted = np.repeat(np.arange(stop - start) >= SAMPLE_SKIP, np.count_nonzero(part, axis=1))
        if not counted.any():
            continue
        size = _model_bytes(_predicted_model(q[offsets[start]:offsets[stop]], part), counted)
        if not math.isfinite(size):
            return None  # a band's alphabet passes a small chunk's table budget: it says nothing of the whole
        bits, cells = bits + size, cells + np.count_nonzero(counted)
    return bits * q.size / cells if cells else None


def _sample_starts(rows: int) -> np.ndarray | None:
    """The first rows of the bands a layer is estimated from (:func:`sampled_rows`)."""
    starts = np.arange(0, rows, SAMPLE_ROWS * SAMPLE_EVERY)
    return starts if starts.size >= SAMPLE_BANDS else None


def sampled_rows(rows: int) -> np.ndarray | None:
    """The rows (a mask) a layer's bytes are estimated from where estimating every row would
    cost too much: bands of :data:`SAMPLE_ROWS`, one in every :data:`SAMPLE_EVERY`; None on a
    grid of fewer than :data:`SAMPLE_BANDS` bands."""
    starts = _sample_starts(rows)
    if starts is None:
        return None
    within = np.arange(rows)[:, None] - starts
    return ((within >= 0) & (within < SAMPLE_ROWS)).any(axis=1)


def _model_bytes(model: tuple | None, counted: np.ndarray | None = None) -> float:
    """Bytes of a kind-5 chunk coded with ``model`` (:func:`_predicted_model`), from its
    probabilities (``counted``: of those cells' values alone, and no chunk overhead); inf where
    there is no model (the layout does not apply)."""
    if model is None:
        return math.inf
    _, e, classes, codes, _ = model
    per_cell = codes[classes]
    coded = per_cell > 0
    if counted is not None:
        coded &= counted
    at_zero, per_step = geometric.log_geometric()
    log_p = at_zero[per_cell[coded]] + np.abs(e[coded]) * per_step[per_cell[coded]]
    bits = -float(np.maximum(log_p, -geometric.TABLE_BITS).sum())
    if counted is not None:
        return bits / 8.0
    present = int(np.count_nonzero(codes))
    listed = int(np.flatnonzero(codes)[-1]) + 1 if present else 1
    return 4.0 + coding.CHUNK_HEAD.size + _WEIGHTS.size + listed + 2 * present + coding.ANS_FLUSH_BYTES + bits / 8.0


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
    n = int(np.count_nonzero(picture))  # all of them kept cells
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
    return _signed_at(picture, kept, sizes, negative)


@kernels.kernel("signed_at")
def _signed_at(picture: np.ndarray, kept: np.ndarray, sizes: np.ndarray, negative: np.ndarray) -> np.ndarray:
    """A sparse layer's integers, one per ``kept`` cell (row-major): ``sizes + 1``, negative where
    the bit of ``negative`` (0/1 bytes) says so, at the cells ``picture`` sets (a subset of
    ``kept``, in order), 0 at the others."""
    nonzero = picture[kept]
    magnitude = sizes + 1
    q = np.zeros(nonzero.size, dtype=np.int64)
    q[nonzero] = np.where(negative[:sizes.size].astype(bool), -magnitude, magnitude)
    return q


# The predicted layout (RESD kind 5, docs/format.md). Its values V fill the residual's whole grid
# in wavefronts of equal 2r + c, so that every neighbour a cell needs is in an earlier one: a
# decoder does a wavefront at a time, with numpy, though each value depends on its west neighbour.

#: The seven neighbours of a cell, as (rows up, columns left), in the order of the weights.
NEIGHBOURS = ((0, 1), (1, 0), (1, 1), (1, -1), (0, 2), (2, 0), (2, -1))  # W N NW NE WW NN NNE
#: Multiplier of each neighbour's |error| in a cell's activity (NNE's error does not count).
ACTIVITY_WEIGHTS = (2, 2, 1, 1, 1, 1, 0)
CLASSES = 64
WEIGHT_BITS = 16
#: Weights are below this in magnitude, values below VALUE_LIMIT: no sum leaves 64 bits.
WEIGHT_LIMIT = 1 << 24
VALUE_LIMIT = 1 << 31
#: Cells whose differences from their west neighbour exceed this are left out of the fit
#: (they would dominate it, and exact integer sums of their products could pass 64 bits).
FIT_LIMIT = 1 << 15
_WEIGHTS = struct.Struct("<7iB")  # the weights, then how many classes the header lists


def _neighbour(up: int, left: int, r: np.ndarray, c: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Flat index of one neighbour of the cells (r, c) under format.md's edge rules: rows × cols
    is the cell (0, 0)'s "neighbour", a zero."""
    rows, cols = shape
    idx = np.maximum(r - up, 0) * cols + np.clip(c - left, 0, cols - 1)
    if up:
        idx = np.where(r == 0, c - 1, idx)  # row 0: the rows above are W
    else:
        idx = np.where(c == 0, (r - 1) * cols, idx)  # column 0: W and WW are N
    return np.where((r == 0) & (c == 0), rows * cols, idx)


def _shifted(grid: np.ndarray, up: int, left: int) -> np.ndarray:
    """Each cell's neighbour (``up`` rows up, ``left`` columns left) in ``grid``, under the edge
    rules of :func:`_neighbour`: ``grid.ravel()[_neighbour(up, left, r, c)]`` at every cell at
    once, by whole rows and columns instead of a gather of flat indices."""
    rows, cols = grid.shape
    out = grid[np.maximum(np.arange(rows) - up, 0)][:, np.clip(np.arange(cols) - left, 0, cols - 1)]
    if up:
        out[0, 1:] = grid[0, :-1]  # row 0: the rows above are W
    else:
        out[1:, 0] = grid[:-1, 0]  # column 0: W and WW are N
    out[0, 0] = 0
    return out


@kernels.kernel("kept_neighbours")
def _kept_neighbours(grid: np.ndarray, kept: np.ndarray, offsets: tuple[tuple[int, int], ...],
                     stride: int = 1) -> np.ndarray:
    """Each kept cell's neighbours (row-major, as ``grid[kept]``; every ``stride``-th kept cell) at
    ``offsets`` (rows up, columns left) under :func:`_shifted`'s edge rules: one row per offset (int64)."""
    cells = np.flatnonzero(kept)[::stride]
    out = np.empty((len(offsets), cells.size), dtype=grid.dtype)
    for row, (up, left) in enumerate(offsets):
        out[row] = _shifted(grid, up, left).ravel()[cells]
    return out


#: Cells a decoder gathers the neighbours of at once (a few MB of indices).
WAVEFRONT_BLOCK_CELLS = 1 << 16


def _wavefront_blocks(shape: tuple[int, int]):
    """The grid's cells in wavefront order (format.md), in blocks of whole wavefronts of about
    :data:`WAVEFRONT_BLOCK_CELLS` cells: yields each block's flat cell indices, their seven
    neighbours' (7 x cells) and where each wavefront starts in the block (and the end)."""
    rows, cols = shape
    waves = np.arange(2 * (rows - 1) + cols)
    r_lo = np.maximum(0, (waves - cols + 2) // 2)
    sizes = np.minimum(rows - 1, waves // 2) - r_lo + 1
    ends = np.cumsum(sizes)
    k0 = 0
    while k0 < waves.size:
        k1 = max(k0 + 1, int(np.searchsorted(ends, ends[k0] - sizes[k0] + WAVEFRONT_BLOCK_CELLS, side="right")))
        n = sizes[k0:k1]
        starts = np.cumsum(n) - n  # of each wavefront in the block
        r = np.repeat(r_lo[k0:k1] - starts, n) + np.arange(int(n.sum()))
        c = np.repeat(waves[k0:k1], n) - 2 * r
        nbs = np.stack([_neighbour(up, left, r, c, shape) for up, left in NEIGHBOURS])
        yield r * cols + c, nbs, np.append(0, np.cumsum(n))
        k0 = k1


def _classes(activity: np.ndarray) -> np.ndarray:
    """Context class of each activity: two per octave (format.md), 0 for no activity."""
    _, b = np.frexp(activity.astype(np.float64))  # the bit length: exact, activities are below 2**53
    b = b.astype(np.int64)
    second = np.where(b >= 2, (activity >> np.maximum(b - 2, 0)) & 1, 0)
    return np.where(activity > 0, np.minimum(CLASSES - 1, 2 * b - 1 + second), 0)


def _prediction(weights: np.ndarray, values: list[np.ndarray]) -> np.ndarray:
    total = np.zeros(values[0].shape, dtype=np.int64)
    for a, v in zip(weights.tolist(), values):
        if a:
            total += a * v
    return (total + (1 << (WEIGHT_BITS - 1))) >> WEIGHT_BITS


@kernels.kernel("filled")
def _filled(q: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """The grid of values V: ``q`` at the kept cells, and at the others their W (format.md)."""
    rows, cols = kept.shape
    grid = np.zeros(kept.shape, dtype=np.int64)
    grid[kept] = q
    # Column 0 takes the value above, back to the last kept cell (0 above the first).
    first = np.where(kept[:, 0], np.arange(rows), -1)
    np.maximum.accumulate(first, out=first)
    grid[:, 0] = np.where(first >= 0, grid[np.maximum(first, 0), 0], 0)
    # Every row then carries its last kept cell (or its column 0) to the right.
    known = np.where(kept | (np.arange(cols) == 0), np.arange(cols), 0)
    np.maximum.accumulate(known, axis=1, out=known)
    return np.take_along_axis(grid, known, axis=1)


#: Rows of :func:`_exact_products`'s blocks: with every value within FIT_LIMIT, each product is
#: below 2**30 and a block's sums below 2**52, so float64 adds them exactly, in any order.
PRODUCT_BLOCK = 1 << 22


def _exact_products(x: np.ndarray) -> np.ndarray:
    """``x @ x.T`` of an integer (k, n) array whose values are within FIT_LIMIT, exactly (int64):
    summed in float64 by blocks, which is exact below 2**53 and a matrix product's speed."""
    total = np.zeros((x.shape[0], x.shape[0]), dtype=np.int64)
    for at in range(0, x.shape[1], PRODUCT_BLOCK):
        block = x[:, at:at + PRODUCT_BLOCK].astype(np.float64, copy=False)
        total += (block @ block.T).astype(np.int64)
    return total


def _exact_solution(rows: list[list[int]]) -> list[Fraction]:
    """The solution of the integer system ``rows`` (m rows of A | b, A positive definite), exactly:
    fraction-free Gauss-Jordan elimination (Bareiss), whose every division is exact, so integers
    carry it and only the m answers are fractions (a tenth of the time of elimination in fractions)."""
    a = [list(row) for row in rows]
    m = len(a)
    previous = 1
    for k in range(m):
        pivot = a[k][k]  # a leading minor of a positive definite matrix: never 0
        for i in range(m):
            if i != k:
                factor = a[i][k]
                a[i] = [(pivot * v - factor * p) // previous for v, p in zip(a[i], a[k])]
        previous = pivot
    return [Fraction(a[i][m], a[i][i]) for i in range(m)]


@kernels.kernel("fit_sums", offsets=NEIGHBOURS, fit_limit=FIT_LIMIT)
def _fit_sums(grid: np.ndarray, kept: np.ndarray, stride: int) -> np.ndarray:
    """The fit's exact sums (7 x 7, int64) over every ``stride``-th kept cell of the filled ``grid``:
    the products of the six other neighbours' and the cell's own value less W, of the cells where
    none of those differences passes :data:`FIT_LIMIT`."""
    w, *others = _kept_neighbours(grid, kept, NEIGHBOURS, stride)
    target = grid[kept][::stride]
    # Integers below VALUE_LIMIT, so their differences are exact in float64, which the products
    # take anyway (no int64 copy first).
    d = np.empty((len(others) + 1, target.size))
    for row, v in enumerate([*others, target]):
        np.subtract(v, w, out=d[row])
    usable = np.abs(d).max(axis=0) <= FIT_LIMIT
    return _exact_products(d if usable.all() else d[:, usable])


def _fit_weights(sums: np.ndarray) -> np.ndarray:
    """Least-squares weights (sum 2**16) of the neighbours from the fit's exact integer sums
    (:func:`_fit_sums`) and an exact solve, so the file is the same on every machine."""
    m = sums.shape[0] - 1
    # The normal equations, plus 1 on the diagonal so they always have a solution.
    a = sums.tolist()
    for i in range(m):
        a[i][i] += 1
    solution = _exact_solution(a[:m])  # m rows of the six weights and the target: A | b
    limit = WEIGHT_LIMIT - 1
    others = [max(-limit, min(limit, round(x * (1 << WEIGHT_BITS)))) for x in solution]
    west = max(-limit, min(limit, (1 << WEIGHT_BITS) - sum(others)))
    return np.array([west] + others, dtype=np.int64)


#: The predicted layout fits its weights on about this many cells, evenly strided: the weights of
#: a smooth least-squares fit move little (the files' bytes by 0.01 % against a fit on every cell
#: on ../shared/data), and a fit on every cell is a third of the model's time on a large map.
FIT_CELLS = 1 << 16


@kernels.kernel("errors_and_classes", offsets=NEIGHBOURS, activity=ACTIVITY_WEIGHTS, classes=CLASSES,
                weight_bits=WEIGHT_BITS)
def _errors_and_classes(grid: np.ndarray, kept: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kind 5's prediction errors of the kept cells (row-major) from the filled ``grid`` (values V)
    and ``weights``, and each kept cell's class from its neighbours' |errors| (format.md)."""
    q = grid[kept]
    e = q - _prediction(weights, list(_kept_neighbours(grid, kept, NEIGHBOURS)))
    errors = np.zeros(kept.shape, dtype=np.int64)
    errors[kept] = np.abs(e)
    counted = [(offset, k) for offset, k in zip(NEIGHBOURS, ACTIVITY_WEIGHTS) if k]
    activity = np.zeros(q.size, dtype=np.int64)
    for row, (_, k) in zip(_kept_neighbours(errors, kept, tuple(o for o, _ in counted)), counted):
        activity += k * row
    return e, _classes(activity)


def _predicted_model(q: np.ndarray, kept: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Kind 5's model of ``q``: the weights (fitted on about :data:`FIT_CELLS` cells), the
    prediction errors, each cell's class, each class's scale code and largest |error|; None when
    its values or errors pass the layout's limits."""
    if np.abs(q).max() >= VALUE_LIMIT:
        return None
    grid = _filled(q, kept)
    stride = max(1, q.size // FIT_CELLS)
    weights = _fit_weights(_fit_sums(grid, kept, stride))
    e, classes = _errors_and_classes(grid, kept, weights)
    if np.abs(e).max() > geometric.MAX_ANS_SYMBOL:
        return None
    lo, band_codes, _ = geometric.band_statistics(e, classes)
    codes = np.zeros(CLASSES, dtype=np.uint8)
    codes[lo:lo + band_codes.size] = band_codes
    max_abs = np.zeros(CLASSES, dtype=np.int64)
    np.maximum.at(max_abs, classes, np.abs(e))
    max_abs[codes == 0] = 0
    if _table_entries(codes, max_abs) > geometric.table_budget(q.size):
        return None
    return weights, e, classes, codes, max_abs


#: The last layers' models (:func:`_shared_model`), per thread: (weak references to ``q`` and ``kept``,
#: model), newest last; as many as :data:`SHARED_MODELS` (rate control sizes the predicted layout of
#: its best candidate and of the map with no spectrum, then codes one of them).
_MODELS = threading.local()
SHARED_MODELS = 2


def _known_model(q: np.ndarray, kept: np.ndarray) -> tuple | None:
    """The entry of :func:`_shared_model` that holds the model of these very arrays, if any."""
    for entry in getattr(_MODELS, "entries", ()):
        if entry[0]() is q and entry[1]() is kept:
            return entry
    return None


def _shared_model(q: np.ndarray, kept: np.ndarray):
    """:func:`_predicted_model` of ``q``, kept for the next call on the same arrays: rate control
    estimates the predicted layout of the layer it keeps (:func:`_estimated_predicted`), then codes
    it (:func:`_encode_predicted`), and the model (fit, errors, contexts) is half of coding it.
    Layers' integers are never changed in place once made."""
    entry = _known_model(q, kept)
    if entry is not None:
        return entry[2]
    model = _predicted_model(q, kept)
    entries = getattr(_MODELS, "entries", None)
    if entries is None:
        entries = _MODELS.entries = []

    def forget(ref: weakref.ref, entries: list = entries) -> None:
        # The model (a few arrays of the map's size) goes with its layer, not with the next layer sized.
        entries[:] = [e for e in entries if e[0] is not ref]

    entries.append((weakref.ref(q, forget), weakref.ref(kept), model))
    del entries[:-SHARED_MODELS]
    return model


@kernels.kernel("coding_order", classes_count=CLASSES)
def _coding_order(kept: np.ndarray, classes: np.ndarray, codes: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kind 5's coding order (format.md): the kept cells whose class has a nonzero code, by
    wavefront, then class, then row, as indices of the kept cells (row-major); where each
    (wavefront, class) group starts in that order (and its end), and each group's class."""
    rows, cols = kept.shape
    r, c = np.nonzero(kept)  # row-major, as classes
    coded = np.flatnonzero(codes[classes])
    # By wave, then class, then row: two stable sorts of small keys (radix sorts), class first;
    # ``coded`` is row-major, so cells of one wave and class stay in row order.
    by_class = coded[np.argsort(classes[coded].astype(np.uint8), kind="stable")]
    wave = 2 * r[by_class] + c[by_class]
    order = by_class[np.argsort(wave.astype(np.uint16 if rows * 2 + cols < 1 << 16 else np.int64), kind="stable")]
    key = (2 * r[order] + c[order]) * CLASSES + classes[order]
    starts = np.flatnonzero(np.diff(key, prepend=-1))
    return order, np.append(starts, order.size), classes[order[starts]]


def _encode_predicted(q: np.ndarray, kept: np.ndarray) -> bytes | None:
    """Kind 5's payload for ``q``, or None when its values or errors pass the layout's limits."""
    model = _shared_model(q, kept)
    if model is None:
        return None
    weights, e, classes, codes, max_abs = model
    order, bounds, group_classes = _coding_order(kept, classes, codes)
    symbols = e[order] + max_abs[classes[order]]
    present = np.flatnonzero(codes)
    words = _class_words(symbols, bounds, group_classes, codes, max_abs)
    listed = int(present[-1]) + 1 if present.size else 1
    return (_WEIGHTS.pack(*weights.tolist(), listed) + codes[:listed].tobytes()
            + max_abs[present].astype("<u2").tobytes() + words.astype("<u4").tobytes())


def _class_words_compiled(symbols: np.ndarray, bounds: np.ndarray, group_classes: np.ndarray, codes: np.ndarray,
                          max_abs: np.ndarray) -> np.ndarray:
    # The same words, without building constriction's tables.
    present = np.flatnonzero(codes)
    tables = geometric.packed_tables(max_abs[present], codes[present])
    return kernels.compiled_module().encode_table_words(symbols, bounds, tables, 2 * max_abs[present] + 1,
                                                        np.searchsorted(present, group_classes))


@kernels.kernel(_class_words_compiled)
def _class_words(symbols: np.ndarray, bounds: np.ndarray, group_classes: np.ndarray, codes: np.ndarray,
                 max_abs: np.ndarray) -> np.ndarray:
    """The ANS words (uint32) of groups of symbols (group g: ``symbols[bounds[g]:bounds[g + 1]]``, of
    class ``group_classes[g]``), each with its class's table (scale ``codes``, ``max_abs``), the last
    group pushed first."""
    coder = constriction.stream.stack.AnsCoder()
    symbols32 = symbols.astype(np.int32)
    for g in range(bounds.size - 2, -1, -1):  # a stack: the last group first
        k = int(group_classes[g])
        coder.encode_reverse(symbols32[bounds[g]:bounds[g + 1]], geometric.table_model(int(max_abs[k]), int(codes[k])))
    return coder.get_compressed()


def _table_entries(codes: np.ndarray, max_abs: np.ndarray) -> int:
    """Table entries a decoder builds: 2 max_abs + 1 for each class of nonzero code."""
    return int(np.sum(2 * max_abs[codes > 0] + 1))


def _decode_predicted(payload: bytes, kept: np.ndarray) -> np.ndarray:
    what = "predicted residual layer"
    if len(payload) < _WEIGHTS.size:
        raise CorruptFileError(f"{what} has a wrong length")
    *head, listed = _WEIGHTS.unpack_from(payload, 0)
    weights = np.array(head, dtype=np.int64)
    if np.abs(weights).max() >= WEIGHT_LIMIT or not 1 <= listed <= CLASSES:
        raise CorruptFileError(f"{what} has an implausible header")
    if len(payload) < _WEIGHTS.size + listed:
        raise CorruptFileError(f"{what} has a wrong length")
    codes = np.zeros(CLASSES, dtype=np.uint8)
    codes[:listed] = np.frombuffer(payload, dtype=np.uint8, count=listed, offset=_WEIGHTS.size)
    words_at = _WEIGHTS.size + listed + 2 * int(np.count_nonzero(codes))
    if len(payload) < words_at or (len(payload) - words_at) % 4:
        raise CorruptFileError(f"{what} has a wrong length")
    max_abs = np.zeros(CLASSES, dtype=np.int64)
    max_abs[codes > 0] = np.frombuffer(payload, dtype="<u2", count=int(np.count_nonzero(codes)),
                                       offset=_WEIGHTS.size + listed)
    if max_abs.max() > geometric.MAX_ANS_SYMBOL:
        raise CorruptFileError(f"{what} has an implausible header")
    rows, cols = kept.shape
    count = int(np.count_nonzero(kept))
    if _table_entries(codes, max_abs) > geometric.table_budget(count):
        raise CorruptFileError(f"{what} asks for larger probability tables than its {count} values allow")
    words = np.frombuffer(payload, dtype="<u4", offset=words_at).astype(np.uint32)
    return _predicted_values(words, kept, weights, codes, max_abs, what)


def _predicted_values_compiled(words: np.ndarray, kept: np.ndarray, weights: np.ndarray, codes: np.ndarray,
                               max_abs: np.ndarray, what: str) -> np.ndarray:
    # The same values in one compiled pass.
    geometric.check_ans_words(words, what)
    present = np.flatnonzero(codes)
    tables = geometric.packed_tables(max_abs[present], codes[present])
    found = kernels.compiled_module().decode_predicted(words, kept, weights, codes, tables, 2 * max_abs[present] + 1)
    if found is None:
        raise CorruptFileError(f"{what} decodes to values beyond 2**31")
    return found[kept.ravel()]


@kernels.kernel(_predicted_values_compiled)
def _predicted_values(words: np.ndarray, kept: np.ndarray, weights: np.ndarray, codes: np.ndarray,
                      max_abs: np.ndarray, what: str) -> np.ndarray:
    """The inverse of :func:`_class_words` over the grid: the values V (int64) of the ``kept`` cells,
    row-major, from ``words``, predicted with ``weights``; ``what`` names the layer in errors."""
    rows, cols = kept.shape
    flat_kept = np.append(kept.ravel(), False)
    values = np.zeros(rows * cols + 1, dtype=np.int64)  # the last: the zero of the edge rules
    errors = np.zeros(rows * cols + 1, dtype=np.int64)
    activity_of = [(n, k) for n, k in enumerate(ACTIVITY_WEIGHTS) if k]
    try:
        coder = constriction.stream.stack.AnsCoder(words)
        for cells, nbs, bounds in _wavefront_blocks(kept.shape):
            rebuilt_all = flat_kept[cells]
            for k0, k1 in zip(bounds[:-1].tolist(), bounds[1:].tolist()):
                at, rebuilt = cells[k0:k1], rebuilt_all[k0:k1]
                if rebuilt.any():
                    activity = np.zeros(k1 - k0, dtype=np.int64)
                    for n, weight in activity_of:
                        activity += weight * np.abs(errors[nbs[n, k0:k1]])
                    classes = np.where(rebuilt, _classes(activity), -1)
                    coded = classes[rebuilt]
                    for cls in np.unique(coded[codes[coded] > 0]).tolist():
                        where = at[classes == cls]
                        width = int(max_abs[cls])
                        errors[where] = coder.decode(geometric.table_model(width, int(codes[cls])), where.size) - width
                neighbours = [values[nbs[n, k0:k1]] for n in range(len(NEIGHBOURS))]
                out = np.where(rebuilt, _prediction(weights, neighbours) + errors[at], neighbours[0])
                if out.size and np.abs(out).max() >= VALUE_LIMIT:  # (a grid of one column has empty wavefronts)
                    raise CorruptFileError(f"{what} decodes to values beyond 2**31")
                values[at] = out
    except CorruptFileError:
        raise
    except Exception as exc:  # noqa: BLE001 - the coder reports damaged input its own way
        raise CorruptFileError(f"{what} does not decode: {exc}") from None
    return values[:-1][kept.ravel()]


#: What ``dftpcc info`` calls each layout, by the kind of a RESD's first chunk.
LAYOUT_NAMES = {coding.KIND_SPARSE_RESIDUAL: "sparse", coding.KIND_PREDICTED_RESIDUAL: "predicted"}


def layout_of(blob: Any) -> str:
    """The layout of a RESD section, from its first chunk's header: ``"predicted"`` (kind 5),
    ``"sparse"`` (kind 4) or ``"chunks"`` (kinds 0 and 3, and a section too short to say)."""
    view = memoryview(blob)
    if len(view) < 4 + coding.CHUNK_HEAD.size or struct.unpack_from("<I", view, 0)[0] == 0:
        return "chunks"
    return LAYOUT_NAMES.get(coding.CHUNK_HEAD.unpack_from(view, 4)[3], "chunks")


def decode_residual(blob: Any, kept: np.ndarray) -> np.ndarray:
    """The integers of a RESD section, one per ``True`` cell of ``kept``."""
    count = int(kept.sum())
    flat = np.zeros(count)
    q = coding.decode_coefficients(blob, count, radius=flat, angle=flat,
                                   whole={coding.KIND_SPARSE_RESIDUAL: lambda p: _decode_sparse(p, kept),
                                          coding.KIND_PREDICTED_RESIDUAL: lambda p: _decode_predicted(p, kept)})
    if q.dtype.kind != "i" or q.size != count:
        raise CorruptFileError("residual layer is not one integer per rebuilt cell")
    return q
