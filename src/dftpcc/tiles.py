"""Tiled maps: the base layer of the map's lowest frequencies, and tiles coded on top of it.

A map larger than one tile is coded in two layers (docs/format.md, *Tiles*):
the base layer holds the whole grid's DCT coefficients up to one cycle per
tile (or the cutoff's whole circle, where that base is small: see
:func:`covering_reach`), and each tile codes with its own DCT what the plane
and the base layer leave on its cells (or nothing, where a covering base layer
alone makes the smaller file at a target). Both share one cutoff and one quantizer step.
:class:`TiledAnalysis` gives rate control (:mod:`dftpcc.ratecontrol`) the same
view of a tiled map that :class:`~dftpcc.analysis.Analysis` gives of a whole
one, so every target works unchanged.
"""

from __future__ import annotations

import copy
import functools
import math
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np

from .sums import dot
from . import coding, occupancy, quantizer, spectrum
from .analysis import Analysis, Trial
from .dem import DEM, Grid, TileGrid
from .fill import fill_empty, fit_plane, plane_values
from .params import Params
from .residual import encode_residual, residual

__all__ = ["BASE_CYCLES_PER_TILE", "MAX_BASE_CYCLES", "MAP_MASK_CELLS", "MAX_COVERING_COEFS", "base_limit", "covering_cycles", "covering_reach", "covering_cutoff", "TILE_OVERLAP", "WIDE_OVERLAP_CUTOFF", "tile_overlap", "coded_window", "TileJob", "TileCode", "code_tile", "base_order", "base_basis", "base_heights", "base_coefficients",
           "tile_grid_of", "tile_coef_code", "tile_mask_code", "TiledAnalysis", "TiledTrial"]

#: The base layer holds the map's frequencies up to this many cycles per tile
#: along the longer side: what a tile alone would pay for in every tile. (The
#: encoder also tries the reach that holds the cutoff's whole circle, see
#: covering_reach, and keeps the smaller file.)
BASE_CYCLES_PER_TILE = 1
#: The most base coefficients a base layer holding the cutoff's whole circle may have: every
#: decode of a region reads and evaluates the whole base layer (a few tens of kB and about 20 ms
#: on a 512-cell tile at this size), so the writer tries it on small maps and coarse rates only.
MAX_COVERING_COEFS = 1 << 17
#: The largest base reach TIDX can state (a u8), cycles per tile.
MAX_BASE_CYCLES = 255
#: A tiled map of at most this many cells may keep its mask and residual layer whole at tile 0 (the
#: map mask and map residual, format.md, *Tile sections*): every region's decode decodes them, a
#: few tens of milliseconds at this size.
MAP_MASK_CELLS = 1 << 20
#: Cells of the neighbouring tiles a tile's transform also spans on each side, at the
#: cutoffs that ring least (see tile_overlap), and the unit a wider overlap grows by.
TILE_OVERLAP = 8
#: From this cutoff up, tiles overlap by twice :data:`TILE_OVERLAP` (see tile_overlap): the
#: cutoff whose circle, of radius (1 - f_c) hypot(H/2, W/2), starts to cut the frequencies along
#: the axes (below it only the diagonal corner of the spectrum goes).
WIDE_OVERLAP_CUTOFF = 1 - 1 / math.sqrt(2)
#: The slack of spectrum's circle, so a coefficient exactly on it is kept everywhere.
_SLACK = 1 + 1e-12


def base_limit(shape: tuple[int, int], tile: int, cutoff: float, cycles: int, *, legacy: bool = False) -> float:
    """Largest radius of the base layer: ``cycles`` per tile along the longer side, within the cutoff's circle
    (of the integer order, the radius of :func:`base_key_limit`; ``legacy``: a 1.1 file's float limit)."""
    if legacy:
        return min(max(shape) / tile * cycles, spectrum.radius_limit(shape, cutoff)) * _SLACK
    return spectrum.key_radius(base_key_limit(shape, tile, cutoff, cycles), dct=True)


def base_key_limit(shape: tuple[int, int], tile: int, cutoff: float, cycles: int) -> int:
    """The largest key ``i² + j²`` of the base layer (docs/format.md, *BASE*): inside the cutoff's
    circle and ``q T² <= 4 S² (cycles max(rows, cols))²``, in exact arithmetic."""
    rows, cols = shape
    reach = Fraction(spectrum.SLACK) ** 2 * 4 * (cycles * max(shape)) ** 2 / (tile * tile)
    return min(spectrum.key_limit(shape, cutoff, dct=True), math.floor(reach), rows * rows + cols * cols)


