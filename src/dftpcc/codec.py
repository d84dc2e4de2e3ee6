"""The whole pipeline: points -> DEM -> spectrum -> coded bytes, and back.

``compress`` and ``decompress`` are the two calls most users need; the
stages they compose live in ``grid``, ``spectrum``, ``coding``,
``container`` and ``rebuild``. Rate control lives here too: the transform
of a DEM is computed once, then cutoffs and quantizer steps are tried
against it until the target (an RMSE, a maximum error or a size) is met
by the smallest (or most accurate) file.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from . import coding, occupancy, spectrum
from .container import Header, pack, unpack
from .errors import CorruptFileError, InvalidInputError
from .grid import DEM, auto_resolution, fill_empty, fit_grid, fit_plane, plane_values, rasterize
from .params import Params, make_params
from .rebuild import dem_to_points

__all__ = ["compress", "decompress", "encode_dem", "decode_dem", "resolve_params", "DEFAULT_CUTOFF"]

#: Cutoff ratio used when neither a cutoff nor a target is given.
DEFAULT_CUTOFF = 0.8
#: With an automatic step, quantization may add this fraction of the
#: gridding error (RMS, metres) to the rebuilt DEM ...
QUANT_FLOOR_FRACTION = 0.5
#: ... but never less than this, for DEMs gridded from one point per cell.
MIN_QUANT_RMSE = 0.001
#: Cutoff ratios rate control tries.
CUTOFF_CANDIDATES = (0.0, 0.3, 0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.93, 0.95, 0.97)
#: Bisection iterations on the quantizer step (log scale).
STEP_ITERATIONS = 18
#: Rounds of measuring the true error and correcting the step search.
CALIBRATION_ROUNDS = 4
#: Rate control stops raising the cutoff once a file is this much larger than the best.
GIVE_UP_FACTOR = 1.3
#: Quantizer steps tried per cutoff for a maximum-error target, as multiples of it.
MAX_ERROR_STEP_FACTORS = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
#: What a file records of the points its DEM cannot represent (DEM.spread).
SPREAD_STATS = ("unrepresented_fraction", "unrepresented_rmse_m")
#: First guess of the bytes a file needs besides mask and coefficients
#: (section table, parameters, statistics, CRS) when sizing to a target.
HEADER_ESTIMATE = 600
#: Bytes the statistics section may grow by between two candidates.
STATS_SLACK = 64
#: Attempts at meeting a size target after measuring the real overhead.
BUDGET_ROUNDS = 3
#: Rounds of refilling the empty cells from the rebuilt map (fill='consistent');
#: measured on the field and coastal plain, a third round gains nothing.
REFILL_ROUNDS = 2
#: With a consistent fill, an RMSE target is searched again for a step up to
#: this much coarser than the one found with the smooth fill, ...
REFILL_STEP_RANGE = 1.25
#: ... in this many bisections (each a refill: about five transforms).
REFILL_STEP_ITERATIONS = 4
#: The residual layer aims this much inside the promised bound, so float
#: round-off in the decoder's inverse transform cannot break the guarantee.
GUARANTEE_MARGIN = 1e-6

Stage = Callable[[str], None]


def _noop(_: str) -> None:
    pass


def resolve_params(points: np.ndarray, *, resolution: float | str = "auto", cutoff: float | None = None,
                   profile: str = "compact", **options: Any) -> Params:
    """:class:`Params` for ``points``, choosing the resolution when it is ``"auto"``."""
    if isinstance(resolution, str):
        if resolution != "auto":
            raise InvalidInputError(f"resolution must be a number of metres or 'auto', got {resolution!r}")
        resolution = auto_resolution(points)
    return make_params(resolution=resolution, cutoff=DEFAULT_CUTOFF if cutoff is None else cutoff,
                       profile=profile, **options)


def compress(points: np.ndarray, *, resolution: float | str = "auto", cutoff: float | None = None,
             profile: str = "compact", crs: dict[str, Any] | None = None,
             on_stage: Stage = _noop, **options: Any) -> bytes:
    """Compress a terrain point cloud into ``.dftpc`` bytes.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        x, y, z in metres; float64 keeps coordinates of 1e7 m exact.
    resolution : float or 'auto'
        DEM cell size in metres; ``auto`` aims at a few points per cell.
    cutoff : float, optional
        Cutoff ratio f_c = 1 - r/r_M in [0, 1) (paper eq. 2). Default 0.8,
        or chosen by rate control when a target is given.
    profile : {'compact', 'paper'}
        ``paper`` stores the raw complex DFT coefficients inside the circle
        exactly as the paper does; ``compact`` (default) detrends, uses the
        mirrored (DCT) transform, quantizes and entropy-codes.
    crs : dict, optional
        Coordinate reference system to carry along (see :mod:`dftpcc.formats`).
    on_stage : callable, optional
        Called with the name of each stage as it starts (progress display).
    **options
        Any other :class:`~dftpcc.params.Params` field: ``step`` (metres),
        ``aggregate``, ``frame``, ``transform``, ``fill``, ``coder``, ``mask``,
        and the rate-control targets ``target_rmse`` (metres),
        ``target_max_error`` (metres), ``target_bpp`` (bits per point).

    Returns
    -------
    bytes

    Raises
    ------
    InvalidInputError
        Empty or non-finite cloud, bad parameter, grid too large, target
        out of reach.
    """
    on_stage("grid")
    points = np.asarray(points)
    params = resolve_params(points, resolution=resolution, cutoff=cutoff, profile=profile, **options)
    grid = fit_grid(points, params.resolution, frame=params.frame)
    dem = rasterize(points, grid, aggregate=params.aggregate)
    return encode_dem(dem, params, point_count=int(points.shape[0]), crs=crs, on_stage=on_stage,
                      cutoff_given=cutoff is not None)


def _footprint(mask: np.ndarray) -> np.ndarray:
    """Occupied cells plus the empty ones the map encloses (one-cell gaps closed, holes filled)."""
    from scipy import ndimage

    closed = ndimage.binary_closing(mask, structure=np.ones((3, 3), bool), border_value=0) | mask
    return ndimage.binary_fill_holes(closed)


@dataclass
class _Trial:
    """One (cutoff, step) tried against a spectrum."""

    cutoff: float
    step: float
    stream: np.ndarray  # what gets entropy-coded (int64 or complex64)
    heights: np.ndarray  # the DEM the decoder will rebuild (relative to z0)
    rmse: float  # on occupied cells, metres
    max_error: float  # on occupied cells, metres


class _Spectrum:
    """What does not change between trials: detrended, filled DEM and its sorted transform."""

    def __init__(self, dem: DEM, params: Params, *, searching: bool):
        self.dem, self.params = dem, params
        self.mask = dem.mask
        self.kept_cells = _footprint(dem.mask) if params.mask == "footprint" else dem.mask
        self.plane = fit_plane(dem) if params.detrend == "plane" else (0.0, 0.0, 0.0)
        self.trend = plane_values(self.plane, dem.grid.shape) if params.detrend == "plane" else 0.0
        # A consistent fill starts from the smooth one (see refilled()).
        fill = "smooth" if params.fill == "consistent" else params.fill
        filled = fill_empty(dem.heights - self.trend, dem.mask, method=fill)
        self.lay = spectrum.layout(params.transform, params.storage, dem.grid.shape)
        # Rate control may try any cutoff; otherwise only the kept circle is needed.
        order, radii, angles = spectrum.kept_order(self.lay, 0.0 if searching else params.cutoff)
        self.order = order
        self.coefs = self._sorted_transform(filled)
        # Frequency of every stored value (a complex one is stored as two reals).
        self.radii = radii
        self.radius = np.repeat(radii, 2) if self._interleaved else radii
        self.angle = np.repeat(angles, 2) if self._interleaved else angles
        # Parseval: squared coefficient error -> mean squared error per cell.
        n = dem.grid.size
        self.parseval = {"dct": 1.0 / n, "half": 2.0 / n, "full": 1.0 / (n * n)}[self.lay.kind]

    def _sorted_transform(self, filled: np.ndarray) -> np.ndarray:
        return spectrum.forward(filled, self.lay).ravel()[self.order]

    @property
    def refillable(self) -> bool:
        """Whether ``fill='consistent'`` has empty cells to refill."""
        return self.params.fill == "consistent" and not bool(self.mask.all())

    def refilled(self, trial: _Trial) -> _Spectrum:
        """This spectrum with the empty cells refilled from what ``trial`` rebuilds there.

        The decoder never shows empty cells (or shows them rebuilt, with
        ``mask='footprint'``), so any fill is as good as another except in
        bits. Refilling them with the rebuilt map, quantizing again and
        repeating (a Gerchberg-Papoulis iteration) drives the fill towards
        heights the coded spectrum already holds, which needs fewer
        coefficients at the same step than the smooth interpolation.
        """
        out = copy.copy(self)
        data = self.dem.heights - self.trend
        for round_ in range(REFILL_ROUNDS):
            if round_:
                trial = out.trial(trial.cutoff, trial.step)
            out.coefs = out._sorted_transform(np.where(self.mask, data, trial.heights - self.trend))
        return out

    @property
    def _interleaved(self) -> bool:
        return self.lay.kind == "half" and self.params.storage == "quantized"

    def count(self, cutoff: float) -> int:
        return int(np.searchsorted(self.radii, spectrum.radius_limit(self.lay.shape, cutoff) * (1 + 1e-12),
                                   side="right"))

    def reals(self, n: int) -> np.ndarray:
        kept = self.coefs[:n]
        return kept.view(np.float64) if np.iscomplexobj(kept) else kept

    def synthesise(self, values: np.ndarray) -> np.ndarray:
        """Heights (relative to z0) from the first ``len(values)`` sorted coefficients."""
        coefs = np.zeros(self.lay.coef_shape, dtype=values.dtype)
        coefs.ravel()[self.order[: values.size]] = values
        return spectrum.inverse(coefs, self.lay) + self.trend

    def quantized(self, cutoff: float, step: float) -> np.ndarray:
        """The integers a quantized trial at (cutoff, step) codes, without rebuilding the DEM."""
        return coding.quantize(self.reals(self.count(cutoff)), coding.short_step(step), self.params.deadzone)

    def trial(self, cutoff: float, step: float) -> _Trial:
        n = self.count(cutoff)
        step = coding.short_step(step)
        if self.params.storage == "complex64":
            stream = self.coefs[:n].astype(np.complex64)
            decoded = stream.astype(np.complex128)
        else:
            stream = self.quantized(cutoff, step)
            decoded = coding.dequantize(stream, step)
            if np.iscomplexobj(self.coefs):
                decoded = decoded.view(np.complex128)
        heights = self.synthesise(decoded)
        err = (heights - self.dem.heights)[self.mask]
        return _Trial(cutoff, step, stream, heights, float(np.sqrt(np.mean(err * err))), float(np.abs(err).max()))

    def proxy_rmse(self, cutoff: float, step: float) -> float:
        """Whole-grid RMSE predicted in the coefficient domain, without an inverse transform."""
        n = self.count(cutoff)
        reals = self.reals(n)
        dropped = self.reals(self.coefs.size)[reals.size:]
        err = reals - coding.dequantize(coding.quantize(reals, step, self.params.deadzone), step)
        total = float(np.dot(err, err)) + float(np.dot(dropped, dropped))
        return math.sqrt(total * self.parseval)

    def encode(self, trial: _Trial, *, exhaustive: bool = True) -> bytes:
        return self.encode_stream(trial.stream, exhaustive=exhaustive)

    def encode_stream(self, stream: np.ndarray, *, exhaustive: bool = True) -> bytes:
        n = stream.size
        return coding.encode_coefficients(stream, radius=self.radius[:n], angle=self.angle[:n],
                                          coder=self.params.coder, exhaustive=exhaustive)


def _step_for_rmse(spec: _Spectrum, cutoff: float, target: float) -> _Trial | None:
    """The coarsest step at ``cutoff`` whose rebuilt DEM is within ``target`` RMSE (occupied cells)."""
    exact = spec.trial(cutoff, _tiny_step(spec))
    if exact.rmse > target:
        return None
    if spec.params.storage != "quantized":
        return exact  # nothing to choose but the cutoff
    best = exact
    goal = target
    for _ in range(CALIBRATION_ROUNDS):
        lo, hi = _tiny_step(spec), max(target, 1e-9) * 1e4
        for _ in range(STEP_ITERATIONS):
            mid = math.sqrt(lo * hi)
            if spec.proxy_rmse(cutoff, mid) <= goal:
                lo = mid
            else:
                hi = mid
        trial = spec.trial(cutoff, lo)
        if trial.rmse <= target:
            if trial.step > best.step:
                best = trial
            if trial.rmse > 0.97 * target:
                break
        # The proxy counts filled cells too: aim it where this step's proxy would have
        # to be for the occupied cells to meet the target. (Scaling the old goal instead
        # fails when even the finest step's proxy is far above it: the filled cells of a
        # gappy map at a high cutoff can hold more error than the whole target.)
        goal = target * spec.proxy_rmse(cutoff, lo) / max(trial.rmse, 1e-12)
    return best


def _tiny_step(spec: _Spectrum) -> float:
    # Fine enough that quantization is negligible next to any sensible target.
    scale = float(np.abs(spec.reals(min(spec.coefs.size, 1))).max()) if spec.coefs.size else 1.0
    return max(scale, 1.0) * 1e-9 if spec.params.storage == "quantized" else 0.0


def _cutoffs(params: Params, cutoff_given: bool) -> tuple[float, ...]:
    return (params.cutoff,) if cutoff_given else CUTOFF_CANDIDATES


def _residual_step(bound: float) -> float:
    """Quantizer step (metres) of the residual layer that keeps every cell within ``bound``."""
    return 2.0 * bound * (1.0 - GUARANTEE_MARGIN)


def _residual(spec: _Spectrum, trial: _Trial, bound: float) -> tuple[np.ndarray, np.ndarray]:
    """Integers that bring every occupied cell within ``bound`` metres, and the corrected heights.

    One integer per rebuilt cell, row-major; interpolated (footprint) cells
    have no measured height and get 0.
    """
    step = _residual_step(bound)
    err = np.where(spec.mask, spec.dem.heights - trial.heights, 0.0)[spec.kept_cells]
    q = np.round(err / step).astype(np.int64)
    heights = trial.heights.copy()
    heights[spec.kept_cells] += q * step
    return q, heights


def _encode_residual(q: np.ndarray, coder: str) -> bytes:
    flat = np.zeros(q.size)  # one band per chunk: the residual has no frequency
    # Every band layout puts all values in band 0, so there is no layout to choose.
    return coding.encode_coefficients(q, radius=flat, angle=flat, coder=coder, exhaustive=False)


def _decode_residual(blob: Any, count: int) -> np.ndarray:
    flat = np.zeros(count)
    q = coding.decode_coefficients(blob, count, radius=flat, angle=flat)
    if q.dtype.kind != "i" or q.size != count:
        raise CorruptFileError("residual layer is not one integer per rebuilt cell")
    return q


_Choice = tuple[_Trial, bytes, np.ndarray | None, bytes]


def _rate_control(spec: _Spectrum, params: Params, point_count: int, fixed_bytes: int,
                  cutoff_given: bool) -> _Choice:
    """Choose cutoff and step for the target in ``params``; returns trial, coefficients, residual."""
    quantized = params.storage == "quantized"
    best: tuple[int, float, _Trial, bytes, np.ndarray | None, bytes] | None = None
    if params.target_rmse > 0:
        for cutoff in _cutoffs(params, cutoff_given):
            trial = _step_for_rmse(spec, cutoff, params.target_rmse)
            if trial is None:
                continue
            blob = spec.encode(trial, exhaustive=False)
            if best is None or len(blob) < best[0]:
                best = (len(blob), trial.rmse, trial, blob, None, b"")
            elif len(blob) > GIVE_UP_FACTOR * best[0]:
                break  # past the best cutoff: sizes only grow from here
        if best is None:
            raise InvalidInputError(f"target RMSE {params.target_rmse} m cannot be reached")
    elif params.target_max_error > 0:
        bound = params.target_max_error
        steps = [bound * f for f in MAX_ERROR_STEP_FACTORS] if quantized else [0.0]
        for cutoff in _cutoffs(params, cutoff_given):
            for step in steps:
                trial = spec.trial(cutoff, step)
                q, _ = _residual(spec, trial, bound)
                blob = spec.encode(trial, exhaustive=False)
                resid = _encode_residual(q, params.coder)
                size = len(blob) + len(resid)
                if best is None or size < best[0]:
                    best = (size, trial.rmse, trial, blob, q, resid)
    else:  # target_bpp
        budget = int(params.target_bpp * point_count / 8) - fixed_bytes
        if budget <= 0:
            raise InvalidInputError(
                f"target {params.target_bpp} bits/point cannot be reached: the occupancy mask and header (CRS included) "
                f"alone need {8 * fixed_bytes / point_count:.4f} bits/point")
        for cutoff in _cutoffs(params, cutoff_given):
            if quantized:
                # Sizes only: the DEM is rebuilt once, for the step found.
                lo, hi = _tiny_step(spec) * 1e3, 1e4
                found = None
                for _ in range(STEP_ITERATIONS):
                    mid = math.sqrt(lo * hi)
                    blob = spec.encode_stream(spec.quantized(cutoff, mid), exhaustive=False)
                    if len(blob) <= budget:
                        found, hi = (mid, blob), mid
                    else:
                        lo = mid
                if found is None:
                    continue
                trial, blob = spec.trial(cutoff, found[0]), found[1]
            else:
                trial = spec.trial(cutoff, 0.0)
                blob = spec.encode(trial, exhaustive=False)
                if len(blob) > budget:
                    continue
            if best is None or trial.rmse < best[1]:
                best = (len(blob), trial.rmse, trial, blob, None, b"")
        if best is None:
            raise InvalidInputError(f"target {params.target_bpp} bits/point cannot be reached with these settings")
    _, _, trial, _, q, resid = best
    # The search sized candidates with one band layout; the file gets the best per chunk.
    return trial, spec.encode(trial), q, resid


def _rate_control_refilled(spec: _Spectrum, params: Params, point_count: int, fixed_bytes: int,
                           cutoff_given: bool) -> tuple[_Spectrum, _Choice]:
    """Rate control, then (``fill='consistent'``) a second choice at the same cutoff, empty cells refilled.

    For an RMSE target the step is searched again upwards, refilling at each
    step tried: a fill consistent with the coded map lowers the error on the
    occupied cells, so a coarser step meets the target. For the other
    targets the search is repeated on the spectrum refilled at the first
    choice. The better of the two is kept: the smaller file for an error
    target, the more accurate one for a size target.
    """
    first = _rate_control(spec, params, point_count, fixed_bytes, cutoff_given)
    if not spec.refillable:
        return spec, first
    if params.target_rmse > 0:
        if params.storage != "quantized":
            return spec, first  # no step to search
        other, trial = _refilled_for_rmse(spec, first[0], params.target_rmse)
        second: _Choice = (trial, other.encode(trial), None, b"")
    else:
        other = spec.refilled(first[0])
        try:
            second = _rate_control(other, params.replace(cutoff=first[0].cutoff), point_count, fixed_bytes, True)
        except InvalidInputError:
            return spec, first  # nothing at this cutoff meets the target with the new fill

    def size(choice: _Choice) -> int:
        return len(choice[1]) + len(choice[3])

    better = second[0].rmse < first[0].rmse if params.target_bpp > 0 else size(second) < size(first)
    return (other, second) if better else (spec, first)


def _refilled_for_rmse(spec: _Spectrum, first: _Trial, target: float) -> tuple[_Spectrum, _Trial]:
    """The coarsest step from ``first.step`` up to :data:`REFILL_STEP_RANGE` times it whose
    refilled map meets ``target`` (``first`` itself when even its own step does not)."""

    def attempt(base: _Trial) -> tuple[_Spectrum, _Trial]:
        other = spec.refilled(base)
        return other, other.trial(base.cutoff, base.step)

    best = attempt(first)
    if best[1].rmse > target:
        return spec, first
    lo, hi = first.step, first.step * REFILL_STEP_RANGE
    for _ in range(REFILL_STEP_ITERATIONS):
        mid = math.sqrt(lo * hi)
        found = attempt(spec.trial(first.cutoff, mid))
        if found[1].rmse <= target:
            best, lo = found, mid
        else:
            hi = mid
    return best


def encode_dem(dem: DEM, params: Params, *, point_count: int | None = None,
               crs: dict[str, Any] | None = None, on_stage: Stage = _noop,
               cutoff_given: bool = True) -> bytes:
    """Code an already gridded DEM (e.g. a GeoTIFF) with ``params``.

    Parameters
    ----------
    dem : DEM
        Heights relative to ``dem.grid.z0`` (metres) and occupancy.
    params : Params
        With a target set, rate control chooses ``cutoff`` (unless
        ``cutoff_given``) and ``step``.
    point_count : int, optional
        Points of the original cloud (for bits per point); default: occupied cells.
    cutoff_given : bool
        Whether ``params.cutoff`` was chosen by the user (rate control then
        only chooses the step).
    """
    if not dem.mask.any():
        raise InvalidInputError("the map has no occupied cell")
    point_count = int(dem.mask.sum()) if point_count is None else point_count
    on_stage("spectrum")
    spec = _Spectrum(dem, params, searching=params.has_target and not cutoff_given)
    mask_blob = occupancy.encode_mask(spec.kept_cells)

    on_stage("encode")
    floor = dem.gridding_rmse or 0.0
    if not params.has_target:
        step = params.step
        if params.storage == "quantized" and step == 0.0:
            target = max(QUANT_FLOOR_FRACTION * floor, MIN_QUANT_RMSE)
            step = coding.choose_step(spec.reals(spec.count(params.cutoff)), target_rmse=target,
                                      n_cells=dem.grid.size, deadzone=params.deadzone)
        # No refill without a target: at a fixed step it lowers the error by a
        # few per cent rather than the size, for two more transforms.
        trial = spec.trial(params.cutoff, step)
        return _finish(spec, params.replace(step=trial.step), trial, spec.encode(trial), None, b"", mask_blob,
                       point_count, crs, on_stage)
    # Rate control. For a size target the header's own bytes count too: start
    # from an estimate, then shrink the budget by any overshoot.
    overhead = len(mask_blob) + HEADER_ESTIMATE
    for _ in range(BUDGET_ROUNDS):
        chosen, (trial, coef_blob, q_resid, resid_blob) = _rate_control_refilled(
            spec, params, point_count, overhead, cutoff_given)
        data = _finish(chosen, params.replace(cutoff=trial.cutoff, step=trial.step), trial, coef_blob, q_resid,
                       resid_blob, mask_blob, point_count, crs, on_stage)
        if params.target_bpp <= 0 or 8 * len(data) <= params.target_bpp * point_count:
            return data
        # Measured now: everything but the coefficients, plus room for the
        # statistics' digits to change with the next candidate.
        overhead = len(data) - len(coef_blob) - len(resid_blob) + STATS_SLACK
    raise InvalidInputError(f"target {params.target_bpp} bits/point cannot be met with these settings")


def _finish(spec: _Spectrum, params: Params, trial: _Trial, coef_blob: bytes, q_resid: np.ndarray | None,
            resid_blob: bytes, mask_blob: bytes, point_count: int, crs: dict[str, Any] | None,
            on_stage: Stage) -> bytes:
    """Measure what the decoder will rebuild and pack the file with those figures."""
    dem, occupied = spec.dem, spec.mask
    floor = dem.gridding_rmse or 0.0
    heights = trial.heights
    if q_resid is not None:
        _, heights = _residual(spec, trial, params.target_max_error)
    err = (heights - dem.heights)[occupied]
    stats: dict[str, Any] = {
        "dem_rmse_m": float(np.sqrt(np.mean(err * err))),
        "dem_max_error_m": float(np.abs(err).max()),
        "gridding_rmse_m": floor,
        "mask_bytes": len(mask_blob),
        "coef_bytes": len(coef_blob),
        "residual_bytes": len(resid_blob),
        "cells_interpolated": int(spec.kept_cells.sum()) - int(occupied.sum()),
    }
    spread = getattr(dem, "spread", None)
    if spread is not None and spread.unrepresented_points:
        # Walls, overhangs, vegetation: what one height per cell could not hold.
        # Two figures say it; the rest of DEM.spread would cost a small map
        # more header than its coefficients.
        full = spread.as_stats()
        stats.update({key: full[key] for key in SPREAD_STATS})
    if dem.counts is not None and params.aggregate == "mean":
        # Per cell, points scatter about their mean, so the errors add in quadrature.
        weighted = float(np.sum(dem.counts[occupied] * err * err)) / max(int(dem.counts.sum()), 1)
        stats["vertical_rmse_m"] = math.sqrt(floor * floor + weighted)
    header = Header(grid=dem.grid, params=params, point_count=point_count, cell_count=int(spec.kept_cells.sum()),
                    plane=spec.plane, crs=crs or {}, stats=stats, coef_count=spec.count(params.cutoff))
    on_stage("container")
    return pack(header, mask_blob, coef_blob, resid_blob)


def decode_dem(header: Header, blobs: dict[bytes, Any], *, cutoff: float | None = None,
               allow_partial: bool = False) -> DEM:
    """Rebuild the DEM of a parsed file.

    Parameters
    ----------
    header : Header
    blobs : dict
        Coded sections from :func:`dftpcc.container.unpack`.
    cutoff : float, optional
        Decode with a larger cutoff than the file was made with (fewer
        coefficients, coarser map). Must be at least the file's cutoff.
    allow_partial : bool
        Accept a truncated coefficient section and decode its whole chunks.
    """
    params, grid = header.params, header.grid
    mask = occupancy.decode_mask(blobs[b"MASK"], grid.shape)
    if int(mask.sum()) != header.cell_count:
        raise CorruptFileError("occupancy mask disagrees with the header's cell count")
    lay = spectrum.layout(params.transform, params.storage, grid.shape)
    n = spectrum.kept_count(lay, params.cutoff)
    if n != header.coef_count:
        raise CorruptFileError("coefficient count disagrees with the grid and cutoff")
    order, radii, angles = spectrum.kept_order(lay, params.cutoff)
    per_coef = 2 if (lay.kind == "half" and params.storage == "quantized") else 1
    radius, angle = np.repeat(radii[:n], per_coef), np.repeat(angles[:n], per_coef)
    stream = coding.decode_coefficients(blobs[b"COEF"], n * per_coef, radius=radius, angle=angle,
                                        allow_partial=allow_partial)
    if stream.size == 0:  # a prefix too short for one whole chunk: the map is its trend
        values = np.zeros(0, dtype=np.complex128 if lay.kind != "dct" else np.float64)
    elif params.storage == "quantized":
        if stream.dtype.kind != "i":
            raise CorruptFileError("quantized file holds float coefficients")
        values = coding.dequantize(stream[: stream.size - stream.size % per_coef], params.step)
        if per_coef == 2:
            values = values.view(np.complex128)
    else:
        if stream.dtype.kind != "c":
            raise CorruptFileError("complex64 file holds integer coefficients")
        values = stream
    if cutoff is not None:
        if not 0.0 <= cutoff < 1.0:
            raise InvalidInputError(f"cutoff must be in [0, 1), got {cutoff!r}")
        if cutoff < params.cutoff:
            raise InvalidInputError(
                f"cannot decode at cutoff {cutoff}: the file keeps only frequencies up to cutoff {params.cutoff}")
        values = values[: spectrum.kept_count(lay, cutoff)]
    if lay.kind == "dct":  # only the low-frequency corner: the inverse pads it with zeros
        shape, where = spectrum.corner(lay, order[: values.size])
    else:
        shape, where = lay.coef_shape, order[: values.size]
    coefs = np.zeros(shape, dtype=values.dtype)
    coefs.ravel()[where] = values
    heights = spectrum.inverse(coefs, lay)
    if params.detrend == "plane":
        heights += plane_values(header.plane, grid.shape)
    complete = values.size == n and cutoff is None
    if b"RESD" in blobs and complete:
        # The residual layer only applies to the full-resolution map it was computed for.
        q = _decode_residual(blobs[b"RESD"], int(mask.sum()))
        heights[mask] += q * _residual_step(params.target_max_error)
    if not np.isfinite(heights).all() and not np.isfinite(heights[mask]).all():
        raise CorruptFileError("coefficients decode to non-finite heights (damaged or crafted file)")
    return DEM(grid=grid, heights=heights, mask=mask)


def decompress(data: bytes, *, max_bytes: int | None = None, cutoff: float | None = None) -> np.ndarray:
    """Decode ``.dftpc`` bytes into a point cloud.

    Parameters
    ----------
    data : bytes
    max_bytes : int, optional
        Use only the first ``max_bytes`` bytes (progressive decoding: a
        prefix holds the low frequencies).
    cutoff : float, optional
        Decode-time cutoff, at least the file's.

    Returns
    -------
    ndarray, shape (cells, 3), float64
        One point per occupied cell, metres, original frame.
    """
    if max_bytes is not None:
        if max_bytes <= 0:
            raise InvalidInputError(f"max_bytes must be positive, got {max_bytes}")
        data = data[:max_bytes]
    header, blobs = unpack(data, allow_truncated_coef=max_bytes is not None)
    dem = decode_dem(header, blobs, cutoff=cutoff, allow_partial=max_bytes is not None)
    return dem_to_points(dem)
