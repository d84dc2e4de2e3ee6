"""Encode stage: a DEM (or a point cloud, gridded first) becomes ``.dftpc`` bytes.

:func:`encode_dem` analyses the DEM once (:mod:`dftpcc.analysis`), codes
the occupancy mask, then either quantizes at the given cutoff and step or
lets rate control (:mod:`dftpcc.ratecontrol`) choose them for a target, and
packs the file with the errors it promises (:mod:`dftpcc.format`).
:func:`compress` is the same for points: grid, rasterize, encode.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Iterable
from typing import Any, Callable, Iterator, NamedTuple

import numpy as np

from .sums import dot, weighted_sq_sum
from . import kernels, occupancy, quantizer, ratecontrol, ratemodel, spectrum
from .cluster import serial
from .analysis import Analysis, Trial
from .format import MapWriter, check_grid, entry_bytes
from .dem import DEM, as_points
from .errors import CoarseMapWarning, InvalidInputError
from .grid import Survey, auto_resolution, fit_grid, rasterize, survey
from .params import MAX_COORDINATE_M, Params, make_params, tile_size_for
from .ratecontrol import Choice
from .residual import GUARANTEE_MARGIN, encode_residual, residual
from .units import length, units_of
from .tiles import (BASE_CYCLES_PER_TILE, MAP_MASK_CELLS, TileCode, TiledAnalysis, code_tile, covering_cutoff,
                    covering_reach, tile_mask_code, tile_overlap)

__all__ = ["compress", "encode_dem", "choose_for_tiles", "grid_points", "params_of", "check_heights", "Stage", "no_stage",
           "QUANT_FLOOR_FRACTION"]

#: With an automatic step, quantization may add this fraction of the
#: gridding error (RMS, metres) to the rebuilt DEM ...
QUANT_FLOOR_FRACTION = 0.5
#: ... but never less than this, for DEMs gridded from one point per cell.
MIN_QUANT_RMSE = 0.001
#: First guess of the bytes a file needs besides mask and coefficients
#: (section table, parameters, statistics, CRS) when sizing to a target.
HEADER_ESTIMATE = 600
#: Bytes the statistics section may grow by between two candidates.
STATS_SLACK = 64
#: Attempts at meeting a size target after measuring the real overhead.
BUDGET_ROUNDS = 3

#: A progress callback: called with the name of each stage as it starts, ``on_stage(name)``,
#: and again as a long stage advances, ``on_stage(name, done)`` with ``done`` in [0, 1].
Stage = Callable[..., None]
#: An automatic step is flagged (CoarseMapWarning) when both its DEM RMSE and the gridding floor
#: it follows exceed this fraction of the map's own height spread (RMS about its mean): the
#: points scatter so much within each cell (vegetation, walls) that the step is coarse for the
#: terrain. Measured at the defaults on ../shared/data: DEM RMSE 0.19-0.59 and floor 0.22-0.46 of
#: the spread on the all-returns forests and coastal plain (flagged); under 0.14 on every DEM,
#: ground-only cloud and the all-returns field (floor 0.11, not flagged).
COARSE_ERROR_FRACTION = 0.15
#: A maximum-error target is at least this many float64 spacings of the map's largest height: below
#: it the gridding, transforms and residual round by as much as the bound (at 3,000 m, 1e-13 m was
#: broken by 0.03 %; from 4 spacings up every target on real heights held).
FLOAT_SPACINGS = 4
#: A maximum-error target is at least float32's smallest normal number (metres): the file states its
#: errors as float32 rounded up (STAT), and below this float32's steps are coarser than the guarantee's
#: margin, so a bound met to the cell could be stated as exceeded (a hypothesis case at 1.4e-45 m).
STATED_ERROR_FLOOR = float(np.finfo(np.float32).tiny)


def no_stage(_: str, done: float | None = None) -> None:
    """The progress callback that shows nothing."""


def params_of(params: Params | None, shortcuts: dict[str, Any]) -> Params:
    """``params``, or :func:`~dftpcc.params.make_params` of ``shortcuts``, with ``shortcuts`` applied."""
    if params is None:
        return make_params(**shortcuts)
    if "profile" in shortcuts:
        raise InvalidInputError("a profile is a preset of Params fields: give it to make_params, not with params")
    return params.replace(**{k: v for k, v in shortcuts.items() if v is not None}) if shortcuts else params


def compress(points: np.ndarray, params: Params | None = None, *, crs: dict[str, Any] | None = None,
             on_stage: Stage = no_stage, backend: kernels.Backend | str | None = None, **shortcuts: Any) -> bytes:
    """Compress a terrain point cloud into ``.dftpc`` bytes.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        x, y, z in metres; float64 keeps coordinates of 1e7 m exact.
    params : Params, optional
        How to compress; default :func:`~dftpcc.params.make_params` of the shortcuts.
    crs : dict, optional
        Coordinate reference system to carry along (see :mod:`dftpcc.io`).
    on_stage : callable, optional
        Called with the name of each stage as it starts (progress display).
    backend : {'numpy', 'compiled'} or dftpcc.kernels.Backend, optional
        Where the kernels run; the bytes are the same either way. By default compiled when numba
        is installed (``pip install 'dftpcc[fast]'``) and the cloud has at least
        :data:`~dftpcc.kernels.COMPILED_MIN_POINTS` points or this process loaded the kernels
        already, else numpy; the environment variable ``DFTPCC_JIT`` (``0``, ``1``) overrides that
        default (:mod:`dftpcc.kernels`).
    **shortcuts
        :class:`~dftpcc.params.Params` fields (and ``profile`` when no
        ``params`` is given): ``resolution`` (metres or ``'auto'``),
        ``cutoff`` (f_c = 1 - r/r_M in [0, 1), paper eq. 2; default 0.8,
        or chosen by rate control when a target is given), ``step``
        (metres), ``aggregate``, ``frame``, ``transform``, ``fill``,
        ``coder``, ``mask``, and the rate-control targets ``target_rmse``
        (metres), ``target_max_error`` (metres), ``target_bpp`` (bits per point).

    Returns
    -------
    bytes

    Raises
    ------
    InvalidInputError
        Empty or non-finite cloud, bad parameter, grid too large, target
        out of reach, unknown backend.
    MissingDependencyError
        ``backend='compiled'`` without numba.
    """
    params = params_of(params, shortcuts)
    with kernels.use(backend, work=kernels.rows_of(points)):
        on_stage("grid")
        points, known = survey(points)
        check_heights(known.z_lo, known.z_hi)  # before gridding overflows on them
        return encode_dem(_grid_points(points, params, known), params,
                          point_count=int(points.shape[0]), crs=crs, on_stage=on_stage)


def grid_points(points: np.ndarray, params: Params) -> DEM:
    """The DEM of ``points`` at ``params.resolution`` (chosen when ``'auto'``), frame and aggregate."""
    return _grid_points(as_points(points), params)


def _grid_points(points: np.ndarray, params: Params, known: Survey | None = None) -> DEM:
    """:func:`grid_points` of checked points (``known``: their :func:`~dftpcc.grid.survey`, if
    made): each pass over millions of points counts."""
    resolution = auto_resolution(points) if params.resolution == "auto" else params.resolution
    grid = fit_grid(points, resolution, frame=params.frame, known=known, checked=True)
    return rasterize(points, grid, aggregate=params.aggregate, checked=True)


def encode_dem(dem: DEM, params: Params, *, point_count: int | None = None,
               crs: dict[str, Any] | None = None, on_stage: Stage = no_stage,
               fill: Callable[..., np.ndarray] | None = None,
               map_tiles: Callable[..., list] | None = None) -> bytes:
    """Code an already gridded DEM (e.g. a GeoTIFF) with ``params``.

    Parameters
    ----------
    dem : DEM
        Heights relative to ``dem.grid.z0`` (metres) and occupancy.
    params : Params
        With a target set, rate control chooses the step, and the cutoff
        unless ``params.cutoff`` is given. The resolution is the grid's.
    point_count : int, optional
        Points of the original cloud (for bits per point); default: occupied cells.
    fill : callable, optional
        Another fill of the empty cells before the transform (see :class:`~dftpcc.analysis.Analysis`).
    map_tiles : callable, optional
        ``map_tiles(func, items, *args)``: how the tiles of a tiled map are coded (default in this
        process; :func:`dftpcc.cluster.executor` gives one on a dask cluster). The bytes are the same.
    """
    if not dem.mask.any():
        raise InvalidInputError("the map has no occupied cell")
    tile = tile_size_for(params, dem.grid.shape)
    params = params.replace(resolution=dem.grid.resolution, tile_size=tile)
    point_count = int(dem.mask.sum()) if point_count is None else point_count
    # What the reader would refuse, refused before any work: heights, then the grid.
    # (z0 + the lowest height is the lowest of z0 + each height: rounding is monotone.)
    occupied = dem.heights[dem.mask]
    check_heights(float(dem.grid.z0 + occupied.min()), float(dem.grid.z0 + occupied.max()))
    layout = _TILES if tile else _WHOLE  # the one place the two layouts part (docs/format.md)
    return layout.encode_dem(dem, params, point_count, crs, on_stage, map_tiles, fill=fill, occupied=occupied)


class _Layout:
    """How a map is laid out in its file, and so analysed, coded and packed: whole (format 1.0,
    :class:`_Whole`) or in tiles (1.1, :class:`_Tiles`). :meth:`encode` (the fixed settings, or rate
    control) is the same for both; the layouts differ in their analysis, their masks, what a trial
    keeps, where the coefficients are coded and how the file is packed."""

    def encode(self, an: Any, params: Params, point_count: int, crs: dict[str, Any] | None, on_stage: Stage,
               map_tiles: Callable[..., list] | None, masks: Masks | None = None, *,
               occupied_heights: np.ndarray | None = None) -> tuple[bytes, float]:
        """:func:`encode_dem` of a checked map's analysis (``masks``: its masks, when known;
        ``occupied_heights``: ``dem.heights[dem.mask]``, if the caller has them): its bytes and the
        cutoff they were coded with."""
        dem = an.dem
        if params.target_max_error > 0:
            _check_max_error(an, params.target_max_error)
        side = self.masks(an) if masks is None else None

        on_stage("encode")
        if not params.has_target:
            cutoff, step = params.cutoff_or_default, params.step
            with spectrum.fft_workers(None if side is None else side.cores_left):
                if params.storage == "quantized" and step == 0.0:
                    target = max(QUANT_FLOOR_FRACTION * (dem.gridding_rmse or 0.0), MIN_QUANT_RMSE)
                    step = quantizer.choose_step(an.largest(cutoff), target_rmse=target,
                                              n_cells=dem.grid.size, deadzone=params.deadzone)
                if params.storage == "quantized":
                    _check_step(an, cutoff, step)
                # No refill without a target: at a fixed step it lowers the error by a
                # few per cent rather than the size, for two more transforms.
                trial = self.trial(an, cutoff, step)
                if params.step == 0.0 and params.storage == "quantized":  # a step was chosen for the user
                    _flag_coarse(dem, trial, occupied_heights, crs)
                coefs = self.coefficients(an, trial)
            if side is not None:
                masks = side.result()
            return (self.pack(Choice(an, trial, coefs), params, masks, point_count, crs, on_stage, map_tiles=map_tiles),
                    cutoff)
        if side is not None:  # rate control weighs the mask's bytes from its start
            masks = side.result()
        # Rate control. For a size target the header's own bytes count too: start
        # from an estimate, then shrink the budget by any overshoot.
        overhead = masks.size + HEADER_ESTIMATE
        for round_ in range(BUDGET_ROUNDS):
            try:
                choice = ratemodel.choose(an, params, point_count, overhead,
                                            progress=lambda done: on_stage("encode", done))
            except InvalidInputError:
                # The estimate can exceed a small map's whole header: measure it before giving up.
                measured = self.overhead(an, params, masks, point_count, crs)
                if params.target_bpp <= 0 or round_ or measured >= overhead:
                    raise
                overhead = measured
                continue
            data = self.pack(choice, params, masks, point_count, crs, on_stage, map_tiles=map_tiles)
            if params.target_bpp <= 0 or 8 * len(data) <= params.target_bpp * point_count:
                return data, choice.trial.cutoff
            # Measured now: everything but the coefficients, plus room for the
            # statistics' digits to change with the next candidate.
            overhead = len(data) - choice.size + STATS_SLACK
        raise InvalidInputError(f"target {params.target_bpp} bits/point cannot be met with these settings")

    def overhead(self, an: Any, params: Params, masks: Masks, point_count: int, crs: dict[str, Any] | None) -> int:
        """Bytes of the file besides its coded coefficients, measured by packing it without them."""
        trial = an.trial(max(ratecontrol.cutoffs(params)), an.tiny_step())
        return len(self.pack(Choice(an, trial, b""), params, masks, point_count, crs, no_stage,
                             header_only=True)) + STATS_SLACK


class _Whole(_Layout):
    """An untiled map: one analysis of the whole grid; the mask coded beside the trial (on a second
    core, with the compiled kernels); the coefficients coded with the trial; the file packed whole."""

    def encode_dem(self, dem: DEM, params: Params, point_count: int, crs: dict[str, Any] | None, on_stage: Stage,
                   map_tiles: Callable[..., list] | None, *, fill: Callable[..., np.ndarray] | None,
                   occupied: np.ndarray) -> bytes:
        check_grid(dem.grid, point_count=point_count, cell_count=occupied.size, params=params)
        return self.encode(self.analysis(dem, params, on_stage, fill), params, point_count, crs, on_stage, map_tiles,
                           occupied_heights=occupied)[0]

    @staticmethod
    def analysis(dem: DEM, params: Params, on_stage: Stage, fill: Callable[..., np.ndarray] | None = None) -> Analysis:
        """The whole map's analysis; the energy the low-pass drops only where rate control needs it."""
        on_stage("spectrum")
        return Analysis(dem, params, searching=params.has_target and params.cutoff is None, fill=fill,
                        outside_energy=params.has_target)

    @staticmethod
    def masks(an: Analysis) -> kernels.Side:
        return kernels.Side(lambda kept: Masks(occupancy.encode_mask(kept), []), an.kept_cells,
                            cells=an.dem.grid.size)

    @staticmethod
    def trial(an: Analysis, cutoff: float, step: float) -> Trial:
        # The file's statistics are made of this trial's errors: kept, not computed again.
        return an.trial(cutoff, step, keep_errors=True)

    @staticmethod
    def coefficients(an: Analysis, trial: Trial) -> bytes:
        return an.encode(trial)

    @staticmethod
    def pack(choice: Choice, params: Params, masks: Masks, point_count: int, crs: dict[str, Any] | None,
             on_stage: Stage, *, map_tiles: Callable[..., list] | None = None, header_only: bool = False) -> bytes:
        """Measure what the decoder will rebuild and pack the file with those figures."""
        an, trial = choice.analysis, choice.trial
        params = params.replace(cutoff=trial.cutoff, step=trial.step)
        dem, occupied = an.dem, an.mask
        heights = trial.heights
        asked_rmse = 0.0
        if choice.residual is not None:
            # The file states the bound its residual layer was made for, whatever the target: the
            # decoder's step, and the promise an RMSE target met by a residual layer keeps as well.
            # Such an RMSE target goes to STAT (target_rmse_m), so the file still says what it was made for.
            asked_rmse = params.target_rmse
            params = params.replace(target_rmse=0.0, target_max_error=choice.bound)
            _, heights = residual(dem.heights, trial.heights, occupied, an.kept_cells, choice.bound)
        # Without a residual layer the decoder rebuilds the trial's heights, whose errors it may have kept.
        errors = trial.errors if choice.residual is None else None
        kept = int(an.kept_cells.sum())
        writer = MapWriter(dem.grid, params, point_count=point_count, plane=an.plane, crs=crs)
        rmse, largest, weighted = _figures(dem, params, heights, occupied, errors=errors,
                                           figures=None if errors is None else (trial.rmse, trial.max_error))
        writer.add(0, masks.map, choice.coefs, choice.residual_blob, cells=kept, squared_error=0.0, max_error=largest,
                   weighted_squared_error=weighted)
        extra = {"target_rmse_m": asked_rmse} if asked_rmse > 0 else {}
        stats = writer.stats(rmse=rmse, max_error=largest, cells_interpolated=kept - int(occupied.sum()),
                             **_map_figures(dem, params), **extra)
        on_stage("container")
        return writer.finish(stats, coef_count=an.count(params.cutoff))


