"""Encode stage: entropy-code the quantized coefficients (:mod:`dftpcc.quantizer` quantizes them).

Coefficients arrive ordered from low to high frequency. They are cut into
chunks of geometrically growing length, each coded on its own, so any prefix
of whole chunks decodes to a coarser map (progressive decoding). Inside a
chunk, integers are coded either with zstd (the baseline) or with an ANS
coder (constriction) whose model is chosen per frequency band (rings, and
sectors of them, see ``BAND_LAYOUTS``): magnitudes fall with frequency, so
each band sends one scale, its mean |q|, and is coded with the two-sided
geometric distribution of that mean, built from integer tables so that
every machine decodes the same bits.

The occupancy mask has its own coder, :mod:`dftpcc.occupancy`.
"""

from __future__ import annotations

import functools
import struct
import zlib
from typing import Callable, NamedTuple

import numpy as np
import zstandard

from . import geometric, kernels
from .errors import CorruptFileError, InvalidInputError

__all__ = [
    "encode_coefficients",
    "estimated_size",
    "decode_coefficients",
]

#: zstd level for coefficient chunks and the mask: high ratio, still fast on small inputs.
ZSTD_LEVEL = 19
#: Length of the first coefficient chunk; each next chunk is CHUNK_GROWTH times longer.
FIRST_CHUNK = 256
CHUNK_GROWTH = 2
#: Chunk header: coefficient count, payload bytes, CRC-32 of the payload.
CHUNK_HEAD = struct.Struct("<IIII")  # count, nbytes, crc32, element kind
#: Element kinds inside a chunk.
KIND_INT = 0  # zigzag byte planes, zstd
KIND_COMPLEX64 = 1  # raw little-endian complex64 (the paper)
KIND_ANS_TABLE = 3  # two-sided geometric per band from integer tables, ANS-coded
KIND_SPARSE_RESIDUAL = 4  # RESD only, its one chunk: nonzero map, magnitudes, signs (dftpcc.residual)
KIND_PREDICTED_RESIDUAL = 5  # RESD only, its one chunk: prediction errors by context (dftpcc.residual)
# (Kind 2, ANS with constriction's QuantizedLaplace, was written only by pre-release
# drafts; it is refused as any unknown kind.)
#: Ways to cut a chunk into frequency bands, one scale each:
#: (ring width in DFT frequency pixels, angular sectors). The encoder keeps,
#: per chunk, the one that codes it smallest (side information included):
#: terrain spectra are often directional (ridges, furrows, slopes).
BAND_LAYOUTS = ((4.0, 1), (8.0, 1), (8.0, 4), (8.0, 16))
#: Band scales are few and small: a fast zstd level codes them as well as a slow one.
#: zstd level of the side information (a compressor per call: zstandard's are not thread-safe).
_SIDE_ZSTD_LEVEL = 3
_ANS_HEAD = struct.Struct("<BII")  # band layout, largest |q| in the chunk, number of band codes
#: Chunks of at most this many values try every band layout and keep the
#: smallest; longer ones code only the layout whose estimated size is smallest.
EXACT_LAYOUT_CHOICE = 4096
#: A chunk never holds more coefficients than this (guards allocation on decode).
MAX_CHUNK_COEFS = 1 << 28


def _chunk_bounds(count: int) -> list[tuple[int, int]]:
    """Chunks of :data:`FIRST_CHUNK`, then each :data:`CHUNK_GROWTH` times longer, so a cut stream
    still decodes its first chunks."""
    bounds, start, size = [], 0, FIRST_CHUNK
    while start < count:
        stop = min(count, start + size)
        bounds.append((start, stop))
        start, size = stop, size * CHUNK_GROWTH
    return bounds


def _zigzag(q: np.ndarray) -> np.ndarray:
    return ((q << 1) ^ (q >> 63)).astype(np.uint64)


def _unzigzag(u: np.ndarray) -> np.ndarray:
    return (u >> np.uint64(1)).astype(np.int64) ^ -(u & np.uint64(1)).astype(np.int64)


