"""Quantization, coefficient chunks and the occupancy mask."""

from __future__ import annotations

import re
import struct
import warnings
import zlib

import numpy as np
import pytest
import zstandard
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import dftpcc
from dftpcc import coding, geometric, quantizer
from dftpcc.errors import CorruptFileError, InvalidInputError


@given(hnp.arrays(np.float64, st.integers(1, 500), elements=st.floats(-1e4, 1e4)),
       st.floats(1e-3, 10.0), st.floats(0.0, 0.45))
@settings(max_examples=60, deadline=None)
def test_quantizer_error_is_bounded(values, step, deadzone):
    q = quantizer.quantize(values, step, deadzone)
    err = np.abs(values - quantizer.dequantize(q, step))
    assert (err <= (0.5 + deadzone) * step * (1 + 1e-9) + 1e-9).all()


@given(hnp.arrays(np.int64, st.integers(0, 3000), elements=st.integers(-(2**40), 2**40)))
@settings(max_examples=60, deadline=None)
def test_integer_stream_round_trips(values):
    blob = coding.encode_coefficients(values)
    np.testing.assert_array_equal(coding.decode_coefficients(blob, values.size), values)


def test_complex_stream_round_trips_as_float32():
    values = (np.arange(1000) * (1 + 0.5j)).astype(np.complex64)
    back = coding.decode_coefficients(coding.encode_coefficients(values), 1000)
    np.testing.assert_array_equal(back, values)


