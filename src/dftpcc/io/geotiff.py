"""GeoTIFF DEMs (rasterio): read as a DEM on their own pixel grid, or as points at their pixel centres; written back.

This module is the one place a GeoTIFF becomes a DEM (:func:`dem_from_geotiff`,
:meth:`GeoTiffReader.dem`) and a DEM becomes a GeoTIFF (:func:`write_geotiff`).
"""

from __future__ import annotations

import math
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Any, ClassVar, Iterable, Iterator

import numpy as np
import rasterio
import rasterio.shutil
from rasterio.abc import FileContainer
from rasterio.io import MemoryFile
from rasterio.transform import Affine

from ..dem import DEM, Grid, RasterSource
from ..errors import InvalidInputError
from ..remote import Remote, Stamp, is_url
from .atomic import atomic_write, writer_errors
from .reader import Reader

__all__ = ["GeoTiffReader", "RasterWindows", "read_raster_dem", "pixel_centres", "dem_from_geotiff", "write_geotiff", "SQUARE_TOLERANCE",
           "raster_source", "output_type", "ROUNDS_BACK_BELOW"]

#: Pixels whose sides differ by less than this fraction count as square.
SQUARE_TOLERANCE = 1e-9


@contextmanager
def _raster_errors(path: str | os.PathLike[str], remote: Remote | None = None) -> Iterator[None]:
    try:
        yield
    except Exception as exc:  # noqa: BLE001 - GDAL raises its own errors on bad files
        if remote is not None and remote.error is not None:
            raise remote.error from None  # GDAL reports a failed read of a URL as its own I/O error
        raise InvalidInputError(f"{path}: cannot read as a GeoTIFF DEM: {exc}") from None


def read_raster_dem(path: str | os.PathLike[str], *, remote: Remote | None = None
                    ) -> tuple[np.ndarray, np.ndarray, Affine, dict[str, Any]]:
    """A GeoTIFF DEM (a path or a URL, ``remote`` its file if opened before) as its pixels.

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
    remote = remote if remote is not None else Remote(str(path)) if is_url(path) else None
    with _raster_errors(path, remote), open_raster(path, remote=remote) as src:
        heights, valid = _read_band(src, None)
        return heights, valid, src.transform, _crs_of(src)


def _stamp(path: str | os.PathLike[str]) -> tuple[int, int]:
    """A file's length (bytes) and modification time (ns); (-1, -1) when it is gone."""
    try:
        st = os.stat(path)
    except OSError:
        return -1, -1
    return st.st_size, st.st_mtime_ns


def open_raster(path: str | os.PathLike[str], *, remote: Remote | None = None) -> Any:
    """``rasterio.open(path)``; a URL is read by range requests through fsspec (:class:`~dftpcc.remote.Remote`,
    each response checked against ``remote`` 's stamp), GDAL asking for the blocks it decodes.

    Raises
    ------
    InvalidInputError
        A URL that cannot be read (no such file, unreachable), and, as GDAL's own errors, a file
        that is not a raster (inside :func:`_raster_errors`).
    """
    if not is_url(path):
        return rasterio.open(path)
    remote = Remote(str(path)) if remote is None else remote
    return rasterio.open(str(path), opener=_OneRemoteFile(remote))


class _OneRemoteFile(FileContainer):
    """The one file at a URL as GDAL's virtual file system sees it (rasterio's ``opener``): GDAL's
    look-ups of side-car files (``.ovr``, ``.aux.xml``, ``.msk``) find nothing, not the raster."""

    def __init__(self, remote: Remote):
        self.remote = remote
        # GDAL holds the file objects it opened by a borrowed reference, kept alive by rasterio in a
        # context variable: a dask task runs in a context of its own, and the next task of the same
        # dataset found a freed object there (a segmentation fault). Held here, for the dataset's life.
        self.files: list[Any] = []

    def _mine(self, path: str) -> bool:
        return path.rstrip("/") == self.remote.url.rstrip("/")

    def open(self, path: str, mode: str = "rb", **kwds: Any) -> Any:
        if not self._mine(path) or "w" in mode or "+" in mode:
            raise FileNotFoundError(path)
        self.files.append(self.remote.open(for_c=True))
        return self.files[-1]

    def isfile(self, path: str) -> bool:
        return self._mine(path)

    def isdir(self, path: str) -> bool:
        return False

    def ls(self, path: str) -> list[str]:
        return []

    def mtime(self, path: str) -> int:
        return 0

    def size(self, path: str) -> int:
        if not self._mine(path):
            raise FileNotFoundError(path)
        return self.remote.stamp.size

    def rm(self, path: str) -> None:
        raise PermissionError(path)