def _pack_ints(q: np.ndarray) -> bytes:
    # Byte planes (low bytes of all values, then the next bytes...) let zstd
    # see the long runs of zero high bytes that small coefficients leave.
    u = _zigzag(q)
    width = max(1, (int(u.max()).bit_length() + 7) // 8) if u.size else 1
    planes = u.astype("<u8").view(np.uint8).reshape(-1, 8)[:, :width].T
    return bytes([width]) + np.ascontiguousarray(planes).tobytes()


def _unpack_ints(raw: bytes, count: int) -> np.ndarray:
    if not raw:
        raise CorruptFileError("coefficient chunk is empty")
    width = raw[0]
    if not 1 <= width <= 8 or len(raw) != 1 + width * count:
        raise CorruptFileError("coefficient chunk has an inconsistent length")
    planes = np.frombuffer(raw, dtype=np.uint8, offset=1).reshape(width, count)
    full = np.zeros((count, 8), dtype=np.uint8)
    full[:, :width] = planes.T
    return _unzigzag(full.view("<u8").ravel())


def unzstd(dctx: zstandard.ZstdDecompressor, payload: bytes, limit: int, what: str) -> bytes:
    """Decompress one zstd frame that must expand to at most ``limit`` bytes.

    The frame's declared size is checked before anything is allocated, so a
    crafted frame cannot ask for more memory than the header allows.
    """
    try:
        declared = zstandard.frame_content_size(payload)
        if declared > limit:
            raise CorruptFileError(f"{what} declares {declared} bytes, more than the {limit} it can hold")
        return dctx.decompress(payload, max_output_size=limit)
    except zstandard.ZstdError as exc:
        raise CorruptFileError(f"{what} does not decompress: {exc}") from None


def band_ids(radius: np.ndarray, angle: np.ndarray, layout: int, *, rings: np.ndarray | None = None) -> np.ndarray:
    """Band number of each coefficient under ``BAND_LAYOUTS[layout]``.

    ``radius`` is in DFT frequency pixels, ``angle`` scaled to [0, 1];
    ``rings``: ``(radius / width).astype(np.int64)`` for the layout's ring width, if known
    (the layouts of one chunk share their rings).
    """
    return _layout_bands(radius, angle, *BAND_LAYOUTS[layout], rings=rings)


def _layout_bands(radius: np.ndarray, angle: np.ndarray, width: float, sectors: int, *,
                  rings: np.ndarray | None = None) -> np.ndarray:
    """:func:`band_ids` under rings of ``width`` and ``sectors`` sectors (the compiled kernels' ``_band_at``)."""
    if rings is None:
        rings = (radius / width).astype(np.int64)
    if sectors == 1:  # one sector: every angle in [0, 1] falls in sector 0
        return rings
    sector = np.minimum((angle * sectors).astype(np.int64), sectors - 1)
    return rings * sectors + sector


def _side_info(codes: np.ndarray) -> bytes:
    """The band scale codes as a zstd frame, or raw when the frame would not be shorter
    (a few bands: the frame's own header outweighs them). A reader tells them apart by
    length: raw is exactly one byte per band."""
    raw = codes.tobytes()
    packed = zstandard.ZstdCompressor(level=_SIDE_ZSTD_LEVEL).compress(raw)
    return packed if len(packed) < len(raw) else raw


class _Bands(NamedTuple):
    """One band layout applied to a chunk: its scale codes, and each value's code."""

    layout: int
    codes: np.ndarray  # one per band, from the chunk's lowest band
    per_value: np.ndarray
    models: int = -1  # distinct nonzero codes among the values (-1: count them from per_value)

    @classmethod
    def of(cls, q: np.ndarray, radius: np.ndarray, angle: np.ndarray, layout: int, *,
           magnitudes: np.ndarray | None = None, rings: np.ndarray | None = None) -> _Bands:
        """The layout's bands of a chunk (``magnitudes``, ``rings``: see :func:`~dftpcc.geometric.band_statistics`
        and :func:`band_ids`, when the caller has them)."""
        bands = band_ids(radius, angle, layout, rings=rings)
        lo, codes, count = geometric.band_statistics(q, bands, magnitudes)
        # The codes the values take are those of the bands holding values: counted per band.
        models = int(np.count_nonzero(np.bincount(codes[count > 0], minlength=256)[1:]))
        return cls(layout, codes, codes[bands - lo], models)

    def table_work(self, max_abs: int) -> int:
        """Table entries the decoder builds: one table per distinct nonzero code."""
        models = self.models if self.models >= 0 else \
            int(np.count_nonzero(np.bincount(self.per_value, minlength=256)[1:]))
        return models * (2 * max_abs + 1)


def _encode_ans_with(q: np.ndarray, b: _Bands, max_abs: int) -> bytes:
    # Zero codes compress well: most high-frequency bands are empty at low rates.
    side = _side_info(b.codes)
    words = geometric.table_words(q, b.per_value, max_abs)
    return _ANS_HEAD.pack(b.layout, max_abs, len(side)) + side + words.astype("<u4").tobytes()


def _estimated_bits(q: np.ndarray, b: _Bands, magnitudes: np.ndarray | None = None) -> float:
    """Bits the ANS chunk of :func:`_encode_ans_with` would take, side information included,
    from the model's probabilities (within 0.01 % of the coded size on real maps);
    ``magnitudes``: ``np.abs(q).astype(np.float64)``, if known."""
    coded = b.per_value > 0
    codes = b.per_value[coded]
    a = np.abs(q[coded]).astype(np.float64) if magnitudes is None else magnitudes[coded]
    # Probability of q under the two-sided geometric of mean |q| scale (see geometric.decay),
    # log2 P(q) = log2((1 - t) / (1 + t)) + |q| log2(t): the two logarithms depend
    # on the scale code alone, so they come from a table of the 255 codes.
    at_zero, per_step = geometric.log_geometric()
    log_p = at_zero[codes] + a * per_step[codes]
    return 8.0 * _side_info_size(b.codes.tobytes()) - float(np.maximum(log_p, -geometric.TABLE_BITS).sum())


@functools.lru_cache(maxsize=4096)
def _side_info_size(raw: bytes) -> int:
    """Bytes of :func:`_side_info` of the band scale codes ``raw``: estimates ask for the same few
    codes again and again (rate control sizes many steps of one stream)."""
    return len(_side_info(np.frombuffer(raw, dtype=np.uint8)))


def _encode_ans(q: np.ndarray, radius: np.ndarray, angle: np.ndarray, exhaustive: bool) -> bytes | None:
    """The chunk ANS-coded with the best band layout, or None when every layout
    would need more tables than :func:`~dftpcc.geometric.table_budget` allows (the caller then uses zstd)."""
    max_abs = int(np.abs(q).max()) if q.size else 0
    magnitudes = np.abs(q).astype(np.float64)  # every layout's scales and estimate use them
    layouts = range(len(BAND_LAYOUTS)) if max_abs and exhaustive else range(1)
    rings: dict[float, np.ndarray] = {}  # per ring width: the layouts share them
    for k in layouts:
        width = BAND_LAYOUTS[k][0]
        if width not in rings:
            rings[width] = (radius / width).astype(np.int64)
    candidates = [b for b in (_Bands.of(q, radius, angle, k, magnitudes=magnitudes, rings=rings[BAND_LAYOUTS[k][0]])
                              for k in layouts)
                  if b.table_work(max_abs) <= geometric.table_budget(q.size)]
    if not candidates:
        return None
    if len(candidates) > 1 and q.size > EXACT_LAYOUT_CHOICE:
        # Long chunks: pick the layout by its estimated size, code it once.
        candidates = [min(candidates, key=lambda b: _estimated_bits(q, b, magnitudes))]
    return min((_encode_ans_with(q, b, max_abs) for b in candidates), key=len)


def _decode_ans(payload: bytes, radius: np.ndarray, angle: np.ndarray, what: str) -> np.ndarray:
    if len(payload) < _ANS_HEAD.size:
        raise CorruptFileError(f"{what} is too short")
    layout, max_abs, side_len = _ANS_HEAD.unpack_from(payload, 0)
    if layout >= len(BAND_LAYOUTS) or max_abs > geometric.MAX_ANS_SYMBOL:
        raise CorruptFileError(f"{what} has an implausible header")
    width, sectors = BAND_LAYOUTS[layout]
    lo, hi, bands = _band_range(radius, angle, width, sectors)
    ncodes = hi - lo + 1
    end = _ANS_HEAD.size + side_len
    if len(payload) < end or (len(payload) - end) % 4:
        raise CorruptFileError(f"{what} has a wrong length")
    side = payload[_ANS_HEAD.size:end]
    if side_len == ncodes:  # few bands: raw codes
        codes = np.frombuffer(side, dtype=np.uint8)
    elif side_len > ncodes:
        raise CorruptFileError(f"{what} has {side_len} bytes of band scales for {ncodes} bands")
    else:
        codes = np.frombuffer(unzstd(zstandard.ZstdDecompressor(), side, ncodes, what), dtype=np.uint8)
    if codes.size != ncodes:
        raise CorruptFileError(f"{what} has {codes.size} band scales, expected {ncodes}")
    words = np.frombuffer(payload, dtype="<u4", offset=end).astype(np.uint32)
    return geometric.coded_values(words, _band_codes(radius, angle, width, sectors, codes, lo, bands), max_abs, what)


@kernels.kernel("layout_totals")
def _layout_totals(radius: np.ndarray, angle: np.ndarray, width: float, sectors: int, magnitudes: np.ndarray
                   ) -> tuple[int, np.ndarray, np.ndarray]:
    """:func:`~dftpcc.geometric.band_sums`' lowest band, counts and sums of ``magnitudes`` under the
    layout of ring ``width`` and ``sectors`` (:func:`band_ids`): rate control sizes every candidate
    stream under every layout by them."""
    return geometric._band_totals(_layout_bands(radius, angle, width, sectors), magnitudes)


@kernels.kernel("band_range")
def _band_range(radius: np.ndarray, angle: np.ndarray, width: float, sectors: int
                ) -> tuple[int, int, np.ndarray | None]:
    """The lowest and highest band of a chunk's values under a layout of ring ``width`` and
    ``sectors`` (:func:`band_ids`), and the bands themselves where the implementation made them
    (None: :func:`_band_codes` works them out again, value by value, without the array)."""
    bands = _layout_bands(radius, angle, width, sectors)
    return int(bands.min()), int(bands.max()), bands


@kernels.kernel("band_codes")
def _band_codes(radius: np.ndarray, angle: np.ndarray, width: float, sectors: int, codes: np.ndarray, lo: int,
                bands: np.ndarray | None) -> np.ndarray:
    """Each value's band scale code (uint8): ``codes[band - lo]``, its band as :func:`_band_range`
    finds it (``bands``, when that made them)."""
    if bands is None:
        lo, hi, bands = _band_range.numpy(radius, angle, width, sectors)
    return codes[bands - lo]


def encode_coefficients(values: np.ndarray, *, radius: np.ndarray | None = None,
                        angle: np.ndarray | None = None, coder: str = "ans", exhaustive: bool = True,
                        progressive: bool = True) -> bytes:
    """Code an ordered coefficient stream as self-checking chunks.

    Parameters
    ----------
    values : ndarray
        int64 (quantized) or complex64 (the paper's raw storage, stored as
        is: real and imaginary float32, little endian).
    radius, angle : ndarray, optional
        Frequency of each value (radius in DFT frequency pixels, angle scaled
        to [0, 1]); needed by ``coder='ans'``, which models by band.
    coder : {'ans', 'zstd'}
        Entropy coder for integer chunks. ``ans`` falls back to zstd for a
        chunk whose values exceed :data:`~dftpcc.geometric.MAX_ANS_SYMBOL`.
    exhaustive : bool
        Try every band layout per chunk (``False``: the first only; faster,
        for rate-control searches that only need a size estimate).
    progressive : bool
        Chunks of growing length, so a prefix of the stream decodes (1.0 files); ``False``: as
        few chunks as the ANS tables allow (:func:`_free_bounds`; a 1.1 file, docs/format.md).
    """
    cctx = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
    if progressive or coder != "ans" or radius is None or np.iscomplexobj(values):
        bounds = _chunk_bounds(values.size) if progressive else [(0, values.size)] if values.size else []
    else:
        bounds = _free_bounds(values, radius, angle, exhaustive)
    if any(stop - start > MAX_CHUNK_COEFS for start, stop in bounds):
        raise InvalidInputError(f"{values.size} coefficients do not fit chunks of at most {MAX_CHUNK_COEFS}: "
                                "use a smaller tile size")
    return _chunks([(stop - start, _code_chunk(values[start:stop], None if radius is None else radius[start:stop],
                                               None if angle is None else angle[start:stop], coder, exhaustive,
                                               cctx)) for start, stop in bounds])


#: :func:`estimated_size` codes a zstd chunk of up to this many values at :data:`ZSTD_LEVEL`, a
#: longer one (a step so fine that its integers pass the ANS coder's range: a candidate that
#: loses anyway) at this faster level, a few % larger.
ESTIMATE_ZSTD_VALUES = 4096
ESTIMATE_ZSTD_LEVEL = 3
#: Bytes an ANS chunk's words may hold beyond its symbols' information: the coder's final state.
ANS_FLUSH_BYTES = 4


def estimated_size(values: np.ndarray, *, radius: np.ndarray | None = None, angle: np.ndarray | None = None,
                   coder: str = "ans", exhaustive: bool = True, progressive: bool = True) -> float:
    """Bytes :func:`encode_coefficients` would code ``values`` in, without coding them.

    An ANS chunk is sized from its model's probabilities (:func:`_estimated_bits`; with
    ``exhaustive``, the smallest band layout's, else the first's: within a few bytes of the coded
    chunk, 0.1 % on real maps), plus its header, band scales and final state;
    a chunk the ANS coder does not take (zstd, complex64) is coded, as the encoder would: those are
    a zstd file's or a first chunk's few large values. Rate control ranks its candidates by this
    size and codes only the one it keeps (:mod:`dftpcc.ratecontrol`).
    """
    if progressive or coder != "ans" or radius is None or np.iscomplexobj(values):
        bounds = _chunk_bounds(values.size) if progressive else [(0, values.size)] if values.size else []
    else:
        bounds = _free_bounds(values, radius, angle, False)
    total = 4.0 + CHUNK_HEAD.size * len(bounds)
    for start, stop in bounds:
        part = values[start:stop]
        if np.iscomplexobj(part):
            total += 8.0 * part.size
            continue
        bits = None
        if coder == "ans" and radius is not None:
            bits = _estimated_ans_bits(part, radius[start:stop], angle[start:stop], exhaustive)
        if bits is None:  # zstd: a first chunk's few values at the encoder's level, a long one faster
            level = ZSTD_LEVEL if part.size <= ESTIMATE_ZSTD_VALUES else ESTIMATE_ZSTD_LEVEL
            total += len(zstandard.ZstdCompressor(level=level).compress(_pack_ints(part)))
        else:
            total += _ANS_HEAD.size + ANS_FLUSH_BYTES + bits / 8.0
    return total


def _estimated_ans_bits(q: np.ndarray, radius: np.ndarray, angle: np.ndarray, exhaustive: bool) -> float | None:
    """:func:`_estimated_bits` of the chunk's smallest band layout within the table budget (as
    :func:`_encode_ans`), or None where the chunk falls back to zstd."""
    max_abs = int(np.abs(q).max()) if q.size else 0
    if max_abs > geometric.MAX_ANS_SYMBOL:
        return None
    magnitudes = np.abs(q).astype(np.float64)
    layouts = range(len(BAND_LAYOUTS)) if max_abs and exhaustive else range(1)
    best = None
    at_zero, per_step = geometric.log_geometric()
    # log2 P(q) = at_zero + |q| per_step (see _estimated_bits) sums band by band from each band's
    # count and sum of |q|, without a code per value; a value whose log2 P the table floors at
    # -TABLE_BITS lies above its code's threshold, and only those few are looked at one by one.
    threshold = (-geometric.TABLE_BITS - at_zero) / per_step
    for k in layouts:
        lo, count, total = _layout_totals(radius, angle, *BAND_LAYOUTS[k], magnitudes)
        codes = geometric.scale_codes(count, total)
        models = int(np.count_nonzero(np.bincount(codes[count > 0], minlength=256)[1:]))
        if models * (2 * max_abs + 1) > geometric.table_budget(q.size):
            continue
        coded = codes > 0
        log_p = float(np.sum(count[coded] * at_zero[codes[coded]] + total[coded] * per_step[codes[coded]]))
        if coded.any() and max_abs > threshold[codes[coded]].min():
            far = np.flatnonzero(magnitudes > threshold[codes[coded]].min())
            c = codes[band_ids(radius[far], angle[far], k) - lo]
            a, c = magnitudes[far][c > 0], c[c > 0]
            exact = at_zero[c] + a * per_step[c]
            log_p += float(np.sum(np.maximum(exact, -geometric.TABLE_BITS) - exact))
        bits = 8.0 * _side_info_size(codes.tobytes()) - log_p
        best = bits if best is None else min(best, bits)
    return best


def _free_bounds(values: np.ndarray, radius: np.ndarray, angle: np.ndarray | None,
                 exhaustive: bool) -> list[tuple[int, int]]:
    """Chunks of a 1.1 stream: 1.0's growing chunks until the rest fits one ANS chunk, then that one.

    Every chunk costs a header, band scales and an ANS flush, so one chunk is smallest, unless the
    low frequencies' large integers widen its alphabet past :func:`~dftpcc.geometric.table_budget` (it would fall
    back to zstd): short first chunks keep them apart.
    """
    bounds, start, size = [], 0, FIRST_CHUNK
    while start < values.size:
        rest = values[start:]
        if int(np.abs(rest).max()) <= geometric.MAX_ANS_SYMBOL and _ans_fits(rest, radius[start:], angle[start:], exhaustive):
            bounds.append((start, values.size))
            break
        stop = min(values.size, start + size)
        bounds.append((start, stop))
        start, size = stop, size * CHUNK_GROWTH
    return bounds


def _ans_fits(q: np.ndarray, radius: np.ndarray, angle: np.ndarray, exhaustive: bool) -> bool:
    """Whether :func:`_encode_ans` finds a band layout within the table budget for ``q``."""
    max_abs = int(np.abs(q).max()) if q.size else 0
    layouts = range(len(BAND_LAYOUTS)) if max_abs and exhaustive else range(1)
    return any(_Bands.of(q, radius, angle, k).table_work(max_abs) <= geometric.table_budget(q.size) for k in layouts)


def _code_chunk(part: np.ndarray, radius: np.ndarray | None, angle: np.ndarray | None, coder: str,
                exhaustive: bool, cctx: zstandard.ZstdCompressor) -> tuple[bytes, int]:
    """One chunk's payload and kind: complex64 as is, else ANS where it applies, else zstd."""
    if np.iscomplexobj(part):
        return part.astype("<c8").tobytes(), KIND_COMPLEX64
    if coder == "ans" and radius is not None and int(np.abs(part).max()) <= geometric.MAX_ANS_SYMBOL and (
            ans := _encode_ans(part, radius, angle, exhaustive)) is not None:
        return ans, KIND_ANS_TABLE
    return cctx.compress(_pack_ints(part)), KIND_INT


def one_chunk(count: int, payload: bytes, kind: int) -> bytes:
    """A stream of ``count`` values as one chunk of ``kind`` (a kind :func:`decode_coefficients`
    takes through ``whole``)."""
    return _chunks([(count, (payload, kind))])


def _chunks(coded: list[tuple[int, tuple[bytes, int]]]) -> bytes:
    """The COEF structure: the chunk count, then each chunk's header and payload."""
    out = [struct.pack("<I", len(coded))]
    for count, (payload, kind) in coded:
        out.append(CHUNK_HEAD.pack(count, len(payload), zlib.crc32(payload), kind))
        out.append(payload)
    return b"".join(out)


def decode_coefficients(blob: bytes | memoryview, expected: int, *, radius: np.ndarray | None = None,
                        angle: np.ndarray | None = None, allow_partial: bool = False,
                        progressive: bool = True,
                        whole: dict[int, Callable[[bytes], np.ndarray]] | None = None,
                        exact: bool = False) -> np.ndarray:
    """Inverse of :func:`encode_coefficients`.

    Parameters
    ----------
    blob : bytes
        The coefficient section (possibly truncated when ``allow_partial``).
    expected : int
        Number of coefficients the header announces.
    radius, angle : ndarray, optional
        Frequency of each of the ``expected`` values (needed for ANS chunks).
    allow_partial : bool
        Return the coefficients of the whole chunks present instead of
        raising when the section is cut short (progressive decoding).
    progressive : bool
        ``False``: a 1.1 stream, whose chunks have lengths of the writer's choosing
        (:func:`encode_coefficients`).
    whole : dict, optional
        Kinds this stream may hold as its only chunk, each with the function that decodes such a
        chunk's payload into all ``expected`` values (``RESD``'s sparse kind, :mod:`dftpcc.residual`).
    exact : bool
        Refuse bytes after the last chunk (a structure whose end is known only from its chunks:
        the magnitudes of a sparse residual).

    Returns
    -------
    ndarray
        int64 or complex128 coefficients, at most ``expected`` of them.
    """
    blob = memoryview(blob)
    if len(blob) < 4:
        if allow_partial:
            return np.zeros(0, dtype=np.int64)
        raise CorruptFileError("coefficient section is truncated")
    (nchunks,) = struct.unpack_from("<I", blob, 0)
    bounds = _chunk_bounds(expected) if progressive else None
    if whole and nchunks == 1 and len(blob) >= 4 + CHUNK_HEAD.size and CHUNK_HEAD.unpack_from(blob, 4)[3] in whole:
        bounds = None  # one chunk of a kind that holds the whole stream, whatever the lengths
    if bounds is not None and nchunks != len(bounds):
        raise CorruptFileError(f"coefficient section has {nchunks} chunks, header implies {len(bounds)}")
    if bounds is None and nchunks > expected:  # every chunk holds a value at least
        raise CorruptFileError(f"coefficient section has {nchunks} chunks for {expected} values")
    pos, parts, stop = 4, [], 0
    dctx = zstandard.ZstdDecompressor()
    for index in range(nchunks):
        if pos + CHUNK_HEAD.size > len(blob):
            if allow_partial:
                break
            raise CorruptFileError(f"coefficient chunk {index} is truncated")
        count, nbytes, crc, kind = CHUNK_HEAD.unpack_from(blob, pos)
        pos += CHUNK_HEAD.size
        # 1.1 streams: chunk lengths of the writer's choosing, together the stream's.
        start, stop = bounds[index] if bounds is not None else (stop, stop + count)
        if count != stop - start or count > MAX_CHUNK_COEFS or count < 1 or stop > expected:
            raise CorruptFileError(f"coefficient chunk {index} holds {count} values, expected "
                                   + (f"{stop - start}" if bounds is not None else f"1 to {expected - start}"))
        if pos + nbytes > len(blob):
            if allow_partial:
                break
            raise CorruptFileError(f"coefficient chunk {index} is truncated")
        payload = bytes(blob[pos:pos + nbytes])
        pos += nbytes
        if zlib.crc32(payload) != crc:
            raise CorruptFileError(f"coefficient chunk {index} fails its checksum")
        what = f"coefficient chunk {index}"
        if whole and kind in whole:
            if nchunks != 1 or count != expected:
                raise CorruptFileError(f"{what} of kind {kind} must be the stream's only chunk, with all "
                                       f"{expected} values")
            parts.append(whole[kind](payload))
        elif kind == KIND_COMPLEX64:
            if nbytes != 8 * count:
                raise CorruptFileError(f"{what} has a wrong length")
            parts.append(np.frombuffer(payload, dtype="<c8").astype(np.complex128))
        elif kind == KIND_INT:
            raw = unzstd(dctx, payload, 1 + 8 * count, what)
            parts.append(_unpack_ints(raw, count))
        elif kind == KIND_ANS_TABLE:
            if radius is None or angle is None or radius.size < stop:
                raise CorruptFileError(f"{what} is ANS-coded but no frequencies are known")
            parts.append(_decode_ans(payload, radius[start:stop], angle[start:stop], what))
        else:
            raise CorruptFileError(f"{what} has unknown kind {kind}")
    if bounds is None and not allow_partial and stop != expected:
        raise CorruptFileError(f"coefficient chunks hold {stop} values, expected {expected}")
    if exact and pos != len(blob):
        raise CorruptFileError(f"coefficient chunks end {len(blob) - pos} bytes before their structure does")
    if not parts:
        return np.zeros(0, dtype=np.int64)
    if len({p.dtype.kind for p in parts}) != 1:
        raise CorruptFileError("coefficient chunks mix kinds")
    return np.concatenate(parts)
