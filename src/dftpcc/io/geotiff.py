"""GeoTIFF DEMs (rasterio): read as a DEM on their own pixel grid, or as points at their pixel centres; written back.

This module is the one place a GeoTIFF becomes a DEM (:func:`dem_from_geotiff`,
:meth:`GeoTiffReader.dem`) and a DEM becomes a GeoTIFF (:func:`write_geotiff`).
"""

from __future__ import annotations

import math
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Any, ClassVar, Iterator

import numpy as np
import rasterio
from rasterio.io import MemoryFile
from rasterio.transform import Affine

from ..dem import DEM, Grid
from ..errors import InvalidInputError
from .atomic import atomic_write, writer_errors
from .reader import Reader

__all__ = ["GeoTiffReader", "read_raster_dem", "pixel_centres", "dem_from_geotiff", "write_geotiff", "SQUARE_TOLERANCE"]

#: Pixels whose sides differ by less than this fraction count as square.
SQUARE_TOLERANCE = 1e-9


@contextmanager
def _raster_errors(path: str | os.PathLike[str]) -> Iterator[None]:
    try:
        yield
    except Exception as exc:  # noqa: BLE001 - GDAL raises its own errors on bad files
        raise InvalidInputError(f"{path}: cannot read as a GeoTIFF DEM: {exc}") from None


def read_raster_dem(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, Affine, dict[str, Any]]:
    """A GeoTIFF DEM as its pixels.

    Returns
    -------
    heights : ndarray, shape (rows, cols), float64
        Metres (the file's unit), rows as stored (a north-up file has row 0
        at the top); NaN where there is no data.
    valid : ndarray, shape (rows, cols), bool
        Pixels with a finite height that are not nodata.
    transform : Affine
        Pixel (col, row) -> x, y of the pixel's corner.
    crs : dict
        ``{"wkt": ...}``, or empty when the file has none.
    """
    with _raster_errors(path), rasterio.open(path) as src:
        band = src.read(1, masked=True)
        crs = {"wkt": src.crs.to_wkt()} if src.crs else {}
        transform = src.transform
    # Integer DEMs (int16 SRTM, MOLA) cannot hold NaN: convert before filling nodata.
    heights = np.asarray(band.astype(np.float64).filled(np.nan), dtype=np.float64)
    valid = ~np.ma.getmaskarray(band) & np.isfinite(heights)
    return heights, valid, transform, crs


def pixel_centres(heights: np.ndarray, valid: np.ndarray, transform: Affine) -> np.ndarray:
    """One point per valid pixel at its centre: (n, 3) float64, row by row as stored."""
    rows, cols = np.nonzero(valid)
    t = transform
    x = t.c + t.a * (cols + 0.5) + t.b * (rows + 0.5)
    y = t.f + t.d * (cols + 0.5) + t.e * (rows + 0.5)
    return np.column_stack([x, y, heights[rows, cols]])


def dem_from_geotiff(path: str | os.PathLike[str]) -> tuple[DEM, dict[str, Any]]:
    """A north-up GeoTIFF DEM as a :class:`~dftpcc.dem.DEM` on its own pixel grid, and its CRS.

    Heights are relative to their mean (metres); the grid's rows run south
    to north, its cells are the pixels (non-square pixels keep both spacings).

    Raises
    ------
    InvalidInputError
        Rotated or east-to-west pixels (read it as points instead, with a
        resolution), or no valid pixel.
    """
    heights, valid, t, crs = read_raster_dem(path)
    if t.b != 0 or t.d != 0 or t.a <= 0:
        raise InvalidInputError(f"{path}: pixels are rotated or flipped; give a --resolution to grid its points")
    if not valid.any():
        raise InvalidInputError(f"{path}: every pixel is nodata")
    rows, cols = heights.shape
    # Grid rows run south to north; a north-up file's row 0 is the northern edge.
    flipped = t.e < 0
    h = heights[::-1] if flipped else heights
    m = valid[::-1] if flipped else valid
    y0 = t.f + t.e * rows if flipped else t.f
    z0 = float(h[m].mean())
    # Planetary DEMs often have slightly (or very) non-square pixels: keep both spacings.
    res_y = abs(t.e) if abs(abs(t.e) - t.a) > SQUARE_TOLERANCE * t.a else None
    grid = Grid(x0=t.c, y0=y0, z0=z0, resolution=t.a, rows=rows, cols=cols, resolution_y=res_y)
    return DEM(grid=grid, heights=np.where(m, h - z0, 0.0), mask=m, gridding_rmse=0.0), crs


