"""Atomic writes, the last step of every output: a file appears complete or not at all.

Every writer of dftpcc (``.dftpc``, point clouds, GeoTIFF) goes through
:func:`atomic_write`, so an interrupted run or a failing writer never leaves
a partial or corrupt output file under the user's name, and a failure is one
error naming that file (:func:`writer_errors` for third-party writers).
"""

from __future__ import annotations

import os
import secrets
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from ..errors import InvalidInputError, advice

__all__ = ["atomic_write", "writer_errors", "check_output"]


#: Temporary files of :func:`atomic_write`: ``.NAME.PID.TOKEN.tmpSUFFIX``.
_TMP_MARK = ".tmp"


def atomic_write(path: str | os.PathLike[str], write: Any) -> None:
    """Create ``path`` through a temporary file in the same folder, renamed into place.

    ``write(tmp_path)`` receives the temporary path. The file is flushed to
    disk, renamed over ``path`` in one step (``os.replace``) and the folder
    entry synced, so ``path`` holds either its previous content or the whole
    new one, never a partial file. If ``write`` raises or the process is
    interrupted (Ctrl-C, SIGTERM under the CLI) the temporary file is
    removed; only a process killed outright (SIGKILL, power loss) leaves it,
    under a hidden name, and the next write to ``path`` removes it.

    Raises
    ------
    InvalidInputError
        The folder of ``path`` does not exist.
    OSError
        The file system refused (permissions, disk full): the error of the
        same class and errno, naming ``path`` rather than the temporary file.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise InvalidInputError(f"{path}: folder {folder} does not exist")
    _remove_stale_temporaries(folder, path.name)
    tmp = folder / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}{_TMP_MARK}{path.suffix}"
    try:
        write(tmp)
        with tmp.open("rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        _sync_folder(folder)
    except OSError as exc:
        raise _naming(path, tmp, exc) from exc
    finally:
        if tmp.exists():
            tmp.unlink()


def check_output(path: str | os.PathLike[str], *, force: bool = False) -> Path:
    """Refuse, before any work, an output path that :func:`atomic_write` could not fill.

    Checks that ``path`` is not a folder or a special file, that its folder
    exists and takes a new file (by creating and removing one: permissions,
    read-only file systems and ``/proc`` all answer that), and that an
    existing file is not write-protected, unless ``force``, as ``cp -f`` and
    ``gdal_translate`` users expect.

    Raises
    ------
    InvalidInputError
        A folder, a special file, a missing folder, or a write-protected file without ``force``.
    OSError
        The folder refuses a new file (the error's class and errno, naming ``path``).
    """
    path = Path(path)
    if path.is_dir():
        raise InvalidInputError(f"{path}: is a folder; give the name of the file to write")
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise InvalidInputError(f"{path}: folder {folder} does not exist")
    if path.exists() or path.is_symlink():
        if not path.is_file():
            raise InvalidInputError(f"{path}: not a regular file; give the name of a file to write")
        if not path.stat().st_mode & 0o222 and not force:
            raise InvalidInputError(f"{path}: the file is write-protected; use {advice('force=True', '--force')} "
                                    f"to replace it")
    probe = folder / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}{_TMP_MARK}"
    try:
        os.close(os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
        os.unlink(probe)
    except OSError as exc:
        raise _naming(path, probe, exc) from exc
    return path


def _naming(path: Path, tmp: Path, exc: OSError) -> OSError:
    """``exc`` as one line about ``path``: writers report the temporary file, or no file at all."""
    text = " ".join(str(exc.strerror or exc).split())  # GDAL explains itself over several lines
    text = text.replace(str(tmp), str(path))
    if exc.errno is None:
        return OSError(f"{path}: cannot write: {text}")
    return OSError(exc.errno, text, str(path))  # the subclass of the errno (PermissionError, ...)


@contextmanager
def writer_errors(path: str | os.PathLike[str], fmt: str) -> Iterator[None]:
    """Third-party writers raise anything on what they cannot represent: one clear error naming ``path``.

    :class:`InvalidInputError` and :class:`OSError` pass as they are (see
    :func:`atomic_write`); anything else becomes an :class:`InvalidInputError`
    ``PATH: cannot write as FMT: ...`` on one line.
    """
    try:
        yield
    except (InvalidInputError, OSError):
        raise
    except Exception as exc:  # noqa: BLE001 - laspy, plyfile, pypcd4, rasterio have no common error
        raise InvalidInputError(f"{path}: cannot write as {fmt}: {' '.join(str(exc).split())}") from None


def _sync_folder(folder: Path) -> None:
    # The rename is durable only once the folder entry is on disk too.
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # some file systems cannot sync a folder; the rename is still atomic
    finally:
        os.close(fd)


def _remove_stale_temporaries(folder: Path, name: str) -> None:
    """Remove temporaries of ``name`` left by writers that were killed outright."""
    prefix = f".{name}."
    try:
        candidates = [p for p in folder.iterdir() if p.name.startswith(prefix) and _TMP_MARK in p.name]
    except OSError:
        return
    for candidate in candidates:
        pid = candidate.name[len(prefix):].split(".", 1)[0]
        if pid.isdigit() and not _alive(int(pid)):
            try:
                candidate.unlink()
            except OSError:
                pass


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # exists but not ours, or cannot tell: leave its file alone
    return True
