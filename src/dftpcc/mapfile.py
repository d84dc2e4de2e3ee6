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

from .format import (MAGIC, VERSION, RemoteSource, Source, cells_allowed, check_max_bytes,
                     check_max_cells, is_url, read_tile, unpack_source)
from . import kernels
from .decoder import Whole, decode_dem, decode_window
from .dem import DEM, Grid
from .errors import InvalidInputError, MissingFileError, ResourceLimitError, advice
from .params import Params
from .rebuild import dem_to_points
from .residual import layout_of
from .spectrum import radius_limit
from .units import units_of
from .io.reader import crs_wkt, parse_crs

__all__ = ["CompressedMap", "open", "decompress", "is_dftpc", "check_bbox"]

#: Rows of the bands an untiled map is written in band by band (a GeoTIFF block is 256 rows).
UNTILED_BLOCK = 512


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
        self._whole: Whole | None = None  # an untiled map's decoded mask and spectrum, once read
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
        """The CRS as the file stores it (``{"wkt": ..., "las_vlrs": [...]}``); see :attr:`crs_wkt`."""
        return self.header.crs

    @property
    def crs_wkt(self) -> str | None:
        """The CRS as WKT (what GDAL, PDAL and pyproj take), or None."""
        return crs_wkt(self.header.crs)

    def parse_crs(self) -> Any:
        """The CRS as a ``rasterio.crs.CRS`` (as rasterio's ``dataset.crs``), or None."""
        return parse_crs(self.header.crs)

    def __repr__(self) -> str:
        g = self.grid
        layout = "tiled" if self.tiled else "untiled"
        crs = units_of(self.header.crs).crs or "no CRS"
        return (f"<CompressedMap {self.name!r}: {self.size:,} bytes, {g.rows:,} x {g.cols:,} cells of "
                f"{g.resolution:g}, {self.header.cell_count:,} rebuilt, {layout}, cutoff {self.params.cutoff:g}, "
                f"{crs}>")

    @property
    def tiled(self) -> bool:
        """Whether the map is coded in tiles (format 1.1), so a region decodes on its own."""
        return self.header.tiles is not None

    @property
    def tile_count(self) -> int:
        """Tiles of the map's tiling (an untiled map is one tile)."""
        return self.header.tiles.tiling.count if self.header.tiles is not None else 1

    @property
    def block(self) -> int:
        """Rows (and columns) of the windows a band-by-band reader asks for: a tiled map's tile size, or
        :data:`UNTILED_BLOCK` cells of an untiled map."""
        return self.header.tiles.tiling.size if self.header.tiles is not None else UNTILED_BLOCK

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
        # By the cells it rebuilds, which the reader bounded by the file's size, not by the points a
        # header says the map was made from: a crafted header must not make a small read load numba.
        return kernels.use(work=self.header.cell_count, min_work=kernels.COMPILED_MIN_MAP_CELLS)

    def _read_dem(self, cutoff: float | None, bbox: Sequence[float] | None,
                  window: tuple[tuple[int, int], tuple[int, int]] | None,
                  map_tiles: Callable[..., list] | None) -> DEM:
        whole = window is None or window == ((0, self.grid.rows), (0, self.grid.cols))
        if cutoff is not None or self._partial or (whole and self.header.tiles is None):
            # An untiled map whole (its mask decoded beside its spectrum), or its own features: a
            # coarser cutoff, a prefix of the file (decoded whole).
            if self.header.tiles is not None:
                raise InvalidInputError("a tiled map (format 1.1) decodes at its own cutoff only")
            dem = decode_dem(self.header, self._blobs, cutoff=cutoff, allow_partial=self._partial)
            if window is not None:
                (r0, r1), (c0, c1) = window
                dem = DEM(grid=dem.grid.window(r0, c0, r1 - r0, c1 - c0), heights=dem.heights[r0:r1, c0:c1],
                          mask=dem.mask[r0:r1, c0:c1])
        else:
            rows, cols = window or ((0, self.grid.rows), (0, self.grid.cols))
            dem = self.read_window(rows, cols, map_tiles=map_tiles)
        if bbox is not None:
            dem = DEM(grid=dem.grid, heights=dem.heights, mask=dem.mask & _centres_inside(dem.grid, bbox))
        return dem

    def read_window(self, rows: tuple[int, int], cols: tuple[int, int], *,
                    map_tiles: Callable[..., list] | None = None) -> DEM:
        """The DEM of the cells ``rows`` x ``cols`` (``(start, stop)`` cell ranges), decoding only what
        they need: a tiled map's tiles they touch; of an untiled map, its mask and coefficients once
        (kept for the next window) and the inverse transform on the window alone. A map larger than
        memory is decoded band by band so."""
        g = self.grid
        if not (0 <= rows[0] < rows[1] <= g.rows and 0 <= cols[0] < cols[1] <= g.cols):
            raise InvalidInputError(f"window rows {rows}, cols {cols} is not inside the {g.rows} x {g.cols} grid")
        if self.header.tiles is not None:
            self._check_budget(rows, cols)
        with self._kernels():
            if self.header.tiles is None and self._whole is None:
                if self._partial:
                    raise InvalidInputError("a prefix of a map (max_bytes) decodes whole: use read_dem")
                self._whole = Whole(self.header, self._blobs)
            return decode_window(self.header, self._blobs, lambda k: read_tile(self._source, self.header, k),
                                 rows=rows, cols=cols, map_tiles=map_tiles, whole=self._whole)

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
        # Clipped to the map in floating point before any integer: a finite box of 1e308 m would
        # otherwise become an infinite cell index (or overflow rotating into the grid's axes).
        x0, x1 = max(xmin, extent[0]), min(xmax, extent[2])
        y0, y1 = max(ymin, extent[1]), min(ymax, extent[3])
        c0 = c1 = r0 = r1 = 0
        if x0 <= x1 and y0 <= y1:
            u, v = g.to_local(np.array([[x0, y0], [x1, y0], [x0, y1], [x1, y1]]))
            cols = np.clip(np.floor(np.array([u.min(), u.max()]) / g.resolution), -1, g.cols)
            rows = np.clip(np.floor(np.array([v.min(), v.max()]) / g.dy), -1, g.rows)
            c0, c1 = max(int(cols[0]), 0), min(int(cols[1]) + 1, g.cols)
            r0, r1 = max(int(rows[0]), 0), min(int(rows[1]) + 1, g.rows)
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
                f"{self.size:,}-byte file; decode a region ({advice('bbox=', '--bbox')}) or, if you trust this "
                f"file, {advice(f'open it with max_cells={cells}', f'give --max-cells {cells}')}")

    def _spectrum_empty(self) -> bool:
        """Whether an untiled map's coefficients are all 0 (a map coded as its residual layer alone)."""
        from . import coding, spectrum

        p = self.header.params
        lay = spectrum.layout(p.transform, p.storage, self.grid.shape, legacy=self.header.legacy_order)
        n = int(self.header.coef_count) * spectrum.values_per_coefficient(lay, p.storage)
        _, radii, angles = spectrum.kept_order(lay, p.cutoff)
        per = spectrum.values_per_coefficient(lay, p.storage)
        radius, angle = (radii[:self.header.coef_count], angles[:self.header.coef_count]) if per == 1 else \
            (np.repeat(radii[:self.header.coef_count], per), np.repeat(angles[:self.header.coef_count], per))
        stream = coding.decode_coefficients(self._blobs[b"COEF"], n, radius=radius, angle=angle,
                                            allow_partial=self._partial)
        return not np.any(stream)

    def _coefficients(self) -> int:
        """Spectral coefficients the file stores: an untiled map's ``coef_count``; a tiled map's base
        layer and every tile's own."""
        if self.header.tiles is None:
            return int(self.header.coef_count)
        return int(self.header.coef_count) + _tile_coefficients(self.header)

    def info(self) -> dict[str, Any]:
        """Header, parameters and sizes as plain JSON-ready data."""
        h = self.header
        g = h.grid
        out = {
            "file": self.name,
            "bytes": self.size,
            "format_version": f"{VERSION[0]}.{h.minor}",
            "points_original": h.point_count,
            "points_rebuilt": h.cell_count,
            "bits_per_point": 8.0 * self.size / h.point_count if h.point_count else None,
            "grid": {"rows": g.rows, "cols": g.cols, "resolution_m": g.resolution,
                     "resolution_y_m": g.resolution_y, "origin": [g.x0, g.y0], "z0_m": g.z0,
                     "angle_rad": g.angle},
            # The "_m" fields are in these units: metres unless the CRS says otherwise.
            "units": dataclasses.asdict(units_of(h.crs)),
            "params": json.loads(h.params.to_json()) | h.notes,  # notes: what a tool on top recorded
            "plane": list(h.plane),
            "crs": (h.crs.get("wkt") or ("LAS GeoKeys" if h.crs.get("las_vlrs") else None)),
            "stats": h.stats,
        }
        out["coefficients"] = self._coefficients()
        if b"RESD" in self._blobs and h.tiles is None:
            # Rate control may code the map as its residual layer alone, the coefficients all 0 at a
            # huge step: say so rather than state that step (decoding the coefficients, not the map).
            out["spectrum_empty"] = self._spectrum_empty()
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


