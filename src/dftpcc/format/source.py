"""Where a reader's bytes come from: memory, a file read by offset (random access), or a URL read by
range requests."""

from __future__ import annotations

from typing import BinaryIO

from ..remote import Remote, is_url

__all__ = ["Source", "RemoteSource", "is_url"]


class Source:
    """The bytes of a ``.dftpc`` file: in memory, or an open file read by offset (random access).

    ``read(offset, length)`` returns up to ``length`` bytes (fewer at the
    end); a tiled map opened from a path reads its header and then only the
    tiles asked for.
    """

    def __init__(self, data: bytes | memoryview | None = None, *, file: BinaryIO | None = None,
                 size: int | None = None):
        self._data = memoryview(data) if data is not None else None
        self._file = file
        self.size = len(self._data) if self._data is not None else int(size or 0)
        #: Bytes read so far (the random-access benchmark reports it).
        self.bytes_read = 0

    def read(self, offset: int, length: int) -> memoryview:
        length = max(0, min(length, self.size - offset))
        self.bytes_read += length
        if self._data is not None:
            return self._data[offset:offset + length]
        assert self._file is not None
        self._file.seek(offset)
        return memoryview(self._file.read(length))

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
        self._data = None


class RemoteSource(Source):
    """The bytes of a map at a URL, read by range requests through fsspec (:class:`dftpcc.remote.Remote`:
    HTTP(S) with aiohttp; ``s3://``, ``gs://`` and the others with the user's fsspec backend): a tiled
    map's reader fetches its header, its index and the tiles it decodes, not the file.

    The file's length and ETag are taken once, on opening. A server that ignores range requests sends
    the whole file to the first one: it is kept, and read from memory (:attr:`whole` says so). A file
    that changes between requests is refused: every response's length and ETag are compared with the
    first's (and the section checksums catch the rest).
    """

    def __init__(self, url: str, *, fs: object | None = None):
        self.remote = Remote(url, fs=fs)
        self.url = url
        super().__init__(size=self.remote.stamp.size)
        #: Set once the server sent the whole file to a range request (then read from memory).
        self.whole = False

    def read(self, offset: int, length: int) -> memoryview:
        length = max(0, min(length, self.size - offset))
        if self._data is not None:
            return super().read(offset, length)
        if length == 0:
            return memoryview(b"")
        data = self.remote.read(offset, offset + length, whole_ok=True)
        if len(data) == self.size and length < self.size:  # no range support: the whole file came
            self._data, self.whole = memoryview(data), True
            return super().read(offset, length)
        self.bytes_read += len(data)
        return memoryview(data)

    def close(self) -> None:
        self._data = None
