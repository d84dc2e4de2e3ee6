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

__all__ = ["atomic_write", "atomic_write_all", "writer_errors", "check_output", "check_distinct"]


#: Temporary files of :func:`atomic_write`: ``.NAME.PID.TOKEN.tmpSUFFIX``.
_TMP_MARK = ".tmp"


def atomic_write(path: str | os.PathLike[str], write: Any) -> None:
    """Create ``path`` through a temporary file in the same folder, renamed into place.

    ``write(tmp_path)`` receives the temporary path (or ``write`` is the file's bytes). The file is flushed to
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
    atomic_write_all([(path, write)])


def atomic_write_all(files: list[tuple[str | os.PathLike[str], Any]]) -> None:
    """Write several files as :func:`atomic_write` does, all of them before any is renamed into place.

    Every ``write(tmp_path)`` runs and every temporary is flushed to disk
    first; only then are they renamed over their paths, in the order given,
    and their folders synced. A failing writer (or an interruption before the
    renames) leaves every path as it was. A process killed during the renames
    leaves the files renamed so far new and the others old: the caller
    chooses the order from which it recovers (:func:`dftpcc.growing.update_file`).

    Raises
    ------
    InvalidInputError, OSError
        As :func:`atomic_write`, naming the file concerned.
    """
    plan = []
    for path, write in files:
        path = Path(path)
        folder = path.parent if str(path.parent) else Path(".")
        if not folder.is_dir():
            raise InvalidInputError(f"{path}: folder {folder} does not exist")
        plan.append((path, folder, write))
    temporaries: list[tuple[Path, Path]] = []
    try:
        for path, folder, write in plan:
            _remove_stale_temporaries(folder, path.name)
            tmp = folder / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}{_TMP_MARK}{path.suffix}"
            temporaries.append((path, tmp))
            try:
                if isinstance(write, (bytes, bytearray, memoryview)):
                    tmp.write_bytes(write)
                else:
                    write(tmp)
                with tmp.open("rb+") as fh:
                    os.fsync(fh.fileno())
            except OSError as exc:
                raise _naming(path, tmp, exc) from exc
        for (path, tmp), (_, folder, _) in zip(temporaries, plan):
            try:
                os.replace(tmp, path)
            except OSError as exc:
                raise _naming(path, tmp, exc) from exc
            _sync_folder(folder)  # each rename on disk before the next: a power loss keeps their order
    finally:
        for _, tmp in temporaries:
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


def check_distinct(outputs: dict[str, str | os.PathLike[str]], inputs: dict[str, str | os.PathLike[str]]) -> None:
    """Refuse an output that is one of the inputs or another output, before anything is read or written.

    Two names are one file when they resolve to the same path (through
    symbolic links and ``..``) or, for files that exist, to the same device
    and inode (hard links). Replacing an input by an output would destroy it
    (``dftpcc update MAP SCAN --delta MAP`` wrote the delta over the new map).

    Parameters
    ----------
    outputs, inputs : dict
        What each file is (``"--delta FILE"``, ``"the map"``) by its path, as the message names it.

    Raises
    ------
    InvalidInputError
        Two of the files are one, named by what they are.
    """
    seen: list[tuple[str, Path, tuple[int, int] | None]] = []
    for role, path in [*inputs.items(), *outputs.items()]:
        seen.append((role, Path(path).resolve(), _identity(Path(path))))
    for k, (role, resolved, ident) in enumerate(seen[len(inputs):], start=len(inputs)):
        for other, other_resolved, other_ident in seen[:k]:
            if resolved == other_resolved or (ident is not None and ident == other_ident):
                raise InvalidInputError(f"{role} is {other} (the same file): give another name; nothing was written")


def _identity(path: Path) -> tuple[int, int] | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_dev, st.st_ino


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
