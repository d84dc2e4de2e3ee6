"""Gridding a cloud into a DEM: geometry, aggregation, fill, resolution."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dftpcc.dem import Grid
from dftpcc.errors import InvalidInputError, MultiHeightWarning
from dftpcc.fill import fill_empty, fit_plane, plane_values
from dftpcc.grid import HEIGHT_QUANTUM_M, CellSums, auto_resolution, fit_grid, lattice_cells, rasterize
from dftpcc.limits import MAX_CELLS


def test_grid_is_minimum_bounding_rectangle_at_centroid_height():
    pts = np.array([[10.0, 20.0, 1.0], [13.9, 21.0, 3.0], [11.0, 25.9, 5.0]])
    g = fit_grid(pts, 1.0)
    # 4 x 6 whole cells around a 3.9 x 5.9 m extent, the 0.1 m overhang split evenly
    assert (g.x0, g.y0) == pytest.approx((9.95, 19.95))
    assert (g.rows, g.cols) == (6, 4)
    assert g.z0 == pytest.approx(3.0)


def test_every_point_falls_in_its_grid():
    rng = np.random.default_rng(1)
    pts = rng.uniform([6e5, 6.6e6, 0], [6e5 + 300, 6.6e6 + 200, 10], size=(5000, 3))
    for frame in ("axis", "oriented"):
        g = fit_grid(pts, 0.7, frame=frame)
        assert (g.flat_index(pts) >= 0).all()


@pytest.mark.parametrize("aggregate,expected", [("mean", 2.0), ("median", 1.5), ("min", 1.0), ("max", 3.5)])
def test_aggregates(aggregate, expected):
    pts = np.array([[0.1, 0.1, 1.0], [0.2, 0.2, 1.5], [0.3, 0.3, 3.5], [5.0, 5.0, 2.0]])
    with pytest.warns(MultiHeightWarning, match="flattened"):  # 2.5 m apart in a 1 m cell, on purpose
        dem = rasterize(pts, fit_grid(pts, 1.0), aggregate=aggregate)
    assert dem.heights[0, 0] + dem.grid.z0 == pytest.approx(expected)
    assert dem.mask.sum() == 2


def test_gridding_rmse_is_the_spread_within_cells():
    pts = np.array([[0.5, 0.5, 1.0], [0.5, 0.5, 3.0], [1.5, 0.5, 7.0]])
    dem = rasterize(pts, fit_grid(pts, 1.0))
    assert dem.gridding_rmse == pytest.approx(math.sqrt((1 + 1 + 0) / 3))


def test_oriented_frame_shrinks_a_diagonal_strip():
    rng = np.random.default_rng(2)
    t = rng.uniform(0, 1000, 20000)
    w = rng.uniform(-20, 20, 20000)
    pts = np.column_stack([t * 0.6 - w * 0.8, t * 0.8 + w * 0.6, rng.normal(0, 0.3, 20000)])  # gentle: the frame is the point
    axis, rotated = fit_grid(pts, 2.0), fit_grid(pts, 2.0, frame="oriented")
    assert rotated.size < 0.15 * axis.size
    assert (rotated.flat_index(pts) >= 0).all()
    # Cell centres map back into the strip.
    rows, cols = np.nonzero(rasterize(pts, rotated).mask)
    x, y = rotated.centres(rows, cols)
    assert np.abs(-0.8 * x + 0.6 * y).max() < 20 + 2 * 2.0


def test_fill_keeps_occupied_cells_and_is_smooth():
    yy, xx = np.mgrid[0:64, 0:64]
    truth = 0.05 * xx + 0.02 * yy
    mask = np.hypot(xx, yy) < 50  # a quarter disc
    filled = fill_empty(np.where(mask, truth, 0.0), mask)
    np.testing.assert_array_equal(filled[mask], truth[mask])
    # The fill continues the surface instead of dropping to zero.
    assert np.abs(np.diff(filled, axis=1)).max() < 0.5
    zero = fill_empty(truth, mask, method="zero")
    assert (zero[~mask] == 0).all()


def test_plane_fit_recovers_a_plane():
    yy, xx = np.mgrid[0:20, 0:30]
    from dftpcc.dem import DEM, Grid

    dem = DEM(Grid(0, 0, 0, 1.0, 20, 30), 1.5 + 0.1 * xx - 0.2 * yy, np.ones((20, 30), bool))
    plane = fit_plane(dem)
    np.testing.assert_allclose(plane, (1.5, 0.1, -0.2), atol=1e-12)
    np.testing.assert_allclose(plane_values(plane, (20, 30)), dem.heights, atol=1e-12)


def test_refuses_a_grid_too_large_for_memory():
    pts = np.array([[0.0, 0.0, 0.0], [1e7, 1e7, 1.0]])  # 10,000 km at 0.1 m
    with pytest.raises(InvalidInputError, match="cells.*limit"):
        fit_grid(pts, 0.1)
    assert MAX_CELLS < (1e8 ** 2)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_resolution(bad):
    with pytest.raises(InvalidInputError, match="resolution"):
        fit_grid(np.zeros((3, 3)), bad)


def test_auto_resolution_tracks_density(field_ground):
    res = auto_resolution(field_ground)
    # about 6.7 ground points per square metre on the field: 4 per cell is ~0.77 m cells
    assert 0.6 < res < 1.0


def test_points_on_a_lattice_of_the_cell_size_sit_mid_cell():
    # A DEM sampled at its pixel centres, at UTM-size coordinates: one point per cell.
    yy, xx = np.mgrid[0:300, 0:200]
    pts = np.column_stack([484649.25 + 47.679 * xx.ravel(), 6632629.75 + 47.679 * yy.ravel(),
                           np.zeros(xx.size)])
    g = fit_grid(pts, 47.679)
    assert (g.rows, g.cols) == (300, 200)
    dem = rasterize(pts, g)
    assert dem.mask.all() and dem.counts.max() == 1


def test_an_oriented_grid_breaks_a_tie_of_rectangles_alike_whole_and_in_chunks():
    # Two minimum-area rectangles of this cloud have equal areas but for the last bit, which depends
    # on the centre the hull is taken about (all the points, or a chunk's hull): found by hypothesis
    # (test_properties), where the whole cloud got 2 x 1 cells at one angle and its chunks 1 x 1.
    from dftpcc.grid import CloudSummary

    xy = np.array([[0.3269722766055607, 0.9872768433379255], [0.31871083848551673, 0.7885489358200289],
                   [0.8698965116962161, 0.391084806539194], [0.4378818731227988, 0.37274890308935305],
                   [0.10695359647277436, 0.47896545416271696], [0.24135214508468228, 0.25714524855112975],
                   [0.1847315568344149, 0.1938645489043107], [0.813827670155021, 0.42298418814422634]])
    points = np.c_[xy, np.zeros(len(xy))]
    resolution = 0.7934916356630581
    summary = CloudSummary(hull=True)
    for point in points:
        summary.add(point[None])
    whole = fit_grid(points, resolution, frame="oriented")
    chunked = summary.fit_grid(resolution, frame="oriented")
    assert (whole.rows, whole.cols, whole.angle) == (chunked.rows, chunked.cols, chunked.angle)


def test_cell_sums_do_not_depend_on_the_order_of_the_scans():
    """A growing map's gridder: exact integer sums, so scans added in any order and any split give
    the same cells to the bit; the means agree with rasterize's within the height quantum."""
    rng = np.random.default_rng(7)
    pts = np.column_stack([rng.uniform(0, 8, 5000), rng.uniform(0, 8, 5000), rng.normal(100, 0.1, 5000)])
    origin = (0.0, 0.0, 100.0)
    row, col, quanta = lattice_cells(pts, origin, 0.5)
    flat = row * 16 + col

    def grown(parts):
        cells = CellSums.empty((16, 16))
        for part in parts:
            cells.add(flat[part], quanta[part])
        return cells

    one = grown([np.arange(pts.shape[0])])
    shuffled = grown(np.array_split(rng.permutation(pts.shape[0]), 7))
    for a, b in ((one.sum, shuffled.sum), (one.count, shuffled.count)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(one.heights()[0], shuffled.heights()[0])
    assert math.isclose(one.squared_spread(), shuffled.squared_spread(), rel_tol=1e-12)
    dem = rasterize(pts, Grid(x0=0.0, y0=0.0, z0=100.0, resolution=0.5, rows=16, cols=16))
    mean, occupied = one.heights()
    np.testing.assert_array_equal(occupied, dem.mask)
    assert np.abs(mean - dem.heights)[occupied].max() <= HEIGHT_QUANTUM_M


def test_cell_sums_report_which_cells_moved():
    """What a growing map re-codes: the cells seen, the new ones, and those whose mean changed
    (a point added at a cell's mean moves nothing)."""
    cells = CellSums.empty((4, 4))
    seen, new, moved = cells.add(np.array([1, 1, 5]), np.array([10.0, 20.0, 7.0]))
    assert seen.tolist() == [1, 5] and new.all() and moved.all()
    seen, new, moved = cells.add(np.array([1, 5, 9]), np.array([15.0, 8.0, 1.0]))
    assert seen.tolist() == [1, 5, 9] and new.tolist() == [False, False, True]
    assert moved.tolist() == [False, True, True]  # cell 1's mean stays 15
