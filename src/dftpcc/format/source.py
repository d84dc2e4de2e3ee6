"""Where a reader's bytes come from: memory, a file read by offset (random access), or a URL read by
range requests."""

from __future__ import annotations

from typing import BinaryIO

from .._optional import import_optional
from ..errors import CorruptFileError, InvalidInputError


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


def is_url(text: object) -> bool:
    """Whether ``text`` names a map by URL (``https://``, ``s3://``...), not a local path."""
    if not isinstance(text, str) or "://" not in text:
        return False
    return text.split("://", 1)[0].lower() not in ("", "file")


class RemoteSource(Source):
    """The bytes of a map at a URL, read by range requests through fsspec (HTTP(S) with aiohttp;
    ``s3://``, ``gs://`` and the others with the user's fsspec backend): a tiled map's reader fetches
    its header, its index and the tiles it decodes, not the file.

    The file's length is taken once, on opening. A server that ignores range requests sends the
    whole file to the first one: it is kept, and read from memory (:attr:`whole` says so). A file
    that changes between requests is refused: by its length when a read comes back short, and by the
    section checksums otherwise.
    """

    def __init__(self, url: str, *, fs: object | None = None):
        if fs is None:
            fsspec = import_optional("fsspec", "remote", needed_for="reading a map by URL")
            try:
                fs, path = fsspec.core.url_to_fs(url)
            except (ImportError, ValueError) as exc:  # a scheme without its backend (s3fs, gcsfs...)
                raise InvalidInputError(f"{url}: no fsspec backend reads this URL ({exc}); install the one "
                                        f"for its scheme") from None
        else:
            path = url
        self.url, self._fs, self._path = url, fs, path
        try:
            info = fs.info(path)  # type: ignore[attr-defined]
        except FileNotFoundError as exc:
            cause = exc.__cause__ or exc.__context__  # fsspec's HTTP says 'not found' for a host it cannot reach
            if cause is not None and not isinstance(cause, FileNotFoundError) and "404" not in str(cause):
                raise InvalidInputError(f"{url}: cannot reach: {_reason(cause)}") from None
            raise InvalidInputError(f"{url}: no such file") from None
        except Exception as exc:  # noqa: BLE001 - the network's and the backend's own errors
            raise InvalidInputError(f"{url}: cannot reach: {_reason(exc)}") from None
        size = info.get("size")
        if not isinstance(size, int) or size < 0:
            raise InvalidInputError(f"{url}: the server does not state the file's length, which reading by "
                                    f"ranges needs: download it first")
        super().__init__(size=size)
        #: Set once the server sent the whole file to a range request (then read from memory).
        self.whole = False

    def read(self, offset: int, length: int) -> memoryview:
        length = max(0, min(length, self.size - offset))
        if self._data is not None:
            return super().read(offset, length)
        if length == 0:
            return memoryview(b"")
        try:
            data = self._fs.cat_file(self._path, start=offset, end=offset + length)  # type: ignore[attr-defined]
        except Exception as exc:  # noqa: BLE001 - the network's and the backend's own errors
            raise InvalidInputError(f"{self.url}: reading bytes {offset:,} to {offset + length:,} failed: "
                                    f"{_reason(exc)}") from None
        if len(data) == self.size and length < self.size:  # no range support: the whole file came
            self._data, self.whole = memoryview(data), True
            return super().read(offset, length)
        self.bytes_read += len(data)
        if len(data) != length:
            raise CorruptFileError(f"{self.url}: asked for bytes {offset:,} to {offset + length:,} of a "
                                   f"{self.size:,}-byte file and got {len(data):,}: the file changed while it "
                                   f"was read")
        return memoryview(data)

    def close(self) -> None:
        self._data = None


def _reason(exc: BaseException) -> str:
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
