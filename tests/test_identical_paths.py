"""The faster stage code of issue 16 against the plain formulas it replaced, bit for bit.

The codec promises the same bytes for the same input (tests/test_digests.py pins them
on the recording machine). The speed-ups reorganise work (blocks of points, views
instead of sorts, tables instead of per-value arithmetic, a corner instead of a
zero-padded array) but must not change one bit of any result, signed zeros included.
Each test runs the straightforward version, kept here as the reference, next to the
library's, on each kernel backend (numpy, and compiled where numba is installed), on inputs built to hit the edges: block boundaries, odd grid sizes, one-cell
wide pyramid levels, stripes of one line, points outside the grid, zero heights.
"""

from __future__ import annotations

import math

import numpy as np
import zstandard
import pytest
import constriction

from dftpcc import coding, geometric, kernels, occupancy, spectrum
from dftpcc.dem import DEM, Grid
from dftpcc.fill import fill_empty, fit_plane
from dftpcc.grid import BLOCK_POINTS, _cells_of, _xy_extremes, fit_grid, rasterize
from dftpcc.rebuild import dem_to_points


@pytest.fixture(autouse=True, params=[b.value for b in kernels.Backend.detect_available()])
def backend(request):
    """Each test on every backend this machine has: the stages' numpy and compiled kernels alike
    against the plain formulas."""
    with kernels.use(request.param):
        yield


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def cloud(rng: np.random.Generator, n: int) -> np.ndarray:
    """A sloping, rough cloud at UTM-size coordinates, with a few high points (vegetation)."""
    xy = rng.uniform([5e5, 6.6e6], [5e5 + 90, 6.6e6 + 60], size=(n, 2))
    z = 100 + 0.1 * (xy[:, 0] - 5e5) + rng.normal(0, 0.2, n)
    z[rng.random(n) < 0.2] += rng.uniform(1, 20)
    return np.column_stack([xy, z])


# --- grid ----------------------------------------------------------------------------

@pytest.mark.parametrize("n", [1, BLOCK_POINTS - 1, BLOCK_POINTS, 2 * BLOCK_POINTS + 7])
def test_blocked_cells_and_extremes_match_the_whole_cloud(n):
    rng = np.random.default_rng(n)
    pts = cloud(rng, n)
    assert _xy_extremes(pts) == tuple(float(f(pts[:, k])) for k in (0, 1) for f in (np.min, np.max))
    grid = fit_grid(pts, 0.7)
    idx, z = _cells_of(pts, grid)
    assert same_bits(idx, grid.flat_index(pts)) and same_bits(z, pts[:, 2] - grid.z0)


def test_points_outside_the_grid_take_the_general_path():
    rng = np.random.default_rng(2)
    pts = cloud(rng, 3 * BLOCK_POINTS)
    grid = fit_grid(pts[: BLOCK_POINTS], 0.5)  # the rest mostly outside
    idx, z = _cells_of(pts, grid)
    full = grid.flat_index(pts)
    assert same_bits(idx, full[full >= 0]) and same_bits(z, pts[full >= 0, 2] - grid.z0)


def test_spread_matches_the_one_pass_formulas():
    rng = np.random.default_rng(3)
    pts = cloud(rng, 3 * BLOCK_POINTS + 11)
    grid = fit_grid(pts, 0.5)
    with pytest.warns(Warning):
        dem = rasterize(pts, grid)
    idx = grid.flat_index(pts)
    z = pts[:, 2] - grid.z0
    # The gridding before blocks: one gather, one difference, whole-array sums.
    dz = z - dem.heights.ravel()[idx]
    sq = dz * dz
    tol = dem.spread.tolerance_m
    far = sq > tol * tol
    assert dem.gridding_rmse == math.sqrt(float(sq.sum()) / sq.size)
    assert dem.spread.max_distance_m == math.sqrt(float(sq.max()))
    assert dem.spread.unrepresented_points == int(np.count_nonzero(far))
    # The far squares summed as one compacted array, in the points' order (numpy's pairwise sum).
    assert dem.spread.unrepresented_rmse_m == math.sqrt(float(sq[far].sum()) / int(far.sum()))
    assert dem.spread.unrepresented_cells == np.unique(idx[far]).size