class _Tiles(_Layout):
    """A tiled map: a base layer and tiles, each tile coded on its own when the file is packed
    (:func:`~dftpcc.tiles.code_tile`, through ``map_tiles``); a trial measures the whole map."""

    def encode_dem(self, dem: DEM, params: Params, point_count: int, crs: dict[str, Any] | None, on_stage: Stage,
                   map_tiles: Callable[..., list] | None, *, fill: Callable[..., np.ndarray] | None,
                   occupied: np.ndarray) -> bytes:
        # The smallest run's file (the earliest of equal ones).
        return min(self.runs(dem, params, point_count, crs, on_stage, map_tiles), key=lambda run: len(run[1]))[1]

    def runs(self, dem: DEM, params: Params, point_count: int, crs: dict[str, Any] | None, on_stage: Stage,
             map_tiles: Callable[..., list] | None) -> Iterator[tuple[str, bytes]]:
        """The files a tiled map is coded as, each run's in turn with its name (the encoder keeps the
        smallest): ``'first'``; then, where the covering base layer applies, ``'covering'`` (that base
        layer and the tiles' own coefficients) and, with a target, ``'base alone'``
        (benchmarks/bench_tiled_runs.py sizes and times each run)."""
        _check_tiled(params)
        first = self.analysis(dem, params, on_stage, base_cycles=BASE_CYCLES_PER_TILE)
        masks = tiled_masks(first)  # every run's: they depend on the occupancy alone
        data, cutoff = self.encode(first, params, point_count, crs, on_stage, map_tiles, masks)
        yield "first", data
        # Where the cutoff's whole circle is a small base layer (covering_reach), the base layer may hold
        # all of it, and the tiles only what its quantization leaves: the tiles no longer repeat the
        # map's frequencies (nor pay for them in their own headers), so their edges rarely show. The
        # reach is that of the first run's cutoff or, where rate control chooses the cutoff and that
        # circle is too large, of the lowest cutoff whose circle is not (in small tiles the first run
        # may keep every frequency, and pay for them in every tile); rate control then searches again.
        # Kept when smaller (a size target keeps its first file). The second run repeats the plane fit
        # and fill of the first (TiledAnalysis). With a target, a third run codes that base layer
        # alone, every tile without coefficients of its own (TiledAnalysis.without_tile_coefs, which
        # shares the second's plane, fill and base layer): on a small map in small tiles, each tile's
        # COEF entry and stream headers (about 40 bytes) cost more than its few coefficients save.
        # No run is left out on the others' sizes: leaving the second out where the third beat the
        # first lost 9.5 % on field_gentle_ign (every return) at a 0.1 m maximum error (make
        # bench-tiled-runs, tests/digests.json), so each is kept until a model predicts its size.
        if params.target_bpp > 0:
            return
        if params.has_target and params.cutoff is None:
            lowest = covering_cutoff(dem.grid.shape, params.tile_size)
            cutoff = max(cutoff, 1.0 if lowest is None else lowest)
        cycles = covering_reach(dem.grid.shape, params.tile_size, cutoff) if cutoff < 1 else None
        if cycles is None or cycles <= BASE_CYCLES_PER_TILE:
            return
        with warnings.catch_warnings():  # the first run has said whatever these would
            warnings.simplefilter("ignore")
            covering = self.analysis(dem, params, on_stage, base_cycles=cycles)
            # Without a target the settings fix the quality, and a base layer alone would lose the
            # tiles' refinement of it: only a target compares files of equal quality.
            analyses = (("covering", covering), ("base alone", covering.without_tile_coefs())) \
                if params.has_target else (("covering", covering),)
        for name, an in analyses:
            with warnings.catch_warnings():  # not held across the yield: the caller's warnings are its own
                warnings.simplefilter("ignore")
                try:
                    other, _ = self.encode(an, params, point_count, crs, on_stage, map_tiles, masks)
                except InvalidInputError:  # a target the base layer alone cannot reach
                    if an.tile_coefs:
                        raise
                    continue
            yield name, other

    @staticmethod
    def analysis(dem: DEM, params: Params, on_stage: Stage, *, base_cycles: int) -> TiledAnalysis:
        """The tiled map's analysis with a base reach of ``base_cycles`` cycles per tile."""
        on_stage("spectrum")
        return TiledAnalysis(dem, params, params.tile_size, searching=params.has_target and params.cutoff is None,
                             base_cycles=base_cycles)

    @staticmethod
    def masks(an: TiledAnalysis) -> kernels.Side:
        return kernels.Side(tiled_masks, an, cells=0)  # at once: the tiles' masks are small

    @staticmethod
    def trial(an: TiledAnalysis, cutoff: float, step: float) -> Trial:
        return an.trial(cutoff, step)

    @staticmethod
    def coefficients(an: TiledAnalysis, trial: Trial) -> bytes:
        return b""  # the tiles are coded when packing

    @staticmethod
    def pack(choice: Choice, params: Params, masks: Masks, point_count: int, crs: dict[str, Any] | None,
             on_stage: Stage, *, map_tiles: Callable[..., list] | None = None, header_only: bool = False) -> bytes:
        """:meth:`_Whole.pack` of a tiled map: the base layer, then every tile coded on its own at the
        chosen cutoff and step, with its errors in the index (``header_only``: without the tiles'
        coefficients, to measure the rest)."""
        an, trial = choice.analysis, choice.trial
        params = params.replace(cutoff=trial.cutoff, step=trial.step)
        dem = an.dem
        map_resid = b""
        if not header_only:
            q = an.base_at(params.cutoff, params.step)
            base_blob = an.base_blob(q)
            on_stage("encode tiles")
            jobs = an.jobs(q, params.cutoff, params.step)
            # A small map may keep its residual whole, which needs the tiles' integers.
            whole = params.target_max_error > 0 and dem.mask.size <= MAP_MASK_CELLS
            for job, blob in zip(jobs, masks.tiles):  # coded already, or none (a full tile; the map mask)
                job.mask_code, job.keep_residual = blob, whole
            codes = (map_tiles or serial)(code_tile, jobs, params, an.refill_step)
            if whole:
                masks, map_resid = map_residual(an, masks, codes, params.coder)
                codes = [dataclasses.replace(c, residual=None, **({"mask": b"", "resid": b""} if map_resid else {}))
                         for c in codes]
        else:  # measuring the header's own bytes: every tile without coefficients
            base_blob = b""
            codes = [TileCode(k, blob, b"", b"", int(an.tile_cells(dem.mask, k).sum()), 0.0, 0.0)
                     for k, blob in zip(an.occupied, masks.tiles)]
        writer = MapWriter(dem.grid, params, point_count=point_count, plane=an.plane, crs=crs, tiling=an.tiling,
                           overlap=tile_overlap(params.cutoff, an.tile), base_cycles=an.base_cycles)
        for c in codes:
            writer.add_code(c)
        stats = writer.stats(**_map_figures(dem, params))
        on_stage("container")
        return writer.finish(stats, coef_count=an.base_count(params.cutoff), base=base_blob, map_mask=masks.map,
                             map_resid=map_resid)


