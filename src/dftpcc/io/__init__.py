"""Read stage (and the final write): point clouds and DEMs in the formats users have, one module per format.

:data:`REGISTRY` maps each format to the module that reads (and writes) it,
imported on first use; :func:`open_reader` opens a file as a
:class:`~dftpcc.io.reader.Reader` that knows its count, CRS and chunks, and
:func:`read` is its one-chunk read. Coordinates stay float64. A CRS travels
as a dict ``{"wkt": str | None, "las_vlrs": [...]}``: the WKT when the source
has one, and the raw LAS georeferencing records (see :mod:`dftpcc.io.las`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from importlib import import_module
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from ..errors import InvalidInputError, MissingDependencyError, UnsupportedFormatError
from .atomic import atomic_write, check_output, writer_errors
from ..remote import is_url, url_suffix
from .reader import DEFAULT_CHUNK_POINTS, PointCloud, Reader

if TYPE_CHECKING:
    from ..dem import DEM
    from .geotiff import dem_from_geotiff, read_raster_dem, write_geotiff

__all__ = ["PointCloud", "Reader", "ChunkedCloud", "Format", "REGISTRY", "FORMATS", "CHUNKED_FORMATS",
           "DEFAULT_CHUNK_POINTS", "URL_FORMATS", "format_of", "sniff_format", "open_reader", "open_chunked", "check_chunkable", "read",
           "stored_point_count", "write", "write_dem", "write_geotiff", "read_raster_dem", "dem_from_geotiff", "atomic_write", "check_output"]

#: A point writer: ``write(tmp_path, points (N, 3) float64, crs dict, format name)``.
PointWriter = Callable[[Path, np.ndarray, "dict[str, Any]", str], None]


@dataclass(frozen=True)
class Format:
    """One entry of the registry: a format, its extensions, and where its reader and writer live.

    Attributes
    ----------
    name : str
        The format name (``--format``).
    extensions : tuple of str
        File extensions that mean this format, lower case with the dot.
    module : str
        The module of :mod:`dftpcc.io` holding its reader (and writer),
        imported the first time the format is used.
    reader : str
        Its :class:`~dftpcc.io.reader.Reader` class.
    writer : str or None
        Its point writer function; None for a format dftpcc does not write points in.
    dem_writer : str or None
        Its DEM writer function, for a raster format (``write(path, dem, *, crs)``).
    not_written : str
        What to say to someone writing points in a format dftpcc only reads.
    streams : bool
        Whether its reader reads from disk chunk by chunk, so that memory
        holds one chunk (:data:`CHUNKED_FORMATS`); other readers read the
        file whole, then slice it.
    by_url : bool
        Whether its reader reads a URL by range requests (:data:`URL_FORMATS`); a file of
        another format at a URL is downloaded first (:func:`dftpcc.files.compress_file`).
    counted : bool
        Whether its header says how many points it holds (a raster: its pixels; a ROS bag: a
        bound), for :func:`stored_point_count`; every format read in chunks does.
    """

    name: str
    extensions: tuple[str, ...]
    module: str
    reader: str
    writer: str | None = None
    dem_writer: str | None = None
    not_written: str = ""
    streams: bool = False
    by_url: bool = False
    counted: bool = False

    def load(self) -> ModuleType:
        """The format's module (imported on first use: rasterio alone takes a fifth of a second)."""
        return import_module(f"{__name__}.{self.module}")

    def reader_class(self) -> type[Reader]:
        return getattr(self.load(), self.reader)

    def writer_function(self) -> PointWriter:
        if self.writer is None:
            raise UnsupportedFormatError(self.not_written)
        return getattr(self.load(), self.writer)


