"""The one reader path (format.reader, decoder.decode_window, CompressedMap.read_window): every map
decodes windows, an untiled one as its single tile, rebuilding only the window's cells."""

from __future__ import annotations

import numpy as np
import pytest

import dftpcc
from dftpcc.files import decompress_bands, wants_bands
from dftpcc import spectrum
from dftpcc.dem import DEM, Grid
from dftpcc.encoder import encode_dem
from dftpcc.params import make_params


def _hills(rows: int = 180, cols: int = 150, seed: int = 5) -> DEM:
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:rows, 0:cols].astype(float)
    h = 0.03 * c - 0.02 * r + 3 * np.sin(r / 19) * np.cos(c / 27) + 0.05 * rng.standard_normal((rows, cols))
    mask = np.ones((rows, cols), dtype=bool)
    mask[40:60, 30:70] = False  # a gap: the window's mask must come out right too
    grid = Grid(x0=500.0, y0=-200.0, z0=0.0, resolution=0.5, rows=rows, cols=cols)
    return DEM(grid=grid, heights=np.where(mask, h, 0.0), mask=mask)


@pytest.mark.parametrize("options", [{}, {"target_max_error": 0.05}, {"profile": "paper"}])
def test_an_untiled_window_equals_the_whole_decode(options):
    dem = _hills()
    data = encode_dem(dem, make_params(**options))
    with dftpcc.open(data) as cmap:
        assert not cmap.tiled
        whole = cmap.read_dem()
        for rows, cols in (((10, 37), (5, 90)), ((0, 180), (149, 150)), ((33, 64), (20, 80)), ((0, 180), (0, 150))):
            part = cmap.read_window(rows, cols)
            assert part.heights.shape == (rows[1] - rows[0], cols[1] - cols[0])
            assert np.array_equal(part.mask, whole.mask[rows[0]:rows[1], cols[0]:cols[1]])
            ref = whole.heights[rows[0]:rows[1], cols[0]:cols[1]]
            assert np.abs(part.heights - ref)[part.mask].max(initial=0.0) < 1e-9
            assert part.grid == whole.grid.window(rows[0], cols[0], *part.heights.shape) or \
                (rows, cols) == ((0, 180), (0, 150))
    if "target_max_error" in options:  # the bound holds on a window
        assert np.abs(part.heights - dem.heights)[part.mask].max() <= options["target_max_error"]


def test_a_small_untiled_window_does_not_run_the_whole_inverse(monkeypatch):
    data = encode_dem(_hills(), make_params())
    calls = []
    real = spectrum.inverse
    monkeypatch.setattr(spectrum, "inverse", lambda *a, **k: calls.append(a[0].shape) or real(*a, **k))
    with dftpcc.open(data) as cmap:
        cmap.read_window((50, 60), (70, 82))
        assert calls == []  # from the basis vectors at the window's cells alone
        cmap.read_dem()  # a whole read runs the transform once
        assert len(calls) == 1


def test_a_bbox_of_an_untiled_map_is_read_as_a_window():
    data = encode_dem(_hills(), make_params())
    with dftpcc.open(data) as cmap:
        xmin, ymin, _, _ = cmap.bounds()
        box = (xmin + 10.0, ymin + 5.0, xmin + 20.0, ymin + 12.0)
        part = cmap.read_points(bbox=box)
        whole = cmap.read_points()
    inside = whole[(whole[:, 0] >= box[0]) & (whole[:, 0] <= box[2]) & (whole[:, 1] >= box[1]) & (whole[:, 1] <= box[3])]
    assert part.shape == inside.shape and np.abs(part - inside).max() < 1e-9


