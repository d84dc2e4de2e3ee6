"""Advisory locks of the files a command reads, changes and writes back (``dftpcc update``, ``patch``).

A growing map is read, added to and written back: two such runs at once
would each write the map they read plus their own scans, and the second
rename would drop the first run's scans. :func:`locked` serialises them on
a lock file beside the map (``MAP.lock``, :func:`lock_path`), held with
``flock`` for the whole read-modify-write. A second run *waits* for the
first and then reads the map the first wrote, so both runs' scans end up in
the map. The kernel drops the lock of a process that dies, even by SIGKILL:
no stale lock can block the map.
"""

from __future__ import annotations

import errno
import fcntl
import os
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Callable, Iterator

__all__ = ["locked", "lock_path", "LOCK_SUFFIX"]

#: The lock file of ``MAP`` is ``MAP`` + this.
LOCK_SUFFIX = ".lock"
#: Errors of a folder that takes no new file.
_READ_ONLY = (errno.EACCES, errno.EPERM, errno.EROFS)


def lock_path(path: str | os.PathLike[str]) -> Path:
    """The lock file of ``path``: ``PATH.lock`` beside it."""
    return Path(f"{os.fspath(path)}{LOCK_SUFFIX}")


@contextmanager
def locked(paths: list[str | os.PathLike[str]], *,
           waiting: Callable[[Path], None] | None = None) -> Iterator[None]:
    """Hold the exclusive locks of ``paths`` (each through :func:`lock_path`) for the ``with`` block.

    Waits as long as another process holds one. The locks are taken in the
    order of the files' resolved paths, so two runs locking the same pair
    cannot deadlock. The lock files are removed on release; one left by a
    killed process is taken over by the next run.

    Parameters
    ----------
    paths : list of path
        The files to lock (the same file named twice is locked once).
    waiting : callable, optional
        Called with the lock file's path when another process holds it, before waiting.
    """
    unique = sorted({Path(os.path.abspath(lock_path(Path(p).resolve()))) for p in paths})
    with ExitStack() as stack:
        for path in unique:
            stack.enter_context(_one(path, waiting))
        yield


@contextmanager
def _one(path: Path, waiting: Callable[[Path], None] | None) -> Iterator[None]:
    while True:
        try:
            fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o644)
        except OSError as exc:
            if exc.errno not in _READ_ONLY:
                raise
            # A folder that takes no new file takes no renamed map either: no dftpcc run can replace
            # the file there (``update -o`` elsewhere only reads it), so there is nothing to guard.
            yield
            return
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                if waiting is not None:
                    waiting(path)
                    waiting = None  # say it once
                fcntl.flock(fd, fcntl.LOCK_EX)
            # The holder before us removes the file on release: a lock taken on a file no longer
            # at the path guards nothing (a third run locks the new file), so take the path's again.
            try:
                held = os.stat(path)
            except FileNotFoundError:
                continue
            mine = os.fstat(fd)
            if (held.st_dev, held.st_ino) != (mine.st_dev, mine.st_ino):
                continue
            try:
                yield
            finally:
                try:
                    os.unlink(path)  # while still held: a waiter sees the file is gone and retries
                except OSError:
                    pass
            return
        finally:
            os.close(fd)
