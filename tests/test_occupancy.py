"""The occupancy mask coder: exact round trips, stripes, and damaged input."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import zstandard
from hypothesis import given, settings
from hypothesis import strategies as st

from dftpcc import occupancy
from dftpcc.errors import CorruptFileError


def _blob_parts(blob: bytes) -> tuple[int, int, bytes, bytes]:
    """kind, stripe, seed frame, ANS words of a context-coded mask."""
    kind, _ = occupancy._HEAD.unpack_from(blob, 0)
    stripe, seed_bytes = occupancy._STRIPES.unpack_from(blob, occupancy._HEAD.size)
    at = occupancy._HEAD.size + occupancy._STRIPES.size
    return kind, stripe, blob[at:at + seed_bytes], blob[at + seed_bytes:]


def _context_blob(head: bytes, stripe: int, seeds: bytes, words: bytes) -> bytes:
    return head + occupancy._STRIPES.pack(stripe, len(seeds)) + seeds + words


def _footprint(rows: int, cols: int, seed: int) -> np.ndarray:
    """A blob-shaped footprint with a few holes, like a rover's map."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:rows, 0:cols]
    r = np.hypot((y - rows / 2) / rows, (x - cols / 2) / cols)
    return (r < 0.4 + 0.05 * np.sin(x / 7.0)) & (rng.random((rows, cols)) > 0.02)


@given(st.integers(1, 40), st.integers(1, 40), st.integers(1, 50), st.floats(0, 1), st.integers(0, 2**32 - 1))
@settings(max_examples=80, deadline=None)
def test_any_mask_round_trips_with_any_stripe(rows, cols, stripe, density, seed):
    mask = np.random.default_rng(seed).random((rows, cols)) < density
    blob = occupancy.encode_mask(mask, stripe=stripe)
    np.testing.assert_array_equal(occupancy.decode_mask(blob, mask.shape), mask)


@pytest.mark.parametrize("shape", [(700, 900), (900, 700)])
def test_large_masks_are_striped_and_stripes_cost_little(shape):
    mask = _footprint(*shape, seed=1)
    assert mask.size >= occupancy.STRIPED_CELLS
    striped = occupancy.encode_mask(mask)
    kind, stripe, seeds, _ = _blob_parts(striped)
    assert (kind, stripe) == (occupancy.KIND_CONTEXT, occupancy.STRIPE_LINES)
    assert seeds  # one seed line per stripe after the first
    np.testing.assert_array_equal(occupancy.decode_mask(striped, shape), mask)
    single = occupancy.encode_mask(mask, stripe=max(shape))
    assert _blob_parts(single)[1] == min(shape) and not _blob_parts(single)[2]
    assert len(striped) <= 1.1 * len(single)


def test_small_masks_use_one_stripe():
    mask = _footprint(60, 80, seed=2)
    kind, stripe, seeds, _ = _blob_parts(occupancy.encode_mask(mask))
    assert (kind, stripe, seeds) == (occupancy.KIND_CONTEXT, 60, b"")


def test_a_compact_footprint_costs_a_few_hundred_bytes():
    y, x = np.mgrid[0:300, 0:400]
    mask = np.hypot((y - 150) / 300, (x - 200) / 400) < 0.4 + 0.05 * np.sin(x / 7.0)
    blob = occupancy.encode_mask(mask)
    assert len(blob) < 500
    assert len(blob) < 0.5 * len(zstandard.compress(np.packbits(mask).tobytes(), 19))


def test_noise_falls_back_to_the_bitmap():
    mask = np.random.default_rng(4).random((50, 64)) < 0.5
    blob = occupancy.encode_mask(mask)
    assert blob[0] == occupancy.KIND_ZSTD
    np.testing.assert_array_equal(occupancy.decode_mask(blob, mask.shape), mask)


@pytest.fixture(scope="module")
def striped():
    mask = _footprint(200, 150, seed=5)
    blob = occupancy.encode_mask(mask, stripe=16)
    return mask, blob, _blob_parts(blob)


def test_the_striped_blob_decodes(striped):
    mask, blob, _ = striped
    np.testing.assert_array_equal(occupancy.decode_mask(blob, mask.shape), mask)


def _runs_frame(values: list[int]) -> bytes:
    planes = np.asarray(values, dtype="<u4").view(np.uint8).reshape(-1, 4).T
    return zstandard.compress(planes.tobytes())


