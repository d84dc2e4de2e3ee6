"""The probability models of quantized values, and their ANS words.

A band of coefficients (or residual values) sends one scale, its mean |q|, as an 8-bit code on a
log2 grid (:func:`band_statistics`); its values are coded with the two-sided geometric
distribution of that mean. The distribution's table is built from integers alone (:func:`decay`:
decimal arithmetic, floored; :func:`table_frequencies`: integer weights out of 2**24), so every
machine builds the same table and decodes the same bits. Values sharing a code share a table
(:func:`code_groups`); :func:`table_words` and :func:`coded_values` are the ANS coder (constriction,
or the compiled coder reading the same tables) over those groups. :func:`table_budget` bounds
the tables a crafted chunk may ask a decoder to build.
"""

from __future__ import annotations

import decimal
import functools
import warnings

import numpy as np

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    import constriction

from . import kernels
from .errors import CorruptFileError

__all__ = ["band_statistics", "band_sums", "band_scales", "scale_codes", "scale_of", "decay", "magnitude_weights", "table_model", "build_table_model",
           "table_frequencies", "packed_tables", "code_groups", "code_order", "log_geometric", "check_ans_words",
           "table_budget", "table_words", "coded_values", "TABLE_BITS", "MAX_ANS_SYMBOL", "SCALE_STEPS",
           "SCALE_BIAS", "MIN_SCALE"]


#: Band scales are sent as 8-bit codes on a log2 grid of 1/SCALE_STEPS octave.
SCALE_STEPS = 8


SCALE_BIAS = 128


#: Smallest band scale used (in quantizer steps); keeps probabilities nonzero.
MIN_SCALE = 0.05


#: Largest integer the ANS coder takes; a chunk with larger ones falls back
#: to zstd. The coder gives every integer of the support a nonzero
#: probability out of 2**24, so a wide support wastes rate on every symbol.
MAX_ANS_SYMBOL = 1 << 15


#: See :func:`table_budget`: building a table of n symbols costs about 6 ns a symbol.
TABLE_ENTRIES_PER_VALUE = 16


TABLE_ENTRIES_PER_CHUNK = 1 << 19


def band_scales(q: np.ndarray, bands: np.ndarray) -> tuple[int, np.ndarray]:
    """First band and 8-bit log-scale codes of the bands in ``bands`` (0 = all zero)."""
    lo, codes, _ = band_statistics(q, bands)
    return lo, codes


def band_statistics(q: np.ndarray, bands: np.ndarray, magnitudes: np.ndarray | None = None
                    ) -> tuple[int, np.ndarray, np.ndarray]:
    """:func:`band_scales` and the number of values in each band; ``magnitudes``:
    ``np.abs(q).astype(np.float64)``, if known (every layout of a chunk needs them)."""
    lo, codes, count, _ = band_sums(q, bands, magnitudes)
    return lo, codes, count


def band_sums(q: np.ndarray, bands: np.ndarray, magnitudes: np.ndarray | None = None
              ) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`band_statistics` and each band's sum of ``|q|``."""
    if magnitudes is None:
        magnitudes = np.abs(q).astype(np.float64)
    lo, count, total = _band_totals(bands, magnitudes)
    return lo, scale_codes(count, total), count, total


def scale_codes(count: np.ndarray, total: np.ndarray) -> np.ndarray:
    """Each band's scale code (uint8, 0 for a band of zeros) from its count of values and sum of |q|."""
    # A band's scale is its mean |q| (the maximum-likelihood Laplace scale; the
    # table models take the geometric distribution of that mean).
    b = np.divide(total, count, out=np.zeros(total.size), where=count > 0)
    codes = np.where(b > 0, np.clip(np.round(np.log2(np.maximum(b, 1e-12)) * SCALE_STEPS) + SCALE_BIAS, 1, 255), 0)
    return codes.astype(np.uint8)


