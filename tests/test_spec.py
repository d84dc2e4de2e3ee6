"""docs/format.md is enough to read a file: an independent decoder agrees with dftpcc.decompress.

`tests/spec_decoder.py` was written from the format document alone. These tests compress
synthetic terrains with many option sets and check that it rebuilds exactly the points
`dftpcc.decompress` does, and that the files exercised every coding the document defines.
"""

from __future__ import annotations

import json
import struct
import zlib

import numpy as np
import pytest

import dftpcc

from . import spec_decoder
from .fuzz import craft

ATOL = 1e-9


def terrain(seed: int, width: float, height: float, n: int, *, holes: bool = True) -> np.ndarray:
    """A smooth surface plus noise on an irregular (wavy ellipse, with holes) footprint."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 1, (n, 2)) * [width, height]
    u, v = xy[:, 0] / width - 0.5, xy[:, 1] / height - 0.5
    theta = np.arctan2(v, u)
    keep = u**2 + v**2 < 0.235 * (1 + 0.06 * np.sin(5 * theta))
    if holes:
        keep &= np.hypot(u - 0.15, v + 0.1) > 0.06
        keep &= (np.sin(xy[:, 0] / 3.0) > -0.9) | (np.abs(v) > 0.2)  # thin gaps
    xy = xy[keep]
    z = (3 * np.sin(xy[:, 0] / 37) + 2 * np.cos(xy[:, 1] / 23)
         + 0.002 * xy[:, 0] * xy[:, 1] / width + 0.05 * xy[:, 0] / width
         + rng.normal(0, 0.05, len(xy)))
    return np.column_stack([xy + [4.5e5, 5.2e6], z + 120.0])


def rotated_strip(seed: int) -> np.ndarray:
    """A diagonal traverse strip (40 m x 400 m at 0.6 rad), for frame='oriented'."""
    rng = np.random.default_rng(seed)
    t = rng.uniform(0, 400, 60_000)
    s = rng.uniform(-20, 20, 60_000)
    a = 0.6
    x = t * np.cos(a) - s * np.sin(a)
    y = t * np.sin(a) + s * np.cos(a)
    z = 0.01 * t + np.sin(t / 15) + 0.3 * np.cos(s / 5) + rng.normal(0, 0.02, len(t))
    return np.column_stack([x + 5e5, y + 4e6, z + 100])


@pytest.fixture(scope="module")
def small() -> np.ndarray:
    return terrain(1, 90, 70, 25_000)


@pytest.fixture(scope="module")
def large() -> np.ndarray:
    """600 x 500 cells (more than 2**18), about 270 000 points: a striped mask."""
    return terrain(2, 600, 500, 380_000)


@pytest.fixture(scope="module")
def tall() -> np.ndarray:
    """500 x 600 cells, taller than wide: a striped mask coded along the columns."""
    return terrain(3, 500, 600, 380_000)


def check(data: bytes) -> dict[bytes, bytes]:
    """Assert the spec decoder rebuilds what dftpcc does; return the file's sections."""
    expected = dftpcc.decompress(data)
    got = spec_decoder.decode(data)
    assert got.dtype == np.float64
    assert got.shape == expected.shape
    np.testing.assert_allclose(got, expected, rtol=0, atol=ATOL)
    return spec_decoder._sections(data)


def chunk_kinds(payload: bytes) -> set[int]:
    (count,), pos, kinds = struct.unpack_from("<I", payload, 0), 4, set()
    for _ in range(count):
        _, nbytes, _, kind = struct.unpack_from("<4I", payload, pos)
        kinds.add(kind)
        pos += 16 + nbytes
    return kinds


def rebuild_file(sections: dict[bytes, bytes]) -> bytes:
    """Lay sections out as format.md describes (preamble, table, table CRC, payloads)."""
    order = [b"GEOM", b"PARM", b"CRS ", b"STAT", b"MASK", b"COEF", b"RESD"]
    tags = [t for t in order if t in sections]
    table, body = b"", b""
    for tag in tags:
        p = sections[tag]
        table += craft.entry(tag, 0, len(p), zlib.crc32(p))
        body += p
    top = spec_decoder.MAGIC + struct.pack("<BBHI", 1, 0, 0, len(tags)) + table
    return top + struct.pack("<I", zlib.crc32(top)) + body


# --------------------------------------------------------------------------- option sets

