"""The coefficient order: exact integers since format 1.2, the legacy ``hypot`` order for 1.0 and 1.1.

A float radius ``hypot(i/2, j/2)`` orders ties of ``i² + j²`` by its last bit, which differs
between C libraries: glibc's puts (28, 47) before (17, 52) although 28² + 47² = 17² + 52² = 2993.
Version 1.2 orders by the integer key, ties in row-major order (docs/format.md, *Which
coefficient is which*); files written before keep decoding as they did (tests/legacy, written by
the last 1.0/1.1 writer, with the digests of what its reader decoded).
"""

from __future__ import annotations

import hashlib
import json
import math
import struct
import zlib
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

import dftpcc
from dftpcc import spectrum, tiles
from dftpcc.experiments.terrain import regolith_plain
from dftpcc.format.sections import table

from . import spec_decoder

LEGACY = Path(__file__).parent / "legacy"
EXPECTED = json.loads((LEGACY / "expected.json").read_text())
#: The first key whose pairs glibc's hypot splits, and its pairs in row-major order.
TIE = [(17, 52), (28, 47), (47, 28), (52, 17)]


def _relabel(data: bytes, minor: int) -> bytes:
    """``data`` with another minor version in its preamble, the table's checksum made to match."""
    _entries, start = table(memoryview(data))
    head = bytearray(data[:start - 4])
    head[9] = minor
    return bytes(head) + struct.pack("<I", zlib.crc32(head)) + data[start:]


def _rough(points: np.ndarray) -> np.ndarray:
    """5 cm of white noise on the heights: with a fine step the tie's high frequencies are not 0."""
    out = points.copy()
    out[:, 2] += np.random.default_rng(3).normal(0, 0.05, len(out))
    return out


