"""PCD point clouds (pypcd4), as the Point Cloud Library writes them: the x, y, z fields, read whole.

PCD has no room for a CRS.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator

import numpy as np
from pypcd4 import PointCloud as PCD

from ..errors import InvalidInputError
from .reader import Reader

__all__ = ["PcdReader", "write_pcd"]


class PcdReader(Reader):
    """A PCD file, read whole on each pass (pypcd4 has no partial read)."""

    def _raw_chunks(self, n: int | None) -> Iterator[np.ndarray]:
        pc = PCD.from_path(self.path)
        if not {"x", "y", "z"} <= set(pc.fields):
            raise InvalidInputError(f"{self.path}: PCD lacks x, y or z fields")
        points = np.asarray(pc.numpy(("x", "y", "z")), dtype=np.float64)
        self.stored_points = points.shape[0]
        yield from self._slices(points, n)


def write_pcd(tmp: Path, points: np.ndarray, crs: dict[str, Any], fmt: str) -> None:
    """Write ``points`` as a binary PCD of float64 x, y, z fields."""
    PCD.from_points(points, ("x", "y", "z"), (np.float64, np.float64, np.float64)).save(tmp)
