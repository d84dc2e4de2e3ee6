"""A compressed map opened for reading: :func:`open` and :class:`CompressedMap`.

Like ``rasterio.open``: a path, a file object or bytes in, the header parsed
and checked at once, the map decoded (:mod:`dftpcc.decoder`) and rebuilt
(:mod:`dftpcc.rebuild`) only when asked.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Any, BinaryIO, Callable, Sequence

import numpy as np

from .container import (MAGIC, VERSION, VERSION_TILED, Source, cells_allowed, check_max_bytes, check_max_cells,
                        read_tile, unpack_source)
from . import kernels
from .decoder import decode_dem, decode_tiled
from .dem import DEM, Grid
from .errors import InvalidInputError, ResourceLimitError
from .params import Params
from .rebuild import dem_to_points
from .residual import layout_of
from .spectrum import radius_limit
from .units import units_of

__all__ = ["CompressedMap", "open", "decompress", "is_dftpc", "check_bbox"]


class CompressedMap:
    """A ``.dftpc`` map opened for reading; use :func:`open`.

    The header is parsed and checked on opening; the mask and coefficients
    are decoded only when :meth:`read_points` or :meth:`read_dem` asks. A
    tiled map opened from a path keeps the file open and reads only the
    tiles a region needs (``bbox=``); close it, or use ``with``.
    """

    def __init__(self, data: bytes | Source, name: str = "<bytes>", *, max_bytes: int | None = None,
                 max_cells: int | None = None, file_size: int | None = None):
        check_max_bytes(max_bytes)
        self.name = name
        source = data if isinstance(data, Source) else Source(data)
        # With max_bytes the budget follows the whole file, which exists, not the prefix read.
        self.size = source.size if file_size is None else file_size
        if max_bytes is not None and max_bytes < source.size:
            source = Source(bytes(source.read(0, max_bytes)))
        self._source = source
        self._partial = max_bytes is not None
        self._max_cells = max_cells
        self.header, self._blobs = unpack_source(source, allow_truncated_coef=self._partial,
                                                 max_cells=cells_allowed(self.size, max_cells))

    # Context-manager protocol, like rasterio.open.
    def __enter__(self) -> "CompressedMap":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._source.close()

    @property
    def params(self) -> Params:
        return self.header.params

    @property
    def grid(self) -> Grid:
        return self.header.grid

    @property
    def crs(self) -> dict[str, Any]:
        return self.header.crs

    @property
    def tiled(self) -> bool:
        """Whether the map is coded in tiles (format 1.1), so a region decodes on its own."""
        return self.header.tiles is not None

    @property
    def bytes_read(self) -> int:
        """Bytes of the file read so far (header, then the tiles decoded)."""
        return self._source.bytes_read

    def bounds(self) -> tuple[float, float, float, float]:
        """The map's extent ``(xmin, ymin, xmax, ymax)`` in its horizontal unit (the grid's corners)."""
        g = self.grid
        xs, ys = _corners(g, 0, g.rows, 0, g.cols)
        return float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max())

    def read_dem(self, *, cutoff: float | None = None, bbox: Sequence[float] | None = None,
                 map_tiles: Callable[..., list] | None = None) -> DEM:
        """The rebuilt DEM (see :func:`dftpcc.decoder.decode_dem`).

        Parameters
        ----------
        cutoff : float, optional
            Decode at a larger cutoff than the file's (untiled maps only).
        bbox : (xmin, ymin, xmax, ymax), optional
            Only this region, in the map's horizontal unit and CRS: the DEM
            of the cells it touches, with only the cells whose centre lies
            inside it marked occupied. Of a tiled map only the tiles the box
            touches are read and decoded.
        map_tiles : callable, optional
            Where a tiled map's tiles are decoded (:func:`dftpcc.cluster.executor`).

        Raises
        ------
        InvalidInputError
            A malformed bbox, or one that misses the map (the message gives its extent).
        CorruptFileError
            A section fails to decode, or decodes to non-finite heights; of a
            tiled map, naming the damaged tile.
        """
        window = None if bbox is None else self._window(bbox)
        with self._kernels():
            return self._read_dem(cutoff, bbox, window, map_tiles)

    def _kernels(self) -> Any:
        """The kernels' backend for a read of this map: the caller's, or the default for its points."""
        return kernels.use(work=self.header.point_count, min_work=kernels.COMPILED_MIN_MAP_POINTS)

    def _read_dem(self, cutoff: float | None, bbox: Sequence[float] | None,
                  window: tuple[tuple[int, int], tuple[int, int]] | None,
                  map_tiles: Callable[..., list] | None) -> DEM:
        if self.header.tiles is None:
            dem = decode_dem(self.header, self._blobs, cutoff=cutoff, allow_partial=self._partial)
            if window is not None:
                (r0, r1), (c0, c1) = window
                dem = DEM(grid=dem.grid.window(r0, c0, r1 - r0, c1 - c0), heights=dem.heights[r0:r1, c0:c1],
                          mask=dem.mask[r0:r1, c0:c1])
        else:
            if cutoff is not None:
                raise InvalidInputError("a tiled map (format 1.1) decodes at its own cutoff only")
            rows, cols = window or ((0, self.grid.rows), (0, self.grid.cols))
            self._check_budget(rows, cols)
            dem = decode_tiled(self.header, self._blobs,
                               lambda k: read_tile(self._source, self.header, k), rows=rows, cols=cols,
                               map_tiles=map_tiles)
        if bbox is not None:
            dem = DEM(grid=dem.grid, heights=dem.heights, mask=dem.mask & _centres_inside(dem.grid, bbox))
        return dem

    def read_window(self, rows: tuple[int, int], cols: tuple[int, int], *,
                    map_tiles: Callable[..., list] | None = None) -> DEM:
        """The DEM of the cells ``rows`` x ``cols`` (``(start, stop)`` cell ranges) of a tiled map,
        decoding only its tiles (a map larger than memory is decoded band by band so)."""
        if self.header.tiles is None:
            raise InvalidInputError("read_window reads a tiled map; read an untiled one whole (read_dem)")
        g = self.grid
        if not (0 <= rows[0] < rows[1] <= g.rows and 0 <= cols[0] < cols[1] <= g.cols):
            raise InvalidInputError(f"window rows {rows}, cols {cols} is not inside the {g.rows} x {g.cols} grid")
        self._check_budget(rows, cols)
        with self._kernels():
            return decode_tiled(self.header, self._blobs, lambda k: read_tile(self._source, self.header, k),
                                rows=rows, cols=cols, map_tiles=map_tiles)

    def read_points(self, *, cutoff: float | None = None, bbox: Sequence[float] | None = None) -> np.ndarray:
        """The rebuilt cloud, shape (cells, 3), float64, original frame (metres); ``bbox`` as for :meth:`read_dem`."""
        with self._kernels():
            return dem_to_points(self.read_dem(cutoff=cutoff, bbox=bbox))

    def _window(self, bbox: Sequence[float]) -> tuple[tuple[int, int], tuple[int, int]]:
        """The rows and columns of the cells ``bbox`` touches, checked against the map's extent."""
        g = self.grid
        extent = self.bounds()

        def describe() -> str:
            return (f"the map covers x {extent[0]:.10g} to {extent[2]:.10g} and y {extent[1]:.10g} to "
                    f"{extent[3]:.10g}")
        try:
            xmin, ymin, xmax, ymax = check_bbox(bbox)
        except InvalidInputError as exc:
            raise InvalidInputError(f"{exc}; {describe()}") from None
        corners = np.array([[xmin, ymin], [xmax, ymin], [xmin, ymax], [xmax, ymax]])
        u, v = g.to_local(corners)
        c0, c1 = int(np.floor(u.min() / g.resolution)), int(np.floor(u.max() / g.resolution)) + 1
        r0, r1 = int(np.floor(v.min() / g.dy)), int(np.floor(v.max() / g.dy)) + 1
        c0, c1, r0, r1 = max(c0, 0), min(c1, g.cols), max(r0, 0), min(r1, g.rows)
        if c0 >= c1 or r0 >= r1:
            raise InvalidInputError(f"bbox {xmin:.10g},{ymin:.10g},{xmax:.10g},{ymax:.10g} lies outside the map: "
                                    f"{describe()}")
        return (r0, r1), (c0, c1)

    def _check_budget(self, rows: tuple[int, int], cols: tuple[int, int]) -> None:
        """Refuse decoding together more cells than the file's size justifies (format.md, *Tiles*)."""
        assert self.header.tiles is not None
        tiling = self.header.tiles.tiling
        # Every cell of the tiles touched, empty tiles too: the DEM decoded spans them all, so a
        # small file naming a huge, nearly empty grid must not allocate it. Plus the base layer,
        # whose coefficient count grows with the grid, not with the tiles decoded, and the map mask
        # and residual.
        s = tiling.size
        height = min(tiling.rows, -(-rows[1] // s) * s) - rows[0] // s * s
        width = min(tiling.cols, -(-cols[1] // s) * s) - cols[0] // s * s
        cells = height * width + _base_extent(self.header.grid, s, self.header.params.cutoff,
                                              self.header.tiles.base_cycles)
        # Decoded whole for any region.
        cells += self.header.grid.size * (int(self.header.tiles.map_mask) + int(self.header.tiles.map_resid))
        allowed = cells_allowed(self.size, self._max_cells)
        if cells > allowed:
            raise ResourceLimitError(
                f"refusing to decode {cells:,} cells of tiles at once, more than the {allowed:,} allowed for a "
                f"{self.size:,}-byte file; decode a region (bbox=) or, if you trust this file, open it with "
                f"max_cells={cells} (command line: --max-cells {cells})")

    def info(self) -> dict[str, Any]:
        """Header, parameters and sizes as plain JSON-ready data."""
        h = self.header
        g = h.grid
        out = {
            "file": self.name,
            "bytes": self.size,
            "format_version": "{}.{}".format(*(VERSION_TILED if h.tiles is not None else VERSION)),
            "points_original": h.point_count,
            "points_rebuilt": h.cell_count,
            "bits_per_point": 8.0 * self.size / h.point_count if h.point_count else None,
            "grid": {"rows": g.rows, "cols": g.cols, "resolution_m": g.resolution,
                     "resolution_y_m": g.resolution_y, "origin": [g.x0, g.y0], "z0_m": g.z0,
                     "angle_rad": g.angle},
            # The "_m" fields are in these units: metres unless the CRS says otherwise.
            "units": dataclasses.asdict(units_of(h.crs)),
            "params": json.loads(h.params.to_json()),
            "plane": list(h.plane),
            "crs": (h.crs.get("wkt") or ("LAS GeoKeys" if h.crs.get("las_vlrs") else None)),
            "stats": h.stats,
        }
        if b"RESD" in self._blobs:  # an untiled file's residual layer, or a tiled one's map residual
            out["residual_layout"] = layout_of(self._blobs[b"RESD"])
        if h.tiles is not None:
            index = h.tiles
            tiling = index.tiling
            out["tiles"] = {
                "size": tiling.size, "tile_rows": tiling.tile_rows, "tile_cols": tiling.tile_cols,
                "count": tiling.count, "occupied": int(np.count_nonzero(index.cells)),
                "tiles": [{"tile": k + 1, "row": k // tiling.tile_cols, "col": k % tiling.tile_cols,
                           "cells": int(index.cells[k]), "bytes": index.tile_bytes(k),
                           "dem_rmse_m": float(index.rmse[k]), "dem_max_error_m": float(index.max_error[k])}
                          for k in map(int, np.flatnonzero(index.cells))],
            }
        return out


def _base_extent(g: Grid, size: int, cutoff: float, cycles: int) -> int:
    """Frequency pairs (i, j) :func:`dftpcc.tiles.base_order` enumerates to find a tiled map's base
    layer of ``cycles`` per tile (the reach its TIDX states).

    They grow with the grid, not with the tiles decoded (a crafted 1 KB file can ask for tens of
    millions), and every decode derives them, whatever the file's STAT claims: they count in the budget.
    """
    limit = min(max(g.rows, g.cols) / size * cycles, radius_limit(g.shape, cutoff))
    side = int(2 * limit * (1 + 1e-9)) + 1
    return min(g.rows, side) * min(g.cols, side)


def check_bbox(bbox: Any) -> tuple[float, float, float, float]:
    """``bbox`` as four finite floats ``(xmin, ymin, xmax, ymax)`` with min <= max, else InvalidInputError."""
    try:
        values = tuple(float(v) for v in bbox)
    except (TypeError, ValueError):
        raise InvalidInputError(f"bbox must be four numbers XMIN,YMIN,XMAX,YMAX; got {bbox!r}") from None
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise InvalidInputError(f"bbox must be four finite numbers XMIN,YMIN,XMAX,YMAX; got {bbox!r}")
    xmin, ymin, xmax, ymax = values
    if xmin > xmax or ymin > ymax:
        raise InvalidInputError(f"bbox {xmin:.10g},{ymin:.10g},{xmax:.10g},{ymax:.10g} has "
                                f"{'XMIN > XMAX' if xmin > xmax else 'YMIN > YMAX'}")
    return values  # type: ignore[return-value]


def _corners(g: Grid, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
    """World x, y of the four corners of the cells [r0, r1) x [c0, c1)."""
    u = np.array([c0, c1, c0, c1], dtype=float) * g.resolution
    v = np.array([r0, r0, r1, r1], dtype=float) * g.dy
    c, s = math.cos(g.angle), math.sin(g.angle)
    return g.x0 + c * u - s * v, g.y0 + s * u + c * v


def _centres_inside(g: Grid, bbox: Sequence[float]) -> np.ndarray:
    """Which cells of ``g`` have their centre inside ``bbox`` (edges included)."""
    xmin, ymin, xmax, ymax = bbox
    if g.angle == 0.0:
        # x follows the column and y the row alone: the same centres, a line of each (a 512-cell
        # tile's read spent 2 ms in the whole grid of them).
        r, c = np.arange(g.rows), np.arange(g.cols)
        x, _ = g.centres(np.zeros(g.cols), c)
        _, y = g.centres(r, np.zeros(g.rows))
        return ((y >= ymin) & (y <= ymax))[:, None] & ((x >= xmin) & (x <= xmax))[None, :]
    rows, cols = np.indices(g.shape)
    x, y = g.centres(rows.ravel(), cols.ravel())
    return ((x >= xmin) & (x <= xmax) & (y >= ymin) & (y <= ymax)).reshape(g.shape)


def open(source: str | os.PathLike[str] | BinaryIO | bytes, *, max_bytes: int | None = None,  # noqa: A001
         max_cells: int | None = None) -> CompressedMap:
    """Open a compressed map from a path, a binary file object or bytes.

    Parameters
    ----------
    source : path, file-like or bytes
    max_bytes : int, optional
        Read only the first ``max_bytes`` bytes, as if the rest had not been
        received yet; the map decodes from the low frequencies it holds.
    max_cells : int, optional
        Largest grid (rows x cols) to accept. By default a file may ask for
        :func:`cell_budget` of its size; raise it for a trusted file that
        :class:`~dftpcc.errors.ResourceLimitError` refused.

    Raises
    ------
    InvalidInputError
        The path does not exist or is not a file, or a bad argument.
    CorruptFileError
        The content is not a valid ``.dftpc`` stream.
    ResourceLimitError
        The header asks for a grid over the budget.
    UnsupportedFormatError
        Another major version of the format.
    """
    # The arguments first (as rasterio does): a bad one is refused before the file is touched.
    check_max_bytes(max_bytes)
    check_max_cells(max_cells)
    if isinstance(source, (bytes, bytearray, memoryview)):
        return CompressedMap(bytes(source), max_bytes=max_bytes, max_cells=max_cells)
    if hasattr(source, "read"):
        return CompressedMap(source.read(), getattr(source, "name", "<stream>"), max_bytes=max_bytes,
                             max_cells=max_cells)
    path = Path(source)
    if not path.is_file():
        raise InvalidInputError(f"{path}: no such file")
    fh = path.open("rb")
    try:
        size = os.fstat(fh.fileno()).st_size
        if max_bytes is not None:
            data = fh.read(max_bytes)
            fh.close()
            return CompressedMap(data, str(path), max_bytes=max_bytes, max_cells=max_cells,
                                 file_size=max(size, len(data)))
        # Read by offset: an untiled map is read whole, a tiled one tile by tile as asked.
        return CompressedMap(Source(file=fh, size=size), str(path), max_cells=max_cells)
    except BaseException:
        fh.close()
        raise


def is_dftpc(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a ``.dftpc`` file (by its magic bytes, not its name)."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(f"{path}: no such file")
    with path.open("rb") as fh:
        return fh.read(len(MAGIC)) == MAGIC


def decompress(data: bytes, *, max_bytes: int | None = None, cutoff: float | None = None,
               backend: kernels.Backend | str | None = None) -> np.ndarray:
    """Decode ``.dftpc`` bytes into a point cloud (:func:`open` of the bytes, then its points).

    Parameters
    ----------
    data : bytes
    max_bytes : int, optional
        Use only the first ``max_bytes`` bytes (progressive decoding: a
        prefix holds the low frequencies; untiled maps only).
    cutoff : float, optional
        Decode-time cutoff, at least the file's (untiled maps only).
    backend : {'numpy', 'compiled'} or dftpcc.kernels.Backend, optional
        Where the kernels run, the same points either way; by default as :func:`dftpcc.compress`
        chooses, from :data:`~dftpcc.kernels.COMPILED_MIN_MAP_POINTS` points the map was made from.

    Returns
    -------
    ndarray, shape (cells, 3), float64
        One point per occupied cell, metres, original frame.
    """
    check_max_bytes(max_bytes)
    if backend is not None:  # refused before the bytes are parsed, as every other argument
        backend = kernels.Backend.of(backend)
    # The bytes' own size sets the decoding budget, as open() does for any file: a small crafted
    # file cannot make this allocate a grid of 2**36 cells.
    with open(bytes(data), max_bytes=max_bytes) as cmap, \
            kernels.use(backend, work=cmap.header.point_count, min_work=kernels.COMPILED_MIN_MAP_POINTS):
        return cmap.read_points(cutoff=cutoff)
