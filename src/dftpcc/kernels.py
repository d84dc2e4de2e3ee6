"""Compiled kernels (numba), optional: the same bytes as the numpy path, in fewer passes.

The occupancy mask's context coder (:mod:`dftpcc.occupancy`) spends most of
its time in numpy passes that put the cells in decoding order and in
hundreds of calls into constriction per tile. Here the same coding is one
loop over the cells: the context counts of the steps before, the
probability of each (step, context) exactly as the numpy path computes it,
and constriction's ANS stack coder with its Bernoulli model (``perfect=False``:
the probability of a 0 quantized to ``1 + floor((1 - p) * (2**24 - 2) /
((1 - p) + p))`` of 2**24; the coder's 64-bit state, 32-bit words, a word
written when the state would overflow, the state's words last). The words
are those of the numpy path, bit for bit (``tests/test_kernels.py``). The
mask's decoder is one loop too, over the cells in decoding order, with
constriction's decoding (the state from the last two words, a word read
whenever the state drops below 2**32, decoding on from the state alone once
the words run out): the numpy path's mask from any words, damaged ones too. The
coefficient coder's integer tables (:mod:`dftpcc.coding`) are coded the same
way, without building constriction's models, and push-pull's levels
(:mod:`dftpcc.fill`) are pulled and pushed in one pass each, with the same
float operations in the same order (so the same bits, signs of zero too).
Sums whose bits reach a file (the gridding's spread, the plane's normal
equations) are added as ``np.sum`` adds them: its identity 0.0, then numpy's
pairwise summation (blocks of up to 128 values in eight accumulators, halved
at multiples of 8 above that), made as the values are, without their arrays.

Loading numba takes a fresh process about 0.3 s, more than a small map's
whole compression, so the kernels are used only once something asks for
them: :func:`load` (a :class:`~dftpcc.mapbuilder.MapBuilder` does, as it
lives for a whole drive) or the environment variable ``DFTPCC_JIT=1``.
``DFTPCC_JIT=0`` keeps the numpy path even then. Without numba installed
(the ``fast`` extra) everything runs on numpy, with the same files.
Compiled code is cached beside the package (numba's ``cache=True``, or in
``NUMBA_CACHE_DIR``), so only the first run on a machine compiles.

As the kernels release the GIL, a stage of a map can run on another core
beside the caller's work on the same map (:class:`Side`: the occupancy mask
while the spectrum is coded or decoded), with the same bytes.
"""

from __future__ import annotations

import math
import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable

import numpy as np

__all__ = ["load", "enabled", "Side", "CORES", "SIDE_MIN_CELLS", "available_cores", "mask_contexts", "encode_mask_words", "decode_mask_lines", "decode_predicted", "encode_table_words",
           "decode_coded_values", "pull", "push",
           "survey", "cell_points",
           "axis_cells", "cell_sums", "distance_sums", "plane_sums",
           "masked_errors", "quantization_sq_error", "weighted_sq_sum",
           "add_plane"]

#: :mod:`dftpcc._compiled` once :func:`load` imported it, and whether it tried. The kernels take the
#: codec's constants (the mask coder's prior, the tables) as arguments, so imports run one way.
_state: dict[str, Any] = {"module": None, "tried": False}


def _env() -> str:
    return os.environ.get("DFTPCC_JIT", "").strip()


def load() -> bool:
    """Compile (or load from the cache) the kernels if numba is installed; True if they are in use.

    Idempotent; ``DFTPCC_JIT=0`` makes it a no-op that returns False.
    """
    if _env() == "0":
        return False
    if not _state["tried"]:
        _state["tried"] = True
        try:
            _state["module"] = _compiled_module()
        except ImportError:
            _state["module"] = None
    return _state["module"] is not None


def enabled() -> bool:
    """True when the compiled kernels are in use (loaded, or ``DFTPCC_JIT=1`` loads them now)."""
    if _env() == "0":
        return False
    if _state["module"] is None and not _state["tried"] and _env() == "1":
        load()
    return _state["module"] is not None


#: Cores one map's coding may use at once; None: every core this process may run on
#: (:func:`available_cores`). 1 keeps every stage in the caller's thread.
CORES: int | None = None

