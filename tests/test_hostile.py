"""Hostile point clouds: each has a decided, documented outcome (docs/errors.md).

NaN/inf rows, duplicates, no point, one point, one cell, walls and
overhangs, huge coordinates, a grid that would not fit in memory.
"""

from __future__ import annotations

import math
import subprocess
import sys
import tracemalloc
import warnings

import numpy as np
import pytest

import dftpcc
from dftpcc.errors import InvalidInputError, MultiHeightWarning
from dftpcc.dem import MULTI_HEIGHT_TOLERANCE_CELLS, drop_nonfinite
from dftpcc.grid import auto_resolution, fit_grid, rasterize

PROFILES = [dict(profile="compact"), dict(profile="paper"), dict(profile="compact", transform="dft"),
            dict(profile="compact", frame="oriented")]


def _terrain(n: int = 2000, seed: int = 0, offset=(0.0, 0.0, 0.0)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 30.0, (n, 2))
    z = 0.3 * np.sin(xy[:, 0] / 5.0) + 0.02 * xy[:, 1] + rng.normal(0.0, 0.005, n)
    return np.column_stack([xy, z]) + np.asarray(offset)


def _quiet(func, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MultiHeightWarning)
        return func(*args, **kwargs)


# --- NaN and inf rows: an error by default, dropping them is an explicit opt-in -----------------

@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nonfinite_rows_are_refused_with_their_row_numbers(bad):
    pts = _terrain(100)
    pts[[3, 50], 2] = bad
    pts[70, 0] = bad
    with pytest.raises(InvalidInputError, match=r"3 of 100 point\(s\) have NaN or infinite.*rows 3, 50, 70.*drop"):
        dftpcc.compress(pts, resolution=1.0)
    with pytest.raises(InvalidInputError, match="NaN or infinite"):
        dftpcc.compress(pts)  # resolution 'auto' checks first


def test_dropping_nonfinite_rows_is_an_explicit_choice(tmp_path):
    pts = _terrain(100)
    dirty = pts.copy()
    dirty[[5, 6], 1] = np.nan
    kept, dropped = drop_nonfinite(dirty)
    assert dropped == 2 and kept.shape == (98, 3)
    np.testing.assert_array_equal(kept, np.delete(pts, [5, 6], axis=0))
    assert dftpcc.decompress(dftpcc.compress(kept, resolution=1.0)).shape[1] == 3
    # The reader offers the same opt-in.
    path = tmp_path / "dirty.xyz"
    path.write_text("0 0 0\n1 1 nan\n2 2 inf\n3 3 3\n")
    assert dftpcc.read(path).points.shape == (4, 3)
    assert dftpcc.read(path, drop_nonfinite=True).points.shape == (2, 3)
    path.write_text("nan 0 0\n1 nan 1\n")
    with pytest.raises(InvalidInputError, match="all 2 points have NaN"):
        dftpcc.read(path, drop_nonfinite=True)


# --- duplicates: accepted; exact duplicates change nothing but the point count -------------------

def test_duplicate_points_change_nothing_but_the_count():
    pts = _terrain(1500)
    once, twice = dftpcc.compress(pts, resolution=1.0), dftpcc.compress(np.vstack([pts, pts]), resolution=1.0)
    np.testing.assert_allclose(dftpcc.decompress(twice), dftpcc.decompress(once), rtol=1e-12, atol=1e-12)
    assert dftpcc.open(twice).header.point_count == 3000
    assert dftpcc.open(once).header.point_count == 1500
    # Some points repeated: each copy weighs in its cell's mean like any other point.
    some = np.vstack([pts, pts[:1], pts[:1]])
    dem, ref = rasterize(some, fit_grid(some, 1.0)), rasterize(pts, fit_grid(pts, 1.0))
    np.testing.assert_array_equal(dem.mask, ref.mask)
    cell = dem.grid.flat_index(pts[:1])[0]
    in_cell = pts[dem.grid.flat_index(pts) == cell, 2]
    expected = (in_cell.sum() + 2 * pts[0, 2]) / (in_cell.size + 2) - dem.grid.z0
    assert dem.heights.ravel()[cell] == pytest.approx(expected, abs=1e-12)


# --- nothing, one point, one cell ---------------------------------------------------------------

@pytest.mark.parametrize("empty", [np.zeros((0, 3)), np.zeros((0, 4))])
def test_an_empty_cloud_is_refused(empty):
    with pytest.raises(InvalidInputError, match="empty"):
        dftpcc.compress(empty, resolution=1.0)
    with pytest.raises(InvalidInputError, match="empty"):
        dftpcc.compress(empty)


@pytest.mark.parametrize("bad", [np.zeros((5, 2)), np.zeros(3), np.array([["a", "b", "c"]]), np.zeros((2, 3), complex)])
def test_not_a_cloud_is_refused(bad):
    with pytest.raises(InvalidInputError, match="points must"):
        dftpcc.compress(bad, resolution=1.0)


