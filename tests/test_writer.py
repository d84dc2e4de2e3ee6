"""The one writer (format.MapWriter): every map is written through it, and a re-stated map keeps
its sections, tiles included."""

from __future__ import annotations

import numpy as np

import dftpcc
from dftpcc.dem import DEM, Grid
from dftpcc.encoder import encode_dem
from dftpcc.experiments.relocalize import with_reloc_stats
from dftpcc.format import reader, restate
from dftpcc.params import make_params


def _terrain(rows: int = 300, cols: int = 260) -> DEM:
    r, c = np.mgrid[0:rows, 0:cols].astype(float)
    h = 0.02 * c + 0.01 * r + 2 * np.sin(r / 23) * np.cos(c / 31)
    mask = np.ones((rows, cols), dtype=bool)
    mask[100:140, 90:150] = False
    return DEM(grid=Grid(x0=0.0, y0=0.0, z0=0.0, resolution=1.0, rows=rows, cols=cols),
               heights=np.where(mask, h, 0.0), mask=mask)


def _sections(data: bytes) -> list[tuple[bytes, int, bytes]]:
    entries, offset = reader.table(memoryview(data))
    out = []
    for tag, tile, length, _crc in entries:
        out.append((tag, tile, data[offset:offset + length]))
        offset += length
    return out


def test_restating_a_tiled_map_keeps_its_tiles():
    data = encode_dem(_terrain(), make_params(tile_size=128, target_max_error=0.05))
    out = with_reloc_stats(data, 0.75)
    with dftpcc.open(data) as before, dftpcc.open(out) as after:
        assert after.tiled and after.header.stats["reloc_success_fraction"] == 0.75
        assert np.array_equal(after.header.tiles.cells, before.header.tiles.cells)
        a, b = before.read_dem(), after.read_dem()
        assert np.array_equal(a.mask, b.mask) and np.array_equal(a.heights, b.heights)
    # Every section but STAT is the same bytes, in the same order.
    assert [s for s in _sections(data) if s[0] != b"STAT"] == [s for s in _sections(out) if s[0] != b"STAT"]


def test_restating_an_untiled_map_changes_only_its_statistics():
    data = encode_dem(_terrain(120, 100), make_params(target_max_error=0.05))
    out = restate(data, reloc_success_fraction=0.5)
    assert [s for s in _sections(data) if s[0] != b"STAT"] == [s for s in _sections(out) if s[0] != b"STAT"]
    assert restate(out) == out  # nothing added: the same bytes
