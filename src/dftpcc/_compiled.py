"""The compiled backend's kernels (numba): the twins of the stages' numpy kernels, the same bits.

:mod:`dftpcc.kernels` imports this module only when a call takes the compiled backend, so that
numba's import (a few tenths of a second) is paid only then. Each kernel is two functions here: the
compiled loop (``_name``, ``@njit``), and, at the end of the module, ``name`` with the signature of
its numpy twin in the stage (the stage's :func:`dftpcc.kernels.kernel` names it), which allocates
the loop's arrays and returns ``NotImplemented`` for an input whose bits the loop could not promise
(the numpy twin then runs). The codec's constants (the mask coder's prior, the tables) come in as
arguments, so imports run one way: the stages import nothing from here.

The compiled loops are module-level functions, so that numba's cache (``cache=True``) finds them
again in the next process: closures that call one another are compiled afresh in every process.

The occupancy mask's context coder is one loop over the cells: the context counts of the steps
before, the probability of each (step, context) exactly as the numpy path computes it, and
constriction's ANS stack coder with its Bernoulli model (``perfect=False``: the probability of a 0
quantized to ``1 + floor((1 - p) * (2**24 - 2) / ((1 - p) + p))`` of 2**24; the coder's 64-bit
state, 32-bit words, a word written when the state would overflow, the state's words last). Its
decoder is one loop too, over the cells in decoding order, with constriction's decoding (the state
from the last two words, a word read whenever the state drops below 2**32, decoding on from the
state alone once the words run out): the numpy path's mask from any words, damaged ones too. The
coefficient coder's integer tables are coded the same way, without building constriction's models,
and push-pull's levels are pulled and pushed in one pass each, with the same float operations in the
same order (so the same bits, signs of zero too). Sums whose bits reach a file (the gridding's
spread, the plane's normal equations) are added as ``np.sum`` adds them: its identity 0.0, then
numpy's pairwise summation (blocks of up to 128 values in eight accumulators, halved at multiples of
8 above that), made as the values are, without their arrays.

Output arrays are allocated by numpy, outside the loops: numpy puts large arrays on huge pages
(madvise), numba's own allocation faults every 4 kB page in (40 ms instead of 17 for the forest's
2.8 M points' cells).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: constriction's probabilities: integers out of 2**PRECISION; FREE: what its Bernoulli model spreads.
PRECISION = 24
TOTAL = 1 << PRECISION
#: The table decoders' quantile slots (2**12 of the 2**24 quantiles; see _decode_coded_values).
SLOT_SHIFT = 12
SLOTS = TOTAL >> SLOT_SHIFT
#: Values of one scale code from which a table decoder builds its slots.
SLOT_MIN_VALUES = 512
FREE = float(TOTAL - 2)


@njit(cache=True, nogil=True)
def _flush(words, count, state):  # pragma: no cover - compiled
    # the coder's final state, low word first, only the words it needs (none for a zero state)
    lo = np.uint32(state & np.uint64(0xFFFFFFFF))
    hi = np.uint32(state >> np.uint64(32))
    if hi != 0:
        words[count] = lo
        words[count + 1] = hi
        count += 2
    elif lo != 0:
        words[count] = lo
        count += 1
    return words[:count].copy()


@njit(cache=True, nogil=True, inline="always")
def _push(words, count, state, bit, z):  # pragma: no cover - compiled
    # constriction's Bernoulli push of one bit whose 0 has the integer probability z (of 2**24)
    if bit:
        left, prob = z, TOTAL - z
    else:
        left, prob = 0, z
    if (state >> np.uint64(64 - PRECISION)) >= np.uint64(prob):
        words[count] = np.uint32(state & np.uint64(0xFFFFFFFF))
        count += 1
        state = state >> np.uint64(32)
    prob_u = np.uint64(prob)
    state = ((state // prob_u) << np.uint64(PRECISION)) | (np.uint64(left) + state % prob_u)
    return count, state


@njit(cache=True, nogil=True)
def _mask_contexts(lines, stripe, ctx):  # pragma: no cover - compiled
    # occupancy._contexts into ctx (uint8, the shape of lines): bits 0-4 the cells at offsets
    # -2..+2 of the line before, bits 5-7 those at -1..+1 of the line before last (line 1 of a
    # stripe: line 0 again; line 0: nothing), each a window slid along the line.
    n, w = lines.shape
    for line in range(n):
        t = line % stripe
        if t == 0:
            for j in range(w):
                ctx[line, j] = 0
            continue
        a = line - 1
        o = a if t == 1 else line - 2
        code = np.int64(0)
        if w > 0:
            code = np.int64(lines[a, 0]) << 3
        if w > 1:
            code |= np.int64(lines[a, 1]) << 4
        old = np.int64(0)
        if w > 0:
            old = np.int64(lines[o, 0]) << 7
        for j in range(w):
            code >>= 1
            if j + 2 < w:
                code |= np.int64(lines[a, j + 2]) << 4
            old = (old >> 1) & 0x60
            if j + 1 < w:
                old |= np.int64(lines[o, j + 1]) << 7
            ctx[line, j] = code | old


@njit(cache=True, nogil=True)
def _encode_mask_words(lines, ctx, stripe, prior_ones, prior_total, first, words):  # pragma: no cover - compiled
    # first: 1 for kind 3, whose line 0 of the first stripe is a seed too (not coded), else 0
    n, w = lines.shape
    n_stripes = (n + stripe - 1) // stripe
    # Per step, per context: the integer probability of a 0 (constriction's quantization).
    # Only the contexts a step's cells have are computed (a few of the 256 on most steps), at the
    # first cell of the step with that context, before any of its cells is counted: so from the
    # counts of the steps before it.
    zero_prob = np.empty((stripe, 256), dtype=np.int64)
    ones = np.zeros(256, dtype=np.int64)
    seen = np.zeros(256, dtype=np.int64)
    stamp = np.full(256, -1, dtype=np.int64)  # the last step whose probability of context c is known
    for s in range(stripe):
        k_end = 1 - first if s == 0 else n_stripes
        for k in range(k_end):
            line = k * stripe + s
            if line >= n:
                break
            for j in range(w):
                c = ctx[line, j]
                if stamp[c] != s:
                    stamp[c] = s
                    p = (ones[c] + prior_ones[c]) / (seen[c] + prior_total)
                    q0 = 1.0 - p
                    zero_prob[s, c] = np.int64(q0 * (FREE / (q0 + p))) + 1
                seen[c] += 1
                ones[c] += lines[line, j]
    # A stack: the cells go in last first. Decoding order: step by step; within a step the
    # outside cells (context 0), the inside ones (255), the rest, each by stripe and column. So per
    # step, one pass backwards pushes the rest and keeps the bits of the outside and inside cells
    # (one probability each in a step), which are pushed after it, inside first.
    # words: the caller's, n * w + 4 of them (see axis_cells)
    outside = np.empty(n_stripes * w, dtype=np.uint8)
    inside = np.empty(n_stripes * w, dtype=np.uint8)
    count = 0
    state = np.uint64(0)
    for s in range(stripe - 1, -1, -1):
        k_end = 1 - first if s == 0 else n_stripes
        n_out = n_in = 0
        for k in range(k_end - 1, -1, -1):
            line = k * stripe + s
            if line >= n:
                continue
            for j in range(w - 1, -1, -1):
                c = ctx[line, j]
                if c == 0:
                    outside[n_out] = lines[line, j]
                    n_out += 1
                elif c == 255:
                    inside[n_in] = lines[line, j]
                    n_in += 1
                else:
                    count, state = _push(words, count, state, lines[line, j], zero_prob[s, c])
        if n_in:
            z = zero_prob[s, 255]
            for t in range(n_in):
                count, state = _push(words, count, state, inside[t], z)
        if n_out:
            z = zero_prob[s, 0]
            for t in range(n_out):
                count, state = _push(words, count, state, outside[t], z)
    return _flush(words, count, state)


@njit(cache=True, nogil=True, inline="always")
def _ans_start(words):  # pragma: no cover - compiled
    # constriction's AnsCoder(words): the state is the last word, with the one before it as its low
    # word if there is one (no word: state 0); and the next word to read
    pos = words.size - 1
    state = np.uint64(0)
    if pos >= 0:
        state = np.uint64(words[pos])
        pos -= 1
        if pos >= 0:
            state = (state << np.uint64(32)) | np.uint64(words[pos])
            pos -= 1
    return state, pos


@njit(cache=True, nogil=True)
def _decode_mask_lines(words, lines, n_lines, stripe, prior_ones, prior_total, first):  # pragma: no cover - compiled
    # The inverse of encode_mask_words, as occupancy._decode_context decodes with constriction:
    # lines (n_stripes * stripe, width), zeros but line 0 of every stripe after the first (the
    # seeds; with first = 1, kind 3, line 0 of the first stripe too), gets the other lines in place. Decoding order as there: step t decodes line t of
    # every stripe that has one (line 0 of the first only); within a step the outside cells
    # (context 0), the inside ones (255), the rest, each by stripe and column; the probability of a
    # context from the counts of the steps before.
    #
    # constriction's AnsCoder(words) (stack.rs, from_compressed): the state is the last word, and
    # the one before it as its low word if there is one (no word: state 0; the caller refuses a
    # last word of zero, as constriction does). A decode: quantile = the state's low 24 bits; the
    # symbol whose interval holds it (a 0 below zero_prob); state = (state >> 24) * probability +
    # quantile - left; below 2**32 the state takes the next word down as its low word, if any is
    # left. Past the last word it keeps decoding from the state alone, as constriction does.
    width = lines.shape[1]
    n_stripes = (n_lines + stripe - 1) // stripe
    mask24 = np.uint64(TOTAL - 1)
    total = np.uint64(TOTAL)
    low = np.uint64(1) << np.uint64(32)
    state, pos = _ans_start(words)
    above = np.zeros((n_stripes, width), dtype=np.uint8)  # codes of line t - 1
    older = np.zeros((n_stripes, width), dtype=np.uint8)  # bits 5-7 of the contexts: line t - 2
    codes = np.empty(width, dtype=np.uint8)
    ctx = np.empty(n_stripes * width, dtype=np.uint8)
    zero_prob = np.empty(256, dtype=np.uint64)
    ones = np.zeros(256, dtype=np.int64)
    seen = np.zeros(256, dtype=np.int64)
    stamp = np.full(256, -1, dtype=np.int64)  # the step whose probability of context c is known
    active = 1
    for t in range(stripe):
        if t >= first:  # kind 3: line 0 of every stripe is a seed, step 0 decodes nothing
            active = 1 if t == 0 else (n_lines - t + stripe - 1) // stripe  # stripes that have a line t
            # The contexts of the step's cells, and the probability of each context they have, from
            # the counts of the steps before (all of them before any cell of the step is counted).
            for s in range(active):
                for j in range(width):
                    c = above[s, j] | older[s, j]
                    ctx[s * width + j] = c
                    if stamp[c] != t:
                        stamp[c] = t
                        p = (ones[c] + prior_ones[c]) / (seen[c] + prior_total)
                        q0 = 1.0 - p
                        zero_prob[c] = np.uint64(np.int64(q0 * (FREE / (q0 + p))) + 1)
            for kind in range(3):
                for s in range(active):
                    row = s * stripe + t
                    for j in range(width):
                        c = ctx[s * width + j]
                        this = 0 if c == 0 else (1 if c == 255 else 2)
                        if this != kind:
                            continue
                        z = zero_prob[c]
                        quantile = state & mask24
                        if quantile < z:
                            bit = 0
                            state = (state >> np.uint64(PRECISION)) * z + quantile
                        else:
                            bit = 1
                            state = (state >> np.uint64(PRECISION)) * (total - z) + (quantile - z)
                        if state < low and pos >= 0:
                            state = (state << np.uint64(32)) | np.uint64(words[pos])
                            pos -= 1
                        lines[row, j] = bit
                        seen[c] += 1
                        ones[c] += bit
        if t == 0:
            active = n_stripes  # the seeds are line 0 of the other stripes
        # The codes of line t (occupancy._codes: bit k the cell at offset k - 2, zeros past the
        # ends); line 1 of a stripe takes line 0 as the line before last as well.
        for s in range(active):
            row = s * stripe + t
            window = 0
            for i in range(width + 2):
                cell = np.int64(lines[row, i]) if i < width else 0
                window = (window >> 1) | (cell << 4)
                if i >= 2:
                    codes[i - 2] = window
            for j in range(width):
                before = codes[j] if t == 0 else above[s, j]
                older[s, j] = (np.int64(before) << 4) & 0xE0
                above[s, j] = codes[j]
    return lines


@njit(cache=True, nogil=True)
def _left(i, lo, csum, at, size, n):  # pragma: no cover - compiled
    # constriction's left cumulative of symbol i: floor(C / 2**24 * (2**24 - n)) + i, C the frequencies below i
    if i < lo:
        c = i
    elif i < lo + size:
        c = lo + csum[at + i - lo]
    else:
        c = lo + csum[at + size] + (i - lo - size)
    return np.int64((c / float(TOTAL)) * float(TOTAL - n)) + i


@njit(cache=True, nogil=True, inline="always")
def _fill_cumulatives(cum, base, lo, csum, at, size, n):  # pragma: no cover - compiled
    # A table's left cumulatives (_left of each of its n symbols, then TOTAL) into cum from base, made
    # once for all the symbols it decodes: its search then reads integers.
    for i in range(n):
        cum[base + i] = _left(i, lo, csum, at, size, n)
    cum[base + n] = TOTAL


@njit(cache=True, nogil=True, inline="always")
def _fill_slots(cum, base, n, slots):  # pragma: no cover - compiled
    # slots[s]: the last symbol whose left cumulative (cum from base) is at most s * 2**SLOT_SHIFT, so
    # a quantile's symbol lies between slots[s] and slots[s + 1] (most often they are equal): a search
    # over those few symbols, not the alphabet.
    a = 0
    for s in range(SLOTS):
        while cum[base + a + 1] <= (s << SLOT_SHIFT):
            a += 1
        slots[s] = a
    slots[SLOTS] = n - 1


@njit(cache=True, nogil=True)
def _decode_coded_values(words, per_value, table_of, lows, csum, near_bounds, alphabets, out):  # pragma: no cover - compiled
    # coding._decode_ans's constriction loop in one pass: the values of each nonzero code c, codes
    # ascending and positions ascending within one, decoded with table table_of[c] as
    # symbol - (n - 1) // 2; values of code 0 stay as they are. They are decoded in that order into
    # ``decoded`` (code c's from count[c]), then laid out by position in one pass down per_value,
    # each code's values read in turn: every array is walked in order, none is scattered into.
    count = np.zeros(257, dtype=np.int64)
    for i in range(per_value.size):
        count[np.int64(per_value[i]) + 1] += 1
    for c in range(256):
        count[c + 1] += count[c]
    decoded = np.empty(per_value.size, dtype=np.int32)  # values are below 2**31 (MAX_ANS_SYMBOL)
    state, pos = _ans_start(words)
    lefts = np.empty(alphabets.max() + 1 if alphabets.size else 1, dtype=np.int64)
    slots = np.empty(SLOTS + 1, dtype=np.int64)
    mask24 = np.uint64(TOTAL - 1)
    low = np.uint64(1) << np.uint64(32)
    for c in range(1, 256):
        if count[c + 1] == count[c]:
            continue
        t = table_of[c]
        n = alphabets[t]
        _fill_cumulatives(lefts, 0, lows[t], csum, near_bounds[t] + t, near_bounds[t + 1] - near_bounds[t], n)
        # A code of few values searches the alphabet instead: the slots would cost more than they save.
        slotted = count[c + 1] - count[c] >= SLOT_MIN_VALUES
        if slotted:
            _fill_slots(lefts, 0, n, slots)
        half = (n - 1) // 2
        # The search and the state's step written out here and in _decode_predicted: as a shared
        # inlined function returning the state, this loop took twice as long (28-37 ms against 15 ms
        # on bench-decode's mosaic at 2 m).
        for j in range(count[c], count[c + 1]):
            quantile = np.int64(state & mask24)
            if slotted:
                s = quantile >> SLOT_SHIFT
                a, b = slots[s], slots[s + 1]
            else:
                a, b = 0, n - 1
            while a < b:
                mid = (a + b + 1) // 2
                if lefts[mid] <= quantile:
                    a = mid
                else:
                    b = mid - 1
            state = (state >> np.uint64(PRECISION)) * np.uint64(lefts[a + 1] - lefts[a]) \
                + np.uint64(quantile - lefts[a])
            if state < low and pos >= 0:
                state = (state << np.uint64(32)) | np.uint64(words[pos])
                pos -= 1
            decoded[j] = a - half
    fill = count[:256].copy()
    for i in range(per_value.size):
        c = np.int64(per_value[i])
        if c:
            out[i] = decoded[fill[c]]
            fill[c] += 1


@njit(cache=True, nogil=True)
def _encode_table_words(symbols, bounds, tables, lows, csum, near_bounds, alphabets):  # pragma: no cover - compiled
    words = np.empty(symbols.size + 4, dtype=np.uint32)
    count = 0
    state = np.uint64(0)
    for g in range(bounds.size - 2, -1, -1):
        t = tables[g]
        n = alphabets[t]
        lo = lows[t]
        at = near_bounds[t] + t  # each table's running sums hold one more entry than its frequencies
        size = near_bounds[t + 1] - near_bounds[t]
        for k in range(bounds[g + 1] - 1, bounds[g] - 1, -1):
            i = symbols[k]
            left = _left(i, lo, csum, at, size, n)
            right = TOTAL if i == n - 1 else _left(i + 1, lo, csum, at, size, n)
            prob = np.uint64(right - left)
            if (state >> np.uint64(64 - PRECISION)) >= prob:
                words[count] = np.uint32(state & np.uint64(0xFFFFFFFF))
                count += 1
                state = state >> np.uint64(32)
            state = ((state // prob) << np.uint64(PRECISION)) | (np.uint64(left) + state % prob)
    return _flush(words, count, state)


@njit(cache=True, nogil=True)
def _pull_level(values, known, mean, any_known):  # pragma: no cover - compiled
    # mean, any_known: the caller's zeros, (rows + 1) // 2 x (cols + 1) // 2 (see axis_cells)
    r, c = values.shape
    rc, cc = mean.shape
    for i in range(rc):
        a, b = 2 * i, 2 * i + 1
        for j in range(cc):
            p, q = 2 * j, 2 * j + 1
            v00 = values[a, p]
            v01 = values[a, q] if q < c else 0.0
            v10 = values[b, p] if b < r else 0.0
            v11 = values[b, q] if (b < r and q < c) else 0.0
            n = np.int64(known[a, p])
            if q < c:
                n += known[a, q]
            if b < r:
                n += known[b, p]
                if q < c:
                    n += known[b, q]
            if n > 0:
                # (row pair) + (row pair), as fill._pairs adds the blocks
                mean[i, j] = ((v00 + v01) + (v10 + v11)) / np.float64(n)
                any_known[i, j] = True


@njit(cache=True, nogil=True)
def _push_level(values, known, coarse, out):  # pragma: no cover - compiled
    # out: the caller's, the shape of values (see axis_cells)
    r, c = values.shape
    rc, cc = coarse.shape
    for i in range(r):
        k = i >> 1
        kn = k + 1 if i & 1 else k - 1  # the coarse row this output leans on, clamped
        kn = min(max(kn, 0), rc - 1)
        for j in range(c):
            v = values[i, j]
            if known[i, j] and v != 0.0:
                out[i, j] = v
                continue
            p = j >> 1
            pn = p + 1 if j & 1 else p - 1
            pn = min(max(pn, 0), cc - 1)
            own = 0.75 * coarse[k, p] + 0.25 * coarse[kn, p]
            side = 0.75 * coarse[k, pn] + 0.25 * coarse[kn, pn]
            up = 0.75 * own + 0.25 * side
            # the blend w * v + (1 - w) * up with w 0 or 1, the same bits (signs of zero too)
            out[i, j] = v + 0.0 * up if known[i, j] else up + v


@njit(cache=True, nogil=True)
def _survey(points):  # pragma: no cover - compiled
    # extremes and np.sum(points[:, 2]) (numpy's pairwise sum of the column: its leaves, each summed
    # while its rows are in cache for the extremes), in one pass over the cloud; and whether a NaN
    # was seen (a NaN is never an extreme; an infinity is).
    n = points.shape[0]
    x_lo = y_lo = z_lo = np.inf
    x_hi = y_hi = z_hi = -np.inf
    nan = False
    ops = _pairwise_plan(n)
    leaves = _leaves(ops)
    sums = np.empty(leaves.shape[0])
    z = points[:, 2]
    for k in range(leaves.shape[0]):
        lo, m = leaves[k, 0], leaves[k, 1]
        sums[k] = _leaf(z, lo, m)
        for i in range(lo, lo + m):
            x, y, h = points[i, 0], points[i, 1], points[i, 2]
            if x < x_lo:
                x_lo = x
            if x > x_hi:
                x_hi = x
            if y < y_lo:
                y_lo = y
            if y > y_hi:
                y_hi = y
            if h < z_lo:
                z_lo = h
            if h > z_hi:
                z_hi = h
            if x != x or y != y or h != h:
                nan = True
    return x_lo, x_hi, y_lo, y_hi, z_lo, z_hi, _fold(ops, sums), nan


@njit(cache=True, nogil=True)
def _cell_points(mask, xs, ys, heights, z0, out):  # pragma: no cover - compiled
    # rebuild.dem_to_points on an axis-aligned grid: (xs[col], ys[row], heights + z0) of every
    # occupied cell, row-major, in one pass, into out (one row per occupied cell).
    rows, cols = mask.shape
    k = 0
    for i in range(rows):
        y = ys[i]
        for j in range(cols):
            if mask[i, j]:
                out[k, 0] = xs[j]
                out[k, 1] = y
                out[k, 2] = heights[i, j] + z0
                k += 1


@njit(cache=True, nogil=True)
def _axis_cells(points, x0, y0, z0, inv_u, inv_v, cols, rows, idx, z):  # pragma: no cover - compiled
    # grid._axis_cells in one pass: floor((x - x0) * inv_u), the same for y, row * cols + col
    # (each rounding as numpy does it, one operation at a time), and z - z0; ok False as soon
    # as a point falls outside the grid (or is NaN).
    # idx, z: the caller's arrays of one value per point (numpy allocates large arrays on huge
    # pages; an allocation in here would fault every 4 kB page in).
    n = points.shape[0]
    for i in range(n):
        u = np.floor((points[i, 0] - x0) * inv_u)
        v = np.floor((points[i, 1] - y0) * inv_v)
        if not (u >= 0.0 and u < cols and v >= 0.0 and v < rows):
            return False
        idx[i] = np.int64(v * cols + u)
        z[i] = points[i, 2] - z0
    return True


@njit(cache=True, nogil=True)
def _cell_sums(idx, z, count, total):  # pragma: no cover - compiled
    # count += np.bincount(idx) and total += np.bincount(idx, weights=z) onto zeros, in one pass
    # and in place: each bin's sum in the points' order, from 0.0, as numpy's loop adds them.
    for i in range(idx.size):
        count[idx[i]] += 1
        total[idx[i]] += z[i]


# numpy's pairwise summation (``np.add.reduce`` of a contiguous float64 array: its identity 0.0
# plus the sum below), so that a sum computed here has numpy's bits: n < 8 values added in turn;
# up to 128 with eight interleaved accumulators; more halved (at a multiple of 8), each half summed
# so, the two added. numba's cache cannot load recursive functions, so the halving is a plan: the
# tree's leaves and additions in post-order (a leaf: its start and length; an addition: -1, -1).
# A sum's kernel makes each leaf's values (a block of at most 128, in cache), adds them with _leaf,
# and _fold adds the leaves' sums up the tree.
PAIRWISE_BLOCK = 128


@njit(cache=True, nogil=True)
def _pairwise_plan(n):  # pragma: no cover - compiled
    # a halved block keeps at least 57 values (half of 129, less 7): fewer than n // 32 + 1 leaves
    ops = np.empty((2 * (n // 32) + 8, 2), dtype=np.int64)
    lo_s, n_s, stage = np.empty(64, np.int64), np.empty(64, np.int64), np.zeros(64, np.int64)
    lo_s[0], n_s[0], top, k = 0, n, 0, 0
    while top >= 0:
        lo, m = lo_s[top], n_s[top]
        if m <= PAIRWISE_BLOCK:
            ops[k, 0], ops[k, 1] = lo, m
            k += 1
            top -= 1
            continue
        half = m // 2
        half -= half % 8
        if stage[top] == 0:  # the left half next
            stage[top] = 1
            lo_s[top + 1], n_s[top + 1], stage[top + 1] = lo, half, 0
            top += 1
        elif stage[top] == 1:  # then the right half
            stage[top] = 2
            lo_s[top + 1], n_s[top + 1], stage[top + 1] = lo + half, m - half, 0
            top += 1
        else:  # both halves summed: add them
            ops[k, 0], ops[k, 1] = -1, -1
            k += 1
            top -= 1
    return ops[:k]


@njit(cache=True, nogil=True)
def _leaves(ops):  # pragma: no cover - compiled
    # the plan's leaves, in order: (start, length) rows
    return ops[ops[:, 0] >= 0]


@njit(cache=True, nogil=True)
def _fold(ops, leaf_sums):  # pragma: no cover - compiled
    # the plan's additions over the sums of its leaves (in the leaves' order), and numpy's identity
    vals, top, k = np.empty(64), -1, 0
    for r in range(ops.shape[0]):
        if ops[r, 0] >= 0:
            top += 1
            vals[top] = leaf_sums[k]
            k += 1
        else:
            top -= 1
            vals[top] = vals[top] + vals[top + 1]
    return 0.0 + vals[0]


@njit(cache=True, nogil=True)
def _leaf(a, lo, n):  # pragma: no cover - compiled
    # (a view and non-negative ranges: LLVM then schedules the eight accumulators well)
    b = a[lo:lo + n]
    if n < 8:
        r = 0.0
        for i in range(n):
            r += b[i]
        return r
    r0, r1, r2, r3, r4, r5, r6, r7 = b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]
    for k in range(1, n // 8):
        i = 8 * k
        r0 += b[i]
        r1 += b[i + 1]
        r2 += b[i + 2]
        r3 += b[i + 3]
        r4 += b[i + 4]
        r5 += b[i + 5]
        r6 += b[i + 6]
        r7 += b[i + 7]
    r = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    for i in range(n - n % 8, n):
        r += b[i]
    return r


@njit(cache=True, nogil=True)
def _leaf_dot(a, b, lo, n):  # pragma: no cover - compiled
    # _leaf of the products a[i] * b[i]
    p, q = a[lo:lo + n], b[lo:lo + n]
    if n < 8:
        r = 0.0
        for i in range(n):
            r += p[i] * q[i]
        return r
    r0, r1, r2, r3 = p[0] * q[0], p[1] * q[1], p[2] * q[2], p[3] * q[3]
    r4, r5, r6, r7 = p[4] * q[4], p[5] * q[5], p[6] * q[6], p[7] * q[7]
    for k in range(1, n // 8):
        i = 8 * k
        r0 += p[i] * q[i]
        r1 += p[i + 1] * q[i + 1]
        r2 += p[i + 2] * q[i + 2]
        r3 += p[i + 3] * q[i + 3]
        r4 += p[i + 4] * q[i + 4]
        r5 += p[i + 5] * q[i + 5]
        r6 += p[i + 6] * q[i + 6]
        r7 += p[i + 7] * q[i + 7]
    r = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    for i in range(n - n % 8, n):
        r += p[i] * q[i]
    return r


@njit(cache=True, nogil=True)
def array_sum(a):  # pragma: no cover - compiled
    # np.sum(a) of a contiguous 1-d float64 array, to the bit
    ops = _pairwise_plan(a.size)
    leaves = _leaves(ops)
    sums = np.empty(leaves.shape[0])
    for k in range(leaves.shape[0]):
        sums[k] = _leaf(a, leaves[k, 0], leaves[k, 1])
    return _fold(ops, sums)


@njit(cache=True, nogil=True)
def array_dot(a, b):  # pragma: no cover - compiled
    # np.sum(np.multiply(a, b)) of two contiguous 1-d float64 arrays of one size, to the bit
    ops = _pairwise_plan(a.size)
    leaves = _leaves(ops)
    sums = np.empty(leaves.shape[0])
    for k in range(leaves.shape[0]):
        sums[k] = _leaf_dot(a, b, leaves[k, 0], leaves[k, 1])
    return _fold(ops, sums)


@njit(cache=True, nogil=True)
def _plane_sums(heights, mask, x, y, z):  # pragma: no cover - compiled
    # fill.fit_plane's sums: the column, row and height of every occupied cell (row-major, into
    # x, y, z: the caller's arrays of one value per occupied cell, and one more), their means, and
    # the five sums of products of the centred values, each as numpy's mean and np.sum add them.
    rows, cols = mask.shape
    k = 0
    for i in range(rows):
        for j in range(cols):  # without branches: a cell is kept by counting it
            x[k] = j
            y[k] = i
            z[k] = heights[i, j]
            k += mask[i, j]
    n = k
    mx, my, mz = array_sum(x[:n]) / n, array_sum(y[:n]) / n, array_sum(z[:n]) / n
    # The products' sums leaf by leaf of one plan: each leaf's values centred (x - mx, as numpy's
    # x -= mx rounds) into blocks in cache, then its five sums as _leaf_dot adds them.
    ops = _pairwise_plan(n)
    leaves = _leaves(ops)
    bx, by, bz = np.empty(PAIRWISE_BLOCK), np.empty(PAIRWISE_BLOCK), np.empty(PAIRWISE_BLOCK)
    sums = np.empty((5, leaves.shape[0]))
    for k in range(leaves.shape[0]):
        lo, m = leaves[k, 0], leaves[k, 1]
        for i in range(m):
            bx[i] = x[lo + i] - mx
            by[i] = y[lo + i] - my
            bz[i] = z[lo + i] - mz
        sums[0, k] = _leaf_dot(bx, bx, 0, m)
        sums[1, k] = _leaf_dot(bx, by, 0, m)
        sums[2, k] = _leaf_dot(by, by, 0, m)
        sums[3, k] = _leaf_dot(bx, bz, 0, m)
        sums[4, k] = _leaf_dot(by, bz, 0, m)
    return (mx, my, mz, _fold(ops, sums[0]), _fold(ops, sums[1]), _fold(ops, sums[2]), _fold(ops, sums[3]),
            _fold(ops, sums[4]))


@njit(cache=True, nogil=True)
def _distance_sums(idx, z, heights, tolerance_sq, far_cells, far_sq):  # pragma: no cover - compiled
    # grid._SpreadCounter.add's figures in one pass: np.sum of sq = (z - heights[idx])**2, its
    # maximum (0 for no points), how many exceed tolerance_sq and np.sum of those (in order), their
    # cells marked in far_cells; far_sq: the caller's scratch of one value per point (the far
    # squares). A block with a far point keeps its far ones and marks their cells without branches
    # (a forest's points are far or near at random); most blocks of ground have none.
    ops = _pairwise_plan(idx.size)
    leaves = _leaves(ops)
    block, sums = np.empty(PAIRWISE_BLOCK), np.empty(leaves.shape[0])
    largest, far = 0.0, 0
    for k in range(leaves.shape[0]):
        lo, n = leaves[k, 0], leaves[k, 1]
        cells, heights_of = idx[lo:lo + n], z[lo:lo + n]
        block_max = 0.0
        for i in range(n):
            d = heights_of[i] - heights[cells[i]]
            s = d * d
            block[i] = s
            block_max = max(block_max, s)
        largest = max(largest, block_max)
        if block_max > tolerance_sq:
            for i in range(n):
                is_far = block[i] > tolerance_sq
                far_sq[far] = block[i]
                far += is_far
                far_cells[cells[i]] |= is_far
        sums[k] = _leaf(block, 0, n)
    return _fold(ops, sums), largest, far, array_sum(far_sq[:far])


@njit(cache=True, nogil=True)
def _masked_errors(heights, ref, mask, out):  # pragma: no cover - compiled
    # (heights - ref)[mask] into out (row-major; the caller's array of one value per set cell, and
    # one more), np.sum of their squares (pairwise, as np.mean(err * err) adds them) and np.abs(err).max()
    rows, cols = mask.shape
    k = 0
    for i in range(rows):
        for j in range(cols):  # without branches: a cell is kept by counting it
            out[k] = heights[i, j] - ref[i, j]
            k += mask[i, j]
    largest = 0.0
    for i in range(k):
        largest = max(largest, abs(out[i]))
    errors = out[:k]
    return array_dot(errors, errors), largest


@njit(cache=True, nogil=True)
def _quantization_sq_error(values, step, offset):  # pragma: no cover - compiled
    # quantizer.choose_step's sq_error: np.sum of (v - q * step)**2 with q = sign(v) * floor(|v| / step +
    # offset) as an int64 (quantizer.quantize, offset = 0.5 - deadzone), pairwise as np.sum adds; and
    # whether every q stayed below 2**63 (else the caller refuses, as quantize does)
    ops = _pairwise_plan(values.size)
    leaves = _leaves(ops)
    block, sums = np.empty(PAIRWISE_BLOCK), np.empty(leaves.shape[0])
    ok = True
    for k in range(leaves.shape[0]):
        lo, n = leaves[k, 0], leaves[k, 1]
        for i in range(n):
            v = values[lo + i]
            q = np.floor(np.abs(v) / step + offset)
            ok &= q < 9.223372036854775808e18
            qi = np.int64(np.sign(v) * q) if q < 9.223372036854775808e18 else np.int64(0)
            e = v - np.float64(qi) * step
            block[i] = e * e
        sums[k] = _leaf(block, 0, n)
    return _fold(ops, sums), ok


@njit(cache=True, nogil=True)
def _weighted_sq_sum(counts, mask, errors, scratch):  # pragma: no cover - compiled
    # np.sum(counts[mask] * errors * errors) (counts: int64, one per cell; errors: one per set cell,
    # row-major), each product as numpy makes it ((count * e) * e), added pairwise as np.sum adds;
    # scratch: the caller's, one value per set cell and one more (the set cells' counts)
    rows, cols = mask.shape
    k = 0
    for i in range(rows):
        for j in range(cols):  # without branches: a cell is kept by counting it
            scratch[k] = counts[i, j]
            k += mask[i, j]
    ops = _pairwise_plan(errors.size)
    leaves = _leaves(ops)
    block, sums = np.empty(PAIRWISE_BLOCK), np.empty(leaves.shape[0])
    for k in range(leaves.shape[0]):
        lo, m = leaves[k, 0], leaves[k, 1]
        for t in range(m):
            e = errors[lo + t]
            block[t] = (scratch[lo + t] * e) * e
        sums[k] = _leaf(block, 0, m)
    return _fold(ops, sums)


@njit(cache=True, nogil=True)
def _add_plane(heights, a, b, c):  # pragma: no cover - compiled
    # heights += fill.plane_values((a, b, c), heights.shape), in place: each cell's (a + b * col) + c * row,
    # as numpy's broadcast evaluates it, then added
    rows, cols = heights.shape
    for i in range(rows):
        ci = c * i
        for j in range(cols):
            heights[i, j] += (a + b * j) + ci


@njit(cache=True, nogil=True)
def _add_residual(heights, mask, q, step):  # pragma: no cover - compiled
    k = 0
    for i in range(heights.size):
        if mask[i]:
            heights[i] += q[k] * step
            k += 1


@njit(cache=True, nogil=True)
def _band_range(radius, angle, width, sectors):  # pragma: no cover - compiled
    lo = np.iinfo(np.int64).max
    hi = np.iinfo(np.int64).min
    for i in range(radius.size):
        band = _band_at(radius[i], angle[i], width, sectors)
        lo = min(lo, band)
        hi = max(hi, band)
    return lo, hi


@njit(cache=True, nogil=True, inline="always")
def _band_at(radius, angle, width, sectors):  # pragma: no cover - compiled
    # As numpy's (radius / width).astype(np.int64): the quotient truncated towards 0.
    ring = np.int64(radius / width)
    if sectors == 1:
        return ring
    return ring * sectors + min(np.int64(angle * sectors), sectors - 1)


@njit(cache=True, nogil=True)
def _band_codes(radius, angle, width, sectors, codes, lo, out):  # pragma: no cover - compiled
    for i in range(radius.size):
        out[i] = codes[_band_at(radius[i], angle[i], width, sectors) - lo]


@njit(cache=True, nogil=True, inline="always")
def _neighbour_at(r, c, up, left, cols):  # pragma: no cover - compiled
    # residual._neighbour for one cell: the flat index of a neighbour under format.md's edge rules,
    # -1 for (0, 0)'s, which is 0
    if r == 0 and c == 0:
        return -1
    if up > 0 and r == 0:
        return c - 1
    if up == 0 and c == 0:
        return (r - 1) * cols
    rr = max(r - up, 0)
    cc = min(max(c - left, 0), cols - 1)
    return rr * cols + cc


@njit(cache=True, nogil=True, inline="always")
def _neighbour_cell(r, c, up, left, cols):  # pragma: no cover - compiled
    # _neighbour_at as (row, column); (-1, -1) for (0, 0)'s, which is 0
    if r == 0 and c == 0:
        return -1, -1
    if up > 0 and r == 0:
        return 0, c - 1
    if up == 0 and c == 0:
        return r - 1, 0
    return max(r - up, 0), min(max(c - left, 0), cols - 1)


#: Wavefronts :func:`_decode_predicted` keeps: a cell's neighbours all lie in the four before its own.
PREDICTED_RING = 5


@njit(cache=True, nogil=True, inline="always")
def _ring_sum(ring, r, c, coeffs, ups, lefts, cols, absolute):  # pragma: no cover - compiled
    # The sum over a cell's neighbours (format.md's edge rules, _neighbour_cell) of coeffs[n] times the
    # neighbour's value in the wavefront ring (its magnitude where ``absolute``)
    total = np.int64(0)
    for n in range(7):
        if coeffs[n]:
            rr, cc = _neighbour_cell(r, c, ups[n], lefts[n], cols)
            if rr >= 0:
                x = ring[(2 * rr + cc) % PREDICTED_RING, rr]
                total += coeffs[n] * (abs(x) if absolute else x)
    return total


@njit(cache=True, nogil=True)
def _decode_predicted(words, kept, weights, codes, lows, csum, near_bounds, alphabets, table_of, values):  # pragma: no cover - compiled
    # RESD kind 5 (residual._decode_predicted): values (rows * cols, zeros) gets every cell's V in
    # wavefront order; the errors of the rebuilt cells are decoded a wavefront at a time, by class
    # (classes ascending, rows ascending within one), with table table_of[class] as
    # encode_table_words reads it, and constriction's decoding as in decode_mask_lines. Returns 0,
    # or 1 when a value reaches 2**31. The neighbours' errors and values are read from rings of
    # the last wavefronts, by row (wavefront 2 r + c): in the grid a wavefront's cells lie a row
    # apart, each of a cell's fourteen reads on another page.
    rows, cols = kept.shape
    ups = (0, 1, 1, 1, 0, 2, 2)
    lefts = (1, 0, 1, -1, 2, 0, -1)
    act_w = (2, 2, 1, 1, 1, 1, 0)
    state, pos = _ans_start(words)
    # Each table's left cumulatives, made once, and where the map is large enough to pay for them,
    # its quantile slots (as _decode_coded_values).
    tables = alphabets.size
    offsets = np.zeros(tables + 1, dtype=np.int64)
    for t in range(tables):
        offsets[t + 1] = offsets[t] + alphabets[t] + 1
    cum = np.empty(offsets[tables], dtype=np.int64)
    for t in range(tables):
        _fill_cumulatives(cum, offsets[t], lows[t], csum, near_bounds[t] + t, near_bounds[t + 1] - near_bounds[t],
                          alphabets[t])
    slotted = rows * cols >= SLOT_MIN_VALUES * tables
    slots = np.empty((tables if slotted else 0, SLOTS + 1), dtype=np.int64)
    for t in range(slots.shape[0]):
        _fill_slots(cum, offsets[t], alphabets[t], slots[t])
    mask24 = np.uint64(TOTAL - 1)
    low = np.uint64(1) << np.uint64(32)
    ring_e = np.zeros((PREDICTED_RING, rows), dtype=np.int64)
    ring_v = np.zeros((PREDICTED_RING, rows), dtype=np.int64)
    longest = min(rows, (cols + 1) // 2 + 1)
    cls = np.empty(longest, dtype=np.int64)
    order = np.empty(longest, dtype=np.int64)
    count = np.zeros(64, dtype=np.int64)
    start = np.zeros(65, dtype=np.int64)
    half = np.int64(1) << np.int64(15)
    limit = np.int64(1) << np.int64(31)
    w0, w1, w2, w3, w4, w5, w6 = weights[0], weights[1], weights[2], weights[3], weights[4], weights[5], weights[6]
    for k in range(2 * (rows - 1) + cols):
        slot = k % PREDICTED_RING
        # The wavefronts before this one: a cell away from the edges (rows 2 on, columns 2 to
        # cols - 2) has its neighbours at fixed places in them, the edge rules left out.
        s1 = (k + PREDICTED_RING - 1) % PREDICTED_RING
        s2 = (k + PREDICTED_RING - 2) % PREDICTED_RING
        s3 = (k + PREDICTED_RING - 3) % PREDICTED_RING
        s4 = (k + PREDICTED_RING - 4) % PREDICTED_RING
        r_lo = max(0, (k - cols + 2) // 2)
        r_hi = min(rows - 1, k // 2)
        m = r_hi - r_lo + 1
        count[:] = 0
        for i in range(m):
            r = r_lo + i
            c = k - 2 * r
            cls[i] = -1
            ring_e[slot, r] = 0
            if kept[r, c]:
                if r >= 2 and 2 <= c <= cols - 2:  # act_w's neighbours, in its order
                    a = (2 * abs(ring_e[s1, r]) + 2 * abs(ring_e[s2, r - 1]) + abs(ring_e[s3, r - 1])
                         + abs(ring_e[s1, r - 1]) + abs(ring_e[s2, r]) + abs(ring_e[s4, r - 2]))
                else:
                    a = _ring_sum(ring_e, r, c, act_w, ups, lefts, cols, True)
                if a == 0:
                    g = 0
                else:
                    b = 0
                    x = a
                    while x:
                        b += 1
                        x >>= 1
                    s = (a >> (b - 2)) & 1 if b >= 2 else 0
                    g = min(63, 2 * b - 1 + s)
                if codes[g]:
                    cls[i] = g
                    count[g] += 1
        start[0] = 0
        for g in range(64):
            start[g + 1] = start[g] + count[g]
        for g in range(64):
            count[g] = start[g]
        for i in range(m):
            if cls[i] >= 0:
                order[count[cls[i]]] = i
                count[cls[i]] += 1
        for j in range(start[64]):
            i = order[j]
            t = table_of[cls[i]]
            base = offsets[t]
            quantile = np.int64(state & mask24)
            if slotted:
                q = quantile >> SLOT_SHIFT
                a, b = slots[t, q], slots[t, q + 1]
            else:
                a, b = 0, alphabets[t] - 1
            while a < b:  # as _decode_coded_values
                mid = (a + b + 1) // 2
                if cum[base + mid] <= quantile:
                    a = mid
                else:
                    b = mid - 1
            state = (state >> np.uint64(PRECISION)) * np.uint64(cum[base + a + 1] - cum[base + a]) \
                + np.uint64(quantile - cum[base + a])
            if state < low and pos >= 0:
                state = (state << np.uint64(32)) | np.uint64(words[pos])
                pos -= 1
            ring_e[slot, r_lo + i] = a - (alphabets[t] - 1) // 2
        for i in range(m):
            r = r_lo + i
            c = k - 2 * r
            if kept[r, c]:
                if r >= 2 and 2 <= c <= cols - 2:  # the neighbours in ups' and lefts' order
                    total = (w0 * ring_v[s1, r] + w1 * ring_v[s2, r - 1] + w2 * ring_v[s3, r - 1]
                             + w3 * ring_v[s1, r - 1] + w4 * ring_v[s2, r] + w5 * ring_v[s4, r - 2]
                             + w6 * ring_v[s3, r - 2])
                else:
                    total = _ring_sum(ring_v, r, c, weights, ups, lefts, cols, False)
                v = ((total + half) >> np.int64(16)) + ring_e[slot, r]
            else:
                rr, cc = _neighbour_cell(r, c, 0, 1, cols)
                v = ring_v[(2 * rr + cc) % PREDICTED_RING, rr] if rr >= 0 else np.int64(0)
            if v >= limit or v <= -limit:
                return 1
            ring_v[slot, r] = v
            values[r * cols + c] = v
    return 0


# --- The kernels, with their numpy twins' signatures ------------------------------------------------


def survey(points: np.ndarray) -> tuple[float, ...]:
    """``grid._survey_values``: x_lo, x_hi, y_lo, y_hi, z_lo, z_hi and the mean height of float64
    points (N, 3+), N > 0, in one pass; declined when a coordinate is not finite (the numpy twin says
    which) or where numpy's reductions could differ (a zero extreme: which of 0.0 and -0.0 is the minimum)."""
    *found, nan = _survey(points)
    extremes = tuple(float(v) for v in found[:6])
    if nan or 0.0 in extremes or not all(math.isfinite(v) for v in extremes):
        return NotImplemented
    return (*extremes, float(found[6]) / points.shape[0])


