"""A point cloud whose grid is coded band by band is gridded band by band too (issue 46, item 1): its
points spilled to a file per band of tile rows, each band gridded alone and read back by windows
(grid.rasterize_bands, stream.compress_bands). The bytes are those of the grid held whole; memory
follows a band, not the map. The size threshold is lowered so that real clouds of ../shared/data play
the part of huge ones."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

import dftpcc
from dftpcc import cli, files, limits, stream
from dftpcc.encoder import params_of
from dftpcc.errors import InvalidInputError
from dftpcc.io import atomic_write

from .conftest import data_file

FIELD = "pointclouds/field_gentle_ign.laz"


@pytest.fixture
def small_threshold(monkeypatch):
    monkeypatch.setattr(stream, "STREAM_CELLS", 50_000)


@pytest.fixture
def banded(monkeypatch):
    """Counts the clouds gridded band by band (and fails where that path does not exist)."""
    calls = []
    rasterize_bands = files.rasterize_bands

    def spy(*args, **kwargs):
        calls.append(kwargs["band_rows"])
        return rasterize_bands(*args, **kwargs)

    monkeypatch.setattr(files, "rasterize_bands", spy)
    return calls


def _whole(src, out, options, **read):
    """Today's path for a large grid: the cloud gridded whole (files.read_dem), coded band by band."""
    params = params_of(None, dict(options))
    dem, count, crs = files.read_dem(str(src), params, **read)
    stream.compress_gridded(dem, out, params, point_count=count, crs=crs, write=atomic_write)
    return out.read_bytes()


@pytest.mark.parametrize("options, read", [
    (dict(tile_size=128, target_rmse=0.05), dict(classes=[2])),  # held whole: one chunk
    (dict(tile_size=128, target_rmse=0.05), dict(classes=[2], chunk_points=100_000)),
    (dict(tile_size=64, aggregate="median", target_max_error=0.1), {}),
    (dict(tile_size=64, aggregate="min"), dict(chunk_points=150_001)),
    (dict(tile_size=100, aggregate="max", resolution=0.5), dict(chunk_points=150_001)),
    (dict(tile_size=64, frame="oriented", target_bpp=1.0), {}),
])
def test_a_cloud_gridded_band_by_band_is_the_bytes_of_the_whole_grid(small_threshold, banded, tmp_path,
                                                                     options, read):
    src = data_file(FIELD)
    cmap = dftpcc.compress_file(src, tmp_path / "bands.dftpc", **options, **read)
    assert banded and cmap.header.tiles.tiling.tile_rows > 3  # several bands
    assert (tmp_path / "bands.dftpc").read_bytes() == _whole(src, tmp_path / "whole.dftpc", options, **read)


def test_a_real_forest_at_a_fine_resolution_is_the_bytes_of_the_whole_grid(small_threshold, banded, tmp_path):
    """The 2.8 M-point forest (all returns: a large height spread) at 0.25 m, read in chunks as bench_big reads
    the 102 M-point mosaic of it."""
    src, options = data_file("pointclouds/forest_slope_bcts_2.8M.laz"), dict(tile_size=512, resolution=0.25)
    with pytest.warns(dftpcc.errors.MultiHeightWarning):
        dftpcc.compress_file(src, tmp_path / "bands.dftpc", chunk_points=1_000_000, **options)
    assert banded == [512]
    assert (tmp_path / "bands.dftpc").read_bytes() == _whole(src, tmp_path / "whole.dftpc", options,
                                                             chunk_points=1_000_000)


def _terrain(rows: int, cols: int, *, seed: int = 0, per_cell: float = 1.5) -> np.ndarray:
    """Points on a rolling surface over ``rows`` x ``cols`` one-metre cells, ``per_cell`` a cell, in scan order."""
    rng = np.random.default_rng(seed)
    n = int(rows * cols * per_cell)
    x, y = rng.uniform(0, cols, n), rng.uniform(0, rows, n)
    order = np.lexsort((x, np.floor(y / 8)))  # strips, as a survey's lines
    x, y = x[order], y[order]
    z = 100 + 5 * np.sin(x / 40) * np.cos(y / 55) + rng.normal(0, 0.05, n)
    return np.column_stack([x, y, z])