def _digest(data: bytes) -> str:
    return hashlib.sha256(np.ascontiguousarray(dftpcc.decompress(data), dtype="<f8").tobytes()).hexdigest()


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_legacy_files_decode_as_their_writer_decoded_them(name):
    data = (LEGACY / name).read_bytes()
    want = EXPECTED[name]
    assert data[9] == want["minor"] in (0, 1)
    assert _digest(data) == want["sha256"]
    assert dftpcc.open(data).info()["format_version"] == f"1.{want['minor']}"
    # The document's reader agrees (it implements the legacy hypot from the document).
    np.testing.assert_allclose(spec_decoder.decode(data), dftpcc.decompress(data), rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", ["tie_dct.dftpc", "tie_dft.dftpc", "tie_tiled.dftpc"])
def test_the_tie_fixtures_hold_coefficients_the_two_orders_place_apart(name):
    # Else they would not show that the reader follows the version's rule.
    data = (LEGACY / name).read_bytes()
    assert _digest(_relabel(data, 2)) != EXPECTED[name]["sha256"]


def _positions(order: np.ndarray, cols: int) -> list[int]:
    where = {int(k): n for n, k in enumerate(order)}
    return [where[i * cols + j] for i, j in TIE]


def test_the_integer_order_puts_a_tie_in_row_major_order_where_hypot_did_not():
    lay = spectrum.layout("dct", "quantized", (60, 60))
    legacy = spectrum.layout("dct", "quantized", (60, 60), legacy=True)
    new, old = _positions(spectrum.kept_order(lay, 0.3)[0], 60), _positions(spectrum.kept_order(legacy, 0.3)[0], 60)
    assert new == sorted(new) and new[-1] - new[0] == 3  # consecutive, row-major
    assert old[1] < old[0]  # glibc: (28, 47) first (the legacy rule, as 1.0 files hold it)
    radii = spectrum.kept_order(lay, 0.3)[1][new]
    assert len(set(radii.tolist())) == 1  # equal keys, equal radii: the bands see no last bit either


def test_a_written_map_holding_a_tie_follows_the_integer_order():
    points = _rough(regolith_plain(12000, size=60.0, craters=3, rocks=10, seed=5))
    data = dftpcc.compress(points, resolution=1.0, cutoff=0.3, step=0.002)
    m = dftpcc.open(data)
    assert data[9] == 2 and m.header.grid.shape == (60, 60) and m.info()["format_version"] == "1.2"
    # The stream's values at the tie are the quantized coefficients of those frequencies, in row-major order.
    order = spectrum.kept_order(spectrum.layout("dct", "quantized", (60, 60)), 0.3)[0]
    assert all(i * 60 + j in set(order[:m.header.coef_count].tolist()) for i, j in TIE)
    points_back = dftpcc.decompress(data)
    np.testing.assert_allclose(spec_decoder.decode(data), points_back, rtol=0, atol=1e-9)
    # Read by the legacy rule, the same bytes are another map: the version decides the order.
    assert not np.array_equal(dftpcc.decompress(_relabel(data, 0)), points_back)


def test_a_tiled_map_follows_the_integer_order_in_its_base_layer_and_tiles():
    data = dftpcc.compress(_rough(regolith_plain(20000, size=120.0, craters=4, rocks=20, seed=6)),
                           resolution=1.0, cutoff=0.3, tile_size=64, step=0.002)
    assert data[9] == 2
    np.testing.assert_allclose(spec_decoder.decode(data), dftpcc.decompress(data), rtol=0, atol=1e-9)
    assert not np.array_equal(dftpcc.decompress(_relabel(data, 1)), dftpcc.decompress(data))


@pytest.mark.parametrize("shape", [(10, 10), (60, 60), (741, 702), (37, 5), (1, 1)])
@pytest.mark.parametrize("cutoff", [0.0, 0.2, 0.3, 0.5, 0.8, 0.95, 1 - 2 ** -40])
def test_the_cut_is_the_exact_rational_one(shape, cutoff):
    rows, cols = shape
    bound = Fraction(1.0 - cutoff) ** 2 * Fraction(1 + 1e-12) ** 2 * (rows * rows + cols * cols)
    for kind, transform, storage, c in (("dct", "dct", "quantized", 1), ("half", "dft", "quantized", 4),
                                        ("full", "dft", "complex64", 4)):
        lay = spectrum.layout(transform, storage, shape)
        want = int(np.count_nonzero([c * int(q) <= bound for q in lay.key.ravel()])) if cutoff > 0 else lay.key.size
        assert spectrum.kept_order(lay, cutoff)[0].size == want == spectrum.kept_count(lay, cutoff), kind


def test_a_circle_through_a_key_keeps_it_although_one_minus_the_cutoff_rounds_down():
    # 1 - 0.8 is 0.19999999999999996: without the slack, (2, 2) on a 10 x 10 grid (0.04 * 200 = 8) would go.
    assert 1 - 0.8 < 0.2
    order = spectrum.kept_order(spectrum.layout("dct", "quantized", (10, 10)), 0.8)[0]
    assert order[-1] == 2 * 10 + 2 and order.size == 9  # every (i, j) with i² + j² <= 8, (2, 2) last


def test_the_base_layer_is_cut_by_the_reach_in_exact_arithmetic():
    # 150 x 150 in 64-cell tiles at reach 1: q T² <= 4 S² (K max)²  ->  q <= 4 * (150/64)² * S², i.e. q <= 21.
    i, j, radius, _ = tiles.base_order((150, 150), 64, 0.2, 1)
    q = i * i + j * j
    assert math.floor(4 * Fraction(150, 64) ** 2 * Fraction(1 + 1e-12) ** 2) == 21
    assert sorted(zip(q, i, j)) == list(zip(q, i, j))  # by key, ties in row-major order
    assert {(a, b) for a, b in zip(i, j)} == {(a, b) for a in range(6) for b in range(6) if a * a + b * b <= 21}
    assert np.array_equal(radius, np.sqrt(q) / 2)


def test_a_growing_map_of_version_1_1_is_updated_into_1_2(tmp_path):
    from dftpcc.mapbuilder import MapBuilder, state_path

    from .test_mapbuilder import drive, new_builder

    for name in ("growing.dftpc", "growing.dftpc.state"):
        (tmp_path / name).write_bytes((LEGACY / name).read_bytes())
    path = tmp_path / "growing.dftpc"
    assert path.read_bytes()[9] == 1 and state_path(path).is_file()
    resumed = MapBuilder.from_file(path)  # the state gives the 1.1 file, byte for byte
    assert resumed.changed_tiles() == sorted(resumed._tiles)  # every legacy tile is coded again
    scans = drive(6, heading=3.5, speed=2.5)
    for points, pose in scans[1:3]:
        resumed.add(points, pose)
    once = new_builder()
    for points, pose in scans[:3]:
        once.add(points, pose)
    data = resumed.encode()
    assert data[9] == 2 and data == once.encode()  # what the same scans give a new map