_WHOLE, _TILES = _Whole(), _Tiles()



def choose_for_tiles(dem: DEM, params: Params, tile: int, *, point_count: int | None = None,
                     base_cycles: int = 1, share: float | None = None) -> tuple[Params, float | None]:
    """The cutoff, step and refill step a tiled map of ``dem`` is coded with (what
    :func:`encode_dem` chooses), for a caller that codes the tiles itself, e.g. a map
    larger than memory whose parameters are chosen on a part of it.

    Returns ``params`` with ``cutoff`` and ``step`` set, and the refill step (None: smooth fill).
    A size target (``target_bpp``) is met on ``dem`` as a part of a larger map, of which it is
    ``share`` of the cells (its masks and that share of a header count against it); without
    ``share`` it needs the whole map and is refused.
    """
    if params.target_bpp > 0 and share is None:
        raise InvalidInputError("a size target (target_bpp) needs the whole map in memory; give a target_rmse, "
                                "a target_max_error, or a cutoff and step")
    params = params.replace(resolution=dem.grid.resolution, tile_size=tile)
    _check_tiled(params)
    an = TiledAnalysis(dem, params, tile, searching=params.has_target and params.cutoff is None,
                       base_cycles=base_cycles)
    if not params.has_target:
        cutoff, step = params.cutoff_or_default, params.step
        if step == 0.0:
            target = max(QUANT_FLOOR_FRACTION * (dem.gridding_rmse or 0.0), MIN_QUANT_RMSE)
            step = quantizer.choose_step(an.largest(cutoff), target_rmse=target, n_cells=dem.grid.size,
                                      deadzone=params.deadzone)
        return params.replace(cutoff=cutoff, step=quantizer.short_step(step)), None
    if params.target_max_error > 0:
        _check_max_error(an, params.target_max_error)
    count = int(dem.mask.sum()) if point_count is None else point_count
    fixed = HEADER_ESTIMATE
    if params.target_bpp > 0:
        fixed = tiled_masks(an).size + math.ceil(HEADER_ESTIMATE * share)
    choice = ratemodel.choose(an, params, count, fixed)
    return params.replace(cutoff=choice.trial.cutoff, step=choice.trial.step), choice.analysis.refill_step


