"""Damaged and crafted tiled (format 1.1) maps: a damaged tile is named, the others still decode,
and a small file naming a huge grid is refused before anything of its size is allocated.

The corpus (tests/corpus/tiled_*, replayed by tests/test_corrupt.py) holds the lying indexes and
tables; these tests need a decode that succeeds next to one that fails, or a file built here.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

import dftpcc
from dftpcc.errors import CorruptFileError, InvalidInputError, ResourceLimitError

from .fuzz import craft
from .fuzz.seeds import seed_files
from .workbound import measure_work

#: Refusing a crafted tiled file, or decoding one 16 x 16 tile of it: at most this much (bytes) ...
SMALL_BYTES = 4 << 20
#: ... and this many Python events (a loop over the tiles a file names would take far more).
FEW_EVENTS = 60_000


@pytest.fixture(scope="module")
def tiled() -> bytes:
    """40 x 40 cells in 16-cell tiles: 3 x 3 tiles, tile 9 empty."""
    return seed_files()["tiled"]


def _tile_box(cmap, k: int) -> list[float]:
    """A bbox of the centres of tile k's cells (1-based), inside the tile by a quarter cell."""
    tiling = cmap.header.tiles.tiling
    r0, r1, c0, c1 = tiling.bounds(k - 1)
    g = cmap.grid
    return [g.x0 + (c0 + 0.25) * g.resolution, g.y0 + (r0 + 0.25) * g.dy,
            g.x0 + (c1 - 0.25) * g.resolution, g.y0 + (r1 - 0.25) * g.dy]


