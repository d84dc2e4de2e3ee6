"""Sweeps, evaluation of files and the pictures, on real terrain and through the command line."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import numpy as np
import pytest

import dftpcc
from dftpcc import cli
from dftpcc.experiments import evaluate, figures, sweep
from dftpcc.cli import main
from dftpcc.errors import InvalidInputError, MissingDependencyError

from .conftest import data_file

CUTOFFS = (0.0, 0.3, 0.6, 0.8, 0.9, 0.95)


def test_parse_cutoffs():
    assert cli.parse_cutoffs("0.8,0.95") == (0.8, 0.95)
    assert cli.parse_cutoffs("0.95, 0.8, 0.8") == (0.8, 0.95)
    assert cli.parse_cutoffs("0,0.1,...,0.95") == pytest.approx(
        (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95))
    assert cli.parse_cutoffs("0,0.05,...,0.95") == pytest.approx(sweep.DEFAULT_CUTOFFS)
    assert len(sweep.DEFAULT_CUTOFFS) == 20
    for bad in ("", "a", "1.0", "-0.1", "...,0.9", "0.5,...,0.9", "0.5,0.4,...,0.9", "0,0.1,..."):
        with pytest.raises(InvalidInputError):
            cli.parse_cutoffs(bad)


def test_one_resolution_or_one_per_input():
    ts = sweep.terrains(["a.las", "b.ply"], [2.0], classes=[2])
    assert [t.resolution for t in ts] == [2.0, 2.0] and ts[0].classes == (2,) and ts[1].name == "b"
    assert [t.resolution for t in sweep.terrains(["a.las", "b.ply"], [2.0, 5.0])] == [2.0, 5.0]
    with pytest.raises(InvalidInputError):
        sweep.terrains(["a.las", "b.ply", "c.ply"], [2.0, 5.0])
    assert [t.name for t in sweep.terrains(["x/map.las", "y/map.las"], [1.0])] == ["x/map", "y/map"]


@pytest.fixture(scope="module")
def mountain() -> np.ndarray:
    return dftpcc.read(data_file("pointclouds/mountain_arid_alirt.las"), classes=[2]).points


@pytest.fixture(scope="module", params=["paper", "compact"])
def mountain_sweep(request, mountain):
    rows = sweep.sweep_points(mountain, cutoffs=CUTOFFS, resolution=2.0, profile=request.param, label="mountain")
    return request.param, rows


def test_sweep_rows_have_every_column_and_real_file_sizes(mountain_sweep, mountain):
    profile, rows = mountain_sweep
    assert [r["cutoff"] for r in rows] == list(CUTOFFS)
    for row in rows:
        assert set(row) == set(sweep.SWEEP_COLUMNS)
        assert all(row[k] is not None for k in sweep.SWEEP_COLUMNS if k != "input"), row
        assert row["points_original"] == mountain.shape[0]
        assert row["bits_per_point"] == pytest.approx(8 * row["bytes"] / mountain.shape[0])
    # The sizes are those of the file dftpcc.compress writes.
    direct = dftpcc.compress(mountain, resolution=2.0, cutoff=0.8, profile=profile)
    assert rows[CUTOFFS.index(0.8)]["bytes"] == len(direct)


def test_bits_fall_and_error_rises_with_the_cutoff_on_real_terrain(mountain_sweep):
    profile, rows = mountain_sweep
    bits = [r["bits_per_point"] for r in rows]
    assert all(b1 < b0 for b0, b1 in zip(bits, bits[1:])), (profile, bits)
    rmse = [r["paper_rmse_m"] for r in rows]
    assert rmse[-1] > rmse[0]
    # Nothing a codec rebuilds beats the DEM it was given: the gridding floor
    # (which the header states to 5 significant digits).
    assert min(rmse) >= rows[0]["gridding_rmse_m"] * (1 - 1e-4)


def test_bits_fall_with_the_cutoff_on_the_large_field_map(field_ground):
    rows = sweep.sweep_points(field_ground, cutoffs=(0.5, 0.8, 0.95), resolution=0.5, profile="paper")
    bits = [r["bits_per_point"] for r in rows]
    assert bits[0] > bits[1] > bits[2]
    # The paper profile stores 64 bits per kept coefficient: size is geometry, not content.
    assert rows[1]["coef_bytes"] >= 8 * rows[1]["coef_count"]


def test_csv_round_trip(tmp_path, mountain_sweep):
    _, rows = mountain_sweep
    path = sweep.write_csv(rows, tmp_path / "sweep.csv")
    with path.open() as fh:
        assert next(csv.reader(fh)) == list(sweep.SWEEP_COLUMNS)
    back = sweep.read_csv(path)
    assert len(back) == len(rows)
    assert back[3]["paper_rmse_m"] == rows[3]["paper_rmse_m"]  # full precision
    assert back[3]["terrain"] == "mountain"


def test_evaluate_a_compressed_file_or_its_rebuilt_cloud(tmp_path, small_terrain):
    src, packed, rebuilt = tmp_path / "t.npy", tmp_path / "t.dftpc", tmp_path / "back.ply"
    np.save(src, small_terrain)
    dftpcc.compress_file(src, packed, resolution=0.5, cutoff=0.8)
    dftpcc.decompress_file(packed, rebuilt)
    a = evaluate.evaluate_files(src, packed)
    b = evaluate.evaluate_files(src, rebuilt)
    assert a["bits_per_point"] == pytest.approx(8 * packed.stat().st_size / small_terrain.shape[0])
    assert a["points_in_header"] == small_terrain.shape[0]
    assert "bits_per_point" not in b
    for key in ("paper_rmse_m", "vertical_rmse_m", "d1_rmse_m", "chamfer_m", "hausdorff_m"):
        assert a[key] == pytest.approx(b[key], rel=1e-9), key
    assert dftpcc.mapfile.is_dftpc(packed) and not dftpcc.mapfile.is_dftpc(rebuilt)


def test_cli_evaluate_table_and_json(tmp_path, small_terrain, capsys):
    src = tmp_path / "t.npy"
    np.save(src, small_terrain)
    assert main(["evaluate", str(src), str(src), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["paper_rmse_m"] == 0.0 and out["d1_psnr_db"] is None  # infinite PSNR is null in JSON
    packed = tmp_path / "t.dftpc"
    dftpcc.compress_file(src, packed, resolution=0.5, cutoff=0.9)
    assert main(["evaluate", str(src), str(packed)]) == 0
    table = capsys.readouterr().out
    assert "bits per point" in table and "Hausdorff distance" in table
    assert main(["evaluate", str(src), str(tmp_path / "missing.ply")]) == 3


def test_cli_sweep_writes_csv_and_figure(tmp_path, capsys):
    rocks = data_file("pointclouds/redrocks_rough.ply")
    mountain = data_file("pointclouds/mountain_arid_alirt.las")
    out = tmp_path / "out"
    code = main(["sweep", str(rocks), str(mountain), "-r", "5,2",
                 "--cutoffs", "0,0.45,...,0.9,0.95", "--profile", "paper", "-o", str(out)])
    assert code == 0
    rows = sweep.read_csv(out / "sweep.csv")
    assert [(r["terrain"], r["cutoff"]) for r in rows] == [
        (name, fc) for name in ("redrocks_rough", "mountain_arid_alirt") for fc in (0.0, 0.45, 0.9, 0.95)]
    assert {r["resolution_m"] for r in rows if r["terrain"] == "redrocks_rough"} == {5.0}
    assert (out / "sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "sweep.csv" in capsys.readouterr().out
    with pytest.raises(SystemExit) as usage:  # argparse: a usage error
        main(["sweep", str(rocks), "--cutoffs", "0.5,1.5", "-o", str(out)])
    assert usage.value.code == 2
    assert main(["sweep", str(rocks), str(mountain), "-r", "1,2,3", "-o", str(out)]) == 3


def test_cli_compare_draws_the_maps(tmp_path):
    mountain = data_file("pointclouds/mountain_arid_alirt.las")
    assert main(["compare", str(mountain), "--classes", "2", "-r", "2", "--profile", "paper",
                 "-o", str(tmp_path)]) == 0
    png = tmp_path / "mountain_arid_alirt_compare_paper.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_missing_matplotlib_is_one_clear_error(tmp_path, monkeypatch, capsys, small_terrain):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib now raises ImportError
    with pytest.raises(MissingDependencyError, match="pip install"):
        figures.require_matplotlib()
    src = tmp_path / "t.npy"
    np.save(src, small_terrain)
    assert main(["compare", str(src), "-r", "0.5", "-o", str(tmp_path)]) == 6
    assert "pip install" in capsys.readouterr().err
    # A sweep still leaves its CSV behind.
    assert main(["sweep", str(src), "-r", "0.5", "--cutoffs", "0.5", "-q", "-o", str(tmp_path)]) == 6
    assert (tmp_path / "sweep.csv").is_file()


def test_close_up_window_goes_where_the_error_is():
    mask = np.ones((100, 120), dtype=bool)
    error = np.zeros(mask.shape)
    error[70:75, 30:35] = 5.0
    r0, c0, size = figures.choose_window(error, mask)
    assert size == 20
    assert r0 <= 70 and 75 <= r0 + size and c0 <= 30 and 35 <= c0 + size
    assert 0 <= r0 and r0 + size <= 100 and 0 <= c0 and c0 + size <= 120


def test_evaluate_with_its_arguments_swapped_says_so(tmp_path, capsys, mountain):
    src = tmp_path / "m.npy"
    np.save(src, mountain)
    packed = tmp_path / "m.dftpc"
    assert main(["compress", str(src), str(packed), "-r", "2", "-q"]) == 0
    assert main(["evaluate", str(packed), str(src)]) == 3
    err = capsys.readouterr().err
    assert "the original point cloud comes first" in err and "swap them" in err and err.count("\n") == 1


def test_evaluate_against_other_points_than_were_compressed_warns(tmp_path, capsys):
    # A newcomer compressed the ground (--classes 2) and evaluated against every return:
    # 0.650 m instead of 0.029 m, without a word.
    src = data_file("pointclouds/mountain_arid_alirt.las")
    packed = tmp_path / "m.dftpc"
    assert main(["compress", str(src), str(packed), "--classes", "2", "-q"]) == 0
    assert main(["evaluate", str(src), str(packed)]) == 0
    err = capsys.readouterr().err
    assert "was made from 35,318 points but" in err and "gives 38,367" in err and "--classes" in err
    assert main(["evaluate", str(src), str(packed), "--classes", "2"]) == 0
    assert "warning" not in capsys.readouterr().err


def test_sweep_and_compare_make_the_map_compress_makes(tmp_path, capsys):
    # A newcomer's report: on a GeoTIFF, sweep and compare resampled to about 2 x 2 pixels while
    # compress kept the pixel grid; sweep ignored --classes on a PLY where compress refuses it.
    gale = data_file("dems/mars_gale_1m.tif")
    assert main(["compress", str(gale), str(tmp_path / "g.dftpc"), "-q"]) == 0
    packed = dftpcc.open(tmp_path / "g.dftpc")
    assert main(["sweep", str(gale), "--cutoffs", "0.8", "-o", str(tmp_path / "s"), "-q"]) == 0
    (row,) = sweep.read_csv(tmp_path / "s" / "sweep.csv")
    assert (row["grid_rows"], row["grid_cols"]) == (packed.grid.rows, packed.grid.cols)
    assert row["resolution_m"] == packed.grid.resolution
    assert row["bytes"] == packed.size  # the very file compress writes
    rocks = data_file("pointclouds/redrocks_rough.ply")
    for command in (["sweep", str(rocks), "-o", str(tmp_path / "r")], ["compare", str(rocks), "-o", str(tmp_path / "c")],
                    ["compress", str(rocks), str(tmp_path / "r.dftpc")]):
        assert main(command + ["--classes", "2"]) == 3
        assert "classes can only be selected in LAS/LAZ files" in capsys.readouterr().err


def test_compare_states_the_size_of_the_file_compress_writes(tmp_path, monkeypatch):
    """compare left out the CRS (about 520 bytes of WKT) that the file carries: 0.133 bits/point where
    compress of the same cloud wrote 0.1395. Every figure printed is the file's."""
    pytest.importorskip("matplotlib")
    from dftpcc.experiments import compare

    las = data_file("pointclouds/mountain_arid_alirt.las")
    shown = {}
    monkeypatch.setattr(compare, "plot_compare", lambda *a, figures, **k: shown.update(figures) or tmp_path)
    compare.compare_file(las, out=tmp_path, cutoffs=(0.8,), classes=[2])
    cmap = dftpcc.compress_file(las, tmp_path / "m.dftpc", classes=[2], cutoff=0.8)
    assert cmap.crs.get("wkt") and shown[0.8]["bytes"] == cmap.size
    assert shown[0.8]["bits_per_point"] == pytest.approx(cmap.info()["bits_per_point"])


