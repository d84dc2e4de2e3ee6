"""Maps larger than memory: a GeoTIFF DEM coded one band of tile rows at a time, and a tiled map
decoded band by band into a GeoTIFF (or a Cloud Optimized GeoTIFF) or LAS/LAZ.

:func:`compress_raster` reads the raster through rasterio windows twice: once for the
reference height, the plane and a decimated copy (from which the base layer's coefficients
come: they hold at most a cycle per tile), once to code the tiles band by band with
:func:`dftpcc.tiles.code_tile`. The cutoff and step are chosen on a block of tiles from the
map's middle (:func:`dftpcc.encoder.choose_for_tiles`) and checked on the whole map at the end.
A band is read, reduced and coded in column blocks of :data:`BLOCK_TILES` tiles (plus the
overlap), so memory follows the tile size, not the map's width; on a dask cluster each worker
reads its own blocks from the file (:func:`_code_block`), and only the coded bytes come back.
A point cloud's grid too large to hold is read the same way from the files it was gridded into,
band by band (:func:`compress_bands` of :func:`dftpcc.grid.rasterize_bands`).
"""

from __future__ import annotations

import math
import warnings
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from . import coding, quantizer
from .cluster import serial
from .format import MapWriter
from .dem import DEM, Grid, TileGrid
from .grid import GriddedBands
from .encoder import Stage, check_heights, choose_for_tiles, no_stage
from .errors import InvalidInputError, RasterTypeWarning
from .fill import PlaneSums, fill_empty
from .params import Params, tile_size_for
from .rebuild import dem_to_point_chunks
from .tiles import (BASE_CYCLES_PER_TILE, TileJob, base_coefficients, base_heights, base_limit, base_order,
                    code_tile, coded_window, tile_overlap)

__all__ = ["compress_raster", "compress_gridded", "compress_bands", "decompress_bands", "codes_in_bands", "STREAM_CELLS", "SAMPLE_TILES", "STREAM_FORMATS"]

#: A GeoTIFF of more cells than this is coded band by band (and a tiled map of more is decoded so).
STREAM_CELLS = 16_000_000
#: Rate control chooses the cutoff and step on this many tiles a side from the map's middle
#: (fewer where they would pass :data:`SAMPLE_CELLS`).
SAMPLE_TILES = 2
#: Most cells of rate control's sample (at least one tile). Its trials hold about a kilobyte a cell
#: at a max-error target (4.3 GB on 2 x 2 tiles of 1,024, 1.2 GB on one): the sample, not the map,
#: set the peak of a run.
SAMPLE_CELLS = 1 << 21
#: Rows and columns of the raster the first pass reads at a time: its sums hold several arrays of a
#: window's occupied cells, so a window is bounded whatever the map's width. A multiple of every
#: decimation block (:data:`SAMPLES_PER_TILE` into a power-of-two tile), so that no block straddles two.
SURVEY_ROWS = 128
SURVEY_COLS = 4096
#: Samples a tile side of the decimated copy the base layer is computed from.
SAMPLES_PER_TILE = 16
#: Attempts at an RMSE target before giving up: a step chosen on part of the map may miss on all of it.
RMSE_ATTEMPTS = 3
#: The middle block's RMSE target, as a fraction of the map's: room for the rest of the map to differ.
SAMPLE_RMSE_MARGIN = 0.95
#: The middle block's size target (bits per point), as a fraction of the map's, for the same reason.
SAMPLE_BPP_MARGIN = 0.95
#: Bits a coded coefficient costs for each halving of the step, about (entropy-coded uniform
#: quantizer: one bit per halving): a size target missed on the whole map takes a coarser step by
#: as many halvings as the excess's share of the bits times this.
BITS_PER_HALVING = 4.0
#: Output formats written band by band.
STREAM_FORMATS = ("tif", "tiff", "las", "laz")
#: Tile columns of the block a band is read, reduced and coded (or decoded and written) in: memory
#: holds a band's rows by this many tiles plus the overlap, whatever the map's width.
BLOCK_TILES = 4
#: Blocks handed to ``map_tiles`` at once: enough to keep a few workers busy between two
#: batches; a block of a map held in memory carries its cells, so this also bounds those copies.
BATCH_BLOCKS = 8
#: Blocks handed to ``map_tiles`` at once when each reads its own cells (a file): only their coded
#: tiles come back, so a larger batch costs little memory, and the workers wait less often for the
#: slowest block of a batch (with 8, a 2-worker run idled about half a block every 4 blocks).
READ_BATCH_BLOCKS = 32
#: Cells of a decoded block turned into points and written to LAS/LAZ at a time: a block of
#: BLOCK_TILES tiles of 1024 cells is 4 M points, whose point array and LAS record would hold
#: about 200 MB more than the block itself.
LAS_CHUNK_CELLS = 1 << 20
#: GDAL's block cache while a raster is read or written band by band, bytes. GDAL's default, 5 % of
#: RAM (1.2 GB on a 24 GB machine), is more than the rest of a run holds; a decoded band's
#: partly written GeoTIFF blocks (a 256-row block row of a block of tiles) must fit in it.
GDAL_CACHE_BYTES = 256 * 1024 ** 2