def _crs_of(src: Any) -> dict[str, Any]:
    return {"wkt": src.crs.to_wkt()} if src.crs else {}


def _read_band(src: Any, window: Any) -> tuple[np.ndarray, np.ndarray]:
    """Heights (float64, NaN where empty) and validity of the first band's ``window`` (None: all), rows as stored."""
    band = src.read(1, window=window, masked=True)
    # Integer DEMs (int16 SRTM, MOLA) cannot hold NaN: convert before filling nodata.
    heights = np.asarray(band.astype(np.float64).filled(np.nan), dtype=np.float64)
    valid = ~np.ma.getmaskarray(band) & np.isfinite(heights)
    return heights, valid


class RasterWindows:
    """A north-up GeoTIFF DEM read by windows of grid rows and columns (row 0 south, as dftpcc's grids).

    The one way a GeoTIFF's pixels become grid cells: :func:`dem_from_geotiff` reads it as one
    window, the band coder (:mod:`dftpcc.stream`) a block of tiles at a time. Pickled, it is its
    path and geometry: a dask worker reopens the file and reads its own windows.

    Parameters
    ----------
    path : path
    cache_bytes : int, optional
        GDAL's block cache while the file is opened and read, bytes (GDAL's default, a share of
        the machine's memory, when None).
    remote : Remote, optional
        The file at the URL ``path`` as a reader opened it before (its stamp the one to hold to).

    Raises
    ------
    InvalidInputError
        Not a readable GeoTIFF; rotated or east-to-west pixels (read it as points instead, with a
        resolution).
    """

    def __init__(self, path: str | os.PathLike[str], *, cache_bytes: int | None = None,
                 remote: Remote | None = None):
        self.path, self.cache_bytes = path, cache_bytes
        #: A URL's file (None for a path): every range response is checked against its first stamp.
        self.remote = remote if remote is not None else Remote(str(path)) if is_url(path) else None
        with _raster_errors(path, self.remote), self._env():
            self.ds = open_raster(path, remote=self.remote)
        t = self.ds.transform
        if t.b != 0 or t.d != 0 or t.a <= 0:
            self.ds.close()
            raise InvalidInputError(f"{path}: pixels are rotated or flipped; give a --resolution to grid its points")
        self.transform = t
        self.rows, self.cols = self.ds.height, self.ds.width
        # Grid rows run south to north; a north-up file's row 0 is the northern edge.
        self.flipped = t.e < 0
        self.crs = _crs_of(self.ds)
        nodata = self.ds.nodata
        self.source = RasterSource(str(self.ds.dtypes[0]), None if nodata is None else float(nodata))
        #: The file's length and modification time when opened (a URL's: its length and ETag, taken
        #: before its first byte was read): a read that spans minutes (or another process, a worker)
        #: checks it still reads that file (:meth:`check_unchanged`).
        self.stamp: tuple[int, int] | Stamp = _stamp(path) if self.remote is None else self.remote.stamp

    def check_unchanged(self) -> None:
        """Raise :class:`InvalidInputError` if the file's length or modification time (a URL's: length
        or ETag) is not the one it had when opened: cells read before and after a change would make a
        map of two files."""
        if self.remote is not None:
            self.remote.check_unchanged()
            return
        now = _stamp(self.path)
        if now != self.stamp:
            raise InvalidInputError(f"{self.path}: the file changed while it was read (length {self.stamp[0]:,} "
                                    f"-> {now[0]:,} bytes, or modified since); nothing was written: run again on "
                                    f"the finished file")

    def _env(self) -> Any:
        return rasterio.Env(GDAL_CACHEMAX=self.cache_bytes) if self.cache_bytes is not None else rasterio.Env()

    def __getstate__(self) -> dict[str, Any]:
        return {key: value for key, value in self.__dict__.items() if key != "ds"}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        # A worker reopening the file checks, at its first read, that it is the one its client
        # opened (raised there, as the task's own error: an error while unpickling reaches the
        # client as a bare Exception).
        # The file is reopened there too: a URL's reopening reads it.
        self.ds = None

    def __enter__(self) -> "RasterWindows":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def read(self, r0: int, r1: int, c0: int = 0, c1: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Heights (metres, float64, NaN where empty) and validity of grid rows [r0, r1) and columns [c0, c1)."""
        from rasterio.windows import Window

        if self.ds is None:  # a worker's copy, not yet reopened (until it is, each task checks the file)
            self.check_unchanged()
            with _raster_errors(self.path, self.remote), self._env():
                self.ds = open_raster(self.path, remote=self.remote)
        c1 = self.cols if c1 is None else c1
        f0 = self.rows - r1 if self.flipped else r0
        with _raster_errors(self.path, self.remote), self._env():
            heights, valid = _read_band(self.ds, Window(c0, f0, c1 - c0, r1 - r0))
        if self.flipped:
            heights, valid = heights[::-1], valid[::-1]
        return heights, valid

    def grid(self, z0: float) -> Grid:
        """The grid of the file's pixels with its datum at ``z0`` metres (non-square pixels keep both spacings)."""
        t = self.transform
        y0 = t.f + t.e * self.rows if self.flipped else t.f
        # Planetary DEMs often have slightly (or very) non-square pixels.
        res_y = abs(t.e) if abs(abs(t.e) - t.a) > SQUARE_TOLERANCE * t.a else None
        return Grid(x0=t.c, y0=y0, z0=z0, resolution=t.a, rows=self.rows, cols=self.cols, resolution_y=res_y)

    def close(self) -> None:
        if self.ds is not None:
            self.ds.close()


def pixel_centres(heights: np.ndarray, valid: np.ndarray, transform: Affine) -> np.ndarray:
    """One point per valid pixel at its centre: (n, 3) float64, row by row as stored."""
    rows, cols = np.nonzero(valid)
    t = transform
    x = t.c + t.a * (cols + 0.5) + t.b * (rows + 0.5)
    y = t.f + t.d * (cols + 0.5) + t.e * (rows + 0.5)
    return np.column_stack([x, y, heights[rows, cols]])


def dem_from_geotiff(path: str | os.PathLike[str], *, remote: Remote | None = None) -> tuple[DEM, dict[str, Any]]:
    """A north-up GeoTIFF DEM as a :class:`~dftpcc.dem.DEM` on its own pixel grid, and its CRS.

    Heights are relative to their mean (metres); the grid's rows run south
    to north, its cells are the pixels (non-square pixels keep both spacings).
    The whole file is one window of :class:`RasterWindows`.

    Raises
    ------
    InvalidInputError
        Rotated or east-to-west pixels (read it as points instead, with a
        resolution), or no valid pixel.
    """
    with RasterWindows(path, remote=remote) as raster:
        h, m = raster.read(0, raster.rows)
        if not m.any():
            raise InvalidInputError(f"{path}: every pixel is nodata")
        z0 = float(h[m].mean())
        dem = DEM(grid=raster.grid(z0), heights=np.where(m, h - z0, 0.0), mask=m, gridding_rmse=0.0,
                  source=raster.source)
        return dem, raster.crs


def raster_source(path: str | os.PathLike[str]) -> RasterSource:
    """The sample type and nodata value of a GeoTIFF's first band (its header only)."""
    remote = Remote(str(path)) if is_url(path) else None
    with _raster_errors(path, remote), open_raster(path, remote=remote) as src:
        nodata = src.nodata
        return RasterSource(str(src.dtypes[0]), None if nodata is None else float(nodata))


#: An integer raster coded within less than this many units of height rounds back to its values exactly.
ROUNDS_BACK_BELOW = 0.5


def output_type(stats: dict[str, Any], *, dtype: str | None = None, nodata: float | None = None,
                bound_holds: bool = True) -> tuple[str, float, str | None]:
    """The sample type and nodata value a rebuilt DEM is written with, and why not the source's.

    By default the source raster's (``STAT`` ``source_dtype``, ``source_nodata``; float32 and NaN
    for a point cloud or a float32 raster). An integer source is written as integers only where the
    file's maximum error (``dem_max_error_m``) is below :data:`ROUNDS_BACK_BELOW`, so that rounding
    gives back its values exactly, and ``bound_holds`` (the map is decoded whole at its own cutoff);
    otherwise float32, keeping its nodata value.

    Parameters
    ----------
    stats : dict
        The file's ``STAT`` figures (``CompressedMap.header.stats``).
    dtype, nodata : optional
        What the user asked for instead (``--dtype``, ``--nodata``): an integer type rounds the heights.
    bound_holds : bool
        False when the map is decoded at another cutoff or from a prefix of the file.

    Returns
    -------
    dtype : str
    nodata : float
        NaN for a float type without a nodata value of its own.
    note : str or None
        Why the source's type was not kept, to tell the user; None when it was (or nothing was asked).
    """
    source = RasterSource.from_stats(stats)
    note = None
    if dtype is not None:
        try:
            dtype = np.dtype(dtype).name
        except TypeError:
            raise InvalidInputError(f"unknown sample type {dtype!r}; use one of int8, uint8, int16, uint16, "
                                    f"int32, uint32, float32, float64") from None
        if dtype not in ("int8", "uint8", "int16", "uint16", "int32", "uint32", "float32", "float64"):
            raise InvalidInputError(f"a GeoTIFF DEM is written as int8, uint8, int16, uint16, int32, uint32, "
                                    f"float32 or float64, not {dtype}")
    elif source is not None and np.dtype(source.dtype).kind in "iu":
        error = stats.get("dem_max_error_m")
        if not bound_holds:
            dtype, note = "float32", (f"written as float32, not as the source's {source.dtype}: decoded at another "
                                      f"cutoff or from part of the file, its errors are not the file's bound "
                                      f"(--dtype {source.dtype} rounds anyway)")
        elif error is None or error >= ROUNDS_BACK_BELOW:
            dtype, note = "float32", (f"written as float32, not as the source's {source.dtype}: the map's max error "
                                      f"{error:.3g} is not below half a unit, so rounding would not give back the "
                                      f"source's values (--dtype {source.dtype} rounds anyway)")
        else:
            dtype = source.dtype
    else:
        dtype = source.dtype if source is not None else "float32"
    if nodata is None:
        if source is not None and source.nodata is not None:
            nodata = source.nodata
        elif np.dtype(dtype).kind in "iu":  # an integer type has no NaN: its most negative (or largest) value
            info = np.iinfo(dtype)
            nodata = float(info.min if np.dtype(dtype).kind == "i" else info.max)
        else:
            nodata = float("nan")
    if np.dtype(dtype).kind in "iu":
        info = np.iinfo(dtype)
        if not (math.isfinite(nodata) and nodata == int(nodata) and info.min <= nodata <= info.max):
            raise InvalidInputError(f"nodata {nodata:g} is not a value of {dtype}; give one (--nodata)")
    return dtype, float(nodata), note



class GeoTiffReader(Reader):
    """A GeoTIFF DEM: its own grid (:meth:`dem`), or its valid pixels as points at their centres.

    The pixels are read whole on each pass; :attr:`points_bound` is the pixel count.
    """

    own_grid: ClassVar[bool] = True

    def _open(self) -> None:
        with _raster_errors(self.path, self.remote), open_raster(self.path, remote=self.remote) as src:
            self.crs = {"wkt": src.crs.to_wkt()} if src.crs else {}
            self._pixels = int(src.width) * int(src.height)

    @property
    def points_bound(self) -> int | None:
        return self._pixels

    def dem(self) -> DEM:
        """The DEM on the file's own pixel grid (see :func:`dem_from_geotiff`)."""
        return dem_from_geotiff(self.path, remote=self.remote)[0]

    def _raw_chunks(self, n: int | None) -> Iterator[np.ndarray]:
        heights, valid, transform, _ = read_raster_dem(self.path, remote=self.remote)
        points = pixel_centres(heights, valid, transform)
        self.stored_points = points.shape[0]
        yield from self._slices(points, n)


#: How a GeoTIFF output is laid out and compressed by default: tiled, DEFLATE with the
#: floating-point predictor (GDAL's PREDICTOR=3), which GIS tools read everywhere.
GEOTIFF_CREATION = {"tiled": True, "blockxsize": 256, "blockysize": 256, "compress": "deflate", "predictor": 3}
#: GDAL's PREDICTOR values: horizontal differencing (integers) and floating point.
INTEGER_PREDICTOR, FLOAT_PREDICTOR = 2, 3


def samples(dem: DEM, dtype: str, nodata: float) -> np.ndarray:
    """The DEM's heights above its datum as ``dtype`` samples, empty cells ``nodata``."""
    values = dem.heights + dem.grid.z0
    kind = np.dtype(dtype).kind
    if kind in "iu":
        values = np.rint(values)
        info = np.iinfo(dtype)
        occupied = values[dem.mask]
        if occupied.size and (occupied.min() < info.min or occupied.max() > info.max):
            raise InvalidInputError(f"heights {occupied.min():g} to {occupied.max():g} do not fit in {dtype} "
                                    f"({info.min} to {info.max}); choose another --dtype")
    else:
        occupied = values[dem.mask].astype(dtype)
    if not math.isnan(nodata) and np.any(occupied == np.asarray(nodata, dtype=dtype)):
        raise InvalidInputError(f"a rebuilt height equals the nodata value {nodata:g}, which would hide it; "
                                f"choose another --nodata")
    out = np.full(dem.heights.shape, nodata, dtype=dtype)
    out[dem.mask] = values[dem.mask].astype(dtype)
    return out


def write_geotiff(path: str | os.PathLike[str], dem: DEM, *, crs: dict[str, Any] | None = None,
                  creation: dict[str, Any] | None = None, dtype: str = "float32", nodata: float = float("nan"),
                  cog: bool = False) -> None:
    """Write a DEM as a GeoTIFF (north-up), empty cells as nodata.

    Heights are written in metres above the DEM's datum (``grid.z0`` added back).
    ``creation``: GDAL creation options (default :data:`GEOTIFF_CREATION`; ``{}``
    for an uncompressed strip layout); tiles larger than the raster are left out.
    ``dtype`` and ``nodata``: the sample type (an integer type rounds the heights to
    the nearest unit) and the value of empty cells (see :func:`output_type`).
    ``cog``: a Cloud Optimized GeoTIFF (GDAL's COG driver).

    Raises
    ------
    InvalidInputError
        A CRS GDAL cannot parse, a missing output folder; heights ``dtype`` cannot hold, or a
        rebuilt height equal to ``nodata``.
    OSError
        The file system refused (permissions, disk full), naming ``path``.
    """
    grid: Grid = dem.grid
    heights = samples(dem, dtype, nodata)[::-1]
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
    if options.get("predictor") == FLOAT_PREDICTOR and np.dtype(dtype).kind in "iu":
        options["predictor"] = INTEGER_PREDICTOR  # the floating-point predictor is for float samples only

    def _write(tmp: Path) -> None:
        # GDAL encodes in memory and Python writes the bytes: a full disk is then an OSError with its
        # errno, not lines of libtiff text on stderr and an exception that says "see previous".
        with MemoryFile() as mem:
            with mem.open(driver="GTiff", height=grid.rows, width=grid.cols, count=1, dtype=dtype,
                          nodata=nodata, transform=transform, crs=wkt or None, **options) as dst:
                dst.write(heights, 1)
            if cog:
                with MemoryFile() as out, mem.open() as src:
                    rasterio.shutil.copy(src, out.name, driver="COG", COMPRESS="DEFLATE",
                                         PREDICTOR=str(options.get("predictor", INTEGER_PREDICTOR)))
                    with open(tmp, "wb") as fh:
                        fh.write(out.getbuffer())
                return
            with open(tmp, "wb") as fh:
                fh.write(mem.getbuffer())

    with writer_errors(path, "tif"):
        atomic_write(path, _write)


def write_geotiff_windows(path: Path, grid: Grid, crs: dict[str, Any], blocks: Iterable[tuple[int, int, DEM]], *,
                          cog: bool, sample: str = "float32", empty: float = float("nan")) -> int:
    """:func:`write_geotiff` of a map that arrives in windows ``(row, column, DEM)`` (decoded band by
    band): each written where it lies, through windowed writes; empty cells ``empty``. A COG is
    written as strips first, then copied by GDAL's COG driver. Returns the occupied cells written.

    Raises
    ------
    InvalidInputError
        A rotated grid (its windows are not the file's).
    """
    import rasterio.shutil
    from rasterio.windows import Window

    if grid.angle != 0.0:
        raise InvalidInputError("a rotated grid (frame 'oriented') is written as points, not as a GeoTIFF")
    r, dy = grid.resolution, grid.dy
    transform = Affine(r, 0.0, grid.x0, 0.0, -dy, grid.y0 + grid.rows * dy)
    target = path.with_suffix(".strips.tif") if cog else path
    predictor = INTEGER_PREDICTOR if np.dtype(sample).kind in "iu" else FLOAT_PREDICTOR
    count = 0
    with rasterio.open(target, "w", driver="GTiff", height=grid.rows, width=grid.cols, count=1,
                       dtype=sample, nodata=empty, transform=transform, crs=crs.get("wkt") or None,
                       BIGTIFF="IF_SAFER", **(GEOTIFF_CREATION | {"predictor": predictor})) as out:
        for r0, c0, dem in blocks:
            values = samples(dem, sample, empty)[::-1]
            count += int(dem.mask.sum())
            h, w = values.shape
            out.write(values, 1, window=Window(c0, grid.rows - r0 - h, w, h))
    if cog:
        try:
            rasterio.shutil.copy(target, path, driver="COG", COMPRESS="DEFLATE", PREDICTOR=str(predictor),
                                 BIGTIFF="IF_SAFER")
        finally:
            target.unlink(missing_ok=True)
    return count
