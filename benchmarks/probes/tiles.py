"""Issue 3 probe: would coding the DEM in tiles beat one global transform?

Cuts the gridded DEM into square tiles; each tile gets its own plane, fill,
DCT, dead-zone quantizer (one step for all tiles: with an orthonormal
transform a common step is what minimises the total squared error) and ANS
coefficient stream, like a whole map does. For each tile size the step is
searched so that the rebuilt DEM meets the same RMSE (occupied cells), and the
coefficient bytes (plus 24 B of plane per tile, no mask) are compared with
one tile covering the map.

    .venv/bin/python -m benchmarks.probes.tiles [--file field_gentle_ign.laz --resolution 0.5 --classes 2]
        [--multiple 1.25] [--tiles 256 128 64]
    .venv/bin/python -m benchmarks.probes.tiles --file mars_gale_1m.tif --relief 0.001

For a point cloud the target is the DEM error that makes the points' vertical
RMSE ``multiple`` times the gridding floor; a GeoTIFF DEM (from dems/) is coded
on its own pixel grid to an RMSE of ``relief`` times the standard deviation of
its heights, as in bench_anchors.py. Prints a table; nothing here fails.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

import dftpcc
from dftpcc import coding, quantizer, spectrum
from dftpcc.fill import fill_empty
from dftpcc.grid import fit_grid, rasterize
from dftpcc.io import read_raster_dem

from benchmarks.common import DEFAULT_DATA, warnings_as_notes

PLANE_BYTES = 24


def code_tile(h: np.ndarray, m: np.ndarray, step: float) -> tuple[int, np.ndarray]:
    """Coefficient bytes of one tile and its rebuilt heights."""
    if not m.any():
        return 0, np.zeros_like(h)
    rows, cols = h.shape
    r, c = np.nonzero(m)
    plane, *_ = np.linalg.lstsq(np.c_[np.ones(r.size), c, r], h[m], rcond=None)
    rr, cc = np.mgrid[0:rows, 0:cols]
    trend = plane[0] + plane[1] * cc + plane[2] * rr
    lay = spectrum.layout("dct", "quantized", (rows, cols))
    order, radii, angles = spectrum.kept_order(lay, 0.0)
    q = quantizer.quantize(spectrum.forward(fill_empty(h - trend, m, method="smooth"), lay).ravel()[order], step, 0.1)
    size = len(coding.encode_coefficients(q, radius=radii, angle=angles)) + PLANE_BYTES
    coefs = np.zeros(lay.coef_shape)
    coefs.ravel()[order] = quantizer.dequantize(q, step)
    return size, spectrum.inverse(coefs, lay) + trend


def code_tiled(heights: np.ndarray, mask: np.ndarray, tile: int, step: float) -> tuple[int, float]:
    total, rebuilt = 0, np.zeros_like(heights)
    for i in range(0, heights.shape[0], tile):
        for j in range(0, heights.shape[1], tile):
            size, rebuilt[i:i + tile, j:j + tile] = code_tile(heights[i:i + tile, j:j + tile],
                                                              mask[i:i + tile, j:j + tile], step)
            total += size
    err = (rebuilt - heights)[mask]
    return total, math.sqrt(float(np.mean(err * err)))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--file", default="field_gentle_ign.laz")
    ap.add_argument("--resolution", type=float, default=0.5)
    ap.add_argument("--classes", type=int, nargs="*", default=[2])
    ap.add_argument("--multiple", type=float, default=1.25)
    ap.add_argument("--relief", type=float, default=0.001, help="DEM target as a fraction of the relief")
    ap.add_argument("--tiles", type=int, nargs="+", default=[256, 128, 64])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    args = ap.parse_args()
    if args.file.lower().endswith((".tif", ".tiff")):
        heights, mask, *_ = read_raster_dem(args.data / "dems" / args.file)
        target = args.relief * float(np.std(heights[mask]))
        print(f"{args.file}, grid {heights.shape[0]} x {heights.shape[1]}; target DEM RMSE {1e3 * target:.2f} mm "
              f"({args.relief:g} of the relief)\n")
    else:
        with warnings_as_notes([]):
            points = dftpcc.read(args.data / "pointclouds" / args.file, classes=args.classes or None).points
            dem = rasterize(points, fit_grid(points, args.resolution))
        heights, mask = dem.heights, dem.mask
        target = dem.gridding_rmse * math.sqrt(args.multiple ** 2 - 1)
        print(f"{args.file}, grid {dem.grid.rows} x {dem.grid.cols}; target DEM RMSE {1e3 * target:.2f} mm "
              f"({args.multiple}x the {1e3 * dem.gridding_rmse:.1f} mm floor on the points)\n")
    print("| tile | step mm | DEM RMSE mm | coefficient + plane bytes | vs one tile |")
    print("|---|---|---|---|---|")
    base = None
    whole = max(heights.shape)
    for tile in [whole] + args.tiles:
        lo, hi = target * 1e-2, target * 1e2
        while hi / lo > 1.01:
            mid = math.sqrt(lo * hi)
            lo, hi = (mid, hi) if code_tiled(heights, mask, tile, mid)[1] <= target else (lo, mid)
        size, err = code_tiled(heights, mask, tile, lo)
        base = base or size
        label = f"{tile} (whole map)" if tile == whole else str(tile)
        print(f"| {label} | {1e3 * lo:.1f} | {1e3 * err:.2f} | {size:,} | {size / base:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
