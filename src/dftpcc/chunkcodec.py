"""One chunk of a raster DEM as a ``.dftpc`` stream, with a maximum error in metres.

The shared core of the numcodecs codec (:mod:`dftpcc.numcodecs_codec`) and
the Zarr v3 codec (:mod:`dftpcc.zarr_codec`): a 2D chunk becomes a DEM on a
unit grid and is coded by :func:`dftpcc.encoder.encode_dem` with a maximum-error
target, so every decoded cell is within the bound of the stored value. It
needs neither zarr nor numcodecs.

No data
    NaN cells and cells equal to the array's fill value are no data: they are
    left out of the map's mask and decode to the fill value (NaN when there is
    none), exactly. Zarr pads a partial edge chunk with the fill value, so the
    padding costs only its share of the mask. A float chunk with NaN cells in
    an array whose fill value is a number is refused: both would decode to the
    same value. Choose a fill value outside the heights' range (NaN, -32768): a
    valid height within the bound of it may decode to it, and readers would
    take that cell for no data. A chunk with no data at all is coded as a 16-byte
    :data:`NO_DATA_MAGIC` record (magic, then rows and columns as u32 LE).

Data types and the bound
    Floats (float16 to float64) decode to their own dtype within ``max_error``
    metres: the map is coded to a slightly tighter bound (:func:`coding_bound`)
    so that rounding to the dtype cannot exceed it. Integers (int8 .. uint64)
    are coded to within ``k + 0.5`` with ``k = floor(max_error)`` and rounded
    on decode, which leaves an error of at most ``k`` (whole units); a bound
    below 1 therefore makes an integer chunk lossless. A bound the arithmetic cannot
    keep (a subnormal one that halves to 0) is refused, and every coded chunk is
    decoded and compared with the array before it is returned: a chunk beyond its
    bound is an error, never a write.

Chunk size
    A chunk has at most :data:`MAX_CHUNK_CELLS` cells (2048 x 2048): coding time
    grows faster than the chunk, so a larger one is refused with the reason
    (the Zarr codec refuses it when the array is created).

Threads
    Zarr codes chunks in threads, and so may the codec: the encoder keeps no
    zstd compressor between calls (zstandard's are not thread-safe) and the
    coefficient-order cache of :mod:`dftpcc.spectrum` is locked.
"""

from __future__ import annotations

import math
import struct
from typing import Any

import numpy as np

from . import mapfile
from ._optional import install_hint
from .dem import DEM, Grid
from .encoder import encode_dem
from .errors import CorruptFileError, DftpccError, InvalidInputError, ResourceLimitError
from .limits import MAX_CELLS, cell_budget
from .params import PROFILES, Params, check_cutoff, make_params
from .residual import GUARANTEE_MARGIN

__all__ = ["NO_DATA_MAGIC", "INSTALL_HINT", "MAX_CHUNK_CELLS", "check_chunk_shape", "chunk_params", "coding_bound", "encode_chunk", "decode_chunk",
           "no_data_value", "check_dtype"]

INSTALL_HINT = install_hint("zarr")
#: First bytes of the record of a chunk without a single valid cell (a ``.dftpc``
#: stream needs one); distinct from the ``.dftpc`` magic ``\\x89DFTPC\\r\\n``.
NO_DATA_MAGIC = b"\x89DFTPC\x00\x00"
_NO_DATA = struct.Struct("<8sII")
#: Data types the codec stores: ``f`` floats, ``i``/``u`` integers of any width.
_KINDS = "fiu"
_FLOAT64_BYTES = 8
#: The largest chunk the codec codes, cells (2048 x 2048): rate control's cost grows faster than the
#: chunk (1024 x 1024 took 5.5 s, 2048 x 2048 39.5 s and 1.5 GB, 4096 x 4096 did not finish in 9 min;
#: issue 41), so a larger chunk is refused rather than left to run for an unknown time.
MAX_CHUNK_CELLS = 1 << 22


def check_dtype(dtype: Any) -> np.dtype:
    """``dtype`` as a numpy dtype if the codec can store it (real floats, integers), else a clear error."""
    dt = np.dtype(dtype)
    # Heights are coded in float64: a wider float (longdouble) would come back rounded to it.
    if dt.kind not in _KINDS or (dt.kind == "f" and dt.itemsize > _FLOAT64_BYTES):
        raise InvalidInputError(f"dftpcc stores heights as floats (up to float64) or integers; got dtype {dt} "
                                f"(cast the array to float32 or float64 first)")
    return dt


def check_chunk_shape(shape: tuple[int, ...]) -> None:
    """Refuse a chunk of more than :data:`MAX_CHUNK_CELLS` cells, with the reason and what to do."""
    if math.prod(shape) > MAX_CHUNK_CELLS:
        raise InvalidInputError(
            f"chunks of {' x '.join(map(str, shape))} cells are more than the {MAX_CHUNK_CELLS:,} (2048 x 2048) dftpcc "
            f"codes in one chunk: coding time grows faster than the chunk (2048 x 2048 takes about 40 s and 1.5 GB, "
            f"4096 x 4096 more than 9 minutes); use smaller chunks, such as 512 x 512")


