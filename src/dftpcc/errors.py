"""The exceptions and warnings dftpcc raises.

The library raises only these (plus ``MemoryError`` from numpy in truly
exceptional cases); the command line turns each into one line on stderr and
a distinct exit code (see ``dftpcc.cli.EXIT_CODES`` and docs/errors.md).
Warnings say that a result is valid but not what the user may think it is.
"""

from __future__ import annotations

__all__ = [
    "advice",
    "speaking_to_the_command_line",
    "DftpccError",
    "InvalidInputError",
    "CorruptFileError",
    "ResourceLimitError",
    "UnsupportedFormatError",
    "MissingFileError",
    "MissingDependencyError",
    "ClusterError",
    "DftpccWarning",
    "MultiHeightWarning",
    "LargeGridWarning",
    "InputMismatchWarning",
    "CoarseMapWarning",
    "RasterTypeWarning",
    "RemoteWarning",
]


class DftpccError(Exception):
    """Base class of every error dftpcc raises on purpose."""


class InvalidInputError(DftpccError, ValueError):
    """The caller's input is unusable: a bad parameter, an empty or non-finite cloud."""


class UnsupportedFormatError(InvalidInputError):
    """A file extension, format name or ``.dftpc`` major version dftpcc cannot read or write."""


class MissingFileError(InvalidInputError, FileNotFoundError):
    """A file to read is not there.

    Both an :class:`InvalidInputError` (the command line's exit status 3) and
    the ``FileNotFoundError`` Python code catches for a missing file.
    """

    def __init__(self, path: object, message: str | None = None):
        InvalidInputError.__init__(self, message or f"{path}: no such file")
        self.filename = str(path)

    def __str__(self) -> str:
        return str(self.args[0])


class CorruptFileError(DftpccError):
    """A ``.dftpc`` stream is truncated, damaged or not a dftpcc file at all."""


class ResourceLimitError(CorruptFileError):
    """A ``.dftpc`` header asks for more cells than the file's size justifies.

    Either a crafted file (a decompression bomb) or a legitimate but
    extremely compressible map; the message gives the numbers, and
    ``dftpcc.open(..., max_cells=N)`` decodes a trusted file anyway.
    """


class MissingDependencyError(DftpccError, ImportError):
    """An optional package needed for this operation is not installed."""


class ClusterError(DftpccError):
    """A dask cluster could not do the work: unreachable, a worker died, or no worker left."""


class DftpccWarning(UserWarning):
    """Base class of the warnings dftpcc issues."""


class MultiHeightWarning(DftpccWarning):
    """Some cells hold points at several heights (a wall, an overhang, vegetation).

    A DEM keeps one height per cell, so those points cannot be rebuilt; the
    message says what fraction of the points and by how much.
    """


class LargeGridWarning(DftpccWarning):
    """A map was written that readers refuse by default (see :class:`ResourceLimitError`)."""


class InputMismatchWarning(DftpccWarning):
    """A map is measured against other points than it was made from (a different point count)."""


class CoarseMapWarning(DftpccWarning):
    """An automatic quantizer step leaves errors beyond the map's own height spread."""


class RemoteWarning(DftpccWarning):
    """A file at a URL is read another way than asked: its server serves no byte ranges, so it is
    downloaded whole first."""


class RasterTypeWarning(DftpccWarning):
    """A rebuilt DEM is not written in the sample type of the raster it came from (its errors are too
    large for an integer type to round back to the source's values); the message says which and why."""


#: Whether messages give the command line's flags (set by ``dftpcc.cli.main``) or Python's arguments.
_COMMAND_LINE = False


def speaking_to_the_command_line(on: bool = True) -> bool:
    """Make :func:`advice` name command-line flags (``dftpcc.cli.main`` does while it runs), or Python
    arguments again; returns the previous setting, to restore."""
    global _COMMAND_LINE
    previous, _COMMAND_LINE = _COMMAND_LINE, on
    return previous


def advice(python: str, command_line: str) -> str:
    """The remedy a message offers, as its reader can apply it: a flag for a user of the command line,
    a function or an argument for a Python caller."""
    return command_line if _COMMAND_LINE else python