def test_dropped_non_finite_points_and_a_synthetic_cloud_keep_the_bytes(small_threshold, banded, tmp_path):
    points = _terrain(300, 400)
    points[::997, 2] = np.nan
    points[5::1499, 0] = np.inf
    src = tmp_path / "c.npy"
    np.save(src, points)
    options = dict(tile_size=64, resolution=1.0, target_rmse=0.05)
    for read in (dict(drop_nonfinite=True), dict(drop_nonfinite=True, chunk_points=33_333)):
        dftpcc.compress_file(src, tmp_path / "bands.dftpc", force=True, **options, **read)
        assert (tmp_path / "bands.dftpc").read_bytes() == _whole(src, tmp_path / "whole.dftpc", options, **read)
    assert len(banded) == 2


def _peak_bytes(src, out, **options) -> int:
    tracemalloc.start()
    try:
        dftpcc.compress_file(src, out, **options)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_memory_follows_a_band_not_the_map(small_threshold, banded, tmp_path):
    """A map four times taller (four times the cells and points, read in chunks) peaks at about the same."""
    peaks = []
    for rows in (512, 2048):
        src = tmp_path / f"t{rows}.npy"
        np.save(src, _terrain(rows, 1024, seed=rows))
        peaks.append(_peak_bytes(src, tmp_path / f"t{rows}.dftpc", tile_size=128, resolution=1.0, cutoff=0.9,
                                 step=0.02, chunk_points=50_000))
    assert peaks[1] < 1.6 * peaks[0], [f"{p / 1e6:.1f} MB" for p in peaks]
    assert len(banded) == 2


def test_a_grid_over_the_cell_limit_is_coded_in_bands_and_a_band_over_it_is_refused(small_threshold, banded,
                                                                                    tmp_path, monkeypatch):
    src = data_file(FIELD)
    monkeypatch.setattr(limits, "MAX_CELLS", 100_000)  # the map: 536 x 508 = 272,288 cells; a band: 128 x 508
    with pytest.raises(InvalidInputError, match="100,000-cell limit"):
        files.read_dem(src, params_of(None, dict(tile_size=128)), classes=[2])  # the grid held whole
    cmap = dftpcc.compress_file(src, tmp_path / "ok.dftpc", tile_size=128, classes=[2], target_rmse=0.05)
    assert cmap.grid.size > limits.MAX_CELLS and banded == [128]
    monkeypatch.setattr(limits, "MAX_CELLS", 50_000)  # under a band's 65,024 cells
    with pytest.raises(InvalidInputError, match=r"one band \(65,024 cells\).*resolution of at least 0\.91 m or a "
                                                r"smaller tile size"):
        dftpcc.compress_file(src, tmp_path / "no.dftpc", tile_size=128, classes=[2])
    assert not (tmp_path / "no.dftpc").exists()
    # The hint's resolution fits.
    dftpcc.compress_file(src, tmp_path / "hint.dftpc", tile_size=128, classes=[2], resolution=0.91)


def test_a_mostly_empty_grid_past_the_cell_limit_is_refused_before_any_file(small_threshold, banded, tmp_path,
                                                                             monkeypatch, capsys):
    """Past the limit of a grid held whole, the band path takes a grid its points fill (a few cells a
    point), not one that a stray point made nearly all empty: one line naming the cause and a
    resolution that would do, before any band file or output is written."""
    monkeypatch.setattr(limits, "MAX_CELLS", 100_000)
    points = _terrain(100, 100)  # 10,000 points on 100 x 100 m
    stray = np.vstack([points, [[20_000.0, 20_000.0, 0.0]]])  # one point 20 km away
    src = tmp_path / "stray.npy"
    np.save(src, stray)
    out = tmp_path / "stray.dftpc"
    with pytest.raises(InvalidInputError, match=r"more than 64 cells a point.*stray points.*resolution of at least"):
        dftpcc.compress_file(src, out, tile_size=64, resolution=1.0)
    assert not out.exists() and _spills(tmp_path) == [] and banded == []
    code = cli.main(["compress", str(src), str(out), "--tile-size", "64", "--resolution", "1", "-q"])
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1 and "stray points" in err
    # Without the stray point the same resolution is a grid its points fill.
    np.save(src, points)
    dftpcc.compress_file(src, out, tile_size=64, resolution=1.0)
    assert out.exists()