@pytest.mark.parametrize("damage, message", [
    ("stripe zero", "wrong length"),
    ("seeds too long", "wrong length"),
    ("words cut", "wrong length"),
    ("seeds dropped", "seed lines"),
    ("runs do not add up", "does not add up"),
    ("trailing seed data", "trailing data"),
    ("seed bomb", "declares"),
    ("seeds not zstd", "does not decompress"),
    ("unneeded seeds", "seed lines it does not need"),
    ("pre-release kind 1", "unknown coding 1"),
])
def test_damaged_masks_are_refused(striped, damage, message):
    mask, blob, (kind, stripe, seeds, words) = striped
    head = blob[:occupancy._HEAD.size]
    width = mask.shape[0]  # transposed: lines run along the 200 rows
    n_seeds = -(-mask.shape[1] // stripe) - 1
    bad = {
        "stripe zero": lambda: _context_blob(head, 0, seeds, words),
        "seeds too long": lambda: head + occupancy._STRIPES.pack(stripe, len(seeds) + 10**6) + seeds + words,
        "words cut": lambda: _context_blob(head, stripe, seeds, words[:-1]),
        "seeds dropped": lambda: _context_blob(head, stripe, b"", words),
        "runs do not add up": lambda: _context_blob(head, stripe, _runs_frame([2, 5, width] * n_seeds), words),
        "trailing seed data": lambda: _context_blob(head, stripe, _runs_frame([1, width] * n_seeds + [7]), words),
        "seed bomb": lambda: _context_blob(head, stripe, zstandard.compress(bytes(10**7)), words),
        "seeds not zstd": lambda: _context_blob(head, stripe, b"\x00" * 12, words),
        "unneeded seeds": lambda: _context_blob(head, mask.shape[1], seeds, words),
        "pre-release kind 1": lambda: struct.pack("<BB", 1, 1) + blob[occupancy._HEAD.size:],
    }[damage]()
    with pytest.raises(CorruptFileError, match=message):
        occupancy.decode_mask(bad, mask.shape)


def test_random_words_never_crash(striped):
    mask, blob, (kind, stripe, seeds, words) = striped
    rng = np.random.default_rng(6)
    head = blob[:occupancy._HEAD.size]
    for _ in range(50):
        noise = rng.integers(0, 256, len(words) // 4 * 4, dtype=np.uint8).tobytes()
        try:
            out = occupancy.decode_mask(_context_blob(head, stripe, seeds, noise), mask.shape)
        except CorruptFileError:
            continue
        assert out.shape == mask.shape and out.dtype == bool


def _tile_of_a_map(rows: int, cols: int, seed: int) -> np.ndarray:
    """A tile cut from the middle of a footprint: its first line runs through occupied cells."""
    return _footprint(3 * rows, 3 * cols, seed)[rows:2 * rows, cols:2 * cols]


@pytest.mark.parametrize("shape", [(200, 300), (300, 200), (600, 520)])
def test_a_tile_cut_through_the_map_sends_its_first_line_as_a_seed(shape):
    # Kind 2 codes the first line's occupied cells in the empty context, at about 4 bits each,
    # and teaches the empty context to expect them; kind 3 sends the line as run lengths.
    tile = _tile_of_a_map(*shape, seed=3)
    first_line = tile[0] if shape[0] <= shape[1] else tile[:, 0]
    assert first_line.mean() > 0.5
    kind2 = occupancy.encode_mask(tile)
    kind3 = occupancy.encode_mask(tile, first_seed=True)
    assert kind2[0] == occupancy.KIND_CONTEXT and kind3[0] == occupancy.KIND_SEEDED
    # About 4 bits of each of the line's occupied cells (not 8 of them: the counts matter too).
    assert len(kind2) - len(kind3) >= first_line.sum() * 4 / 8 * 0.8
    np.testing.assert_array_equal(occupancy.decode_mask(kind3, tile.shape), tile)
    # Its frame holds a seed for every stripe, the first included.
    _, stripe, seeds, _ = _blob_parts(kind3)
    n_stripes = -(-min(shape) // min(stripe, min(shape)))
    lines = tile.T if shape[0] > shape[1] else tile
    np.testing.assert_array_equal(occupancy._decode_seeds(seeds, n_stripes, max(shape)),
                                  lines[::min(stripe, min(shape))])


def test_an_empty_first_line_keeps_kind_2():
    # The map's own edge: nothing to gain from a seed, and the 1.0 bytes stay.
    mask = _footprint(120, 90, seed=4)
    assert not mask[:, 0].any() and not mask[0].any()
    assert occupancy.encode_mask(mask, first_seed=True) == occupancy.encode_mask(mask)


@given(st.integers(1, 40), st.integers(1, 40), st.integers(1, 50), st.floats(0, 1), st.integers(0, 2**32 - 1))
@settings(max_examples=60, deadline=None)
def test_kind_3_round_trips_with_any_stripe(rows, cols, stripe, density, seed):
    mask = np.random.default_rng(seed).random((rows, cols)) < density
    transposed = rows > cols
    lines = (mask.T if transposed else mask).astype(np.uint8)
    blob = occupancy._HEAD.pack(occupancy.KIND_SEEDED, transposed) + occupancy._encode_context(
        lines, min(stripe, lines.shape[0]), first_seed=True)
    np.testing.assert_array_equal(occupancy.decode_mask(blob, mask.shape), mask)