#: A stage runs beside the caller only on grids of at least this many cells, where a patchy mask's
#: coder takes milliseconds (2.4-2.8 ms at 512 x 512 here, against 0.6-0.8 ms at 256 x 256 and 30-40 us
#: for a thread's hand-over): smaller maps, zarr chunks among them, have little to gain.
SIDE_MIN_CELLS = 1 << 18

_pool: dict[str, ThreadPoolExecutor] = {}
_pool_lock = threading.Lock()


def available_cores() -> int:
    """The cores this process may run on (``os.sched_getaffinity``, so ``taskset`` counts)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _cores() -> int:
    return available_cores() if CORES is None else max(1, int(CORES))


class Side:
    """``fn(*args)`` run on a thread of its own, beside the caller's work on the same map, or at once.

    Beside the caller when the compiled kernels are in use (they release the GIL for their whole
    pass; numpy's many short passes and constriction's calls would mostly wait for each other),
    the process may use more than one core (:data:`CORES`) and the grid has at least
    :data:`SIDE_MIN_CELLS` cells; otherwise ``fn`` runs at once, in the caller's thread, as a serial
    coder would. Either way :meth:`result` gives its value or raises its error: the bytes do not
    depend on where it ran. The occupancy mask's coder is the stage that runs so (its own
    arrays, nothing shared with the spectrum's): ``encoder`` and ``decoder`` use it.
    """

    def __init__(self, fn: Callable[..., Any], *args: Any, cells: int):
        cores = _cores() if enabled() and cells >= SIDE_MIN_CELLS else 1
        self._future: Future | None = None
        self._left = cores - 1
        if cores > 1:
            self._future = _executor().submit(fn, *args)
        else:
            self._value = fn(*args)

    def cores_left(self) -> int | None:
        """The cores the caller's own work may use now: all but this stage's while it runs, None
        (no limit) once it is done or when it ran at once. For :func:`dftpcc.spectrum.fft_workers`,
        which asks before each transform: a map whose mask codes in no time (a full raster) keeps
        every core for its transforms."""
        return None if self._future is None or self._future.done() else self._left

    def result(self) -> Any:
        """``fn(*args)``, waiting for it if it runs beside; its exception if it raised one."""
        return self._value if self._future is None else self._future.result()


if hasattr(os, "register_at_fork"):  # a forked child has none of the pool's threads: it makes its own
    os.register_at_fork(after_in_child=_pool.clear)


def _executor() -> ThreadPoolExecutor:
    # One pool for the process; several callers (zarr's chunk threads) may each have a stage beside.
    with _pool_lock:
        if "pool" not in _pool:
            _pool["pool"] = ThreadPoolExecutor(max_workers=max(2, os.cpu_count() or 2),
                                               thread_name_prefix="dftpcc-side")
        return _pool["pool"]


def encode_mask_words(lines: np.ndarray, ctx: np.ndarray, stripe: int, prior_ones: np.ndarray,
                      prior_total: float, first_seed: bool = False) -> np.ndarray:
    """The context coder's ANS words of the line-major mask ``lines`` (uint8, 0/1) with the contexts
    ``ctx`` (see ``occupancy._contexts``): what ``occupancy._encode_context`` gets from constriction
    (``first_seed``: kind 3, line 0 of the first stripe not coded)."""
    module = _state["module"]
    lines = np.ascontiguousarray(lines, dtype=np.uint8)
    words = np.empty(lines.size + 4, dtype=np.uint32)  # numpy's allocation: huge pages (see axis_cells)
    return module.encode_mask_words(lines, np.ascontiguousarray(ctx), int(stripe), prior_ones, float(prior_total),
                                    int(first_seed), words)


def mask_contexts(lines: np.ndarray, stripe: int) -> np.ndarray:
    """``occupancy._contexts`` of the line-major mask ``lines`` (uint8, 0/1), in one pass."""
    lines = np.ascontiguousarray(lines, dtype=np.uint8)
    if lines.ndim != 2 or stripe < 1:
        raise ValueError("lines must be a 2-d mask and stripe at least 1")
    ctx = np.empty_like(lines)  # numpy's allocation: see axis_cells
    _state["module"].mask_contexts(lines, int(stripe), ctx)
    return ctx


def decode_mask_lines(words: np.ndarray, lines: np.ndarray, n_lines: int, stripe: int, prior_ones: np.ndarray,
                      prior_total: float, first_seed: bool = False) -> np.ndarray:
    """The inverse of :func:`encode_mask_words`, as ``occupancy._decode_context`` decodes with constriction.

    ``words``: the ANS words (uint32, their last word not zero: constriction refuses that, and so must
    the caller); ``lines``: the line-major mask, ``(n_stripes * stripe, width)`` uint8, zeros but line 0 of
    every stripe after the first (the seed lines; of the first too with ``first_seed``, kind 3); the other lines are decoded into it in place, and it
    is returned. Any words decode to some mask, as they do with constriction (which decodes on from its
    state alone past the last word)."""
    # The kernel writes into lines without bounds checks: its shape must be what it assumes.
    if lines.dtype != np.uint8 or lines.ndim != 2 or not lines.flags.c_contiguous:
        raise ValueError("lines must be a C-contiguous 2-d uint8 array")
    if stripe < 1 or n_lines < 0 or lines.shape[0] < -(-n_lines // stripe) * stripe:
        raise ValueError("lines must hold every line of the stripes")
    return _state["module"].decode_mask_lines(np.ascontiguousarray(words, dtype=np.uint32), lines, int(n_lines),
                                              int(stripe), np.ascontiguousarray(prior_ones, dtype=np.float64),
                                              float(prior_total), int(first_seed))


def _packed_tables(cumulatives: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Tables' running sums end to end, and where each table's frequencies start (and the end),
    as the compiled table coders read them."""
    near_bounds = np.zeros(len(cumulatives) + 1, dtype=np.int64)
    np.cumsum([a.size - 1 for a in cumulatives], out=near_bounds[1:])
    return (np.concatenate(cumulatives) if cumulatives else np.zeros(0, np.int64)), near_bounds