SMALL_OPTIONS = {
    "default": {},
    "paper": {"profile": "paper"},
    "dft-compact": {"transform": "dft"},
    "zstd": {"coder": "zstd"},
    "footprint": {"mask": "footprint"},
    "cutoff-0": {"cutoff": 0.0},
    "cutoff-0.9": {"cutoff": 0.9},
    "max-error": {"target_max_error": 0.03},
    "max-error-dft-zstd": {"target_max_error": 0.03, "transform": "dft", "coder": "zstd"},
    "paper-cutoff-0": {"profile": "paper", "cutoff": 0.0},
    "dft-cutoff-0": {"transform": "dft", "cutoff": 0.0},
    "dft-zstd-0.9": {"transform": "dft", "coder": "zstd", "cutoff": 0.9},
    "footprint-max-error": {"mask": "footprint", "target_max_error": 0.05},
    # A coarse bound: a residual of mostly zeros, one sparse chunk (RESD kind 4).
    "max-error-coarse": {"target_max_error": 0.15},
    # A step so fine that the lowest frequencies pass MAX_ANS_SYMBOL: zstd chunks, then ANS ones.
    "fine-step": {"cutoff": 0.5, "step": 1e-4},
    "target-rmse": {"target_rmse": 0.05},
}


@pytest.mark.parametrize("options", SMALL_OPTIONS.values(), ids=SMALL_OPTIONS.keys())
def test_small_map(small, options):
    sections = check(dftpcc.compress(small, resolution=1.0, **options))
    assert (b"RESD" in sections) == ("target_max_error" in options)


@pytest.mark.parametrize("resolution", [0.5, 0.7, 1.3])
def test_small_map_other_grids(small, resolution):
    for options in ({}, {"transform": "dft"}, {"profile": "paper"}):
        check(dftpcc.compress(small, resolution=resolution, **options))


LARGE_OPTIONS = {name: SMALL_OPTIONS[name] for name in
                 ("default", "paper", "dft-compact", "zstd", "footprint", "cutoff-0", "cutoff-0.9")}
LARGE_OPTIONS["max-error"] = {"target_max_error": 0.1}


@pytest.mark.parametrize("options", LARGE_OPTIONS.values(), ids=LARGE_OPTIONS.keys())
def test_large_map_striped_mask(large, options):
    sections = check(dftpcc.compress(large, resolution=1.0, **options))
    g = spec_decoder._geom(sections[b"GEOM"])
    assert g["rows"] * g["cols"] > 2**18
    mask = sections[b"MASK"]
    stripe, seed_bytes = struct.unpack_from("<II", mask, 2)
    assert mask[:2] == b"\x02\x00" and stripe < g["rows"] and seed_bytes > 0


@pytest.mark.parametrize("options", [{}, {"mask": "footprint", "transform": "dft"}],
                         ids=["default", "footprint-dft"])
def test_tall_map_transposed_striped_mask(tall, options):
    sections = check(dftpcc.compress(tall, resolution=1.0, **options))
    g = spec_decoder._geom(sections[b"GEOM"])
    assert g["rows"] > g["cols"] and g["rows"] * g["cols"] > 2**18
    mask = sections[b"MASK"]
    stripe, seed_bytes = struct.unpack_from("<II", mask, 2)
    assert mask[:2] == b"\x02\x01" and stripe < g["cols"] and seed_bytes > 0


@pytest.mark.parametrize("options", [{}, {"profile": "paper"}, {"transform": "dft"},
                                     {"target_max_error": 0.02}],
                         ids=["default", "paper", "dft", "max-error"])
def test_oriented_frame(options):
    sections = check(dftpcc.compress(rotated_strip(4), resolution=1.0, frame="oriented",
                                     **options))
    g = spec_decoder._geom(sections[b"GEOM"])
    assert abs(g["angle"]) > 0.1


def test_zstd_mask():
    """A scattered footprint whose mask the writer codes as a zstd bitmap (kind 0)."""
    rng = np.random.default_rng(5)
    xy = rng.uniform(0, 40, (1000, 2))
    points = np.column_stack([xy, 0.1 * np.sin(xy[:, 0] / 5) + rng.normal(0, 0.1, len(xy))])
    for options in ({}, {"profile": "paper"}, {"transform": "dft", "coder": "zstd"}):
        sections = check(dftpcc.compress(points, resolution=1.0, **options))
        assert sections[b"MASK"][0] == 0


@pytest.mark.parametrize("rows", [49, 96, 103, 239])
def test_dft_tied_radii(rows):
    """Grids whose row frequencies are not exact in floating point (see the decoder's layout)."""
    rng = np.random.default_rng(rows)
    xy = rng.uniform(0, 1, (rows * 60, 2)) * [60, rows]
    keep = (xy[:, 0] / 60 - 0.5) ** 2 + (xy[:, 1] / rows - 0.5) ** 2 < 0.25
    xy = xy[keep]
    z = np.sin(xy[:, 0] / 7) + np.cos(xy[:, 1] / 5) + rng.normal(0, 0.05, len(xy))
    points = np.column_stack([xy, z])
    for cutoff in (0.3, 0.8):
        sections = check(dftpcc.compress(points, resolution=1.0, transform="dft", cutoff=cutoff))
        assert spec_decoder._geom(sections[b"GEOM"])["rows"] == rows