def _flip_in(data: bytes, tag: bytes, tile: int) -> bytes:
    start, length = next((off, n) for t, k, off, n, _crc in craft.table(data) if t == tag and k == tile)
    buf = bytearray(data)
    buf[start + length // 2] ^= 0x08
    return bytes(buf)


@pytest.mark.parametrize("tag", [b"MASK", b"COEF"])
@pytest.mark.parametrize("tile", [1, 5, 8])
def test_a_damaged_tile_is_named_and_the_others_still_decode(tiled, tag, tile):
    damaged = _flip_in(tiled, tag, tile)
    name = tag.decode()
    with measure_work(max_events=FEW_EVENTS) as work:
        with pytest.raises(CorruptFileError, match=rf"^tile {tile} \(tile row \d, column \d\): section {name} "
                                                   "fails its checksum"):
            dftpcc.open(damaged).read_points()
    assert work.peak_bytes < SMALL_BYTES, work
    with pytest.raises(CorruptFileError, match=rf"^tile {tile} "):
        dftpcc.decompress(damaged)
    # Another tile (2 or 4, neighbours of the damaged one) decodes as from the sound file.
    other = 2 if tile != 2 else 4
    with dftpcc.open(tiled) as sound, dftpcc.open(damaged) as cmap:
        box = _tile_box(cmap, other)
        np.testing.assert_array_equal(cmap.read_points(bbox=box), sound.read_points(bbox=box))
        assert cmap.read_points(bbox=box).shape[0] == cmap.header.tiles.cells[other - 1]
        with pytest.raises(CorruptFileError, match=rf"^tile {tile} "):
            cmap.read_points(bbox=_tile_box(cmap, tile))


def test_a_file_cut_inside_a_tile_decodes_the_tiles_before(tiled, tmp_path):
    """Read by offset from a path, a cut file still yields its whole tiles; the cut one is named."""
    path = tmp_path / "cut.dftpc"
    path.write_bytes(tiled[:-3])  # inside tile 8's COEF, the last section
    with dftpcc.open(path) as cmap, dftpcc.open(tiled) as sound:
        box = _tile_box(cmap, 1)
        np.testing.assert_array_equal(cmap.read_points(bbox=box), sound.read_points(bbox=box))
        with pytest.raises(CorruptFileError, match=r"^tile 8 .*truncated"):
            cmap.read_points()


def test_a_tiled_map_refuses_progressive_decoding_and_a_cutoff(tiled):
    with pytest.raises(InvalidInputError, match="no progressive decoding"):
        dftpcc.open(tiled, max_bytes=len(tiled) - 10)
    with pytest.raises(InvalidInputError, match="own cutoff"):
        dftpcc.open(tiled).read_points(cutoff=0.95)
    with pytest.raises(InvalidInputError, match="own cutoff"):
        dftpcc.decompress(tiled, cutoff=0.95)


def test_the_spec_decoder_names_the_same_damaged_tile(tiled):
    from . import spec_decoder

    with pytest.raises(ValueError, match=r"^tile 5: section b'COEF' fails its checksum"):
        spec_decoder.decode(_flip_in(tiled, b"COEF", 5))


# --- a small file naming a huge grid ----------------------------------------------------------------

#: 64 x 64 tiles of 4096 cells, the last row and column 16 cells: 6.6e10 cells (2**36 is the format's
#: limit), one occupied 16 x 16 tile, and a file of about 1 KB.
SPARSE_TILE = 4096
SPARSE_SIDE = 63 * SPARSE_TILE + 16


@pytest.fixture(scope="module")
def sparse() -> bytes:
    last = (SPARSE_SIDE // SPARSE_TILE + 1) ** 2
    return craft.tiled_file(SPARSE_SIDE, SPARSE_SIDE, SPARSE_TILE, {last: 200})


def test_a_huge_nearly_empty_grid_is_refused_whole_before_allocating(sparse):
    assert len(sparse) < 4_000
    for decode in (lambda: dftpcc.open(sparse).read_points(), lambda: dftpcc.decompress(sparse)):
        with measure_work(max_events=FEW_EVENTS) as work:
            with pytest.raises(ResourceLimitError, match=r"refusing to decode [\d,]+ cells") as info:
                decode()
        assert work.peak_bytes < SMALL_BYTES, work
        # Every cell of the grid counts, empty tiles too: the DEM decoded would span them.
        asked = int(re.search(r"decode ([\d,]+) cells", str(info.value)).group(1).replace(",", ""))
        assert asked >= SPARSE_SIDE**2


def test_the_one_occupied_tile_of_a_huge_grid_decodes_alone(sparse):
    with dftpcc.open(sparse) as cmap:
        box = _tile_box(cmap, cmap.header.tiles.tiling.count)
        with measure_work(max_events=FEW_EVENTS) as work:
            points = cmap.read_points(bbox=box)
    assert work.peak_bytes < SMALL_BYTES, work
    assert points.shape == (200, 3) and np.isfinite(points).all()
    # The 200 cells are the first of the 16 x 16 tile, row-major, at height 0 (every coefficient is 0).
    np.testing.assert_array_equal(points[:, 2], 0.0)
    assert cmap.info()["tiles"]["occupied"] == 1


def test_a_base_layer_of_millions_of_coefficients_in_a_kilobyte_is_refused():
    """A strip of 2048-cell tiles at cutoff 0: 8.4 million base coefficients, all zero, code in 1.5 KB."""
    data = (Path(__file__).resolve().parent / "corpus" / "tiled_base_bomb.dftpc").read_bytes()
    with dftpcc.open(data) as cmap:
        box = _tile_box(cmap, cmap.header.tiles.tiling.count)  # one small tile: the base alone is too much
        with measure_work(max_events=FEW_EVENTS) as work:
            with pytest.raises(ResourceLimitError, match="refusing to decode"):
                cmap.read_points(bbox=box)
    assert work.peak_bytes < SMALL_BYTES, work


def test_the_base_layer_counts_at_the_reach_the_index_states():
    """TIDX may state any base reach (a u8; here 8 cycles per tile): the budget counts the base layer's
    frequency pairs at that reach, not at the 1 cycle dftpcc writes, so a 374-byte file cannot make
    one 16 x 16 tile's decode enumerate 4 million of them."""
    crafted = craft.tiled_file(2048, 2048, 16, {1: 200}, cutoff=0.0, reach=8)
    assert len(crafted) < 1_000
    with dftpcc.open(crafted) as cmap:
        assert cmap.header.tiles.base_cycles == 8
        with measure_work(max_events=FEW_EVENTS) as work:
            with pytest.raises(ResourceLimitError, match=r"refusing to decode 4,194,560 cells"):
                cmap.read_points(bbox=_tile_box(cmap, 1))
    assert work.peak_bytes < SMALL_BYTES, work
    # At the reach dftpcc writes, the same map's tile decodes within the budget.
    with dftpcc.open(craft.tiled_file(2048, 2048, 16, {1: 200}, cutoff=0.0)) as cmap:
        assert cmap.read_points(bbox=_tile_box(cmap, 1)).shape == (200, 3)


TILED_SEEDS = ["tiled", "tiled_max_error_zstd", "tiled_max_error_sparse", "tiled_map_mask_max_error",
               "tiled_max_error_predicted", "tiled_map_residual", "tiled_map_mask", "tiled_base_only"]


@pytest.mark.parametrize("seed", TILED_SEEDS)
def test_every_damaged_section_of_every_tile_is_named_with_its_tile(seed):
    """Issue 41, item 11: a byte flipped at the start or end of any section of any tile (RESD
    included, tile 0's too) is refused, and the error names the section and, beyond tile 0, the tile."""
    data = seed_files()[seed]
    table = craft.table(data)
    assert any(tile > 0 for _tag, tile, *_ in table) or seed in ("tiled_map_residual", "tiled_base_only")
    if seed != "tiled":
        assert any(tag == b"RESD" for tag, *_ in table) or seed in ("tiled_map_mask", "tiled_base_only")
    tiling = dftpcc.open(data).header.tiles.tiling
    for tag, tile, offset, length, _crc in table:
        name = tag.decode().strip()
        if tile == 0:
            expected = rf"^section {name} fails its checksum"
        else:
            row, column = divmod(tile - 1, tiling.tile_cols)
            expected = rf"^tile {tile} \(tile row {row}, column {column}\): section {name} fails its checksum"
        for pos in sorted({offset, offset + length - 1}):  # its first and last byte
            buf = bytearray(data)
            buf[pos] ^= 0x10
            with pytest.raises(CorruptFileError, match=expected):
                dftpcc.open(bytes(buf)).read_points()