def decode_predicted(words: np.ndarray, kept: np.ndarray, weights: np.ndarray, codes: np.ndarray,
                     lows: list[int], cumulatives: list[np.ndarray], alphabets: np.ndarray) -> np.ndarray | None:
    """``RESD`` kind 5's values V on the whole grid (``residual._decode_predicted``), in one compiled
    pass; None when one reaches 2**31. ``lows``, ``cumulatives``, ``alphabets``: the tables of the
    classes of nonzero ``codes``, in class order (as :func:`encode_table_words` takes them);
    ``words``: as for :func:`decode_mask_lines`."""
    csum, near_bounds = _packed_tables(cumulatives)
    table_of = np.full(len(codes), -1, dtype=np.int64)
    table_of[np.flatnonzero(codes)] = np.arange(np.count_nonzero(codes))
    values = np.zeros(kept.size, dtype=np.int64)
    status = _state["module"].decode_predicted(
        np.ascontiguousarray(words, dtype=np.uint32), np.ascontiguousarray(kept, dtype=np.bool_),
        np.ascontiguousarray(weights, dtype=np.int64), np.ascontiguousarray(codes, dtype=np.uint8),
        np.asarray(lows, dtype=np.int64), csum, near_bounds, np.ascontiguousarray(alphabets, dtype=np.int64),
        table_of, values)
    return None if status else values


def decode_coded_values(words: np.ndarray, per_value: np.ndarray, present: np.ndarray, lows: list[int],
                        cumulatives: list[np.ndarray], n: int) -> np.ndarray:
    """``coding._decode_ans``'s values in one compiled pass: each value's scale code ``per_value``
    (uint8; 0: the value is 0), the nonzero codes ``present`` among them, ascending, with their tables
    (``coding._table_cumulative``) of one alphabet of ``n`` symbols; ``words``: as for
    :func:`decode_mask_lines`. The values of one code are decoded in turn, codes ascending, as
    :func:`encode_table_words` pushes them."""
    csum, near_bounds = _packed_tables(cumulatives)
    table_of = np.zeros(256, dtype=np.int64)
    table_of[np.asarray(present, dtype=np.int64)] = np.arange(len(present))
    out = np.zeros(per_value.size, dtype=np.int64)
    _state["module"].decode_coded_values(np.ascontiguousarray(words, dtype=np.uint32),
                                         np.ascontiguousarray(per_value, dtype=np.uint8), table_of,
                                         np.asarray(lows, dtype=np.int64), csum, near_bounds,
                                         np.full(len(cumulatives), n, dtype=np.int64), out)
    return out