def rough(seed: int, rows: int, cols: int, *, holes: bool = True) -> np.ndarray:
    """A rough surface (integrated noise), a point per cell of 1 m, a hole in it: at a fine bound
    its cheapest residual layer is predicted (RESD kind 5)."""
    rng = np.random.default_rng(seed)
    z = np.cumsum(np.cumsum(rng.normal(0, 0.3, (rows, cols)), 0), 1) * 0.1 + rng.normal(0, 0.02, (rows, cols))
    yy, xx = np.mgrid[:rows, :cols] + 0.5
    keep = np.hypot(yy - rows / 3, xx - cols / 2) > rows / 6 if holes else np.ones((rows, cols), bool)
    return np.column_stack([xx[keep] + 4.5e5, yy[keep] + 5.2e6, z[keep] + 300.0])


@pytest.mark.parametrize("holes", [False, True])
@pytest.mark.parametrize("bound", [0.005, 0.02])
def test_a_rough_map_has_a_predicted_residual_layer(holes, bound):
    data = dftpcc.compress(rough(3, 40, 52, holes=holes), resolution=1.0, target_max_error=bound)
    sections = check(data)
    assert chunk_kinds(sections[b"RESD"]) == {5}
    got = dftpcc.decompress(data)
    pts = rough(3, 40, 52, holes=holes)
    order = np.lexsort((pts[:, 0], pts[:, 1]))  # the rebuilt points are row-major, one per cell
    assert got.shape == pts.shape
    assert np.abs(got[:, 2] - pts[order, 2]).max() <= bound


def test_every_coding_is_exercised(small):
    """The option sets above reach every MASK and COEF kind the document defines."""
    kinds = set()
    for options in ({}, {"coder": "zstd"}, {"profile": "paper"}):
        sections = spec_decoder._sections(dftpcc.compress(small, resolution=1.0, **options))
        kinds |= chunk_kinds(sections[b"COEF"])
    assert kinds == {0, 1, 3}
    # A stream's chunks may mix the integer kinds; a coarse bound's residual is one sparse chunk.
    fine = spec_decoder._sections(dftpcc.compress(small, resolution=1.0, **SMALL_OPTIONS["fine-step"]))
    assert chunk_kinds(fine[b"COEF"]) == {0, 3}
    coarse = spec_decoder._sections(dftpcc.compress(small, resolution=1.0, **SMALL_OPTIONS["max-error-coarse"]))
    assert chunk_kinds(coarse[b"RESD"]) == {4}
    # Rough terrain at a fine bound: the residual is the map, predicted (kind 5).
    predicted = spec_decoder._sections(dftpcc.compress(rough(3, 40, 52), resolution=1.0, target_max_error=0.01))
    assert chunk_kinds(predicted[b"RESD"]) == {5}


# --------------------------------------------------------------------------- crafted headers

def test_row_spacing_and_short_geometry(small):
    """Non-square cells (GEOM row spacing) and an 88-byte GEOM (square cells)."""
    data = dftpcc.compress(small, resolution=1.0)
    sections = spec_decoder._sections(data)
    geom = sections[b"GEOM"]
    assert len(geom) == 88  # square cells: the row spacing is left out
    stretched = geom[:88] + struct.pack("<d", 1.75)
    for new in (stretched, geom[:88] + struct.pack("<d", 0.0)):
        crafted = rebuild_file({**sections, b"GEOM": new})
        check(crafted)
    points = spec_decoder.decode(rebuild_file({**sections, b"GEOM": stretched}))
    base = spec_decoder.decode(data)
    g = spec_decoder._geom(geom)
    np.testing.assert_allclose((points[:, 1] - g["y0"]) / 1.75, base[:, 1] - g["y0"], atol=1e-6)


def test_refusals(small):
    data = dftpcc.compress(small, resolution=1.0)
    sections = spec_decoder._sections(data)
    bad = [b"\x88" + data[1:],                                   # magic
           data[:8] + b"\x02" + data[9:],                        # major version
           data[:-1] + bytes([data[-1] ^ 1]),                    # a section's CRC
           rebuild_file({k: v for k, v in sections.items() if k != b"COEF"}),
           rebuild_file({**sections, b"MASK": b"\x01" + sections[b"MASK"][1:]})]
    for crafted in bad:
        with pytest.raises(dftpcc.DftpccError):
            dftpcc.decompress(crafted)
        with pytest.raises(ValueError):
            spec_decoder.decode(crafted)


# --------------------------------------------------------------------------- tiles (version 1.1)

