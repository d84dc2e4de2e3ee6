"""The DEM the raster anchors code: dftpcc's grid of a cloud, its empty cells filled, its mask packed.

Shared by the equal-RMSE sweep (bench_anchors) and the equal-maximum-error
table (max_error), so both hand every raster codec the same heights and
charge it the same side information.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import zstandard
from scipy import ndimage

from dftpcc.dem import Grid
from dftpcc.grid import fit_grid, rasterize

__all__ = ["MASK_ZSTD_LEVEL", "RASTER_HEADER_BYTES", "U16_MAX", "ONE_THREAD", "JPEGXL_EFFORT", "Raster",
           "make_raster", "unpack_mask", "raster_points", "unit_range", "to_u16"]

#: zstd level for the occupancy bitmap of the raster anchors (as ANCHORS.md).
MASK_ZSTD_LEVEL = 19
#: Side information a raster anchor needs to put its DEM back in place: grid
#: origin, cell size, rows, cols, height offset and range, as eight 8-byte
#: numbers. With it the JPEG2000 figures of ANCHORS.md are reproduced.
RASTER_HEADER_BYTES = 8 * 8
U16_MAX = 65535
#: Codecs with a thread option run on one, as ANCHORS.md's speeds are per core.
ONE_THREAD = 1
#: libjxl's encoder effort (1-9; 7 is its default). Lossless on our quantized
#: DEMs, 9 saved 0-2.6 % for 3-4x the time.
JPEGXL_EFFORT = 7


@dataclass
class Raster:
    """Mean-height DEM of a cloud on dftpcc's axis-aligned grid, ready for raster codecs.

    Attributes
    ----------
    grid : Grid
    heights : ndarray (rows, cols), float64
        Mean height per cell relative to ``grid.z0`` (metres); 0 where empty.
    filled : ndarray (rows, cols), float64
        ``heights`` with every empty cell given its nearest occupied cell's value.
    mask : ndarray (rows, cols), bool
    mask_blob : bytes
        Occupancy bit-packed and zstd-compressed.
    """

    grid: Grid
    heights: np.ndarray
    filled: np.ndarray
    mask: np.ndarray
    mask_blob: bytes


def make_raster(points: np.ndarray, resolution: float) -> Raster:
    """The raster of ``points`` (N, 3 metres) on the grid dftpcc fits at ``resolution`` metres."""
    grid = fit_grid(points, resolution)
    dem = rasterize(points, grid)
    mask = dem.mask
    if mask.all():
        filled = dem.heights
    else:
        nearest = ndimage.distance_transform_edt(~mask, return_distances=False, return_indices=True)
        filled = dem.heights[tuple(nearest)]
    blob = zstandard.ZstdCompressor(level=MASK_ZSTD_LEVEL).compress(np.packbits(mask.ravel()).tobytes())
    return Raster(grid, dem.heights, filled, mask, blob)


def unpack_mask(grid: Grid, mask_blob: bytes) -> np.ndarray:
    """The occupancy of a raster anchor from its zstd-compressed bitmap."""
    raw = zstandard.ZstdDecompressor().decompress(mask_blob)
    return np.unpackbits(np.frombuffer(raw, np.uint8), count=grid.size).astype(bool).reshape(grid.shape)


def raster_points(grid: Grid, mask: np.ndarray, heights: np.ndarray) -> np.ndarray:
    """Decoded cloud of a raster anchor: one point per occupied cell, at its centre (as dftpcc)."""
    rows, cols = np.nonzero(mask)
    x, y = grid.centres(rows, cols)
    return np.column_stack([x, y, heights[rows, cols] + grid.z0])


def unit_range(raster: Raster) -> tuple[np.ndarray, float, float]:
    """The filled DEM scaled to [0, 1] over its range, with the offset and span (metres) that undo it."""
    lo, hi = float(raster.filled.min()), float(raster.filled.max())
    span = hi - lo if hi > lo else 1.0
    return (raster.filled - lo) / span, lo, span


def to_u16(raster: Raster) -> tuple[np.ndarray, float, float]:
    """The filled DEM scaled to 16 bits over its range (as ANCHORS.md's JPEG2000), offset and span in metres."""
    unit, lo, span = unit_range(raster)
    return np.round(unit * U16_MAX).astype(np.uint16), lo, span