#: Format name -> its entry.
REGISTRY: dict[str, Format] = {f.name: f for f in (
    Format("las", (".las",), "las", "LasReader", "write_las", streams=True, counted=True, by_url=True),
    Format("laz", (".laz",), "las", "LasReader", "write_las", streams=True, counted=True, by_url=True),
    Format("ply", (".ply",), "ply", "PlyReader", "write_ply", streams=True, counted=True),
    Format("pcd", (".pcd",), "pcd", "PcdReader", "write_pcd"),
    Format("xyz", (".xyz", ".txt"), "text", "TextReader", "write_text"),
    Format("csv", (".csv",), "text", "TextReader", "write_text"),
    Format("npy", (".npy",), "npy", "NpyReader", "write_npy", streams=True, counted=True),
    Format("drc", (".drc",), "drc", "DracoReader",
           not_written="Draco files are read, not written: write .ply, .pcd, .las or .npy"),
    Format("tif", (".tif", ".tiff"), "geotiff", "GeoTiffReader", dem_writer="write_geotiff",
           not_written="a GeoTIFF holds a DEM, not points: use write_geotiff", by_url=True,
           counted=True),
    Format("rosbag", (".bag", ".db3", ".mcap"), "rosbag", "BagReader",
           not_written="ROS bags are read, not written as files: a ROS 2 bag of the map is a folder "
                       "(decompress MAP out_bag/, or dftpcc.io.rosmap.write_map_bag); "
                       "write .ply, .pcd, .las or .npy", streams=True, counted=True),
)}
#: Extension -> format name.
FORMATS: dict[str, str] = {ext: f.name for f in REGISTRY.values() for ext in f.extensions}
#: Extensions dftpcc writes (points or a DEM), sorted.
WRITTEN_EXTENSIONS: tuple[str, ...] = tuple(sorted(ext for f in REGISTRY.values() if f.writer or f.dem_writer
                                                   for ext in f.extensions))
#: Formats read chunk by chunk from disk (:func:`open_chunked`).
CHUNKED_FORMATS: tuple[str, ...] = tuple(name for name, f in REGISTRY.items() if f.streams)
#: Formats read from a URL by range requests (:class:`dftpcc.remote.Remote`), without a download.
URL_FORMATS: tuple[str, ...] = tuple(name for name, f in REGISTRY.items() if f.by_url)

#: Functions of a format module offered here, imported on first use (see :func:`__getattr__`).
_LAZY = {"write_geotiff": "geotiff", "read_raster_dem": "geotiff", "dem_from_geotiff": "geotiff"}


#: The format modules, imported on first use too (``dftpcc.io.las`` works without an import).
_MODULES = {f.module for f in REGISTRY.values()}


def __getattr__(name: str) -> Any:
    # The GeoTIFF functions live with rasterio in io/geotiff.py, imported when first asked for.
    if name in _LAZY:
        return getattr(import_module(f"{__name__}.{_LAZY[name]}"), name)
    if name in _MODULES:
        return import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY) | _MODULES)


def format_of(path: str | os.PathLike[str], fmt: str | None = None, *, output: bool = False) -> str:
    """The format name of ``path``: ``fmt`` when given, else from its extension (a folder: a ROS 2 bag).

    ``output``: ``path`` is to be written, so an unknown extension is answered with the
    extensions dftpcc writes (not those it only reads, such as ``.drc`` or ``.bag``).

    Raises
    ------
    UnsupportedFormatError
        An unknown format name or extension.
    """
    if fmt:
        fmt = fmt.lower().lstrip(".")
        if fmt not in REGISTRY:
            raise UnsupportedFormatError(f"unknown format {fmt!r}; known: {', '.join(sorted(REGISTRY))}")
        return fmt
    if is_url(path):
        ext = url_suffix(str(path))
    elif Path(path).is_dir() and (Path(path) / "metadata.yaml").is_file():
        return "rosbag"  # a ROS 2 bag is a folder
    else:
        ext = Path(path).suffix.lower()
    if ext not in FORMATS:
        known = WRITTEN_EXTENSIONS if output else tuple(sorted(FORMATS))
        bag = ", or a folder name ending in / for a ROS 2 bag" if output else ""
        raise UnsupportedFormatError(
            f"{path}: cannot tell the format from the extension {ext or '(none)'}; "
            f"use one of {', '.join(known)}{bag}, or name the format (--format)")
    return FORMATS[ext]


#: Leading bytes that name a format, for a stream without an extension (standard input).
MAGIC_BYTES: tuple[tuple[bytes, str], ...] = (
    (b"ply\n", "ply"), (b"ply\r\n", "ply"), (b"\x93NUMPY", "npy"), (b"DRACO", "drc"),
    (b"II*\x00", "tif"), (b"MM\x00*", "tif"), (b"II+\x00", "tif"), (b"MM\x00+", "tif"),
    (b"#ROSBAG", "rosbag"), (b"# .PCD", "pcd"), (b"VERSION", "pcd"),
)
#: Byte of a LAS header holding the point format id; LAZ sets its top bits (laszip's convention).
_LAS_POINT_FORMAT_BYTE = 104
_LAZ_BITS = 0xC0


def sniff_format(head: bytes) -> str | None:
    """The format a file's first bytes (at least 105 for LAS/LAZ) announce, or None (text, or unknown).

    As GDAL and PDAL identify a file by its signature, not its name.
    """
    if head.startswith(b"LASF"):
        if len(head) > _LAS_POINT_FORMAT_BYTE and head[_LAS_POINT_FORMAT_BYTE] & _LAZ_BITS:
            return "laz"
        return "las"
    return next((fmt for magic, fmt in MAGIC_BYTES if head.startswith(magic)), None)


