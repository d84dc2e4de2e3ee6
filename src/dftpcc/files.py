"""Files in, files out: join the read stage (:mod:`dftpcc.io`) to the codec.

:func:`compress_file` opens a reader, grids its chunks (one chunk when the cloud fits
in memory) or takes a raster's own DEM, encodes and writes the ``.dftpc``;
:func:`decompress_file` decodes one and writes the points or a GeoTIFF.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Callable, Iterable, Iterator, Sequence

import numpy as np

from . import io, kernels
from . import stream
from .cluster import check_executor, executor
from .format import unpack
from .dem import DEM, Grid
from .encoder import Stage, encode_dem, no_stage, params_of
from .grid import CloudSummary, check_chunked_aggregate, rasterize, rasterize_bands, rasterize_chunks
from .errors import InvalidInputError, RasterTypeWarning, RemoteWarning
from .io import DEFAULT_CHUNK_POINTS, Reader, atomic_write, check_output, format_of, open_reader, write
from .limits import MAX_CELLS, check_band_size, check_grid_size, check_spill_space, holds_in_memory
from .mapfile import CompressedMap
from .mapfile import open as open_map
from .params import Params, tile_size_for
from .rebuild import dem_to_dense_points, dem_to_points
from .remote import Remote, is_url, one_version, url_suffix

__all__ = ["compress_file", "decompress_file", "read_dem", "check_compressed_output", "dem_from_geotiff", "reads_in_chunks", "stored_point_count"]


def stored_point_count(src: str | os.PathLike[str], format: str | None = None) -> int | None:  # noqa: A002
    """:func:`dftpcc.io.stored_point_count`: points a file holds (a ROS bag: a bound; a GeoTIFF: its pixels)."""
    return io.stored_point_count(src, format)


def dem_from_geotiff(path: str | os.PathLike[str]) -> tuple[DEM, dict[str, Any]]:
    """:func:`dftpcc.io.geotiff.dem_from_geotiff`: a GeoTIFF DEM on its own pixel grid, and its CRS."""
    return io.dem_from_geotiff(path)


def reads_in_chunks(src: str | os.PathLike[str], format: str | None = None,  # noqa: A002
                    chunk_points: int | None = None, aggregate: str = "mean") -> bool:
    """Whether :func:`compress_file` reads ``src`` in chunks.

    Always when ``chunk_points`` is given (the format must allow it);
    otherwise when the file holds more points (:func:`~dftpcc.io.stored_point_count`)
    than the available memory can compress in one piece (:func:`~dftpcc.limits.holds_in_memory`),
    or, for an ``aggregate`` other than the median, more than :data:`HELD_POINTS`.
    """
    if chunk_points is None and not io.REGISTRY[format_of(src, format)].streams:
        return False  # read whole whatever its size: no need to open it
    with open_reader(src, format=format, chunk_points=chunk_points) as reader:
        return _chunk_size(reader, aggregate) is not None


#: A cloud of more points than this is read in chunks even where the memory would hold it whole (but
#: for the median, which needs a cell's points at once): held, 100 M points took 8.3 GB where the
#: chunks and a grid coded band by band take 0.7 GB; a cloud this large grids, at its own spacing,
#: into a map coded band by band (:data:`~dftpcc.stream.STREAM_CELLS`).
HELD_POINTS = 16_000_000


def _chunk_size(reader: Reader, aggregate: str) -> int | None:
    """Points per chunk to compress from ``reader``: None (the whole cloud, one chunk) when it fits in
    memory and is not larger than :data:`HELD_POINTS` (or the ``aggregate`` is the median)."""
    if reader.chunk_points is not None:
        return reader.chunk_points
    bound = reader.points_bound
    if reader.streams and bound and (not holds_in_memory(bound) or bound > HELD_POINTS and aggregate != "median"):
        return DEFAULT_CHUNK_POINTS
    return None


#: Bytes of a stream read to tell its format (a LAS header's point format id is byte 104).
SNIFF_BYTES = 128

#: A path, or a binary stream (standard input or output, an open file).
Source = str | os.PathLike[str] | IO[bytes]


def _is_stream(target: Any) -> bool:
    return hasattr(target, "read") or hasattr(target, "write")


@contextmanager
def _as_path(src: Source, format: str | None) -> Iterator[str | os.PathLike[str]]:  # noqa: A002
    """``src`` as a path readers can open: a stream or a pipe (``/dev/stdin``) is copied to a temporary
    file, as is a URL of a format not read by range requests or on a server that serves none."""
    remote = Remote(src) if is_url(src) else None
    if remote is not None and (format or io.FORMATS.get(url_suffix(src))) in io.URL_FORMATS:
        if remote.serves_ranges():
            yield src  # read by range requests
            return
        warnings.warn(f"{src}: the server does not serve byte ranges: the file is downloaded whole to a "
                      f"temporary file first ({remote.stamp.size:,} bytes)", RemoteWarning, stacklevel=4)
    if remote is None and not _is_stream(src) and (Path(src).is_file() or Path(src).is_dir()
                                                   or not Path(src).exists()):
        yield src  # a file, a ROS 2 bag folder, or a missing path the reader reports
        return
    with tempfile.TemporaryDirectory(prefix="dftpcc-") as tmp:
        raw = Path(tmp) / "stream"
        if remote is not None:
            remote.download(raw)
            format = format or io.FORMATS.get(url_suffix(src))  # noqa: A001 - else told by its first bytes
        with raw.open("ab") as out:
            if _is_stream(src):
                shutil.copyfileobj(src, out)
            elif remote is None:
                with open(src, "rb") as fh:
                    shutil.copyfileobj(fh, out)
        if format is None:
            with raw.open("rb") as fh:
                format = io.sniff_format(fh.read(SNIFF_BYTES))  # noqa: A001
        if format is None:
            raise InvalidInputError(f"{getattr(src, 'name', src)}: a stream has no extension and its first bytes "
                                    f"name no binary format; name its format (--format xyz, csv, ...)")
        name = format_of(f"x.{format}", format)
        ext = next(e for e, f in io.FORMATS.items() if f == name)
        path = raw.rename(raw.with_suffix(ext))
        yield path


def check_compressed_output(dst: Source, *, force: bool = False) -> None:
    """Refuse, before any work, a ``.dftpc`` output that cannot be written or is named like another format.

    A name with a point-cloud or raster extension (``out.ply``) would hold a
    ``.dftpc`` under a misleading name: refused unless ``force``.
    """
    if _is_stream(dst):
        return
    ext = Path(dst).suffix.lower()
    if ext in io.FORMATS and not force:
        raise InvalidInputError(f"{dst}: a .dftpc file would be written under the {ext} extension of another "
                                f"format; name it .dftpc (to rebuild a {ext} file use decompress), or use --force")
    check_output(dst, force=force)


def compress_file(src: Source, dst: Source, params: Params | None = None, *,
                  format: str | None = None, classes: Sequence[int] | None = None,  # noqa: A002
                  drop_nonfinite: bool = False, chunk_points: int | None = None, topic: str | None = None,
                  force: bool = False, on_stage: Stage = no_stage, pose_topic: str | None = None,
                  map_frame: str | None = None, workers: int | None = None, scheduler: str | None = None,
                  backend: kernels.Backend | str | None = None, **shortcuts: Any) -> CompressedMap:
    """Compress the point cloud in ``src`` into the ``.dftpc`` file ``dst``.

    Parameters
    ----------
    src, dst : path or binary stream
        A stream (standard input or output) or a pipe is read or written
        whole; reading one needs ``format``.
    params : Params, optional
        As :func:`dftpcc.compress`, as are ``**shortcuts``.
    format, classes, drop_nonfinite, topic, pose_topic, map_frame
        As :func:`dftpcc.read` (``topic``: the PointCloud2 topic of a ROS bag;
        ``pose_topic``: the poses of its scans, recorded in the sensor frame;
        ``map_frame``: with ``/tf``, the frame of the map).
    chunk_points : int, optional
        Read the cloud in chunks of this many points (LAS, LAZ, PLY, NPY,
        ROS bags). By default a cloud is read whole when it fits in memory
        (:func:`~dftpcc.limits.holds_in_memory` of its header's count), else
        in chunks of :data:`~dftpcc.io.DEFAULT_CHUNK_POINTS`: three or four
        passes over the file, memory holding the grid and one chunk. The map
        is the same up to float round-off; ``aggregate='median'`` needs the
        whole cloud and is refused in chunks. A grid coded in tiles over
        :data:`~dftpcc.stream.STREAM_CELLS` cells (to a path) is not held:
        it is gridded band by band into a temporary folder beside ``dst``
        (:func:`~dftpcc.grid.rasterize_bands`) and coded from there, memory
        holding one band of tile rows and one chunk; the file is the same,
        byte for byte, and the limit is on a band's cells
        (:func:`~dftpcc.limits.check_band_size`), not the map's.
    on_stage : callable, optional
        Called with the name of each stage as it starts.
    workers, scheduler : optional
        Code a tiled map's tiles on a local dask cluster of ``workers``
        processes, or on the running scheduler at ``scheduler``
        (:func:`dftpcc.cluster.executor`); the file is byte-identical.
    backend : {'numpy', 'compiled'} or dftpcc.kernels.Backend, optional
        As :func:`dftpcc.compress`; the default counts the points the file's header states
        (LAS, LAZ, PLY, NPY), and takes numpy for the other formats unless this process loaded
        the compiled kernels already or ``DFTPCC_JIT=1``.

    A GeoTIFF source with ``resolution='auto'`` is coded on its own pixel
    grid; with a resolution, its pixel centres are gridded as points.

    Returns
    -------
    CompressedMap
        The written map, opened (header parsed).

    Raises
    ------
    InvalidInputError
        As :func:`dftpcc.compress` and :func:`dftpcc.read`; an option the
        format cannot honour (``classes``, ``topic``, ``chunk_points``) or a
        median in chunks, before the file is read.
    """
    # Parameters and options checked before the first pass over a file that may take minutes to read.
    params = params_of(params, shortcuts)
    check_compressed_output(dst, force=force)
    check_executor(workers, scheduler)
    with one_version(), kernels.use(backend, work=None if _is_stream(src) else stored_point_count(src, format)):
        return _compress_file(src, dst, params, format=format, classes=classes, drop_nonfinite=drop_nonfinite,
                              chunk_points=chunk_points, topic=topic, on_stage=on_stage, pose_topic=pose_topic,
                              map_frame=map_frame, workers=workers, scheduler=scheduler)


def _compress_file(src: Source, dst: Source, params: Params, *, format: str | None,  # noqa: A002
                   classes: Sequence[int] | None, drop_nonfinite: bool, chunk_points: int | None, topic: str | None,
                   on_stage: Stage, pose_topic: str | None, map_frame: str | None, workers: int | None,
                   scheduler: str | None) -> CompressedMap:
    on_stage("read")
    with _as_path(src, format) as path:
        if not _is_stream(src) and streams_raster(path, params, format):
            # Larger than memory: coded band of tile rows by band, straight into the file.
            with executor(workers, scheduler) as map_tiles:
                stream.compress_raster(path, dst, params, map_tiles=map_tiles, on_stage=on_stage,
                                       write=atomic_write)
            return open_map(dst)
        with open_reader(path, format=format, classes=classes, topic=topic, drop_nonfinite=drop_nonfinite,
                         chunk_points=chunk_points, pose_topic=pose_topic, map_frame=map_frame) as reader:
            if reader.own_grid and params.resolution == "auto":
                dem = reader.dem()
                count = int(dem.mask.sum())
            else:
                cloud = _fit(reader, params, on_stage, bands=None if _is_stream(dst) else _folder(dst))
                if cloud.in_bands:
                    # A grid larger than memory: gridded band by band on disk, each band coded from there.
                    _compress_in_bands(cloud, dst, params, workers=workers, scheduler=scheduler, on_stage=on_stage,
                                       name=str(path))
                    return open_map(dst)
                dem, count = cloud.rasterize(params.aggregate), cloud.summary.count
            crs = reader.crs
    with executor(workers, scheduler) as map_tiles:
        if not _is_stream(dst) and stream.codes_in_bands(dem.grid.shape, params):
            # A large grid: its tiles coded band by band, memory holding the grid and one band.
            stream.compress_gridded(dem, dst, params, point_count=count, crs=crs, map_tiles=map_tiles,
                                    on_stage=on_stage, write=atomic_write)
            return open_map(dst)
        data = encode_dem(dem, params, point_count=count, crs=crs, on_stage=on_stage, map_tiles=map_tiles)
    on_stage("write")
    if _is_stream(dst):
        dst.write(data)
        dst.flush()
    else:
        atomic_write(dst, data)
    # Named for the file written, so that its repr and messages say where it is.
    return CompressedMap(data, "<stream>" if _is_stream(dst) else str(dst), max_cells=_trusted(data))


def streams_raster(src: str | os.PathLike[str], params: Params, format: str | None = None) -> bool:  # noqa: A002
    """Whether :func:`compress_file` codes ``src`` band by band: a GeoTIFF (a file, or a URL on a
    server that serves byte ranges) on its own grid of more than :data:`~dftpcc.stream.STREAM_CELLS`
    cells, in tiles."""
    if params.resolution != "auto" or format_of(src, format) not in ("tif", "tiff"):
        return False
    if not (Path(src).is_file() or is_url(src) and Remote(str(src)).serves_ranges()):
        return False
    from .io.geotiff import open_raster

    try:
        with open_raster(src) as ds:
            shape = (ds.height, ds.width)
    except Exception:  # noqa: BLE001 - the reader says what is wrong, on the in-memory path
        return False
    return stream.codes_in_bands(shape, params)


def wants_bands(src: Any, dst: Any, *, format: str | None = None, cog: bool = False,  # noqa: A002
                bbox: Any = None, cutoff: float | None = None, max_bytes: int | None = None) -> bool:
    """Whether a decode of ``src`` into ``dst`` goes band by band (:func:`decompress_bands`): a COG, or a
    map of more than :data:`~dftpcc.stream.STREAM_CELLS` cells written whole to GeoTIFF, LAS or LAZ.
    A region (``bbox``) or a coarser map (``cutoff``, ``max_bytes``) is decoded as one piece, in every
    output format."""
    if bbox is not None or cutoff is not None or max_bytes is not None:
        return False  # a region or a coarser map, decoded whole (it is read whole or refused)
    if cog:
        return True
    if _is_stream(src) or _is_stream(dst):
        return False
    try:
        if format_of(dst, format) not in stream.STREAM_FORMATS or not Path(src).is_file():
            return False
    except InvalidInputError:  # decompress_file says what is wrong with the output's name
        return False
    try:
        with open_map(src) as cmap:
            return cmap.grid.size > stream.STREAM_CELLS
    except Exception:  # noqa: BLE001 - decompress_file reports what is wrong with the file
        return False


def decompress_bands(src: Source, dst: str | os.PathLike[str], *, format: str | None = None,  # noqa: A002
                     cog: bool = False, force: bool = False, max_cells: int | None = None,
                     workers: int | None = None, scheduler: str | None = None,
                     on_stage: Stage = no_stage, dtype: str | None = None, nodata: float | None = None) -> int:
    """Decode the map ``src`` one band of rows at a time into ``dst``: a GeoTIFF (a Cloud Optimized
    GeoTIFF with ``cog``), LAS or LAZ. Of a tiled map memory holds one band of tiles, never the map;
    an untiled map keeps its decoded mask and spectrum and rebuilds each band from them (it was coded
    whole, so they fit).

    Returns
    -------
    int
        Points (valid cells) written.
    """
    fmt = format_of(dst, format, output=True)
    if fmt not in stream.STREAM_FORMATS:
        raise InvalidInputError(f"{dst}: band-by-band decoding writes GeoTIFF, LAS or LAZ, not {fmt}")
    if cog and fmt not in ("tif", "tiff"):
        raise InvalidInputError(f"{dst}: a Cloud Optimized GeoTIFF is a .tif")
    if (dtype is not None or nodata is not None) and fmt not in ("tif", "tiff"):
        raise InvalidInputError(f"{dst}: --dtype and --nodata apply to a GeoTIFF (.tif) output, not {fmt}")
    check_output(dst, force=force)
    check_executor(workers, scheduler)
    if _is_stream(src):  # a pipe: held in memory, the reader needs to seek
        src = src.read()
    with open_map(src, max_cells=max_cells) as cmap:
        with executor(workers, scheduler, tiles=cmap.tile_count) as map_tiles:
            return stream.decompress_bands(cmap, dst, fmt, cog=cog, map_tiles=map_tiles, on_stage=on_stage,
                                           write=atomic_write, dtype=dtype, nodata=nodata)


def read_dem(src: str | os.PathLike[str], params: Params, *, format: str | None = None,  # noqa: A002
             classes: Sequence[int] | None = None, topic: str | None = None, drop_nonfinite: bool = False,
             chunk_points: int | None = None, on_stage: Stage = no_stage,
             pose_topic: str | None = None, map_frame: str | None = None) -> tuple[DEM, int, dict[str, Any]]:
    """The DEM :func:`compress_file` codes for ``src``: a raster's own grid (resolution ``'auto'``),
    or the cloud gridded at ``params``; with the points it came from and the CRS.

    Every command that turns a file into a map (compress, sweep, compare) goes through here.

    Returns
    -------
    dem : DEM
    point_count : int
        Points read (pixels, for a raster's own grid).
    crs : dict
    """
    with open_reader(src, format=format, classes=classes, topic=topic, drop_nonfinite=drop_nonfinite,
                     chunk_points=chunk_points, pose_topic=pose_topic, map_frame=map_frame) as reader:
        if reader.own_grid and params.resolution == "auto":
            dem = reader.dem()
            return dem, int(dem.mask.sum()), reader.crs
        dem, count = _grid(reader, params, on_stage)
        return dem, count, reader.crs


def _grid(reader: Reader, params: Params, on_stage: Stage) -> tuple[DEM, int]:
    """Summarise the reader's chunks, [choose the resolution], fit the grid, rasterize; and the points read."""
    cloud = _fit(reader, params, on_stage)
    return cloud.rasterize(params.aggregate), cloud.summary.count


@dataclass
class _Cloud:
    """A cloud summarised and its grid fitted: held whole (``held``, one chunk) or read in chunks of ``n``;
    ``in_bands``: its grid is coded band by band from files (:func:`_compress_in_bands`)."""

    reader: Reader
    n: int | None
    held: list[np.ndarray]
    summary: CloudSummary
    grid: Grid
    in_bands: bool

    def chunks(self) -> Iterable[np.ndarray]:
        return iter(self.held) if self.n is None else self.reader.chunks(self.n)

    def rasterize(self, aggregate: str) -> DEM:
        if self.n is None:
            return rasterize(self.held[0], self.grid, aggregate=aggregate)
        return rasterize_chunks(self.chunks, self.grid, aggregate=aggregate)

    def segments(self) -> Iterator[Iterator[np.ndarray]]:
        """The points as :func:`~dftpcc.grid.rasterize_bands` takes them: a held cloud is one segment (let go
        once read), in pieces of :data:`~dftpcc.io.DEFAULT_CHUNK_POINTS`; a cloud read in chunks, a segment each."""
        if self.n is None:
            points = self.held.pop()
            yield (points[i:i + DEFAULT_CHUNK_POINTS] for i in range(0, points.shape[0], DEFAULT_CHUNK_POINTS))
            return
        for chunk in self.reader.chunks(self.n):
            yield iter((chunk,))


def _fit(reader: Reader, params: Params, on_stage: Stage, *, bands: Path | None = None) -> _Cloud:
    """Summarise the reader's chunks, [choose the resolution], fit the grid.

    A cloud that fits in memory is one chunk, read once and held: that is the
    whole-cloud computation exactly (the same sums, extremes and cell
    heights), and any aggregate, the median included, applies to it. With ``bands`` (the folder its
    files would go in), a grid that :func:`~dftpcc.stream.codes_in_bands` is held to the limit of a
    band (:func:`~dftpcc.limits.check_band_size`), not of a grid held whole, and to the room on that
    disk (:func:`~dftpcc.limits.check_spill_space`).
    """
    n = _chunk_size(reader, params.aggregate)
    held: list[np.ndarray] = []
    if n is None:
        parts = list(reader.chunks(None))
        held = [np.concatenate(parts)] if len(parts) > 1 else parts
    else:
        check_chunked_aggregate(params.aggregate)
    chunks: Callable[[], Iterable[np.ndarray]] = (lambda: iter(held)) if n is None else (lambda: reader.chunks(n))
    summary = CloudSummary(hull=params.frame == "oriented")
    for points in chunks():
        summary.add(points)
    if not summary.count:
        raise reader.empty_error()
    resolution = summary.auto_resolution(chunks) if params.resolution == "auto" else params.resolution
    on_stage("grid")

    def check_size(rows: float, cols: float, resolution: float) -> None:
        shape = (int(rows), int(cols)) if math.isfinite(rows * cols) else None
        if bands is not None and shape is not None and stream.codes_in_bands(shape, params):
            check_band_size(tile_size_for(params, shape), rows, cols, resolution, summary.count)
            check_spill_space(summary.count, rows, cols, resolution, bands)
        else:
            check_grid_size(rows, cols, resolution)

    grid = summary.fit_grid(resolution, frame=params.frame, check_size=check_size)
    return _Cloud(reader, n, held, summary, grid, bands is not None and stream.codes_in_bands(grid.shape, params))


def _folder(dst: str | os.PathLike[str]) -> Path:
    """The folder ``dst`` is written in: where a cloud gridded band by band spills to."""
    return Path(dst).parent if str(Path(dst).parent) else Path(".")


#: Prefix of the folder a cloud gridded band by band spills to, beside the output.
SPILL_PREFIX = ".dftpcc-bands-"


def _compress_in_bands(cloud: _Cloud, dst: str | os.PathLike[str], params: Params, *, workers: int | None,
                       scheduler: str | None, on_stage: Stage, name: str) -> None:
    """Grid ``cloud`` band by band into a temporary folder beside ``dst`` (:func:`~dftpcc.grid.rasterize_bands`;
    removed at the end, also on an error) and code it from there (:func:`~dftpcc.stream.compress_bands`):
    the bytes :func:`~dftpcc.stream.compress_gridded` writes of the grid held whole."""
    with tempfile.TemporaryDirectory(prefix=SPILL_PREFIX, dir=_folder(dst)) as tmp:
        bands = rasterize_bands(cloud.segments(), cloud.grid, tmp, band_rows=tile_size_for(params, cloud.grid.shape),
                                aggregate=params.aggregate, on_stage=on_stage)
        with executor(workers, scheduler) as map_tiles:
            stream.compress_bands(bands, dst, params, point_count=cloud.summary.count, crs=cloud.reader.crs,
                                  name=name, map_tiles=map_tiles, on_stage=on_stage, write=atomic_write)


def _trusted(data: bytes) -> int:
    """The grid size of a map we just wrote: opening our own output needs no decompression-bomb budget."""
    return unpack(data, max_cells=MAX_CELLS)[0].grid.size


def decompress_file(src: Source, dst: Source, *,
                    format: str | None = None, max_bytes: int | None = None,  # noqa: A002
                    cutoff: float | None = None, max_cells: int | None = None, force: bool = False,
                    bbox: Sequence[float] | None = None, workers: int | None = None,
                    scheduler: str | None = None, densify: int = 1, dtype: str | None = None,
                    nodata: float | None = None, cog: bool = False, on_stage: Stage = no_stage,
                    backend: kernels.Backend | str | None = None) -> np.ndarray:
    """Decode the ``.dftpc`` file ``src`` and write the rebuilt map to ``dst``.

    ``bbox`` (xmin, ymin, xmax, ymax, the map's units and CRS) writes only that region; of a
    tiled map only the tiles it touches are read and decoded. ``workers`` or ``scheduler``
    decode a tiled map's tiles on a dask cluster, as for :func:`compress_file`. ``densify`` K > 1
    writes K x K samples of the rebuilt surface per cell instead of one point
    (:func:`~dftpcc.rebuild.dem_to_dense_points`: what a scan registers against best,
    docs/relocalization.md); a GeoTIFF output keeps its cells.

    The output format comes from ``dst``'s extension; ``.tif`` writes the
    rebuilt DEM as a GeoTIFF, any other the point cloud. The CRS read from
    the original file is written back where the format has room for it. ``backend``: as for
    :func:`dftpcc.decompress`.

    A GeoTIFF is written in the sample type and with the nodata value of the raster the map was
    made from, where the file's bound lets an integer type round back to its values
    (:func:`~dftpcc.io.geotiff.output_type`; a :class:`~dftpcc.errors.RasterTypeWarning` says
    when it does not); ``dtype`` and ``nodata`` choose others; ``cog`` writes a Cloud Optimized
    GeoTIFF. ``on_stage`` is called with each stage's name (``decode``, ``write``).

    Returns
    -------
    ndarray, shape (cells, 3)
        The rebuilt points, metres.
    """
    if _is_stream(dst) and format is None:
        raise InvalidInputError("a stream has no extension: name the output format (--format xyz, npy, ply, ...)")
    fmt = format_of("x" if _is_stream(dst) else dst, format, output=True)
    if not _is_stream(dst):
        check_output(dst, force=force)
    check_executor(workers, scheduler)
    if isinstance(densify, bool) or not isinstance(densify, int) or densify < 1:
        raise InvalidInputError(f"densify must be a whole number >= 1, got {densify!r}")
    raster = io.REGISTRY[fmt].dem_writer is not None
    if densify > 1 and raster:
        raise InvalidInputError(f"{dst}: a {fmt} output holds the DEM's cells; densify applies to point outputs")
    if not raster and (dtype is not None or nodata is not None or cog):
        raise InvalidInputError(f"{dst}: --dtype, --nodata and --cog apply to a GeoTIFF (.tif) output, not {fmt}")
    if backend is not None:
        backend = kernels.Backend.of(backend)
    if not _is_stream(src) and Path(src).exists() and not Path(src).is_file():
        with open(src, "rb") as fh:  # a pipe such as /dev/stdin
            src = _Buffer(fh.read(), str(src))
    with open_map(src, max_bytes=max_bytes, max_cells=max_cells) as cmap, \
            kernels.use(backend, work=cmap.header.cell_count, min_work=kernels.COMPILED_MIN_MAP_CELLS):
        if raster:  # the sample type and nodata checked before decoding
            from .io.geotiff import output_type

            sample, empty, note = output_type(cmap.header.stats, dtype=dtype, nodata=nodata,
                                              bound_holds=cutoff is None and max_bytes is None)
        on_stage("decode")
        with executor(workers, scheduler, tiles=cmap.tile_count) as map_tiles:
            dem = cmap.read_dem(cutoff=cutoff, bbox=bbox, map_tiles=map_tiles)
        crs = cmap.crs
        on_stage("write")
        points = dem_to_points(dem) if densify == 1 else dem_to_dense_points(dem, densify)
    with tempfile.TemporaryDirectory(prefix="dftpcc-") if _is_stream(dst) else _nothing() as tmp:
        target = Path(tmp) / f"out.{fmt}" if _is_stream(dst) else dst
        if raster:
            if note:
                warnings.warn(f"{getattr(dst, 'name', dst)}: {note}", RasterTypeWarning, stacklevel=2)
            io.write_dem(target, dem, crs=crs, format=fmt, dtype=sample, nodata=empty, cog=cog)
        else:
            write(target, points, crs=crs, format=fmt)
        if _is_stream(dst):
            with open(target, "rb") as fh:
                shutil.copyfileobj(fh, dst)
            dst.flush()
    return points


class _Buffer:
    """Bytes read from a pipe, with the pipe's name for messages."""

    def __init__(self, data: bytes, name: str):
        self.data, self.name = data, name

    def read(self) -> bytes:
        return self.data


@contextmanager
def _nothing() -> Iterator[None]:
    yield None