def covering_cycles(shape: tuple[int, int], tile: int, cutoff: float) -> int:
    """The fewest cycles per tile (along the longer side) whose base layer holds the cutoff's whole
    circle: beyond it, :func:`base_limit` is the cutoff's radius."""
    return max(1, math.ceil(spectrum.radius_limit(shape, cutoff) * tile / max(shape)))


def covering_reach(shape: tuple[int, int], tile: int, cutoff: float) -> int | None:
    """The base reach (cycles per tile) that holds the cutoff's whole circle, if that base layer has at
    most :data:`MAX_COVERING_COEFS` coefficients and TIDX can state it; else None."""
    cycles = covering_cycles(shape, tile, cutoff)
    radius = spectrum.radius_limit(shape, cutoff)
    # The circle's quarter in (i, j) holds about pi r^2 pairs: only count them exactly when near the cap.
    if cycles > MAX_BASE_CYCLES or math.pi * radius * radius > 2 * MAX_COVERING_COEFS:
        return None
    return cycles if base_order(shape, tile, cutoff, cycles)[0].size <= MAX_COVERING_COEFS else None


def covering_cutoff(shape: tuple[int, int], tile: int) -> float | None:
    """The lowest cutoff, in hundredths, whose whole circle :func:`covering_reach` accepts (None if
    none below 1 does): where rate control chooses the cutoff, the covering base layer is tried with
    the reach of the larger of this and the cutoff chosen with one cycle per tile."""
    low, high = -1, 100  # in hundredths: `high` is accepted (or 100: none is), `low` is not
    while high - low > 1:  # the base layer shrinks as the cutoff rises
        mid = (low + high) // 2
        if covering_reach(shape, tile, mid / 100) is None:
            low = mid
        else:
            high = mid
    return high / 100 if high < 100 else None