def encode_table_words(symbols: np.ndarray, bounds: np.ndarray, lows: list[int], cumulatives: list[np.ndarray],
                       n: int | np.ndarray, tables: np.ndarray | None = None) -> np.ndarray:
    """The ANS words of groups of symbols 0..n-1 (group g: ``symbols[bounds[g]:bounds[g + 1]]``), each
    with its table (``coding._table_cumulative``: a floor of 1 of 2**24 but the frequencies whose running
    sums ``cumulatives[t]`` holds, from symbol ``lows[t]``; t is ``tables[g]``, else g), pushed as
    ``coding._encode_ans_with`` pushes them to constriction: the last group first, each group last
    symbol first. Many groups may share a few tables (``RESD`` kind 5: a group per class and wavefront);
    ``n``: one alphabet size for all the tables, or one for each."""
    module = _state["module"]
    csum, near_bounds = _packed_tables(cumulatives)
    if tables is None:
        tables = np.arange(len(cumulatives), dtype=np.int64)
    alphabets = np.broadcast_to(np.asarray(n, dtype=np.int64), (len(cumulatives),))
    return module.encode_table_words(np.ascontiguousarray(symbols, dtype=np.int64), np.asarray(bounds, np.int64),
                                     np.asarray(tables, dtype=np.int64), np.asarray(lows, dtype=np.int64), csum,
                                     near_bounds, np.ascontiguousarray(alphabets))


def pull(values: np.ndarray, known: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Push-pull's coarser level (``fill._push_pull``): the mean of the known values of each 2x2 block
    (sums added as ``fill._pairs`` adds them, zeros past odd edges) and whether any of the four is known."""
    r, c = values.shape
    mean, any_known = np.zeros(((r + 1) // 2, (c + 1) // 2)), np.zeros(((r + 1) // 2, (c + 1) // 2), dtype=bool)
    _state["module"].pull(np.ascontiguousarray(values, dtype=np.float64), np.ascontiguousarray(known), mean, any_known)
    return mean, any_known


def push(values: np.ndarray, known: np.ndarray, coarse: np.ndarray) -> np.ndarray:
    """Push-pull's blend of a level with the 2x bilinear upsampling of the filled ``coarse`` level
    (``fill._push_pull``): the known cells keep their values, the others take the upsampling."""
    out = np.empty(values.shape)  # numpy's allocation: see axis_cells
    _state["module"].push(np.ascontiguousarray(values, dtype=np.float64), np.ascontiguousarray(known),
                          np.ascontiguousarray(coarse, dtype=np.float64), out)
    return out


def _compiled_module():
    from . import _compiled  # ImportError without numba: the numpy path

    return _compiled


def survey(points: np.ndarray) -> tuple[float, float, float, float, float, float, float] | None:
    """x_lo, x_hi, y_lo, y_hi, z_lo, z_hi and ``np.sum(points[:, 2])`` of float64 points (N, 3+), N > 0,
    in one pass, to numpy's bits; None when a coordinate is not finite (the caller's numpy path says
    which) or where numpy's reductions could differ (a zero extreme: which of 0.0 and -0.0 is the minimum)."""
    *found, nan = _state["module"].survey(points)
    extremes = tuple(float(v) for v in found[:6])
    if nan or 0.0 in extremes or not all(math.isfinite(v) for v in extremes):
        return None
    return (*extremes, float(found[6]))  # type: ignore[return-value]