class Masks(NamedTuple):
    """A map's coded masks: the map mask (an untiled map's ``MASK``; a tiled map's at tile 0, b"":
    none) and each occupied tile's ``MASK`` (b"": none), in the order of ``TiledAnalysis.occupied``
    (none for an untiled map)."""

    map: bytes
    tiles: list[bytes]

    @property
    def size(self) -> int:
        """Bytes of the coded masks."""
        return len(self.map) + sum(map(len, self.tiles))


def tiled_masks(an: TiledAnalysis) -> Masks:
    """The masks of a tiled map: the whole grid's at tile 0 where it has at most
    :data:`~dftpcc.tiles.MAP_MASK_CELLS` cells and that is shorter, entries counted, than the tiles'
    own (each pays its header, seeds and entry, and its context model learns the map again);
    else each tile's (docs/format.md, *Tile sections*)."""
    mask = an.dem.mask
    per = [tile_mask_code(an.tile_cells(mask, k)) for k in an.occupied]
    if mask.size > MAP_MASK_CELLS or not any(per):  # too large to decode for every region; or all full
        return Masks(b"", per)
    whole = occupancy.encode_mask(mask)
    if _entries([(0, whole)]) < _entries(zip([k + 1 for k in an.occupied], per)):
        return Masks(whole, [b""] * len(per))
    return Masks(b"", per)


