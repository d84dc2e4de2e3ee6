"""Where a reader's bytes come from: memory or a file read by offset (random access)."""

from __future__ import annotations

from typing import BinaryIO


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
