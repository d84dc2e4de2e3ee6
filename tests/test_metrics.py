"""Metrics: hand-computed cases, invariants (zero, symmetry, bounds), and the codec's own figures."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import dftpcc
from dftpcc import metrics
from dftpcc.errors import InvalidInputError

from .conftest import data_file

#: Relative precision of the errors a .dftpc header states (5 significant digits).
STATED_PRECISION = 1e-4
#: Floating-point tolerance for distances computed from metre-scale coordinates (metres).
TOL = 1e-9


def test_bits_per_point_by_hand():
    assert metrics.bits_per_point(1000, 8000) == 1.0
    assert metrics.bits_per_point(3, 2) == 12.0
    with pytest.raises(InvalidInputError):
        metrics.bits_per_point(10, 0)


def test_identical_clouds_have_zero_error(small_terrain):
    out = metrics.evaluate(small_terrain, small_terrain)
    for key in ("paper_rmse_m", "paper_rmse_3d_m", "vertical_rmse_m", "vertical_max_m", "vertical_p95_m",
                "d1_rmse_m", "chamfer_m", "hausdorff_m"):
        assert out[key] == pytest.approx(0.0, abs=TOL), key
    assert out["d1_psnr_db"] == math.inf


def test_two_point_clouds_by_hand():
    # Each original point's partner is straight above it: 1 m and 3 m.
    a = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    b = np.array([[0.0, 0.0, 1.0], [10.0, 0.0, 3.0]])
    out = metrics.evaluate(a, b, peak=10.0, compressed_bytes=4)
    assert out["paper_rmse_m"] == pytest.approx(math.sqrt(5.0))
    assert out["d1_rmse_m"] == pytest.approx(math.sqrt(5.0))
    assert out["chamfer_m"] == pytest.approx(2.0 + 2.0)
    assert out["hausdorff_m"] == pytest.approx(3.0)
    # Two rebuilt points make no triangle: the surface is the nearest rebuilt height.
    assert out["vertical_rmse_m"] == pytest.approx(math.sqrt(5.0))
    assert out["vertical_max_m"] == pytest.approx(3.0)
    assert out["vertical_p95_m"] == pytest.approx(1.0 + 0.95 * 2.0)  # linear percentile of {1, 3}
    assert out["d1_psnr_db"] == pytest.approx(10 * math.log10(3 * 100 / 5.0))
    assert out["bits_per_point"] == pytest.approx(8 * 4 / 2)


def test_directions_differ_and_symmetric_d1_takes_the_worse():
    a = np.array([[0.0, 0.0, 0.0]])
    b = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 4.0]])
    d1 = metrics.point_to_point(a, b, peak=10.0)
    assert d1.rmse_forward == pytest.approx(0.0)
    assert d1.rmse_backward == pytest.approx(math.sqrt(8.0))  # distances 0 and 4
    assert d1.rmse == pytest.approx(math.sqrt(8.0))
    assert d1.psnr == pytest.approx(10 * math.log10(300 / 8.0))
    assert metrics.chamfer_distance(a, b) == pytest.approx(0.0 + 2.0)
    assert metrics.hausdorff_distance(a, b) == pytest.approx(4.0)


def _plane(xy: np.ndarray) -> np.ndarray:
    return 0.3 * xy[:, 0] - 0.2 * xy[:, 1] + 5.0


def test_surface_interpolation_is_exact_on_a_plane_and_paper_rmse_pairs_the_own_cell():
    # Rebuilt: centres of 1 m cells on the plane z = x. Original: one point off-centre on it.
    centres = np.array([[0.5, 0.5], [1.5, 0.5], [0.5, 1.5], [1.5, 1.5]])
    rebuilt = np.column_stack([centres, centres[:, 0]])
    original = np.array([[1.2, 0.5, 1.2]])
    assert metrics.vertical_errors(original, rebuilt).max == pytest.approx(0.0, abs=TOL)
    # Its own cell is (1, 1)-(2, 1)'s centre (1.5, 0.5) at z 1.5: 0.3 m below, 0.3 m aside.
    assert metrics.paper_rmse(original, rebuilt) == pytest.approx(0.3)
    assert metrics.paper_rmse(original, rebuilt, include_horizontal=True) == pytest.approx(math.hypot(0.3, 0.3))


def test_a_point_on_a_cell_edge_pairs_with_the_cell_the_gridder_puts_it_in():
    # floor(1.0 / 1.0) = 1: the point on the edge x = 1 belongs to the cell centred at 1.5.
    rebuilt = np.array([[0.5, 0.5, 0.0], [1.5, 0.5, 2.0]])
    original = np.array([[1.0, 0.5, 2.0]])
    assert metrics.paper_rmse(original, rebuilt) == pytest.approx(0.0)


def test_interpolated_error_removes_the_slope_inside_cells():
    rng = np.random.default_rng(0)
    u = np.arange(20) + 0.5
    gx, gy = np.meshgrid(u, u)
    grid_xy = np.column_stack([gx.ravel(), gy.ravel()])
    rebuilt = np.column_stack([grid_xy, _plane(grid_xy)])
    xy = rng.uniform(1.0, 19.0, size=(5000, 2))
    original = np.column_stack([xy, _plane(xy)])
    vert = metrics.vertical_errors(original, rebuilt)
    assert vert.max < 1e-9
    # The own-cell pairing charges the slope times the offset from the centre.
    offset = xy - (np.floor(xy) + 0.5)
    expected = np.sqrt(np.mean((0.3 * offset[:, 0] - 0.2 * offset[:, 1]) ** 2))
    assert metrics.paper_rmse(original, rebuilt) == pytest.approx(expected, rel=1e-9)


clouds = arrays(np.float64, st.tuples(st.integers(1, 40), st.just(3)),
                elements=st.floats(-100, 100, allow_nan=False, width=32))


@settings(max_examples=60, deadline=None)
@given(clouds, clouds)
def test_symmetry_and_bounds(a, b):
    assert metrics.chamfer_distance(a, b) == pytest.approx(metrics.chamfer_distance(b, a))
    assert metrics.hausdorff_distance(a, b) == pytest.approx(metrics.hausdorff_distance(b, a))
    ab = metrics.point_to_point(a, b, peak=1.0)
    ba = metrics.point_to_point(b, a, peak=1.0)
    assert ab.rmse == pytest.approx(ba.rmse)
    assert ab.rmse_forward == pytest.approx(ba.rmse_backward)
    haus = metrics.hausdorff_distance(a, b)
    # A maximum bounds every root mean square and every mean of the same distances.
    assert haus >= ab.rmse - TOL
    assert haus >= metrics.chamfer_distance(a, b) / 2 - TOL
    assert metrics.vertical_errors(a, b).max >= metrics.vertical_errors(a, b).rmse - TOL


#: Points on a quarter-metre lattice, heights within +-5 m: distinct x, y are
#: far apart compared with the tie-break nudge, slopes are bounded.
lattice = st.integers(-400, 400).map(lambda v: v / 4)
lattice_clouds = st.lists(st.tuples(lattice, lattice, st.integers(-20, 20).map(lambda v: v / 4)),
                          min_size=1, max_size=40).map(np.array)


@settings(max_examples=30, deadline=None)
@given(lattice_clouds, st.floats(-5, 5), st.floats(-5, 5), st.floats(-5, 5))
def test_a_pure_vertical_shift_is_measured_exactly(a, dx, dy, dz):
    _, first = np.unique(a[:, :2], axis=0, return_index=True)
    a = a[first]  # one height per x, y, so every point's x, y partner is itself
    shifted = a + [0.0, 0.0, dz]
    assert metrics.paper_rmse(a, shifted) == pytest.approx(abs(dz), abs=1e-9)
    # Interpolating 1e-6 m off a vertex on slopes under 40 m/m costs under 1e-4 m.
    assert metrics.vertical_errors(a, shifted).max == pytest.approx(abs(dz), abs=1e-4)
    # Nearest neighbours can only be closer than the shifted twin.
    moved = a + [dx, dy, dz]
    assert metrics.hausdorff_distance(a, moved) <= math.sqrt(dx * dx + dy * dy + dz * dz) + 1e-6


def test_metrics_do_not_depend_on_where_the_map_is(small_terrain):
    rebuilt = dftpcc.decompress(dftpcc.compress(small_terrain, resolution=0.5, cutoff=0.8))
    near = metrics.evaluate(small_terrain, rebuilt)
    offset = np.array([484_000.0, 6_632_000.0, 100.0])  # Lambert-93-size coordinates
    far = metrics.evaluate(small_terrain + offset, rebuilt + offset)
    for key in near:
        if key not in ("psnr_peak_m", "d1_psnr_db"):
            assert far[key] == pytest.approx(near[key], rel=1e-6, abs=1e-9), key


def test_evaluate_agrees_with_each_metric(small_terrain):
    rebuilt = dftpcc.decompress(dftpcc.compress(small_terrain, resolution=0.5, cutoff=0.9, profile="paper"))
    out = metrics.evaluate(small_terrain, rebuilt)
    d1 = metrics.point_to_point(small_terrain, rebuilt)
    vert = metrics.vertical_errors(small_terrain, rebuilt)
    assert out["d1_rmse_m"] == pytest.approx(d1.rmse)
    assert out["d1_psnr_db"] == pytest.approx(d1.psnr)
    assert out["chamfer_m"] == pytest.approx(metrics.chamfer_distance(small_terrain, rebuilt))
    assert out["hausdorff_m"] == pytest.approx(metrics.hausdorff_distance(small_terrain, rebuilt))
    assert (out["vertical_rmse_m"], out["vertical_max_m"], out["vertical_p95_m"]) == pytest.approx(
        (vert.rmse, vert.max, vert.p95))
    assert out["paper_rmse_m"] == pytest.approx(metrics.paper_rmse(small_terrain, rebuilt))
    assert out["points_rebuilt"] == rebuilt.shape[0]


@pytest.mark.parametrize("profile", ["paper", "compact"])
def test_paper_rmse_matches_what_the_codec_reports_on_real_terrain(profile):
    # The encoder states each point's error against its own cell's rebuilt height;
    # our pairing must find that very cell for every point, or the two would differ.
    points = dftpcc.read(data_file("pointclouds/mountain_arid_alirt.las"), classes=[2]).points
    data = dftpcc.compress(points, resolution=2.0, cutoff=0.9, profile=profile)
    stated = dftpcc.open(data).header.stats["vertical_rmse_m"]
    ours = metrics.paper_rmse(points, dftpcc.decompress(data))
    # The file states its errors to STATED_PRECISION, rounded up.
    assert ours <= stated * (1 + 1e-12)
    assert ours == pytest.approx(stated, rel=STATED_PRECISION)


@pytest.mark.parametrize("bad", [np.zeros((0, 3)), np.zeros((4, 2)), np.array([[0.0, np.nan, 1.0]])])
def test_bad_clouds_are_refused(bad):
    good = np.zeros((3, 3))
    with pytest.raises(InvalidInputError):
        metrics.evaluate(bad, good)
    with pytest.raises(InvalidInputError):
        metrics.chamfer_distance(good, bad)