def map_residual(an: TiledAnalysis, masks: Masks, codes: list[TileCode], coder: str) -> tuple[Masks, bytes]:
    """The map residual (tile 0's ``RESD``, beside the map mask) where the two are shorter,
    entries counted, than ``masks`` and the tiles' residual layers; else ``masks`` and b""
    (docs/format.md, *Tile sections*). A sparse residual is mostly its nonzero map, whose context
    model learns the map again in every tile, as a mask's does. ``codes`` hold their integers
    (``TileJob.keep_residual``), in the order of ``an.occupied``."""
    mask = an.dem.mask
    q = np.zeros(mask.shape, dtype=np.int64)
    for c in codes:
        an.tile_cells(q, c.k)[an.tile_cells(mask, c.k)] = c.residual
    whole_mask = masks.map or occupancy.encode_mask(mask)
    whole = encode_residual(q[mask], coder, mask)
    theirs = (_entries([(0, masks.map)] + [(k + 1, b) for k, b in zip(an.occupied, masks.tiles)])
              + _entries((c.k + 1, c.resid) for c in codes))
    if _entries([(0, whole_mask), (0, whole)]) < theirs:
        return Masks(whole_mask, [b""] * len(masks.tiles)), whole
    return masks, b""


def _entries(parts: Iterable[tuple[int, bytes]]) -> int:
    """Bytes of the payloads ``(tile number in the table, payload)`` and of their section entries (b"": none)."""
    return sum(entry_bytes(t, len(b)) + len(b) for t, b in parts if b)