def test_a_prefix_window_is_refused_not_guessed():
    data = encode_dem(_hills(), make_params())
    with dftpcc.open(data, max_bytes=len(data) // 2) as cmap:
        with pytest.raises(dftpcc.InvalidInputError, match="decodes whole"):
            cmap.read_window((0, 10), (0, 10))


def test_an_untiled_map_decodes_to_a_cog(tmp_path, monkeypatch):
    rasterio = pytest.importorskip("rasterio")
    from dftpcc import cli, mapfile

    monkeypatch.setattr(mapfile, "UNTILED_BLOCK", 64)  # several bands of a small map
    dem = _hills()
    src = tmp_path / "map.dftpc"
    src.write_bytes(encode_dem(dem, make_params(target_max_error=0.05)))
    assert cli.main(["decompress", str(src), str(tmp_path / "cog.tif"), "--cog", "-q"]) == 0
    assert cli.main(["decompress", str(src), str(tmp_path / "whole.tif"), "-q"]) == 0
    assert wants_bands(src, tmp_path / "cog.tif", cog=True)  # the one band path, as a tiled map's
    with rasterio.open(tmp_path / "cog.tif") as cog, rasterio.open(tmp_path / "whole.tif") as whole:
        assert cog.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG" and cog.shape == whole.shape == dem.grid.shape
        a, b = cog.read(1), whole.read(1)
    assert np.array_equal(np.isnan(a), np.isnan(b))
    assert np.nanmax(np.abs(a.astype(float) - b)) <= 1e-3  # float32 either way
    # ... and band by band through the one window reader, as a tiled map is.
    assert decompress_bands(src, tmp_path / "bands.tif", cog=True) == int(dem.mask.sum())
    with rasterio.open(tmp_path / "bands.tif") as bands:
        c = bands.read(1)
    assert np.array_equal(np.isnan(a), np.isnan(c)) and np.nanmax(np.abs(c.astype(float) - a)) <= 1e-3


def test_a_large_untiled_map_is_written_band_by_band_as_a_tiled_one_is(tmp_path, monkeypatch):
    """Past STREAM_CELLS every map goes band by band to LAS (memory holds one band of points); the
    points are those of a whole decode, in the same order."""
    pytest.importorskip("laspy")
    from dftpcc import mapfile, stream

    monkeypatch.setattr(mapfile, "UNTILED_BLOCK", 64)
    dem = _hills()
    src = tmp_path / "map.dftpc"
    src.write_bytes(encode_dem(dem, make_params(target_max_error=0.05)))
    assert not wants_bands(src, tmp_path / "out.las")
    monkeypatch.setattr(stream, "STREAM_CELLS", dem.grid.size - 1)
    assert wants_bands(src, tmp_path / "out.las") and not wants_bands(src, tmp_path / "out.las", cutoff=0.5)
    assert decompress_bands(src, tmp_path / "bands.las") == int(dem.mask.sum())
    whole = dftpcc.decompress_file(src, tmp_path / "whole.las")
    bands = dftpcc.read(tmp_path / "bands.las").points
    assert bands.shape == whole.shape and np.abs(bands - whole).max() <= 1e-3  # LAS's scale


def test_a_tiled_integer_dem_comes_back_in_its_type_band_by_band(tmp_path):
    """The band-by-band GeoTIFF writer keeps the source's sample type and nodata as a whole decode does."""
    rasterio = pytest.importorskip("rasterio")
    from dftpcc import cli

    from .conftest import data_file

    src = str(data_file("dems/moon_kepler_lola_48m.tif"))
    m = tmp_path / "k.dftpc"
    assert cli.main(["compress", src, str(m), "--target-max-error", "0.49", "--tile-size", "128", "-q"]) == 0
    assert dftpcc.open(m).tiled
    out = tmp_path / "k.tif"
    assert cli.main(["decompress", str(m), str(out), "--cog", "-q"]) == 0
    with rasterio.open(src) as a, rasterio.open(out) as b:
        assert b.dtypes[0] == a.dtypes[0] == "int16" and b.nodata == a.nodata
        assert np.array_equal(a.read(1), b.read(1))  # within half a unit: every height rounds back
    out32 = tmp_path / "k32.tif"
    assert cli.main(["decompress", str(m), str(out32), "--cog", "--dtype", "float32", "-q"]) == 0
    with rasterio.open(out32) as c:
        assert c.dtypes[0] == "float32"
