"""File-level helpers: read a cloud, compress it, write the ``.dftpc``; and back."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .dem import DEM, Grid
from .encoder import Stage, compress, encode_dem, no_stage, params_of
from .errors import InvalidInputError
from .grid import CloudSummary, check_chunked_aggregate, rasterize_chunks
from .io import (CHUNKED_FORMATS, DEFAULT_CHUNK_POINTS, atomic_write, check_chunkable, format_of, open_chunked, read,
                 read_raster_dem, stored_point_count, write, write_geotiff)
from .limits import holds_in_memory
from .mapfile import CompressedMap
from .mapfile import open as open_map
from .rebuild import dem_to_points
from .params import Params

__all__ = ["compress_file", "decompress_file", "dem_from_geotiff", "reads_in_chunks"]

#: Pixels whose sides differ by less than this fraction count as square.
SQUARE_TOLERANCE = 1e-9


def reads_in_chunks(src: str | os.PathLike[str], format: str | None = None,  # noqa: A002
                    chunk_points: int | None = None) -> bool:
    """Whether :func:`compress_file` reads ``src`` in chunks.

    Always when ``chunk_points`` is given (the format must allow it);
    otherwise when the file holds more points (:func:`~dftpcc.io.stored_point_count`)
    than the available memory can compress in one piece (:func:`~dftpcc.limits.holds_in_memory`).
    """
    fmt = format_of(src, format)
    if chunk_points is not None:
        check_chunkable(src, format)
        return True
    if fmt not in CHUNKED_FORMATS:
        return False
    stored = stored_point_count(src, fmt)
    return bool(stored) and not holds_in_memory(stored)


def compress_file(src: str | os.PathLike[str], dst: str | os.PathLike[str], params: Params | None = None, *,
                  format: str | None = None, classes: Sequence[int] | None = None,  # noqa: A002
                  drop_nonfinite: bool = False, chunk_points: int | None = None, topic: str | None = None,
                  on_stage: Stage = no_stage, **shortcuts: Any) -> CompressedMap:
    """Compress the point cloud in ``src`` into the ``.dftpc`` file ``dst``.

    Parameters are those of :func:`dftpcc.compress` and :func:`dftpcc.read`
    (``topic``: the PointCloud2 topic of a ROS bag).
    A GeoTIFF source with ``resolution='auto'`` is coded on its own pixel grid.
    A cloud too large to hold in memory (LAS, LAZ, PLY, NPY) is read in
    chunks of ``chunk_points`` (default :data:`~dftpcc.io.DEFAULT_CHUNK_POINTS`),
    three or four passes over the file, so memory holds the grid and one chunk
    (:func:`reads_in_chunks`); giving ``chunk_points`` forces it. The file is
    the same up to float round-off. ``aggregate='median'`` cannot be chunked.

    Returns
    -------
    CompressedMap
        The written map, opened (header parsed).
    """
    # Parameters checked before the first pass over a file that may take minutes to read.
    params = params_of(params, shortcuts)
    on_stage("read")
    if format_of(src, format) == "tif" and params.resolution == "auto":
        dem, crs = dem_from_geotiff(src)
        data = encode_dem(dem, params, crs=crs, on_stage=on_stage)
    elif reads_in_chunks(src, format, chunk_points):
        data = _compress_chunked(src, params, format=format, classes=classes, drop_nonfinite=drop_nonfinite,
                                 topic=topic, chunk_points=chunk_points or DEFAULT_CHUNK_POINTS, on_stage=on_stage)
    else:
        cloud = read(src, format=format, classes=classes, drop_nonfinite=drop_nonfinite, topic=topic)
        data = compress(cloud.points, params, crs=cloud.crs, on_stage=on_stage)
    on_stage("write")
    atomic_write(dst, lambda tmp: Path(tmp).write_bytes(data))
    return open_map(data)


def _compress_chunked(src: str | os.PathLike[str], params: Params, *, format: str | None,  # noqa: A002
                      classes: Sequence[int] | None, drop_nonfinite: bool, topic: str | None, chunk_points: int,
                      on_stage: Stage) -> bytes:
    """:func:`dftpcc.compress` of a cloud read in chunks: summary, [auto resolution], heights, spread."""
    check_chunked_aggregate(params.aggregate)
    cloud = open_chunked(src, format=format, classes=classes, drop_nonfinite=drop_nonfinite,
                         chunk_points=chunk_points, topic=topic)
    summary = CloudSummary(hull=params.frame == "oriented")
    for points in cloud.chunks():
        summary.add(points)
    if not summary.count:
        if cloud.dropped:
            raise InvalidInputError(f"{src}: all {cloud.dropped:,} points have NaN or infinite coordinates")
        raise InvalidInputError(f"{src}: no points" + (" of the selected classes" if classes else ""))
    resolution = summary.auto_resolution(cloud.chunks) if params.resolution == "auto" else params.resolution
    on_stage("grid")
    grid = summary.fit_grid(resolution, frame=params.frame)
    dem = rasterize_chunks(cloud.chunks, grid, aggregate=params.aggregate)
    return encode_dem(dem, params, point_count=summary.count, crs=cloud.crs, on_stage=on_stage)


def decompress_file(src: str | os.PathLike[str], dst: str | os.PathLike[str], *,
                    format: str | None = None, max_bytes: int | None = None,  # noqa: A002
                    cutoff: float | None = None, max_cells: int | None = None) -> np.ndarray:
    """Decode the ``.dftpc`` file ``src`` and write the rebuilt map to ``dst``.

    The output format comes from ``dst``'s extension; ``.tif`` writes the
    rebuilt DEM as a GeoTIFF, any other the point cloud. The CRS read from
    the original file is written back where the format has room for it.

    Returns
    -------
    ndarray, shape (cells, 3)
        The rebuilt points.
    """
    fmt = format_of(dst, format)
    with open_map(src, max_bytes=max_bytes, max_cells=max_cells) as cmap:
        dem = cmap.read_dem(cutoff=cutoff)
        crs = cmap.crs
    points = dem_to_points(dem)
    if fmt == "tif":
        write_geotiff(dst, dem, crs=crs)
    else:
        write(dst, points, crs=crs, format=fmt)
    return points


def dem_from_geotiff(path: str | os.PathLike[str]) -> tuple[DEM, dict[str, Any]]:
    """A north-up GeoTIFF DEM as a :class:`DEM` on its own pixel grid.

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
