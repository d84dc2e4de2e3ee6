"""dftpcc as a Zarr v3 array-to-bytes codec: :class:`DftpccCodec`, named ``dftpcc``.

Each chunk of a 2D DEM array is coded by :mod:`dftpcc.chunkcodec` with a
maximum error in metres; the array's dtype and fill value come from its
metadata (fill-value cells and NaN are no data, see there). Registered under
the ``zarr.codecs`` entry point, so zarr (and xarray, dask on top of it)
reopen a store made with it by name once dftpcc is installed::

    zarr.create_array(store, shape=dem.shape, chunks=(256, 256), dtype="float32", fill_value=np.nan,
                      serializer=DftpccCodec(max_error=0.05), compressors=None)

The codec replaces zarr's ``bytes`` serializer; a bytes-to-bytes compressor
after it gains nothing (the stream is entropy-coded already).
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from ._optional import import_optional
from .chunkcodec import check_chunk_shape, check_dtype, chunk_params, decode_chunk, encode_chunk
from .errors import InvalidInputError
from .params import Params

import_optional("zarr.abc.codec", "zarr", needed_for="the Zarr codec", name="zarr 3")  # zarr 2 has no zarr.abc

from zarr.abc.codec import ArrayBytesCodec  # noqa: E402
from zarr.core.common import parse_named_configuration  # noqa: E402
from zarr.registry import register_codec  # noqa: E402

if TYPE_CHECKING:
    from zarr.core.array_spec import ArraySpec
    from zarr.core.buffer import Buffer, NDBuffer

__all__ = ["DftpccCodec", "CODEC_NAME"]

#: The codec's name in array metadata and under the ``zarr.codecs`` entry point.
CODEC_NAME = "dftpcc"


@dataclass(frozen=True)
class DftpccCodec(ArrayBytesCodec):
    """Lossy DEM serializer with a maximum error in metres, for Zarr v3 arrays.

    Parameters
    ----------
    max_error : float
        Largest error on any valid cell, in the array's height unit (metres);
        for integer arrays, ``floor(max_error)`` whole units (lossless below 1).
    cell_size : float
        Width of a cell in metres (recorded in each chunk's header).
    profile : str
        dftpcc profile (``compact`` or ``paper``).
    cutoff : float, optional
        Cutoff ratio in [0, 1); default: chosen per chunk by rate control.
    """

    is_fixed_size = False

    max_error: float
    cell_size: float = 1.0
    profile: str = "compact"
    cutoff: float | None = None

    def __init__(self, *, max_error: float, cell_size: float = 1.0, profile: str = "compact",
                 cutoff: float | None = None) -> None:
        chunk_params(max_error, cell_size=cell_size, profile=profile, cutoff=cutoff)  # refuse bad values now
        object.__setattr__(self, "max_error", float(max_error))
        object.__setattr__(self, "cell_size", float(cell_size))
        object.__setattr__(self, "profile", profile)
        object.__setattr__(self, "cutoff", None if cutoff is None else float(cutoff))

    @property
    def params(self) -> Params:
        """The :class:`~dftpcc.params.Params` each chunk is coded with."""
        return chunk_params(self.max_error, cell_size=self.cell_size, profile=self.profile, cutoff=self.cutoff)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "DftpccCodec":
        _, configuration = parse_named_configuration(data, CODEC_NAME)
        return cls(**configuration)

    def to_dict(self) -> dict[str, Any]:
        configuration: dict[str, Any] = {"max_error": self.max_error, "cell_size": self.cell_size,
                                         "profile": self.profile}
        if self.cutoff is not None:
            configuration["cutoff"] = self.cutoff
        return {"name": CODEC_NAME, "configuration": configuration}

    def validate(self, *, shape: tuple[int, ...], dtype: Any, chunk_grid: Any) -> None:
        """Refuse, when the array is created, what no chunk of it could be coded as."""
        if len(shape) != 2:
            raise InvalidInputError(f"dftpcc codes 2D DEM arrays (rows, cols); this array has shape {shape}")
        check_dtype(dtype.to_native_dtype())
        chunk_shape = getattr(chunk_grid, "chunk_shape", None)  # a regular grid: every chunk this shape
        if chunk_shape is not None:
            check_chunk_shape(tuple(chunk_shape))

    def _encode_sync(self, chunk_array: NDBuffer, chunk_spec: ArraySpec) -> Buffer | None:
        data = encode_chunk(chunk_array.as_numpy_array(), self.params, fill_value=chunk_spec.fill_value)
        return chunk_spec.prototype.buffer.from_bytes(data)

    def _decode_sync(self, chunk_bytes: Buffer, chunk_spec: ArraySpec) -> NDBuffer:
        chunk = decode_chunk(chunk_bytes.to_bytes(), chunk_spec.dtype.to_native_dtype(),
                             fill_value=chunk_spec.fill_value, shape=chunk_spec.shape)
        return chunk_spec.prototype.nd_buffer.from_numpy_array(chunk)

    # Coding a chunk is CPU work in numpy, which releases the GIL: threads, like zarr's own compressors.
    async def _encode_single(self, chunk_array: NDBuffer, chunk_spec: ArraySpec) -> Buffer | None:
        return await asyncio.to_thread(self._encode_sync, chunk_array, chunk_spec)

    async def _decode_single(self, chunk_bytes: Buffer, chunk_spec: ArraySpec) -> NDBuffer:
        return await asyncio.to_thread(self._decode_sync, chunk_bytes, chunk_spec)

    def compute_encoded_size(self, input_byte_length: int, chunk_spec: ArraySpec) -> int:
        raise NotImplementedError("dftpcc chunks have a variable size")


# As zarr does for its own codecs: importing the module is enough to read a store, even from a
# checkout installed before its entry point existed (or unpickled in a dask worker).
register_codec(CODEC_NAME, DftpccCodec)
