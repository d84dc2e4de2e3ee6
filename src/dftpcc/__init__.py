"""dftpcc: terrain point cloud map compression by low-pass filtering the DFT of a DEM.

Pipeline, one module per stage::

    io (read) -> grid (DEM) -> fill, spectrum (condition, transform, low-pass)
    -> encoder (analysis, ratecontrol, residual; coding, occupancy) -> container (.dftpc bytes)
    -> decoder -> rebuild (points) -> metrics (measure)

``mapfile.open`` reads a file through container, decoder and rebuild;
``files`` joins io to the codec; ``experiments`` holds the paper's sweep
and comparison on top; ``cli`` is the command line.

Most users need only :func:`compress`, :func:`decompress`, :func:`compress_file`,
:func:`decompress_file`, :func:`open`, :func:`read` and :func:`write`.
"""

from __future__ import annotations

from .encoder import compress
from .errors import (
    CoarseMapWarning,
    InputMismatchWarning,
    CorruptFileError,
    DftpccError,
    DftpccWarning,
    InvalidInputError,
    LargeGridWarning,
    MissingDependencyError,
    MultiHeightWarning,
    ResourceLimitError,
    UnsupportedFormatError,
)
from .files import compress_file, decompress_file
from .io import PointCloud, read, write
from .mapfile import CompressedMap, decompress, open
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
    "ResourceLimitError",
    "DftpccWarning",
    "MultiHeightWarning",
    "LargeGridWarning",
    "InputMismatchWarning",
    "CoarseMapWarning",
    "__version__",
]
