"""Rate control keeps its promise on every file in ../shared/data.

Each target is checked by decoding the file and comparing with an
independently gridded DEM, not by trusting the statistics the file states.
"""

from __future__ import annotations

import math
import struct
import warnings

import numpy as np
import pytest

import dftpcc
from dftpcc.files import dem_from_geotiff
from dftpcc.grid import fit_grid, rasterize
from dftpcc import ratecontrol
from dftpcc.params import Params, make_params

from .conftest import data_file

# (file, resolution in metres or None for a DEM's own grid, LAS classes)
CASES = [
    ("pointclouds/field_gentle_ign.laz", 0.5, [2]),
    ("pointclouds/coastal_plain_ign.laz", 2.0, [2]),
    ("pointclouds/rural_valley_ign.laz", 2.0, [2]),
    ("pointclouds/urban_autzen.laz", 2.0, None),
    ("pointclouds/forest_hills_topography.laz", 1.0, [2]),
    ("pointclouds/forest_slope_bcts_2.8M.laz", 2.0, [2]),
    ("pointclouds/rolling_strip_raleigh_2.3M.laz", 20.0, None),
    ("pointclouds/mountain_arid_alirt.las", 2.0, None),
    ("pointclouds/redrocks_rough.ply", 5.0, None),
    ("dems/mars_gale_1m.tif", None, None),
    ("dems/moon_kepler_lola_48m.tif", None, None),
    ("dems/mars_korolev_mola.tif", None, None),
    ("dems/earth_bigtujunga_srtm30.tif", None, None),
    ("dems/earth_davos_10m.tif", None, None),
    ("dems/earth_heidelberg_25m.tif", None, None),
]


def _load(name, resolution, classes):
    """The gridded DEM and a function that compresses it with given options."""
    path = data_file(name)
    if resolution is None:
        dem, _ = dem_from_geotiff(path)

        def encode(**options):
            from dftpcc.encoder import encode_dem

            return encode_dem(dem, make_params(resolution=dem.grid.resolution, **options))

        return dem, dem.mask.sum(), encode
    points = dftpcc.read(path, classes=classes).points
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # vegetation and walls: reported elsewhere
        dem = rasterize(points, fit_grid(points, resolution))

        def encode(**options):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return dftpcc.compress(points, resolution=resolution, **options)

    return dem, points.shape[0], encode


@pytest.mark.parametrize("name,resolution,classes", CASES, ids=[c[0].split("/")[1] for c in CASES])
def test_targets_hold_on_real_terrain(name, resolution, classes):
    dem, n_points, encode = _load(name, resolution, classes)
    relief = float(np.ptp(dem.heights[dem.mask]))

    target_rmse = 0.002 * relief
    data = encode(target_rmse=target_rmse)
    err = (dftpcc.open(data).read_dem().heights - dem.heights)[dem.mask]
    assert np.sqrt(np.mean(err**2)) <= target_rmse * (1 + 1e-9)

    target_max = 0.005 * relief
    data = encode(target_max_error=target_max)
    err = (dftpcc.open(data).read_dem().heights - dem.heights)[dem.mask]
    assert np.abs(err).max() <= target_max

    # A size target, loose enough to be reachable on every file (the mask alone
    # must fit), tight enough that the search has work to do.
    stats = dftpcc.open(data).header.stats
    floor_bytes = stats["mask_bytes"] + 1500
    target_bpp = max(0.2, 8 * floor_bytes / n_points * 1.5)
    data = encode(target_bpp=target_bpp)
    assert 8 * len(data) <= target_bpp * n_points
    m = dftpcc.open(data)
    assert m.params.target_bpp == target_bpp
    assert m.header.stats["dem_rmse_m"] > 0


def test_more_bits_buy_less_error(field_ground):
    errors = []
    for bpp in (0.08, 0.15, 0.4):
        m = dftpcc.open(dftpcc.compress(field_ground, resolution=0.5, target_bpp=bpp))
        errors.append(m.header.stats["dem_rmse_m"])
    assert errors[0] > errors[1] > errors[2]