def chunk_params(max_error: Any, *, cell_size: Any = 1.0, profile: str = "compact",
                 cutoff: float | None = None) -> Params:
    """The codec's configuration checked and turned into :class:`~dftpcc.params.Params`.

    Parameters
    ----------
    max_error : float
        Largest error allowed on any valid cell, in the array's height unit (metres).
    cell_size : float
        Width of a cell in metres; the transform is the same for any size, but
        the file records it.
    profile : str
        A :data:`~dftpcc.params.PROFILES` name.
    cutoff : float, optional
        Cutoff ratio in [0, 1); by default rate control chooses it per chunk.

    Raises
    ------
    InvalidInputError
        A value out of range.
    """
    if isinstance(max_error, bool) or not (isinstance(max_error, (int, float)) and math.isfinite(max_error)
                                           and max_error > 0):
        raise InvalidInputError(f"max_error must be a positive number of metres, got {max_error!r}")
    if profile not in PROFILES:
        raise InvalidInputError(f"profile must be one of {', '.join(PROFILES)}; got {profile!r}")
    if cutoff is not None:
        check_cutoff(cutoff)
    return make_params(resolution=cell_size, profile=profile, cutoff=cutoff, target_max_error=float(max_error))


def no_data_value(dtype: np.dtype, fill_value: Any) -> float | int | None:
    """What no-data cells of a ``dtype`` array hold: the fill value, NaN for a float array
    without one, None for an integer array without one (every cell is data)."""
    if fill_value is None:
        return math.nan if dtype.kind == "f" else None
    value = np.asarray(fill_value).astype(dtype).item() if dtype.kind != "f" else float(fill_value)
    return value


def coding_bound(max_error: float, values: np.ndarray) -> float:
    """The bound (metres) the map is coded to, so ``values.dtype`` holds the decoded heights within ``max_error``.

    An integer cell decoded within ``k + 0.5`` rounds to within ``k = floor(max_error)``.
    A float cell ``h`` decoded to ``d`` is rounded to the nearest value ``r`` of its dtype;
    ``h`` is one, so ``|r - d| <= min(|h - d|, s / 2)`` with ``s`` the dtype's spacing at
    the largest height: coding within ``max(max_error - s / 2, max_error / 2)`` keeps
    ``|r - h| <= max_error``.
    """
    if values.dtype.kind in "iu":
        return (math.floor(max_error) + 0.5) * (1.0 - GUARANTEE_MARGIN)
    largest = float(np.max(np.abs(values))) if values.size else 0.0
    spacing = float(np.spacing(values.dtype.type(largest + max_error)))
    bound = max(max_error - spacing / 2.0, max_error / 2.0)
    if not bound > 0:  # a subnormal max_error halves to 0, which would mean "no target" to the encoder
        raise InvalidInputError(f"max_error {max_error!r} is too fine for float arithmetic: the map would be coded "
                                f"to a bound of {bound!r} (no bound at all); give at least {2 * math.ulp(0.0)!r}")
    return bound


def _valid_cells(values: np.ndarray, nodata: float | int | None) -> np.ndarray:
    """Cells holding data; refuses what the codec cannot give back exactly (see the module notes)."""
    if values.dtype.kind != "f":
        return np.ones(values.shape, bool) if nodata is None else values != nodata
    nan = np.isnan(values)
    if nodata is not None and not math.isnan(nodata):
        if nan.any():
            raise InvalidInputError(
                f"{int(nan.sum())} cell(s) of the chunk are NaN but the array's fill value is {nodata!r}: both would "
                f"read back as {nodata!r}; create the array with fill_value=nan (or replace the NaN cells)")
        valid = values != nodata
    else:
        valid = ~nan
    if not np.isfinite(values[valid]).all():
        raise InvalidInputError("the chunk holds infinite heights; dftpcc stores finite heights and NaN as no data")
    return valid


