"""A compressed map opened for reading: :func:`open` and :class:`CompressedMap`.

Like ``rasterio.open``: a path, a file object or bytes in, the header parsed
and checked at once, the map decoded (:mod:`dftpcc.decoder`) and rebuilt
(:mod:`dftpcc.rebuild`) only when asked.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from .container import MAGIC, VERSION, cells_allowed, check_max_bytes, check_max_cells, unpack
from .decoder import decode_dem
from .dem import DEM, Grid
from .errors import InvalidInputError
from .params import Params
from .rebuild import dem_to_points
from .units import units_of

__all__ = ["CompressedMap", "open", "is_dftpc"]


class CompressedMap:
    """A ``.dftpc`` map opened for reading; use :func:`open`.

    The header is parsed and checked on opening; the mask and coefficients
    are decoded only when :meth:`read_points` or :meth:`read_dem` asks.
    """

    def __init__(self, data: bytes, name: str = "<bytes>", *, max_bytes: int | None = None,
                 max_cells: int | None = None, file_size: int | None = None):
        check_max_bytes(max_bytes)
        self.name = name
        # With max_bytes the budget follows the whole file, which exists, not the prefix read.
        self.size = len(data) if file_size is None else file_size
        if max_bytes is not None:
            data = data[:max_bytes]
        self._data = data
        self._partial = max_bytes is not None
        self.header, self._blobs = unpack(data, allow_truncated_coef=self._partial,
                                          max_cells=cells_allowed(self.size, max_cells))

    # Context-manager protocol, like rasterio.open: nothing to release but
    # the buffer, yet `with dftpcc.open(...) as m:` reads naturally.
    def __enter__(self) -> "CompressedMap":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._data = b""

    @property
    def params(self) -> Params:
        return self.header.params

    @property
    def grid(self) -> Grid:
        return self.header.grid

    @property
    def crs(self) -> dict[str, Any]:
        return self.header.crs

    def read_dem(self, *, cutoff: float | None = None) -> DEM:
        """The rebuilt DEM (see :func:`dftpcc.decoder.decode_dem`).

        Raises
        ------
        CorruptFileError
            A section fails to decode, or decodes to non-finite heights.
        """
        return decode_dem(self.header, self._blobs, cutoff=cutoff, allow_partial=self._partial)

    def read_points(self, *, cutoff: float | None = None) -> np.ndarray:
        """The rebuilt cloud, shape (cells, 3), float64, original frame (metres)."""
        return dem_to_points(self.read_dem(cutoff=cutoff))

    def info(self) -> dict[str, Any]:
        """Header, parameters and sizes as plain JSON-ready data."""
        h = self.header
        g = h.grid
        return {
            "file": self.name,
            "bytes": self.size,
            "format_version": f"{VERSION[0]}.{VERSION[1]}",
            "points_original": h.point_count,
            "points_rebuilt": h.cell_count,
            "bits_per_point": 8.0 * self.size / h.point_count if h.point_count else None,
            "grid": {"rows": g.rows, "cols": g.cols, "resolution_m": g.resolution,
                     "resolution_y_m": g.resolution_y, "origin": [g.x0, g.y0], "z0_m": g.z0,
                     "angle_rad": g.angle},
            # The "_m" fields are in these units: metres unless the CRS says otherwise.
            "units": dataclasses.asdict(units_of(h.crs)),
            "params": json.loads(h.params.to_json()),
            "plane": list(h.plane),
            "crs": (h.crs.get("wkt") or ("LAS GeoKeys" if h.crs.get("las_vlrs") else None)),
            "stats": h.stats,
        }


def open(source: str | os.PathLike[str] | BinaryIO | bytes, *, max_bytes: int | None = None,  # noqa: A001
         max_cells: int | None = None) -> CompressedMap:
    """Open a compressed map from a path, a binary file object or bytes.

    Parameters
    ----------
    source : path, file-like or bytes
    max_bytes : int, optional
        Read only the first ``max_bytes`` bytes, as if the rest had not been
        received yet; the map decodes from the low frequencies it holds.
    max_cells : int, optional
        Largest grid (rows x cols) to accept. By default a file may ask for
        :func:`cell_budget` of its size; raise it for a trusted file that
        :class:`~dftpcc.errors.ResourceLimitError` refused.

    Raises
    ------
    InvalidInputError
        The path does not exist or is not a file, or a bad argument.
    CorruptFileError
        The content is not a valid ``.dftpc`` stream.
    ResourceLimitError
        The header asks for a grid over the budget.
    UnsupportedFormatError
        Another major version of the format.
    """
    # The arguments first (as rasterio does): a bad one is refused before the file is touched.
    check_max_bytes(max_bytes)
    check_max_cells(max_cells)
    if isinstance(source, (bytes, bytearray, memoryview)):
        return CompressedMap(bytes(source), max_bytes=max_bytes, max_cells=max_cells)
    if hasattr(source, "read"):
        return CompressedMap(source.read(), getattr(source, "name", "<stream>"), max_bytes=max_bytes,
                             max_cells=max_cells)
    path = Path(source)
    if not path.is_file():
        raise InvalidInputError(f"{path}: no such file")
    with path.open("rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        data = fh.read() if max_bytes is None else fh.read(max_bytes)
    return CompressedMap(data, str(path), max_bytes=max_bytes, max_cells=max_cells, file_size=max(size, len(data)))


def is_dftpc(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a ``.dftpc`` file (by its magic bytes, not its name)."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(f"{path}: no such file")
    with path.open("rb") as fh:
        return fh.read(len(MAGIC)) == MAGIC
