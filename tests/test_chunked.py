"""Clouds read in chunks (larger than memory): the same DEM and file as read whole, bounded memory."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import warnings

import numpy as np
import pytest

import dftpcc
from dftpcc import files
from dftpcc.errors import InvalidInputError, MultiHeightWarning
from dftpcc.io import open_chunked
from dftpcc.grid import CloudSummary, fit_grid, rasterize, rasterize_chunks

from .conftest import data_file

FIELD = "pointclouds/field_gentle_ign.laz"


def _summary(cloud, *, hull=False) -> CloudSummary:
    summary = CloudSummary(hull=hull)
    for points in cloud.chunks():
        summary.add(points)
    return summary


def _same_grid(a, b) -> None:
    # The projection plane is a mean summed in another order: equal to round-off.
    assert (a.x0, a.y0, a.resolution, a.rows, a.cols, a.angle) == (b.x0, b.y0, b.resolution, b.rows, b.cols, b.angle)
    assert a.z0 == pytest.approx(b.z0, abs=1e-9)


@pytest.mark.parametrize("aggregate", ["mean", "min", "max"])
def test_chunks_grid_the_field_as_a_whole_read_does(field_ground, aggregate):
    cloud = open_chunked(data_file(FIELD), classes=[2], chunk_points=50_000)
    summary = _summary(cloud)
    assert summary.count == field_ground.shape[0]
    grid = summary.fit_grid(0.5)
    whole = rasterize(field_ground, fit_grid(field_ground, 0.5), aggregate=aggregate)
    _same_grid(grid, whole.grid)
    chunked = rasterize_chunks(cloud.chunks, grid, aggregate=aggregate)
    np.testing.assert_array_equal(chunked.mask, whole.mask)
    np.testing.assert_array_equal(chunked.counts, whole.counts)
    np.testing.assert_allclose(chunked.heights, whole.heights, rtol=0, atol=1e-9)
    assert chunked.gridding_rmse == pytest.approx(whole.gridding_rmse, rel=1e-9)
    assert chunked.spread.unrepresented_points == whole.spread.unrepresented_points
    assert chunked.spread.unrepresented_cells == whole.spread.unrepresented_cells
    assert chunked.spread.max_distance_m == pytest.approx(whole.spread.max_distance_m, rel=1e-9)


def test_chunks_choose_the_same_automatic_resolution(field_ground):
    cloud = open_chunked(data_file(FIELD), classes=[2], chunk_points=100_000)
    assert _summary(cloud).auto_resolution(cloud.chunks) == pytest.approx(dftpcc.grid.auto_resolution(field_ground),
                                                                           rel=1e-12)


def test_chunks_fit_the_same_oriented_frame():
    path = data_file("pointclouds/mountain_arid_alirt.las")
    points = dftpcc.read(path).points
    cloud = open_chunked(path, chunk_points=5_000)
    _same_grid(_summary(cloud, hull=True).fit_grid(2.0, frame="oriented"), fit_grid(points, 2.0, frame="oriented"))


def test_compress_file_in_chunks_writes_the_same_map(tmp_path):
    src = data_file(FIELD)
    whole = files.compress_file(src, tmp_path / "whole.dftpc", resolution=0.5, classes=[2], target_rmse=0.02)
    chunked = files.compress_file(src, tmp_path / "chunked.dftpc", resolution=0.5, classes=[2], target_rmse=0.02,
                                  chunk_points=100_000)
    assert chunked.header.point_count == whole.header.point_count
    assert chunked.crs == whole.crs and chunked.crs  # the LAS georeferencing travels too
    a, b = whole.read_dem(), chunked.read_dem()
    np.testing.assert_array_equal(a.mask, b.mask)
    np.testing.assert_allclose(a.heights[a.mask] + a.grid.z0, b.heights[b.mask] + b.grid.z0, rtol=0, atol=1e-6)
    for key in ("dem_rmse_m", "vertical_rmse_m", "gridding_rmse_m"):
        assert chunked.header.stats[key] == pytest.approx(whole.header.stats[key], rel=1e-6)


def test_a_ply_read_in_chunks_gives_the_very_same_bytes(tmp_path):
    src = data_file("pointclouds/redrocks_rough.ply")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MultiHeightWarning)
        files.compress_file(src, tmp_path / "a.dftpc", resolution=5.0)
        files.compress_file(src, tmp_path / "b.dftpc", resolution=5.0, chunk_points=7_000)
    assert (tmp_path / "a.dftpc").read_bytes() == (tmp_path / "b.dftpc").read_bytes()


def test_a_multi_height_cloud_read_in_chunks_still_warns(tmp_path):
    with pytest.warns(MultiHeightWarning, match="lie more than 5 m"):
        files.compress_file(data_file("pointclouds/redrocks_rough.ply"), tmp_path / "a.dftpc", resolution=5.0,
                            chunk_points=7_000)


def test_nonfinite_rows_are_named_across_chunks(tmp_path, small_terrain):
    pts = small_terrain.copy()
    pts[[250, 251], 2] = np.nan
    src = tmp_path / "holes.npy"
    np.save(src, pts)
    # Chunks of 100: the bad rows are in the third, and the message counts rows from the file's start.
    with pytest.raises(InvalidInputError, match=r"2 of the .* point\(s\) have NaN .*\(rows 250, 251\)"):
        files.compress_file(src, tmp_path / "h.dftpc", resolution=0.5, chunk_points=100)
    assert not (tmp_path / "h.dftpc").exists()
    out = files.compress_file(src, tmp_path / "h.dftpc", resolution=0.5, chunk_points=100, drop_nonfinite=True)
    assert out.header.point_count == pts.shape[0] - 2
    np.save(src, np.full((10, 3), np.inf))
    with pytest.raises(InvalidInputError, match="all 10 points have NaN or infinite"):
        files.compress_file(src, tmp_path / "h.dftpc", resolution=0.5, chunk_points=4, drop_nonfinite=True)


def test_what_cannot_be_chunked_is_refused_clearly(tmp_path, small_terrain):
    src = tmp_path / "t.xyz"
    dftpcc.write(src, small_terrain)
    with pytest.raises(InvalidInputError, match="xyz files cannot be read in chunks"):
        files.compress_file(src, tmp_path / "t.dftpc", resolution=0.5, chunk_points=1000)
    npy = tmp_path / "t.npy"
    np.save(npy, small_terrain)
    with pytest.raises(InvalidInputError, match="median"):
        files.compress_file(npy, tmp_path / "t.dftpc", resolution=0.5, aggregate="median", chunk_points=1000)
    with pytest.raises(InvalidInputError, match="chunk_points must be a positive integer"):
        open_chunked(npy, chunk_points=0)
    assert not (tmp_path / "t.dftpc").exists()


def test_a_median_needs_the_whole_cloud_which_is_read_whole_when_it_fits(tmp_path, small_terrain, monkeypatch):
    npy = tmp_path / "t.npy"
    np.save(npy, small_terrain)
    out = tmp_path / "t.dftpc"
    whole = dftpcc.compress(small_terrain, resolution=0.5, aggregate="median")
    assert files.compress_file(npy, out, resolution=0.5, aggregate="median") is not None
    assert out.read_bytes() == whole  # the one-chunk read is the whole-cloud computation
    out.unlink()
    # A cloud too large for memory is read in chunks, where a median is refused before any pass.
    monkeypatch.setattr(dftpcc.limits, "available_memory", lambda: small_terrain.shape[0] * dftpcc.limits.IN_MEMORY_BYTES_PER_POINT)
    monkeypatch.setattr(files.Reader, "chunks", lambda *a, **k: pytest.fail("the file was read"))
    with pytest.raises(InvalidInputError, match="aggregate 'median' needs all of a cell's points"):
        files.compress_file(npy, out, resolution=0.5, aggregate="median")
    assert not out.exists()


@pytest.mark.parametrize("options", [{}, {"frame": "oriented"}, {"aggregate": "max", "target_rmse": 0.01}])
def test_a_file_read_whole_gives_the_bytes_of_the_points_compressed(tmp_path, small_terrain, options):
    # compress_file grids the one chunk through the summary of chunked reading: it must be exact.
    for ext in (".npy", ".ply", ".las"):
        src = tmp_path / f"t{ext}"
        dftpcc.write(src, small_terrain)
        points = dftpcc.read(src).points
        files.compress_file(src, tmp_path / "t.dftpc", **options)
        assert (tmp_path / "t.dftpc").read_bytes() == dftpcc.compress(points, **options), ext


def test_chunked_reading_starts_by_itself_when_memory_is_short(tmp_path, small_terrain, monkeypatch):
    npy = tmp_path / "t.npy"
    np.save(npy, small_terrain)
    monkeypatch.setattr(dftpcc.limits, "available_memory", lambda: 10 ** 12)
    assert not files.reads_in_chunks(npy)
    # Less memory than the points would need held whole.
    monkeypatch.setattr(dftpcc.limits, "available_memory", lambda: small_terrain.shape[0] * dftpcc.limits.IN_MEMORY_BYTES_PER_POINT)
    assert files.reads_in_chunks(npy)
    assert not files.reads_in_chunks(tmp_path / "t.pcd")  # a format read whole


def test_a_cloud_of_more_points_than_held_points_is_read_in_chunks_whatever_the_memory(tmp_path, small_terrain,
                                                                                      monkeypatch):
    """A cloud larger than HELD_POINTS is read in chunks even with memory to spare (held, 100 M points
    took 8.3 GB), but for the median, which needs a cell's points at once; each file meets its target."""
    npy = tmp_path / "t.npy"
    np.save(npy, small_terrain)
    monkeypatch.setattr(dftpcc.limits, "available_memory", lambda: 10 ** 12)
    assert not files.reads_in_chunks(npy)
    monkeypatch.setattr(files, "HELD_POINTS", small_terrain.shape[0] - 1)
    assert files.reads_in_chunks(npy) and not files.reads_in_chunks(npy, aggregate="median")
    sizes, real = [], files._chunk_size
    monkeypatch.setattr(files, "_chunk_size", lambda *a: sizes.append(real(*a)) or sizes[-1])
    for aggregate in ("mean", "median"):
        out = tmp_path / f"{aggregate}.dftpc"
        files.compress_file(npy, out, resolution=1.0, target_rmse=0.05, aggregate=aggregate)
        assert dftpcc.open(str(out)).header.stats["dem_rmse_m"] <= 0.05
    assert sizes == [files.DEFAULT_CHUNK_POINTS, None]


