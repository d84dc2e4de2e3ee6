"""Encode stage, occupancy: which cells of the grid are rebuilt.

The mask is coded with an adaptive context model: a cell's context is the
five cells around it on the previous line and the three on the line before,
and the probability of a 1 in each context is counted from everything
decoded before. Only previous lines enter a context, so a whole line
decodes at once.

To keep the number of sequential steps small on large maps, the lines are
cut into stripes of ``stripe`` lines that are decoded in lockstep: step t
decodes line t of every stripe. The first line of every stripe but the
first has no line above it yet; those few *seed* lines are sent first as
run lengths. Within a step, the cells whose context is all empty or all
full (most cells of a real footprint) are decoded with one fixed model
each, the rest with one model per cell.

A tile's first line is a cut through the map, not the map's edge: there
kind 3 sends it as a seed too (format 1.1's tiles only).

A bit-packed, zstd'd bitmap is the fallback when it is smaller.
"""

from __future__ import annotations

import math
import struct
import warnings

import numpy as np
import zstandard
from scipy.special import betaln

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    import constriction

from . import kernels
from .coding import unzstd
from .geometric import check_ans_words
from .errors import CorruptFileError

__all__ = ["encode_mask", "decode_mask", "STRIPE_LINES"]

#: Coding kinds (first byte of the mask section). Kind 1, a line-context
#: coder without stripes, was only written by pre-release builds.
KIND_ZSTD = 0
KIND_CONTEXT = 2
#: Kind 2 with line 0 of the first stripe sent as a seed as well (format 1.1).
KIND_SEEDED = 3
_HEAD = struct.Struct("<BB")  # kind, transposed
_STRIPES = struct.Struct("<II")  # lines per stripe, bytes of the seed frame
CONTEXTS = 256
#: The two contexts that cover most cells of a real footprint: nothing
#: around (outside) and everything around (inside).
OUTSIDE, INSIDE = 0, CONTEXTS - 1
#: Prior of the adaptive counts: one pseudo-cell per context, a 1 with the
#: odds of the eight neighbours that are set. The model then starts close to
#: right, which matters most in the first steps, when every stripe codes a
#: line with counts from only a few lines.
PRIOR_TOTAL = 1.0
PRIOR_ONES = (np.array([bin(c).count("1") for c in range(CONTEXTS)]) + 0.5) / 9.0
#: Lines per stripe the encoder writes on a large mask: each stripe costs a
#: seed line and a slower start, each line of a stripe one decoding step.
#: Against one stripe, 64 lines cost 1.1 % more bytes on the 0.9 M-cell
#: forest mask (4.5 % on the field's 0.5 M cells) and decode 1.5x (3x) faster.
STRIPE_LINES = 64
#: Masks of fewer cells decode in milliseconds anyway: one stripe, no seeds.
STRIPED_CELLS = 1 << 18
#: The bitmap fallback rarely wins; a middle zstd level keeps it from costing
#: a tenth of a second on large maps.
#: zstd levels of the bit-packed mask and of the seed lines (a compressor per call: zstandard's are
#: not thread-safe, and zarr codes chunks in threads).
_BITMAP_LEVEL = 9
_SEED_LEVEL = 19
#: Runs of cells sharing one context's probability at least this long are coded with that
#: probability's own model (a few ns a cell, against a few tens with a probability per cell,
#: and a microsecond or two a call).
FIXED_MODEL_RUN = 64


def _codes(lines: np.ndarray) -> np.ndarray:
    """5-bit code of each cell's neighbourhood (offsets -2..+2) along the last axis."""
    padded = np.zeros(lines.shape[:-1] + (lines.shape[-1] + 4,), dtype=np.uint8)  # np.pad, without its overhead
    padded[..., 2:-2] = lines
    return _codes_of_padded(padded)


def _codes_of_padded(p: np.ndarray) -> np.ndarray:
    # Bit k is the cell at offset k - 2; pairs first, so six operations instead of nine.
    pairs = (p[..., 1:] << 1) | p[..., :-1]
    return (pairs[..., 3:] << 3) | (pairs[..., 1:-2] << 1) | p[..., :-4]