def _spills(folder):
    return sorted(p.name for p in folder.glob(files.SPILL_PREFIX + "*"))


def test_the_spill_folder_is_removed_after_success_and_after_an_error(small_threshold, banded, tmp_path,
                                                                      monkeypatch):
    src = data_file(FIELD)
    seen, stages = [], []

    def on_stage(name, done=None):
        stages.append((name, done))
        if name == "encode" and done is None:
            seen.append(_spills(tmp_path))

    dftpcc.compress_file(src, tmp_path / "ok.dftpc", tile_size=128, classes=[2], on_stage=on_stage)
    assert len(seen[0]) == 1 and _spills(tmp_path) == []
    grid = [done for name, done in stages if name == "grid" and done is not None]
    assert grid == sorted(grid) and grid[-1] == 1.0 and len(grid) > 3  # progress band by band

    code_block = stream._code_block
    during = []

    def failing(block, job):
        during.append(_spills(tmp_path))
        if len(during) == 3:
            raise InvalidInputError("disk gone")
        return code_block(block, job)

    monkeypatch.setattr(stream, "_code_block", failing)
    with pytest.raises(InvalidInputError, match="disk gone"):
        dftpcc.compress_file(src, tmp_path / "bad.dftpc", tile_size=128, classes=[2])
    assert len(during[-1]) == 1
    assert _spills(tmp_path) == [] and not (tmp_path / "bad.dftpc").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ok.dftpc"]


def test_the_cli_says_in_one_line_when_a_band_would_not_fit(small_threshold, banded, tmp_path, monkeypatch,
                                                            capsys):
    monkeypatch.setattr(limits, "MAX_CELLS", 50_000)
    out = tmp_path / "x.dftpc"
    code = cli.main(["compress", str(data_file(FIELD)), str(out), "--tile-size", "128", "--classes", "2", "-q"])
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1 and "one band" in err and "Traceback" not in err
    assert not out.exists() and _spills(tmp_path) == []


def test_a_cloud_in_bands_on_two_workers_is_the_serial_bytes(small_threshold, banded, tmp_path):
    """Each worker reads its windows from the band files by their path."""
    src = data_file(FIELD)
    dftpcc.compress_file(src, tmp_path / "s.dftpc", tile_size=64, classes=[2], target_rmse=0.05)
    dftpcc.compress_file(src, tmp_path / "p.dftpc", tile_size=64, classes=[2], target_rmse=0.05, workers=2)
    assert len(banded) == 2
    assert (tmp_path / "p.dftpc").read_bytes() == (tmp_path / "s.dftpc").read_bytes()


def test_a_disk_without_room_for_the_band_files_is_refused_before_they_are_written(small_threshold, tmp_path,
                                                                                  monkeypatch):
    monkeypatch.setattr(limits, "SPILL_BYTES_PER_POINT", 10 ** 12)  # a petabyte for 683,023 points: no disk has it
    with pytest.raises(InvalidInputError, match=r"band by band needs about .* free; the points' files alone"):
        dftpcc.compress_file(data_file(FIELD), tmp_path / "x.dftpc", tile_size=128, classes=[2])
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setattr(limits, "SPILL_BYTES_PER_POINT", 0)
    monkeypatch.setattr(limits, "SPILL_BYTES_PER_CELL", 10 ** 9)  # a gigabyte a cell: the hint is a resolution
    with pytest.raises(InvalidInputError, match=r"free; use a resolution of at least \d"):
        dftpcc.compress_file(data_file(FIELD), tmp_path / "x.dftpc", tile_size=128, classes=[2])
