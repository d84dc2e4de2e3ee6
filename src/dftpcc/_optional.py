"""Optional dependencies in one place: what each extra installs, and the one guard that imports a
module of an extra or says how to install it (:class:`~dftpcc.errors.MissingDependencyError`, exit
status 6 on the command line).

The extras are those of ``pyproject.toml``; a module that needs one calls :func:`import_optional`
where it first needs it, so ``import dftpcc`` never pays for, nor fails on, an extra.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from .errors import MissingDependencyError

__all__ = ["EXTRAS", "install_hint", "import_optional"]

#: Each extra of ``pyproject.toml`` a module imports, and what it installs (the hint's words).
EXTRAS = {
    "dask": "dask.distributed",
    "zarr": "zarr, numcodecs, xarray and dask",
    "fast": "numba",
    "plot": "matplotlib",
    "slam": "the small_gicp package",
    "ros": "the rosbags package",
    "draco": "the DracoPy package",
    "remote": "fsspec and aiohttp",
    "ros2": "rclpy and the message wheels, no ROS installation needed",
}


def install_hint(extra: str) -> str:
    """The command that installs ``extra`` (a key of :data:`EXTRAS`), and what it brings."""
    return f"pip install 'dftpcc[{extra}]' ({EXTRAS[extra]})"


def import_optional(module: str, extra: str, *, needed_for: str, name: str | None = None) -> ModuleType:
    """``module``, imported, or the error that names the extra installing it.

    Parameters
    ----------
    module : str
        The dotted module to import (a submodule imports its packages too).
    extra : str
        The extra of dftpcc that installs it (a key of :data:`EXTRAS`).
    needed_for : str
        What needs it, the message's subject: ``"reading ROS bags"``.
    name : str, optional
        What the message calls the package; its top-level module by default.

    Raises
    ------
    MissingDependencyError
        The module (or one it imports) is not installed: ``"<needed_for> needs <name>, which is not
        installed: pip install 'dftpcc[<extra>]' (...)"``.
    """
    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingDependencyError(f"{needed_for} needs {name or module.split('.')[0]}, which is not installed: "
                                     f"{install_hint(extra)}") from None
