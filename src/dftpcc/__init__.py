"""dftpcc: terrain point cloud map compression by low-pass filtering the DFT of a DEM.

Pipeline, one module per stage::

    io (read) -> grid (DEM) -> fill, spectrum (condition, transform, low-pass)
    -> encoder (analysis, ratecontrol, residual; coding, occupancy) -> format (.dftpc bytes: one writer, one reader)
    -> decoder -> rebuild (points) -> metrics (measure)

``mapfile.open`` reads a file through format, decoder and rebuild;
``files`` joins io to the codec; ``experiments`` holds the paper's sweep
and comparison on top; ``cli`` is the command line.

Most users need only :func:`compress`, :func:`decompress`, :func:`compress_file`,
:func:`decompress_file`, :func:`open`, :func:`read` and :func:`write`.
"""

from __future__ import annotations

import importlib as _importlib
from types import ModuleType as _ModuleType
from typing import TYPE_CHECKING, Any

from .errors import (
    CoarseMapWarning,
    InputMismatchWarning,
    CorruptFileError,
    DftpccError,
    DftpccWarning,
    InvalidInputError,
    LargeGridWarning,
    MissingDependencyError,
    MissingFileError,
    MultiHeightWarning,
    ResourceLimitError,
    UnsupportedFormatError,
)

if TYPE_CHECKING:  # what the names below resolve to, for type checkers and IDEs
    from .encoder import compress
    from .files import compress_file, decompress_file
    from .io import PointCloud, read, write
    from .mapfile import CompressedMap, decompress, open
    from .params import PROFILES, Params, make_params

#: The top-level API, imported on first use (PEP 562): the codec pulls in scipy.fft, rasterio and
#: constriction, which ``dftpcc --help`` and the exceptions do not need (as SciPy and scikit-image
#: load their submodules).
_LAZY = {
    "compress": "encoder",
    "compress_file": "files", "decompress_file": "files",
    "PointCloud": "io", "read": "io", "write": "io",
    "CompressedMap": "mapfile", "decompress": "mapfile", "open": "mapfile",
    "PROFILES": "params", "Params": "params", "make_params": "params",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(_importlib.import_module(f".{_LAZY[name]}", __name__), name)
    else:
        try:  # a submodule (dftpcc.coding, ...), as the eager imports used to make every one reachable
            value = _importlib.import_module(f".{name}", __name__)
        except ModuleNotFoundError as exc:
            if exc.name != f"{__name__}.{name}":
                raise
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    # The public API and the submodules loaded so far; not the helpers this file imports for itself.
    loaded = {name for name, value in globals().items()
              if isinstance(value, _ModuleType) and value.__name__.startswith(f"{__name__}.")}
    return sorted(set(__all__) | loaded)


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
    "MissingFileError",
    "ResourceLimitError",
    "DftpccWarning",
    "MultiHeightWarning",
    "LargeGridWarning",
    "InputMismatchWarning",
    "CoarseMapWarning",
    "__version__",
]