_PEAK = textwrap.dedent("""
    import sys

    import numpy as np

    import dftpcc
    from dftpcc.files import compress_file

    # A small map first, so the code's own memory (numba's compiled kernels under DFTPCC_JIT=1, the
    # transforms' plans) is in the baseline, not in the growth the cloud causes.
    xy = np.random.default_rng(0).uniform(0, 60, (5000, 2))
    dftpcc.compress(np.c_[xy, np.zeros(5000)], resolution=1.0, cutoff=0.9)

    def peak():  # this process's own peak resident memory (getrusage would count the parent's)
        with open("/proc/self/status") as fh:
            return next(int(line.split()[1]) * 1024 for line in fh if line.startswith("VmHWM:"))

    before = peak()
    compress_file(sys.argv[1], sys.argv[1] + ".dftpc", resolution=1.0, cutoff=0.9,
                  chunk_points=int(sys.argv[2]) or None)
    print(peak() - before)
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="peak memory read from /proc (Linux)")
def test_memory_holds_one_chunk_not_the_cloud(tmp_path):
    # 4 M points (96 MB of float64) on a 200 x 200 m map: read whole, the
    # peak grows by several copies of them; in chunks, by about one chunk.
    import laspy

    rng = np.random.default_rng(5)
    n = 4_000_000
    header = laspy.LasHeader(point_format=0, version="1.2")
    header.scales, header.offsets = np.array([0.001, 0.001, 0.001]), np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = rng.uniform(0, 200, n), rng.uniform(0, 200, n), rng.normal(0, 0.1, n)
    src = tmp_path / "big.las"
    las.write(src)
    del las
    growth = {}
    for chunk in (0, 200_000):
        out = subprocess.run([sys.executable, "-c", _PEAK, str(src), str(chunk)], capture_output=True, text=True,
                             timeout=300, check=True)
        growth[chunk] = int(out.stdout.strip())
    assert growth[0] > 96e6, growth  # the whole cloud was held
    assert growth[200_000] < 0.3 * growth[0], growth


def test_a_truncated_file_read_in_chunks_fails_clearly(tmp_path, small_terrain):
    laz = tmp_path / "cut.laz"
    laz.write_bytes(data_file(FIELD).read_bytes()[:1_500_000])  # the header promises more points
    npy = tmp_path / "cut.npy"
    np.save(npy, small_terrain)
    npy.write_bytes(npy.read_bytes()[:5_000])
    for src, fmt in ((laz, "laz"), (npy, "npy")):
        out = tmp_path / f"{fmt}.dftpc"
        with pytest.raises(InvalidInputError, match=f"cannot read as {fmt}"):
            files.compress_file(src, out, resolution=0.5, chunk_points=50_000)
        assert not out.exists()