def test_cutoff_given_with_a_target_fixes_the_cutoff(field_ground):
    m = dftpcc.open(dftpcc.compress(field_ground, resolution=0.5, cutoff=0.7, target_rmse=0.03))
    assert m.params.cutoff == 0.7
    assert m.header.stats["dem_rmse_m"] <= 0.03


def test_a_fixed_cutoff_under_a_target_searches_the_step_only(tmp_path):
    # A newcomer's report: --cutoff 0.5 with --target-rmse wrote 566,822 B at a step of 0.000 mm,
    # where rate control choosing the same cutoff 0.5 wrote 21,630 B: the step search ignored
    # the energy the low-pass drops when only the kept circle was sorted.
    from dftpcc.cli import main

    src = data_file("pointclouds/field_gentle_ign.laz")
    chosen, fixed = tmp_path / "chosen.dftpc", tmp_path / "fixed.dftpc"
    assert main(["compress", str(src), str(chosen), "--classes", "2", "-r", "0.5", "--target-rmse", "0.02", "-q"]) == 0
    cutoff = dftpcc.open(chosen).params.cutoff
    assert main(["compress", str(src), str(fixed), "--classes", "2", "-r", "0.5", "--target-rmse", "0.02",
                 "--cutoff", str(cutoff), "-q"]) == 0
    a, b = dftpcc.open(chosen), dftpcc.open(fixed)
    assert b.params.cutoff == cutoff
    assert b.header.stats["dem_rmse_m"] <= 0.02
    assert b.size <= 1.02 * a.size  # the same search at the same cutoff (measured: equal)


def test_a_target_out_of_reach_at_a_fixed_cutoff_says_what_to_change(tmp_path, capsys):
    from dftpcc.cli import main

    src = data_file("pointclouds/field_gentle_ign.laz")
    code = main(["compress", str(src), str(tmp_path / "x.dftpc"), "--classes", "2", "-r", "0.5",
                 "--target-rmse", "0.02", "--cutoff", "0.8", "-q"])
    err = capsys.readouterr().err
    assert code == 3 and not (tmp_path / "x.dftpc").exists()
    assert "cannot be reached at cutoff 0.8: the low-pass alone leaves 0.024 m" in err
    assert "lower the cutoff" in err and len(err.strip().splitlines()) == 1


def test_unreachable_targets_fail_clearly(small_terrain):
    with pytest.raises(dftpcc.InvalidInputError, match="cannot be reached"):
        dftpcc.compress(small_terrain, resolution=0.5, target_bpp=0.0001)
    with pytest.raises(dftpcc.InvalidInputError, match="at most one"):
        dftpcc.compress(small_terrain, resolution=0.5, target_bpp=1, target_rmse=0.1)


def test_paper_profile_rate_control_picks_the_cutoff(field_ground):
    # The paper's open question: which cutoff for this terrain? Answered for an error.
    m = dftpcc.open(dftpcc.compress(field_ground, resolution=0.5, profile="paper", target_rmse=0.1))
    assert m.params.storage == "complex64"
    assert m.header.stats["dem_rmse_m"] <= 0.1
    assert m.params.cutoff in (0.0, 0.3, 0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.93, 0.95, 0.97)


def test_footprint_mask_costs_less_and_keeps_the_error(field_ground):
    exact = dftpcc.open(dftpcc.compress(field_ground, resolution=0.5, cutoff=0.8))
    foot = dftpcc.open(dftpcc.compress(field_ground, resolution=0.5, cutoff=0.8, mask="footprint"))
    assert foot.header.stats["mask_bytes"] < 0.5 * exact.header.stats["mask_bytes"]
    assert foot.header.stats["dem_rmse_m"] == pytest.approx(exact.header.stats["dem_rmse_m"])
    assert foot.header.cell_count == exact.header.cell_count + foot.header.stats["cells_interpolated"]
    # every original point's own cell is still rebuilt
    dem = foot.read_dem()
    idx = dem.grid.flat_index(field_ground)
    assert dem.mask.ravel()[idx].all()


def _no_residual_for_rmse(monkeypatch):
    """Rate control without the residual-layer files for an RMSE target: the search's and the
    model's (dftpcc.ratemodel) alternatives both left out."""
    from dftpcc import ratecontrol, ratemodel

    monkeypatch.setattr(ratecontrol, "corrected_for_rmse", lambda an, params, first: None)
    monkeypatch.setattr(ratemodel, "_corrected_for_rmse", lambda *args: None)