def _check_tiled(params: Params) -> None:
    """Refuse parameters a tiled map cannot be coded with (docs/format.md, *Tiles*)."""
    wrong = {name: getattr(params, name) for name, need in
             (("transform", "dct"), ("storage", "quantized"), ("detrend", "plane"), ("mask", "exact"))
             if getattr(params, name) != need}
    if wrong:
        raise InvalidInputError(
            f"a tiled map is coded with transform=dct, storage=quantized, detrend=plane and mask=exact (the "
            f"compact profile); not with {', '.join(f'{k}={v}' for k, v in wrong.items())}: use tile_size=0 "
            f"(--tile-size 0) to code this map whole")


def check_heights(lowest: float, highest: float) -> None:
    """Refuse heights (metres) outside the ±:data:`~dftpcc.params.MAX_COORDINATE_M` a file holds."""
    if not max(abs(lowest), abs(highest)) <= MAX_COORDINATE_M:
        raise InvalidInputError(
            f"the heights are out of range: they run from {lowest:g} to {highest:g} m, and a .dftpc file "
            f"holds heights within ±{MAX_COORDINATE_M:g} m")


def _height_range(an: Analysis) -> str:
    occupied = an.dem.grid.z0 + an.dem.heights[an.mask]
    return f"{float(occupied.min()):.6g} to {float(occupied.max()):.6g} m"