def axis_cells(points: np.ndarray, grid) -> tuple[np.ndarray, np.ndarray] | None:  # noqa: ANN001 - a dem.Grid
    """``grid._axis_cells``: the flat cell index and the height above ``grid.z0`` of every point of an
    axis-aligned grid, the same arithmetic; None when a point lies outside the grid."""
    if points.dtype != np.float64:
        return NotImplemented
    n = points.shape[0]
    idx, z = np.empty(n, dtype=np.int64), np.empty(n)
    ok = _axis_cells(points, float(grid.x0), float(grid.y0), float(grid.z0), 1.0 / grid.resolution, 1.0 / grid.dy,
                     int(grid.cols), int(grid.rows), idx, z)
    return (idx, z) if ok else None


def cell_sums(idx: np.ndarray, z: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """``grid._cell_sums``: ``np.bincount(idx, minlength=size)`` and ``np.bincount(idx, weights=z,
    minlength=size)`` in one pass, the same bits (each bin sums its points in order, from 0.0)."""
    if idx.shape != z.shape or idx.ndim != 1:  # the loop indexes without checks
        raise ValueError("idx and z must be 1-d arrays of one value per point")
    count, total = np.zeros(size, dtype=np.int64), np.zeros(size)
    _cell_sums(np.ascontiguousarray(idx, dtype=np.int64), np.ascontiguousarray(z, dtype=np.float64), count, total)
    return count, total


def distance_sums(idx: np.ndarray, z: np.ndarray, heights: np.ndarray, tolerance_sq: float,
                  far_cells: np.ndarray | None) -> tuple[float, float, int, float, np.ndarray]:
    """``grid._distance_sums``: with ``sq = (z - heights[idx])**2``, ``sq.sum()``, its maximum (0 for no
    points), how many exceed ``tolerance_sq`` and their sum, each to numpy's bits; the far points'
    cells set True in ``far_cells`` (allocated here when None), which is returned."""
    if far_cells is None:
        far_cells = np.zeros(heights.size, dtype=bool)
    if far_cells.dtype != np.bool_ or not far_cells.flags.c_contiguous or far_cells.size != heights.size:
        raise ValueError("far_cells must be a contiguous bool array of one value per cell, as heights")
    if idx.shape != z.shape or idx.ndim != 1:
        raise ValueError("idx and z must be 1-d arrays of one value per point")
    far_sq = np.empty(idx.size)  # the far squares, in order
    total, largest, far, far_total = _distance_sums(
        np.ascontiguousarray(idx, dtype=np.int64), np.ascontiguousarray(z, dtype=np.float64),
        np.ascontiguousarray(heights, dtype=np.float64).reshape(-1), float(tolerance_sq), far_cells, far_sq)
    return float(total), float(largest), int(far), float(far_total), far_cells


def plane_sums(heights: np.ndarray, mask: np.ndarray) -> tuple[float, ...]:
    """``fill._plane_sums``: the means of the column, row and height of the cells set in ``mask``
    (at least one), and the sums of products xx, xy, yy, xz, yz of the centred values, to the bit."""
    if heights.shape != mask.shape or heights.ndim != 2:
        raise ValueError("heights and mask must be 2-d arrays of one shape")
    mask = np.ascontiguousarray(mask, dtype=np.bool_)
    occupied = int(np.count_nonzero(mask))
    if occupied == 0:
        raise ValueError("mask must have a set cell")
    # One more value each than occupied cells: the loop writes every cell's, keeping the occupied ones.
    x, y, z = np.empty(occupied + 1), np.empty(occupied + 1), np.empty(occupied + 1)
    return tuple(float(v) for v in _plane_sums(np.ascontiguousarray(heights, dtype=np.float64), mask, x, y, z))


def add_plane(heights: np.ndarray, plane: tuple[float, float, float]) -> None:
    """``fill.add_plane`` in one pass, in place, to the bit; declined but for C-contiguous 2-d float64 heights."""
    if heights.dtype != np.float64 or heights.ndim != 2 or not heights.flags.c_contiguous:
        return NotImplemented
    a, b, c = (float(v) for v in plane)
    _add_plane(heights, a, b, c)
    return None


def pull(values: np.ndarray, known: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``fill._pull``: the mean of the known values of each 2x2 block (summed as ``fill._pairs`` sums
    the blocks of a large level, zeros past odd edges) and whether any of the four is known."""
    r, c = values.shape
    mean, any_known = np.zeros(((r + 1) // 2, (c + 1) // 2)), np.zeros(((r + 1) // 2, (c + 1) // 2), dtype=bool)
    _pull_level(np.ascontiguousarray(values, dtype=np.float64), np.ascontiguousarray(known), mean, any_known)
    return mean, any_known


def push(values: np.ndarray, known: np.ndarray, coarse: np.ndarray) -> np.ndarray:
    """``fill._push``: the known cells keep their values, the others take the 2x bilinear upsampling
    of the filled ``coarse`` level."""
    out = np.empty(values.shape)
    _push_level(np.ascontiguousarray(values, dtype=np.float64), np.ascontiguousarray(known),
          np.ascontiguousarray(coarse, dtype=np.float64), out)
    return out


def cell_points(mask: np.ndarray, xs: np.ndarray, ys: np.ndarray, heights: np.ndarray, z0: float) -> np.ndarray:
    """``rebuild._cell_points``: ``(xs[col], ys[row], heights + z0)`` of every cell set in ``mask``,
    row-major; declined for heights other than float64."""
    if heights.dtype != np.float64:
        return NotImplemented
    rows, cols = mask.shape
    if xs.shape != (cols,) or ys.shape != (rows,) or heights.shape != mask.shape:
        raise ValueError("xs, ys and heights must match the mask's columns, rows and shape")
    mask = np.ascontiguousarray(mask, dtype=np.bool_)
    out = np.empty((int(np.count_nonzero(mask)), 3))
    _cell_points(mask, np.ascontiguousarray(xs, dtype=np.float64), np.ascontiguousarray(ys, dtype=np.float64),
                 np.ascontiguousarray(heights), float(z0), out)
    return out


def mask_contexts(lines: np.ndarray, stripe: int) -> np.ndarray:
    """``occupancy._contexts`` of the line-major mask ``lines`` (uint8, 0/1), in one pass."""
    lines = np.ascontiguousarray(lines, dtype=np.uint8)
    if lines.ndim != 2 or stripe < 1:
        raise ValueError("lines must be a 2-d mask and stripe at least 1")
    ctx = np.empty_like(lines)
    _mask_contexts(lines, int(stripe), ctx)
    return ctx


def encode_mask_words(lines: np.ndarray, ctx: np.ndarray, stripe: int, first_seed: bool, *,
                      prior_ones: np.ndarray, prior_total: float) -> np.ndarray:
    """``occupancy._context_words``: the context coder's ANS words of the line-major mask ``lines``
    (uint8, 0/1) with the contexts ``ctx`` (``first_seed``: kind 3, line 0 of the first stripe not coded)."""
    lines = np.ascontiguousarray(lines, dtype=np.uint8)
    words = np.empty(lines.size + 4, dtype=np.uint32)
    return _encode_mask_words(lines, np.ascontiguousarray(ctx), int(stripe), prior_ones, float(prior_total),
                              int(first_seed), words)


def decode_mask_lines(words: np.ndarray, lines: np.ndarray, n_lines: int, first_seed: bool, *,
                      prior_ones: np.ndarray, prior_total: float) -> np.ndarray:
    """``occupancy._context_lines``: the mask ``lines`` (``(n_stripes, stripe, width)`` uint8, the seed
    lines set) decoded from ``words`` in place, as ``(n_lines, width)`` booleans. Any words decode to
    some mask, as they do with constriction (which decodes on from its state alone past the last
    word); the caller refuses those constriction refuses (a last word of 0)."""
    # The loop writes into lines without bounds checks: its shape must be what it assumes.
    if lines.dtype != np.uint8 or lines.ndim != 3 or not lines.flags.c_contiguous:
        raise ValueError("lines must be a C-contiguous 3-d uint8 array")
    n_stripes, stripe, width = lines.shape
    if stripe < 1 or n_lines < 0 or n_stripes * stripe < n_lines:
        raise ValueError("lines must hold every line of the stripes")
    flat = lines.reshape(-1, width)
    _decode_mask_lines(np.ascontiguousarray(words, dtype=np.uint32), flat, int(n_lines), int(stripe),
                       np.ascontiguousarray(prior_ones, dtype=np.float64), float(prior_total), int(first_seed))
    return flat[:n_lines].view(bool)


@njit(cache=True, nogil=True)
def _packed_cumulative(weights, starts, max_abs, lows, csum, near_bounds):  # pragma: no cover - compiled
    # geometric._table_frequencies, then its running sums from 0, for each table k: its weights
    # (|q| = 0, 1, ...) weights[starts[k]:starts[k + 1]], its alphabet 2 * max_abs[k] + 1, its
    # frequencies at csum[near_bounds[k] + k + 1:], each 1 + w * free // total (integers, as numpy's),
    # the remainder to q = 0
    for k in range(max_abs.size):
        w0 = starts[k]
        known = starts[k + 1] - w0
        n = 2 * max_abs[k] + 1
        free = TOTAL - n
        total = np.int64(0)
        for i in range(known):
            total += weights[w0 + i]
        total = 2 * total - weights[w0]  # both sides of q = 0
        at = near_bounds[k] + k
        size = 2 * known - 1
        spent = np.int64(0)
        for i in range(size):
            w = weights[w0 + abs(i - (known - 1))]
            f = 1 + w * free // total
            csum[at + 1 + i] = f
            spent += f
        csum[at + known] += TOTAL - spent - (n - size)
        csum[at] = 0
        for i in range(size):
            csum[at + 1 + i] += csum[at + i]
        lows[k] = max_abs[k] - known + 1


def packed_cumulative(weights: list[np.ndarray], max_abs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The table coders' tables: for table k, the integer weights ``weights[k]`` of |q| = 0, 1, ...
    (``geometric.magnitude_weights``, cut to ``max_abs[k] + 1``) and its magnitude bound ``max_abs[k]``,
    made into ``geometric.table_frequencies``' frequencies in one pass. Returned as each table's
    lowest symbol above the floor of 1, the tables' running sums from 0 end to end, and where each
    table's frequencies start (and the end): what the coders below read."""
    max_abs = np.ascontiguousarray(max_abs, dtype=np.int64)
    starts = np.zeros(len(weights) + 1, dtype=np.int64)
    np.cumsum([w.size for w in weights], out=starts[1:])
    near_bounds = np.zeros(len(weights) + 1, dtype=np.int64)
    np.cumsum(2 * np.diff(starts) - 1, out=near_bounds[1:])
    csum = np.empty(int(near_bounds[-1]) + len(weights), dtype=np.int64)
    lows = np.empty(len(weights), dtype=np.int64)
    flat = np.concatenate(weights).astype(np.int64, copy=False) if weights else np.zeros(0, np.int64)
    _packed_cumulative(flat, starts, max_abs, lows, csum, near_bounds)
    return lows, csum, near_bounds


def encode_table_words(symbols: np.ndarray, bounds: np.ndarray, tables: tuple[np.ndarray, np.ndarray, np.ndarray],
                       n: int | np.ndarray, table_of: np.ndarray | None = None) -> np.ndarray:
    """The ANS words of groups of symbols 0..n-1 (group g: ``symbols[bounds[g]:bounds[g + 1]]``), each
    with its table (:func:`packed_cumulative`'s: a floor of 1 of 2**24 but the frequencies from each
    table's lowest symbol; table ``table_of[g]``, else g), pushed as constriction's coder pushes them:
    the last group first, each group last symbol first. ``n``: one alphabet size for all the tables,
    or one for each."""
    lows, csum, near_bounds = tables
    if table_of is None:
        table_of = np.arange(lows.size, dtype=np.int64)
    alphabets = np.broadcast_to(np.asarray(n, dtype=np.int64), (lows.size,))
    return _encode_table_words(np.ascontiguousarray(symbols, dtype=np.int64), np.asarray(bounds, np.int64),
                               np.asarray(table_of, dtype=np.int64), lows, csum, near_bounds,
                               np.ascontiguousarray(alphabets))


@njit(cache=True, nogil=True)
def _dequantize_into(out, where, q, step):  # pragma: no cover - compiled
    for i in range(q.size):
        out[where[i]] = float(q[i]) * step


def dequantize_into(shape: tuple[int, int], where: np.ndarray, q: np.ndarray, step: float) -> np.ndarray:
    """``quantizer.dequantize_into`` in one pass (the same float operations: the integer made a
    float, times the step); ``where`` comes from the layout (no position is checked here), so it
    declines one that is not as long as ``q``."""
    if q.dtype != np.int64 or where.dtype != np.int64 or where.shape != q.shape or q.ndim != 1:
        return NotImplemented
    out = np.zeros(shape)
    _dequantize_into(out.reshape(-1), where, q, float(step))
    return out


@njit(cache=True, nogil=True)
def _kept_neighbours(flat, kept, ups, lefts, cols, stride, out):  # pragma: no cover - compiled
    k = 0
    for cell in range(kept.size):
        if kept[cell]:
            if k % stride == 0:
                r, c = cell // cols, cell % cols
                for t in range(ups.size):
                    i = _neighbour_at(r, c, ups[t], lefts[t], cols)
                    out[t, k // stride] = 0 if i < 0 else flat[i]
            k += 1


def kept_neighbours(grid: np.ndarray, kept: np.ndarray, offsets: tuple[tuple[int, int], ...],
                    stride: int = 1) -> np.ndarray:
    """``residual._kept_neighbours`` in one pass over the kept cells, each neighbour read where it
    is (no shifted copy of the grid per neighbour)."""
    if grid.dtype != np.int64 or kept.dtype != np.bool_ or grid.shape != kept.shape or grid.ndim != 2 or stride < 1:
        return NotImplemented
    ups = np.array([up for up, _ in offsets], dtype=np.int64)
    lefts = np.array([left for _, left in offsets], dtype=np.int64)
    out = np.empty((len(offsets), -(-int(np.count_nonzero(kept)) // stride)), dtype=np.int64)
    _kept_neighbours(np.ascontiguousarray(grid).reshape(-1), np.ascontiguousarray(kept).reshape(-1), ups, lefts,
                     grid.shape[1], stride, out)
    return out


@njit(cache=True, nogil=True)
def _filled(q, kept, rows, cols, grid):  # pragma: no cover - compiled
    # residual._filled: q at the kept cells (row-major), at the others their W; column 0's W is the
    # cell above, and (0, 0)'s a zero.
    k = 0
    for r in range(rows):
        base = r * cols
        for c in range(cols):
            cell = base + c
            if kept[cell]:
                grid[cell] = q[k]
                k += 1
            elif c:
                grid[cell] = grid[cell - 1]
            else:
                grid[cell] = grid[cell - cols] if r else 0


def filled(q: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """``residual._filled`` in one pass over the grid."""
    if q.dtype != np.int64 or kept.dtype != np.bool_ or kept.ndim != 2 or q.ndim != 1 \
            or q.size != np.count_nonzero(kept):
        return NotImplemented
    rows, cols = kept.shape
    grid = np.empty(kept.shape, dtype=np.int64)
    _filled(q, np.ascontiguousarray(kept).reshape(-1), rows, cols, grid.reshape(-1))
    return grid


@njit(cache=True, nogil=True)
def _fit_sums(flat, kept, rows, cols, stride, limit, sums):  # pragma: no cover - compiled
    # residual._fit_sums: int64 sums of products of the differences from W (six neighbours, then the
    # cell), every stride-th kept cell whose differences are all within limit (each product below
    # 2**30, so 2**33 cells fit in int64: exact, as numpy's float64 blocks).
    ups = (0, 1, 1, 1, 0, 2, 2)
    lefts = (1, 0, 1, -1, 2, 0, -1)
    d = np.empty(7, dtype=np.int64)
    k = -1
    for r in range(rows):
        base = r * cols
        for c in range(cols):
            cell = base + c
            if not kept[cell]:
                continue
            k += 1
            if k % stride:
                continue
            if r >= 2 and 2 <= c <= cols - 2:  # the interior: neighbours by offset
                w = flat[cell - 1]
                d[0] = flat[cell - cols] - w
                d[1] = flat[cell - cols - 1] - w
                d[2] = flat[cell - cols + 1] - w
                d[3] = flat[cell - 2] - w
                d[4] = flat[cell - 2 * cols] - w
                d[5] = flat[cell - 2 * cols + 1] - w
            else:
                at = _neighbour_at(r, c, 0, 1, cols)
                w = flat[at] if at >= 0 else 0
                for n in range(1, 7):
                    at = _neighbour_at(r, c, ups[n], lefts[n], cols)
                    d[n - 1] = (flat[at] if at >= 0 else 0) - w
            d[6] = flat[cell] - w
            usable = True
            for i in range(7):
                if abs(d[i]) > limit:
                    usable = False
            if not usable:
                continue
            for i in range(7):
                for j in range(i, 7):
                    sums[i, j] += d[i] * d[j]
    for i in range(7):
        for j in range(i):
            sums[i, j] = sums[j, i]


def fit_sums(grid: np.ndarray, kept: np.ndarray, stride: int, *, offsets: tuple, fit_limit: int) -> np.ndarray:
    """``residual._fit_sums`` in one pass over the kept cells, each neighbour read where it is."""
    if (offsets != ((0, 1), (1, 0), (1, 1), (1, -1), (0, 2), (2, 0), (2, -1)) or fit_limit > 1 << 15
            or grid.dtype != np.int64 or kept.dtype != np.bool_ or grid.shape != kept.shape or grid.ndim != 2
            or stride < 1 or np.count_nonzero(kept) > 1 << 32):
        return NotImplemented
    rows, cols = grid.shape
    sums = np.zeros((7, 7), dtype=np.int64)
    _fit_sums(np.ascontiguousarray(grid).reshape(-1), np.ascontiguousarray(kept).reshape(-1), rows, cols, stride,
              fit_limit, sums)
    return sums


@njit(cache=True, nogil=True)
def _median_errors(flat, kept, rows, cols, e):  # pragma: no cover - compiled
    # residual._median_errors: each kept cell's value less LOCO-I's median of its W, N and NW
    # (format.md's edge rules, _neighbour_at), row-major.
    k = 0
    for r in range(rows):
        base = r * cols
        for c in range(cols):
            cell = base + c
            if not kept[cell]:
                continue
            if r >= 1 and c >= 1:
                w, n, nw = flat[cell - 1], flat[cell - cols], flat[cell - cols - 1]
            else:
                at = _neighbour_at(r, c, 0, 1, cols)
                w = flat[at] if at >= 0 else 0
                at = _neighbour_at(r, c, 1, 0, cols)
                n = flat[at] if at >= 0 else 0
                at = _neighbour_at(r, c, 1, 1, cols)
                nw = flat[at] if at >= 0 else 0
            lo, hi = min(w, n), max(w, n)
            e[k] = flat[cell] - min(max(w + n - nw, lo), hi)
            k += 1


def median_errors(grid: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """``residual._median_errors`` in one pass, each neighbour read where it is."""
    if grid.dtype != np.int64 or kept.dtype != np.bool_ or grid.shape != kept.shape or grid.ndim != 2:
        return NotImplemented
    rows, cols = grid.shape
    where = np.ascontiguousarray(kept).reshape(-1)
    e = np.empty(int(np.count_nonzero(where)), dtype=np.int64)
    _median_errors(np.ascontiguousarray(grid).reshape(-1), where, rows, cols, e)
    return e


@njit(cache=True, nogil=True)
def _predicted_errors(flat, kept, weights, rows, cols, e, magnitude):  # pragma: no cover - compiled
    # residual._errors_and_classes' first half: each kept cell's prediction error (row-major, into
    # e) and |error| at its cell (magnitude, zeros elsewhere); the interior's neighbours by offset,
    # the edges' under format.md's rules (_neighbour_at). Integer arithmetic: the numpy twin's bits.
    ups = (0, 1, 1, 1, 0, 2, 2)
    lefts = (1, 0, 1, -1, 2, 0, -1)
    w0, w1, w2, w3, w4, w5, w6 = weights[0], weights[1], weights[2], weights[3], weights[4], weights[5], weights[6]
    half = np.int64(1) << np.int64(15)
    k = 0
    for r in range(rows):
        base = r * cols
        for c in range(cols):
            cell = base + c
            if not kept[cell]:
                continue
            if r >= 2 and 2 <= c <= cols - 2:
                total = (w0 * flat[cell - 1] + w1 * flat[cell - cols] + w2 * flat[cell - cols - 1]
                         + w3 * flat[cell - cols + 1] + w4 * flat[cell - 2] + w5 * flat[cell - 2 * cols]
                         + w6 * flat[cell - 2 * cols + 1])
            else:
                total = np.int64(0)
                for n in range(7):
                    at = _neighbour_at(r, c, ups[n], lefts[n], cols)
                    if at >= 0:
                        total += weights[n] * flat[at]
            err = flat[cell] - ((total + half) >> np.int64(16))
            e[k] = err
            magnitude[cell] = abs(err)
            k += 1


@njit(cache=True, nogil=True)
def _activity_classes(magnitude, kept, rows, cols, classes):  # pragma: no cover - compiled
    # residual._errors_and_classes' second half: each kept cell's class (row-major) from its
    # neighbours' |errors| (residual.ACTIVITY_WEIGHTS), as residual._classes.
    ups = (0, 1, 1, 1, 0, 2)
    lefts = (1, 0, 1, -1, 2, 0)
    act_w = (2, 2, 1, 1, 1, 1)
    k = 0
    for r in range(rows):
        base = r * cols
        for c in range(cols):
            cell = base + c
            if not kept[cell]:
                continue
            if r >= 2 and 2 <= c <= cols - 2:
                a = (2 * magnitude[cell - 1] + 2 * magnitude[cell - cols] + magnitude[cell - cols - 1]
                     + magnitude[cell - cols + 1] + magnitude[cell - 2] + magnitude[cell - 2 * cols])
            else:
                a = np.int64(0)
                for n in range(6):
                    at = _neighbour_at(r, c, ups[n], lefts[n], cols)
                    if at >= 0:
                        a += act_w[n] * magnitude[at]
            if a == 0:
                g = 0
            else:
                b = 0
                x = a
                while x:
                    b += 1
                    x >>= 1
                s = (a >> (b - 2)) & 1 if b >= 2 else 0
                g = min(63, 2 * b - 1 + s)
            classes[k] = g
            k += 1


@njit(cache=True, nogil=True)
def _coding_order(kept, classes, codes, rows, cols, order, bounds, group_classes):  # pragma: no cover - compiled
    # residual._coding_order: the coded kept cells (code of their class > 0) by wavefront, then
    # class, then row, as indices of the kept cells (row-major); each (wavefront, class) group's
    # start in bounds and class in group_classes. Returns the number of groups.
    at = np.empty(rows * cols, dtype=np.int64)
    k = 0
    for cell in range(rows * cols):
        if kept[cell]:
            at[cell] = k
            k += 1
        else:
            at[cell] = -1
    count = np.zeros(64, dtype=np.int64)
    n = 0
    groups = 0
    for wave in range(2 * (rows - 1) + cols):
        r_lo = max(0, (wave - cols + 2) // 2)
        r_hi = min(rows - 1, wave // 2)
        count[:] = 0
        for r in range(r_lo, r_hi + 1):
            p = at[r * cols + wave - 2 * r]
            if p >= 0 and codes[classes[p]]:
                count[classes[p]] += 1
        start = n
        for g in range(64):
            if count[g]:
                bounds[groups] = start
                group_classes[groups] = g
                groups += 1
                c = count[g]
                count[g] = start
                start += c
        for r in range(r_lo, r_hi + 1):
            p = at[r * cols + wave - 2 * r]
            if p >= 0 and codes[classes[p]]:
                order[count[classes[p]]] = p
                count[classes[p]] += 1
        n = start
    bounds[groups] = n
    return groups


def coding_order(kept: np.ndarray, classes: np.ndarray, codes: np.ndarray, *, classes_count: int
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``residual._coding_order`` in one counting sort per wavefront (no sorts of the whole map)."""
    if (classes_count != 64 or kept.dtype != np.bool_ or kept.ndim != 2 or classes.dtype != np.int64
            or codes.shape != (64,)):
        return NotImplemented
    rows, cols = kept.shape
    coded = int(np.count_nonzero(codes[classes]))
    order = np.empty(coded, dtype=np.int64)
    bounds = np.empty(coded + 1, dtype=np.int64)
    group_classes = np.empty(coded, dtype=np.int64)
    groups = _coding_order(np.ascontiguousarray(kept).reshape(-1), classes, codes.astype(np.int64), rows, cols,
                           order, bounds, group_classes)
    return order, bounds[:groups + 1].copy(), group_classes[:groups].copy()


def errors_and_classes(grid: np.ndarray, kept: np.ndarray, weights: np.ndarray, *, offsets: tuple, activity: tuple,
                       classes: int, weight_bits: int) -> tuple[np.ndarray, np.ndarray]:
    """``residual._errors_and_classes`` in two passes over the grid, each neighbour read where it is
    (no neighbour arrays); declines any layout constant other than the ones written in here."""
    if (offsets != ((0, 1), (1, 0), (1, 1), (1, -1), (0, 2), (2, 0), (2, -1)) or activity != (2, 2, 1, 1, 1, 1, 0)
            or classes != 64 or weight_bits != 16 or grid.dtype != np.int64 or kept.dtype != np.bool_
            or grid.shape != kept.shape or grid.ndim != 2 or weights.shape != (7,)):
        return NotImplemented
    rows, cols = grid.shape
    flat = np.ascontiguousarray(grid).reshape(-1)
    where = np.ascontiguousarray(kept).reshape(-1)
    n = int(np.count_nonzero(where))
    e = np.empty(n, dtype=np.int64)
    magnitude = np.zeros(rows * cols, dtype=np.int64)
    _predicted_errors(flat, where, weights.astype(np.int64), rows, cols, e, magnitude)
    out = np.empty(n, dtype=np.int64)
    _activity_classes(magnitude, where, rows, cols, out)
    return e, out


@njit(cache=True, nogil=True)
def _signed_at(picture, kept, sizes, negative, out):  # pragma: no cover - compiled
    k = j = 0
    for cell in range(kept.size):
        if kept[cell]:
            if picture[cell]:
                out[k] = -(sizes[j] + 1) if negative[j] else sizes[j] + 1
                j += 1
            else:
                out[k] = 0
            k += 1


def signed_at(picture: np.ndarray, kept: np.ndarray, sizes: np.ndarray, negative: np.ndarray) -> np.ndarray:
    """``residual._signed_at`` in one pass over the cells; declines a picture that sets a cell
    ``kept`` does not, or sizes not one per set cell (the caller has checked both)."""
    if (picture.shape != kept.shape or picture.dtype != np.bool_ or kept.dtype != np.bool_
            or sizes.dtype != np.int64 or negative.size < sizes.size):
        return NotImplemented
    flat_p, flat_k = np.ascontiguousarray(picture).reshape(-1), np.ascontiguousarray(kept).reshape(-1)
    if sizes.size != int(np.count_nonzero(flat_p)):
        return NotImplemented
    out = np.empty(int(np.count_nonzero(flat_k)), dtype=np.int64)
    _signed_at(flat_p, flat_k, sizes, np.ascontiguousarray(negative, dtype=np.uint8), out)
    return out


def add_residual(heights: np.ndarray, mask: np.ndarray, q: np.ndarray, step: float) -> None:
    """``heights[mask] += q * step`` in one pass over the cells (the same float operations:
    the integer made a float, times the step, added)."""
    if (heights.dtype != np.float64 or not heights.flags.c_contiguous or mask.dtype != np.bool_
            or q.dtype != np.int64 or heights.shape != mask.shape or q.size != int(np.count_nonzero(mask))):
        return NotImplemented
    _add_residual(heights.reshape(-1), np.ascontiguousarray(mask).reshape(-1), q, float(step))
    return None


@njit(cache=True, nogil=True)
def _band_totals(bands, magnitudes, count, total, lo):  # pragma: no cover - compiled
    # np.bincount's loops, both at once: in the values' order, so the same sums to the bit
    for i in range(bands.size):
        k = bands[i] - lo
        count[k] += 1
        total[k] += magnitudes[i]


@njit(cache=True, nogil=True)
def _int_range(values):  # pragma: no cover - compiled
    lo = values[0]
    hi = values[0]
    for i in range(1, values.size):
        lo = min(lo, values[i])
        hi = max(hi, values[i])
    return lo, hi


def band_totals(bands: np.ndarray, magnitudes: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """``geometric._band_totals`` in two passes, without the bands' shifted copy and the two
    bincounts' own passes; declines an empty chunk or other dtypes."""
    if (bands.size == 0 or bands.dtype != np.int64 or magnitudes.dtype != np.float64
            or magnitudes.shape != bands.shape):
        return NotImplemented
    bands, magnitudes = np.ascontiguousarray(bands), np.ascontiguousarray(magnitudes)
    lo, hi = _int_range(bands)
    count = np.zeros(int(hi - lo) + 1, dtype=np.intp)
    total = np.zeros(int(hi - lo) + 1)
    _band_totals(bands, magnitudes, count, total, lo)
    return int(lo), count, total


@njit(cache=True, nogil=True)
def _layout_totals(radius, angle, width, sectors, magnitudes, count, total, lo):  # pragma: no cover - compiled
    # _band_totals with each value's band worked out where it is added (coding.band_ids' arithmetic)
    for i in range(radius.size):
        k = _band_at(radius[i], angle[i], width, sectors) - lo
        count[k] += 1
        total[k] += magnitudes[i]


def layout_totals(radius: np.ndarray, angle: np.ndarray, width: float, sectors: int, magnitudes: np.ndarray
                  ) -> tuple[int, np.ndarray, np.ndarray]:
    """``coding._layout_totals`` in two passes, without the bands' arrays; declines an empty chunk
    or other dtypes."""
    if (radius.size == 0 or radius.dtype != np.float64 or angle.dtype != np.float64
            or magnitudes.dtype != np.float64 or not radius.shape == angle.shape == magnitudes.shape):
        return NotImplemented
    radius, angle, magnitudes = (np.ascontiguousarray(a) for a in (radius, angle, magnitudes))
    lo, hi = _band_range(radius, angle, float(width), int(sectors))
    count = np.zeros(int(hi - lo) + 1, dtype=np.intp)
    total = np.zeros(int(hi - lo) + 1)
    _layout_totals(radius, angle, float(width), int(sectors), magnitudes, count, total, lo)
    return int(lo), count, total


def band_range(radius: np.ndarray, angle: np.ndarray, width: float, sectors: int) -> tuple[int, int, None]:
    """The lowest and highest band (``coding.band_ids``) of a chunk's values, in one pass without
    the bands' array (``coding._band_codes`` finds each again); declines an empty or non-float chunk."""
    if radius.size == 0 or radius.dtype != np.float64 or angle.dtype != np.float64:
        return NotImplemented
    lo, hi = _band_range(radius, angle, float(width), int(sectors))
    return int(lo), int(hi), None


def band_codes(radius: np.ndarray, angle: np.ndarray, width: float, sectors: int, codes: np.ndarray, lo: int,
               bands: np.ndarray | None) -> np.ndarray:
    """Each value's band scale code, ``codes[band - lo]``, in one pass (uint8)."""
    if bands is not None or radius.dtype != np.float64 or angle.dtype != np.float64 or codes.dtype != np.uint8:
        return NotImplemented
    out = np.empty(radius.size, dtype=np.uint8)
    _band_codes(np.ascontiguousarray(radius), np.ascontiguousarray(angle), float(width), int(sectors),
                codes, int(lo), out)
    return out


@njit(cache=True, nogil=True)
def _code_counts(codes, out):  # pragma: no cover - compiled
    for i in range(codes.size):
        out[codes[i]] += 1


def code_counts(codes: np.ndarray) -> np.ndarray:
    """``np.bincount(codes, minlength=256)`` of uint8 scale codes in one pass (numpy's widens every
    code to an intp first: a third of a table decode's time)."""
    out = np.zeros(256, dtype=np.int64)
    _code_counts(np.ascontiguousarray(codes, dtype=np.uint8), out)
    return out


def decode_coded_values(words: np.ndarray, per_value: np.ndarray, present: np.ndarray,
                        tables: tuple[np.ndarray, np.ndarray, np.ndarray], n: int) -> np.ndarray:
    """The values of an ANS chunk: each value's scale code ``per_value`` (uint8; 0: the value is 0),
    the nonzero codes ``present`` among them, ascending, with their tables (as
    :func:`encode_table_words` takes them) of one alphabet of ``n`` symbols. The values of one code are
    decoded in turn, codes ascending, as :func:`encode_table_words` pushes them."""
    lows, csum, near_bounds = tables
    table_of = np.zeros(256, dtype=np.int64)
    table_of[np.asarray(present, dtype=np.int64)] = np.arange(len(present))
    out = np.zeros(per_value.size, dtype=np.int64)
    _decode_coded_values(np.ascontiguousarray(words, dtype=np.uint32), np.ascontiguousarray(per_value, dtype=np.uint8),
                         table_of, lows, csum, near_bounds, np.full(lows.size, n, dtype=np.int64), out)
    return out


def decode_predicted(words: np.ndarray, kept: np.ndarray, weights: np.ndarray, codes: np.ndarray,
                     tables: tuple[np.ndarray, np.ndarray, np.ndarray], alphabets: np.ndarray) -> np.ndarray | None:
    """``RESD`` kind 5's values V on the whole grid, in one pass; None when one reaches 2**31.
    ``tables`` (:func:`packed_cumulative`), ``alphabets``: those of the classes of nonzero ``codes``, in class order."""
    lows, csum, near_bounds = tables
    table_of = np.full(len(codes), -1, dtype=np.int64)
    table_of[np.flatnonzero(codes)] = np.arange(np.count_nonzero(codes))
    values = np.zeros(kept.size, dtype=np.int64)
    status = _decode_predicted(
        np.ascontiguousarray(words, dtype=np.uint32), np.ascontiguousarray(kept, dtype=np.bool_),
        np.ascontiguousarray(weights, dtype=np.int64), np.ascontiguousarray(codes, dtype=np.uint8),
        lows, csum, near_bounds, np.ascontiguousarray(alphabets, dtype=np.int64), table_of, values)
    return None if status else values


def masked_errors(heights: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, float, float]:
    """``analysis._trial_errors``: ``err = (heights - ref)[mask]``, its RMS and largest magnitude, to
    numpy's bits, in two passes; declined where numpy's figures could differ (no set cell, a NaN)."""
    if not (heights.shape == ref.shape == mask.shape and heights.ndim == 2):
        raise ValueError("heights, ref and mask must be 2-d arrays of one shape")
    mask = np.ascontiguousarray(mask, dtype=np.bool_)
    n = int(np.count_nonzero(mask))
    # Every cell's error is written at the count of set cells before it: one more than the set cells.
    out = np.empty(n + 1)
    sq_sum, largest = _masked_errors(np.ascontiguousarray(heights, dtype=np.float64),
                                     np.ascontiguousarray(ref, dtype=np.float64), mask, out)
    if n == 0 or not np.isfinite(sq_sum):
        return NotImplemented
    return out[:n], float(np.sqrt(sq_sum / n)), float(largest)


def quantization_sq_error(values: np.ndarray, step: float, deadzone: float) -> float:
    """``quantizer.quantization_sq_error``: the sum of squares of ``values - dequantize(quantize(values,
    step, deadzone), step)`` to numpy's bits; declined where ``quantize`` would refuse (an integer
    past 2**63), so the numpy twin raises as it does."""
    total, ok = _quantization_sq_error(np.ascontiguousarray(values, dtype=np.float64), float(step),
                                       0.5 - float(deadzone))
    return float(total) if ok else NotImplemented


def weighted_sq_sum(counts: np.ndarray, mask: np.ndarray, errors: np.ndarray) -> float:
    """``sums.weighted_sq_sum``: ``np.sum(counts[mask] * errors * errors)`` to numpy's bits, without the
    products' arrays; declined for counts other than int64."""
    if counts.dtype != np.int64:
        return NotImplemented
    mask = np.ascontiguousarray(mask, dtype=np.bool_)
    if counts.shape != mask.shape or counts.ndim != 2 or errors.ndim != 1:
        raise ValueError("counts and mask must be 2-d arrays of one shape, errors 1-d")
    if errors.size != int(np.count_nonzero(mask)):  # the loop walks the set cells without bounds checks
        raise ValueError("errors must hold one value per set cell of mask")
    scratch = np.empty(errors.size + 1)  # the set cells' counts
    return float(_weighted_sq_sum(np.ascontiguousarray(counts), mask, np.ascontiguousarray(errors, dtype=np.float64),
                                  scratch))

