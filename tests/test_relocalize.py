"""Relocalization against rebuilt maps and the cutoff that keeps it (dftpcc.experiments.relocalize, CLI recommend).

The reduced case of docs/relocalization.md: a 130 m square of Mars Gale, a
few scans of a 16-beam 50 m lidar (fixed seeds), GICP from guesses 0.5 m and
5 degrees off, two cutoffs, and --target-reloc once through the API and once
through the CLI. Tolerances are stated at each assert, from the full run.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys

import numpy as np
import pytest

import dftpcc
from dftpcc import cli
from dftpcc.format.header import params_for_file as _params_for_file, params_from_file
from dftpcc.dem import DEM, Grid
from dftpcc.encoder import encode_dem
from dftpcc.errors import InvalidInputError, MissingDependencyError
from dftpcc.experiments import relocalize as rl
from dftpcc.files import dem_from_geotiff
from dftpcc.params import Params
from dftpcc.rebuild import dem_to_dense_points, dem_to_points

from .conftest import data_file

pytest.importorskip("small_gicp")

#: The crop of Gale the reduced case runs on: rows and columns from 100, 130 cells of 1 m.
CROP = (100, 100, 130)
SCANS = 5


def crop(dem: DEM, i0: int, j0: int, n: int) -> DEM:
    g = dem.grid
    grid = dataclasses.replace(g, x0=g.x0 + j0 * g.resolution, y0=g.y0 + i0 * g.dy, rows=n, cols=n)
    return DEM(grid=grid, heights=dem.heights[i0:i0 + n, j0:j0 + n].copy(), mask=dem.mask[i0:i0 + n, j0:j0 + n].copy())


@pytest.fixture(scope="module")
def gale() -> DEM:
    dem, _ = dem_from_geotiff(data_file("dems/mars_gale_1m.tif"))
    return crop(dem, *CROP)


@pytest.fixture(scope="module")
def scans(gale):
    surface, _ = rl.surface_dem(gale)
    return rl.simulate_scans(surface, SCANS, lidar=rl.RECOMMEND_LIDAR, seed=1)


@pytest.fixture(scope="module")
def chosen(gale) -> rl.Recommendation:
    return rl.recommend(gale, 0.05, scans=SCANS, seed=0)


def test_perturbation_and_error_are_exact():
    rng = np.random.default_rng(0)
    pose = np.eye(4)
    pose[:3, 3] = (10.0, -3.0, 2.0)
    for _ in range(5):
        guess = rl.perturb(pose, rng)
        dt, dr = rl.pose_error(guess, pose)
        assert dt == pytest.approx(rl.OFFSET_M, abs=1e-12)
        assert dr == pytest.approx(rl.OFFSET_DEG, abs=1e-9)


def test_gicp_relocalizes_against_the_true_surface(gale, scans):
    """Measured: median 6 mm, every scan within 10 cm and 1 degree. Asserted: all succeed, median under 2 cm."""
    surface, _ = rl.surface_dem(gale)
    outcome = rl.relocalize_map(surface.sample(0.25), scans, seed=2)
    assert outcome.success() == 1.0
    assert outcome.median_m < 0.02 and outcome.median_deg < 0.1


def test_two_cutoffs(gale, scans):
    """f_c 0.5 keeps relocalization (measured median 13 mm, all succeed); f_c 0.95 loses it (measured 1.4 m, none)."""
    _, to_map = rl.surface_dem(gale)
    out = {}
    for cutoff in (0.5, 0.95):
        points = dftpcc.open(encode_dem(gale, Params(cutoff=cutoff))).read_points() - to_map[:3, 3]
        out[cutoff] = rl.relocalize_map(points, scans, seed=2)
    assert out[0.5].success() >= 0.8 and out[0.5].median_m < 0.04
    assert out[0.95].success() <= 0.2 and out[0.95].median_m > 0.2
    assert out[0.95].coarse >= 0.6  # still the right basin: 2 m and 5 degrees


def test_recommend_chooses_the_smallest_file_that_relocalizes(gale, chosen):
    """Measured on this crop: f_c 0.95 to 0.8 fail, 0.75 relocalizes every scan within 5 cm."""
    tried = chosen.tried
    assert [r["bytes"] for r in tried] == sorted(r["bytes"] for r in tried)
    assert all(r["success"] < rl.RECOMMEND_FRACTION for r in tried[:-1])
    assert tried[-1]["success"] >= rl.RECOMMEND_FRACTION and tried[-1]["cutoff"] == chosen.params.cutoff
    assert 0.5 <= chosen.params.cutoff <= 0.85
    with dftpcc.open(chosen.data) as cmap:
        assert cmap.header.notes == {"target_reloc": 0.05} and cmap.info()["params"]["target_reloc"] == 0.05
        assert cmap.params.cutoff == chosen.params.cutoff
        assert cmap.header.stats["reloc_success_fraction"] == pytest.approx(chosen.success, abs=1e-6)
        points = cmap.read_points()
    # The statistics are the only change: the map is that of the plain file at the chosen cutoff.
    plain = dftpcc.open(encode_dem(gale, Params(cutoff=chosen.params.cutoff))).read_points()
    np.testing.assert_array_equal(points, plain)


def test_recommend_refusals(gale):
    with pytest.raises(InvalidInputError, match=r"cannot be met: a scan counts when within 0.0001 m and 1 degree .* % within 1 degree"):
        rl.recommend(gale, 1e-4, scans=2, cutoffs=(0.9, 0.5))
    with pytest.raises(InvalidInputError, match="smaller than the simulated lidar's range"):
        rl.recommend(crop(gale, 0, 0, 40), 0.05, scans=2)
    empty = DEM(grid=gale.grid, heights=gale.heights, mask=np.zeros_like(gale.mask))
    empty.mask[:2, :] = True  # valid ground only along the border, outside where rovers are placed
    with pytest.raises(InvalidInputError, match=r"too little ground .* \d+ % of the map's cells are empty"):
        rl.recommend(empty, 0.05, scans=2)
    with pytest.raises(InvalidInputError, match="do not give one"):
        rl.recommend(gale, 0.05, Params(cutoff=0.5))
    with pytest.raises(InvalidInputError, match="alone"):
        rl.recommend(gale, 0.05, Params(target_rmse=0.1))
    with pytest.raises(InvalidInputError, match="measures maps coded whole"):
        rl.recommend(gale, 0.05, Params(tile_size=64))
    for bad in (0, -1, math.inf, True):
        with pytest.raises(InvalidInputError, match="positive number of metres"):
            rl.check_target_reloc(bad)


def test_target_reloc_is_a_note_beside_the_parameters_not_one_of_them():
    """The codec's parameters hold no experiment's field; the file keeps it as a PARM note, read
    back and written again unchanged, and a file made without it has none."""
    assert "target_reloc" not in _params_for_file(Params(cutoff=0.8, step=0.01))
    assert "target_reloc" not in {f.name for f in dataclasses.fields(Params)}
    params, notes = params_from_file(json.dumps({"cutoff": 0.5, "step": 0.01, "target_reloc": 0.05}), 1.0)
    assert params.cutoff == 0.5 and notes == {"target_reloc": 0.05}
    assert params_from_file(json.dumps({"cutoff": 0.5, "step": 0.01}), 1.0)[1] == {}


@pytest.fixture(scope="module")
def gale_npy(gale, tmp_path_factory):
    path = tmp_path_factory.mktemp("reloc") / "gale.npy"
    np.save(path, dem_to_points(gale))
    return path


def test_cli_recommend_and_compress(gale_npy, tmp_path, capsys):
    args = ["--target-reloc", "0.05", "--resolution", "1", "--reloc-scans", str(SCANS)]
    assert cli.main(["recommend", str(gale_npy), *args, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["success"] >= rl.RECOMMEND_FRACTION and report["params"]["target_reloc"] == 0.05
    out = tmp_path / "g.dftpc"
    assert cli.main(["compress", str(gale_npy), str(out), *args[:2], *args[2:]]) == 0
    assert "relocalized within 0.05 m" in capsys.readouterr().out
    with dftpcc.open(out) as cmap:
        assert cmap.params.cutoff == report["params"]["cutoff"]
        assert cmap.header.stats["reloc_success_fraction"] >= rl.RECOMMEND_FRACTION


def test_cli_refusals(gale_npy, tmp_path, capsys, monkeypatch):
    out = tmp_path / "x.dftpc"
    base = ["compress", str(gale_npy), str(out), "--resolution", "1", "--reloc-scans", "2"]
    assert cli.main([*base, "--target-reloc", "0.0001"]) == 3
    assert "cannot be met: a scan counts when within" in capsys.readouterr().err
    assert not out.exists()
    assert cli.main([*base, "--target-reloc", "0.05", "--cutoff", "0.5"]) == 3
    assert "do not give one" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:
        cli.main([*base, "--target-reloc", "0.05", "--target-rmse", "0.1"])
    assert stop.value.code == 2
    monkeypatch.setitem(sys.modules, "small_gicp", None)
    assert cli.main([*base, "--target-reloc", "0.05"]) == 6
    assert "pip install 'dftpcc[slam]'" in capsys.readouterr().err
    assert not out.exists()
    with pytest.raises(MissingDependencyError):
        rl.MapTarget(np.zeros((100, 3)))


def test_dense_rebuild():
    """factor 1 is dem_to_points; inside the map the samples lie on a planar DEM exactly; K*K per cell."""
    rows, cols = 12, 15
    i, j = np.mgrid[0:rows, 0:cols]
    grid = Grid(x0=100.0, y0=200.0, z0=5.0, resolution=0.5, rows=rows, cols=cols)
    mask = np.ones((rows, cols), bool)
    mask[0, :4] = False
    dem = DEM(grid=grid, heights=0.3 * j - 0.2 * i, mask=mask)
    np.testing.assert_array_equal(dem_to_dense_points(dem, 1), dem_to_points(dem))
    dense = dem_to_dense_points(dem, 3)
    assert dense.shape == (mask.sum() * 9, 3)
    col = (dense[:, 0] - 100.0) / 0.5 - 0.5
    row = (dense[:, 1] - 200.0) / 0.5 - 0.5
    inner = (row >= 1) & (row <= rows - 2) & (col >= 0) & (col <= cols - 1)
    np.testing.assert_allclose(dense[inner, 2], 5.0 + 0.3 * col[inner] - 0.2 * row[inner], atol=1e-12)
    # Each cell's samples average to its height (the symmetric lattice), borders included up to the slope.
    np.testing.assert_allclose(dense.reshape(-1, 9, 3).mean(axis=1)[:, :2], dem_to_points(dem)[:, :2], atol=1e-12)
    for bad in (0, 1.5, True, -2):
        with pytest.raises(InvalidInputError, match="densify"):
            dem_to_dense_points(dem, bad)


def test_decompress_densify_writes_k_by_k_samples_per_cell(tmp_path):
    """The option docs/relocalization.md measures: a denser rebuilt cloud for registration."""
    import subprocess
    import sys

    import dftpcc
    from dftpcc.rebuild import dem_to_dense_points

    src = tmp_path / "g.dftpc"
    dftpcc.compress_file(data_file("dems/mars_gale_1m.tif"), src, cutoff=0.8)
    one = dftpcc.decompress_file(src, tmp_path / "one.npy")
    three = dftpcc.decompress_file(src, tmp_path / "three.npy", densify=3)
    assert three.shape[0] == 9 * one.shape[0]
    np.testing.assert_array_equal(three, dem_to_dense_points(dftpcc.open(src).read_dem(), 3))
    bad = subprocess.run([sys.executable, "-m", "dftpcc", "decompress", str(src), str(tmp_path / "x.tif"),
                          "--densify", "3"], capture_output=True, text=True)
    assert bad.returncode == 3 and "densify applies to point outputs" in bad.stderr
    assert not (tmp_path / "x.tif").exists()


def test_scans_are_placed_on_a_sparse_map(gale):
    """A sparse cloud gridded finely leaves most cells empty: the rays fell through the gaps and a
    scan came back empty ('no lidar return ... no valid ground within 50 m'). The rover now drives
    the map's footprint, its gaps filled, and a scan without returns is drawn again."""
    rng = np.random.default_rng(2)
    sparse_mask = gale.mask & (rng.random(gale.mask.shape) < 0.3)
    sparse = DEM(grid=gale.grid, heights=np.where(sparse_mask, gale.heights, 0.0), mask=sparse_mask)
    surface, _ = rl.surface_dem(sparse)
    assert np.isfinite(surface.heights).mean() > 0.95
    cast = rl.simulate_scans(surface, 3, lidar=rl.RECOMMEND_LIDAR, seed=0)
    assert len(cast) == 3 and all(scan.points.shape[0] > 100 for scan in cast)