@pytest.mark.parametrize("options", PROFILES)
def test_one_point_is_a_one_cell_map(options):
    pts = np.array([[631_000.25, 4_833_000.75, 118.5]])
    data = dftpcc.compress(pts, resolution=0.5, **options)
    m = dftpcc.open(data)
    assert m.grid.shape == (1, 1) and m.header.cell_count == 1 and m.header.point_count == 1
    back = dftpcc.decompress(data)
    assert back.shape == (1, 3)
    # At the centre of its cell (half a cell away at most), at its own height.
    assert np.hypot(*(back[0, :2] - pts[0, :2])) <= 0.5 * math.sqrt(2) / 2 + 1e-9
    assert back[0, 2] == pytest.approx(118.5, abs=1e-4)


def test_one_point_needs_a_resolution():
    with pytest.raises(InvalidInputError, match="one x, y position; give a resolution"):
        dftpcc.compress(np.array([[1.0, 2.0, 3.0]]))
    with pytest.raises(InvalidInputError, match="one x, y position"):
        auto_resolution(np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 7.0]]))


def test_all_points_in_one_cell_are_a_one_cell_map_at_their_mean_height():
    rng = np.random.default_rng(4)
    pts = np.column_stack([rng.uniform(10.0, 10.4, 300), rng.uniform(20.0, 20.4, 300), rng.normal(5.0, 0.01, 300)])
    data = dftpcc.compress(pts, resolution=1.0)
    back = dftpcc.decompress(data)
    assert back.shape == (1, 3)
    assert back[0, 2] == pytest.approx(pts[:, 2].mean(), abs=1e-4)
    stats = dftpcc.open(data).header.stats
    assert stats["gridding_rmse_m"] == pytest.approx(pts[:, 2].std(), rel=1e-4)  # 5 significant digits


def test_a_transect_along_an_axis_gets_an_automatic_resolution():
    x = np.linspace(0.0, 100.0, 401)
    pts = np.column_stack([x, np.full_like(x, 7.0), np.sin(x / 10.0)])
    res = auto_resolution(pts)
    assert res == pytest.approx(4 * 0.25)  # four points per cell along the line
    back = dftpcc.decompress(dftpcc.compress(pts))
    assert back.shape[0] == fit_grid(pts, res).cols


# --- walls and overhangs: the DEM keeps one height per cell, and says what it lost ----------------

def _ground_and_wall(res: float = 1.0):
    rng = np.random.default_rng(7)
    ground = np.column_stack([rng.uniform(0, 40, 8000), rng.uniform(0, 40, 8000), rng.normal(0, 0.01, 8000)])
    # A 10 m vertical wall along x = 20 and a ledge (overhang) at 3 m over a 4 x 4 m patch.
    wall = np.column_stack([np.full(1000, 20.3), rng.uniform(0, 40, 1000), rng.uniform(0, 10, 1000)])
    ledge = np.column_stack([rng.uniform(5, 9, 400), rng.uniform(5, 9, 400), np.full(400, 3.0)])
    return np.vstack([ground, wall, ledge])


def test_a_wall_and_an_overhang_are_reported():
    pts = _ground_and_wall()
    grid = fit_grid(pts, 1.0)
    with pytest.warns(MultiHeightWarning, match=r"% of the points .* lie more than 1 m .* up to") as record:
        dem = rasterize(pts, grid)
    spread = dem.spread
    # Measured independently: distance of each point to its own cell's mean height.
    idx = grid.flat_index(pts)
    dz = np.abs(pts[:, 2] - grid.z0 - dem.heights.ravel()[idx])
    far = dz > MULTI_HEIGHT_TOLERANCE_CELLS * 1.0
    assert spread.unrepresented_points == far.sum() > 0
    assert spread.fraction == pytest.approx(far.mean())
    assert spread.unrepresented_cells == np.unique(idx[far]).size
    assert spread.unrepresented_rmse_m == pytest.approx(np.sqrt(np.mean(dz[far] ** 2)))
    assert spread.max_distance_m == pytest.approx(dz.max())
    assert 0.05 < spread.fraction < 0.2  # wall and ledge points, not the ground
    assert f"{100 * spread.fraction:.2f} %" in str(record[0].message)
    stats = spread.as_stats()
    assert stats["unrepresented_fraction"] == spread.fraction and stats["unrepresented_tolerance_m"] == 1.0


def test_compressing_a_wall_warns_but_works():
    pts = _ground_and_wall()
    with pytest.warns(MultiHeightWarning):
        data = dftpcc.compress(pts, resolution=1.0)
    assert dftpcc.decompress(data).shape[0] == dftpcc.open(data).header.cell_count


def test_gentle_terrain_does_not_warn():
    with warnings.catch_warnings():
        warnings.simplefilter("error", MultiHeightWarning)
        dem = rasterize(_terrain(), fit_grid(_terrain(), 0.5))
    assert dem.spread.unrepresented_points == 0 and dem.spread.fraction == 0.0