def _tile_coefficients(header: Any) -> int:
    """Coefficients a tiled map's tiles store: each tile with a ``COEF`` section keeps every
    coefficient of its coded window below the cutoff (docs/format.md, *Decoding a tile*)."""
    from . import spectrum, tiles

    index = header.tiles
    total = 0
    for k in map(int, np.flatnonzero(index.cells)):
        if b"COEF" not in index.sections.get(k, {}):
            continue
        w0, w1, v0, v1 = tiles.coded_window(index.tiling, k, index.overlap)
        total += spectrum.kept_count(spectrum.layout("dct", "quantized", (w1 - w0, v1 - v0), legacy=header.legacy_order),
                                     header.params.cutoff)
    return total


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


def open(source: str | os.PathLike[str] | BinaryIO | bytes, mode: str = "r", *,  # noqa: A001
         max_bytes: int | None = None, max_cells: int | None = None, **settings: Any) -> Any:
    """Open a compressed map: ``"r"`` to read it (a :class:`CompressedMap`), ``"a"`` to add scans to a
    growing map and ``"w"`` to start one (a :class:`~dftpcc.growing.GrowingMap`, which writes the
    map and its state on closing), as laspy's ``open_las`` gives a reader, an appender or a writer.

    Parameters
    ----------
    source : path, file-like or bytes
        A path for ``"a"`` and ``"w"``.
    mode : {'r', 'a', 'w'}
    settings
        ``"w"``: the new map's ``resolution`` (metres, required), ``tile_size``, ``cutoff``, ``step``,
        ``crs``, ``origin`` (see :class:`~dftpcc.mapbuilder.MapBuilder`).
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
    if mode not in ("r", "a", "w"):
        raise InvalidInputError(f"mode must be 'r' (read), 'a' (add scans to a growing map) or 'w' (start one), "
                                f"got {mode!r}")
    if mode != "r":
        if max_bytes is not None or max_cells is not None or not isinstance(source, (str, os.PathLike)):
            raise InvalidInputError(f"mode {mode!r} opens a growing map by its path, without max_bytes or max_cells")
        from .growing import open_growing  # the writer side, loaded only for it

        return open_growing(source, mode, **settings)
    if settings:
        raise InvalidInputError(f"reading a map takes no settings: {', '.join(sorted(settings))}")
    check_max_bytes(max_bytes)
    check_max_cells(max_cells)
    if isinstance(source, (bytes, bytearray, memoryview)):
        return CompressedMap(bytes(source), max_bytes=max_bytes, max_cells=max_cells)
    if hasattr(source, "read"):
        return CompressedMap(source.read(), getattr(source, "name", "<stream>"), max_bytes=max_bytes,
                             max_cells=max_cells)
    if is_url(source):  # range requests: the header, then the tiles a region needs
        remote = RemoteSource(str(source))
        return CompressedMap(remote, str(source), max_bytes=max_bytes, max_cells=max_cells)
    path = Path(source)
    if not path.is_file():
        raise MissingFileError(path)
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
        raise MissingFileError(path)
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
        chooses, from :data:`~dftpcc.kernels.COMPILED_MIN_MAP_CELLS` points the map was made from.

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
            kernels.use(backend, work=cmap.header.cell_count, min_work=kernels.COMPILED_MIN_MAP_CELLS):
        return cmap.read_points(cutoff=cutoff)
