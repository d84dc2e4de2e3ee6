"""Quantization, coefficient chunks and the occupancy mask."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from dftpcc import coding
from dftpcc.errors import CorruptFileError


@given(hnp.arrays(np.float64, st.integers(1, 500), elements=st.floats(-1e4, 1e4)),
       st.floats(1e-3, 10.0), st.floats(0.0, 0.45))
@settings(max_examples=60, deadline=None)
def test_quantizer_error_is_bounded(values, step, deadzone):
    q = coding.quantize(values, step, deadzone)
    err = np.abs(values - coding.dequantize(q, step))
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
    step = coding.choose_step(values, target_rmse=0.01, n_cells=10000, deadzone=0.2)
    err = values - coding.dequantize(coding.quantize(values, step, 0.2), step)
    assert np.sqrt(np.sum(err**2) / 10000) <= 0.01
    # and it is not needlessly fine: twice the step breaks the target
    err2 = values - coding.dequantize(coding.quantize(values, 2 * step, 0.2), 2 * step)
    assert np.sqrt(np.sum(err2**2) / 10000) > 0.01
