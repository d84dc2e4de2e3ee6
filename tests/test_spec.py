"""docs/format.md is enough to read a file: an independent decoder agrees with dftpcc.decompress.

`tests/spec_decoder.py` was written from the format document alone. These tests compress
synthetic terrains with many option sets and check that it rebuilds exactly the points
`dftpcc.decompress` does, and that the files exercised every coding the document defines.
"""

from __future__ import annotations

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


def test_every_coding_is_exercised(small):
    """The option sets above reach every MASK and COEF kind the document defines."""
    kinds = set()
    for options in ({}, {"coder": "zstd"}, {"profile": "paper"}):
        sections = spec_decoder._sections(dftpcc.compress(small, resolution=1.0, **options))
        kinds |= chunk_kinds(sections[b"COEF"])
    assert kinds == {0, 1, 3}


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
