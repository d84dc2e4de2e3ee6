"""Read stage (and the final write): point clouds and DEMs in the formats users have.

LAS/LAZ (laspy + lazrs), PLY (plyfile), PCD (pypcd4), XYZ/CSV/TXT (numpy),
NPY, and GeoTIFF DEMs (rasterio). The format comes from the file extension
unless named. Coordinates stay float64. A CRS travels as a dict
``{"wkt": str | None, "las_vlrs": [...]}``: the WKT when the source has one,
and the raw LAS georeferencing records so a LAS -> .dftpc -> LAS round trip
gives back the very same records.
"""

from __future__ import annotations

import base64
import os
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from . import rosbag
from ..dem import DEM, Grid, nonfinite_error
from ..dem import drop_nonfinite as _drop_nonfinite  # read() has a keyword of that name
from ..errors import InvalidInputError, MissingDependencyError, UnsupportedFormatError
from .atomic import atomic_write

__all__ = ["PointCloud", "ChunkedCloud", "read", "open_chunked", "write", "read_raster_dem", "write_geotiff", "FORMATS",
           "format_of"]

#: Extension -> format name.
FORMATS = {
    ".las": "las", ".laz": "laz", ".ply": "ply", ".pcd": "pcd",
    ".xyz": "xyz", ".txt": "xyz", ".csv": "csv", ".npy": "npy",
    ".tif": "tif", ".tiff": "tif",
    ".bag": "rosbag", ".db3": "rosbag", ".mcap": "rosbag",
}
#: LAS VLRs that carry georeferencing (LASF_Projection).
_LAS_CRS_USER = "LASF_Projection"
_WKT_RECORD = 2112


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


def format_of(path: str | os.PathLike[str], fmt: str | None = None) -> str:
    """The format name of ``path`` from ``fmt`` or its extension."""
    if fmt:
        fmt = fmt.lower().lstrip(".")
        if fmt not in set(FORMATS.values()):
            raise UnsupportedFormatError(f"unknown format {fmt!r}; known: {', '.join(sorted(set(FORMATS.values())))}")
        return fmt
    if Path(path).is_dir() and (Path(path) / "metadata.yaml").is_file():
        return "rosbag"  # a ROS 2 bag is a folder
    ext = Path(path).suffix.lower()
    if ext not in FORMATS:
        raise UnsupportedFormatError(
            f"{path}: cannot tell the format from the extension {ext or '(none)'}; "
            f"use one of {', '.join(sorted(FORMATS))} or name the format")
    return FORMATS[ext]


def read(path: str | os.PathLike[str], *, format: str | None = None,  # noqa: A002
         classes: Sequence[int] | None = None, drop_nonfinite: bool = False,
         topic: str | None = None) -> PointCloud:
    """Read a point cloud.

    Parameters
    ----------
    path : path
    format : str, optional
        ``las``, ``laz``, ``ply``, ``pcd``, ``xyz``, ``csv``, ``npy``,
        ``tif`` (every valid pixel of a GeoTIFF DEM becomes a point at its
        centre) or ``rosbag`` (a ROS 1 ``.bag`` or a ROS 2 bag folder, see
        :mod:`dftpcc.rosbag`); default from the extension.
    classes : sequence of int, optional
        LAS/LAZ only: keep points of these classification codes (2 = ground).
    drop_nonfinite : bool
        Drop rows with a NaN or infinite coordinate instead of returning
        them (compression refuses them). Default: keep them.
    topic : str, optional
        ROS bags only: the PointCloud2 topic (default: the bag's only one).

    Raises
    ------
    InvalidInputError
        Missing or unreadable file, no x/y/z, or no point left.
    """
    path = Path(path)
    fmt = format_of(path, format)
    _check_source(path, fmt, classes, topic)
    reader = {"las": _read_las, "laz": _read_las, "ply": _read_ply, "pcd": _read_pcd,
              "xyz": _read_text, "csv": _read_text, "npy": _read_npy, "tif": _read_tif}.get(fmt)
    try:
        if fmt in ("las", "laz"):
            cloud = reader(path, classes)
        elif fmt == "rosbag":
            cloud = PointCloud(rosbag.read_bag(path, topic))
        else:
            cloud = reader(path)
    except (InvalidInputError, MissingDependencyError):
        raise
    except Exception as exc:  # noqa: BLE001 - third-party readers raise anything on bad files
        raise InvalidInputError(f"{path}: cannot read as {fmt}: {exc}") from None
    pts = cloud.points
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InvalidInputError(f"{path}: expected x, y, z columns, got shape {pts.shape}")
    if drop_nonfinite and pts.shape[0]:
        cloud.points, dropped = _drop_nonfinite(pts)
        if cloud.points.shape[0] == 0:
            raise InvalidInputError(f"{path}: all {dropped:,} points have NaN or infinite coordinates")
    if cloud.points.shape[0] == 0:
        raise InvalidInputError(f"{path}: no points" + (" of the selected classes" if classes else ""))
    return cloud