def test_truncated_stream_decodes_whole_chunks_only_when_allowed():
    values = np.arange(5000, dtype=np.int64) % 7 - 3
    blob = coding.encode_coefficients(values)
    with pytest.raises(CorruptFileError, match="truncated"):
        coding.decode_coefficients(blob[:-10], values.size)
    part = coding.decode_coefficients(blob[: len(blob) // 2], values.size, allow_partial=True)
    assert 0 < part.size < values.size
    np.testing.assert_array_equal(part, values[: part.size])


def test_flipped_bit_is_caught():
    values = np.arange(3000, dtype=np.int64)
    blob = bytearray(coding.encode_coefficients(values))
    blob[-5] ^= 0x10
    with pytest.raises(CorruptFileError, match="checksum"):
        coding.decode_coefficients(bytes(blob), values.size)


def test_step_choice_meets_its_target():
    values = np.random.default_rng(0).laplace(scale=0.5, size=4000)
    step = quantizer.choose_step(values, target_rmse=0.01, n_cells=10000, deadzone=0.2)
    err = values - quantizer.dequantize(quantizer.quantize(values, step, 0.2), step)
    assert np.sqrt(np.sum(err**2) / 10000) <= 0.01
    # and it is not needlessly fine: twice the step breaks the target
    err2 = values - quantizer.dequantize(quantizer.quantize(values, 2 * step, 0.2), 2 * step)
    assert np.sqrt(np.sum(err2**2) / 10000) > 0.01


def test_kind_2_chunks_of_the_drafts_are_refused():
    # Kind 2 (ANS with constriction's QuantizedLaplace models) was written only by
    # pre-release drafts; a reader refuses it as any kind it does not know. The chunk is
    # made as the drafts made it, so only its kind is foreign.
    import constriction

    rng = np.random.default_rng(3)
    values = np.round(rng.laplace(scale=3.0, size=200)).astype(np.int64)
    radius, angle = np.linspace(0, 30, values.size), np.zeros(values.size)
    max_abs = int(np.abs(values).max())
    bands = coding.band_ids(radius, angle, 0)
    lo, codes = geometric.band_scales(values, bands)
    coder = constriction.stream.stack.AnsCoder()
    for code, where in reversed(geometric.code_groups(codes[bands - lo])):
        scale = max(2.0 ** ((code - 128) / 8), 0.05)
        model = constriction.stream.model.QuantizedLaplace(-max_abs - 1, max_abs + 1, 0.0, scale)
        coder.encode_reverse(values[where].astype(np.int32), model)
    side = zstandard.compress(codes.tobytes())
    payload = struct.pack("<BII", 0, max_abs, len(side)) + side + coder.get_compressed().astype("<u4").tobytes()
    blob = struct.pack("<I", 1) + struct.pack("<IIII", values.size, len(payload), zlib.crc32(payload), 2) + payload
    with pytest.raises(CorruptFileError, match="coefficient chunk 0 has unknown kind 2"):
        coding.decode_coefficients(blob, values.size, radius=radius, angle=angle)
    assert not hasattr(coding, "KIND_ANS")


def test_table_models_are_fixed_integers():
    # The decay of each scale code is an exact integer: pin a few, so a change
    # in how they are computed cannot slip through.
    assert geometric.decay(128) == 27145  # b = 1: (sqrt(2) - 1) * 65536, floored
    assert geometric.decay(1) == 1637  # b = 0.05 (the floor of the scale)
    assert geometric.decay(255) == 65534
    w = geometric.magnitude_weights(128)
    assert w[0] == 1 << 32 and w[1] == ((1 << 32) * 27145) >> 16


def test_a_chunk_may_not_ask_for_huge_probability_tables():
    # 256 values, each in its own band scale group, with a magnitude bound of 2**15:
    # 255 tables of 65,537 symbols would take a third of a second to build.
    values = np.zeros(256, dtype=np.int64)
    values[::2] = np.round(2.0 ** (np.arange(128) / 8.5))  # ~120 distinct band scales
    assert values.max() <= geometric.MAX_ANS_SYMBOL  # so only the table budget rules ANS out
    radius, angle = np.arange(256) * 8.0, np.zeros(256)  # one band per value with layouts 0 and 1
    blob = coding.encode_coefficients(values, radius=radius, angle=angle)
    # The encoder falls back to zstd for such a chunk ...
    assert struct.unpack_from("<I", blob, 16)[0] == coding.KIND_INT
    np.testing.assert_array_equal(coding.decode_coefficients(blob, 256, radius=radius, angle=angle), values)
    # ... and a crafted ANS chunk asking for them is refused before any is built.
    bands = coding.band_ids(radius, angle, 1)
    lo, codes = geometric.band_scales(values, bands)
    side = zstandard.compress(np.maximum(codes, 1).tobytes())
    payload = struct.pack("<BII", 1, geometric.MAX_ANS_SYMBOL, len(side)) + side + b"\0" * 8
    chunk = struct.pack("<IIII", 256, len(payload), zlib.crc32(payload), coding.KIND_ANS_TABLE) + payload
    with pytest.raises(CorruptFileError, match="larger probability tables"):
        coding.decode_coefficients(struct.pack("<I", 1) + chunk, 256, radius=radius, angle=angle)


def test_few_band_scales_are_stored_raw_and_a_longer_side_is_refused():
    values = np.array([5, -3, 2, 0, 1, 0, 0, -1] * 4, dtype=np.int64)
    radius, angle = np.linspace(0, 3, values.size), np.zeros(values.size)  # one band
    blob = coding.encode_coefficients(values, radius=radius, angle=angle)
    kind = struct.unpack_from("<I", blob, 16)[0]
    layout, max_abs, side = struct.unpack_from("<BII", blob, 20)
    assert kind == coding.KIND_ANS_TABLE and side == 1  # one raw byte, not a 10-byte zstd frame
    np.testing.assert_array_equal(coding.decode_coefficients(blob, values.size, radius=radius, angle=angle), values)
    payload = bytearray(blob[20:30] + b"\x80" + blob[30:])  # a second byte of scales ...
    struct.pack_into("<I", payload, 5, 2)  # ... for one band
    chunk = struct.pack("<IIII", values.size, len(payload), zlib.crc32(bytes(payload)), kind) + bytes(payload)
    with pytest.raises(CorruptFileError, match="bytes of band scales"):
        coding.decode_coefficients(struct.pack("<I", 1) + chunk, values.size, radius=radius, angle=angle)


# --- the quantizer never wraps: a step too fine for the map is refused -----------------------------

def test_the_quantizer_refuses_a_step_whose_integers_would_wrap():
    values = np.array([1.0, -3.0, 250.0, 0.0])
    finest = quantizer.finest_step(values)
    q = quantizer.quantize(values, finest, 0.1)
    assert q.dtype == np.int64 and 2**61 < np.abs(q).max() < 2**63 and np.sign(q[2]) == 1
    np.testing.assert_allclose(quantizer.dequantize(q, finest), values, rtol=1e-12)
    for step in (finest / 1.01, 1e-20, 1e-300, 5e-324):
        with pytest.raises(InvalidInputError, match="too fine .* smallest workable step is"):
            quantizer.quantize(values, step, 0.1)


@given(hnp.arrays(np.float64, st.integers(1, 50), elements=st.floats(-1e15, 1e15)), st.floats(0.0, 0.45))
@settings(max_examples=60, deadline=None)
def test_at_the_finest_step_every_integer_fits_and_keeps_its_sign(values, deadzone):
    step = quantizer.finest_step(values)
    if not step:
        return  # all zeros: any step
    q = quantizer.quantize(values, step, deadzone)
    assert (np.sign(q) * np.sign(values) >= 0).all()
    # Within a step, up to float64's own rounding of integers this large (a few ulp of the value).
    assert (np.abs(values - quantizer.dequantize(q, step)) <= step + 4 * np.spacing(np.abs(values))).all()


@pytest.fixture(scope="module")
def gentle() -> np.ndarray:
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0, 50, (2, 4000))
    return np.c_[x, y, 100 + 0.05 * x + np.sin(y / 5) + rng.normal(0, 0.01, x.size)]


@pytest.mark.parametrize("step", [1e-300, 1e-20])
@pytest.mark.parametrize("options", [{}, {"transform": "dft"}, {"coder": "zstd"}], ids=["dct", "dft", "zstd"])
def test_a_step_too_fine_for_the_heights_is_refused_with_the_finest_that_works(gentle, step, options):
    # 1e-300 ended in struct.error in the ANS coder; 1e-20 wrapped the int64 quantizer
    # with only numpy's cast warning, and wrote a worse map.
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no cast warning on the way
        with pytest.raises(InvalidInputError) as info:
            dftpcc.compress(gentle, resolution=1.0, step=step, **options)
    message = str(info.value)
    assert re.search(rf"quantizer step {step:g} m is too fine for this map's height range "
                     r"\(99\.\d+ to 103\.\d+ m\).* smallest workable step is [0-9.e+-]+ m", message), message
    finest = float(re.search(r"smallest workable step is ([0-9.e+-]+) m", message).group(1))
    data = dftpcc.compress(gentle, resolution=1.0, step=finest, **options)
    assert dftpcc.open(data).params.step == finest
    # Quantized that finely the map is the low-passed one: as good as the finest usual step.
    usual = dftpcc.open(dftpcc.compress(gentle, resolution=1.0, step=1e-6, **options)).header.stats
    assert dftpcc.open(data).header.stats["dem_rmse_m"] <= usual["dem_rmse_m"] * (1 + 1e-6)


@pytest.mark.parametrize("profile", ["compact", "paper"])
def test_a_maximum_error_too_fine_for_the_heights_is_refused(gentle, profile):
    with pytest.raises(InvalidInputError, match=r"target maximum error 1e-300 m is too fine for this map's height "
                                                r"range .* smallest workable target is [0-9.e+-]+ m"):
        dftpcc.compress(gentle, resolution=1.0, target_max_error=1e-300, profile=profile)


@pytest.mark.parametrize("profile", ["compact", "paper"])
def test_the_smallest_workable_target_is_taken_and_half_of_it_refused(gentle, profile):
    """Issue 41, item 12: the refusal at its boundary (a check loosened 1000x passed the 1e-300 test alone)."""
    with pytest.raises(InvalidInputError) as info:
        dftpcc.compress(gentle, resolution=1.0, target_max_error=1e-300, profile=profile)
    finest = float(re.search(r"smallest workable target is ([0-9.e+-]+) m", str(info.value)).group(1))
    with pytest.raises(InvalidInputError, match=f"target maximum error {finest / 2:g} m is too fine"):
        dftpcc.compress(gentle, resolution=1.0, target_max_error=finest / 2, profile=profile)
    data = dftpcc.compress(gentle, resolution=1.0, target_max_error=finest, profile=profile)
    assert dftpcc.open(data).header.stats["dem_max_error_m"] <= finest


def test_the_cli_says_the_step_is_too_fine_in_one_line(capsys, tmp_path, gentle):
    from dftpcc import cli

    src, out = tmp_path / "cloud.npy", tmp_path / "out.dftpc"
    np.save(src, gentle)
    assert cli.main(["compress", str(src), str(out), "-r", "1", "--step", "1e-300"]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "too fine for this map's height range" in err[0], err
    assert not out.exists()


# --- heights a file cannot hold ----------------------------------------------------------------------

@pytest.mark.parametrize("z", [(-4e299, 4e299), (0.0, 3e12), (-2e12, -1.5e12)])
def test_heights_out_of_range_are_refused_as_such(gentle, z):
    # Heights spanning 1e300 used to be reported as a bad step ("step must be a finite number").
    points = gentle.copy()
    points[:, 2] = np.where(points[:, 0] > 25, z[1], z[0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # refused before gridding: no overflow on the way
        with pytest.raises(InvalidInputError, match=re.escape(f"heights are out of range: they run from {z[0]:g} to "
                                                              f"{z[1]:g} m, and a .dftpc file holds heights within "
                                                              "±1e+12 m")):
            dftpcc.compress(points, resolution=1.0)


def test_a_dem_with_heights_out_of_range_is_refused(gentle):
    from dftpcc import encoder
    from dftpcc.dem import DEM, Grid

    grid = Grid(0.0, 0.0, 10.0, 1.0, 4, 4)
    heights = np.zeros(grid.shape)
    heights[0, 0] = 5e299
    dem = DEM(grid, heights, np.ones(grid.shape, bool), gridding_rmse=0.0)
    with pytest.raises(InvalidInputError, match=r"heights are out of range: they run from 10 to 5e\+299 m"):
        encoder.encode_dem(dem, dftpcc.make_params(resolution=1.0))


def _chunk_headers(blob: bytes) -> list[tuple[int, int]]:
    """(value count, kind) of each chunk of a COEF-structured section."""
    (n,), pos, headers = struct.unpack_from("<I", blob, 0), 4, []
    for _ in range(n):
        count, nbytes, _crc, kind = struct.unpack_from("<IIII", blob, pos)
        headers.append((count, kind))
        pos += 16 + nbytes
    return headers


def _chunk_counts(blob: bytes) -> list[int]:
    return [count for count, _kind in _chunk_headers(blob)]


def _chunk_kinds(blob: bytes) -> list[int]:
    return [kind for _count, kind in _chunk_headers(blob)]


def test_a_stream_without_progressive_decoding_takes_as_few_chunks_as_its_tables_allow():
    rng = np.random.default_rng(5)
    n = 5000
    radius, angle = np.sort(rng.uniform(0, 200, n)), rng.uniform(0, 1, n)
    small = np.round(rng.laplace(0, 40, n) * np.exp(-radius / 40)).astype(np.int64)
    one = coding.encode_coefficients(small, radius=radius, angle=angle, progressive=False)
    growing = coding.encode_coefficients(small, radius=radius, angle=angle)
    assert _chunk_counts(one) == [n] and len(_chunk_counts(growing)) == 5
    assert len(one) < len(growing)  # four chunk headers, band scales and ANS flushes fewer
    # Large low frequencies would widen one chunk's alphabet past the table budget: the first
    # chunks keep them apart, and the rest is one chunk.
    large = small.copy()
    large[:300] = rng.integers(-30000, 30000, 300) * (rng.uniform(size=300) < 0.5)
    counts = _chunk_counts(coding.encode_coefficients(large, radius=radius, angle=angle, progressive=False))
    assert counts == [256, 512, n - 768]
    for q in (small, large):
        blob = coding.encode_coefficients(q, radius=radius, angle=angle, progressive=False)
        back = coding.decode_coefficients(blob, n, radius=radius, angle=angle, progressive=False)
        np.testing.assert_array_equal(back, q)


def test_free_chunk_lengths_must_hold_the_stream_exactly():
    values = np.arange(600, dtype=np.int64) % 7 - 3
    cctx = zstandard.ZstdCompressor()
    def chunks(*counts):
        at = np.cumsum((0,) + counts)
        return coding._chunks([(c, coding._code_chunk(values[a:a + c], None, None, "zstd", False, cctx))
                               for a, c in zip(at, counts)])
    np.testing.assert_array_equal(coding.decode_coefficients(chunks(100, 500), 600, progressive=False), values)
    for counts, message in (((100, 499), "hold 599 values, expected 600"), ((100, 501), "holds 501 values"),
                            ((0, 600), "holds 0 values")):
        with pytest.raises(CorruptFileError, match=message):
            coding.decode_coefficients(chunks(*counts), 600, progressive=False)
    with pytest.raises(CorruptFileError, match="601 chunks for 600 values"):
        coding.decode_coefficients(struct.pack("<I", 601), 600, progressive=False)
    # A 1.0 stream keeps its rule: the same two chunks are refused there.
    with pytest.raises(CorruptFileError, match="chunk 0 holds 100 values, expected 256"):
        coding.decode_coefficients(chunks(100, 500), 600)


def test_a_residual_of_mostly_zeros_is_coded_sparse_where_shorter():
    """A residual layer at a coarse bound is mostly 0, with its corrections where the terrain is
    rough: kind 3 codes every 0 at its scale floor, the sparse layout (RESD kind 4) codes the
    picture of the nonzero cells and their sizes. The smaller layout is written; dense residuals
    keep the chunks, and both decode."""
    from dftpcc.residual import decode_residual, encode_residual

    rng = np.random.default_rng(5)
    kept = np.ones((200, 500), bool)
    kept[:, :40] = False  # cells the file does not rebuild
    n = int(kept.sum())
    rough = np.zeros(kept.shape, bool)
    for r, c in zip(rng.integers(0, 190, 30), rng.integers(40, 490, 30)):  # 30 rough patches
        rough[r:r + 10, c:c + 10] = True
    sparse = np.where(rough & (rng.random(kept.shape) < 0.3), rng.choice([-2, -1, 1, 2], kept.shape), 0)[kept]
    dense = np.round(rng.laplace(0, 3, n)).astype(np.int64)
    flat = np.zeros(n)
    for q in (sparse.astype(np.int64), dense):
        blob = encode_residual(q, "ans", kept)
        np.testing.assert_array_equal(decode_residual(blob, kept), q)
        chunked = coding.encode_coefficients(q, radius=flat, angle=flat, exhaustive=False)
        assert len(blob) <= len(chunked)
        if q is dense:
            assert blob == chunked and set(_chunk_kinds(blob)) == {coding.KIND_ANS_TABLE}
        else:
            assert _chunk_kinds(blob) == [coding.KIND_SPARSE_RESIDUAL] and len(blob) < 0.8 * len(chunked)
    # Kind 4 belongs to RESD alone: a coefficient stream refuses it.
    with pytest.raises(CorruptFileError, match="unknown kind 4"):
        coding.decode_coefficients(encode_residual(sparse.astype(np.int64), "ans", kept), n, radius=flat, angle=flat,
                                   progressive=False)


def test_a_sparse_residual_that_lies_is_refused():
    from dftpcc.residual import _LENGTH, decode_residual, encode_residual

    kept = np.ones((100, 200), bool)
    kept[0:10, 150:160] = False
    corrections = np.zeros(kept.shape, np.int64)
    corrections[40:50, 3:13] = np.random.default_rng(2).choice([-3, -1, 0, 0, 0, 1, 2], (10, 10))
    q = corrections[kept]
    blob = encode_residual(q, "ans", kept)
    assert _chunk_kinds(blob) == [coding.KIND_SPARSE_RESIDUAL]
    payload = blob[20:]

    def wrapped(p: bytes, count: int = q.size) -> bytes:
        return coding.one_chunk(count, p, coding.KIND_SPARSE_RESIDUAL)

    with pytest.raises(CorruptFileError, match="corrects a cell that is not rebuilt"):
        elsewhere = np.ones_like(kept)
        elsewhere[40:50, 3:13] = False  # as many cells rebuilt, but not those the residual corrects
        decode_residual(blob, elsewhere)
    with pytest.raises(CorruptFileError, match="stray sign bit"):
        decode_residual(wrapped(payload[:-1] + bytes([payload[-1] | 1])), kept)
    with pytest.raises(CorruptFileError, match="runs past the chunk"):
        decode_residual(wrapped(_LENGTH.pack(1 << 30) + payload[4:]), kept)
    with pytest.raises(CorruptFileError, match="only chunk"):
        decode_residual(wrapped(payload, q.size - 1), kept)
    two = struct.pack("<I", 2) + blob[4:] + blob[4:]
    with pytest.raises(CorruptFileError):
        decode_residual(two, kept)


def test_a_sparse_residual_with_bytes_between_its_magnitudes_and_signs_is_refused():
    """The magnitudes' structure must end where the signs start (docs/format.md, RESD kind 4)."""
    from dftpcc.residual import _LENGTH, decode_residual, encode_residual

    kept = np.ones((100, 200), bool)
    corrections = np.zeros(kept.shape, np.int64)
    corrections[40:50, 3:13] = np.random.default_rng(2).choice([-3, -1, 0, 0, 0, 1, 2], (10, 10))
    q = corrections.ravel()
    payload = encode_residual(q, "ans", kept)[20:]
    (length,) = _LENGTH.unpack_from(payload, 0)
    n = int(np.count_nonzero(q))
    signs_at = len(payload) - (n + 7) // 8
    padded = payload[:signs_at] + b"\x00" + payload[signs_at:]
    section = coding.one_chunk(q.size, padded, coding.KIND_SPARSE_RESIDUAL)
    with pytest.raises(CorruptFileError, match="bytes before their structure does"):
        decode_residual(section, kept)
    from . import spec_decoder  # the document's reader refuses it too

    with pytest.raises(ValueError, match="do not end where the signs start"):
        spec_decoder._residual(section, kept)
    np.testing.assert_array_equal(spec_decoder._residual(encode_residual(q, "ans", kept), kept), q)
    assert length > 0


def _rough_levels(seed: int, shape: tuple[int, int]) -> np.ndarray:
    """Heights on integer steps of a rough surface (integrated noise): neighbours predict each
    other, as on alpine terrain at a fine bound."""
    rng = np.random.default_rng(seed)
    z = np.cumsum(np.cumsum(rng.normal(0, 1.0, shape), 0), 1) + rng.normal(0, 2.0, shape)
    return np.round(z).astype(np.int64)


def test_a_rough_residual_is_coded_predicted_and_decodes_as_the_document_says():
    """Where the residual is the map itself, RESD kind 5 (each value predicted from its decoded
    neighbours, its error coded given theirs) is written, far smaller than the chunks; the library
    and the document's reader decode it alike, holes and all."""
    from dftpcc.residual import decode_residual, encode_residual

    from . import spec_decoder

    levels = _rough_levels(7, (60, 75))
    kept = np.ones(levels.shape, bool)
    kept[20:30, 10:40] = False  # a hole
    kept[:, -3:] = False  # cells past the footprint at every row's end
    kept[0, 0] = False  # the first cell too
    q = levels[kept]
    blob = encode_residual(q, "ans", kept)
    assert _chunk_kinds(blob) == [coding.KIND_PREDICTED_RESIDUAL]
    assert len(blob) < 0.6 * len(encode_residual(q, "ans", kept, predicted=False))
    np.testing.assert_array_equal(decode_residual(blob, kept), q)
    np.testing.assert_array_equal(spec_decoder._residual(blob, kept), q)
    # A zstd file keeps zstd chunks; kind 5 belongs to RESD alone: a coefficient stream refuses it.
    assert set(_chunk_kinds(encode_residual(q, "zstd", kept))) == {coding.KIND_INT}
    flat = np.zeros(q.size)
    with pytest.raises(CorruptFileError, match="unknown kind 5"):
        coding.decode_coefficients(blob, q.size, radius=flat, angle=flat, progressive=False)


@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (9, 1), (2, 2), (3, 5), (5, 3), (4, 64)])
def test_a_predicted_residual_takes_every_edge_rule(shape):
    """Grids of one row, one column and two of each: the rules for neighbours off the grid."""
    from dftpcc.residual import _decode_predicted, _encode_predicted

    from . import spec_decoder

    rng = np.random.default_rng(shape[0] * 100 + shape[1])
    levels = _rough_levels(shape[0] + shape[1], shape) * 5
    for kept in (np.ones(shape, bool), rng.random(shape) < 0.6):
        if not kept.any():
            continue
        q = levels[kept]
        payload = _encode_predicted(q, kept)
        np.testing.assert_array_equal(_decode_predicted(payload, kept), q)
        section = coding.one_chunk(q.size, payload, coding.KIND_PREDICTED_RESIDUAL)
        np.testing.assert_array_equal(spec_decoder._residual(section, kept), q)


def test_predicted_weights_are_exact_and_sum_to_one():
    """The least-squares weights come from exact sums and an exact solve, in 1/2**16, summing to 1:
    a constant map is predicted exactly, and a plane leaves no error away from the edges."""
    from dftpcc.residual import WEIGHT_BITS, _WEIGHTS, _encode_predicted

    kept = np.ones((30, 40), bool)
    flat = np.full(kept.shape, 17, np.int64)
    plane = np.add.outer(3 * np.arange(30), 2 * np.arange(40)).astype(np.int64)
    for grid in (flat, plane):
        payload = _encode_predicted(grid.ravel(), kept)
        *weights, listed = _WEIGHTS.unpack_from(payload, 0)
        assert sum(weights) == 1 << WEIGHT_BITS
        # Few classes, few words: the errors are at the edges only.
        assert len(payload) < _WEIGHTS.size + 100, (len(payload), listed)


def test_predicted_weights_solve_is_the_exact_rational_solution():
    """The fraction-free elimination gives the normal equations' rational solution itself: A x = b
    holds in fractions, on systems near singular (two neighbours alike), of large sums and of small."""
    from fractions import Fraction

    from dftpcc.residual import _exact_solution

    rng = np.random.default_rng(5)
    for t in range(300):
        scale = [1, 30, 1 << 15][t % 3]
        d = rng.integers(-scale, scale + 1, (7, int(rng.integers(1, 40))))
        if t % 4 == 0:
            d[2] = d[1]
        sums = (d @ d.T).tolist()
        rows = [[sums[i][j] + (i == j) for j in range(6)] + [sums[i][6]] for i in range(6)]
        x = _exact_solution(rows)
        assert all(isinstance(v, Fraction) for v in x)
        assert all(sum(row[j] * x[j] for j in range(6)) == row[6] for row in rows)


def _predicted_payload(weights, codes, widths, words: bytes) -> bytes:
    from dftpcc.residual import _WEIGHTS

    return (_WEIGHTS.pack(*weights, len(codes)) + bytes(codes)
            + np.array([m for m, c in zip(widths, codes) if c], "<u2").tobytes() + words)


def test_a_predicted_residual_that_lies_is_refused():
    from dftpcc.residual import _WEIGHTS, decode_residual, encode_residual

    from . import spec_decoder

    levels = _rough_levels(3, (30, 40))
    kept = np.ones(levels.shape, bool)
    q = levels.ravel()
    blob = encode_residual(q, "ans", kept)
    assert _chunk_kinds(blob) == [coding.KIND_PREDICTED_RESIDUAL]
    payload = blob[20:]
    *weights, listed = _WEIGHTS.unpack_from(payload, 0)
    codes = list(payload[_WEIGHTS.size:_WEIGHTS.size + listed])
    n_coded = sum(1 for c in codes if c)
    widths_at = _WEIGHTS.size + listed
    coded_widths = iter(np.frombuffer(payload, "<u2", count=n_coded, offset=widths_at).tolist())
    widths = [next(coded_widths) if c else 0 for c in codes]
    words = payload[widths_at + 2 * n_coded:]
    assert _predicted_payload(weights, codes, widths, words) == payload

    def chunk(p: bytes) -> bytes:
        return coding.one_chunk(q.size, p, coding.KIND_PREDICTED_RESIDUAL)

    cases = [
        ("implausible header", chunk(_predicted_payload([1 << 24] + weights[1:], codes, widths, words))),
        ("implausible header", chunk(_predicted_payload(weights, codes, [(1 << 15) + 1] * listed, words))),
        ("implausible header", chunk(_WEIGHTS.pack(*weights, 0) + payload[_WEIGHTS.size:])),  # no class listed
        ("implausible header", chunk(_WEIGHTS.pack(*weights, 65) + payload[_WEIGHTS.size:])),
        ("wrong length", chunk(payload + b"\x00")),
        ("wrong length", chunk(payload[:_WEIGHTS.size + 3])),
        ("wrong length", chunk(payload[:10])),
        # Every class coded over 2**15 symbols: tables far beyond what 1,200 values may ask for.
        ("larger probability tables", chunk(_predicted_payload(weights, [128] * 64, [1 << 15] * 64, words))),
        # W weighted 2**23 / 2**16 = 128: each value 128 times its west neighbour's, soon past 2**31.
        ("beyond 2\\*\\*31", chunk(_predicted_payload([1 << 23] + [0] * 6, codes, widths, words))),
    ]
    for message, section in cases:
        with pytest.raises(CorruptFileError, match=message):
            decode_residual(section, kept)
        with pytest.raises(ValueError):
            spec_decoder._residual(section, kept)
    with pytest.raises(CorruptFileError, match="only chunk"):
        decode_residual(coding.one_chunk(q.size - 1, payload, coding.KIND_PREDICTED_RESIDUAL), kept)
    with pytest.raises(CorruptFileError):
        decode_residual(struct.pack("<I", 2) + blob[4:] + blob[4:], kept)


def test_the_residual_layout_is_named_from_its_first_chunk():
    from dftpcc.residual import encode_residual, layout_of

    kept = np.ones((60, 75), bool)
    rough = _rough_levels(7, kept.shape).ravel()
    sparse = np.zeros(kept.size, np.int64)
    sparse[100:110] = 1
    dense = np.round(np.random.default_rng(1).laplace(0, 3, kept.size)).astype(np.int64)
    assert layout_of(encode_residual(rough, "ans", kept)) == "predicted"
    assert layout_of(encode_residual(sparse, "ans", kept)) == "sparse"
    assert layout_of(encode_residual(dense, "ans", kept)) == "chunks"
    assert layout_of(b"") == layout_of(struct.pack("<I", 0)) == "chunks"


@pytest.mark.parametrize("bound", [1e-14, 1e-300])
def test_residual_integers_that_would_wrap_are_refused(bound):
    """Issue 41, item 12: residual.residual cast to int64 without the limit quantizer.quantize has (a cell 1e6 m
    off at a bound of 1e-14 m is 5e19 steps: the cast wrapped to another integer without a word)."""
    from dftpcc.residual import residual

    target = np.array([[1e6, 0.0], [2.0, -3.0]])
    rebuilt = np.zeros_like(target)
    everywhere = np.ones(target.shape, bool)
    with pytest.raises(InvalidInputError, match=rf"target maximum error {bound:g} m is too fine for residuals up to "
                                                r"1e\+06 m.* smallest workable target is [0-9.e+-]+ m"):
        residual(target, rebuilt, everywhere, everywhere, bound)
    q, heights = residual(target, rebuilt, everywhere, everywhere, 1e-3)
    assert np.abs(heights - target).max() <= 1e-3


def test_the_wide_coding_tables_kept_in_cache_stay_few():
    """A slowly decaying band scale's tables are up to a quarter of a megabyte each, and a map's tiles
    ask for hundreds of distinct (bound, scale) pairs: all were kept (390 MB of them decoding a 20,000²
    map), now a few; the narrow ones, small and asked for again and again, keep their large cache."""
    import tracemalloc

    from dftpcc import geometric

    for name in ("table_frequencies", "_wide_frequencies"):
        getattr(getattr(geometric, name, None), "cache_clear", lambda: None)()
    bounds = range(2000, 2300)
    tracemalloc.start()
    try:
        start = tracemalloc.get_traced_memory()[0]
        tables = [geometric.table_frequencies(b, 200)[1].nbytes for b in bounds]  # 8,451 weights: wide tables
        held = tracemalloc.get_traced_memory()[0] - start
    finally:
        tracemalloc.stop()
    one = max(tables)
    assert held < 100 * one < len(bounds) * one / 2, (held, one)
    lo, near = geometric.table_frequencies(2100, 200)  # a cached table is the one built afresh
    fresh = geometric._table_frequencies(2100, 200)
    assert lo == fresh[0] and near.tobytes() == fresh[1].tobytes()