def _older(codes: np.ndarray) -> np.ndarray:
    """Bits 5-7 of a context (offsets -1..+1 of the line before last) from that line's codes."""
    return (codes << 4) & 0xE0


def _bernoulli(p: float | None = None):
    if p is None:
        return constriction.stream.model.Bernoulli(perfect=False)
    return constriction.stream.model.Bernoulli(p, perfect=False)


def _runs(line: np.ndarray) -> np.ndarray:
    """Run lengths of a 0/1 line, starting with a run of zeros (possibly empty)."""
    change = np.flatnonzero(line[1:] != line[:-1]) + 1
    runs = np.diff(np.concatenate(([0], change, [line.size])))
    return np.concatenate(([0], runs)) if line[0] else runs


def _encode_seeds(seeds: np.ndarray) -> bytes:
    if seeds.shape[0] == 0:
        return b""
    values = []
    for line in seeds:
        runs = _runs(line)
        values += [runs.size, *runs]
    # Byte planes: the high bytes of small run lengths compress to nothing.
    planes = np.asarray(values, dtype="<u4").view(np.uint8).reshape(-1, 4).T
    return zstandard.ZstdCompressor(level=_SEED_LEVEL).compress(planes.tobytes())


def _decode_seeds(frame: bytes, count: int, width: int) -> np.ndarray:
    seeds = np.zeros((count, width), dtype=np.uint8)
    if count == 0:
        if frame:
            raise CorruptFileError("occupancy mask has seed lines it does not need")
        return seeds
    limit = 4 * count * (width + 2)  # at most width + 1 runs and their count per line
    raw = unzstd(zstandard.ZstdDecompressor(), frame, limit, "occupancy mask seed lines")
    if len(raw) % 4:
        raise CorruptFileError("occupancy mask seed lines have a wrong length")
    values = np.frombuffer(raw, dtype=np.uint8).reshape(4, -1).T.copy().view("<u4").ravel().astype(np.int64)
    pos = 0
    for i in range(count):
        n = int(values[pos]) if pos < values.size else -1
        runs = values[pos + 1: pos + 1 + n]
        if n < 1 or runs.size != n or int(runs.sum()) != width:
            raise CorruptFileError(f"occupancy mask seed line {i} does not add up to {width} cells")
        seeds[i] = np.repeat(np.arange(n, dtype=np.uint8) & 1, runs)
        pos += 1 + n
    if pos != values.size:
        raise CorruptFileError("occupancy mask seed lines have trailing data")
    return seeds


#: Order of a cell's context kind within a decoding step: outside, inside, the rest.
_KIND = np.full(CONTEXTS, 2, dtype=np.int32)
_KIND[OUTSIDE], _KIND[INSIDE] = 0, 1
_KIND8 = _KIND.astype(np.uint8)


@kernels.kernel("mask_contexts")
def _contexts(lines: np.ndarray, stripe: int) -> np.ndarray:
    """Context of every cell of the line-major mask ``lines`` (n, w).

    Line t of a stripe sees lines t-1 and t-2 of the same stripe; line 1
    takes line 0 for both, line 0 sees nothing.
    """
    codes = _codes(lines)
    ctx = np.empty_like(codes)
    ctx[:1] = 0
    ctx[1:] = codes[:-1]
    ctx[::stripe] = 0  # line 0 of a stripe sees nothing
    bits = _older(codes)
    older = np.empty_like(codes)
    older[:2] = 0
    older[2:] = bits[:-2]
    older[::stripe] = 0
    if stripe > 1:
        older[1::stripe] = bits[::stripe][: older[1::stripe].shape[0]]  # line 1: line 0 again
    ctx |= older
    return ctx


def _seed_lines(lines: np.ndarray, stripe: int, first_seed: bool = False) -> np.ndarray:
    """Line 0 of every stripe but the first (of every stripe with ``first_seed``): sent as run
    lengths, before the context-coded cells."""
    return lines[0 if first_seed else stripe::stripe]


