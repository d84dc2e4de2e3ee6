"""Maps larger than memory (issue 12, point 5): a GeoTIFF coded one band of tile rows at a time, a
gridded cloud coded so, and tiled maps decoded band by band into GeoTIFF, COG and LAZ. The size
threshold is lowered so that real maps of ../shared/data play the part of huge ones."""

from __future__ import annotations

import pickle

import laspy
import numpy as np
import pytest
import rasterio

import dftpcc
from dftpcc import stream
from dftpcc.errors import InvalidInputError

from .conftest import data_file


@pytest.fixture
def small_threshold(monkeypatch):
    monkeypatch.setattr(stream, "STREAM_CELLS", 50_000)


@pytest.fixture(scope="module")
def mosaic(tmp_path_factory) -> str:
    """Mars Gale mirrored 2 x 2 with height offsets and a nodata hole: 674 x 696 float32 pixels."""
    with rasterio.open(data_file("dems/mars_gale_1m.tif")) as ds:
        a, profile = ds.read(1).astype(np.float32), ds.profile
    big = np.block([[a, a[:, ::-1] + 3.0], [a[::-1] - 2.0, a[::-1, ::-1]]])
    big[50:120, 400:520] = np.nan
    path = tmp_path_factory.mktemp("stream") / "mosaic.tif"
    profile.update(height=big.shape[0], width=big.shape[1], dtype="float32", nodata=float("nan"))
    with rasterio.open(path, "w", **profile) as out:
        out.write(big, 1)
    return str(path)


#: How far below a size target a band-coded file may fall (its step is chosen on the map's middle).
BPP_TOLERANCE = 0.25


def _reference(path: str) -> np.ma.MaskedArray:
    with rasterio.open(path) as ds:
        return ds.read(1, masked=True)[::-1]  # grid rows run south to north


@pytest.mark.parametrize("target", [dict(target_max_error=0.1), dict(target_rmse=0.03)])
def test_a_raster_coded_band_by_band_keeps_its_promise(small_threshold, mosaic, tmp_path, target):
    out = tmp_path / "m.dftpc"
    cmap = dftpcc.compress_file(mosaic, out, tile_size=128, **target)
    assert cmap.tiled
    dem = cmap.read_dem()
    ref = _reference(mosaic)
    np.testing.assert_array_equal(dem.mask, ~np.ma.getmaskarray(ref))
    err = (dem.heights + dem.grid.z0 - ref.filled(np.nan))[dem.mask]
    if "target_max_error" in target:
        assert np.abs(err).max() <= target["target_max_error"]
    else:
        assert np.sqrt(np.mean(err ** 2)) <= target["target_rmse"]
    assert np.sqrt(np.mean(err ** 2)) <= cmap.header.stats["dem_rmse_m"] * (1 + 1e-6)


@pytest.mark.parametrize("bpp", [1.0, 3.0])
def test_a_size_target_on_a_map_coded_band_by_band(small_threshold, mosaic, tmp_path, bpp):
    """--target-bpp is chosen on the map's middle and checked on the whole file: at most the target,
    and within BPP_TOLERANCE of it (not a file far smaller than asked)."""
    out = tmp_path / "m.dftpc"
    cmap = dftpcc.compress_file(mosaic, out, tile_size=128, target_bpp=bpp)
    assert cmap.tiled and cmap.header.params.target_bpp == bpp
    got = 8 * out.stat().st_size / cmap.header.point_count
    assert (1 - BPP_TOLERANCE) * bpp <= got <= bpp