# --- fill ------------------------------------------------------------------------------

def _ref_upsample2(a: np.ndarray, axis: int) -> np.ndarray:
    a = np.moveaxis(a, axis, 0)
    before = np.concatenate([a[:1], a[:-1]])
    after = np.concatenate([a[1:], a[-1:]])
    out = np.empty((2 * a.shape[0],) + a.shape[1:])
    out[0::2] = 0.75 * a + 0.25 * before
    out[1::2] = 0.75 * a + 0.25 * after
    return np.moveaxis(out, 0, axis)


def _ref_push_pull(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    if weights.min() >= 1.0:
        return values
    if min(values.shape) <= 1 and values.size <= 2:
        total = weights.sum()
        mean = (values * weights).sum() / total if total else 0.0
        return np.where(weights > 0, values, mean)
    r, c = values.shape
    pr, pc = r % 2, c % 2
    v = np.pad(values * weights, ((0, pr), (0, pc)))
    w = np.pad(weights, ((0, pr), (0, pc)))
    wsum = w.reshape(v.shape[0] // 2, 2, v.shape[1] // 2, 2).sum(axis=(1, 3))
    vsum = v.reshape(v.shape[0] // 2, 2, v.shape[1] // 2, 2).sum(axis=(1, 3))
    coarse_v = np.divide(vsum, wsum, out=np.zeros_like(vsum), where=wsum > 0)
    coarse = _ref_push_pull(coarse_v, np.minimum(wsum, 1.0))
    up = _ref_upsample2(_ref_upsample2(coarse, 0), 1)[:r, :c]
    wc = np.minimum(weights, 1.0)
    return wc * values + (1.0 - wc) * up


@pytest.mark.parametrize("shape", [(1, 1), (2, 3), (5, 2), (7, 3), (64, 2), (131, 97), (97, 131), (300, 5),
                                   (256, 256), (301, 403)])
def test_push_pull_matches_the_padded_reshape_version(shape):
    rng = np.random.default_rng(sum(shape))
    for occupied in (0.02, 0.5, 0.97):
        heights = rng.normal(0, 10, shape)
        heights[rng.random(shape) < 0.1] = 0.0  # zeros, whose sign the blend decides
        heights[rng.random(shape) < 0.05] = -0.0
        mask = rng.random(shape) < occupied
        mask.flat[0] = True
        expected = _ref_push_pull(np.where(mask, heights, 0.0), mask.astype(np.float64))
        assert same_bits(fill_empty(heights, mask), expected)


def test_plane_matches_the_index_version():
    rng = np.random.default_rng(4)
    mask = rng.random((203, 157)) < 0.6
    heights = rng.normal(0, 3, mask.shape) + 0.1 * np.arange(157)
    dem = DEM(grid=Grid(0.0, 0.0, 0.0, 1.0, *mask.shape), heights=heights, mask=mask)
    rows, cols = np.nonzero(mask)
    x, y, z = cols.astype(float), rows.astype(float), heights[rows, cols]
    mx, my, mz = x.mean(), y.mean(), z.mean()
    x -= mx
    y -= my
    z = z - mz
    # The sums are numpy's pairwise ones (dftpcc.sums.dot), not BLAS's: the same on every thread count.
    xx, xy, yy, xz, yz = (float(np.sum(a * b)) for a, b in ((x, x), (x, y), (y, y), (x, z), (y, z)))
    b, c = np.linalg.solve(np.array([[xx, xy], [xy, yy]]), np.array([xz, yz]))
    assert fit_plane(dem) == (float(mz - b * mx - c * my), float(b), float(c))


# --- spectrum, rebuild ---------------------------------------------------------------------

@pytest.mark.parametrize("shape", [(157, 64), (64, 157), (301, 97)])
def test_corner_inverse_in_the_full_order_matches_the_zero_padded_array(shape):
    lay = spectrum.layout("dct", "quantized", shape)
    order, _, _ = spectrum.kept_order(lay, 0.8)
    values = np.random.default_rng(5).normal(0, 1, order.size)
    full = np.zeros(lay.coef_shape)
    full.ravel()[order] = values
    corner_shape, where = spectrum.corner(lay, order)
    corner = np.zeros(corner_shape)
    corner.ravel()[where] = values
    assert same_bits(spectrum.inverse(corner, lay, first_axis=1), spectrum.inverse(full, lay))


@pytest.mark.parametrize("angle", [0.0, 0.3])
def test_rebuilt_points_match_the_flat_index_version(angle):
    rng = np.random.default_rng(6)
    grid = Grid(x0=5e5, y0=6.6e6, z0=101.5, resolution=0.5, rows=53, cols=71, angle=angle)
    mask = rng.random(grid.shape) < 0.4
    dem = DEM(grid=grid, heights=rng.normal(0, 2, grid.shape), mask=mask)
    flat = np.flatnonzero(mask)
    rows, cols = np.divmod(flat, grid.cols)
    x, y = grid.centres(rows, cols)
    expected = np.column_stack([x, y, dem.heights.ravel()[flat] + grid.z0])
    assert same_bits(dem_to_points(dem), expected)


# --- coding --------------------------------------------------------------------------

def test_size_estimate_and_groups_match_the_per_value_formulas():
    rng = np.random.default_rng(7)
    n = 20000
    q = np.round(rng.laplace(0, 1, n) * rng.uniform(0.01, 40, n)).astype(np.int64)
    radius, angle = rng.uniform(0, 300, n), rng.uniform(0, 1, n)
    for layout in range(len(coding.BAND_LAYOUTS)):
        b = coding._Bands.of(q, radius, angle, layout)
        coded = b.per_value > 0
        scale = geometric.scale_of(b.per_value[coded])
        a = np.abs(q[coded]).astype(np.float64)
        t = (np.sqrt(1 + scale * scale) - 1) / scale
        log_p = np.log2((1 - t) / (1 + t)) + a * np.log2(np.maximum(t, 1e-300))
        expected = 8.0 * len(coding._side_info(b.codes)) - float(np.maximum(log_p, -geometric.TABLE_BITS).sum())
        assert coding._estimated_bits(q, b) == expected
        assert b.table_work(7) == int(np.count_nonzero(np.unique(b.per_value))) * 15
        order = np.argsort(b.per_value, kind="stable")
        sorted_codes = b.per_value[order]
        present = np.unique(sorted_codes)
        bounds = np.searchsorted(sorted_codes, present).tolist() + [n]
        expected_groups = [(int(c), order[bounds[k]:bounds[k + 1]]) for k, c in enumerate(present) if c > 0]
        groups = geometric.code_groups(b.per_value)
        assert [c for c, _ in groups] == [c for c, _ in expected_groups]
        assert all(same_bits(g, e) for (_, g), (_, e) in zip(groups, expected_groups))


# --- occupancy -------------------------------------------------------------------------

def _ref_contexts(lines: np.ndarray, stripe: int) -> np.ndarray:
    codes = occupancy._codes(lines)
    t = np.arange(lines.shape[0]) % stripe
    ctx = np.zeros(lines.shape, dtype=np.uint8)
    ctx[1:] = np.where((t[1:] >= 1)[:, None], codes[:-1], 0)
    older = np.zeros_like(ctx)
    older[2:] = np.where((t[2:] >= 2)[:, None], occupancy._older(codes[:-2]), 0)
    older[1:] |= np.where((t[1:] == 1)[:, None], occupancy._older(codes[:-1]), 0)
    return ctx | older


def _ref_encode_context(lines: np.ndarray, stripe: int) -> bytes:
    """The context coder as first written: one global stable sort into decoding order."""
    n_lines = lines.shape[0]
    contexts = occupancy.CONTEXTS
    t = np.arange(n_lines) % stripe
    coded = (t > 0) | (np.arange(n_lines) == 0)
    seeds = lines[~coded]
    ctx = _ref_contexts(lines, stripe)[coded]
    bits = lines[coded]
    step = t[coded][:, None]
    flat = (ctx.astype(np.intp) + contexts * step).ravel()
    ones = np.bincount(flat, weights=bits.ravel(), minlength=stripe * contexts).reshape(stripe, contexts)
    total = np.bincount(flat, minlength=stripe * contexts).reshape(stripe, contexts).astype(np.float64)
    ones = np.vstack([np.zeros(contexts), np.cumsum(ones, axis=0)[:-1]])
    total = np.vstack([np.zeros(contexts), np.cumsum(total, axis=0)[:-1]])
    prob = (ones + occupancy.PRIOR_ONES) / (total + occupancy.PRIOR_TOTAL)
    group = np.where(ctx == occupancy.OUTSIDE, 0, np.where(ctx == occupancy.INSIDE, 1, 2))
    key = (group + 3 * step).astype(np.uint16).ravel()
    order = np.argsort(key, kind="stable")
    key, bits, ctx = key[order], bits.ravel()[order].astype(np.int32), ctx.ravel()[order]
    starts = np.concatenate(([0], np.flatnonzero(np.diff(key)) + 1, [key.size]))
    coder = constriction.stream.stack.AnsCoder()
    model = occupancy._bernoulli()
    for start, stop in zip(starts[-2::-1], starts[:0:-1]):
        s, g = divmod(int(key[start]), 3)
        if g == 2:
            coder.encode_reverse(bits[start:stop], model, prob[s, ctx[start:stop]])
        else:
            p = prob[s, occupancy.OUTSIDE if g == 0 else occupancy.INSIDE]
            coder.encode_reverse(bits[start:stop], occupancy._bernoulli(p))
    seed_frame = occupancy._encode_seeds(seeds)
    return (occupancy._STRIPES.pack(stripe, len(seed_frame)) + seed_frame
            + coder.get_compressed().astype("<u4").tobytes())


def _ref_encode_mask(mask: np.ndarray, stripe: int) -> bytes:
    transposed = mask.shape[0] > mask.shape[1]
    lines = (mask.T if transposed else mask).astype(np.uint8)
    candidates = [
        occupancy._HEAD.pack(occupancy.KIND_CONTEXT, transposed) + _ref_encode_context(lines, min(stripe, lines.shape[0])),
        occupancy._HEAD.pack(occupancy.KIND_ZSTD, 0)
        + zstandard.ZstdCompressor(level=occupancy._BITMAP_LEVEL).compress(np.packbits(mask.ravel()).tobytes()),
    ]
    return min(candidates, key=len)


def _footprint_mask(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """A disc-like footprint with holes and speckle, as real maps have."""
    r, c = np.indices(shape)
    disc = (r - shape[0] * 0.3) ** 2 + (c - shape[1] * 0.4) ** 2 < (0.6 * max(shape)) ** 2
    return disc & (rng.random(shape) < 0.97) | (rng.random(shape) < 0.01)


@pytest.mark.parametrize("shape,stripe", [((1, 1), 64), ((3, 40), 1), ((40, 3), 2), ((130, 77), 64),
                                          ((77, 130), 5), ((200, 150), 64), ((64, 64), 64), ((150, 300), 7)])
def test_mask_bytes_match_the_sorting_coder(shape, stripe):
    rng = np.random.default_rng(shape[0] * 1000 + shape[1])
    lines = (rng.random(shape) < 0.5).astype(np.uint8)
    assert same_bits(occupancy._contexts(lines, stripe), _ref_contexts(lines, stripe))
    for mask in (_footprint_mask(rng, shape), np.ones(shape, bool), np.zeros(shape, bool), lines.astype(bool)):
        assert occupancy.encode_mask(mask, stripe=stripe) == _ref_encode_mask(mask, stripe)
