"""PLY point clouds (plyfile): the x, y, z of the vertex element, mapped from disk and read in chunks.

A CRS travels as a ``crs WKT`` comment, the only room a PLY header has for it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
from plyfile import PlyData, PlyElement

from ..errors import InvalidInputError
from .reader import Reader, xyz_columns

__all__ = ["PlyReader", "write_ply"]

#: The comment that carries a WKT.
_CRS_COMMENT = "crs "


class PlyReader(Reader):
    """A PLY file: binary vertex data stays on disk and each pass reads it slice by slice."""

    def _open(self) -> None:
        columns, self.crs = self._columns()
        self.stored_points = len(columns[0])

    def _columns(self) -> tuple[list[np.ndarray], dict[str, Any]]:
        """x, y and z as arrays mapped from disk (read as sliced), and the CRS."""
        ply = PlyData.read(str(self.path), mmap=True)
        if "vertex" not in ply:
            raise InvalidInputError(f"{self.path}: PLY file has no vertex element")
        data = ply["vertex"].data
        if not {"x", "y", "z"} <= set(data.dtype.names or ()):
            raise InvalidInputError(f"{self.path}: PLY vertices lack x, y or z")
        return [data[c] for c in "xyz"], ply_crs(ply.comments)

    def _raw_chunks(self, n: int | None) -> Iterator[np.ndarray]:
        # Mapped again on each pass, so that the pages read are not held between passes.
        columns, _ = self._columns()
        size = len(columns[0])
        step = n or max(size, 1)
        for start in range(0, size, step):
            yield xyz_columns(columns, start, start + step)


def ply_crs(comments: Sequence[str]) -> dict[str, Any]:
    """The CRS dict of a PLY header's comments."""
    wkt = next((c[len(_CRS_COMMENT):] for c in comments if c.startswith(_CRS_COMMENT)), None)
    return {"wkt": wkt} if wkt else {}


def write_ply(tmp: Path, points: np.ndarray, crs: dict[str, Any], fmt: str) -> None:
    """Write ``points`` as a binary PLY of float64 vertices, with the CRS's WKT as a comment."""
    vertex = np.empty(points.shape[0], dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
    vertex["x"], vertex["y"], vertex["z"] = points[:, 0], points[:, 1], points[:, 2]
    comments = ["made by dftpcc"] + ([f"{_CRS_COMMENT}{crs['wkt']}"] if crs.get("wkt") else [])
    PlyData([PlyElement.describe(vertex, "vertex")], text=False, comments=comments).write(str(tmp))