def open_reader(path: str | os.PathLike[str], *, format: str | None = None,  # noqa: A002
                classes: Sequence[int] | None = None, topic: str | None = None, drop_nonfinite: bool = False,
                chunk_points: int | None = None, pose_topic: str | None = None,
                map_frame: str | None = None) -> Reader:
    """Open a point cloud (or GeoTIFF DEM) file for reading, as laspy's ``open`` does: the header only.

    Parameters
    ----------
    path : path or URL
        A URL (``https://``, ``s3://``...) of a LAS, LAZ or GeoTIFF file is read by range
        requests through fsspec (:data:`URL_FORMATS`, :class:`dftpcc.remote.Remote`).
    format : str, optional
        A name of :data:`REGISTRY`; default from the extension (:func:`format_of`).
    classes : sequence of int, optional
        LAS/LAZ only: keep points of these classification codes (2 = ground).
    topic : str, optional
        ROS bags only: the PointCloud2 topic (default: the bag's only one).
    pose_topic : str, optional
        ROS bags only: the poses (``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped``
        or ``/tf``) of scans recorded in the sensor frame; each scan is placed
        in the poses' frame at its stamp (:func:`dftpcc.io.rosbag.posed_scans`);
        ``/tf`` is read with ``/tf_static`` as a tree.
    map_frame : str, optional
        ROS bags with a TF ``pose_topic`` only: the frame to place the scans
        in (default: the root of their TF tree).
    drop_nonfinite : bool
        Drop rows with a NaN or infinite coordinate instead of refusing
        (:meth:`~Reader.chunks`) or returning them (:meth:`~Reader.read`).
    chunk_points : int, optional
        Points per chunk of :meth:`~Reader.chunks`; only for the formats
        read in chunks (:data:`CHUNKED_FORMATS`). Default: one chunk.

    Returns
    -------
    Reader
        A context manager; ``stored_points``, ``crs``, ``chunks(n)``, ``read()``.

    Raises
    ------
    UnsupportedFormatError
        An unknown format or extension.
    InvalidInputError
        Missing or unreadable file, an option the format cannot honour,
        ``chunk_points`` for a format read whole, a bad ``chunk_points``.
    MissingDependencyError
        The format needs an optional package that is not installed.
    """
    path = str(path) if is_url(path) else Path(path)
    fmt = format_of(path, format)
    if chunk_points is not None:
        check_chunkable(path, fmt)
    entry = REGISTRY[fmt]
    if isinstance(path, str) and not entry.by_url:
        raise InvalidInputError(f"{path}: {fmt} files are not read by URL (only {', '.join(URL_FORMATS)}): "
                                f"download it first, or compress it (compress downloads it)")
    return entry.reader_class()(path, format=fmt, classes=classes, topic=topic, drop_nonfinite=drop_nonfinite,
                                chunk_points=chunk_points, streams=entry.streams, pose_topic=pose_topic,
                                map_frame=map_frame)


def open_chunked(path: str | os.PathLike[str], *, format: str | None = None,  # noqa: A002
                 classes: Sequence[int] | None = None, drop_nonfinite: bool = False,
                 chunk_points: int = DEFAULT_CHUNK_POINTS, topic: str | None = None) -> Reader:
    """:func:`open_reader` for a cloud to read chunk by chunk (:data:`CHUNKED_FORMATS`).

    ``chunk_points`` defaults to :data:`DEFAULT_CHUNK_POINTS`; each call of
    the reader's ``chunks()`` reads the file again, so memory holds one chunk.

    Raises
    ------
    InvalidInputError
        As :func:`open_reader`, and a format that cannot be read in chunks.
    """
    check_chunkable(path, format)
    return open_reader(path, format=format, classes=classes, topic=topic, drop_nonfinite=drop_nonfinite,
                       chunk_points=chunk_points)


#: The name :func:`open_chunked` returned before readers were per format.
ChunkedCloud = Reader


def check_chunkable(path: str | os.PathLike[str], format: str | None = None) -> str:  # noqa: A002
    """The format of ``path``, or a clear error if it cannot be read chunk by chunk."""
    fmt = format_of(path, format)
    if not REGISTRY[fmt].streams:
        raise InvalidInputError(f"{path}: {fmt} files cannot be read in chunks; chunked reading supports "
                                f"{', '.join(f.upper() for f in CHUNKED_FORMATS)}")
    return fmt