def cell_points(mask: np.ndarray, xs: np.ndarray, ys: np.ndarray, heights: np.ndarray, z0: float) -> np.ndarray:
    """``rebuild.dem_to_points`` of an axis-aligned grid: ``(xs[col], ys[row], heights + z0)`` of every
    cell set in ``mask`` (rows, cols), row-major; ``xs`` one x per column, ``ys`` one y per row."""
    rows, cols = mask.shape
    if xs.shape != (cols,) or ys.shape != (rows,) or heights.shape != mask.shape:
        raise ValueError("xs, ys and heights must match the mask's columns, rows and shape")
    mask = np.ascontiguousarray(mask, dtype=np.bool_)
    out = np.empty((int(np.count_nonzero(mask)), 3))
    _state["module"].cell_points(mask, np.ascontiguousarray(xs, dtype=np.float64),
                                 np.ascontiguousarray(ys, dtype=np.float64),
                                 np.ascontiguousarray(heights, dtype=np.float64), float(z0), out)
    return out


def axis_cells(points: np.ndarray, x0: float, y0: float, z0: float, inv_u: float, inv_v: float, cols: int,
               rows: int) -> tuple[np.ndarray, np.ndarray] | None:
    """``grid._axis_cells``: the flat cell index and the height above ``z0`` of every point of an
    axis-aligned grid, the same arithmetic; None when a point lies outside the grid."""
    # The outputs are allocated here, by numpy, which puts large arrays on huge pages (madvise); numba's
    # own allocation faults every 4 kB page in: 40 ms instead of 17 for the forest's 2.8 M points.
    n = points.shape[0]
    idx, z = np.empty(n, dtype=np.int64), np.empty(n)
    ok = _state["module"].axis_cells(points, float(x0), float(y0), float(z0), float(inv_u), float(inv_v),
                                     int(cols), int(rows), idx, z)
    return (idx, z) if ok else None


def cell_sums(idx: np.ndarray, z: np.ndarray, count: np.ndarray, total: np.ndarray) -> None:
    """``count += np.bincount(idx, minlength=count.size)`` and ``total += np.bincount(idx, weights=z,
    minlength=total.size)``, in one pass and in place; the same bits where ``count`` and ``total``
    were zeros (each bin sums its points in order, from 0.0)."""
    # The kernel indexes without checks: idx are cells of the grid, the arrays one value per cell.
    if (count.dtype != np.int64 or total.dtype != np.float64 or count.shape != total.shape or count.ndim != 1
            or not (count.flags.c_contiguous and total.flags.c_contiguous) or idx.shape != z.shape):
        raise ValueError("count (int64) and total (float64) must be contiguous arrays of one value per cell")
    _state["module"].cell_sums(np.ascontiguousarray(idx, dtype=np.int64), np.ascontiguousarray(z, dtype=np.float64),
                               count, total)


def distance_sums(idx: np.ndarray, z: np.ndarray, heights: np.ndarray, tolerance_sq: float,
                  far_cells: np.ndarray) -> tuple[float, float, int, float]:
    """With ``sq = (z - heights[idx])**2``: ``sq.sum()``, its maximum (0 for no points), how many
    exceed ``tolerance_sq`` and the sum of those (``sq[sq > tolerance_sq].sum()``), each to numpy's
    bits (pairwise sums); the far points' cells are set True in ``far_cells`` (bool, one per cell
    of the grid, in place)."""
    # idx are cells of the grid (the kernel does not check them): heights and far_cells hold one per cell.
    if far_cells.dtype != np.bool_ or not far_cells.flags.c_contiguous or far_cells.size != heights.size:
        raise ValueError("far_cells must be a contiguous bool array of one value per cell, as heights")
    if idx.shape != z.shape or idx.ndim != 1:
        raise ValueError("idx and z must be 1-d arrays of one value per point")
    # The far squares, in order; numpy's allocation: see axis_cells.
    far_sq = np.empty(idx.size)
    total, largest, far, far_total = _state["module"].distance_sums(
        np.ascontiguousarray(idx, dtype=np.int64), np.ascontiguousarray(z, dtype=np.float64),
        np.ascontiguousarray(heights, dtype=np.float64).reshape(-1), float(tolerance_sq), far_cells, far_sq)
    return float(total), float(largest), int(far), float(far_total)