def test_a_size_target_missed_on_the_whole_map_is_coded_again_or_refused(small_threshold, mosaic, tmp_path,
                                                                         monkeypatch):
    """A step chosen on the middle that gives the whole file too many bits: a coarser step, coded
    again; still missed after RMSE_ATTEMPTS: one error, no file."""
    choose = stream.choose_for_tiles

    def too_fine(*args, **kwargs):  # a middle that takes a finer step than the whole map can afford
        chosen, refill = choose(*args, **kwargs)
        return chosen.replace(step=chosen.step / 3), refill

    monkeypatch.setattr(stream, "choose_for_tiles", too_fine)
    coded = []
    code = stream._code_bands
    monkeypatch.setattr(stream, "_code_bands", lambda *a: coded.append(a[2].step) or code(*a))
    out = tmp_path / "m.dftpc"
    cmap = dftpcc.compress_file(mosaic, out, tile_size=128, target_bpp=2.0)
    assert len(coded) > 1 and coded[1] > coded[0]
    assert 8 * out.stat().st_size / cmap.header.point_count <= 2.0
    coded.clear()
    monkeypatch.setattr(stream, "BITS_PER_HALVING", 0.0)  # a retry that does not change the step
    with pytest.raises(InvalidInputError, match="bits/point was missed"):
        dftpcc.compress_file(mosaic, tmp_path / "n.dftpc", tile_size=128, target_bpp=2.0)
    assert len(coded) == stream.RMSE_ATTEMPTS and not (tmp_path / "n.dftpc").exists()