def read(path: str | os.PathLike[str], *, format: str | None = None,  # noqa: A002
         classes: Sequence[int] | None = None, drop_nonfinite: bool = False,
         topic: str | None = None, pose_topic: str | None = None, map_frame: str | None = None) -> PointCloud:
    """Read a point cloud whole.

    Parameters
    ----------
    path : path
    format : str, optional
        ``las``, ``laz``, ``ply``, ``pcd``, ``xyz``, ``csv``, ``npy``,
        ``drc`` (Draco, with the optional DracoPy), ``tif`` (every valid
        pixel of a GeoTIFF DEM becomes a point at its centre) or ``rosbag``
        (a ROS 1 ``.bag`` or a ROS 2 bag folder, see :mod:`dftpcc.io.rosbag`);
        default from the extension.
    classes : sequence of int, optional
        LAS/LAZ only: keep points of these classification codes (2 = ground).
    drop_nonfinite : bool
        Drop rows with a NaN or infinite coordinate instead of returning
        them (compression refuses them). Default: keep them.
    topic : str, optional
        ROS bags only: the PointCloud2 topic (default: the bag's only one).
    pose_topic : str, optional
        ROS bags only: the poses of scans in the sensor frame (as :func:`open_reader`).
    map_frame : str, optional
        ROS bags with a TF ``pose_topic`` only: the frame to place them in (as :func:`open_reader`).

    Returns
    -------
    PointCloud
        x, y, z (N, 3) float64 in the file's units, and its CRS.

    Raises
    ------
    InvalidInputError
        Missing or unreadable file, no x/y/z, an option the format cannot
        honour, or no point left.
    """
    with open_reader(path, format=format, classes=classes, topic=topic, drop_nonfinite=drop_nonfinite,
                     pose_topic=pose_topic, map_frame=map_frame) as reader:
        return reader.read()


def stored_point_count(path: str | os.PathLike[str], format: str | None = None) -> int | None:  # noqa: A002
    """Points a file holds, for the formats whose header says (:attr:`Format.counted`); else None.

    From the header for LAS, LAZ, PLY and NPY; a GeoTIFF's pixels. A ROS bag has no such count:
    its size over 12 bytes (one float32 x, y, z, the smallest point a
    PointCloud2 holds) bounds it from above.
    """
    try:
        if not REGISTRY[format_of(path, format)].counted:
            return None
        with open_reader(path, format=format) as reader:
            return reader.points_bound
    except (InvalidInputError, MissingDependencyError, OSError):
        return None


def write(path: str | os.PathLike[str], points: np.ndarray, *, crs: dict[str, Any] | None = None,
          format: str | None = None) -> None:  # noqa: A002
    """Write points to ``path`` in the format of its extension (or ``format``).

    The file appears complete or not at all (temporary file, then rename).
    For a DEM as GeoTIFF use :func:`write_geotiff`.

    Parameters
    ----------
    path : path
    points : array_like, shape (N, 3)
        x, y, z in metres.
    crs : dict, optional
        Written where the format has room for it (LAS records, a PLY comment).
    format : str, optional
        Default from the extension.

    Raises
    ------
    UnsupportedFormatError
        A format dftpcc only reads (GeoTIFF, ROS bags, Draco).
    InvalidInputError
        The writer cannot represent the points or the CRS (e.g. a LAS
        record over 64 KiB, a WKT a PLY comment cannot hold), or the folder
        does not exist.
    OSError
        The file system refused (permissions, disk full); the message names ``path``.
    """
    fmt = format_of(path, format, output=True)
    writer = REGISTRY[fmt].writer_function()
    points = np.asarray(points, dtype=np.float64)
    with writer_errors(path, fmt):
        atomic_write(path, lambda tmp: writer(tmp, points, crs or {}, fmt))


def write_dem(path: str | os.PathLike[str], dem: DEM, *, crs: dict[str, Any] | None = None,
              format: str | None = None, **options: Any) -> None:  # noqa: A002
    """Write a DEM to ``path`` in a raster format (GeoTIFF: :func:`~dftpcc.io.geotiff.write_geotiff`,
    which takes ``**options``: ``dtype``, ``nodata``, ``cog``).

    Raises
    ------
    UnsupportedFormatError
        A format that holds points, not a DEM.
    """
    fmt = format_of(path, format, output=True)
    entry = REGISTRY[fmt]
    if entry.dem_writer is None:
        raise UnsupportedFormatError(f"{path}: {fmt} files hold points, not a DEM: write points with write()")
    getattr(entry.load(), entry.dem_writer)(path, dem, crs=crs, **options)