def _check_source(path: Path, fmt: str, classes: Sequence[int] | None, topic: str | None) -> None:
    """The checks every reader shares: the file exists, the options fit the format."""
    if fmt == "rosbag":
        rosbag.bag_folder(path)  # a file or a ROS 2 folder
    elif not path.is_file():
        raise InvalidInputError(f"{path}: no such file")
    if classes is not None and fmt not in ("las", "laz"):
        raise InvalidInputError("classes can only be selected in LAS/LAZ files")
    if topic is not None and fmt != "rosbag":
        raise InvalidInputError("a topic can only be chosen in ROS bags")


def _read_las(path: Path, classes: Sequence[int] | None) -> PointCloud:
    import laspy

    las = laspy.read(path)
    pts = np.column_stack([np.asarray(las.x, dtype=np.float64), np.asarray(las.y, dtype=np.float64),
                           np.asarray(las.z, dtype=np.float64)])
    if classes is not None:
        pts = pts[np.isin(np.asarray(las.classification), np.asarray(list(classes)))]
    return PointCloud(pts, _las_crs(list(las.header.vlrs) + list(getattr(las, "evlrs", None) or [])))


def _las_crs(records: Sequence[Any]) -> dict[str, Any]:
    """The CRS dict of a LAS file's (E)VLRs: its WKT and its georeferencing records, raw."""
    vlrs, wkt = [], None
    for vlr in records:
        if getattr(vlr, "user_id", "") != _LAS_CRS_USER:
            continue
        data = vlr.record_data_bytes() if hasattr(vlr, "record_data_bytes") else bytes(vlr.record_data)
        vlrs.append({"record_id": int(vlr.record_id), "description": str(vlr.description),
                     "data": base64.b64encode(data).decode("ascii")})
        if vlr.record_id == _WKT_RECORD:
            wkt = data.rstrip(b"\0").decode("utf-8", "replace")
    return {"wkt": wkt, "las_vlrs": vlrs} if vlrs else {}


def _read_ply(path: Path) -> PointCloud:
    from plyfile import PlyData

    ply = PlyData.read(str(path))
    if "vertex" not in ply:
        raise InvalidInputError(f"{path}: PLY file has no vertex element")
    v = ply["vertex"]
    names = v.data.dtype.names or ()
    if not {"x", "y", "z"} <= set(names):
        raise InvalidInputError(f"{path}: PLY vertices lack x, y or z")
    pts = np.column_stack([np.asarray(v[c], dtype=np.float64) for c in "xyz"])
    return PointCloud(pts, _ply_crs(ply.comments))


def _ply_crs(comments: Sequence[str]) -> dict[str, Any]:
    wkt = next((c[len("crs "):] for c in comments if c.startswith("crs ")), None)
    return {"wkt": wkt} if wkt else {}


