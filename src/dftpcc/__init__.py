"""dftpcc: terrain point cloud map compression by low-pass filtering the DFT of a DEM.

Pipeline, one module per stage::

    formats (read) -> grid (DEM) -> spectrum (transform, low-pass)
    -> coding (quantize, entropy-code) -> container (.dftpc bytes)
    -> codec.decode_dem -> rebuild (points) -> metrics (measure)

Most users need only :func:`compress`, :func:`decompress`, :func:`compress_file`,
:func:`decompress_file`, :func:`open`, :func:`read` and :func:`write`.
"""

from __future__ import annotations

from .codec import compress, decompress
from .container import CompressedMap, open
from .errors import (
    CorruptFileError,
    DftpccError,
    InvalidInputError,
    MissingDependencyError,
    UnsupportedFormatError,
)
from .files import compress_file, decompress_file
from .formats import PointCloud, read, write
from .params import PROFILES, Params, make_params

__version__ = "0.1.0"

__all__ = [
    "compress",
    "decompress",
    "compress_file",
    "decompress_file",
    "open",
    "read",
    "write",
    "CompressedMap",
    "PointCloud",
    "Params",
    "PROFILES",
    "make_params",
    "DftpccError",
    "InvalidInputError",
    "CorruptFileError",
    "UnsupportedFormatError",
    "MissingDependencyError",
    "__version__",
]
