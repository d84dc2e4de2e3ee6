"""Decode stage: a parsed ``.dftpc`` becomes a DEM again.

The decoder derives the coefficient order, count and interleaving from the
grid's shape and the cutoff alone (:mod:`dftpcc.spectrum`, shared with the
encoder), decodes the mask and the coefficients, inverts the transform, adds
the plane back and, for a complete file, the residual layer.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from . import coding, occupancy, spectrum
from .container import Header, check_max_bytes, unpack
from .dem import DEM
from .errors import CorruptFileError, InvalidInputError
from .fill import plane_values
from .params import check_cutoff
from .rebuild import dem_to_points
from .residual import decode_residual, residual_step

__all__ = ["decode_dem", "decompress"]


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
    if cutoff is not None:
        check_cutoff(cutoff)
        if cutoff < params.cutoff:
            raise InvalidInputError(
                f"cannot decode at cutoff {cutoff}: the file keeps only frequencies up to cutoff {params.cutoff}")
    mask = occupancy.decode_mask(blobs[b"MASK"], grid.shape)
    if int(mask.sum()) != header.cell_count:
        raise CorruptFileError("occupancy mask disagrees with the header's cell count")
    lay = spectrum.layout(params.transform, params.storage, grid.shape)
    n = spectrum.kept_count(lay, params.cutoff)
    if n != header.coef_count:
        raise CorruptFileError("coefficient count disagrees with the grid and cutoff")
    order, radii, angles = spectrum.kept_order(lay, params.cutoff)
    per_coef = spectrum.values_per_coefficient(lay, params.storage)
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
        q = decode_residual(blobs[b"RESD"], int(mask.sum()))
        heights[mask] += q * residual_step(params.target_max_error)
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
    check_max_bytes(max_bytes)
    if max_bytes is not None:
        data = data[:max_bytes]
    header, blobs = unpack(data, allow_truncated_coef=max_bytes is not None)
    return dem_to_points(decode_dem(header, blobs, cutoff=cutoff, allow_partial=max_bytes is not None))