def check_tiled(data: bytes) -> dict:
    """Assert the spec decoder rebuilds a tiled file as dftpcc does (points and mask); return its
    layout: ``sections`` (tile 0), ``entries`` (the table), ``cells`` per tile, ``size`` T, ``grid``."""
    assert data[8:10] == b"\x01\x02", "not a version 1.2 file"
    check(data)
    mask, _heights = spec_decoder.decode_grid(data)
    np.testing.assert_array_equal(mask, dftpcc.open(data).read_dem().mask)
    sections = spec_decoder._sections(data)
    g = spec_decoder._geom(sections[b"GEOM"])
    size = spec_decoder._json(sections[b"PARM"])["tile_size"]
    n = -(-g["rows"] // size) * -(-g["cols"] // size)
    _overlap, _reach, cells, _rmse, _max = spec_decoder._tile_index(sections[b"TIDX"], n, size)
    return {"sections": sections, "entries": spec_decoder._table(data)[1], "cells": cells, "size": size,
            "grid": g}


def tile_shapes(layout: dict) -> list[tuple[int, int]]:
    g, size = layout["grid"], layout["size"]
    tx = -(-g["cols"] // size)
    boxes = [spec_decoder._tile_box(k, g["rows"], g["cols"], size, tx) for k in range(1, len(layout["cells"]) + 1)]
    return [(r1 - r0, c1 - c0) for r0, r1, c0, c1 in boxes]


def synthetic_dem(rows: int, cols: int, seed: int = 0, *, holes: bool = True):
    """A DEM of exactly rows x cols cells (1 m): waves, a slope and noise; holes in a disc and a band."""
    from dftpcc.dem import DEM, Grid

    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:rows, 0:cols]
    heights = (2 * np.sin(c / 9.0) + np.cos(r / 13.0) + 0.01 * r + 0.003 * c
               + rng.normal(0, 0.02, (rows, cols)))
    mask = np.ones((rows, cols), bool)
    if holes:
        mask &= np.hypot(r - 0.6 * rows, c - 0.3 * cols) > 0.15 * min(rows, cols)
        mask &= (r + c) % 37 != 0
    return DEM(Grid(4.5e5, 5.2e6, 100.0, 1.0, rows, cols), heights, mask, gridding_rmse=0.0)


def encode_tiled(dem, **options) -> bytes:
    from dftpcc import encoder

    return encoder.encode_dem(dem, dftpcc.make_params(resolution=dem.grid.resolution, **options))


def test_tiled_real_dem(tmp_path):
    """The Gale crater DEM (337 x 348 cells) in 128-cell tiles: 3 x 3, the last row and column 81 and 92."""
    from .conftest import data_file

    out = tmp_path / "gale.dftpc"
    dftpcc.compress_file(data_file("dems/mars_gale_1m.tif"), out, tile_size=128)
    layout = check_tiled(out.read_bytes())
    assert (layout["grid"]["rows"], layout["grid"]["cols"]) == (337, 348)
    assert tile_shapes(layout)[-1] == (81, 92)


def test_tiled_point_cloud_with_empty_tiles(field_ground, tile_masks):
    """The IGN field's quarter disc at 1 m in 128-cell tiles: a corner tile holds no cell, no section."""
    data = dftpcc.compress(field_ground, resolution=1.0, tile_size=128)
    layout = check_tiled(data)
    empty = [k + 1 for k, c in enumerate(layout["cells"]) if c == 0]
    assert empty, layout["cells"]
    assert not {tile for _tag, tile, *_ in layout["entries"]} & set(empty)
    # Tiles whose first line cuts through the field send it as a seed (MASK kind 3), the others not.
    kinds = {payload[0] for tag, _k, payload in craft.split_tiled(data) if tag == b"MASK"}
    assert {2, 3} <= kinds, kinds


@pytest.mark.parametrize("target", [dict(target_rmse=0.05), dict(target_max_error=0.1)], ids=["rmse", "max-error"])
def test_a_tiled_map_may_be_its_base_layer_alone(field_ground, target):
    """The field at 1 m in 128-cell tiles at a target: the base layer holds the cutoff's whole
    circle and no tile has a COEF (format.md, TIDX: the tiles' heights are the base layer's)."""
    data = dftpcc.compress(field_ground, resolution=1.0, tile_size=128, **target)
    layout = check_tiled(data)
    assert not [k for tag, k, *_ in layout["entries"] if tag == b"COEF" and k > 0]
    assert max(layout["cells"]) > 0 and b"BASE" in layout["sections"]


def test_a_small_tiled_map_keeps_its_mask_whole_at_tile_0(field_ground, monkeypatch):
    """The field at 1 m in 128-cell tiles: the map mask at tile 0 and no tile's MASK, shorter than
    the tiles' masks, and the same map to the bit in both readers."""
    from dftpcc import encoder

    data = dftpcc.compress(field_ground, resolution=1.0, tile_size=128)
    layout = check_tiled(data)
    masks = [(tile, payload) for tag, tile, payload in craft.split_tiled(data) if tag == b"MASK"]
    assert [tile for tile, _p in masks] == [0]
    monkeypatch.setattr(encoder, "MAP_MASK_CELLS", 0)
    own = dftpcc.compress(field_ground, resolution=1.0, tile_size=128)
    assert not any(tag == b"MASK" and tile == 0 for tag, tile, _p in craft.split_tiled(own))
    assert len(data) < len(own)
    assert dftpcc.open(data).info()["stats"]["mask_bytes"] == len(masks[0][1])
    a, b = dftpcc.open(data).read_dem(), dftpcc.open(own).read_dem()
    np.testing.assert_array_equal(a.mask, b.mask)
    assert a.heights.tobytes() == b.heights.tobytes()
    np.testing.assert_array_equal(spec_decoder.decode(data), spec_decoder.decode(own))
    assert layout["cells"].tolist() == check_tiled(own)["cells"].tolist()
    # A region reads the map mask and its tiles only.
    whole = spec_decoder.decode(data)
    box = [whole[:, 0].min() + 100, whole[:, 1].min() + 100, whole[:, 0].min() + 200, whole[:, 1].min() + 300]
    inside = ((whole[:, 0] >= box[0]) & (whole[:, 0] <= box[2]) & (whole[:, 1] >= box[1]) & (whole[:, 1] <= box[3]))
    np.testing.assert_allclose(dftpcc.open(data).read_points(bbox=box), whole[inside], rtol=0, atol=ATOL)


def test_a_map_mask_refuses_what_disagrees_with_it():
    """A tile's MASK beside the map mask, a map mask whose cells per tile are not the index's, and
    a map mask of another shape: both readers refuse them (dftpcc with its own error)."""
    from dftpcc import occupancy

    data = encode_tiled(synthetic_dem(90, 70, 5), tile_size=32)
    sections = split_tiled(data)
    i = next(i for i, (tag, tile, _p) in enumerate(sections) if tag == b"MASK")
    assert sections[i][1] == 0
    mask = occupancy.decode_mask(sections[i][2], (90, 70))
    tile_mask = occupancy.encode_mask(mask[:32, :32], first_seed=True)
    moved = mask.copy()
    r, c = np.argwhere(mask[:32, :32])[0]
    moved[r, c] = False
    r, c = np.argwhere(~mask[32:64, :32])[0]
    moved[32 + r, c] = True  # the same count over the map, one cell more in tile 4, one less in tile 1
    cases = {
        "a tile's MASK too": (sections + [(b"MASK", 1, tile_mask)], "tile 1 has sections"),
        "cells in other tiles": ([(t, k, occupancy.encode_mask(moved) if j == i else p)
                                  for j, (t, k, p) in enumerate(sections)], "cell count"),
        "another shape": ([(t, k, occupancy.encode_mask(mask[:, :64]) if j == i else p)
                           for j, (t, k, p) in enumerate(sections)], "map mask"),
    }
    for name, (lying, message) in cases.items():
        lie = join_tiled(lying)
        with pytest.raises(dftpcc.DftpccError, match=message):
            dftpcc.open(lie).read_dem()
        with pytest.raises(ValueError):
            spec_decoder.decode(lie)


def test_a_small_tiled_map_keeps_its_residual_whole_at_tile_0(field_ground, monkeypatch):
    """The field at 1 m in 128-cell tiles within 8 cm: the map residual beside the map mask at tile
    0, no tile's RESD, shorter than each tile's, the same integers so the same map to the bit, in
    both readers and for a region."""
    from dftpcc import encoder

    data = dftpcc.compress(field_ground, resolution=1.0, tile_size=128, target_max_error=0.08)
    check_tiled(data)
    at = {(tag, tile) for tag, tile, _p in craft.split_tiled(data) if tag in (b"MASK", b"RESD")}
    assert at == {(b"MASK", 0), (b"RESD", 0)}
    monkeypatch.setattr(encoder, "map_residual", lambda an, masks, codes, coder: (masks, b""))
    own = dftpcc.compress(field_ground, resolution=1.0, tile_size=128, target_max_error=0.08)
    assert (b"RESD", 0) not in {(tag, tile) for tag, tile, _p in craft.split_tiled(own)}
    assert len(data) < len(own)
    info = dftpcc.open(data).info()["stats"]
    assert info["residual_bytes"] == len(craft.section(data, b"RESD"))
    assert info["dem_max_error_m"] <= 0.08
    a, b = dftpcc.open(data).read_dem(), dftpcc.open(own).read_dem()
    np.testing.assert_array_equal(a.mask, b.mask)
    assert a.heights.tobytes() == b.heights.tobytes()
    whole = spec_decoder.decode(data)
    np.testing.assert_array_equal(whole, spec_decoder.decode(own))
    box = [whole[:, 0].min() + 100, whole[:, 1].min() + 100, whole[:, 0].min() + 200, whole[:, 1].min() + 300]
    inside = ((whole[:, 0] >= box[0]) & (whole[:, 0] <= box[2]) & (whole[:, 1] >= box[1]) & (whole[:, 1] <= box[3]))
    np.testing.assert_allclose(dftpcc.open(data).read_points(bbox=box), whole[inside], rtol=0, atol=ATOL)


def test_a_map_residual_refuses_what_disagrees_with_it():
    """A map residual without the map mask, beside a tile's RESD, without a bound, or of another
    count than the map mask's cells: both readers refuse them (dftpcc with its own error)."""
    from dftpcc import occupancy
    from dftpcc.residual import decode_residual, encode_residual

    data = encode_tiled(synthetic_dem(90, 70, 5), tile_size=32, target_max_error=0.05)
    sections = split_tiled(data)
    assert {(tag, tile) for tag, tile, _p in sections if tag in (b"MASK", b"RESD")} == {(b"MASK", 0), (b"RESD", 0)}
    mask = occupancy.decode_mask(craft.section(data, b"MASK"), (90, 70))
    q = decode_residual(craft.section(data, b"RESD"), mask)
    fewer = mask.copy()
    fewer[tuple(np.argwhere(mask)[0])] = False
    cases = {
        "no map mask": (join_tiled([s for s in sections if s[:2] != (b"MASK", 0)]), "needs the map mask"),
        "a tile's RESD too": (join_tiled(sections + [(b"RESD", 1, craft.section(data, b"RESD"))]),
                              "tile 1 has sections"),
        "no bound": (craft.with_json(data, b"PARM", {**craft.json_of(data, b"PARM"), "target_max_error": 0.0}),
                     "without a maximum-error target"),
        "one value short": (craft.replace_section(data, b"RESD", encode_residual(q[1:], "ans", fewer)),
                            "map residual: "),
    }
    for name, (lie, message) in cases.items():
        with pytest.raises(dftpcc.DftpccError, match=message):
            dftpcc.open(lie).read_dem()
        with pytest.raises(ValueError):
            spec_decoder.decode(lie)


@pytest.mark.parametrize("coder", ["ans", "zstd"])
def test_tiled_max_error_has_a_residual_layer_per_tile(coder, tile_masks):
    data = encode_tiled(synthetic_dem(150, 100, 1), tile_size=64, target_max_error=0.02, coder=coder)
    layout = check_tiled(data)
    resd = {tile for tag, tile, *_ in layout["entries"] if tag == b"RESD"}
    assert resd == {k + 1 for k, c in enumerate(layout["cells"]) if c} and len(resd) == 6
    # Each tile's residual takes its own layout: chunks, or one sparse chunk (kind 4).
    kinds = [chunk_kinds(payload) for tag, _k, payload in craft.split_tiled(data) if tag == b"RESD"]
    assert {4} in kinds and (coder == "zstd" or any(4 not in k for k in kinds)), kinds


@pytest.mark.parametrize("rows,cols,size", [(67, 33, 32), (33, 97, 16), (140, 40, 64)],
                         ids=["thin-last-row-and-col", "tiles-of-16", "tall-tiles"])
def test_tiled_non_square_last_tiles(rows, cols, size):
    """Last tile row and column of 3 and 1 cells, tiles of the smallest size, tiles taller than wide."""
    layout = check_tiled(encode_tiled(synthetic_dem(rows, cols, 2), tile_size=size))
    shapes = tile_shapes(layout)
    assert shapes[-1] == (rows - (rows - 1) // size * size, cols - (cols - 1) // size * size)
    assert any(h != w for h, w in shapes)


@pytest.mark.parametrize("cutoff", [0.0, 0.5, 0.97])
def test_tiled_cutoffs(cutoff):
    """The base layer's radius is one cycle per tile, or the file's cutoff when that is lower (0.97)."""
    check_tiled(encode_tiled(synthetic_dem(90, 70, 3), tile_size=32, cutoff=cutoff))


def test_tiled_base_reach_past_eight_cycles():
    """On a small map the writer may take a base layer of the cutoff's whole circle at a reach past 8
    cycles per tile (tiles.covering_reach): TIDX states any u8, and the spec decoder follows it."""
    data = encode_tiled(synthetic_dem(90, 70, 3), tile_size=16, cutoff=0.0, step=0.1)
    layout = check_tiled(data)
    reach = spec_decoder._tile_index(layout["sections"][b"TIDX"], len(layout["cells"]), 16)[1]
    assert reach > 8, reach
    # The base layer leaves the tiles little: those whose coefficients are all 0 have no COEF.
    with_coef = {tile for tag, tile, *_ in layout["entries"] if tag == b"COEF"}
    occupied = {k + 1 for k, c in enumerate(layout["cells"]) if c}
    assert with_coef < occupied, (with_coef, occupied)


def test_a_tile_may_hold_its_zero_coefficients(monkeypatch):
    """Files written before tiles left out all-zero coefficients hold a COEF of zeros: they read
    the same, to the bit, as the file without them."""
    from dftpcc import tiles

    dem = synthetic_dem(90, 70, 3)
    lean = encode_tiled(dem, tile_size=16, cutoff=0.0, step=0.1)
    monkeypatch.setattr(tiles, "tile_coef_code", lambda an, stream, **kw: an.encode_stream(
        stream, progressive=False, **kw))
    full = encode_tiled(dem, tile_size=16, cutoff=0.0, step=0.1)
    assert len(lean) < len(full)
    check_tiled(full)
    a, b = dftpcc.open(lean).read_dem(), dftpcc.open(full).read_dem()
    np.testing.assert_array_equal(a.heights, b.heights)
    np.testing.assert_array_equal(spec_decoder.decode(lean), spec_decoder.decode(full))


def test_tile_index_errors_in_either_layout():
    """TIDX coding 2 (the errors in byte planes, as written) and coding 1 (one after another, as
    files written before) state the same figures to both readers; the figures written are at least
    the measured ones, within 2^-15, with their 8 low mantissa bits 0, and none above the map's."""
    import zstandard

    dem = synthetic_dem(90, 70, 6)
    data = encode_tiled(dem, tile_size=32, target_max_error=0.02)
    sections = split_tiled(data)
    k = next(i for i, (tag, _t, _p) in enumerate(sections) if tag == b"TIDX")
    tidx = sections[k][2]
    assert tidx[0] == 2
    body = zstandard.ZstdDecompressor().decompress(tidx[8:])
    n = 3 * 3
    planes = np.frombuffer(body[4 * n:], np.uint8).reshape(4, -1)
    figures = planes.T.copy().view("<f4").ravel()
    capped = figures == figures[figures.size // 2:].max()  # the largest max error: the map's, in STAT
    assert capped.sum() >= 1 and not planes[0][~capped].any()  # the low mantissa byte of the others
    raw = planes.T.copy().tobytes()
    sections[k] = (b"TIDX", 0, bytes([1]) + tidx[1:8] + zstandard.ZstdCompressor().compress(body[:4 * n] + raw))
    old = join_tiled(sections)
    a, b = dftpcc.open(data), dftpcc.open(old)
    assert a.info()["tiles"] == b.info()["tiles"]
    np.testing.assert_array_equal(spec_decoder.decode(data), spec_decoder.decode(old))
    assert check_tiled(old)["cells"].tolist() == check_tiled(data)["cells"].tolist()
    # Stated against measured, per tile.
    heights = a.read_dem().heights
    stated_max = a.info()["stats"]["dem_max_error_m"]
    for t in a.info()["tiles"]["tiles"]:
        r, c = t["row"] * 32, t["col"] * 32
        m = dem.mask[r:r + 32, c:c + 32]
        err = (heights[r:r + 32, c:c + 32] - dem.heights[r:r + 32, c:c + 32])[m]
        for stated, measured in ((t["dem_rmse_m"], np.sqrt(np.mean(err ** 2))), (t["dem_max_error_m"], np.abs(err).max())):
            assert measured * (1 - 1e-6) <= stated <= measured * (1 + 2 ** -14) + 1e-12
        assert t["dem_max_error_m"] <= stated_max


def test_tiled_region_matches_the_whole_decode():
    """A bbox decode reads the same points as the whole decode gives inside the box."""
    data = encode_tiled(synthetic_dem(90, 70, 4), tile_size=32)
    whole = spec_decoder.decode(data)
    x0, y0 = 4.5e5, 5.2e6
    for box in ([x0 + 10.25, y0 + 40.25, x0 + 20.25, y0 + 50.25], [x0 + 30.25, y0 + 0.25, x0 + 69.75, y0 + 89.75]):
        inside = ((whole[:, 0] >= box[0]) & (whole[:, 0] <= box[2]) & (whole[:, 1] >= box[1])
                  & (whole[:, 1] <= box[3]))
        np.testing.assert_allclose(dftpcc.open(data).read_points(bbox=box), whole[inside], rtol=0, atol=ATOL)


def split_tiled(data: bytes) -> list[tuple[bytes, int, bytes]]:
    """``[(tag, tile, payload), ...]`` in table order."""
    return [(tag, tile, data[off:off + length]) for tag, tile, off, length, _crc in spec_decoder._table(data)[1]]


def join_tiled(sections: list[tuple[bytes, int, bytes]], minor: int = 2) -> bytes:
    """A file of these sections (format.md's layout), every checksum correct."""
    table = b"".join(craft.entry(tag, tile, len(p), zlib.crc32(p)) for tag, tile, p in sections)
    top = spec_decoder.MAGIC + struct.pack("<BBHI", 1, minor, 0, len(sections)) + table
    return top + struct.pack("<I", zlib.crc32(top)) + b"".join(p for _tag, _tile, p in sections)


def with_tile_index(data: bytes, cells: np.ndarray) -> bytes:
    """The file with TIDX stating other cell counts (figures kept per tile with cells), CRCs fixed."""
    import zstandard

    sections = split_tiled(data)
    k = next(i for i, (tag, _t, _p) in enumerate(sections) if tag == b"TIDX")
    tidx = sections[k][2]
    cells = np.asarray(cells, np.uint32)
    m = int(np.count_nonzero(cells))
    index = cells.astype("<u4").view(np.uint8).reshape(-1, 4).T.tobytes() + struct.pack(f"<{2 * m}f", *[0.01] * 2 * m)
    sections[k] = (b"TIDX", 0, tidx[:7] + zstandard.ZstdCompressor().compress(index))
    return join_tiled(sections)


def test_tiled_refusals(tile_masks):
    """Lying tiled files: both decoders refuse them (dftpcc with its own error)."""
    data = encode_tiled(synthetic_dem(90, 70, 5), tile_size=32)
    layout = check_tiled(data)
    cells = layout["cells"].copy()
    sections = split_tiled(data)
    tile_sections = [i for i, (_tag, tile, _p) in enumerate(sections) if tile]
    more = cells.copy()
    more[0] += 1
    full = cells.copy()
    full[0], full[1] = 32 * 32 + 1, full[1] - (32 * 32 + 1 - full[0])
    beyond = list(sections)
    beyond[tile_sections[-1]] = (beyond[tile_sections[-1]][0], len(cells) + 1, beyond[tile_sections[-1]][2])
    flipped = bytearray(data)
    flipped[spec_decoder._table(data)[1][tile_sections[1]][2] + 5] ^= 4  # inside tile 1's COEF
    parm = spec_decoder._json(layout["sections"][b"PARM"])
    bad = {
        "cells-sum": with_tile_index(data, more),
        "cells-over-tile": with_tile_index(data, full),
        "tile-beyond-count": join_tiled(beyond),
        "missing-mask": join_tiled([s for i, s in enumerate(sections) if i != tile_sections[0]]),
        "damaged-tile": bytes(flipped),
        "labelled-1.0": join_tiled(sections, minor=0),
        "tile-size-differs": join_tiled([(t, k, json.dumps({**parm, "tile_size": 64}).encode() if t == b"PARM" else p)
                                         for t, k, p in sections]),
        "dft-transform": join_tiled([(t, k, json.dumps({**parm, "transform": "dft"}).encode() if t == b"PARM" else p)
                                     for t, k, p in sections]),
        "mask-at-tile-0": join_tiled(sections[:5] + [(b"MASK", 0, sections[tile_sections[0]][2])] + sections[5:]),
        "no-base": join_tiled([s for s in sections if s[0] != b"BASE"]),
    }
    for name, crafted in bad.items():
        with pytest.raises(dftpcc.DftpccError):
            dftpcc.decompress(crafted)
            pytest.fail(f"{name}: dftpcc decoded it")
        with pytest.raises(ValueError):
            spec_decoder.decode(crafted)
            pytest.fail(f"{name}: the spec decoder decoded it")


def test_tiled_rough_map_has_predicted_residual_layers(tile_masks):
    """Each tile's residual takes its own layout; on rough terrain at a fine bound, kind 5."""
    from dftpcc.dem import DEM, Grid

    rng = np.random.default_rng(4)
    heights = np.cumsum(np.cumsum(rng.normal(0, 0.03, (70, 90)), 0), 1) + rng.normal(0, 0.02, (70, 90))
    mask = np.ones(heights.shape, bool)
    mask[30:40, 20:50] = False
    dem = DEM(Grid(4.5e5, 5.2e6, 100.0, 1.0, 70, 90), heights, mask, gridding_rmse=0.0)
    data = encode_tiled(dem, tile_size=32, target_max_error=0.005)
    check_tiled(data)
    kinds = [chunk_kinds(payload) for tag, _k, payload in craft.split_tiled(data) if tag == b"RESD"]
    # The four full tiles at least; the thin last ones (6 rows, 26 columns) may keep chunks.
    assert len(kinds) == 9 and kinds.count({5}) >= 4, kinds
