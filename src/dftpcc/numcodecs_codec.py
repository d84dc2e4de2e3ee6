"""dftpcc as a numcodecs codec: :class:`Dftpcc`, ``codec_id = "dftpcc"``.

For Zarr format 2 arrays (``compressor=Dftpcc(...)``), tifffile, kerchunk and
anything else that takes a numcodecs codec; registered under the
``numcodecs.codecs`` entry point, so ``numcodecs.get_codec({"id": "dftpcc", ...})``
finds it once dftpcc is installed. The chunk is coded by
:mod:`dftpcc.chunkcodec` (no data, dtypes and the bound are described there).
Zarr format 3 arrays use :class:`dftpcc.zarr_codec.DftpccCodec`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ._optional import import_optional
from .chunkcodec import check_dtype, chunk_params, decode_chunk, encode_chunk
from .errors import InvalidInputError

import_optional("numcodecs.abc", "zarr", needed_for="the numcodecs codec")

from numcodecs.abc import Codec  # noqa: E402
from numcodecs.compat import ndarray_copy  # noqa: E402
from numcodecs.registry import register_codec  # noqa: E402

__all__ = ["Dftpcc"]


class Dftpcc(Codec):
    """Lossy DEM codec with a maximum error in metres, for numcodecs.

    Parameters
    ----------
    max_error : float
        Largest error on any valid cell, in the array's height unit (metres);
        for integer arrays, ``floor(max_error)`` whole units (lossless below 1).
    dtype : str or dtype
        The chunks' dtype (float or integer). numcodecs decodes a byte string
        without knowing the array, so the codec carries it, as imagecodecs' SZ3 does.
    fill_value : float or int, optional
        Cells equal to it are no data and decode to it exactly; NaN cells of a
        float array always are (and decode to NaN when no fill value is given).
    cell_size : float
        Width of a cell in metres (recorded in each chunk's header).
    profile : str
        dftpcc profile (``compact`` or ``paper``).
    cutoff : float, optional
        Cutoff ratio in [0, 1); default: chosen per chunk by rate control.

    Notes
    -----
    ``encode`` needs the chunk as a 2D array (zarr format 2 passes it so); a flat
    buffer has lost the shape and is refused.
    """

    codec_id = "dftpcc"

    def __init__(self, *, max_error: float, dtype: Any, fill_value: float | int | None = None,
                 cell_size: float = 1.0, profile: str = "compact", cutoff: float | None = None) -> None:
        self._params = chunk_params(max_error, cell_size=cell_size, profile=profile, cutoff=cutoff)
        self.max_error = float(max_error)
        self.dtype = check_dtype(dtype).str
        # NaN is what "no fill value" already means for floats, and JSON has no NaN.
        if fill_value is not None and isinstance(fill_value, float) and math.isnan(fill_value):
            fill_value = None
        if fill_value is not None and not isinstance(fill_value, (int, float, np.number)):
            raise InvalidInputError(f"fill_value must be a number or None, got {fill_value!r}")
        self.fill_value = None if fill_value is None else np.asarray(fill_value).item()
        self.cell_size = float(cell_size)
        self.profile = profile
        self.cutoff = cutoff

    def encode(self, buf: Any) -> bytes:
        """The chunk ``buf`` (2D array of :attr:`dtype`) as bytes."""
        values = np.asarray(buf)
        if values.ndim != 2:
            raise InvalidInputError(
                f"dftpcc codes 2D chunks of a DEM; got an array of shape {values.shape} (a flat buffer has lost "
                f"its shape: give the codec the chunk's array, as zarr format 2 does)")
        if values.dtype != np.dtype(self.dtype):
            raise InvalidInputError(f"this codec was made for {np.dtype(self.dtype)} chunks; got {values.dtype} "
                                    f"(give dtype={values.dtype.str!r})")
        return encode_chunk(values, self._params, fill_value=self.fill_value)

    def decode(self, buf: Any, out: Any = None) -> np.ndarray:
        """The chunk coded in ``buf``, as a 2D array of :attr:`dtype` (copied into ``out`` if given)."""
        # numcodecs may hand a flat ``out``: only its size is known, and it bounds the chunk.
        max_cells = None if out is None else int(np.asarray(out).size)
        chunk = decode_chunk(buf, self.dtype, fill_value=self.fill_value, max_cells=max_cells)
        return chunk if out is None else ndarray_copy(chunk, out)

    def get_config(self) -> dict[str, Any]:
        config: dict[str, Any] = {"id": self.codec_id, "max_error": self.max_error, "dtype": self.dtype,
                                  "cell_size": self.cell_size, "profile": self.profile}
        if self.fill_value is not None:
            config["fill_value"] = self.fill_value
        if self.cutoff is not None:
            config["cutoff"] = self.cutoff
        return config

    def __repr__(self) -> str:
        config = self.get_config()
        del config["id"]
        return f"{type(self).__name__}({', '.join(f'{k}={v!r}' for k, v in config.items())})"


# As numcodecs does for its own codecs: importing the module registers the codec.
register_codec(Dftpcc)
