"""The exceptions dftpcc raises.

The library raises only these (plus ``MemoryError`` from numpy in truly
exceptional cases); the command line turns each into one line on stderr and
a distinct exit code (see ``dftpcc.cli.EXIT_CODES``).
"""

from __future__ import annotations

__all__ = [
    "DftpccError",
    "InvalidInputError",
    "CorruptFileError",
    "UnsupportedFormatError",
    "MissingDependencyError",
]


class DftpccError(Exception):
    """Base class of every error dftpcc raises on purpose."""


class InvalidInputError(DftpccError, ValueError):
    """The caller's input is unusable: a bad parameter, an empty or non-finite cloud."""


class UnsupportedFormatError(InvalidInputError):
    """A file extension or format name dftpcc cannot read or write."""


class CorruptFileError(DftpccError):
    """A ``.dftpc`` stream is truncated, damaged or not a dftpcc file at all."""


class MissingDependencyError(DftpccError, ImportError):
    """An optional package needed for this operation is not installed."""
