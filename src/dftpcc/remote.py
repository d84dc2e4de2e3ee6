"""Files at URLs, read by range requests through fsspec: a map's header and tiles, a GeoTIFF's
blocks, a LAS/LAZ file's chunks. Every response is checked against the file as it was first seen
(its length and ETag), so a file replaced on the server between two requests is refused, not read
as parts of two files.

:class:`Remote` is one file at a URL and its checked reads; :meth:`Remote.open` a buffered, seekable
file object over it (what GDAL, through rasterio's ``opener``, and laspy read).
"""

from __future__ import annotations

import io
import os
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Any, Iterator
from urllib.parse import urlsplit

from ._optional import import_optional
from .errors import InvalidInputError

__all__ = ["Remote", "Stamp", "NoRangesError", "one_version", "is_url", "url_suffix", "READ_AHEAD_BYTES"]

#: Bytes a remote file object reads ahead of what is asked: one request serves a run of small reads
#: (laspy's points, GDAL's consecutive TIFF blocks) instead of one request each.
READ_AHEAD_BYTES = 1 << 20


def is_url(text: object) -> bool:
    """Whether ``text`` names a file by URL (``https://``, ``s3://``...), not a local path."""
    if not isinstance(text, str) or "://" not in text:
        return False
    return text.split("://", 1)[0].lower() not in ("", "file")


def url_suffix(url: str) -> str:
    """The extension of the file a URL names (``.tif``), lower case; its query and fragment left out."""
    return os.path.splitext(urlsplit(url).path)[1].lower()


#: The stamps of the URLs a run has opened (see :func:`one_version`); None outside one.
_SEEN: ContextVar[dict[str, "Stamp"] | None] = ContextVar("dftpcc_remote_seen", default=None)


@contextmanager
def one_version() -> Iterator[None]:
    """Within this, every :class:`Remote` of a URL holds to the first stamp taken of it: a run that
    opens a URL several times (to probe it, to size it, to read it) reads one version of the file."""
    token = _SEEN.set({})
    try:
        yield
    finally:
        _SEEN.reset(token)


@dataclass(frozen=True)
class Stamp:
    """What identifies one version of a file at a URL: its length (bytes) and its ETag (else its
    Last-Modified date; None when the server sends neither)."""

    size: int
    version: str | None

    def differs(self, other: "Stamp") -> str | None:
        """How ``other`` is not this version, in words; None when it is."""
        if other.size != self.size:
            return f"its length went from {self.size:,} to {other.size:,} bytes"
        if self.version is not None and other.version is not None and other.version != self.version:
            what = "ETag" if other.version.startswith(('"', "W/")) else "modification date"
            return f"its {what} went from {self.version} to {other.version}"
        return None


class NoRangesError(InvalidInputError):
    """The server answered a range request with the whole file: it does not serve byte ranges."""