class GeoTiffReader(Reader):
    """A GeoTIFF DEM: its own grid (:meth:`dem`), or its valid pixels as points at their centres.

    The pixels are read whole on each pass; :attr:`points_bound` is the pixel count.
    """

    own_grid: ClassVar[bool] = True

    def _open(self) -> None:
        with _raster_errors(self.path), rasterio.open(self.path) as src:
            self.crs = {"wkt": src.crs.to_wkt()} if src.crs else {}
            self._pixels = int(src.width) * int(src.height)

    @property
    def points_bound(self) -> int | None:
        return self._pixels

    def dem(self) -> DEM:
        """The DEM on the file's own pixel grid (see :func:`dem_from_geotiff`)."""
        return dem_from_geotiff(self.path)[0]

    def _raw_chunks(self, n: int | None) -> Iterator[np.ndarray]:
        heights, valid, transform, _ = read_raster_dem(self.path)
        points = pixel_centres(heights, valid, transform)
        self.stored_points = points.shape[0]
        yield from self._slices(points, n)


#: How a GeoTIFF output is laid out and compressed by default: tiled, DEFLATE with the
#: floating-point predictor (GDAL's PREDICTOR=3), which GIS tools read everywhere.
GEOTIFF_CREATION = {"tiled": True, "blockxsize": 256, "blockysize": 256, "compress": "deflate", "predictor": 3}


def write_geotiff(path: str | os.PathLike[str], dem: DEM, *, crs: dict[str, Any] | None = None,
                  creation: dict[str, Any] | None = None) -> None:
    """Write a DEM as a float32 GeoTIFF (north-up), empty cells as nodata (NaN).

    Heights are written in metres above the DEM's datum (``grid.z0`` added back).
    ``creation``: GDAL creation options (default :data:`GEOTIFF_CREATION`; ``{}``
    for an uncompressed strip layout); tiles larger than the raster are left out.

    Raises
    ------
    InvalidInputError
        A CRS GDAL cannot parse, a missing output folder.
    OSError
        The file system refused (permissions, disk full), naming ``path``.
    """
    grid: Grid = dem.grid
    heights = np.where(dem.mask, dem.heights + grid.z0, np.nan).astype(np.float32)[::-1]
    c, s = math.cos(grid.angle), math.sin(grid.angle)
    r, dy = grid.resolution, grid.dy
    # Row 0 of the file is the last grid row (largest v): flip v.
    top_x = grid.x0 - s * grid.rows * dy
    top_y = grid.y0 + c * grid.rows * dy
    transform = Affine(c * r, s * dy, top_x, s * r, -c * dy, top_y)
    wkt = (crs or {}).get("wkt")
    options = dict(GEOTIFF_CREATION if creation is None else creation)
    if options.get("tiled") and min(grid.rows, grid.cols) < options.get("blockxsize", 256):
        options = {k: v for k, v in options.items() if k not in ("tiled", "blockxsize", "blockysize")}

    def _write(tmp: Path) -> None:
        # GDAL encodes in memory and Python writes the bytes: a full disk is then an OSError with its
        # errno, not lines of libtiff text on stderr and an exception that says "see previous".
        with MemoryFile() as mem:
            with mem.open(driver="GTiff", height=grid.rows, width=grid.cols, count=1, dtype="float32",
                          nodata=float("nan"), transform=transform, crs=wkt or None, **options) as dst:
                dst.write(heights, 1)
            with open(tmp, "wb") as fh:
                fh.write(mem.getbuffer())

    with writer_errors(path, "tif"):
        atomic_write(path, _write)

