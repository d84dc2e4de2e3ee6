"""What every reader of the read stage shares: open a file, know its count and CRS, give its points in chunks.

A format module subclasses :class:`Reader` and says how to open its file
(:meth:`Reader._open`) and how to yield its raw x, y, z (:meth:`Reader._raw_chunks`);
the checks, the non-finite rows and the one error message for a bad file live here.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Iterator, Sequence

import numpy as np

from ..dem import nonfinite_error
from ..errors import InvalidInputError, MissingDependencyError, MissingFileError
from ..remote import Remote, is_url

__all__ = ["PointCloud", "Reader", "DEFAULT_CHUNK_POINTS", "xyz_columns", "crs_wkt", "parse_crs"]

#: Points per chunk unless told otherwise (about 24 MB of float64 x, y, z).
DEFAULT_CHUNK_POINTS = 1_000_000

#: Where each selection option applies, for the refusal of a format that cannot honour it.
_OPTION_HOME = {
    "classes": "classes can only be selected in LAS/LAZ files",
    "topic": "a topic can only be chosen in ROS bags",
    "pose_topic": "poses can only be read from ROS bags",
    "map_frame": "a map frame can only be chosen in ROS bags (with a TF pose topic)",
}


@dataclass
class PointCloud:
    """Points and the georeferencing they came with.

    Attributes
    ----------
    points : ndarray, shape (N, 3), float64
        x, y, z in the file's units (metres for dftpcc's defaults).
    crs : dict
        ``{"wkt": ..., "las_vlrs": [...]}``; empty when the file has none.
    """

    points: np.ndarray
    crs: dict[str, Any] = field(default_factory=dict)

    @property
    def crs_wkt(self) -> str | None:
        """The CRS as WKT (what GDAL, PDAL and pyproj take), or None when the file had none."""
        return crs_wkt(self.crs)

    def parse_crs(self) -> Any:
        """The CRS as a ``rasterio.crs.CRS`` (as laspy's ``header.parse_crs()``), or None."""
        return parse_crs(self.crs)

    def __repr__(self) -> str:
        wkt = self.crs_wkt
        crs = "no CRS" if not self.crs else f"CRS {wkt[:40]!r}..." if wkt else "LAS GeoKeys CRS"
        return f"<PointCloud of {self.points.shape[0]:,} points, {crs}>"


def crs_wkt(crs: dict[str, Any] | None) -> str | None:
    """The WKT of a CRS dict ``{"wkt": ..., "las_vlrs": [...]}``, or None when it has none (no CRS, or
    LAS GeoKeys only: those are written back to LAS byte for byte, not parsed)."""
    return str(crs["wkt"]) if crs and crs.get("wkt") else None


def parse_crs(crs: dict[str, Any] | None) -> Any:
    """A CRS dict as a ``rasterio.crs.CRS`` (rasterio is a dependency; ``pyproj.CRS(result.to_wkt())``
    converts it), or None when there is none or GDAL cannot read it."""
    from rasterio.crs import CRS
    from rasterio.errors import CRSError

    wkt = crs_wkt(crs)
    if wkt is None:
        return None
    try:
        return CRS.from_wkt(wkt)
    except CRSError:
        return None


def xyz_columns(columns: Sequence[np.ndarray], start: int = 0, stop: int | None = None) -> np.ndarray:
    """Rows ``start:stop`` of three x, y, z column arrays (perhaps mapped from disk) as one (n, 3) float64 array."""
    return np.column_stack([np.asarray(c[start:stop], dtype=np.float64) for c in columns])


class Reader:
    """A point cloud file opened for reading, in the manner of laspy's ``LasReader``.

    Opening reads the header only (where the format has one); each
    :meth:`chunks` call is a new pass over the file, so memory holds one
    chunk, not the cloud; :meth:`read` is the pass of a single chunk.
    Use as a context manager, or call :meth:`close`.

    Parameters
    ----------
    path : path or str
        The file (a ROS 2 bag: its folder), or its URL for the formats read by range requests
        (``Format.by_url``): :attr:`remote` then reads it, each response checked against the
        file as first seen.
    format : str
        The format name it is read as (``las``, ``laz``, ...).
    classes : sequence of int, optional
        Classification codes to keep, for the formats that have them.
    topic : str, optional
        The PointCloud2 topic, for ROS bags.
    pose_topic : str, optional
        The topic of the scans' poses, for ROS bags of scans in the sensor
        frame (see :mod:`dftpcc.io.rosbag`).
    map_frame : str, optional
        ROS bags with a TF ``pose_topic``: the frame to place the scans in
        (default: the root of their TF tree).
    drop_nonfinite : bool
        Drop rows with a NaN or infinite coordinate rather than refuse them.
    chunk_points : int, optional
        Points per chunk of :meth:`chunks`; None: the whole cloud as one chunk.
    streams : bool
        Whether the format is read chunk by chunk from disk (else a pass
        reads the file whole and slices it).

    Attributes
    ----------
    stored_points : int or None
        Points the file holds before any selection, from its header; None
        when the format has no count (a ROS bag) or only once it is read.
    crs : dict
        As :attr:`PointCloud.crs`.
    dropped : int
        Rows dropped as non-finite in the last complete pass.

    Raises
    ------
    InvalidInputError
        A missing or unreadable file, an option the format cannot honour
        (named with the format), a bad ``chunk_points``.
    """

    #: Selection options this format honours (``classes``, ``topic``).
    options: ClassVar[frozenset[str]] = frozenset()
    #: Whether the source is a raster whose pixels form a DEM of their own (see :meth:`dem`).
    own_grid: ClassVar[bool] = False

    def __init__(self, path: str | os.PathLike[str], *, format: str,  # noqa: A002
                 classes: Sequence[int] | None = None, topic: str | None = None, drop_nonfinite: bool = False,
                 chunk_points: int | None = None, streams: bool = False, pose_topic: str | None = None,
                 map_frame: str | None = None):
        #: The file at a URL (its length and ETag taken now), or None for a local path.
        self.remote = Remote(str(path)) if is_url(path) else None
        self.path: Path | str = str(path) if self.remote is not None else Path(path)
        self.format = format
        self.classes, self.topic, self.drop_nonfinite = classes, topic, drop_nonfinite
        self.pose_topic, self.map_frame = pose_topic, map_frame
        self.streams = streams
        self._locate()
        for name, value in (("classes", classes), ("topic", topic), ("pose_topic", pose_topic),
                            ("map_frame", map_frame)):
            if value is not None and name not in self.options:
                raise InvalidInputError(f"{self.path}: the {name} option does not apply to {format} files; "
                                        f"{_OPTION_HOME[name]}")
        if chunk_points is not None and not (isinstance(chunk_points, int) and chunk_points > 0):
            raise InvalidInputError(f"chunk_points must be a positive integer, got {chunk_points!r}")
        self.chunk_points = chunk_points
        self.stored_points: int | None = None
        self.crs: dict[str, Any] = {}
        self.dropped = 0
        with self._errors():
            self._open()

    # -- what a format module provides -------------------------------------------------------------

    def _locate(self) -> None:
        """Refuse a source that is not there (a ROS bag also accepts a folder; a URL was checked on opening)."""
        if self.remote is None and not Path(self.path).is_file():
            raise MissingFileError(self.path)

    def _open(self) -> None:
        """Read the header: set :attr:`stored_points` and :attr:`crs` where the format has them."""

    def _raw_chunks(self, n: int | None) -> Iterator[np.ndarray]:
        """One pass: (m, 3) float64 arrays of the selected points, about ``n`` each (None: one chunk)."""
        raise NotImplementedError

    def dem(self) -> Any:
        """The DEM on the source's own pixel grid, for a raster (:attr:`own_grid`) source."""
        raise InvalidInputError(f"{self.path}: {self.format} files hold points, not a DEM")

    def _binary(self) -> Any:
        """The file as an open binary file object: local, or the URL read by checked range requests."""
        return open(self.path, "rb") if self.remote is None else self.remote.open()

    # -- what every reader offers ------------------------------------------------------------------

    @property
    def points_bound(self) -> int | None:
        """An upper bound of the points a pass yields, for memory planning (points); None if unknown."""
        return self.stored_points

    def chunks(self, n: int | None = None) -> Iterator[np.ndarray]:
        """One pass over the file: finite (m, 3) float64 arrays of the selected points.

        Parameters
        ----------
        n : int, optional
            Points per chunk (a ROS bag gives whole messages, about ``n``);
            default the ``chunk_points`` the reader was opened with, where
            None is the whole cloud as one chunk.

        Raises
        ------
        InvalidInputError
            A row with a NaN or infinite coordinate (unless ``drop_nonfinite``;
            rows are counted from the start of the file's selected points),
            or a file that stops being readable part way.
        """
        return self._pass(self.chunk_points if n is None else n, keep_nonfinite=False)

    def read(self) -> PointCloud:
        """The whole cloud: the pass of one chunk.

        Unlike :meth:`chunks`, rows with a NaN or infinite coordinate are
        returned as stored unless ``drop_nonfinite`` (compression refuses
        them, with their row numbers).

        Raises
        ------
        InvalidInputError
            An unreadable file, no point (of the selected classes), or only
            non-finite points when they are dropped.
        """
        parts = list(self._pass(None, keep_nonfinite=not self.drop_nonfinite))
        points = parts[0] if len(parts) == 1 else np.concatenate(parts) if parts else np.zeros((0, 3))
        if not points.shape[0]:
            raise self.empty_error()
        return PointCloud(points, self.crs)

    def empty_error(self) -> InvalidInputError:
        """The error for a pass that gave no point: all dropped, none stored, or none of the selected classes."""
        if self.dropped:
            return InvalidInputError(f"{self.path}: all {self.dropped:,} points have NaN or infinite coordinates")
        return InvalidInputError(f"{self.path}: no points" + (" of the selected classes" if self.classes else ""))

    def close(self) -> None:
        """Release what the reader holds open (nothing for most formats: each pass opens the file)."""

    def __enter__(self) -> Reader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.format} {str(self.path)!r}, {self.stored_points} points>"

    # -- shared machinery --------------------------------------------------------------------------

    def _pass(self, n: int | None, *, keep_nonfinite: bool) -> Iterator[np.ndarray]:
        row, dropped = 0, 0
        with self._errors():
            for pts in self._raw_chunks(n):
                finite = np.isfinite(pts).all(axis=1)
                if not keep_nonfinite and not finite.all():
                    if not self.drop_nonfinite:
                        total = "the file's" + (f" {self.stored_points:,}" if self.stored_points is not None else "")
                        raise nonfinite_error(row + np.flatnonzero(~finite), total)
                    dropped += int(pts.shape[0] - finite.sum())
                    pts = pts[finite]
                row += pts.shape[0]
                yield pts
        self.dropped = dropped

    @contextmanager
    def _errors(self) -> Iterator[None]:
        """Third-party readers raise anything on a bad file: one clear error instead."""
        try:
            yield
        except (InvalidInputError, MissingDependencyError):
            raise
        except Exception as exc:
            if self.remote is not None and self.remote.error is not None:
                raise self.remote.error from None  # a failed read of the URL, wrapped by the format's library  # noqa: BLE001 - laspy, plyfile, pypcd4, GDAL, rosbags have no common error
            raise InvalidInputError(f"{self.path}: cannot read as {self.format}: {exc}") from None

    @staticmethod
    def _slices(points: np.ndarray, n: int | None) -> Iterator[np.ndarray]:
        """A cloud read whole, as chunks of ``n`` (None: itself)."""
        if n is None or n >= points.shape[0]:
            yield points
            return
        for start in range(0, points.shape[0], n):
            yield points[start:start + n]