@kernels.kernel("band_totals")
def _band_totals(bands: np.ndarray, magnitudes: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """The lowest of ``bands`` (int64, one per value), then each band's count of values and sum of
    ``magnitudes`` from there (``np.bincount``'s: added in the values' order). Rate control sizes
    every candidate stream by these, once per band layout."""
    lo = int(bands.min())
    local = bands - lo
    n = int(local.max()) + 1
    return lo, np.bincount(local, minlength=n), np.bincount(local, weights=magnitudes, minlength=n)


def scale_of(codes: np.ndarray) -> np.ndarray:
    return np.where(codes > 0, np.maximum(2.0 ** ((codes.astype(np.float64) - SCALE_BIAS) / SCALE_STEPS), MIN_SCALE), 0.0)


#: Probabilities of the table models are integers out of 2**TABLE_BITS.
TABLE_BITS = 24


@functools.lru_cache(maxsize=None)
def decay(code: int) -> int:
    """Ratio between successive magnitudes of band scale ``code``, in 1/65536.

    The two-sided geometric ``P(q) ~ t**|q|`` whose mean ``|q|`` is the band's
    scale b has ``t = (sqrt(1 + b*b) - 1) / b``. Computed in decimal at 50
    digits (correctly rounded square root and power), then floored: the same
    integer on every machine, unlike a float ``exp`` or ``pow``.
    """
    with decimal.localcontext() as ctx:
        ctx.prec = 50
        b = max(decimal.Decimal(2) ** (decimal.Decimal(code - SCALE_BIAS) / SCALE_STEPS),
                decimal.Decimal(str(MIN_SCALE)))
        return int(((1 + b * b).sqrt() - 1) / b * (1 << 16))


@functools.lru_cache(maxsize=None)
def magnitude_weights(code: int) -> np.ndarray:
    """Integer weights of |q| = 0, 1, ...: ``w0 = 2**32``, ``w(k) = w(k-1) * decay >> 16``,
    up to MAX_ANS_SYMBOL or the first zero."""
    r, w = decay(code), [1 << 32]
    while w[-1] and len(w) <= MAX_ANS_SYMBOL:
        w.append((w[-1] * r) >> 16)
    return np.array(w, dtype=np.int64)


#: Table models of at most this magnitude bound are cached (at most ~70 kB
#: each, so the cache stays under ~20 MB); wider ones (up to 0.3 MB) are rare,
#: first chunks only, and built each time.
CACHED_TABLE_MAX_ABS = 8192


#: Narrow tables (at most ~8 kB each, mostly constriction's fixed overhead) have a cache of
#: their own, so the many a map's later chunks use (every band scale at every small bound)
#: are not pushed out by the wide ones: 2048 of them stay under ~16 MB.
NARROW_TABLE_MAX_ABS = 255


NARROW_TABLES_CACHED = 2048
#: Frequency tables wider than NARROW_TABLE_MAX_ABS hold up to 2 x 32,768 int64 (half a megabyte,
#: a slowly decaying band scale's): this many of them are cached. In the one cache of
#: 2048 they shared with the narrow ones, decoding a 20,000² map (400 tiles) held 390 MB of them, and
#: a band-coded run's memory grew with the tiles it had coded.
WIDE_TABLES_CACHED = 64


def table_model(max_abs: int, code: int):
    """constriction model of the values -max_abs..max_abs (symbols 0..2*max_abs) of a band."""
    if max_abs <= NARROW_TABLE_MAX_ABS:
        return _narrow_table_model(max_abs, code)
    if max_abs <= CACHED_TABLE_MAX_ABS:
        return _cached_table_model(max_abs, code)
    return build_table_model(max_abs, code)


@functools.lru_cache(maxsize=NARROW_TABLES_CACHED)
def _narrow_table_model(max_abs: int, code: int):
    return build_table_model(max_abs, code)


@functools.lru_cache(maxsize=256)
def _cached_table_model(max_abs: int, code: int):
    return build_table_model(max_abs, code)


def table_frequencies(max_abs: int, code: int) -> tuple[int, np.ndarray]:
    """:func:`_table_frequencies`, cached (:data:`NARROW_TABLES_CACHED` narrow ones, :data:`WIDE_TABLES_CACHED` wide)."""
    if max_abs <= NARROW_TABLE_MAX_ABS:
        return _narrow_frequencies(max_abs, code)
    return _wide_frequencies(max_abs, code)


def _table_frequencies(max_abs: int, code: int) -> tuple[int, np.ndarray]:
    """Frequencies out of 2**24 of the symbols 0..2*max_abs of :func:`table_model`: 1 + w(|q|) *
    (2**24 - n) // total for each of the n = 2*max_abs+1 values (total: the sum of their weights),
    the remainder to q = 0. Returned as the first symbol above the floor of 1 and the frequencies
    from there: only the |q| with a nonzero weight (a few dozen: the weights decay geometrically)
    take more than that floor, so only those are computed. The constriction models are built from
    them; the compiled coders make the same integers themselves (:func:`packed_tables`)."""
    known = magnitude_weights(code)[: max_abs + 1]
    both = np.concatenate([known[:0:-1], known])  # |q| < known.size, around q = 0
    n = 2 * max_abs + 1
    free = (1 << TABLE_BITS) - n
    near = 1 + both * free // int(both.sum())
    near[known.size - 1] += (1 << TABLE_BITS) - int(near.sum()) - (n - both.size)
    near.flags.writeable = False  # cached: shared by every caller
    return max_abs - known.size + 1, near


_narrow_frequencies = functools.lru_cache(maxsize=NARROW_TABLES_CACHED)(_table_frequencies)
_wide_frequencies = functools.lru_cache(maxsize=WIDE_TABLES_CACHED)(_table_frequencies)


def build_table_model(max_abs: int, code: int):
    """See :func:`table_model` and :func:`table_frequencies`. The probabilities handed to
    constriction are those integers over 2**24, exact in float64, so its table is the same
    everywhere."""
    lo, near = table_frequencies(max_abs, code)
    probabilities = np.full(2 * max_abs + 1, 1.0 / (1 << TABLE_BITS))
    probabilities[lo: lo + near.size] = near / float(1 << TABLE_BITS)
    return constriction.stream.model.Categorical(probabilities, perfect=False)


def code_groups(codes: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """Positions of the values sharing each nonzero scale code, codes ascending.

    Values with one code share one concrete model, so the coder builds each
    model once instead of once per value (ten times faster on large maps).
    """
    order, present, bounds = code_order(codes)
    return [(int(code), order[bounds[k]:bounds[k + 1]]) for k, code in enumerate(present.tolist())]


def code_order(codes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`code_groups` as arrays: the positions of the values of nonzero code, by code (stable),
    the codes present, and where each one's positions start (and the end)."""
    order = np.argsort(codes, kind="stable")
    # Codes are bytes: a histogram gives the codes present and where each one's run starts.
    counts = np.bincount(codes, minlength=256)
    counts[0] = 0
    present = np.flatnonzero(counts)
    skip = codes.size - int(counts.sum())  # the zero codes sort first
    bounds = np.zeros(present.size + 1, dtype=np.int64)
    np.cumsum(counts[present], out=bounds[1:])
    return order[skip:], present, bounds


def packed_tables(max_abs: int | np.ndarray, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The compiled table coders' tables of scale ``codes`` at magnitude bound ``max_abs`` (one for all,
    or one per code): :func:`table_frequencies`' frequencies, made in one compiled pass from
    :func:`magnitude_weights` (a map's decode asks for hundreds of distinct tables: a few
    milliseconds made one by one in numpy, and too many to cache), packed as the coders read them."""
    codes = np.asarray(codes, dtype=np.int64)
    bounds = np.broadcast_to(np.asarray(max_abs, dtype=np.int64), codes.shape)
    weights = [magnitude_weights(code)[: bound + 1] for code, bound in zip(codes.tolist(), bounds.tolist())]
    return kernels.compiled_module().packed_cumulative(weights, bounds)


def _table_words_compiled(q: np.ndarray, per_value: np.ndarray, max_abs: int) -> np.ndarray:
    # The same words, without building constriction's tables.
    order, present, bounds = code_order(per_value)
    return kernels.compiled_module().encode_table_words(q[order] + max_abs, bounds, packed_tables(max_abs, present),
                                                        2 * max_abs + 1)


@kernels.kernel(_table_words_compiled)
def table_words(q: np.ndarray, per_value: np.ndarray, max_abs: int) -> np.ndarray:
    """The ANS words (uint32) of the values ``q`` (|q| <= ``max_abs``) grouped by their scale codes
    ``per_value`` (0: not coded), each group with its code's table, codes ascending."""
    coder = constriction.stream.stack.AnsCoder()
    # A stack coder decodes last-in first-out: push the groups in reverse.
    for code, where in reversed(code_groups(per_value)):
        coder.encode_reverse((q[where] + max_abs).astype(np.int32), table_model(max_abs, code))
    return coder.get_compressed()


@functools.lru_cache(maxsize=1)
def log_geometric() -> tuple[np.ndarray, np.ndarray]:
    """Per scale code (index 0 unused): ``log2((1 - t) / (1 + t))`` and ``log2(t)`` of
    :func:`_estimated_bits`, each the same numpy arithmetic it would do value by value."""
    scale = scale_of(np.arange(256, dtype=np.uint8))
    scale[0] = 1.0  # code 0 (an empty band) is never coded; any finite scale keeps the table finite
    t = (np.sqrt(1 + scale * scale) - 1) / scale
    return np.log2((1 - t) / (1 + t)), np.log2(np.maximum(t, 1e-300))


def check_ans_words(words: np.ndarray, what: str) -> None:
    """Refuse, with constriction's own message, ANS words that constriction would not take: a last
    word of 0. The compiled decoders read words as they are, so they ask here first."""
    if words.size and words[-1] == 0:
        try:
            constriction.stream.stack.AnsCoder(words)
        except Exception as exc:  # noqa: BLE001 - the coder reports damaged input its own way
            raise CorruptFileError(f"{what} does not decode: {exc}") from None
        raise CorruptFileError(f"{what} does not decode: its words end in a zero word")


def table_budget(count: int) -> int:
    """Most table entries (models x symbols) an ANS chunk of ``count`` values may ask
    the decoder to build: models cost time to build, so a crafted chunk must not
    make a few bytes cost seconds."""
    return TABLE_ENTRIES_PER_VALUE * count + TABLE_ENTRIES_PER_CHUNK


def _coded_values_compiled(words: np.ndarray, per_value: np.ndarray, max_abs: int, what: str) -> np.ndarray:
    # The same values, the groups sorted and decoded in one compiled pass.
    compiled = kernels.compiled_module()
    present = np.flatnonzero(compiled.code_counts(per_value)[1:]) + 1
    if present.size * (2 * max_abs + 1) > table_budget(per_value.size):
        raise CorruptFileError(f"{what} asks for larger probability tables than its {per_value.size} values allow")
    check_ans_words(words, what)
    return compiled.decode_coded_values(words, per_value, present, packed_tables(max_abs, present), 2 * max_abs + 1)


@kernels.kernel(_coded_values_compiled)
def coded_values(words: np.ndarray, per_value: np.ndarray, max_abs: int, what: str) -> np.ndarray:
    """The inverse of :func:`table_words`: the values (int64) whose scale codes are ``per_value``,
    from ``words``; ``what`` names the chunk in errors."""
    out = np.zeros(per_value.size, dtype=np.int64)
    groups = code_groups(per_value)
    if len(groups) * (2 * max_abs + 1) > table_budget(per_value.size):
        raise CorruptFileError(f"{what} asks for larger probability tables than its {per_value.size} values allow")
    try:
        coder = constriction.stream.stack.AnsCoder(words)
        for code, where in groups:
            out[where] = coder.decode(table_model(max_abs, code), where.size) - max_abs
    except Exception as exc:  # noqa: BLE001 - the coder reports damaged input its own way
        raise CorruptFileError(f"{what} does not decode: {exc}") from None
    if np.abs(out).max(initial=0) > max_abs:
        raise CorruptFileError(f"{what} decodes outside its stated range")
    return out