class Remote:
    """One file at a URL, read by range requests; each response checked against ``expect`` (the
    first stamp seen, by default the one taken on opening).

    Over HTTP(S) every response's total length (``Content-Range``) and ETag are compared with the
    stamp; with other fsspec backends (``s3://``, ``gs://``...) the length of every response.

    Parameters
    ----------
    url : str
    expect : Stamp, optional
        The version the caller read before (a dask worker: its client's): refused if the file is not it.
    fs : fsspec filesystem, optional
        The filesystem to read ``url`` with (default: fsspec's for its scheme).

    Raises
    ------
    InvalidInputError
        No fsspec backend for the scheme, no such file, the host cannot be reached, a server that does
        not state the length, or not the ``expect`` ed version.
    MissingDependencyError
        fsspec (or aiohttp for HTTP) is not installed.
    """

    def __init__(self, url: str, *, expect: Stamp | None = None, fs: Any = None):
        self._connect(url, fs)
        self.stamp = self._stat()
        seen = _SEEN.get()
        if expect is None and seen is not None:  # within one_version(): the run's first stamp of the URL
            expect = seen.setdefault(url, self.stamp)
        if expect is not None:
            self._check(self.stamp, expect)
            self.stamp = expect

    def _connect(self, url: str, fs: Any) -> None:
        if fs is None:
            fsspec = import_optional("fsspec", "remote", needed_for="reading a file by URL")
            try:
                fs, path = fsspec.core.url_to_fs(url)
            except (ImportError, ValueError) as exc:  # a scheme without its backend (s3fs, gcsfs...)
                raise InvalidInputError(f"{url}: no fsspec backend reads this URL ({exc}); install the one "
                                        f"for its scheme") from None
        else:
            path = url
        self.url, self.fs, self.path = url, fs, path
        self._http = type(fs).__module__.endswith("implementations.http")
        #: Bytes received so far.
        self.bytes_read = 0
        self._ranges: bool | None = None
        #: The error of the last read that failed: a reader that wraps reads in its own errors (GDAL
        #: turns a failed read into "read failed") says this one instead.
        self.error: InvalidInputError | None = None

    def __getstate__(self) -> dict[str, Any]:
        return {"url": self.url, "stamp": self.stamp}

    def __setstate__(self, state: dict[str, Any]) -> None:
        # A worker's copy: its first request is checked against the client's stamp (no request
        # here: an error while unpickling reaches a dask client as a bare Exception).
        self._connect(state["url"], None)
        self.stamp = state["stamp"]

    def _stat(self) -> Stamp:
        try:
            info = self.fs.info(self.path)
        except FileNotFoundError as exc:
            cause = exc.__cause__ or exc.__context__  # fsspec's HTTP says 'not found' for a host it cannot reach
            if cause is not None and not isinstance(cause, FileNotFoundError) and "404" not in str(cause):
                raise InvalidInputError(f"{self.url}: cannot reach: {_reason(cause)}") from None
            raise InvalidInputError(f"{self.url}: no such file") from None
        except Exception as exc:  # noqa: BLE001 - the network's and the backend's own errors
            raise InvalidInputError(f"{self.url}: cannot reach: {_reason(exc)}") from None
        size = info.get("size")
        if not isinstance(size, int) or size < 0:
            raise InvalidInputError(f"{self.url}: the server does not state the file's length, which reading by "
                                    f"ranges needs: download it first")
        version = info.get("ETag") or info.get("Last-Modified") or info.get("etag") or info.get("LastModified")
        return Stamp(size, None if version is None else str(version))

    def _check(self, seen: Stamp, expect: Stamp | None = None) -> None:
        change = (expect or self.stamp).differs(seen)
        if change is not None:
            raise InvalidInputError(f"{self.url}: the file changed while it was read ({change}); nothing was "
                                    f"written: run again once it stays the same")

    def check_unchanged(self) -> None:
        """Raise :class:`InvalidInputError` unless the server still has the version first seen."""
        self._check(self._stat())

    def read(self, start: int, end: int, *, whole_ok: bool = False) -> bytes:
        """Bytes ``start`` to ``end`` (exclusive, clipped to the file).

        ``whole_ok``: a server that ignores the range and sends the whole file is answered with the
        whole file (else :class:`NoRangesError`, before its body is read).

        Raises
        ------
        InvalidInputError
            The file changed since its stamp was taken, or the request failed.
        NoRangesError
            The server sent the whole file, and ``whole_ok`` is false.
        """
        try:
            return self._read(start, end, whole_ok)
        except InvalidInputError as exc:
            self.error = exc
            raise

    def _read(self, start: int, end: int, whole_ok: bool) -> bytes:
        end = min(end, self.stamp.size)
        if end <= start:
            return b""
        try:
            if self._http:
                data = self._http_range(start, end, whole_ok)
            else:
                data = self.fs.cat_file(self.path, start=start, end=end)
        except InvalidInputError:
            raise
        except Exception as exc:  # noqa: BLE001 - the network's and the backend's own errors
            raise InvalidInputError(f"{self.url}: reading bytes {start:,} to {end:,} failed: {_reason(exc)}") from None
        self.bytes_read += len(data)
        if len(data) == self.stamp.size and end - start < self.stamp.size:
            return data  # the whole file, from a server without ranges (whole_ok)
        if len(data) != end - start:
            raise InvalidInputError(f"{self.url}: asked for bytes {start:,} to {end:,} of a {self.stamp.size:,}-byte "
                                    f"file and got {len(data):,}: the file changed while it was read; nothing was "
                                    f"written: run again once it stays the same")
        return data

    def _http_range(self, start: int, end: int, whole_ok: bool) -> bytes:
        """One HTTP range request on fsspec's session, its headers checked against the stamp."""
        from fsspec.asyn import sync

        fs = self.fs

        async def get() -> bytes:
            session = await fs.set_session()
            kw = dict(fs.kwargs)
            headers = dict(kw.pop("headers", None) or {})
            headers["Range"] = f"bytes={start}-{end - 1}"
            async with session.get(fs.encode_url(self.path), headers=headers, **kw) as r:
                if r.status == 404:
                    raise InvalidInputError(f"{self.url}: no such file (it was there when first read)")
                r.raise_for_status()
                version = r.headers.get("ETag") or r.headers.get("Last-Modified")
                if r.status == 206:
                    total = r.headers.get("Content-Range", "").rpartition("/")[2]
                    size = int(total) if total.isdigit() else self.stamp.size
                else:  # 200: the whole file
                    size = int(r.headers.get("Content-Length", self.stamp.size))
                self._check(Stamp(size, version))
                if r.status != 206 and not whole_ok:
                    raise NoRangesError(f"{self.url}: the server does not serve byte ranges")
                return await r.read()

        return sync(fs.loop, get)

    def serves_ranges(self) -> bool:
        """Whether the server answers a range request with the range (asked once, with one byte)."""
        if self._ranges is None:
            try:
                self.read(0, 1)
                self._ranges = True
            except NoRangesError:
                self._ranges = False
        return self._ranges

    def open(self, *, for_c: bool = False) -> io.BufferedReader:
        """A seekable binary file object over the URL, reading :data:`READ_AHEAD_BYTES` at a time.

        ``for_c``: the reader is a C library calling back into Python (GDAL through rasterio's
        ``opener``), where an exception aborted the process: a failed read ends the file there
        instead (GDAL then fails the read), and :attr:`error` says why.
        """
        return io.BufferedReader(_RawRemote(self, for_c), buffer_size=READ_AHEAD_BYTES)

    def download(self, dst: str | os.PathLike[str]) -> None:
        """Copy the whole file to ``dst`` (streamed: memory holds a piece of it); refused if its length
        is not the stamp's, or the server's length or ETag changed by the end.

        Raises
        ------
        InvalidInputError
            The download failed or the file changed.
        """
        try:
            self.fs.get_file(self.path, str(dst))
        except Exception as exc:  # noqa: BLE001 - the network's and the backend's own errors
            raise InvalidInputError(f"{self.url}: downloading it failed: {_reason(exc)}") from None
        got = os.path.getsize(dst)
        if got != self.stamp.size:
            raise InvalidInputError(f"{self.url}: the file changed while it was read (its length went from "
                                    f"{self.stamp.size:,} to {got:,} bytes); nothing was written: run again once "
                                    f"it stays the same")
        self.check_unchanged()


class _RawRemote(io.RawIOBase):
    """The unbuffered file object of :meth:`Remote.open`: each read one checked range request."""

    def __init__(self, remote: Remote, for_c: bool):
        super().__init__()
        self.remote, self.pos, self.for_c = remote, 0, for_c
        self.name = remote.url

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self.pos, io.SEEK_END: self.remote.stamp.size}[whence]
        self.pos = max(0, base + offset)
        return self.pos

    def tell(self) -> int:
        return self.pos

    def readinto(self, buffer: Any) -> int:
        view = memoryview(buffer).cast("B")
        try:
            data = self.remote.read(self.pos, self.pos + len(view))
        except InvalidInputError:
            if not self.for_c:
                raise
            return 0  # remote.error holds the reason
        view[:len(data)] = data
        self.pos += len(data)
        return len(data)


def _reason(exc: BaseException) -> str:
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