def test_band_by_band_decoding_writes_what_a_whole_decode_does(small_threshold, mosaic, tmp_path):
    src = tmp_path / "m.dftpc"
    dftpcc.compress_file(mosaic, src, tile_size=128, cutoff=0.8, step=0.01)
    whole = dftpcc.decompress_file(src, tmp_path / "whole.tif")
    assert dftpcc.files.wants_bands(src, tmp_path / "x.tif")
    n = dftpcc.files.decompress_bands(src, tmp_path / "bands.tif")
    dftpcc.files.decompress_bands(src, tmp_path / "cog.tif", cog=True)
    assert n == whole.shape[0]
    with rasterio.open(tmp_path / "whole.tif") as a, rasterio.open(tmp_path / "bands.tif") as b, \
            rasterio.open(tmp_path / "cog.tif") as c:
        assert a.transform == b.transform == c.transform
        np.testing.assert_array_equal(a.read(1), b.read(1))
        np.testing.assert_array_equal(a.read(1), c.read(1))
        assert c.overviews(1)  # a COG carries its overviews
    assert dftpcc.files.decompress_bands(src, tmp_path / "bands.laz") == n
    las = laspy.read(tmp_path / "bands.laz")
    # The same points band after band, each band block after block (BLOCK_TILES tile columns), each
    # block in row order; to the LAS millimetre.
    cmap = dftpcc.open(src)
    rows, cols = cmap.grid.cell_of(whole)
    tile, width = cmap.block, stream.BLOCK_TILES * cmap.block
    assert cmap.grid.cols > width  # more than one block a band: not the row order of the whole map
    order = np.lexsort((cols, rows, cols // width, rows // tile))
    np.testing.assert_allclose(np.c_[las.x, las.y, las.z], whole[order], atol=0.0006)


def test_a_map_no_wider_than_a_block_is_written_to_laz_in_row_order(small_threshold, mosaic, tmp_path,
                                                                     monkeypatch):
    src = tmp_path / "m.dftpc"
    dftpcc.compress_file(mosaic, src, tile_size=128, cutoff=0.8, step=0.01)
    whole = dftpcc.decompress_file(src, tmp_path / "whole.tif")
    monkeypatch.setattr(stream, "BLOCK_TILES", 6)  # 768 columns: the 696 of the map
    dftpcc.files.decompress_bands(src, tmp_path / "rows.laz")
    las = laspy.read(tmp_path / "rows.laz")
    np.testing.assert_allclose(np.c_[las.x, las.y, las.z], whole, atol=0.0006)


def test_laz_is_decoded_in_blocks_whatever_the_maps_width(small_threshold, mosaic, tmp_path, monkeypatch):
    """Memory follows a block of BLOCK_TILES tiles, not a band of the map's width: no window the
    writer asks for is wider, and the peak of a map four times as wide is about the same."""
    import tracemalloc

    with rasterio.open(mosaic) as ds:
        a, profile = ds.read(1)[:256], ds.profile
    peaks, windows = {}, []
    monkeypatch.setattr(stream, "BLOCK_TILES", 2)
    read = dftpcc.mapfile.CompressedMap.read_window
    monkeypatch.setattr(dftpcc.mapfile.CompressedMap, "read_window",
                        lambda self, rows, cols, **kw: windows.append(cols) or read(self, rows, cols, **kw))
    for copies in (1, 4):
        wide = np.hstack([a + 5.0 * k for k in range(copies)])
        path = tmp_path / f"wide{copies}.tif"
        profile.update(height=wide.shape[0], width=wide.shape[1])
        with rasterio.open(path, "w", **profile) as out:
            out.write(wide, 1)
        dftpcc.compress_file(path, tmp_path / f"wide{copies}.dftpc", tile_size=64, cutoff=0.8, step=0.01)
        tracemalloc.start()
        try:
            dftpcc.files.decompress_bands(tmp_path / f"wide{copies}.dftpc", tmp_path / f"wide{copies}.laz")
            peaks[copies] = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert max(c1 - c0 for c0, c1 in windows) == 2 * 64
    # A band of the map's width made it 3.3 times; what is left grows with the map's values, not its
    # width (the entropy coder's cached tables, a bounded cache: 1.2 times).
    assert peaks[4] < 1.6 * peaks[1], peaks


def test_a_band_is_written_to_laz_in_parts_of_rows_with_the_same_bytes(small_threshold, mosaic, tmp_path,
                                                                        monkeypatch):
    """A band of tile rows across a wide map is millions of points: it goes to the LAS writer in parts
    of about LAS_CHUNK_CELLS cells (whole rows), and the file is the one a band at a time writes."""
    from dftpcc.io import las

    src = tmp_path / "m.dftpc"
    dftpcc.compress_file(mosaic, src, tile_size=128, cutoff=0.8, step=0.01)
    dftpcc.files.decompress_bands(src, tmp_path / "band.laz")
    monkeypatch.setattr(stream, "LAS_CHUNK_CELLS", 5_000)
    sizes = []
    write = las.write_las_chunks
    monkeypatch.setattr(las, "write_las_chunks",
                        lambda path, chunks, *a: write(path, (sizes.append(len(c)) or c for c in chunks), *a))
    dftpcc.files.decompress_bands(src, tmp_path / "parts.laz")
    assert 0 < max(sizes) <= 5_000 and len(sizes) > 674 * 696 // 5_000
    assert (tmp_path / "parts.laz").read_bytes() == (tmp_path / "band.laz").read_bytes()


def test_a_gridded_cloud_is_coded_band_by_band(small_threshold, tmp_path):
    cmap = dftpcc.compress_file(data_file("pointclouds/field_gentle_ign.laz"), tmp_path / "f.dftpc",
                                tile_size=128, classes=[2], target_rmse=0.05)
    assert cmap.tiled and cmap.header.stats["dem_rmse_m"] <= 0.05
    assert "vertical_rmse_m" in cmap.header.stats


def test_cog_needs_a_tif(tmp_path, mosaic, small_threshold):
    src = tmp_path / "m.dftpc"
    dftpcc.compress_file(mosaic, src, tile_size=128, cutoff=0.8, step=0.01)
    with pytest.raises(InvalidInputError, match="COG|Cloud Optimized"):
        dftpcc.files.decompress_bands(src, tmp_path / "x.laz", cog=True)


@pytest.mark.parametrize("source", ["raster", "cloud"])
def test_the_block_width_does_not_change_a_byte(small_threshold, mosaic, tmp_path, monkeypatch, source):
    """A band is read and coded a block of tile columns at a time; the bytes do not depend on how many."""
    src = mosaic if source == "raster" else data_file("pointclouds/field_gentle_ign.laz")
    extra = {} if source == "raster" else {"classes": [2]}
    written = []
    for tiles in (1, 2, 100):  # one tile a block, a few, the whole band
        monkeypatch.setattr(stream, "BLOCK_TILES", tiles)
        monkeypatch.setattr(stream, "BATCH_BLOCKS", 3)
        out = tmp_path / f"b{tiles}.dftpc"
        cmap = dftpcc.compress_file(src, out, tile_size=128, target_rmse=0.05, **extra)
        assert cmap.tiled and cmap.header.tiles.tiling.tile_cols > 2
        written.append(out.read_bytes())
    assert written[0] == written[1] == written[2]


def test_the_base_layer_of_a_window_is_the_bits_of_the_whole():
    """Each cell of the base layer has the same bits whatever window it is computed in (BLAS's do not):
    the whole map, a band, a block of columns, a bbox."""
    from dftpcc.tiles import base_heights, base_order

    shape, tile = (3001, 2999), 256
    i, j, _, _ = base_order(shape, tile, 0.0)
    values = np.random.default_rng(7).normal(size=i.size)
    rows = (3 * tile - 8, 4 * tile + 8)
    whole = base_heights(values, i, j, shape, rows, (0, shape[1]))
    for c0, c1 in [(0, 1), (248, 520), (1016, 2056), (2990, 2999)]:
        np.testing.assert_array_equal(base_heights(values, i, j, shape, rows, (c0, c1)), whole[:, c0:c1])
    for r0, r1 in [(rows[0], rows[0] + 1), (rows[0] + 5, rows[1] - 3)]:
        np.testing.assert_array_equal(base_heights(values, i, j, shape, (r0, r1), (248, 520)),
                                      whole[r0 - rows[0]:r1 - rows[0], 248:520])
    # The same layer as the decoder's BLAS product, to round-off.
    np.testing.assert_allclose(whole, base_heights(values, i, j, shape, rows, (0, shape[1]), exact=False),
                               rtol=0, atol=1e-9)


def test_a_decoded_geotiff_is_the_same_bytes_whatever_the_block_width(small_threshold, mosaic, tmp_path, monkeypatch):
    src = tmp_path / "m.dftpc"
    dftpcc.compress_file(mosaic, src, tile_size=128, cutoff=0.8, step=0.01)
    written = []
    for tiles in (1, 4, 100):
        monkeypatch.setattr(stream, "BLOCK_TILES", tiles)
        dftpcc.files.decompress_bands(src, tmp_path / f"b{tiles}.tif")
        written.append((tmp_path / f"b{tiles}.tif").read_bytes())
    assert written[0] == written[1] == written[2]


def test_a_geotiff_read_by_windows_is_the_whole_read(tmp_path):
    """One reader for the whole-file and the band paths: any window is the same cells as the whole DEM."""
    from dftpcc.io.geotiff import RasterWindows, dem_from_geotiff

    path = data_file("dems/mars_korolev_mola.tif")  # int16 with nodata, north-up (flipped rows)
    dem, _ = dem_from_geotiff(path)
    whole = np.where(dem.mask, dem.heights + dem.grid.z0, np.nan)
    with RasterWindows(path) as raster:
        assert raster.grid(dem.grid.z0) == dem.grid
        for (r0, r1), (c0, c1) in [((0, 1), (0, 859)), ((17, 200), (300, 301)), ((100, 349), (5, 600))]:
            h, m = raster.read(r0, r1, c0, c1)
            np.testing.assert_array_equal(m, dem.mask[r0:r1, c0:c1])
            np.testing.assert_allclose(h[m], whole[r0:r1, c0:c1][m], rtol=0, atol=1e-9)
            assert np.isnan(h[~m]).all()


def test_the_plane_summed_band_by_band_is_the_plane_of_the_whole():
    from dftpcc.fill import PlaneSums, fit_plane
    from dftpcc.io.geotiff import dem_from_geotiff

    dem, _ = dem_from_geotiff(data_file("dems/earth_bigtujunga_srtm30.tif"))
    heights = dem.heights + dem.grid.z0
    fit = None
    for r0 in range(0, dem.grid.rows, 50):
        rows, cols = np.nonzero(dem.mask[r0:r0 + 50])
        z = heights[r0:r0 + 50][rows, cols]
        fit = fit or PlaneSums(float(z.mean()))
        fit.add(cols.astype(float), (rows + r0).astype(float), z)
    assert fit.count == int(dem.mask.sum())
    np.testing.assert_allclose(fit.mean(), dem.grid.z0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fit.plane(dem.grid.z0), fit_plane(dem), rtol=1e-9, atol=1e-9)


def test_the_base_coefficients_of_block_means_are_those_of_the_map_they_stand_for():
    """A decimated copy's coefficients (``block`` > 1) are the whole map's when each block is flat."""
    from dftpcc.tiles import base_coefficients, base_order

    shape, tile, d = (1000, 1300), 128, 8  # edges cut the last blocks
    i, j, _, _ = base_order(shape, tile, 0.0)
    means = np.random.default_rng(3).normal(size=(-(-shape[0] // d), -(-shape[1] // d)))
    full = np.kron(means, np.ones((d, d)))[:shape[0], :shape[1]]
    np.testing.assert_allclose(base_coefficients(means, i, j, rows=shape[0], cols=shape[1], block=d),
                               base_coefficients(full, i, j), rtol=0, atol=1e-9)


def test_rate_controls_sample_is_bounded_by_cells(mosaic, monkeypatch):
    """The sample rate control codes is at most SAMPLE_CELLS (at least a tile): its trials, not the map,
    set the peak memory of a large tile size."""
    raster = stream._Raster(mosaic)
    try:
        grid = raster.grid(0.0)
        assert stream._sample(raster, grid, 128, 0.0).grid.shape == (256, 256)  # 2 x 2 tiles
        monkeypatch.setattr(stream, "SAMPLE_CELLS", 128 * 128 * 3)
        assert stream._sample(raster, grid, 128, 0.0).grid.shape == (128, 128)
    finally:
        raster.close()


def test_the_survey_in_narrow_windows_finds_the_same_plane(mosaic, monkeypatch):
    """The first pass reads windows of SURVEY_COLS columns, so its memory does not follow the map's width;
    the plane, height and decimated copy are those of full-width bands, to round-off."""
    raster = stream._Raster(mosaic)
    try:
        wide = stream._survey(raster, 128, lambda *a: None)
        monkeypatch.setattr(stream, "SURVEY_COLS", 64)
        reads = []
        read = raster.read
        monkeypatch.setattr(raster, "read", lambda *a: reads.append(a) or read(*a))
        narrow = stream._survey(raster, 128, lambda *a: None)
    finally:
        raster.close()
    assert max(c1 - c0 for _, _, c0, c1 in reads) == 64
    assert narrow["cells"] == wide["cells"]
    np.testing.assert_allclose(narrow["z0"], wide["z0"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(narrow["plane"], wide["plane"], rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(narrow["counts"], wide["counts"])
    # Sums of heights about each pass's reference (its first window's mean).
    np.testing.assert_allclose(narrow["sums"] + narrow["ref"] * narrow["counts"],
                               wide["sums"] + wide["ref"] * wide["counts"], rtol=1e-12, atol=1e-6)


@pytest.mark.parametrize("tile", [128, 200])  # blocks of 8 cells inside every window; blocks of 12 straddling
def test_the_survey_is_mapped_by_rows_and_gives_the_serial_bits(mosaic, monkeypatch, tile):
    """The first pass goes to the map (a cluster: each worker reads its own rows) in tasks of
    SURVEY_TASK_ROWS rows, added back in order: the same bits as one pass here. A tile whose
    decimation blocks straddle windows is surveyed here (their sums would round otherwise)."""
    monkeypatch.setattr(stream, "SURVEY_TASK_ROWS", 256)
    monkeypatch.setattr(stream, "SURVEY_COLS", 256)
    mapped = []

    def recording(func, items, *args):
        mapped.append((func.__name__, list(items)))
        return [func(pickle.loads(pickle.dumps(item)), *pickle.loads(pickle.dumps(args))) for item in items]

    raster = stream._Raster(mosaic)
    try:
        here = stream._survey(raster, tile, lambda *a: None)
        there = stream._survey(raster, tile, lambda *a: None, recording)
    finally:
        raster.close()
    if tile == 128:
        assert [name for name, _ in mapped] == ["_survey_rows"] and mapped[0][1] == [(0, 256), (256, 512), (512, 674)]
    else:
        assert mapped == []
    for key in here:
        assert np.asarray(there[key]).tobytes() == np.asarray(here[key]).tobytes(), key


@pytest.mark.parametrize("workers", [None, 2])
def test_an_input_that_changes_during_the_run_is_refused_and_nothing_is_written(small_threshold, mosaic, tmp_path,
                                                                               monkeypatch, workers):
    """A GeoTIFF rewritten between the survey and the tiles' reads (by length or modification time) would
    make a map of two files: one error, no output (serial: checked before the file is written; on a
    cluster: also where each worker reopens it)."""
    import os
    import shutil

    src = tmp_path / "in.tif"
    shutil.copy(mosaic, src)
    sample = stream._sample

    def touched(*args, **kwargs):  # after the survey, before the tiles are read
        st = os.stat(src)
        os.utime(src, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
        return sample(*args, **kwargs)

    monkeypatch.setattr(stream, "_sample", touched)
    out = tmp_path / "m.dftpc"
    with pytest.raises(InvalidInputError, match="changed while it was read"):
        dftpcc.compress_file(src, out, tile_size=128, cutoff=0.8, step=0.05, workers=workers)
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.tif"]


def test_a_full_disk_while_a_band_coded_map_is_written_leaves_nothing(small_threshold, mosaic, tmp_path, monkeypatch):
    """The tiles spooled, the disk fills while the file is written: one OSError naming the file, and neither
    a partial map nor the temporary beside it."""
    import errno
    import subprocess
    import sys

    from dftpcc.format.writer import MapWriter

    def full(self, out):
        out.write(b"\0" * 1000)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(MapWriter, "write_payloads", full)
    out = tmp_path / "m.dftpc"
    with pytest.raises(OSError, match="No space left") as info:
        dftpcc.compress_file(mosaic, out, tile_size=128, cutoff=0.8, step=0.05)
    assert str(out) in str(info.value)
    assert not list(tmp_path.iterdir())
    # The command line says it in one line, with a non-zero exit.
    code = ("import sys, errno, runpy; from dftpcc import stream; from dftpcc.format.writer import MapWriter\n"
            "stream.STREAM_CELLS = 50_000\n"
            "def full(self, out):\n    out.write(b'0' * 1000); raise OSError(errno.ENOSPC, 'No space left on device')\n"
            "MapWriter.write_payloads = full\n"
            "sys.argv = ['dftpcc', 'compress', sys.argv[1], sys.argv[2], '--tile-size', '128', '--cutoff', '0.8',"
            " '--step', '0.05']\n"
            "runpy.run_module('dftpcc', run_name='__main__')\n")
    result = subprocess.run([sys.executable, "-c", code, mosaic, str(out)], capture_output=True, text=True)
    assert result.returncode != 0
    assert result.stderr.strip().count("\n") == 0 and "No space left" in result.stderr
    assert not list(tmp_path.iterdir())