def base_order(shape: tuple[int, int], tile: int, cutoff: float,
               cycles: int = BASE_CYCLES_PER_TILE, *, legacy: bool = False
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The base layer's coefficients: row and column frequency indices, radii and angles, in stream order.

    Every (i, j) with ``sqrt(i² + j²) / 2`` at most ``cycles`` cycles per tile and inside the
    cutoff's circle (decided on the integer key ``i² + j²``, :func:`base_key_limit`), sorted by
    that key, ties in row-major order of (i, j); none when ``cycles`` is 0 (a map whose tiles
    depend on nothing else, as a growing map needs). ``legacy``: a 1.1 file's order, by the
    float radius ``hypot(i/2, j/2)``.
    """
    rows, cols = shape
    if cycles == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, np.zeros(0), np.zeros(0)
    limit = base_limit(shape, tile, cutoff, cycles, legacy=legacy)
    ki, kj = min(rows, int(2 * limit) + 1), min(cols, int(2 * limit) + 1)
    i, j = np.divmod(np.arange(ki * kj), kj)
    if legacy:
        radius = np.hypot(i / 2.0, j / 2.0)
        inside = np.flatnonzero(radius <= limit)
        order = inside[np.argsort(radius[inside], kind="stable")]
    else:
        key = i * i + j * j
        inside = np.flatnonzero(key <= base_key_limit(shape, tile, cutoff, cycles))
        order = inside[np.argsort(key[inside], kind="stable")]  # ties in row-major order of (i, j)
        radius = np.sqrt(key.astype(float)) * 0.5
    i, j = i[order], j[order]
    angle = np.clip(np.arctan2(i.astype(float), j.astype(float)) / (math.pi / 2), 0.0, 1.0)
    return i, j, radius[order], angle


def base_basis(n: int, k: int, start: int, stop: int) -> np.ndarray:
    """The first ``k`` orthonormal DCT-II basis vectors of length ``n`` at samples ``[start, stop)``: shape (stop - start, k)."""
    samples = np.arange(start, stop, dtype=float)[:, None]
    freq = np.arange(k, dtype=float)[None, :]
    out = math.sqrt(2.0 / n) * np.cos(math.pi * freq * (2.0 * samples + 1.0) / (2.0 * n))
    out[:, 0] = 1.0 / math.sqrt(n)
    return out


def base_heights(values: np.ndarray, i: np.ndarray, j: np.ndarray, shape: tuple[int, int],
                 rows: tuple[int, int], cols: tuple[int, int], *, exact: bool = True) -> np.ndarray:
    """The base layer (metres) on the cells ``[rows[0], rows[1]) x [cols[0], cols[1])`` of a ``shape`` grid.

    ``exact`` (the encoders): each cell's value has the same bits whatever
    window it is computed in (a whole map, a band, a block of tiles), so the
    in-memory, band and cluster coders quantize the same residuals and write
    the same bytes: numpy's own sum-of-products loops (``einsum`` without
    ``optimize``) add a cell's terms in one order, where BLAS's sums depend on
    the matrices' shapes and its threads (a band's cells came out otherwise
    under ``OPENBLAS_NUM_THREADS=1``). ``exact=False`` (the decoder): BLAS,
    about 1.5 ms faster on a 512-cell tile (a quarter of its read), with
    heights that may differ in their last bit between windows. (Rate control's trials, which
    evaluate the whole grid, use its inverse DCT instead: :meth:`TiledAnalysis.trial`.)
    """
    h, w = rows[1] - rows[0], cols[1] - cols[0]
    if values.size == 0:
        return np.zeros((h, w))
    ki, kj = int(i.max()) + 1, int(j.max()) + 1
    g = np.zeros((ki, kj))
    g[i, j] = values
    basis_rows, basis_cols = base_basis(shape[0], ki, *rows), base_basis(shape[1], kj, *cols)
    if not exact:
        return basis_rows @ g @ basis_cols.T
    along = np.einsum("rk,kl->rl", basis_rows, g, optimize=False)
    return np.einsum("rl,cl->rc", along, basis_cols, optimize=False)


def base_coefficients(filled: np.ndarray, i: np.ndarray, j: np.ndarray, *, row_start: int = 0,
                      rows: int | None = None, block: int = 1, cols: int | None = None) -> np.ndarray:
    """The base coefficients (i, j) of a filled map, or a band of its rows' share of them.

    The DCT is separable, so a band ``filled`` of the map's rows starting at
    ``row_start`` contributes ``basis_rows.T @ band @ basis_cols``; the bands
    of a map add up to its coefficients (a map larger than memory is read band
    by band). ``rows``: the map's row count (default: the band is the map).

    ``block`` > 1: ``filled`` holds the means of ``block`` x ``block`` cells of a whole map of
    ``rows`` x ``cols`` cells (the last blocks cut by its edges), a decimated copy of a map too
    large to hold: each mean stands for its cells, so each basis vector is summed over them.
    """
    if i.size == 0:
        return np.zeros(0)
    ki, kj = int(i.max()) + 1, int(j.max()) + 1
    if block > 1:
        if rows is None or cols is None or row_start:
            raise ValueError("a decimated map's coefficients need the whole map's rows and cols")
        br = np.add.reduceat(base_basis(rows, ki, 0, rows), np.arange(0, rows, block), axis=0)
        bc = np.add.reduceat(base_basis(cols, kj, 0, cols), np.arange(0, cols, block), axis=0)
        return (br.T @ filled @ bc)[i, j]
    n_rows = filled.shape[0] if rows is None else rows
    br = base_basis(n_rows, ki, row_start, row_start + filled.shape[0])
    bc = base_basis(filled.shape[1], kj, 0, filled.shape[1])
    return (br.T @ filled @ bc)[i, j]


def tile_overlap(cutoff: float, tile: int) -> int:
    """Cells of its neighbours' a tile's transform spans on each side at ``cutoff``.

    The low-pass rings past a window's edge, and its ringing decays slowly
    (as a sinc's sidelobes, about 1/distance), so a window must reach well
    beyond its tile for the tile's own edge cells to be clear of it.
    :data:`TILE_OVERLAP` (8) cells below :data:`WIDE_OVERLAP_CUTOFF` (0.29), where
    the low-pass drops only the spectrum's diagonal corner, twice that from
    it, and at most half a tile (what a reader accepts). Measured
    (docs/benchmarks.md, *The tile overlap against the seams*): at f_c 0.6 to
    0.93, 8 cells left seams of 1.19-1.25x the RMSE elsewhere on Kepler and the
    mountain, 16 cells 1.08-1.13x, 24 no better; a wider window costs bytes
    (its coefficients grow with its area), +6 % on the field at f_c 0 for
    16 cells, where nothing rings. The overlap is a function of the cutoff,
    so a coder that knows the cutoff knows the windows; the file states it
    (``TIDX``).
    """
    wide = cutoff >= WIDE_OVERLAP_CUTOFF
    return min(2 * TILE_OVERLAP if wide else TILE_OVERLAP, tile // 2)


def tile_grid_of(grid: Grid, size: int) -> TileGrid:
    return TileGrid(grid.rows, grid.cols, size)


def coded_window(tiling: TileGrid, k: int, overlap: int) -> tuple[int, int, int, int]:
    """The cells tile ``k``'s transform spans: the tile and ``overlap`` cells around it, within the map."""
    r0, r1, c0, c1 = tiling.bounds(k)
    return (max(0, r0 - overlap), min(tiling.rows, r1 + overlap),
            max(0, c0 - overlap), min(tiling.cols, c1 + overlap))


@dataclass
class TiledTrial(Trial):
    """A trial of every tile at one (cutoff, step), with the base layer's integers."""

    base: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    tiles: list[Trial] = field(default_factory=list)


class TiledAnalysis:
    """A tiled map conditioned once for rate control: the base layer and one Analysis per occupied tile.

    Duck-types :class:`~dftpcc.analysis.Analysis` for :mod:`dftpcc.ratecontrol`:
    a trial quantizes the base layer and every tile at the same (cutoff,
    step) and measures the whole map; the coded stream is the base layer's
    integers followed by each tile's, in tile order.

    A tile's window reaches :func:`tile_overlap` cells into its neighbours,
    which grows with the cutoff: the tiles' analyses are built per overlap,
    the first time a cutoff that needs it is asked for (rate control tries
    the cutoffs in rising order).

    Parameters
    ----------
    dem : DEM
        The whole map.
    params : Params
        ``transform='dct'``, ``storage='quantized'``, ``detrend='plane'``.
    tile : int
        Tile side, cells.
    searching : bool
        As for Analysis: whether trials may ask for any cutoff.
    base_cycles : int
        The base layer's reach, cycles per tile (TIDX).
    """

    def __init__(self, dem: DEM, params: Params, tile: int, *, searching: bool,
                 base_cycles: int = BASE_CYCLES_PER_TILE):
        self.dem, self.params, self.tile = dem, params, tile
        self.base_cycles = base_cycles
        #: Whether the tiles code coefficients of their own (False: :meth:`without_tile_coefs`).
        self.tile_coefs = True
        self.searching = searching
        self.tiling = tile_grid_of(dem.grid, tile)
        self.mask = self.kept_cells = dem.mask
        self.plane = fit_plane(dem)
        self.trend = plane_values(self.plane, dem.grid.shape)
        self.lay = spectrum.layout("dct", "quantized", dem.grid.shape)
        self.parseval = 1.0 / dem.grid.size
        lowest = 0.0 if searching else params.cutoff_or_default
        self.base_i, self.base_j, self.base_radius, self.base_angle = base_order(dem.grid.shape, tile, lowest,
                                                                                 base_cycles)
        detrended = dem.heights - self.trend
        filled = fill_empty(detrended, dem.mask, method="smooth")
        self.base_coefs = base_coefficients(filled, self.base_i, self.base_j)
        self.base_exact = base_heights(self.base_coefs, self.base_i, self.base_j, dem.grid.shape,
                                       (0, dem.grid.rows), (0, dem.grid.cols))
        self.rest = detrended - self.base_exact
        #: The occupied tiles (an empty tile has no sections at all).
        self.occupied = [k for k in range(self.tiling.count) if self.tile_cells(dem.mask, k).any()]
        #: Each overlap's tiles: (tile, its window's analysis), in tile order.
        self._by_overlap: dict[int, list[tuple[int, Analysis]]] = {}
        #: The step of the trial whose rebuilt map refilled the empty cells (None: smooth fill).
        self.refill_step: float | None = None
        #: The overlap of the lowest cutoff asked for, whose tiles serve the questions without a cutoff.
        self.overlap = tile_overlap(lowest, tile)
        self.tiles = self.tiles_with(self.overlap)
        # Overlap and lengths of the parts of the last stream quantized, by its total length (see encode_stream).
        self._splits: dict[int, tuple[int, list[int]]] = {}
        self._last_parts: tuple[np.ndarray, bool, list[bytes]] | None = None
        self._proxy_cache: dict[float, tuple[np.ndarray, float]] = {}

    def tiles_with(self, overlap: int) -> list[tuple[int, Analysis]]:
        """The occupied tiles' analyses on windows of ``overlap`` cells around them (built once)."""
        found = self._by_overlap.get(overlap)
        if found is not None:
            return found
        if not self.tile_coefs:
            return self._by_overlap.setdefault(overlap, [])
        if self.refill_step is not None:
            raise RuntimeError("a refilled tiled analysis holds the tiles of one cutoff's overlap only")
        tile_params = _tile_params(self.params)
        out = []
        for k in self.occupied:
            # A tile's transform spans its cells and a margin of its neighbours': the low-pass
            # blurs the window's edges, and those lie outside the tile.
            w0, w1, v0, v1 = coded_window(self.tiling, k, overlap)
            sub = DEM(grid=self.dem.grid.window(w0, v0, w1 - w0, v1 - v0), heights=self.rest[w0:w1, v0:v1],
                      mask=self.dem.mask[w0:w1, v0:v1])
            out.append((k, Analysis(sub, tile_params, searching=self.searching)))
        self._by_overlap[overlap] = out
        return out

    def untrended(self) -> TiledAnalysis:
        """This analysis (:meth:`Analysis.untrended`): the tiles are coded against the plane and the
        base layer, so a tiled map keeps its plane even where its spectrum is empty."""
        return self

    def tile_cells(self, values: np.ndarray, k: int) -> np.ndarray:
        """The cells of tile ``k`` of a map-sized array."""
        r0, r1, c0, c1 = self.tiling.bounds(k)
        return values[r0:r1, c0:c1]

    def tiles_at(self, cutoff: float) -> list[tuple[int, Analysis]]:
        """The occupied tiles' analyses on the windows ``cutoff`` needs (:func:`tile_overlap`)."""
        return self.tiles_with(tile_overlap(cutoff, self.tile))

    def base_at(self, cutoff: float, step: float) -> np.ndarray:
        """The base layer's integers at (cutoff, step)."""
        return quantizer.quantize(self.base_coefs[: self.base_count(cutoff)], quantizer.short_step(step),
                               self.params.deadzone)

    def base_blob(self, q: np.ndarray) -> bytes:
        """The BASE section of the base layer's integers ``q``."""
        return coding.encode_coefficients(q, radius=self.base_radius[: q.size], angle=self.base_angle[: q.size],
                                          coder=self.params.coder, progressive=False)

    def jobs(self, q: np.ndarray, cutoff: float, step: float) -> list[TileJob]:
        """One :class:`TileJob` per occupied tile at ``cutoff``, against the base layer ``q`` decoded at ``step``."""
        grid = self.dem.grid
        decoded = base_heights(quantizer.dequantize(q, quantizer.short_step(step)), self.base_i[: q.size],
                               self.base_j[: q.size], grid.shape, (0, grid.rows), (0, grid.cols))
        overlap = tile_overlap(cutoff, self.tile)
        out = []
        for k in self.occupied:
            r0, r1, c0, c1 = self.tiling.bounds(k)
            w0, w1, v0, v1 = coded_window(self.tiling, k, overlap)
            counts = None if self.dem.counts is None else self.dem.counts[r0:r1, c0:c1]
            out.append(TileJob(k, self.rest[w0:w1, v0:v1], self.dem.mask[w0:w1, v0:v1],
                               (r0 - w0, r1 - w0, c0 - v0, c1 - v0),
                               decoded[r0:r1, c0:c1] - self.base_exact[r0:r1, c0:c1], counts,
                               coefs=self.tile_coefs))
        return out

    # -- what rate control asks of an analysis --------------------------------------------------

    def base_count(self, cutoff: float) -> int:
        limit = base_limit(self.dem.grid.shape, self.tile, cutoff, self.base_cycles)
        return int(np.searchsorted(self.base_radius, limit, side="right"))

    def counts(self, cutoff: float) -> list[int]:
        """Values per part at ``cutoff``: the base layer, then each occupied tile."""
        return [self.base_count(cutoff)] + [an.count(cutoff) for _, an in self.tiles_at(cutoff)]

    def count(self, cutoff: float) -> int:
        return sum(self.counts(cutoff))

    @property
    def coefs(self) -> np.ndarray:
        """Every sorted coefficient the map may store at the lowest cutoff (base layer, then the tiles')."""
        return np.concatenate([self.base_coefs] + [an.coefs for _, an in self.tiles])

    def reals(self, n: int) -> np.ndarray:
        return self.coefs[:n]

    def largest(self, cutoff: float) -> np.ndarray:
        """The values kept at ``cutoff`` (for the checks on the finest step)."""
        parts = [self.base_coefs[: self.base_count(cutoff)]]
        parts += [an.reals(an.count(cutoff)) for _, an in self.tiles_at(cutoff)]
        return np.concatenate(parts)

    @property
    def refillable(self) -> bool:
        return any(an.refillable for _, an in self.tiles)

    def tiny_step(self) -> float:
        scale = max([float(np.abs(self.base_coefs[:1]).max(initial=0.0))]
                    + [float(np.abs(an.reals(min(an.coefs.size, 1))).max(initial=0.0)) for _, an in self.tiles])
        return max(scale, 1.0) * 1e-9

    def quantized(self, cutoff: float, step: float) -> np.ndarray:
        step = quantizer.short_step(step)
        base = quantizer.quantize(self.base_coefs[: self.base_count(cutoff)], step, self.params.deadzone)
        parts = [base] + [an.quantized(cutoff, step) for _, an in self.tiles_at(cutoff)]
        stream = np.concatenate(parts)
        self._splits[stream.size] = (tile_overlap(cutoff, self.tile), [p.size for p in parts])
        return stream

    def trial(self, cutoff: float, step: float) -> TiledTrial:
        step = quantizer.short_step(step)
        grid = self.dem.grid
        nb = self.base_count(cutoff)
        base = quantizer.quantize(self.base_coefs[:nb], step, self.params.deadzone)
        # A trial measures the whole map's errors for rate control: the inverse DCT of the base
        # layer's corner gives them some five times faster than base_heights' exact sums on a large
        # base layer, with bits that depend on the grid's shape only (as every transform's here,
        # and unlike BLAS's). The tiles are coded against the exact base layer (jobs).
        heights = self.trend + self._base_map(quantizer.dequantize(base, step), nb)
        trials = []
        overlap = tile_overlap(cutoff, self.tile)
        for k, an in self.tiles_with(overlap):
            t = an.trial(cutoff, step)
            r0, r1, c0, c1 = self.tiling.bounds(k)
            w0, _, v0, _ = coded_window(self.tiling, k, overlap)
            heights[r0:r1, c0:c1] += t.heights[r0 - w0:r1 - w0, c0 - v0:c1 - v0]
            trials.append(t)
        err = (heights - self.dem.heights)[self.mask]
        stream = np.concatenate([base] + [t.stream for t in trials])
        self._splits[stream.size] = (overlap, [base.size] + [t.stream.size for t in trials])
        return TiledTrial(cutoff, step, stream, heights, float(np.sqrt(np.mean(err * err))),
                          float(np.abs(err).max()), base=base, tiles=trials)

    def _base_map(self, values: np.ndarray, n: int) -> np.ndarray:
        """The base layer of the first ``n`` coefficients ``values`` on the whole grid, by the inverse DCT."""
        if n == 0:
            return np.zeros(self.dem.grid.shape)
        i, j = self.base_i[:n], self.base_j[:n]
        corner = np.zeros((int(i.max()) + 1, int(j.max()) + 1))
        corner[i, j] = values
        return spectrum.inverse(corner, self.lay, overwrite=True)

    def proxy_rmse(self, cutoff: float, step: float) -> float:
        """As :meth:`Analysis.proxy_rmse`, over the base layer and every tile (each orthonormal)."""
        kept, lost = self._proxy_parts(cutoff)
        err = kept - quantizer.dequantize(quantizer.quantize(kept, step, self.params.deadzone), step)
        return math.sqrt((dot(err, err) + lost) * self.parseval)

    def energy_at(self, cutoff: float) -> tuple[np.ndarray, float]:
        """As :meth:`Analysis.energy_at`, over the base layer and every tile; the base layer's values
        past ``cutoff``'s count are lost too (the tiles code what the whole base layer leaves): a
        base layer that holds the lowest cutoff's circle (:func:`covering_reach`) keeps a small
        share of it at a high cutoff, and the model, blind to that, predicted almost no error."""
        kept, lost = self._proxy_parts(cutoff)
        dropped = self.base_coefs[self.base_count(cutoff):]
        return kept, lost + dot(dropped, dropped)

    def _proxy_parts(self, cutoff: float) -> tuple[np.ndarray, float]:
        """Every value kept at ``cutoff`` in one array, and the energy the low-pass drops (cached:
        rate control asks for the same cutoff at many steps)."""
        cached = self._proxy_cache.get(cutoff)
        if cached is None:
            kept = [self.base_coefs[: self.base_count(cutoff)]]
            lost = 0.0
            if not self.tile_coefs:  # what the base layer leaves on the occupied cells, all lost
                left = self.rest[self.mask]
                lost = dot(left, left) * self.mask.size / left.size
            for _, an in self.tiles_at(cutoff):
                n = an.count(cutoff)
                kept.append(an.reals(n))
                dropped = an.reals(an.coefs.size)[kept[-1].size:]
                lost += dot(dropped, dropped) + an.outside_energy
            cached = self._proxy_cache[cutoff] = (np.concatenate(kept), lost)
        return cached

    def without_tile_coefs(self) -> "TiledAnalysis":
        """This map as its base layer alone: no tile codes coefficients (no ``COEF``), and the plane,
        fill and base layer are this analysis's, not computed again. For a base layer holding the
        cutoff's whole circle (:func:`covering_reach`): on a small map of small tiles each tile's
        section entry and stream headers (about 40 bytes) cost more than its few coefficients save."""
        out = copy.copy(self)
        out.tile_coefs = False
        out._by_overlap = {}
        out.tiles = out.tiles_with(out.overlap)
        out._splits, out._last_parts, out._proxy_cache = {}, None, {}
        return out

    def refilled(self, trial: TiledTrial) -> "TiledAnalysis":
        """The analysis refilled at ``trial``: the tiles of its cutoff's overlap only (rate control
        searches a refilled analysis at that cutoff alone)."""
        out = copy.copy(self)
        out.refill_step = trial.step
        out.overlap = tile_overlap(trial.cutoff, self.tile)
        out.tiles = [(k, an.refilled(t) if an.refillable else an)
                     for (k, an), t in zip(self.tiles_at(trial.cutoff), trial.tiles)]
        out._by_overlap = {out.overlap: out.tiles}
        out._splits, out._last_parts, out._proxy_cache = {}, None, {}
        return out

    def encode(self, trial: Trial, *, exhaustive: bool = True) -> bytes:
        return self.encode_stream(trial.stream, exhaustive=exhaustive)

    def encode_stream(self, stream: np.ndarray, *, exhaustive: bool = True) -> bytes:
        """All parts' COEF sections joined (rate control only needs their size; :meth:`parts` splits them)."""
        return b"".join(self.parts(stream, exhaustive=exhaustive))

    def estimate(self, trial: Trial, *, exhaustive: bool = False) -> float:
        return self.estimate_stream(trial.stream, exhaustive=exhaustive)

    def estimate_stream(self, stream: np.ndarray, *, exhaustive: bool = False) -> float:
        """Bytes of :meth:`encode_stream`, estimated without coding (rate control's model)."""
        overlap, sizes = self._splits[stream.size]
        bounds = np.cumsum([0] + sizes)
        pieces = [stream[a:b] for a, b in zip(bounds[:-1], bounds[1:])]
        base = pieces[0]
        total = coding.estimated_size(base, radius=self.base_radius[: base.size], angle=self.base_angle[: base.size],
                                      coder=self.params.coder, exhaustive=exhaustive, progressive=False)
        for (_, an), piece in zip(self.tiles_with(overlap), pieces[1:]):
            if piece.any():  # an all-zero tile codes no COEF (tile_coef_code)
                total += an.estimate_stream(piece, exhaustive=exhaustive, progressive=False)
        return total

    def parts(self, stream: np.ndarray, *, exhaustive: bool = True) -> list[bytes]:
        """The BASE section and each occupied tile's COEF section of ``stream``."""
        memo = self._last_parts
        if memo is not None and memo[0] is stream and memo[1] == exhaustive:
            return memo[2]  # rate control's final encode, asked again by the packer
        overlap, sizes = self._splits[stream.size]
        bounds = np.cumsum([0] + sizes)
        pieces = [stream[a:b] for a, b in zip(bounds[:-1], bounds[1:])]
        base = pieces[0]
        out = [coding.encode_coefficients(base, radius=self.base_radius[: base.size],
                                          angle=self.base_angle[: base.size], coder=self.params.coder,
                                          exhaustive=exhaustive, progressive=False)]
        out += [tile_coef_code(an, piece, exhaustive=exhaustive)
                for (_, an), piece in zip(self.tiles_with(overlap), pieces[1:])]
        self._last_parts = (stream, exhaustive, out)
        return out


@dataclass
class TileJob:
    """What coding one tile needs, and nothing of the rest of the map (it travels to a worker).

    Attributes
    ----------
    k : int
        Tile (0-based).
    rest : ndarray
        Heights of the tile's coded window minus the plane and the exact base layer, metres.
    mask : ndarray of bool
        Occupied cells of the window.
    inner : (r0, r1, c0, c1)
        The tile's own cells within the window.
    base_error : ndarray
        The decoded base layer minus the exact one on the tile's cells, metres.
    counts : ndarray, optional
        Points per cell of the tile (for the points' vertical error).
    mask_code, coef_code : bytes, optional
        The tile's MASK or COEF section when the caller knows it already: a
        section is a function of the cells it codes (MASK: which of the tile's
        own cells are occupied; COEF: every height and cell of the window), so
        one coded before from the same cells at the same settings is the same bytes. :func:`code_tile`
        then keeps it instead of coding it again (a growing map whose scan only
        added points to occupied cells keeps its mask; one whose cells kept
        their means but not their counts keeps both and updates its errors).
    keep_residual : bool
        Return the residual layer's integers too (:attr:`TileCode.residual`), for a map residual.
    coefs : bool
        False: the tile codes no coefficients (no ``COEF``); its heights are the base layer's
        (``TiledAnalysis.tile_coefs``).
    """

    k: int
    rest: np.ndarray
    mask: np.ndarray
    inner: tuple[int, int, int, int]
    base_error: np.ndarray
    counts: np.ndarray | None = None
    mask_code: bytes | None = None
    coef_code: bytes | None = None
    keep_residual: bool = False
    coefs: bool = True


@dataclass
class TileCode:
    """One tile coded: its sections and the errors it leaves (metres)."""

    k: int
    mask: bytes
    coef: bytes
    resid: bytes
    cells: int
    squared_error: float
    max_error: float
    weighted_squared_error: float = 0.0  # sum of points per cell x squared error
    residual: np.ndarray | None = None  # the RESD integers, one per occupied cell (TileJob.keep_residual)

    @property
    def rmse(self) -> float:
        return math.sqrt(self.squared_error / self.cells)


@functools.lru_cache(maxsize=16)
def _tile_params(params: Params) -> Params:
    """A tile's own parameters: no plane of its own, coded whole (Params are frozen; a growing map
    codes a dozen tiles a scan with the same ones, and replace() validates them each time)."""
    return params.replace(detrend="none", tile_size=0)


#: Where a tile's window sits: tiles are coded on a grid of their own, unit cells (only shapes matter).
_WINDOW_GRID = dict(x0=0.0, y0=0.0, z0=0.0, resolution=1.0)


def tile_coef_code(an: Analysis, stream: np.ndarray, *, exhaustive: bool = True) -> bytes:
    """A tile's COEF section of ``stream``: none (b"") when every value is 0 (format.md, TIDX)."""
    if not stream.any():
        return b""
    return an.encode_stream(stream, exhaustive=exhaustive, progressive=False)


def tile_mask_code(mask: np.ndarray) -> bytes:
    """A tile's ``MASK`` payload: none (b"") for a full tile, whose mask the reader takes as every
    cell (docs/format.md, TIDX); else its own coding, the first line a seed where that is shorter."""
    return b"" if mask.all() else occupancy.encode_mask(mask, first_seed=True)


def code_tile(job: TileJob, params: Params, refill_step: float | None = None) -> TileCode:
    """Code one tile at ``params.cutoff`` and ``params.step``: a pure function of the job, so the
    bytes are the same whichever process or machine runs it.

    ``refill_step``: with ``fill='consistent'``, the step of the trial whose rebuilt heights refill
    the window's empty cells (as rate control chose it); None keeps the smooth fill. Sections the
    job already holds (``job.mask_code``, ``job.coef_code``) are kept, not coded again; the errors
    are always measured.
    """
    r0, r1, c0, c1 = job.inner
    target = job.rest[r0:r1, c0:c1]
    mask = job.mask[r0:r1, c0:c1]
    coef_code = b""
    if job.coefs:
        tile_params = _tile_params(params)
        sub = DEM(grid=Grid(rows=job.rest.shape[0], cols=job.rest.shape[1], **_WINDOW_GRID),
                  heights=job.rest, mask=job.mask)
        # The errors are measured on the tile's own cells below, not over the window (as a trial
        # would), and the energy outside the circle serves rate control only.
        an = Analysis(sub, tile_params, searching=False, outside_energy=False)
        if refill_step is not None and an.refillable:
            an = an.refilled(an.trial(params.cutoff, refill_step))
        stream, heights = an.rebuilt(params.cutoff, params.step)
        rebuilt = heights[r0:r1, c0:c1] + job.base_error
        coef_code = tile_coef_code(an, stream) if job.coef_code is None else job.coef_code
    else:  # the base layer's heights alone
        rebuilt = job.base_error
    resid, q = b"", None
    if params.target_max_error > 0:
        q, rebuilt = residual(target, rebuilt, mask, mask, params.target_max_error)
        resid = encode_residual(q, params.coder, mask)
    err = (rebuilt - target)[mask]
    weighted = float(np.sum(job.counts[mask] * err * err)) if job.counts is not None else 0.0
    mask_code = tile_mask_code(mask) if job.mask_code is None else job.mask_code
    return TileCode(job.k, mask_code, coef_code, resid, int(mask.sum()), dot(err, err), float(np.abs(err).max()),
                    weighted, q if job.keep_residual else None)
