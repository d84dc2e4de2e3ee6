"""The whole pipeline: points -> DEM -> spectrum -> coded bytes, and back.

``compress`` and ``decompress`` are the two calls most users need; the
stages they compose live in ``grid``, ``spectrum``, ``coding``,
``container`` and ``rebuild``.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from . import coding, spectrum
from .container import Header, pack, unpack
from .errors import CorruptFileError, InvalidInputError
from .grid import DEM, auto_resolution, fill_empty, fit_grid, fit_plane, plane_values, rasterize
from .params import Params, make_params
from .rebuild import dem_to_points

__all__ = ["compress", "decompress", "encode_dem", "decode_dem", "resolve_params"]

#: With an automatic step, quantization may add this fraction of the
#: gridding error (RMS, metres) to the rebuilt DEM ...
QUANT_FLOOR_FRACTION = 0.5
#: ... but never less than this, for DEMs gridded from one point per cell.
MIN_QUANT_RMSE = 0.001

Stage = Callable[[str], None]


def _noop(_: str) -> None:
    pass


def resolve_params(points: np.ndarray, *, resolution: float | str = "auto", cutoff: float = 0.8,
                   profile: str = "compact", **options: Any) -> Params:
    """:class:`Params` for ``points``, choosing the resolution when it is ``"auto"``."""
    if isinstance(resolution, str):
        if resolution != "auto":
            raise InvalidInputError(f"resolution must be a number of metres or 'auto', got {resolution!r}")
        resolution = auto_resolution(points)
    return make_params(resolution=resolution, cutoff=cutoff, profile=profile, **options)


def compress(points: np.ndarray, *, resolution: float | str = "auto", cutoff: float = 0.8,
             profile: str = "compact", crs: dict[str, Any] | None = None,
             on_stage: Stage = _noop, **options: Any) -> bytes:
    """Compress a terrain point cloud into ``.dftpc`` bytes.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        x, y, z in metres; float64 keeps coordinates of 1e7 m exact.
    resolution : float or 'auto'
        DEM cell size in metres; ``auto`` aims at a few points per cell.
    cutoff : float
        Cutoff ratio f_c = 1 - r/r_M in [0, 1) (paper eq. 2).
    profile : {'compact', 'paper'}
        ``paper`` stores the raw complex DFT coefficients inside the circle
        exactly as the paper does; ``compact`` (default) detrends, uses the
        mirrored (DCT) transform, quantizes and entropy-codes.
    crs : dict, optional
        Coordinate reference system to carry along (see :mod:`dftpcc.formats`).
    on_stage : callable, optional
        Called with the name of each stage as it starts (progress display).
    **options
        Any other :class:`~dftpcc.params.Params` field (``step``,
        ``aggregate``, ``frame``, ``transform``, ``fill``, ...).

    Returns
    -------
    bytes

    Raises
    ------
    InvalidInputError
        Empty or non-finite cloud, bad parameter, grid too large.
    """
    on_stage("grid")
    points = np.asarray(points)
    params = resolve_params(points, resolution=resolution, cutoff=cutoff, profile=profile, **options)
    grid = fit_grid(points, params.resolution, frame=params.frame)
    dem = rasterize(points, grid, aggregate=params.aggregate)
    return encode_dem(dem, params, point_count=int(points.shape[0]), crs=crs, on_stage=on_stage)


def encode_dem(dem: DEM, params: Params, *, point_count: int | None = None,
               crs: dict[str, Any] | None = None, on_stage: Stage = _noop) -> bytes:
    """Code an already gridded DEM (e.g. a GeoTIFF) with ``params``.

    Parameters
    ----------
    dem : DEM
        Heights relative to ``dem.grid.z0`` (metres) and occupancy.
    params : Params
    point_count : int, optional
        Points of the original cloud (for bits per point); default: occupied cells.
    """
    if not dem.mask.any():
        raise InvalidInputError("the map has no occupied cell")
    mask = dem.mask
    n_occupied = int(mask.sum())
    point_count = n_occupied if point_count is None else point_count
    on_stage("spectrum")
    plane = fit_plane(dem) if params.detrend == "plane" else (0.0, 0.0, 0.0)
    trend = plane_values(plane, dem.grid.shape) if params.detrend == "plane" else 0.0
    filled = fill_empty(dem.heights - trend, mask, method=params.fill)
    lay = spectrum.layout(params.transform, params.storage, dem.grid.shape)
    order = spectrum.kept_order(lay, params.cutoff)
    kept = spectrum.forward(filled, lay).ravel()[order]

    on_stage("encode")
    floor = dem.gridding_rmse or 0.0
    if params.storage == "complex64":
        stream = kept.astype(np.complex64)
        decoded = stream.astype(np.complex128)
    else:
        reals = _as_reals(kept)
        step = params.step
        if step == 0.0:
            target = max(QUANT_FLOOR_FRACTION * floor, MIN_QUANT_RMSE)
            step = coding.choose_step(reals, target_rmse=target, n_cells=dem.grid.size,
                                      deadzone=params.deadzone)
            params = params.replace(step=step)
        stream = coding.quantize(reals, step, params.deadzone)
        decoded = _from_reals(coding.dequantize(stream, step), lay)
    coef_blob = coding.encode_coefficients(stream)
    mask_blob = coding.encode_mask(mask)

    # Measure what the decoder will rebuild, so the file states its own error.
    rebuilt = _synthesise(decoded, order, lay) + trend
    err = (rebuilt - dem.heights)[mask]
    stats: dict[str, Any] = {
        "dem_rmse_m": float(np.sqrt(np.mean(err * err))),
        "dem_max_error_m": float(np.abs(err).max()),
        "gridding_rmse_m": floor,
        "mask_bytes": len(mask_blob),
        "coef_bytes": len(coef_blob),
    }
    if dem.counts is not None and params.aggregate == "mean":
        # Per cell, points scatter about their mean, so the errors add in quadrature.
        weighted = float(np.sum(dem.counts[mask] * err * err)) / max(int(dem.counts.sum()), 1)
        stats["vertical_rmse_m"] = math.sqrt(floor * floor + weighted)
    header = Header(grid=dem.grid, params=params, point_count=point_count, cell_count=n_occupied,
                    plane=plane, crs=crs or {}, stats=stats, coef_count=int(order.size))
    on_stage("container")
    return pack(header, mask_blob, coef_blob)


def _as_reals(kept: np.ndarray) -> np.ndarray:
    """Real values to quantize: a complex coefficient becomes (real, imag)."""
    if np.iscomplexobj(kept):
        return kept.view(np.float64).copy()
    return kept


def _from_reals(values: np.ndarray, lay: spectrum.Layout) -> np.ndarray:
    if lay.kind == "dct":
        return values
    return values.view(np.complex128)


def _synthesise(kept: np.ndarray, order: np.ndarray, lay: spectrum.Layout) -> np.ndarray:
    coefs = np.zeros(lay.coef_shape, dtype=kept.dtype if np.iscomplexobj(kept) else np.float64)
    coefs.ravel()[order[: kept.size]] = kept
    return spectrum.inverse(coefs, lay)


def decode_dem(header: Header, mask_blob: bytes | memoryview, coef_blob: bytes | memoryview,
               *, cutoff: float | None = None, allow_partial: bool = False) -> DEM:
    """Rebuild the DEM of a parsed file.

    Parameters
    ----------
    cutoff : float, optional
        Decode with a larger cutoff than the file was made with (fewer
        coefficients, coarser map). Must be at least the file's cutoff.
    allow_partial : bool
        Accept a truncated coefficient section and decode its whole chunks.
    """
    params, grid = header.params, header.grid
    mask = coding.decode_mask(mask_blob, grid.shape)
    if int(mask.sum()) != header.cell_count:
        raise CorruptFileError("occupancy mask disagrees with the header's cell count")
    lay = spectrum.layout(params.transform, params.storage, grid.shape)
    order = spectrum.kept_order(lay, params.cutoff)
    if order.size != header.coef_count:
        raise CorruptFileError("coefficient count disagrees with the grid and cutoff")
    per_coef = 2 if (lay.kind == "half" and params.storage == "quantized") else 1
    stream = coding.decode_coefficients(coef_blob, order.size * per_coef, allow_partial=allow_partial)
    if params.storage == "quantized":
        if stream.dtype.kind != "i":
            raise CorruptFileError("quantized file holds float coefficients")
        values = _from_reals(coding.dequantize(stream[: stream.size - stream.size % per_coef], params.step), lay)
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
        values = values[: spectrum.kept_order(lay, cutoff).size]
    heights = _synthesise(values, order, lay)
    if params.detrend == "plane":
        heights += plane_values(header.plane, grid.shape)
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
    header, mask_blob, coef_blob = unpack(data, allow_truncated_coef=max_bytes is not None)
    dem = decode_dem(header, mask_blob, coef_blob, cutoff=cutoff, allow_partial=max_bytes is not None)
    return dem_to_points(dem)
