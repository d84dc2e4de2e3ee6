"""The container: what ``dftpcc.open`` accepts and refuses, and what ``pack`` will write.

The corrupt-file corpus (tests/test_corrupt.py) covers the reader's checks one file each;
these tests pin the rules that involve both sides: the arguments of ``open``, the integers of
the section table, the bytes after the last section, and the writer applying the reader's checks.
"""

from __future__ import annotations

import io

import pytest

import dftpcc
from dftpcc.errors import InvalidInputError

from .fuzz.seeds import seed_files


@pytest.fixture(scope="module")
def seeds() -> dict[str, bytes]:
    return seed_files()


@pytest.fixture(scope="module")
def good(seeds) -> bytes:
    return seeds["with_crs"]


# --- the arguments of open ---------------------------------------------------------------------------

class _Unread(io.BytesIO):
    """A stream that fails the test if anything reads it."""

    def read(self, *args):  # type: ignore[override]
        raise AssertionError("the file was read before the arguments were checked")


@pytest.mark.parametrize("bad", [0, -1, 1.5, "100", True])
def test_max_bytes_is_checked_before_the_file_is_read(tmp_path, good, bad):
    with pytest.raises(InvalidInputError, match="max_bytes"):
        dftpcc.open(_Unread(good), max_bytes=bad)
    # A path is not even looked at: the argument is wrong whatever the file.
    with pytest.raises(InvalidInputError, match="max_bytes"):
        dftpcc.open(tmp_path / "missing.dftpc", max_bytes=bad)
    with pytest.raises(InvalidInputError, match="max_bytes"):
        dftpcc.decompress(good, max_bytes=bad)


@pytest.mark.parametrize("bad", [0, -1, 1.5, "10", True])
def test_max_cells_is_checked_before_the_file_is_read(tmp_path, good, bad):
    with pytest.raises(InvalidInputError, match="max_cells"):
        dftpcc.open(_Unread(good), max_cells=bad)
    with pytest.raises(InvalidInputError, match="max_cells"):
        dftpcc.open(tmp_path / "missing.dftpc", max_cells=bad)


def test_a_negative_max_bytes_does_not_read_the_whole_file(tmp_path, good):
    path = tmp_path / "m.dftpc"
    path.write_bytes(good)
    with pytest.raises(InvalidInputError, match="max_bytes must be a positive"):
        dftpcc.open(path, max_bytes=-1)