def test_evaluate_on_a_latitude_longitude_map_reports_heights_only(tmp_path):
    """A PSNR peak of '3113.008 m' mixed degrees and metres; D1, Chamfer and Hausdorff meant nothing."""
    korolev = data_file("dems/mars_korolev_mola.tif")
    out = tmp_path / "k.dftpc"
    dftpcc.compress_file(korolev, out)
    result = subprocess.run([sys.executable, "-m", "dftpcc", "evaluate", str(korolev), str(out)],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    for absent in ("D1 PSNR", "PSNR peak", "D1 point-to-point", "Chamfer distance", "Hausdorff distance"):
        assert absent not in result.stdout, result.stdout
    assert "vertical error RMSE" in result.stdout and "degrees of longitude and latitude" in result.stdout
    rows = evaluate.evaluate_files(korolev, out)
    assert "d1_rmse_m" not in rows and rows["vertical_rmse_m"] > 0
    dftpcc.compress_file(data_file("dems/mars_gale_1m.tif"), tmp_path / "g.dftpc")
    projected = evaluate.evaluate_files(data_file("dems/mars_gale_1m.tif"), tmp_path / "g.dftpc")
    assert "d1_rmse_m" in projected and "note" not in projected


def test_figures_label_their_axes_and_scales(tmp_path, monkeypatch):
    """sweep's y label was the column name 'paper_rmse (m)' with no gridding floor (the mountain's
    0.45 m at f_c 0 read as codec error); compare's close-ups clipped rebuilt heights to black and
    had no colour bar."""
    pytest.importorskip("matplotlib")
    from dftpcc.dem import DEM, Grid

    kept = {}
    monkeypatch.setattr(figures, "_save", lambda fig, path, **k: kept.setdefault("fig", fig) and path)
    rows = [{"terrain": "hill", "cutoff": fc, "bits_per_point": 1 - fc, "paper_rmse_m": 0.5 + fc,
             "resolution_m": 1.0, "gridding_rmse_m": 0.45} for fc in (0.0, 0.5, 0.9)]
    figures.plot_sweep(rows, tmp_path / "s.png")
    ax = kept.pop("fig").axes[1]
    assert ax.get_ylabel() == "RMSE, own-cell pairing (m)"
    assert any(list(line.get_ydata()) == [0.45, 0.45] for line in ax.get_lines()), "no gridding-floor line"

    yy, xx = np.mgrid[:40, :40]
    heights = np.sin(xx / 5.0) + yy / 20.0
    grid = Grid(x0=0.0, y0=0.0, z0=100.0, resolution=1.0, rows=40, cols=40)
    original = DEM(grid=grid, heights=heights, mask=np.ones((40, 40), bool))
    rebuilt = DEM(grid=grid, heights=heights + 3.0, mask=original.mask)  # above every original height
    figures.plot_compare(original, {0.9: rebuilt}, tmp_path / "c.png", window=(0, 0, 16))
    fig = kept.pop("fig")
    bars = [a for a in fig.axes if a.get_ylabel().startswith("height")]
    assert len(bars) == 3, [a.get_ylabel() for a in fig.axes]  # whole maps, close-ups, errors
    lows, highs = zip(*(b.get_ylim() for b in bars[:2]))
    assert max(highs) >= 100.0 + heights[:16, :16].max() + 3.0 - 1e-9  # the rebuilt close-up is on the scale