def plane_sums(heights: np.ndarray, mask: np.ndarray) -> tuple[float, float, float, float, float, float, float, float]:
    """``fill.fit_plane``'s sums, to the bit: the means of the column, row and height of the
    cells set in ``mask`` (rows, cols; at least one), and the sums of products xx, xy, yy, xz, yz of
    the centred values, each added as numpy's ``mean`` and ``sum`` add (pairwise)."""
    if heights.shape != mask.shape or heights.ndim != 2:
        raise ValueError("heights and mask must be 2-d arrays of one shape")
    mask = np.ascontiguousarray(mask, dtype=np.bool_)
    occupied = int(np.count_nonzero(mask))
    if occupied == 0:
        raise ValueError("mask must have a set cell")
    # One more value each than occupied cells: the kernel writes every cell's, keeping the occupied
    # ones (numpy's allocation: see axis_cells).
    x, y, z = np.empty(occupied + 1), np.empty(occupied + 1), np.empty(occupied + 1)
    found = _state["module"].plane_sums(np.ascontiguousarray(heights, dtype=np.float64), mask, x, y, z)
    return tuple(float(v) for v in found)  # type: ignore[return-value]


def masked_errors(heights: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, float, float] | None:
    """``err = (heights - ref)[mask]``, ``np.sum(err * err)`` and ``np.abs(err).max()`` to numpy's
    bits, in two passes; None where numpy's figures could differ (no set cell, a NaN)."""
    if not (heights.shape == ref.shape == mask.shape and heights.ndim == 2):
        raise ValueError("heights, ref and mask must be 2-d arrays of one shape")
    mask = np.ascontiguousarray(mask, dtype=np.bool_)
    n = int(np.count_nonzero(mask))
    # Every cell's error is written at the count of set cells before it, so one more than the set
    # cells holds them all (numpy's allocation: see axis_cells).
    out = np.empty(n + 1)
    sq_sum, largest = _state["module"].masked_errors(np.ascontiguousarray(heights, dtype=np.float64),
                                                     np.ascontiguousarray(ref, dtype=np.float64), mask, out)
    if n == 0 or not np.isfinite(sq_sum):
        return None
    return out[:n], float(sq_sum), float(largest)


def quantization_sq_error(values: np.ndarray, step: float, deadzone: float) -> float | None:
    """``coding.choose_step``'s error of quantizing ``values`` (float64) with ``step``: the sum of
    squares of ``values - dequantize(quantize(values, step, deadzone), step)`` to numpy's bits; None
    where ``quantize`` would refuse (an integer past 2**63), so the caller raises as it does."""
    total, ok = _state["module"].quantization_sq_error(np.ascontiguousarray(values, dtype=np.float64), float(step),
                                                       0.5 - float(deadzone))
    return float(total) if ok else None


def weighted_sq_sum(counts: np.ndarray, mask: np.ndarray, errors: np.ndarray) -> float:
    """``np.sum(counts[mask] * errors * errors)`` to numpy's bits, without the products' arrays
    (``counts``: int64 per cell; ``errors``: one per set cell of ``mask``, row-major)."""
    mask = np.ascontiguousarray(mask, dtype=np.bool_)
    if counts.shape != mask.shape or counts.ndim != 2 or errors.ndim != 1:
        raise ValueError("counts and mask must be 2-d arrays of one shape, errors 1-d")
    if errors.size != int(np.count_nonzero(mask)):  # the kernel walks the set cells without bounds checks
        raise ValueError("errors must hold one value per set cell of mask")
    scratch = np.empty(errors.size + 1)  # the set cells' counts (numpy's allocation: see axis_cells)
    return float(_state["module"].weighted_sq_sum(np.ascontiguousarray(counts, dtype=np.int64), mask,
                                                  np.ascontiguousarray(errors, dtype=np.float64), scratch))


def add_plane(heights: np.ndarray, plane: tuple[float, float, float]) -> None:
    """``heights += fill.plane_values(plane, heights.shape)`` in place, to the bit, in one pass
    (``heights``: a C-contiguous 2-d float64 array)."""
    if heights.dtype != np.float64 or heights.ndim != 2 or not heights.flags.c_contiguous:
        raise ValueError("heights must be a C-contiguous 2-d float64 array")
    a, b, c = (float(v) for v in plane)
    _state["module"].add_plane(heights, a, b, c)
