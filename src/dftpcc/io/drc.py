"""Draco point clouds (``.drc``, Google's geometry compression), decoded whole by DracoPy.

Reading needs the optional DracoPy package (``pip install 'dftpcc[draco]'``).
Draco stores quantized float32 positions and no CRS; the points come back as
float64 in the file's own units.
"""

from __future__ import annotations

from typing import Iterator

import numpy as np

from .._optional import import_optional, install_hint
from ..errors import InvalidInputError
from .reader import Reader

__all__ = ["DracoReader", "INSTALL_HINT"]

INSTALL_HINT = install_hint("draco")


class DracoReader(Reader):
    """A Draco file: its geometry (point cloud or mesh vertices) decoded whole on each pass."""

    def _open(self) -> None:
        _dracopy()  # a missing package is said before any work

    def _raw_chunks(self, n: int | None) -> Iterator[np.ndarray]:
        decoded = _dracopy().decode(self.path.read_bytes())
        points = np.asarray(decoded.points, dtype=np.float64)
        if points.size == 0:
            points = points.reshape(0, 3)  # an empty geometry has no shape to speak of
        if points.ndim != 2 or points.shape[1] != 3:
            raise InvalidInputError(f"{self.path}: expected x, y, z positions, got shape {points.shape}")
        self.stored_points = points.shape[0]
        yield from self._slices(points, n)


def _dracopy():  # type: ignore[no-untyped-def]
    return import_optional("DracoPy", "draco", needed_for="reading Draco files")