def test_consistent_fill_makes_rate_controlled_files_smaller(field_ground, monkeypatch):
    # A third of the field's cells are empty (buildings and trees left out of
    # the ground class): refilling them from the coded map needs fewer bits
    # for the same error than the push-pull fill (4.5 % when this was written).
    # The low-pass alone is compared: at this target a coarser low-pass with a
    # residual layer is smaller still, and its base is not refilled.
    from dftpcc import ratecontrol

    _no_residual_for_rmse(monkeypatch)
    sizes = {}
    for fill in ("smooth", "consistent"):
        data = dftpcc.compress(field_ground, resolution=0.5, target_rmse=0.02, fill=fill)
        m = dftpcc.open(data)
        assert m.header.stats["dem_rmse_m"] <= 0.02
        assert m.params.fill == fill
        sizes[fill] = m.header.stats["coef_bytes"]
    assert sizes["consistent"] < 0.98 * sizes["smooth"], sizes


def test_consistent_fill_leaves_full_maps_alone():
    # One point per cell of a 60 x 50 lattice: no empty cell, nothing to
    # refill, so the very same coefficients as the smooth fill.
    y, x = np.mgrid[0:50, 0:60] + 0.5
    pts = np.column_stack([x.ravel(), y.ravel(), (np.sin(x / 7) * np.cos(y / 5) + 0.01 * x).ravel()])
    stats = [dftpcc.open(dftpcc.compress(pts, resolution=1.0, target_rmse=0.01, fill=fill)).header.stats
             for fill in ("smooth", "consistent")]
    assert stats[0]["coef_bytes"] == stats[1]["coef_bytes"]
    assert stats[0]["dem_rmse_m"] == stats[1]["dem_rmse_m"] <= 0.01


def test_the_step_search_uses_the_headroom_of_a_gappy_map(field_ground):
    # At a high cutoff the filled cells of the field hold more error than the
    # whole target, so the whole-grid proxy never came down to its goal and the
    # search kept the finest step: 10,775 bytes at 88 % of the target, where a
    # coarse step meets it with 3,830.
    floor = dftpcc.open(dftpcc.compress(field_ground, resolution=0.5, cutoff=0.0)).header.stats["gridding_rmse_m"]
    target = 3 * floor
    m = dftpcc.open(dftpcc.compress(field_ground, resolution=0.5, target_rmse=target))
    assert 0.9 * target <= m.header.stats["dem_rmse_m"] <= target
    assert m.params.step > 0.1  # metres: a real quantizer step, not the exact fallback


def test_a_max_error_search_goes_coarser_while_the_file_shrinks(monkeypatch):
    """On rough terrain the residual layer carries most of the map: the best file came at the
    coarsest step of the fixed ladder (16 times the bound) on Davos at 1 cm. The search doubles the
    step at the cutoffs that were still shrinking there, keeps the guarantee, and finds a smaller
    file than the fixed ladder."""
    from dftpcc import ratecontrol, residual

    dem, _, encode = _load("dems/earth_davos_10m.tif", None, None)
    bound = 0.01
    monkeypatch.setattr(residual, "_encode_predicted", lambda q, kept: None)  # the search alone
    with ratecontrol.method("search"):  # the search's own ladder (the model's steps go as far)
        found = encode(target_max_error=bound)
        monkeypatch.setattr(ratecontrol, "MAX_ERROR_STEP_FACTOR_LIMIT", ratecontrol.MAX_ERROR_STEP_FACTORS[-1])
        ladder = encode(target_max_error=bound)
    with dftpcc.open(found) as cmap, dftpcc.open(ladder) as fixed:
        assert cmap.params.step > ratecontrol.MAX_ERROR_STEP_FACTORS[-1] * bound
        assert fixed.params.step <= ratecontrol.MAX_ERROR_STEP_FACTORS[-1] * bound
        err = np.abs(cmap.read_dem().heights - dem.heights)[dem.mask]
    assert len(found) < 0.97 * len(ladder), (len(found), len(ladder))
    assert err.max() <= bound