def test_the_command_line_prints_the_wall_warning_in_one_line(tmp_path):
    src, out = tmp_path / "wall.npy", tmp_path / "wall.dftpc"
    np.save(src, _ground_and_wall())
    # Not -q: it prints nothing but errors (tests/test_cli.py::test_quiet_prints_no_warning).
    result = subprocess.run([sys.executable, "-m", "dftpcc", "compress", str(src), str(out), "-r", "1"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert all(ln.startswith("dftpcc: warning: ") for ln in lines), lines  # one line per warning
    assert sum("% of the points" in ln for ln in lines) == 1, lines


# --- huge coordinates, huge extents ------------------------------------------------------------------

@pytest.mark.parametrize("options", PROFILES)
def test_coordinates_of_ten_million_metres_round_trip(options):
    offset = (1.0e7, 1.0e7, 1.0e7)
    pts = _terrain(3000, offset=offset)
    data = _quiet(dftpcc.compress, pts, resolution=1.0, cutoff=0.0, **options)
    at_origin = _quiet(dftpcc.compress, pts - np.asarray(offset), resolution=1.0, cutoff=0.0, **options)
    back = dftpcc.decompress(data)
    dem = _quiet(rasterize, pts, fit_grid(pts, 1.0, frame=options.get("frame", "axis")))
    rows, cols = np.nonzero(dem.mask)
    x, y = dem.grid.centres(rows, cols)
    # Cell centres come back to the micrometre, heights within the error the file states.
    np.testing.assert_allclose(back[:, 0], x, rtol=0, atol=1e-6)
    np.testing.assert_allclose(back[:, 1], y, rtol=0, atol=1e-6)
    err = back[:, 2] - (dem.heights[rows, cols] + dem.grid.z0)
    stats = dftpcc.open(data).header.stats
    assert np.abs(err).max() <= stats["dem_max_error_m"] + 1e-6
    # Large coordinates cost no accuracy: the same cloud at the origin does no better.
    assert stats["dem_rmse_m"] <= 1.001 * dftpcc.open(at_origin).header.stats["dem_rmse_m"] + 1e-9


def test_a_grid_that_would_not_fit_in_memory_is_refused_with_the_numbers():
    pts = np.array([[0.0, 0.0, 0.0], [1.0e7, 1.0e7, 1.0]])  # 10,000 km at 0.1 m
    tracemalloc.start()
    try:
        with pytest.raises(InvalidInputError) as info:
            dftpcc.compress(pts, resolution=0.1)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    message = str(info.value)
    assert "100,000,001 x 100,000,001 grid" in message and "1e+16 cells" in message
    assert "PB of memory" in message and "at least 1100 m" in message
    assert peak < 1 << 20  # refused before allocating anything grid-sized
    # The suggested resolution fits.
    assert fit_grid(pts, 1100.0).size <= dftpcc.limits.MAX_CELLS


def test_the_memory_limit_follows_the_machine(monkeypatch):
    from dftpcc import limits

    monkeypatch.setattr(limits, "available_memory", lambda: 128 * 1000 * limits.ENCODE_BYTES_PER_CELL)
    pts = np.array([[0.0, 0.0, 0.0], [999.0, 999.0, 1.0]])  # a million cells at 1 m
    with pytest.raises(InvalidInputError, match=r"exceeds the 128,000 cells that the available memory"):
        fit_grid(pts, 1.0)
    assert fit_grid(pts, 3.0).size <= 128_000


@pytest.mark.parametrize("resolution", [1e-300, 5e-324])
def test_a_vanishing_resolution_is_refused_not_overflowed(resolution):
    with pytest.raises(InvalidInputError, match="below the smallest cell size a map may have, 1e-09 m"):
        dftpcc.compress(_terrain(10), resolution=resolution)
    with pytest.raises(InvalidInputError, match="more cells than can be counted|exceeds"):
        dftpcc.compress(_terrain(10, offset=(0.0, 0.0, 0.0)) * np.array([1e12, 1e12, 1.0]), resolution=1e-9)


def test_coordinates_too_large_for_float64_cells_are_refused():
    pts = _terrain(100, offset=(1e15, 1e15, 0.0))
    with pytest.raises(InvalidInputError, match="resolved only to .* subtract an offset"):
        dftpcc.compress(pts, resolution=0.1)
    with pytest.raises(InvalidInputError, match="more cells than can be counted"):
        dftpcc.compress(np.array([[0.0, 0.0, 0.0], [1e300, -1e300, 0.0]]), resolution=1.0)


def test_an_integer_geotiff_is_read(tmp_path):
    rasterio = pytest.importorskip("rasterio")
    from rasterio.transform import from_origin

    heights = (np.arange(20 * 30, dtype=np.int16).reshape(20, 30) % 97) - 40
    path = tmp_path / "int16.tif"
    with rasterio.open(path, "w", driver="GTiff", height=20, width=30, count=1, dtype="int16", nodata=-32768,
                       transform=from_origin(500000.0, 4000000.0, 30.0, 30.0)) as dst:
        heights[0, 0] = -32768
        dst.write(heights, 1)
    cmap = dftpcc.compress_file(path, tmp_path / "int16.dftpc", cutoff=0.0)
    assert cmap.header.cell_count == 20 * 30 - 1
    dem = cmap.read_dem()
    np.testing.assert_allclose(dem.heights[dem.mask] + dem.grid.z0, heights[::-1][dem.mask], atol=0.05)