def encode_chunk(values: Any, params: Params, *, fill_value: Any = None) -> bytes:
    """Code one 2D chunk.

    Parameters
    ----------
    values : array_like, shape (rows, cols), float or integer
        Heights in metres (the array's unit).
    params : Params
        From :func:`chunk_params`; ``target_max_error`` is the bound in metres.
    fill_value : scalar, optional
        The array's fill value: cells equal to it (and NaN cells) are no data.

    Returns
    -------
    bytes
        A ``.dftpc`` stream, or a :data:`NO_DATA_MAGIC` record when no cell holds data.

    Raises
    ------
    InvalidInputError
        Not 2D, larger than :data:`MAX_CHUNK_CELLS`, an unsupported dtype, infinite
        heights, NaN cells with a numeric fill value, or a bound too fine for the heights.
    """
    values = np.asarray(values)
    check_dtype(values.dtype)
    if values.ndim != 2 or values.size == 0:
        raise InvalidInputError(f"dftpcc codes 2D chunks (rows, cols) of a DEM; got a chunk of shape {values.shape}")
    check_chunk_shape(values.shape)
    valid = _valid_cells(values, no_data_value(values.dtype, fill_value))
    rows, cols = values.shape
    if not valid.any():
        return _NO_DATA.pack(NO_DATA_MAGIC, rows, cols)
    heights = values.astype(np.float64)
    z0 = float(heights[valid].mean())
    bound = coding_bound(params.target_max_error, values[valid])
    grid = Grid(x0=0.0, y0=0.0, z0=z0, resolution=float(params.resolution), rows=rows, cols=cols)
    dem = DEM(grid, np.where(valid, heights - z0, 0.0), valid)
    data = encode_dem(dem, params.replace(target_max_error=bound))
    # The promise is checked, not assumed: the chunk is decoded as a reader will and every valid cell
    # compared (a bound that rounded to "no target" once gave a chunk 28 m off without a word).
    _check_bound(decode_chunk(data, values.dtype, fill_value=fill_value, shape=values.shape), values, valid,
                 params.target_max_error)
    return data


def _check_bound(decoded: np.ndarray, values: np.ndarray, valid: np.ndarray, max_error: float) -> None:
    """Raise if a decoded chunk's valid cells are not within ``max_error`` (metres; whole units of an integer dtype)."""
    allowed = math.floor(max_error) if values.dtype.kind in "iu" else max_error
    error = float(np.abs(decoded[valid].astype(np.float64) - values[valid].astype(np.float64)).max())
    # The float64 difference of two nearby heights is exact (Sterbenz); an ulp of slack covers the rest.
    if not error <= allowed + math.ulp(allowed):
        raise DftpccError(f"the coded chunk is {error!r} m off the array at worst, beyond its max_error of "
                          f"{max_error!r} m: not written (a dftpcc bug; please report it with the chunk)")


def decode_chunk(data: Any, dtype: Any, *, fill_value: Any = None, shape: tuple[int, ...] | None = None,
                 max_cells: int | None = None) -> np.ndarray:
    """Decode one chunk coded by :func:`encode_chunk`.

    Parameters
    ----------
    data : bytes-like
        The coded chunk.
    dtype : dtype
        The array's dtype, which the result has.
    fill_value : scalar, optional
        The array's fill value, given to no-data cells (NaN for floats by default).
    shape : tuple of int, optional
        The chunk shape expected; a stream of another shape is corrupt.
    max_cells : int, optional
        Largest chunk (cells) to accept; default ``prod(shape)``, else the
        budget of :func:`dftpcc.open` (:func:`~dftpcc.limits.cell_budget` of the chunk's size).

    Returns
    -------
    ndarray, shape (rows, cols), ``dtype``

    Raises
    ------
    CorruptFileError
        Not a coded chunk, or not of ``shape``.
    """
    dt = check_dtype(dtype)
    data = bytes(data)
    nodata = no_data_value(dt, fill_value)
    if max_cells is None and shape is not None:
        max_cells = math.prod(shape)
    if data[:len(NO_DATA_MAGIC)] == NO_DATA_MAGIC:
        if len(data) != _NO_DATA.size:
            raise CorruptFileError(f"a no-data chunk record is {_NO_DATA.size} bytes, got {len(data)}")
        _, rows, cols = _NO_DATA.unpack(data)
        _check_shape((rows, cols), shape, cell_budget(len(data)) if max_cells is None else max_cells)
        if nodata is None:
            raise CorruptFileError("a no-data chunk in an integer array without a fill value")
        return np.full((rows, cols), nodata, dtype=dt)
    dem = mapfile.open(data, max_cells=None if max_cells is None else max(1, max_cells)).read_dem()
    _check_shape(dem.grid.shape, shape, MAX_CELLS if max_cells is None else max_cells)
    if nodata is None and not dem.mask.all():
        raise CorruptFileError("a chunk with no-data cells in an integer array without a fill value")
    heights = dem.grid.z0 + dem.heights
    if dt.kind in "iu":
        info = np.iinfo(dt)
        # The stored value is in range, so clipping never moves a cell away from it.
        heights = np.clip(np.rint(heights), info.min, info.max)
    out = heights.astype(dt)
    if not dem.mask.all():
        out[~dem.mask] = nodata
    return out


def _check_shape(found: tuple[int, int], expected: tuple[int, ...] | None, max_cells: int) -> None:
    if expected is not None and tuple(found) != tuple(expected):
        raise CorruptFileError(f"the coded chunk is {found[0]} x {found[1]} cells; the array's chunks are "
                               f"{' x '.join(map(str, expected))}")
    if found[0] * found[1] > max_cells:
        raise ResourceLimitError(f"the coded chunk is {found[0]} x {found[1]} cells, more than the {max_cells:,} allowed")