def test_rough_terrain_at_a_fine_bound_is_predicted_rather_than_low_passed(monkeypatch):
    """Davos at 1 and 20 cm: the smallest file has no spectrum, and its residual layer, the heights
    on steps of 2E, is predicted from their neighbours (RESD kind 5); smaller than the best
    low-pass with a chunked residual, within the bound, and decoded as the document says on a
    window of it."""
    from dftpcc import residual
    from dftpcc.format.reader import _sections

    from . import spec_decoder

    dem, _, encode = _load("dems/earth_davos_10m.tif", None, None)
    for bound in (0.01, 0.2):
        found = encode(target_max_error=bound)
        sections, _ = _sections(memoryview(found), allow_truncated_coef=False)
        assert struct.unpack_from("<I", bytes(sections[b"RESD"]), 16)[0] == 5
        with dftpcc.open(found) as cmap:
            err = np.abs(cmap.read_dem().heights - dem.heights)[dem.mask]
        assert err.max() <= bound
        with monkeypatch.context() as m:
            m.setattr(residual, "_encode_predicted", lambda q, kept: None)
            without = encode(target_max_error=bound)
        assert len(found) < 0.93 * len(without), (bound, len(found), len(without))
    # A window of Davos through the document's reader (cell by cell in Python: a small one).
    from dftpcc.dem import DEM

    window = DEM(grid=dem.grid.window(200, 300, 48, 64), heights=dem.heights[200:248, 300:364],
                 mask=dem.mask[200:248, 300:364])
    from dftpcc.encoder import encode_dem

    data = encode_dem(window, make_params(resolution=dem.grid.resolution, target_max_error=0.01))
    sections, _ = _sections(memoryview(data), allow_truncated_coef=False)
    assert struct.unpack_from("<I", bytes(sections[b"RESD"]), 16)[0] == 5
    np.testing.assert_allclose(spec_decoder.decode(data), dftpcc.decompress(data), rtol=0, atol=1e-9)


def test_a_scattered_map_at_an_rmse_target_is_predicted_rather_than_low_passed(monkeypatch):
    """The coastal plain's ground at 2 m (39 % of cells occupied, scattered): near the gridding
    floor a transform must code the empty cells too, and the smallest file within the RMSE is the
    heights on steps of 2E predicted from their neighbours. Its PARM states E as
    target_max_error; the decoded map meets the RMSE asked for and every cell is within E. At a
    looser target a coarse low-pass keeps most cells within it, and a sparse layer at a bound
    well past the target brings back the few it leaves far off: smaller than the low-pass alone."""
    from dftpcc import ratecontrol

    dem, _, encode = _load("pointclouds/coastal_plain_ign.laz", 2.0, [2])

    def decoded_within(data, target):
        with dftpcc.open(data) as cmap:
            assert cmap.params.target_rmse == 0.0 and target <= cmap.params.target_max_error
            err = (cmap.read_dem().heights - dem.heights)[dem.mask]
            assert np.abs(err).max() <= cmap.params.target_max_error
            assert np.sqrt(np.mean(err ** 2)) <= target
            return cmap

    found, loose = encode(target_rmse=0.0275), encode(target_rmse=0.0933)
    cmap = decoded_within(found, 0.0275)
    assert cmap.info().get("residual_layout") == "predicted" and cmap.params.target_max_error <= 2 * 0.0275
    cmap = decoded_within(loose, 0.0933)
    assert cmap.params.cutoff < max(ratecontrol.CUTOFF_CANDIDATES) and cmap.params.target_max_error > 2 * 0.0933
    _no_residual_for_rmse(monkeypatch)
    assert len(found) < 0.8 * len(encode(target_rmse=0.0275))
    assert len(loose) < 0.93 * len(encode(target_rmse=0.0933))


def _rough_scattered(n=160, seed=1):
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(n) + 0.5, np.arange(n) + 0.5)
    z = 100 + np.cumsum(rng.normal(0, 1, (n, n)), 0) + np.cumsum(rng.normal(0, 1, (n, n)), 1)
    keep = rng.random((n, n)) > 0.4
    return np.c_[x[keep], y[keep], z[keep]]


