"""NPY point clouds (numpy): an (N, 3+) array or a structured one with x, y, z fields, mapped and read in chunks.

Only real numbers are points: a complex or object array is refused, as
:func:`dftpcc.compress` refuses one.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..errors import InvalidInputError
from .reader import Reader, xyz_columns

__all__ = ["NpyReader", "write_npy"]

#: numpy kinds that are coordinates: boolean, signed, unsigned, float (as :func:`dftpcc.dem.as_points`).
_REAL_KINDS = "biuf"


class NpyReader(Reader):
    """A ``.npy`` file, mapped from disk: each pass reads it slice by slice."""

    def _open(self) -> None:
        self.stored_points = len(self._columns()[0])

    def _columns(self) -> list[np.ndarray]:
        arr = np.load(self.path, mmap_mode="r", allow_pickle=False)
        if arr.dtype.names:
            if not {"x", "y", "z"} <= set(arr.dtype.names):
                raise InvalidInputError(f"{self.path}: the array's fields lack x, y or z "
                                        f"(fields: {', '.join(arr.dtype.names)})")
            columns = [arr[c] for c in "xyz"]
        elif arr.ndim != 2 or arr.shape[1] < 3:
            raise InvalidInputError(f"{self.path}: expected an (N, 3) array, got shape {arr.shape}")
        else:
            columns = [arr[:, k] for k in range(3)]
        for column in columns:
            if column.dtype.kind not in _REAL_KINDS:
                raise InvalidInputError(f"{self.path}: points must be real numbers, got dtype {column.dtype}")
        return columns

    def _raw_chunks(self, n: int | None) -> Iterator[np.ndarray]:
        columns = self._columns()  # mapped again on each pass: pages read are not held between passes
        size = len(columns[0])
        step = n or max(size, 1)
        for start in range(0, size, step):
            yield xyz_columns(columns, start, start + step)


def write_npy(tmp: Path, points: np.ndarray, crs: dict[str, Any], fmt: str) -> None:
    """Write ``points`` as an (N, 3) float64 ``.npy`` (it has no room for a CRS)."""
    with open(tmp, "wb") as fh:
        np.save(fh, points)