def _read_pcd(path: Path) -> PointCloud:
    from pypcd4 import PointCloud as PCD

    pc = PCD.from_path(path)
    fields = list(pc.fields)
    if not {"x", "y", "z"} <= set(fields):
        raise InvalidInputError(f"{path}: PCD lacks x, y or z fields")
    arr = pc.numpy(("x", "y", "z"))
    return PointCloud(np.asarray(arr, dtype=np.float64))


def _read_text(path: Path) -> PointCloud:
    with path.open("r", encoding="utf-8", errors="replace") as fh:
        first = fh.readline()
    delimiter = "," if "," in first else None
    skip = 0
    try:
        [float(t) for t in (first.split(",") if delimiter else first.split())[:3]]
    except ValueError:
        skip = 1  # a header line
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # an empty file is reported as "no points"
        data = np.loadtxt(path, delimiter=delimiter, skiprows=skip, usecols=(0, 1, 2), ndmin=2,
                          dtype=np.float64)
    return PointCloud(data)


def _read_npy(path: Path) -> PointCloud:
    arr = np.load(path, allow_pickle=False)
    if arr.dtype.names:
        arr = np.column_stack([arr[c] for c in "xyz"])
    arr = np.asarray(arr, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise InvalidInputError(f"{path}: expected an (N, 3) array, got shape {arr.shape}")
    return PointCloud(arr[:, :3])


#: Formats :func:`open_chunked` reads chunk by chunk.
CHUNKED_FORMATS = ("las", "laz", "ply", "npy", "rosbag")
#: Points per chunk unless told otherwise (about 24 MB of float64 x, y, z).
DEFAULT_CHUNK_POINTS = 1_000_000


@dataclass
class ChunkedCloud:
    """A point cloud file read chunk by chunk, as many passes as the caller needs.

    Made by :func:`open_chunked`. Each call of :meth:`chunks` reads the file
    again, so memory holds one chunk, not the cloud.

    Attributes
    ----------
    path : Path
    format : str
    crs : dict
        As :attr:`PointCloud.crs`.
    stored_points : int or None
        Points in the file, before class selection (None for a ROS bag,
        whose messages would all have to be read to count them).
    """

    path: Path
    format: str
    crs: dict[str, Any]
    stored_points: int | None
    classes: Sequence[int] | None = None
    topic: str | None = None
    drop_nonfinite: bool = False
    chunk_points: int = DEFAULT_CHUNK_POINTS
    #: Rows dropped as non-finite in the last complete pass.
    dropped: int = 0

    def chunks(self) -> Iterator[np.ndarray]:
        """One pass over the file: finite (n, 3) float64 arrays of the selected points.

        Raises
        ------
        InvalidInputError
            A row with a NaN or infinite coordinate (unless ``drop_nonfinite``),
            or a file that stops being readable part way.
        """
        row, dropped = 0, 0
        try:
            for pts in self._raw_chunks():
                finite = np.isfinite(pts).all(axis=1)
                if not finite.all():
                    if not self.drop_nonfinite:
                        total = "the file's" + (f" {self.stored_points:,}" if self.stored_points is not None else "")
                        raise nonfinite_error(row + np.flatnonzero(~finite), total)
                    dropped += int(pts.shape[0] - finite.sum())
                    pts = pts[finite]
                row += pts.shape[0]
                yield pts
        except (InvalidInputError, MissingDependencyError):
            raise
        except Exception as exc:  # noqa: BLE001 - third-party readers raise anything on bad files
            raise InvalidInputError(f"{self.path}: cannot read as {self.format}: {exc}") from None
        self.dropped = dropped

    def _raw_chunks(self) -> Iterator[np.ndarray]:
        n = self.chunk_points
        if self.format in ("las", "laz"):
            import laspy

            wanted = None if self.classes is None else np.asarray(list(self.classes))
            with laspy.open(self.path) as fh:
                for part in fh.chunk_iterator(n):
                    pts = np.column_stack([np.asarray(part.x, dtype=np.float64), np.asarray(part.y, dtype=np.float64),
                                           np.asarray(part.z, dtype=np.float64)])
                    yield pts if wanted is None else pts[np.isin(np.asarray(part.classification), wanted)]
        elif self.format == "rosbag":
            yield from rosbag.bag_chunks(self.path, self.topic, n)
        else:
            xyz, _ = _mapped_xyz(self.path, self.format)
            for start in range(0, self.stored_points, n):
                yield np.column_stack([np.asarray(c[start:start + n], dtype=np.float64) for c in xyz])


def _mapped_xyz(path: Path, fmt: str) -> tuple[list[np.ndarray], dict[str, Any]]:
    """x, y and z of a PLY or NPY file as arrays mapped from disk (read as sliced), and its CRS."""
    if fmt == "npy":
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
        if arr.dtype.names:
            return [arr[c] for c in "xyz"], {}
        if arr.ndim != 2 or arr.shape[1] < 3:
            raise InvalidInputError(f"{path}: expected an (N, 3) array, got shape {arr.shape}")
        return [arr[:, k] for k in range(3)], {}
    from plyfile import PlyData

    ply = PlyData.read(str(path), mmap=True)  # binary vertex data stays on disk
    if "vertex" not in ply:
        raise InvalidInputError(f"{path}: PLY file has no vertex element")
    data = ply["vertex"].data
    if not {"x", "y", "z"} <= set(data.dtype.names or ()):
        raise InvalidInputError(f"{path}: PLY vertices lack x, y or z")
    return [data[c] for c in "xyz"], _ply_crs(ply.comments)


def open_chunked(path: str | os.PathLike[str], *, format: str | None = None,  # noqa: A002
                 classes: Sequence[int] | None = None, drop_nonfinite: bool = False,
                 chunk_points: int = DEFAULT_CHUNK_POINTS, topic: str | None = None) -> ChunkedCloud:
    """Open a point cloud to read it chunk by chunk (:data:`CHUNKED_FORMATS`).

    Reads the header (and CRS) only. Parameters as :func:`read`, plus
    ``chunk_points``, the points per chunk.

    Raises
    ------
    InvalidInputError
        Missing or unreadable file, a format that cannot be read in chunks,
        a bad ``chunk_points``.
    """
    path = Path(path)
    fmt = check_chunkable(path, format)
    _check_source(path, fmt, classes, topic)
    if not (isinstance(chunk_points, int) and chunk_points > 0):
        raise InvalidInputError(f"chunk_points must be a positive integer, got {chunk_points!r}")
    try:
        if fmt in ("las", "laz"):
            import laspy

            with laspy.open(path) as fh:
                header = fh.header
                records = list(header.vlrs) + list(getattr(header, "evlrs", None) or [])
                stored, crs = int(header.point_count), _las_crs(records)
        elif fmt == "rosbag":
            stored, crs = None, {}
        else:
            xyz, crs = _mapped_xyz(path, fmt)
            stored = len(xyz[0])
    except InvalidInputError:
        raise
    except Exception as exc:  # noqa: BLE001 - third-party readers raise anything on bad files
        raise InvalidInputError(f"{path}: cannot read as {fmt}: {exc}") from None
    return ChunkedCloud(path, fmt, crs, stored, classes, topic, drop_nonfinite, chunk_points)


def check_chunkable(path: str | os.PathLike[str], format: str | None = None) -> str:  # noqa: A002
    """The format of ``path``, or a clear error if :func:`open_chunked` cannot read it."""
    fmt = format_of(path, format)
    if fmt not in CHUNKED_FORMATS:
        raise InvalidInputError(f"{path}: {fmt} files cannot be read in chunks; chunked reading supports "
                                f"{', '.join(f.upper() for f in CHUNKED_FORMATS)}")
    return fmt


def stored_point_count(path: str | os.PathLike[str], format: str | None = None) -> int | None:  # noqa: A002
    """Points a file holds, for the formats read in chunks; else None.

    From the header for LAS, LAZ, PLY and NPY. A ROS bag has no such count:
    its size over 12 bytes (one float32 x, y, z, the smallest point a
    PointCloud2 holds) bounds it from above.
    """
    try:
        if format_of(path, format) == "rosbag":
            return rosbag.size_bound(path) // 12
        return open_chunked(path, format=format).stored_points
    except (InvalidInputError, OSError):
        return None


def read_raster_dem(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, Any, dict[str, Any]]:
    """A GeoTIFF DEM as (heights, valid mask, affine transform, crs dict).

    Heights are float64, rows as stored (north-up files have row 0 at the top).
    """
    import rasterio

    try:
        with rasterio.open(path) as src:
            band = src.read(1, masked=True)
            crs = {"wkt": src.crs.to_wkt()} if src.crs else {}
            transform = src.transform
    except Exception as exc:  # noqa: BLE001 - GDAL raises its own errors on bad files
        raise InvalidInputError(f"{path}: cannot read as a GeoTIFF DEM: {exc}") from None
    # Integer DEMs (int16 SRTM, MOLA) cannot hold NaN: convert before filling nodata.
    heights = np.asarray(band.astype(np.float64).filled(np.nan), dtype=np.float64)
    valid = ~np.ma.getmaskarray(band) & np.isfinite(heights)
    return heights, valid, transform, crs


def _read_tif(path: Path) -> PointCloud:
    heights, valid, transform, crs = read_raster_dem(path)
    rows, cols = np.nonzero(valid)
    a, b, c, d, e, f = transform.a, transform.b, transform.c, transform.d, transform.e, transform.f
    x = c + a * (cols + 0.5) + b * (rows + 0.5)
    y = f + d * (cols + 0.5) + e * (rows + 0.5)
    return PointCloud(np.column_stack([x, y, heights[rows, cols]]), crs)


def write(path: str | os.PathLike[str], points: np.ndarray, *, crs: dict[str, Any] | None = None,
          format: str | None = None) -> None:  # noqa: A002
    """Write points to ``path`` in the format of its extension (or ``format``).

    The file appears complete or not at all (temporary file, then rename).
    For a DEM as GeoTIFF use :func:`write_geotiff`.

    Raises
    ------
    InvalidInputError
        The writer cannot represent the points or the CRS (e.g. a LAS
        record over 64 KiB, a WKT a PLY comment cannot hold).
    OSError
        The file system refused (permissions, disk full).
    """
    fmt = format_of(path, format)
    if fmt == "tif":
        raise UnsupportedFormatError("a GeoTIFF holds a DEM, not points: use write_geotiff")
    if fmt == "rosbag":
        raise UnsupportedFormatError("ROS bags are read, not written: write .ply, .pcd, .las or .npy")
    points = np.asarray(points, dtype=np.float64)
    writer = {"las": _write_las, "laz": _write_las, "ply": _write_ply, "pcd": _write_pcd,
              "xyz": _write_text, "csv": _write_text, "npy": _write_npy}[fmt]
    with _writer_errors(path, fmt):
        atomic_write(path, lambda tmp: writer(tmp, points, crs or {}, fmt))


@contextmanager
def _writer_errors(path: str | os.PathLike[str], fmt: str) -> Iterator[None]:
    """Third-party writers raise anything on what they cannot represent: one clear error instead."""
    try:
        yield
    except (InvalidInputError, OSError):
        raise
    except Exception as exc:  # noqa: BLE001 - laspy, plyfile, pypcd4, rasterio have no common error
        raise InvalidInputError(f"{path}: cannot write as {fmt}: {exc}") from None


#: LAS output stores coordinates as integers of this many metres.
LAS_SCALE = 0.001


def _write_las(tmp: Path, points: np.ndarray, crs: dict[str, Any], fmt: str) -> None:
    import laspy
    from laspy.vlrs.vlr import VLR

    vlrs = [VLR(user_id=_LAS_CRS_USER, record_id=v["record_id"], description=v.get("description", ""),
                record_data=base64.b64decode(v["data"])) for v in crs.get("las_vlrs", [])]
    has_wkt = any(v.record_id == _WKT_RECORD for v in vlrs)
    if not vlrs and crs.get("wkt"):
        vlrs = [VLR(user_id=_LAS_CRS_USER, record_id=_WKT_RECORD, description="OGC WKT",
                    record_data=crs["wkt"].encode() + b"\0")]
        has_wkt = True
    # LAS 1.4 point format 6 requires WKT; GeoTIFF keys go in a 1.2 file.
    header = laspy.LasHeader(point_format=6 if has_wkt or not vlrs else 0,
                             version="1.4" if has_wkt or not vlrs else "1.2")
    if has_wkt:
        header.global_encoding.wkt = True
    header.vlrs.extend(vlrs)
    header.scales = np.array([LAS_SCALE] * 3)
    header.offsets = np.floor(points.min(axis=0)) if points.size else np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    las.classification = np.full(points.shape[0], 2, dtype=np.uint8)  # a terrain model: ground
    with open(tmp, "wb") as fh:
        las.write(fh, do_compress=(fmt == "laz"))


def _write_ply(tmp: Path, points: np.ndarray, crs: dict[str, Any], fmt: str) -> None:
    from plyfile import PlyData, PlyElement

    vertex = np.empty(points.shape[0], dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
    vertex["x"], vertex["y"], vertex["z"] = points[:, 0], points[:, 1], points[:, 2]
    comments = ["made by dftpcc"] + ([f"crs {crs['wkt']}"] if crs.get("wkt") else [])
    PlyData([PlyElement.describe(vertex, "vertex")], text=False, comments=comments).write(str(tmp))


def _write_pcd(tmp: Path, points: np.ndarray, crs: dict[str, Any], fmt: str) -> None:
    from pypcd4 import PointCloud as PCD

    PCD.from_points(points, ("x", "y", "z"), (np.float64, np.float64, np.float64)).save(tmp)


def _write_text(tmp: Path, points: np.ndarray, crs: dict[str, Any], fmt: str) -> None:
    np.savetxt(tmp, points, fmt="%.6f", delimiter="," if fmt == "csv" else " ",
               header="x,y,z" if fmt == "csv" else "", comments="")


def _write_npy(tmp: Path, points: np.ndarray, crs: dict[str, Any], fmt: str) -> None:
    with open(tmp, "wb") as fh:
        np.save(fh, points)


def write_geotiff(path: str | os.PathLike[str], dem: DEM, *, crs: dict[str, Any] | None = None) -> None:
    """Write a DEM as a float32 GeoTIFF (north-up), empty cells as nodata (NaN)."""
    import rasterio
    from rasterio.transform import Affine

    grid: Grid = dem.grid
    heights = np.where(dem.mask, dem.heights + grid.z0, np.nan).astype(np.float32)[::-1]
    import math

    c, s = math.cos(grid.angle), math.sin(grid.angle)
    r, dy = grid.resolution, grid.dy
    # Row 0 of the file is the last grid row (largest v): flip v.
    top_x = grid.x0 - s * grid.rows * dy
    top_y = grid.y0 + c * grid.rows * dy
    transform = Affine(c * r, s * dy, top_x, s * r, -c * dy, top_y)
    wkt = (crs or {}).get("wkt")

    def _write(tmp: Path) -> None:
        with rasterio.open(tmp, "w", driver="GTiff", height=grid.rows, width=grid.cols, count=1,
                           dtype="float32", nodata=float("nan"), transform=transform,
                           crs=wkt or None) as dst:
            dst.write(heights, 1)

    with _writer_errors(path, "tif"):
        atomic_write(path, _write)