def _encode_context(lines: np.ndarray, stripe: int, seed_frame: bytes | None = None,
                    first_seed: bool = False) -> bytes:
    """The context-coded mask (kind 2, or 3 with ``first_seed``); ``seed_frame``:
    :func:`_encode_seeds` of its seed lines, if known."""
    ctx = _contexts(lines, stripe)
    if seed_frame is None:
        seed_frame = _encode_seeds(_seed_lines(lines, stripe, first_seed))
    head = _STRIPES.pack(stripe, len(seed_frame)) + seed_frame
    return head + _context_words(lines, ctx, stripe, first_seed).astype("<u4").tobytes()


@kernels.kernel("encode_mask_words", prior_ones=PRIOR_ONES, prior_total=PRIOR_TOTAL)
def _context_words(lines: np.ndarray, ctx: np.ndarray, stripe: int, first_seed: bool) -> np.ndarray:
    """The ANS words (uint32) of the line-major mask ``lines`` (uint8, 0/1) with its contexts ``ctx``
    (:func:`_contexts`), coded in decoding order (``first_seed``: kind 3, line 0 of the first stripe not coded)."""
    n_lines, width = lines.shape
    # Step s decodes line s of every stripe (line 0 of the first stripe only, the
    # others' are seeds; none with first_seed): by stripe, then column. The lines in that order:
    line = np.arange(n_lines)
    step_of = line % stripe
    if stripe >= n_lines:  # one stripe (a tile's mask): the lines in their own order, step = line
        first = int(first_seed)
        steps, bits, c = step_of[first:], lines[first:], ctx[first:]
    else:
        order = np.lexsort((line // stripe, step_of))
        order = order[(step_of[order] > 0) | ((order == 0) & (not first_seed))]
        steps, bits, c = step_of[order], lines[order], ctx[order]
    # Decoding order: step by step; within a step the outside cells, then the
    # inside cells, then the rest, each by stripe and column. The decoder takes
    # a step's outside (inside) cells with one model of their probability, which
    # codes to the same words as the adaptive model given that probability per
    # cell; so the cells go to the coder in long stretches: a step's outside or
    # inside run of at least FIXED_MODEL_RUN cells with its one model (cheaper per
    # cell), everything between with the adaptive one.
    #
    # Most cells of a tile are in such runs, and a run needs its bits only: so the
    # per-cell work (the order, a probability per cell) is done on the other cells
    # alone, the *adaptive* ones, and a run's bits are a slice of its kind's bits.
    # Group (s, k): the cells of kind k (0 outside, 1 inside, 2 the rest) of step s.
    one = bits.view(bool)
    kinds = (c == OUTSIDE, c == INSIDE)
    # Per coded line (byte sums in the narrowest type that holds a line: faster than count_nonzero).
    count_type = np.uint16 if width <= np.iinfo(np.uint16).max else np.int64

    def line_sums(m: np.ndarray) -> np.ndarray:
        return m.view(np.uint8).sum(axis=1, dtype=count_type).astype(np.int64)

    in_line = [line_sums(m) for m in kinds]
    ones_in_line = [line_sums(m & one) for m in kinds]
    in_line.append(width - in_line[0] - in_line[1])

    def per_step(v: np.ndarray) -> np.ndarray:
        return np.bincount(steps, weights=v, minlength=stripe).astype(np.int64)

    size = np.stack([per_step(v) for v in in_line], axis=1)  # (stripe, 3)
    fixed = size >= FIXED_MODEL_RUN
    fixed[:, 2] = False
    adaptive_size = np.where(fixed, 0, size)
    adaptive_start = (np.cumsum(adaptive_size) - adaptive_size.ravel()).reshape(stripe, 3)
    adaptive_before = np.cumsum(adaptive_size, axis=0) - adaptive_size  # per kind, in the steps before s
    rest = ~(kinds[0] | kinds[1])
    chosen = [kinds[0] & ~fixed[steps, 0][:, None], kinds[1] & ~fixed[steps, 1][:, None], rest]
    flat_one, flat_c = one.reshape(-1), c.reshape(-1)
    # The adaptive cells in decoding order: a stable counting sort by (step, kind), as the
    # steps of the coded lines never decrease: each cell goes to its group's start plus its
    # rank among the group's cells.
    seq = np.empty(int(adaptive_size.sum()), dtype=np.intp)
    for k in range(3):
        cells = np.flatnonzero(chosen[k])
        per_line = np.where(fixed[steps, k], 0, in_line[k])
        shift = (adaptive_start[:, k] - adaptive_before[:, k])[steps]
        seq[np.repeat(shift, per_line) + np.arange(cells.size)] = cells
    # Counts seen before each step: per-step histograms, accumulated, shifted by one step
    # (row s: the steps before s), over the contexts that occur only (a tile's mask has a
    # few dozen of the 256); then the probability of each (step, context).
    rest_c = c[rest]
    rest_steps = np.repeat(steps, in_line[2])
    seen = np.bincount(rest_c, minlength=CONTEXTS)
    seen[OUTSIDE] += size[:, 0].sum()
    seen[INSIDE] += size[:, 1].sum()
    present = np.flatnonzero(seen)
    compact = np.zeros(CONTEXTS, dtype=np.int64)
    compact[present] = np.arange(present.size)
    # Laid out (context, step + 1), so the sums over the steps run along contiguous rows and
    # the running sum at (context, s) counts the steps before s.
    span = stripe + 1
    key = compact[rest_c] * span + rest_steps + 1
    total = np.bincount(key, minlength=span * present.size).reshape(present.size, span)
    ones = np.bincount(key[one[rest]], minlength=span * present.size).reshape(present.size, span)
    for k, context in ((0, OUTSIDE), (1, INSIDE)):
        if size[:, k].any():
            total[compact[context], 1:] += size[:, k]
            ones[compact[context], 1:] += per_step(ones_in_line[k])
    ones_before, total_before = np.cumsum(ones, axis=1).ravel(), np.cumsum(total, axis=1).ravel()

    def prob(context: np.ndarray, step: np.ndarray) -> np.ndarray:
        at = compact[context] * span + step
        return (ones_before[at] + PRIOR_ONES[context]) / (total_before[at] + PRIOR_TOTAL)

    group_step = np.repeat(np.arange(stripe), adaptive_size.sum(axis=1))
    adaptive_bits = flat_one[seq].astype(np.int32)
    adaptive_prob = prob(flat_c[seq], group_step)
    # The runs' bits: each kind's cells in decoding order, a run a slice of them.
    run_bits = [bits[m].astype(np.int32) if fixed[:, k].any() else None for k, m in enumerate(kinds)]
    run_start = np.cumsum(size[:, :2], axis=0) - size[:, :2]
    runs = np.flatnonzero(fixed.ravel())[::-1]
    run_step, run_kind = np.divmod(runs, 3)
    run_prob = prob(np.where(run_kind == 0, OUTSIDE, INSIDE), run_step)
    coder = constriction.stream.stack.AnsCoder()
    model = _bernoulli()
    # A stack: the last cells are pushed first (encode_reverse pushes an array last first too).
    end = adaptive_bits.size
    for k, a, r, n, p in zip(run_kind.tolist(), adaptive_start.ravel()[runs].tolist(),
                             run_start[run_step, run_kind].tolist(), size.ravel()[runs].tolist(),
                             run_prob.tolist()):
        if a < end:
            coder.encode_reverse(adaptive_bits[a:end], model, adaptive_prob[a:end])
        coder.encode_reverse(run_bits[k][r:r + n], _bernoulli(p))  # type: ignore[index]
        end = a
    if end:
        coder.encode_reverse(adaptive_bits[:end], model, adaptive_prob[:end])
    return coder.get_compressed()


def _decode_context(payload: bytes, shape: tuple[int, int], first_seed: bool = False) -> np.ndarray:
    n_lines, width = shape
    first = int(first_seed)
    if len(payload) < _STRIPES.size:
        raise CorruptFileError("occupancy mask is truncated")
    stripe, seed_bytes = _STRIPES.unpack_from(payload, 0)
    words_at = _STRIPES.size + seed_bytes
    if stripe < 1 or words_at > len(payload) or (len(payload) - words_at) % 4:
        raise CorruptFileError("occupancy mask has a wrong length")
    stripe = min(stripe, n_lines)
    n_stripes = math.ceil(n_lines / stripe)
    # Stripe s, line t is row s of lines[:, t]; rows past the map stay empty.
    lines = np.zeros((n_stripes, stripe, width), dtype=np.uint8)
    lines[1 - first:, 0] = _decode_seeds(payload[_STRIPES.size:words_at], n_stripes - 1 + first, width)
    words = np.frombuffer(payload, dtype="<u4", offset=words_at).astype(np.uint32)
    check_ans_words(words, "occupancy mask")  # constriction's own message, for both backends
    return _context_lines(words, lines, n_lines, first_seed)


@kernels.kernel("decode_mask_lines", prior_ones=PRIOR_ONES, prior_total=PRIOR_TOTAL)
def _context_lines(words: np.ndarray, lines: np.ndarray, n_lines: int, first_seed: bool) -> np.ndarray:
    """The inverse of :func:`_context_words`: ``lines`` (``(n_stripes, stripe, width)`` uint8, zeros but
    the seed lines: line 0 of every stripe after the first, of the first too with ``first_seed``)
    decoded in place from ``words``, returned as the ``(n_lines, width)`` boolean mask."""
    n_stripes, stripe, width = lines.shape
    first = int(first_seed)
    padded = np.zeros((n_stripes, width + 4), dtype=np.uint8)  # lines with two empty cells each side
    ones, total = np.zeros(CONTEXTS), np.zeros(CONTEXTS)
    above = older = np.zeros((1, width), dtype=np.uint8)
    try:
        coder = constriction.stream.stack.AnsCoder(words)
        model = _bernoulli()
        for t in range(stripe):
            if t >= first:  # kind 3: line 0 of every stripe is a seed
                active = 1 if t == 0 else -(-(n_lines - t) // stripe)  # stripes that have a line t
                ctx = (above[:active] | older[:active]).ravel()
                prob = (ones + PRIOR_ONES) / (total + PRIOR_TOTAL)
                line = np.empty(ctx.size, dtype=np.uint8)
                outside, inside = ctx == OUTSIDE, ctx == INSIDE
                for where, c in ((outside, OUTSIDE), (inside, INSIDE)):
                    n = np.count_nonzero(where)
                    if n:
                        bits = coder.decode(_bernoulli(prob[c]), n)
                        line[where] = bits
                        ones[c] += np.count_nonzero(bits)
                        total[c] += n
                rest = ~(outside | inside)
                rest_ctx = ctx[rest]
                if rest_ctx.size:
                    bits = coder.decode(model, prob[rest_ctx])
                    line[rest] = bits
                    ones += np.bincount(rest_ctx, weights=bits, minlength=CONTEXTS)
                    total += np.bincount(rest_ctx, minlength=CONTEXTS)
                lines[:active, t] = line.reshape(active, width)
            if t == 0:
                active = n_stripes  # the seeds are line 0 of the other stripes
            padded[:active, 2:-2] = lines[:active, t]
            # On the flat buffer (contiguous, so fast); codes that straddle two
            # stripes land in the padding columns and are dropped.
            flat = padded[:active].reshape(-1)
            codes = np.empty_like(padded[:active])
            codes.reshape(-1)[:-4] = _codes_of_padded(flat)
            codes = codes[:, :width]
            # Line 1 of a stripe takes line 0 as the line before last as well.
            older, above = _older(codes if t == 0 else above[:active]), codes
    except CorruptFileError:
        raise
    except Exception as exc:  # noqa: BLE001 - the coder reports damaged input its own way
        raise CorruptFileError(f"occupancy mask does not decode: {exc}") from None
    return lines.reshape(-1, width)[:n_lines].view(bool)


def estimated_size(mask: np.ndarray) -> float:
    """Bytes :func:`encode_mask` would code ``mask`` in with the context model, without coding it
    (rate control's model of a sparse residual layer's picture): each context's adaptive counts
    cost, whatever the order of its cells, the log-ratio of two Beta functions of its counts and
    prior; the stripes' seed lines are coded, as the encoder does. The stripes' counts learn a
    step later than this sequential model, so the coded mask is a little longer (a few %)."""
    stripe = STRIPE_LINES if mask.size >= STRIPED_CELLS else max(mask.shape)
    lines = (mask.T if mask.shape[0] > mask.shape[1] else mask).astype(np.uint8)
    stripe = min(stripe, lines.shape[0])
    ctx = _contexts(lines, stripe).astype(np.int64)
    ones = np.bincount(ctx.ravel(), weights=lines.ravel(), minlength=CONTEXTS)
    total = np.bincount(ctx.ravel(), minlength=CONTEXTS).astype(np.float64)
    a, b = PRIOR_ONES, PRIOR_TOTAL - PRIOR_ONES
    nats = float(np.sum(betaln(a, b) - betaln(ones + a, total - ones + b)))
    seeds = _encode_seeds(_seed_lines(lines, stripe))
    return _HEAD.size + _STRIPES.size + len(seeds) + nats / math.log(2) / 8.0 + 4.0


def encode_mask(mask: np.ndarray, *, stripe: int | None = None, first_seed: bool = False) -> bytes:
    """Code the occupancy mask; the smaller of the context model and zstd wins.

    The context coder runs along the longer axis, line after line across
    the shorter one, so there are as few sequential steps as possible.

    Parameters
    ----------
    mask : ndarray of bool, shape (rows, cols)
    stripe : int, optional
        Lines per stripe; default :data:`STRIPE_LINES` on masks of at least
        :data:`STRIPED_CELLS` cells, else one stripe.
    first_seed : bool
        Also try kind 3, the first line sent as a seed (format 1.1: a tile's mask, whose first
        line cuts through the map), when that line has an occupied cell; kind 2 on a tie.
    """
    if stripe is None:
        stripe = STRIPE_LINES if mask.size >= STRIPED_CELLS else max(mask.shape)
    if stripe < 1:
        raise ValueError("stripe must be at least 1 line")
    transposed = mask.shape[0] > mask.shape[1]
    lines = (mask.T if transposed else mask).astype(np.uint8)
    stripe = min(stripe, lines.shape[0])
    bitmap = _HEAD.pack(KIND_ZSTD, 0) + zstandard.ZstdCompressor(level=_BITMAP_LEVEL).compress(
        np.packbits(mask.ravel()).tobytes())
    seed_frame = _encode_seeds(_seed_lines(lines, stripe))
    # The context coder's output holds both headers and the seed frame at least;
    # a bitmap shorter than that wins without running it (a full DEM's mask).
    if len(bitmap) < _HEAD.size + _STRIPES.size + len(seed_frame):
        return bitmap
    context = _HEAD.pack(KIND_CONTEXT, transposed) + _encode_context(lines, stripe, seed_frame)
    choices = [context, bitmap]  # the context coder on a tie, as always
    # An empty first line costs kind 2 next to nothing (and teaches the empty context what it is).
    if first_seed and lines[0].any():
        choices.insert(1, _HEAD.pack(KIND_SEEDED, transposed) + _encode_context(lines, stripe, first_seed=True))
    return min(choices, key=len)


def decode_mask(blob: bytes | memoryview, shape: tuple[int, int]) -> np.ndarray:
    """Inverse of :func:`encode_mask`; checks the size against ``shape``."""
    blob = bytes(blob)
    if len(blob) < _HEAD.size:
        raise CorruptFileError("occupancy mask is truncated")
    kind, transposed = _HEAD.unpack_from(blob, 0)
    payload = blob[_HEAD.size:]
    if kind in (KIND_CONTEXT, KIND_SEEDED):
        # The encoder always runs along the longer axis (fewest sequential
        # lines); a file claiming otherwise could make decoding crawl.
        if transposed != (shape[0] > shape[1]):
            raise CorruptFileError("occupancy mask runs along the wrong axis")
        lines = _decode_context(payload, (shape[1], shape[0]) if transposed else shape,
                                first_seed=kind == KIND_SEEDED)
        return lines.T.copy() if transposed else lines
    if kind != KIND_ZSTD:
        raise CorruptFileError(f"occupancy mask has unknown coding {kind}")
    nbytes = (shape[0] * shape[1] + 7) // 8
    raw = unzstd(zstandard.ZstdDecompressor(), payload, nbytes, "occupancy mask")
    if len(raw) != nbytes:
        raise CorruptFileError("occupancy mask has the wrong size for the grid")
    bits = np.unpackbits(np.frombuffer(raw, dtype=np.uint8), count=shape[0] * shape[1])
    return bits.astype(bool).reshape(shape)