Map = Callable[..., list]


def _gdal_env() -> Any:
    """GDAL's settings while a map streams: a bounded block cache (:data:`GDAL_CACHE_BYTES`)."""
    import rasterio

    return rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_BYTES)


class _Raster:
    """A GeoTIFF read by windows (:class:`~dftpcc.io.geotiff.RasterWindows`) under the bounded GDAL
    cache; a dask worker reopens it by its path, so no cells travel from the main process."""

    in_memory = False
    counted: int | None = None  # a raster's cells are not counted points

    def __init__(self, path: str | os.PathLike[str]):
        from .io.geotiff import RasterWindows  # rasterio, loaded only for a raster

        self.windows = RasterWindows(path, cache_bytes=GDAL_CACHE_BYTES)
        self.path, self.rows, self.cols, self.crs = path, self.windows.rows, self.windows.cols, self.windows.crs
        self.point_count: int | None = None  # the valid pixels, counted on the first pass

    def read(self, r0: int, r1: int, c0: int = 0, c1: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        return self.windows.read(r0, r1, c0, c1)

    def counts(self, r0: int, r1: int, c0: int = 0, c1: int | None = None) -> None:
        return None

    def grid(self, z0: float) -> Grid:
        return self.windows.grid(z0)

    def check_unchanged(self) -> None:
        self.windows.check_unchanged()

    def close(self) -> None:
        self.windows.close()


def _at_height(g: Grid, z0: float) -> Grid:
    """The grid ``g`` with its heights about ``z0`` (metres)."""
    return Grid(x0=g.x0, y0=g.y0, z0=z0, resolution=g.resolution, rows=g.rows, cols=g.cols, angle=g.angle,
                resolution_y=g.resolution_y)


class _Grid:
    """An already gridded map (a point cloud read in chunks) read by rows like a raster.

    It lives in the main process only: its blocks carry their cells to where they are coded.
    """

    in_memory = True

    def __init__(self, dem: DEM, point_count: int, crs: dict[str, Any], name: str):
        self.dem, self.path, self.crs = dem, name, crs
        self.rows, self.cols = dem.grid.shape
        self.point_count = point_count

    def read(self, r0: int, r1: int, c0: int = 0, c1: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        c1 = self.cols if c1 is None else c1
        m = self.dem.mask[r0:r1, c0:c1]
        return np.where(m, self.dem.heights[r0:r1, c0:c1] + self.dem.grid.z0, np.nan), m

    def counts(self, r0: int, r1: int, c0: int = 0, c1: int | None = None) -> np.ndarray | None:
        c1 = self.cols if c1 is None else c1
        return None if self.dem.counts is None else self.dem.counts[r0:r1, c0:c1]

    def grid(self, z0: float) -> Grid:
        return _at_height(self.dem.grid, z0)

    def check_unchanged(self) -> None:
        pass

    def close(self) -> None:
        pass

    @property
    def counted(self) -> int | None:
        """Points gridded (the counts' sum), or None without counts."""
        return None if self.dem.counts is None else int(self.dem.counts.sum())


class _Bands:
    """A cloud's grid on disk, gridded band by band (:class:`~dftpcc.grid.GriddedBands`), read by
    windows as a GeoTIFF is; a dask worker reads its own windows from the files."""

    in_memory = False

    def __init__(self, bands: GriddedBands, point_count: int, crs: dict[str, Any], name: str):
        self.bands, self.path, self.crs, self.point_count = bands, name, crs, point_count
        self.rows, self.cols = bands.grid.shape
        self.counted: int | None = bands.counted

    def read(self, r0: int, r1: int, c0: int = 0, c1: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        c1 = self.cols if c1 is None else c1
        m = self.bands.mask(r0, r1, c0, c1)
        return np.where(m, self.bands.heights(r0, r1, c0, c1) + self.bands.grid.z0, np.nan), m

    def counts(self, r0: int, r1: int, c0: int = 0, c1: int | None = None) -> np.ndarray:
        return self.bands.counts(r0, r1, c0, self.cols if c1 is None else c1)

    def grid(self, z0: float) -> Grid:
        return _at_height(self.bands.grid, z0)

    def check_unchanged(self) -> None:
        pass

    def close(self) -> None:
        pass


def _release_heap() -> None:
    """Give the C heap's free pages back to the system (glibc's ``malloc_trim``; elsewhere nothing).

    A block's arrays of a few to 30 MB come from the heap once glibc's adaptive mmap threshold has
    risen, and the freed pages between them stay resident: a band-coded map's peak crept up with
    the blocks coded (+160 MB from 10,000² to 20,000²), not with what a block needs.
    """
    global _TRIM
    if _TRIM is None:
        try:
            import ctypes

            _TRIM = ctypes.CDLL("libc.so.6").malloc_trim
        except (OSError, AttributeError):
            _TRIM = False
    if _TRIM:
        _TRIM(0)


_TRIM: Any = None


def _bands(rows: int, tile: int) -> Iterator[tuple[int, int]]:
    for start in range(0, rows, tile):
        yield start, min(rows, start + tile)


#: Rows of the raster one task of the first pass surveys (windows of :data:`SURVEY_ROWS` by
#: :data:`SURVEY_COLS`, in order): on a cluster, a worker decodes each GeoTIFF block of its rows once.
SURVEY_TASK_ROWS = 1024


@dataclass(frozen=True)
class _SurveyPass:
    """What every task of the first pass shares: the raster (a worker reopens it), the heights'
    reference (the first occupied window's mean), the decimation block, and whether blocks lie
    whole inside windows (then a window's block sums are final)."""

    source: Any
    ref: float
    block: int
    aligned: bool


def _survey_rows(rows: tuple[int, int], job: _SurveyPass) -> list[Any]:
    """The first pass over grid rows ``rows`` (:func:`_survey_windows`), as a list: a task's result."""
    out = list(_survey_windows(rows, job))
    _release_heap()
    return out


def _survey_windows(rows: tuple[int, int], job: _SurveyPass) -> Iterator[Any]:
    """The first pass over grid rows ``rows``, window by window: for each occupied window, its plane
    sums, its lowest and highest heights, and its decimated block sums and counts (the blocks it
    covers, when they lie whole inside it; else its cells' blocks and heights, for the caller to
    add in order); None for an empty window. A pure function of the rows and the pass: the same
    bits here or on a worker."""
    raster, d = job.source, job.block
    for r0, r1 in _bands_from(rows, SURVEY_ROWS):
        for c0, c1 in _bands(raster.cols, SURVEY_COLS):
            h, m = raster.read(r0, r1, c0, c1)
            if not m.any():
                yield None
                continue
            rr, cc = np.nonzero(m)
            z = h[rr, cc]
            del h
            fit = PlaneSums(job.ref)
            lowest, highest = float(z.min()), float(z.max())
            rr += r0
            cc += c0
            fit.add(cc.astype(float), rr.astype(float), z)
            rr //= d
            cc //= d
            zr = z - job.ref
            if job.aligned:  # every block of the window is whole in it: its sums, in the cells' order
                b0, k0 = r0 // d, c0 // d
                shape = (-(-(r1 - r0) // d), -(-(c1 - c0) // d))
                flat = (rr - b0) * shape[1] + (cc - k0)
                sums = np.bincount(flat, weights=zr, minlength=shape[0] * shape[1]).reshape(shape)
                counts = np.bincount(flat, minlength=shape[0] * shape[1]).reshape(shape).astype(float)
                yield fit.moments, lowest, highest, (b0, k0, sums, counts)
            else:
                yield fit.moments, lowest, highest, (rr, cc, zr)


def _bands_from(rows: tuple[int, int], size: int) -> Iterator[tuple[int, int]]:
    for start in range(rows[0], rows[1], size):
        yield start, min(rows[1], start + size)


def _survey(raster: _Raster, tile: int, on_stage: Stage, run: Map = serial) -> dict[str, Any]:
    """First pass: the reference height, the plane (:class:`~dftpcc.fill.PlaneSums`), the height
    range and a decimated copy (block sums and counts).

    Rows of :data:`SURVEY_TASK_ROWS` are surveyed by ``run`` (on a cluster, each worker reads its
    own) when the decimation blocks lie whole inside the windows; their sums are added here in the
    windows' order, so the bits are the serial pass's.
    """
    d = max(1, tile // SAMPLES_PER_TILE)
    rb, cb = -(-raster.rows // d), -(-raster.cols // d)
    sums, counts = np.zeros((rb, cb)), np.zeros((rb, cb))
    on_stage("read")
    ref = _first_mean(raster)
    if ref is None:
        raise InvalidInputError(f"{raster.path}: every pixel is nodata")
    # A block straddling two windows gets its sum in two parts, whose addition rounds otherwise than
    # the cell-by-cell sum: such a map (a tile side not 16 times a power of two) is surveyed here.
    aligned = SURVEY_ROWS % d == 0 and SURVEY_COLS % d == 0
    parallel = aligned and not raster.in_memory and run is not serial
    job = _SurveyPass(raster, ref, d, aligned)
    fit = PlaneSums(ref)
    lowest, highest = math.inf, -math.inf
    tasks = list(_bands(raster.rows, SURVEY_TASK_ROWS))
    step = BATCH_BLOCKS if parallel else 1
    for i in range(0, len(tasks), step):
        on_stage("read", tasks[i][0] / raster.rows)
        if parallel:
            windows: Iterator[Any] = (w for part in run(_survey_rows, tasks[i:i + step], job) for w in part)
        else:  # one window at a time: a window's cells are not held past it
            windows = _survey_windows(tasks[i], job)
        for window in windows:
            if window is None:
                continue
            moments, low, high, blocks = window
            fit.moments += moments
            lowest, highest = min(lowest, low), max(highest, high)
            if aligned:
                b0, k0, s, c = blocks
                sums[b0:b0 + s.shape[0], k0:k0 + s.shape[1]] += s
                counts[b0:b0 + s.shape[0], k0:k0 + s.shape[1]] += c
            else:
                rows, cols, zr = blocks
                np.add.at(sums, (rows, cols), zr)
                np.add.at(counts, (rows, cols), 1.0)
    check_heights(lowest, highest)
    z0 = fit.mean()
    return {"z0": z0, "plane": fit.plane(z0), "block": d, "sums": sums, "counts": counts,
            "ref": fit.ref, "cells": fit.count}


def _first_mean(raster: Any) -> float | None:
    """The mean height of the first occupied window of the first pass (its sums' reference), or None."""
    for r0, r1 in _bands(raster.rows, SURVEY_ROWS):
        for c0, c1 in _bands(raster.cols, SURVEY_COLS):
            h, m = raster.read(r0, r1, c0, c1)
            if m.any():
                return float(h[m].mean())
    return None


def _base_coefficients(survey: dict[str, Any], shape: tuple[int, int], tile: int, cycles: int
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The base layer's coefficients (exact, unquantized) from the decimated copy
    (:func:`dftpcc.tiles.base_coefficients` of its block means, detrended and filled)."""
    i, j, radius, angle = base_order(shape, tile, 0.0, cycles)
    if i.size == 0:
        return i, j, radius, angle, np.zeros(0)
    d, sums, counts = survey["block"], survey["sums"], survey["counts"]
    mask = counts > 0
    a, b, c = survey["plane"]
    rb, cb = sums.shape
    # Block means about z0 minus the plane at the block's mean position (the plane is linear).
    rows_c = (np.arange(rb) * d + (np.minimum(np.arange(rb) * d + d, shape[0]) - 1)) / 2.0
    cols_c = (np.arange(cb) * d + (np.minimum(np.arange(cb) * d + d, shape[1]) - 1)) / 2.0
    means = np.where(mask, sums / np.maximum(counts, 1) + survey["ref"] - survey["z0"], 0.0)
    means -= np.where(mask, a + b * cols_c[None, :] + c * rows_c[:, None], 0.0)
    filled = fill_empty(means, mask, method="smooth")
    return i, j, radius, angle, base_coefficients(filled, i, j, rows=shape[0], cols=shape[1], block=d)


def _sample(raster: Any, grid: Grid, tile: int, gridding_rmse: float) -> DEM:
    """A block of :data:`SAMPLE_TILES` x :data:`SAMPLE_TILES` tiles from the map's middle (fewer, down to
    one, where they would pass :data:`SAMPLE_CELLS`), in memory."""
    tiling = TileGrid(grid.rows, grid.cols, tile)

    side = max(1, min(SAMPLE_TILES, math.isqrt(SAMPLE_CELLS) // tile))

    def span(count: int, size: int) -> tuple[int, int]:
        n = min(side, -(-size // tile))
        first = max(0, count // 2 - n // 2)
        return first * tile, min(size, (first + n) * tile)

    r0, r1 = span(tiling.tile_rows, grid.rows)
    c0, c1 = span(tiling.tile_cols, grid.cols)
    h, m = raster.read(r0, r1, c0, c1)
    if not m.any():  # an empty middle: the first band of tiles that has data
        for r0, r1 in _bands(grid.rows, tile * side):
            h, m = raster.read(r0, r1, 0, min(grid.cols, tile * side * 4))
            c0, c1 = 0, h.shape[1]
            if m.any():
                break
    return DEM(grid=grid.window(r0, c0, h.shape[0], h.shape[1]),
               heights=np.where(m, h - grid.z0, 0.0), mask=m, gridding_rmse=gridding_rmse)


def codes_in_bands(shape: tuple[int, int], params: Params) -> bool:
    """Whether a map of ``shape`` is coded band by band (:func:`compress_raster`, :func:`compress_gridded`):
    more than :data:`STREAM_CELLS` cells, in tiles. A map coded whole (``tile_size`` 0, or one tile
    holds it) is coded in memory: it was asked so, or it fits."""
    return shape[0] * shape[1] > STREAM_CELLS and tile_size_for(params, shape) > 0


def compress_raster(src: str | os.PathLike[str], dst: str | os.PathLike[str], params: Params, *,
                    map_tiles: Map | None = None, on_stage: Stage = no_stage,
                    write: Callable[[str | os.PathLike[str], Callable[[Path], None]], None]) -> None:
    """Code the GeoTIFF DEM ``src`` as a tiled map ``dst``, one band of tile rows at a time, a block of
    :data:`BLOCK_TILES` tiles at a time within it.

    Parameters
    ----------
    params : Params
        A target RMSE, maximum error or size (``target_bpp``), or a cutoff and step (automatic
        when 0). The cutoff and step are chosen on the map's middle; an RMSE or size target is
        checked on the whole map, the step changed and the map coded again if missed.
    map_tiles : callable, optional
        Where the tiles are coded (:func:`dftpcc.cluster.executor`).
    write : callable
        ``write(dst, fill)`` creates ``dst`` atomically, ``fill(tmp_path)`` writing its bytes
        (:func:`dftpcc.io.atomic_write`).

    Raises
    ------
    InvalidInputError
        A raster that is not a north-up DEM, no valid pixel, heights out of range, a file that
        changed while it was read, or an RMSE or size target missed on the whole map after
        :data:`RMSE_ATTEMPTS` steps chosen on part of it.
    """
    _compress(_Raster(src), dst, params, map_tiles=map_tiles, on_stage=on_stage, write=write)


def compress_gridded(dem: DEM, dst: str | os.PathLike[str], params: Params, *, point_count: int,
                     crs: dict[str, Any], map_tiles: Map | None = None, on_stage: Stage = no_stage,
                     write: Callable[[str | os.PathLike[str], Callable[[Path], None]], None]) -> None:
    """:func:`compress_raster` of a map already gridded (a point cloud read in chunks): memory holds
    the grid and a few blocks of tiles, not the several copies of the map an in-memory encode makes."""
    _compress(_Grid(dem, point_count, crs, "<grid>"), dst, params, map_tiles=map_tiles, on_stage=on_stage,
              write=write, gridding_rmse=dem.gridding_rmse or 0.0, spread=dem.spread)


def compress_bands(bands: GriddedBands, dst: str | os.PathLike[str], params: Params, *, point_count: int,
                   crs: dict[str, Any], name: str, map_tiles: Map | None = None, on_stage: Stage = no_stage,
                   write: Callable[[str | os.PathLike[str], Callable[[Path], None]], None]) -> None:
    """:func:`compress_gridded` of a cloud's grid on disk (:func:`~dftpcc.grid.rasterize_bands`), read
    by windows as :func:`compress_raster` reads a GeoTIFF: memory holds a band, not the map, and the
    file's bytes are those :func:`compress_gridded` writes of the same grid. ``name``: the cloud's, for messages."""
    _compress(_Bands(bands, point_count, crs, name), dst, params, map_tiles=map_tiles, on_stage=on_stage,
              write=write, gridding_rmse=bands.gridding_rmse or 0.0, spread=bands.spread)


def _compress(raster: Any, dst: str | os.PathLike[str], params: Params, *, map_tiles: Map | None,
              on_stage: Stage, write: Callable[..., None], gridding_rmse: float = 0.0, spread: Any = None) -> None:
    src = raster.path
    run = map_tiles or serial
    try:
        tile = tile_size_for(params, (raster.rows, raster.cols))
        if not tile:
            raise InvalidInputError(f"{src}: a {raster.rows} x {raster.cols} raster fits one tile: code it in memory")
        survey = _survey(raster, tile, on_stage, run)
        grid = raster.grid(survey["z0"])
        cycles = BASE_CYCLES_PER_TILE
        bi, bj, bradius, bangle, bcoefs = _base_coefficients(survey, grid.shape, tile, cycles)
        on_stage("rate control")
        aim = params.replace(target_rmse=params.target_rmse * SAMPLE_RMSE_MARGIN) if params.target_rmse else params
        aim = aim.replace(target_bpp=params.target_bpp * SAMPLE_BPP_MARGIN) if params.target_bpp else aim
        sample = _sample(raster, grid, tile, gridding_rmse)
        chosen, refill = choose_for_tiles(sample, aim, tile, base_cycles=cycles,
                                          share=sample.grid.size / grid.size if params.target_bpp else None)
        del sample
        chosen = chosen.replace(target_rmse=params.target_rmse, target_bpp=params.target_bpp)
        chosen = chosen.replace(resolution=grid.resolution)
        for attempt in range(RMSE_ATTEMPTS):
            writer, stats, nb, base_blob = _code_bands(raster, grid, chosen, refill, tile, survey,
                                                       (bi, bj, bradius, bangle, bcoefs), run, on_stage,
                                                       gridding_rmse, spread)
            missed = _missed(writer, stats, nb, base_blob, params)
            if missed is None:
                break
            ratio = _step_ratio(writer, stats, nb, base_blob, params)
            writer.close()
            if attempt + 1 == RMSE_ATTEMPTS:
                raise InvalidInputError(f"{missed} on the whole map with the step chosen on its middle; "
                                        f"give a {'larger' if params.target_bpp else 'smaller'} target or a --step")
            chosen = chosen.replace(step=quantizer.short_step(chosen.step * ratio))
        with writer:
            start = writer.head(stats, coef_count=nb, base=base_blob)  # every check, before the file is created
            raster.check_unchanged()  # the tiles coded are of the file surveyed, or nothing is written

            def fill(tmp: Path) -> None:
                with open(tmp, "wb") as out:
                    out.write(start)
                    writer.write_payloads(out)

            on_stage("write")
            write(dst, fill)
    finally:
        raster.close()


def _bits_per_point(writer: MapWriter, stats: dict[str, Any], nb: int, base_blob: bytes) -> float:
    """The file's bits per original point: its header and index (:meth:`MapWriter.head`) and its tiles' sections."""
    size = len(writer.head(stats, coef_count=nb, base=base_blob)) + sum(entry[2] for entry in writer.entries)
    return 8.0 * size / writer.point_count


def _missed(writer: MapWriter, stats: dict[str, Any], nb: int, base_blob: bytes, params: Params) -> str | None:
    """What a coded map misses of an RMSE or size target, or None (met, or neither asked)."""
    if params.target_rmse > 0 and stats["dem_rmse_m"] > params.target_rmse:
        return f"target RMSE {params.target_rmse:g} m was missed ({stats['dem_rmse_m']:.4g} m)"
    if params.target_bpp > 0:
        bpp = _bits_per_point(writer, stats, nb, base_blob)
        if bpp > params.target_bpp:
            return f"target {params.target_bpp:g} bits/point was missed ({bpp:.4g})"
    return None


def _step_ratio(writer: MapWriter, stats: dict[str, Any], nb: int, base_blob: bytes, params: Params) -> float:
    """How much to scale the step after a miss of :func:`_missed`."""
    if params.target_rmse > 0 and stats["dem_rmse_m"] > params.target_rmse:
        # Part of the error is the low-pass's, which the step does not change: shrink the step
        # by the square of the miss, a little inside.
        return SAMPLE_RMSE_MARGIN * (params.target_rmse / stats["dem_rmse_m"]) ** 2
    bpp = _bits_per_point(writer, stats, nb, base_blob)
    return 2.0 ** (BITS_PER_HALVING * (bpp - SAMPLE_BPP_MARGIN * params.target_bpp) / bpp)


@dataclass(frozen=True)
class _Pass:
    """What every block of one coding pass shares; small, so it travels to each worker once.

    ``source`` is the raster a block reads its cells from (a worker reopens it by its path),
    or None when the blocks carry their cells (a map held in this process).
    """

    source: Any
    shape: tuple[int, int]
    z0: float
    plane: tuple[float, float, float]
    tiling: TileGrid
    base: tuple[np.ndarray, np.ndarray, np.ndarray]  # the exact values and their (i, j)
    base_error: np.ndarray  # decoded minus exact base values
    params: Params
    refill: float | None


@dataclass(frozen=True)
class _Block:
    """A block of tiles of one band: the window its coding reads (the tiles plus the overlap).

    ``cells``: the window's heights and mask when the map is held in memory, else None (read
    from the pass's source where the block is coded); ``counts``: points per cell of the
    block's tile rows and columns (the window without its overlap), for a gridded cloud held
    in memory (else read from the source with the cells).
    """

    rows: tuple[int, int]
    cols: tuple[int, int]
    tiles: tuple[int, ...]
    cells: tuple[np.ndarray, np.ndarray] | None = None
    counts: np.ndarray | None = None


def _blocks(raster: Any, tiling: TileGrid, band: int, overlap: int) -> Iterator[_Block]:
    """The column blocks of band ``band`` (tile row), each :data:`BLOCK_TILES` tiles wide, with
    ``overlap`` cells around."""
    first = band * tiling.tile_cols
    for j0 in range(0, tiling.tile_cols, BLOCK_TILES):
        ks = tuple(range(first + j0, first + min(tiling.tile_cols, j0 + BLOCK_TILES)))
        t0, t1, c0, _ = tiling.bounds(ks[0])
        c1 = tiling.bounds(ks[-1])[3]
        w0, w1 = max(0, t0 - overlap), min(tiling.rows, t1 + overlap)
        u0, u1 = max(0, c0 - overlap), min(tiling.cols, c1 + overlap)
        if raster.in_memory:
            yield _Block((w0, w1), (u0, u1), ks, raster.read(w0, w1, u0, u1), raster.counts(t0, t1, c0, c1))
        else:  # read where the block is coded, counts too: a batch of blocks does not hold them all here
            yield _Block((w0, w1), (u0, u1), ks)


def _code_block(block: _Block, job: _Pass) -> list[Any]:
    """Read (or take) one block's window, take off the plane and the base layer, code its occupied tiles.

    A pure function of the block and the pass: the same bytes in this process or on a worker.
    """
    (w0, w1), (u0, u1) = block.rows, block.cols
    heights, m = block.cells if block.cells is not None else job.source.read(w0, w1, u0, u1)
    band_counts = block.counts
    if block.cells is None:  # a gridded cloud's points per cell, from its files (a raster has none)
        t0, t1, b0, _ = job.tiling.bounds(block.tiles[0])
        band_counts = job.source.counts(t0, t1, b0, job.tiling.bounds(block.tiles[-1])[3])
    a, b, c = job.plane
    values, bi, bj = job.base
    rest = heights - job.z0  # a new array: a worker's received cells may be read-only
    rest[~m] = 0.0
    rest -= b * np.arange(u0, u1, dtype=float)[None, :]
    rest -= c * np.arange(w0, w1, dtype=float)[:, None] + a
    rest -= base_heights(values, bi, bj, job.shape, (w0, w1), (u0, u1))
    first = job.tiling.bounds(block.tiles[0])[2]  # the column the block's counts start at
    overlap = tile_overlap(job.params.cutoff, job.tiling.size)
    codes = []
    for k in block.tiles:
        t0, t1, c0, c1 = job.tiling.bounds(k)
        if not m[t0 - w0:t1 - w0, c0 - u0:c1 - u0].any():
            continue
        _, _, v0, v1 = coded_window(job.tiling, k, overlap)
        # What quantizing the base layer changed on the tile (the layer is linear in its values).
        error = base_heights(job.base_error, bi, bj, job.shape, (t0, t1), (c0, c1))
        counts = None if band_counts is None else band_counts[:, c0 - first:c1 - first]
        codes.append(code_tile(TileJob(k, rest[:, v0 - u0:v1 - u0], m[:, v0 - u0:v1 - u0],
                                       (t0 - w0, t1 - w0, c0 - v0, c1 - v0), error, counts),
                               job.params, job.refill))
    del heights, m, rest, band_counts
    _release_heap()  # before the next block's arrays are allocated, here or on a worker
    return codes


def _batches(blocks: Iterator[_Block], size: int = BATCH_BLOCKS) -> Iterator[list[_Block]]:
    batch: list[_Block] = []
    for block in blocks:
        batch.append(block)
        if len(batch) == size:
            yield batch
            batch = []
    if batch:
        yield batch


def _code_bands(raster: Any, grid: Grid, params: Params, refill: float | None, tile: int,
                survey: dict[str, Any], base: tuple, run: Map, on_stage: Stage, gridding_rmse: float,
                spread: Any):
    """Second pass: every band of tile rows coded block by block (:func:`_code_block`) and spooled in order."""
    bi, bj, bradius, bangle, bcoefs = base
    nb = int(np.searchsorted(bradius, base_limit(grid.shape, tile, params.cutoff, BASE_CYCLES_PER_TILE),
                             side="right")) if bi.size else 0
    q = quantizer.quantize(bcoefs[:nb], params.step, params.deadzone)
    base_blob = coding.encode_coefficients(q, radius=bradius[:nb], angle=bangle[:nb], coder=params.coder,
                                           progressive=False)
    base_error = quantizer.dequantize(q, params.step) - bcoefs[:nb]
    tiling = TileGrid(grid.rows, grid.cols, tile)
    job = _Pass(None if raster.in_memory else raster, grid.shape, grid.z0, survey["plane"], tiling,
                (bcoefs[:nb], bi[:nb], bj[:nb]), base_error, params, refill)
    n = tiling.count
    points = raster.point_count if raster.point_count is not None else survey["cells"]
    writer = MapWriter(grid, params, point_count=points, plane=survey["plane"], crs=raster.crs, tiling=tiling,
                       overlap=tile_overlap(params.cutoff, tile), base_cycles=BASE_CYCLES_PER_TILE, spool=True)
    on_stage("encode")
    blocks = (block for band in range(tiling.tile_rows) for block in _blocks(raster, tiling, band, writer.overlap))
    for batch in _batches(blocks, BATCH_BLOCKS if raster.in_memory else READ_BATCH_BLOCKS):
        on_stage("encode", batch[0].tiles[0] / n)
        for code in (code for codes in run(_code_block, batch, job) for code in codes):
            writer.add_code(code)
    counted = raster.counted
    stats = writer.stats(gridding_rmse=gridding_rmse,
                         spread=spread.as_stats() if spread is not None and spread.unrepresented_points else None,
                         vertical_points=max(counted, 1) if counted is not None and params.aggregate == "mean"
                         else None)
    return writer, stats, nb, base_blob


def decompress_bands(cmap: Any, dst: str | os.PathLike[str], fmt: str, *, cog: bool = False,
                     map_tiles: Map | None = None, on_stage: Stage = no_stage,
                     write: Callable[[str | os.PathLike[str], Callable[[Path], None]], None],
                     dtype: str | None = None, nodata: float | None = None) -> int:
    """Decode the map ``cmap`` band by band (of :attr:`~dftpcc.mapfile.CompressedMap.block` rows) into ``dst``
    (GeoTIFF, COG, LAS or LAZ).

    Memory holds a block of :data:`BLOCK_TILES` tiles (a band's rows by that many tile columns),
    never a band of the map's width. A GeoTIFF is written block by block, column strip after column
    strip; LAS and LAZ band after band and, within a band, block after block, each block's points in
    row order: points in row order across the whole width would need the whole band of tiles
    decoded before its first row is complete. A map no wider than a block lists its points in row
    order, as a whole decode does. Returns the points (valid cells) written. A GeoTIFF takes the
    sample type and nodata value of :func:`~dftpcc.io.geotiff.output_type` (the source raster's
    where the file's bound allows it, or ``dtype`` and ``nodata``), as a whole decode does.
    """
    if fmt not in STREAM_FORMATS:
        raise InvalidInputError(f"band-by-band decoding writes {', '.join(STREAM_FORMATS)}, not {fmt}")
    size = cmap.block
    grid = cmap.grid
    written = 0
    if fmt in ("tif", "tiff"):  # checked before the first band is decoded
        from .io.geotiff import output_type

        sample, empty, note = output_type(cmap.header.stats, dtype=dtype, nodata=nodata)
        if note:
            warnings.warn(f"{dst}: {note}", RasterTypeWarning, stacklevel=2)

    width = BLOCK_TILES * size
    cells = grid.rows * grid.cols

    def blocks() -> Iterator[tuple[int, int, DEM]]:
        # Column strips of BLOCK_TILES tiles, each from south to north: a GeoTIFF block that
        # straddles two bands is completed by the next window written, so GDAL's cache holds
        # a strip's few partly written blocks, not a block row of the whole width.
        done = 0
        for c0 in range(0, grid.cols, width):
            c1 = min(grid.cols, c0 + width)
            for r0, r1 in _bands(grid.rows, size):
                on_stage("decode", done / cells)
                yield r0, c0, cmap.read_window((r0, r1), (c0, c1), map_tiles=map_tiles)
                done += (r1 - r0) * (c1 - c0)

    def band_blocks() -> Iterator[DEM]:
        # Band after band, each in blocks from west to east: a cloud's points keep the bands' order.
        for r0, r1 in _bands(grid.rows, size):
            for c0 in range(0, grid.cols, width):
                on_stage("decode", (r0 * grid.cols + c0 * (r1 - r0)) / cells)
                yield cmap.read_window((r0, r1), (c0, min(grid.cols, c0 + width)), map_tiles=map_tiles)

    def fill(tmp: Path) -> None:
        nonlocal written
        if fmt in ("tif", "tiff"):
            from .io.geotiff import write_geotiff_windows  # rasterio, loaded only for a raster

            with _gdal_env():
                written = write_geotiff_windows(tmp, grid, cmap.crs, blocks(), cog=cog, sample=sample, empty=empty)
        else:
            from .io.las import write_las_chunks  # laspy, loaded only for a cloud

            corners = (grid.x0, grid.y0, grid.x0 + grid.cols * grid.resolution, grid.y0 + grid.rows * grid.dy)
            points = (part for dem in band_blocks() for part in dem_to_point_chunks(dem, LAS_CHUNK_CELLS))
            written = write_las_chunks(tmp, points, cmap.crs,
                                       np.floor([min(corners[0], corners[2]), min(corners[1], corners[3]), grid.z0]), fmt)

    write(dst, fill)
    return written
