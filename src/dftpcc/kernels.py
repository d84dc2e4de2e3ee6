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
are those of the numpy path, bit for bit (``tests/test_kernels.py``).

Loading numba takes a fresh process about 0.3 s, more than a small map's
whole compression, so the kernels are used only once something asks for
them: :func:`load` (a :class:`~dftpcc.mapbuilder.MapBuilder` does, as it
lives for a whole drive) or the environment variable ``DFTPCC_JIT=1``.
``DFTPCC_JIT=0`` keeps the numpy path even then. Without numba installed
(the ``fast`` extra) everything runs on numpy, with the same files.
Compiled code is cached beside this module (numba's ``cache=True``), so only
the first run on a machine compiles.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

__all__ = ["load", "enabled", "encode_mask_words", "encode_table_words"]

#: The mask coder's prior (see :mod:`dftpcc.occupancy`); passed in, not imported, so imports run one way.
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
            _state["module"] = _compile()
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


def encode_mask_words(lines: np.ndarray, ctx: np.ndarray, stripe: int, prior_ones: np.ndarray,
                      prior_total: float) -> np.ndarray:
    """The context coder's ANS words of the line-major mask ``lines`` (uint8, 0/1) with the contexts
    ``ctx`` (see ``occupancy._contexts``): what ``occupancy._encode_context`` gets from constriction."""
    module = _state["module"]
    return module.encode_mask_words(np.ascontiguousarray(lines, dtype=np.uint8), np.ascontiguousarray(ctx),
                                    int(stripe), prior_ones, float(prior_total))


def encode_table_words(symbols: list[np.ndarray], lows: list[int], nears: list[np.ndarray], n: int) -> np.ndarray:
    """The ANS words of groups of symbols 0..n-1, each group with its table (``coding._table_frequencies``:
    a floor of 1 of 2**24 but ``nears[g]`` from symbol ``lows[g]``), pushed as ``coding._encode_ans_with``
    pushes them to constriction: the last group first, each group last symbol first."""
    module = _state["module"]
    bounds = np.zeros(len(symbols) + 1, dtype=np.int64)
    bounds[1:] = np.cumsum([s.size for s in symbols])
    near_bounds = np.zeros(len(nears) + 1, dtype=np.int64)
    near_bounds[1:] = np.cumsum([a.size for a in nears])
    # Running sums of each table's frequencies, from 0: the cumulative frequency below a symbol.
    csum = np.concatenate([np.concatenate(([0], np.cumsum(a))) for a in nears]) if nears else np.zeros(0, np.int64)
    return module.encode_table_words(
        np.concatenate(symbols).astype(np.int64) if symbols else np.zeros(0, np.int64), bounds,
        np.asarray(lows, dtype=np.int64), csum.astype(np.int64), near_bounds, int(n))


def _compile():
    import numba  # noqa: F401 - ImportError: the numpy path

    from numba import njit

    precision = 24
    total = 1 << precision
    free = float(total - 2)

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

    @njit(cache=True, nogil=True)
    def _encode(lines, ctx, stripe, prior_ones, prior_total):  # pragma: no cover - compiled
        n, w = lines.shape
        n_stripes = (n + stripe - 1) // stripe
        # Per step, per context: the integer probability of a 0 (constriction's quantization).
        zero_prob = np.empty((stripe, 256), dtype=np.int64)
        ones = np.zeros(256, dtype=np.int64)
        seen = np.zeros(256, dtype=np.int64)
        for s in range(stripe):
            for c in range(256):
                p = (ones[c] + prior_ones[c]) / (seen[c] + prior_total)
                q0 = 1.0 - p
                zero_prob[s, c] = np.int64(q0 * (free / (q0 + p))) + 1
            k_end = 1 if s == 0 else n_stripes
            for k in range(k_end):
                line = k * stripe + s
                if line >= n:
                    break
                for j in range(w):
                    c = ctx[line, j]
                    seen[c] += 1
                    ones[c] += lines[line, j]
        # A stack: the cells go in last first. Decoding order: step by step; within a step the
        # outside cells (context 0), the inside ones (255), the rest, each by stripe and column.
        words = np.empty(n * w + 4, dtype=np.uint32)
        count = 0
        state = np.uint64(0)
        for s in range(stripe - 1, -1, -1):
            k_end = 1 if s == 0 else n_stripes
            for kind in range(2, -1, -1):
                for k in range(k_end - 1, -1, -1):
                    line = k * stripe + s
                    if line >= n:
                        continue
                    for j in range(w - 1, -1, -1):
                        c = ctx[line, j]
                        this = 0 if c == 0 else (1 if c == 255 else 2)
                        if this != kind:
                            continue
                        z = zero_prob[s, c]
                        if lines[line, j]:
                            left, prob = z, total - z
                        else:
                            left, prob = 0, z
                        if (state >> np.uint64(64 - precision)) >= np.uint64(prob):
                            words[count] = np.uint32(state & np.uint64(0xFFFFFFFF))
                            count += 1
                            state = state >> np.uint64(32)
                        prob_u = np.uint64(prob)
                        state = ((state // prob_u) << np.uint64(precision)) | (np.uint64(left) + state % prob_u)
        return _flush(words, count, state)

    @njit(cache=True, nogil=True)
    def _left(i, lo, csum, at, size, n):  # pragma: no cover - compiled
        # constriction's left cumulative of symbol i: floor(C / 2**24 * (2**24 - n)) + i, C the frequencies below i
        if i < lo:
            c = i
        elif i < lo + size:
            c = lo + csum[at + i - lo]
        else:
            c = lo + csum[at + size] + (i - lo - size)
        return np.int64((c / float(total)) * float(total - n)) + i

    @njit(cache=True, nogil=True)
    def _encode_tables(symbols, bounds, lows, csum, near_bounds, n):  # pragma: no cover - compiled
        words = np.empty(symbols.size + 4, dtype=np.uint32)
        count = 0
        state = np.uint64(0)
        for g in range(bounds.size - 2, -1, -1):
            lo = lows[g]
            at = near_bounds[g] + g  # each table's running sums hold one more entry than its frequencies
            size = near_bounds[g + 1] - near_bounds[g]
            for k in range(bounds[g + 1] - 1, bounds[g] - 1, -1):
                i = symbols[k]
                left = _left(i, lo, csum, at, size, n)
                right = total if i == n - 1 else _left(i + 1, lo, csum, at, size, n)
                prob = np.uint64(right - left)
                if (state >> np.uint64(64 - precision)) >= prob:
                    words[count] = np.uint32(state & np.uint64(0xFFFFFFFF))
                    count += 1
                    state = state >> np.uint64(32)
                state = ((state // prob) << np.uint64(precision)) | (np.uint64(left) + state % prob)
        return _flush(words, count, state)

    class _Module:
        encode_mask_words = staticmethod(_encode)
        encode_table_words = staticmethod(_encode_tables)

    return _Module