def _check_step(an: Analysis, cutoff: float, step: float) -> None:
    """Refuse, before quantizing, a step so fine that the integers would wrap (see :func:`quantizer.finest_step`)."""
    finest = quantizer.finest_step(an.largest(cutoff))
    if quantizer.short_step(step) < finest:
        raise InvalidInputError(
            f"quantizer step {step:g} m is too fine for this map's height range ({_height_range(an)}): its "
            f"coefficients would quantize to integers beyond the 64-bit range; the smallest workable step is "
            f"{finest:g} m")


def _check_max_error(an: Analysis, bound: float) -> None:
    """Refuse a maximum-error target so fine that rate control's steps or the residual layer's
    integers would wrap: the finest workable target, from the coefficients and the heights."""
    coefs = an.reals(an.coefs.size)
    need = 0.0
    if an.params.storage == "quantized":  # the finest step rate control tries is a fraction of the bound
        need = quantizer.finest_step(coefs) / min(ratecontrol.MAX_ERROR_STEP_FACTORS)
    # A residual is at most the height's distance from the plane plus the rebuilt map's,
    # and no rebuilt height lies farther from the plane than the root of the energy of
    # the coefficients (Parseval); twice that for the quantization on top.
    spread = float(np.abs((an.dem.heights - an.trend)[an.mask]).max())
    energy = an.dem.grid.size * spectrum.mse_per_squared_error(an.lay) * dot(coefs, coefs)
    residuals = spread + 2.0 * math.sqrt(energy)
    need = max(need, quantizer.finest_step(np.array([residuals])) / (2.0 * (1.0 - GUARANTEE_MARGIN)))
    top = abs(an.dem.grid.z0) + float(np.abs(an.dem.heights[an.mask]).max())
    need = max(need, FLOAT_SPACINGS * float(np.spacing(top)))
    if bound < need:
        raise InvalidInputError(
            f"target maximum error {bound:g} m is too fine for this map's height range ({_height_range(an)}): "
            f"its coefficients or residuals would quantize to integers beyond the 64-bit range, or float64 "
            f"heights round by as much; the smallest workable target is {quantizer.round_up(need):g} m")
    if bound < STATED_ERROR_FLOOR:
        raise InvalidInputError(
            f"target maximum error {bound:g} m is below the {STATED_ERROR_FLOOR:.3g} m a file states its errors "
            f"to (float32, rounded up: finer steps would state more than the target); the smallest workable "
            f"target is {quantizer.round_up(STATED_ERROR_FLOOR):g} m")


