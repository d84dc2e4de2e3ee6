"""Text point clouds (numpy): XYZ/TXT (whitespace) and CSV, x, y, z in the first three columns, read whole.

A first line that is not numbers is a header and skipped; text has no room for a CRS.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .reader import Reader

__all__ = ["TextReader", "write_text"]

#: Decimals written per coordinate (micrometres for metres).
TEXT_DECIMALS = 6


class TextReader(Reader):
    """An XYZ, TXT or CSV file, parsed whole on each pass (text cannot be mapped)."""

    def _raw_chunks(self, n: int | None) -> Iterator[np.ndarray]:
        with self.path.open("r", encoding="utf-8", errors="replace") as fh:
            first = fh.readline()
        delimiter = "," if "," in first else None
        skip = 0
        try:
            [float(t) for t in (first.split(",") if delimiter else first.split())[:3]]
        except ValueError:
            skip = 1  # a header line
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # an empty file is reported as "no points"
            data = np.loadtxt(self.path, delimiter=delimiter, skiprows=skip, usecols=(0, 1, 2), ndmin=2,
                              dtype=np.float64)
        self.stored_points = data.shape[0]
        yield from self._slices(data, n)


def write_text(tmp: Path, points: np.ndarray, crs: dict[str, Any], fmt: str) -> None:
    """Write ``points`` as text: space-separated for ``xyz``, comma-separated with an ``x,y,z`` header for ``csv``."""
    np.savetxt(tmp, points, fmt=f"%.{TEXT_DECIMALS}f", delimiter="," if fmt == "csv" else " ",
               header="x,y,z" if fmt == "csv" else "", comments="")