def test_a_map_with_no_spectrum_is_offered_only_where_its_residual_can_carry_it():
    """A rough, scattered map at an RMSE target: whole, its smallest file is predicted; tiled, the
    tiles would code their residuals against bases the map's trial only approximates, and with the
    footprint mask the cells without a height would all be rebuilt at 0, so neither is offered
    one. Every file meets the target."""
    pts = _rough_scattered()
    grid = fit_grid(pts, 1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        dem = rasterize(pts, grid)
        for options, layout in (({}, "predicted"), ({"tile_size": 64}, None), ({"mask": "footprint"}, None)):
            data = dftpcc.compress(pts, resolution=1.0, target_rmse=0.2, **options)
            with dftpcc.open(data) as cmap:
                assert cmap.info().get("residual_layout") == layout, options
                rebuilt = cmap.read_dem().heights
            err = (rebuilt - dem.heights)[dem.mask]
            assert np.sqrt(np.mean(err ** 2)) <= 0.2, options
            if options.get("mask") == "footprint":  # the enclosed empty cells: between their neighbours
                assert np.nanmin(rebuilt) >= dem.heights[dem.mask].min() - 5.0


def test_an_rmse_file_with_a_residual_layer_decodes_as_the_document_says():
    """docs/format.md, RESD: a file made for an RMSE target that holds a residual layer states its
    bound as target_max_error; the document's reader decodes it as any maximum-error file."""
    from . import spec_decoder

    pts = _rough_scattered(n=40, seed=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        data = dftpcc.compress(pts, resolution=1.0, target_rmse=0.2)
    with dftpcc.open(data) as cmap:
        assert cmap.info().get("residual_layout") == "predicted" and cmap.params.target_max_error > 0
    np.testing.assert_allclose(spec_decoder.decode(data), dftpcc.decompress(data), rtol=0, atol=1e-9)


def test_the_map_with_no_spectrum_needs_every_rebuilt_cell_measured():
    """With the footprint mask the cells a map encloses are rebuilt without a measured height: with
    no spectrum their residual is 0 and they would decode at the map's base height, not between
    their neighbours, however small the file. So the spectrum-free candidate is not built for
    them, at a maximum-error target as at an RMSE one; it is when every rebuilt cell is measured."""
    from dftpcc import ratecontrol
    from dftpcc.analysis import Analysis

    rng = np.random.default_rng(5)
    n = 64
    x, y = np.meshgrid(np.arange(n) + 0.5, np.arange(n) + 0.5)
    z = np.cumsum(rng.normal(0, 1, (n, n)), 0) + np.cumsum(rng.normal(0, 1, (n, n)), 1)
    keep = rng.random((n, n)) > 0.01
    pts = np.c_[x[keep], y[keep], z[keep]]
    dem = rasterize(pts, fit_grid(pts, 1.0))
    for mask, expected in (("exact", True), ("footprint", False)):
        params = make_params(resolution=1.0, target_max_error=0.2, mask=mask)
        an = Analysis(dem, params, searching=True, outside_energy=True)
        assert (ratecontrol._spectrum_free(an, params) is not None) == expected, mask
        assert (ratecontrol.predicted_map(an, params, 0.2) is not None) == expected, mask


def _hills_with_walls(n=96, seed=3, walls=40):
    """Gentle hills (a few long waves) with ``walls`` single cells standing 3 m proud and a tenth
    of the cells empty: a low-pass meets a fine RMSE only at a fine step, where the walls cost
    every frequency."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(n) + 0.5, np.arange(n) + 0.5)
    z = 2.0 * np.sin(x / 17.0) + 1.5 * np.cos(y / 23.0) + 0.01 * rng.normal(size=x.shape)
    cells = rng.choice(n * n, walls, replace=False)
    z.ravel()[cells] += 3.0
    keep = rng.random(n * n) > 0.1
    keep[cells] = True
    return np.c_[x.ravel(), y.ravel(), z.ravel()][keep]


@pytest.mark.parametrize("mask", ["exact", "footprint"])
def test_a_few_far_off_cells_are_corrected_rather_than_low_passed(monkeypatch, mask):
    """At an RMSE target a coarse low-pass keeps the hills within it and a sparse residual layer
    brings back the walls it leaves far off: a file with a spectrum (cutoff below the highest tried)
    and a layer at a bound well past the target, smaller than the low-pass alone, whose decoded map
    meets the target with every cell within the bound it states, as the document's reader decodes
    it. With the footprint mask too (the low-pass rebuilds the cells without a height)."""
    from dftpcc import ratecontrol

    from . import spec_decoder

    pts = _hills_with_walls()
    dem = rasterize(pts, fit_grid(pts, 1.0))
    target = 0.1
    data = dftpcc.compress(pts, resolution=1.0, target_rmse=target, mask=mask)
    with dftpcc.open(data) as cmap:
        assert cmap.params.cutoff < max(ratecontrol.CUTOFF_CANDIDATES)
        bound = cmap.params.target_max_error
        assert cmap.params.target_rmse == 0.0 and bound > 2 * target
        assert cmap.info().get("residual_layout") in ("sparse", "predicted", "chunked")
        err = (cmap.read_dem().heights - dem.heights)[dem.mask]
    assert np.abs(err).max() <= bound and np.sqrt(np.mean(err ** 2)) <= target
    np.testing.assert_allclose(spec_decoder.decode(data), dftpcc.decompress(data), rtol=0, atol=1e-9)
    _no_residual_for_rmse(monkeypatch)
    low_passed = dftpcc.compress(pts, resolution=1.0, target_rmse=target, mask=mask)
    assert len(data) < 0.9 * len(low_passed), (len(data), len(low_passed))


def test_a_tiled_map_at_an_rmse_target_gets_no_residual_layer():
    """A tiled map's tiles would code their residuals against bases the map's trial only
    approximates, so its RMSE target is met by the low-pass alone, and met."""
    pts = _hills_with_walls(n=128)
    data = dftpcc.compress(pts, resolution=1.0, target_rmse=0.1, tile_size=64)
    with dftpcc.open(data) as cmap:
        assert cmap.params.target_rmse == 0.1 and cmap.params.target_max_error == 0.0
        assert cmap.header.stats["dem_rmse_m"] <= 0.1


class _FloorAnalysis:
    """A stand-in Analysis whose error is a cutoff's floor plus the quantizer's share, in quadrature,
    each with its own slope on the occupied cells and in the whole grid's proxy: as a tiled map
    coded by its base layer alone (rolling_strip_raleigh in 256-cell tiles), where the floor is
    most of an RMSE target and the occupied cells gain error faster than the proxy."""

    params = Params()

    def __init__(self, floor: float, occupied: float, whole: float):
        self.floor, self.occupied, self.whole = floor, occupied, whole
        self.trials: list[float] = []

    def tiny_step(self) -> float:
        return 1e-7

    def proxy_rmse(self, cutoff: float, step: float) -> float:
        return math.hypot(self.floor, self.whole * step)

    def trial(self, cutoff: float, step: float):
        from types import SimpleNamespace

        self.trials.append(step)
        return SimpleNamespace(step=step, rmse=math.hypot(self.floor, self.occupied * step))


def test_an_rmse_search_corrects_the_quantizers_share_and_lands_inside_the_target():
    """Where the cutoff's floor is most of the target, correcting the whole proxy by the measured
    ratio closes in on the target from above, a hair over each round, and the search kept the
    unquantized step (62 kB for a 5.3 kB file on a real map); correcting the quantizer's share
    then lands inside the target in one more round."""
    target = 14.102
    an = _FloorAnalysis(12.777, 0.0197, 0.0123)
    trial = ratecontrol.step_for_rmse(an, 0.5, target)
    assert ratecontrol.CLOSE_ENOUGH * target < trial.rmse <= target
    # the unquantized trial, the ratio's rounds, the share's first round and its correction
    assert len(an.trials) <= 1 + ratecontrol.CALIBRATION_ROUNDS + 2
    # With no floor the ratio's rounds land, and the share's are not run.
    an = _FloorAnalysis(0.0, 0.0197, 0.0123)
    trial = ratecontrol.step_for_rmse(an, 0.0, target)
    assert ratecontrol.CLOSE_ENOUGH * target < trial.rmse <= target and len(an.trials) <= 3