def _flag_coarse(dem: DEM, trial: Trial, heights: np.ndarray | None = None,
                 crs: dict[str, Any] | None = None) -> None:
    """Warn when an automatic step leaves a DEM error that is a large part of the map's own height spread
    (``heights``: the occupied cells' heights above z0, if the caller has them), in the heights' unit
    (``crs``: :func:`~dftpcc.units.units_of`)."""
    heights = dem.heights[dem.mask] if heights is None else heights
    spread = float(np.sqrt(np.mean((heights - heights.mean()) ** 2))) if heights.size else 0.0
    floor = dem.gridding_rmse or 0.0
    if spread > 0 and min(trial.rmse, floor) > COARSE_ERROR_FRACTION * spread:
        unit = units_of(crs).vertical

        def say(value: float) -> str:
            return length(value, unit)

        warnings.warn(
            f"the automatic step of {say(trial.step)} (DEM RMSE {say(trial.rmse)}, max {say(trial.max_error)}) is "
            f"coarse for a map whose heights spread by {say(spread)} RMS: the step follows the points' scatter "
            f"within each cell ({say(dem.gridding_rmse or 0.0)} RMS: vegetation, walls?); keep ground points only "
            f"(e.g. --classes 2), or give a --step or a --target-rmse", CoarseMapWarning, stacklevel=3)


def _map_figures(dem: DEM, params: Params) -> dict[str, Any]:
    """What :meth:`MapWriter.stats` needs of the map besides its tiles: the gridding floor, the points
    one height per cell could not hold, and the points the vertical error is averaged over."""
    spread = dem.spread
    mean = dem.counts is not None and params.aggregate == "mean"
    # The raster it came from, to be written back alike (docs/format.md, STAT: source_dtype, source_nodata).
    source = dem.source.as_stats() if dem.source is not None else {}
    return {"gridding_rmse": dem.gridding_rmse or 0.0,
            "spread": spread.as_stats() if spread is not None and spread.unrepresented_points else None,
            "vertical_points": max(int(dem.counts.sum()), 1) if mean else None, **source}


def _figures(dem: DEM, params: Params, heights: np.ndarray, occupied: np.ndarray, *, errors: np.ndarray | None = None,
             figures: tuple[float, float] | None = None) -> tuple[float, float, float]:
    """An untiled map's RMSE and largest error over its occupied cells (metres) and its points'
    weighted squared error (metres², 0 without counts); ``errors``: ``(heights - dem.heights)[occupied]``
    if the caller has them, ``figures`` their RMSE and largest magnitude (``Trial.rmse``,
    ``Trial.max_error``: the same arithmetic)."""
    err = (heights - dem.heights)[occupied] if errors is None else errors
    rmse, largest = (float(np.sqrt(np.mean(err * err))), float(np.abs(err).max())) if figures is None else figures
    weighted = 0.0
    if dem.counts is not None and params.aggregate == "mean":
        # Per cell, points scatter about their mean, so the errors add in quadrature.
        weighted = weighted_sq_sum(dem.counts, occupied, err)
    return rmse, largest, weighted
