"""Issue 3 probe: how much could richer context models save, coefficients and mask?

An upper bound, not a coder: the empirical conditional entropy of the
symbols given a context, with the statistics known in advance (no learning
cost), against the same with the contexts the file format uses now.

- Coefficients: the quantized DCT of the DEM (plane removed, smooth fill) at
  the step that meets the target RMSE as one tile of ``probes/tiles.py``. Now:
  one model per frequency band (8 bands per octave of radius here, finer than
  the format's). Richer: band x the size of the already decoded neighbours
  (u-1, v), (u, v-1), (u-1, v-1), (u-2, v), (u, v-2), in 8 classes.
- Mask: the occupancy bits in raster order. Now: the 8 causal neighbours of
  MASK kind 2. Richer: those x the count in a 7 x 3 causal window x the
  density over the 8 rows above (8 classes each).

    .venv/bin/python -m benchmarks.probes.contexts [--multiple 1.25 3] [--relief 0.001 0.01]

Prints a table; nothing here fails.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

import dftpcc
from dftpcc import coding, occupancy, quantizer, spectrum
from dftpcc.fill import fill_empty
from dftpcc.grid import fit_grid, rasterize
from dftpcc.io import read_raster_dem

from benchmarks.common import DEFAULT_DATA, warnings_as_notes
from benchmarks.probes.tiles import code_tiled

#: (file, resolution, classes) as in bench_anchors.py; a .tif is read from dems/.
FILES = (("field_gentle_ign.laz", 0.5, [2]), ("coastal_plain_ign.laz", 2.0, [2]), ("mars_gale_1m.tif", None, None))


def conditional_bits(symbols: np.ndarray, context: np.ndarray) -> float:
    """Total bits of ``symbols`` coded with one static model per context value."""
    offset = int(symbols.min())
    span = int(symbols.max()) - offset + 1
    joint = np.unique(context.astype(np.int64) * span + (symbols - offset), return_counts=True)[1]
    ctx = np.unique(context, return_counts=True)[1]
    return float(-(joint * np.log2(joint)).sum() + (ctx * np.log2(ctx)).sum())


def coefficient_bits(heights: np.ndarray, mask: np.ndarray, step: float) -> tuple[int, float, float]:
    """Bytes the file format needs now, and the two conditional-entropy bounds in bytes."""
    r, c = np.nonzero(mask)
    plane, *_ = np.linalg.lstsq(np.c_[np.ones(r.size), c, r], heights[mask], rcond=None)
    rr, cc = np.mgrid[0:heights.shape[0], 0:heights.shape[1]]
    detrended = heights - (plane[0] + plane[1] * cc + plane[2] * rr)
    lay = spectrum.layout("dct", "quantized", heights.shape)
    order, radii, angles = spectrum.kept_order(lay, 0.0)
    grid_q = quantizer.quantize(spectrum.forward(fill_empty(detrended, mask, method="smooth"), lay).ravel(),
                             step, 0.1).reshape(lay.coef_shape)
    q = grid_q.ravel()[order]
    actual = len(coding.encode_coefficients(q, radius=radii, angle=angles))
    band = np.floor(8 * np.log2(1 + radii)).astype(np.int64)
    a = np.pad(np.abs(grid_q), ((2, 0), (2, 0))).astype(np.float64)
    near = a[1:-1, 2:] + a[2:, 1:-1] + a[1:-1, 1:-1] + 0.5 * (a[:-2, 2:] + a[2:, :-2])
    size = np.minimum(7, np.floor(np.log2(1 + 2 * near))).astype(np.int64).ravel()[order]
    return actual, conditional_bits(q, band) / 8, conditional_bits(q, band * 8 + size) / 8


def mask_bits(mask: np.ndarray) -> tuple[int, float, float]:
    """Bytes of MASK kind 2 now, and the two conditional-entropy bounds in bytes."""
    m = mask.astype(np.int64)
    rows, cols = m.shape
    pad = np.pad(m, ((8, 0), (3, 3)))

    def at(dr: int, dc: int) -> np.ndarray:  # the cell dr rows up and dc columns right
        return pad[8 - dr:8 - dr + rows, 3 + dc:3 + dc + cols]

    eight = [at(0, -1), at(0, -2), at(1, -1), at(1, 0), at(1, 1), at(1, -2), at(1, 2), at(2, 0)]
    ctx8 = sum(bit << i for i, bit in enumerate(eight))
    window = sum(at(dr, dc) for dr in (1, 2, 3) for dc in range(-3, 4)) + at(0, -1) + at(0, -2) + at(0, -3)
    above = ndimage.uniform_filter(pad[:-8, 3:-3].astype(np.float64), size=(8, 17), origin=(3, 0), mode="constant")
    rich = (ctx8 * 8 + np.minimum(window // 3, 7)) * 8 + np.minimum((above * 8).astype(np.int64), 7)
    flat = m.ravel()
    return (len(occupancy.encode_mask(mask)), conditional_bits(flat, ctx8.ravel()) / 8,
            conditional_bits(flat, rich.ravel()) / 8)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--multiple", type=float, nargs="+", default=[1.25, 3.0])
    ap.add_argument("--relief", type=float, nargs="+", default=[0.001, 0.01])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    args = ap.parse_args()
    print("| map | level | part | format now, B | static, same contexts, B | static, richer contexts, B "
          "| richer / same |")
    print("|---|---|---|---|---|---|---|")
    for name, resolution, classes in FILES:
        if name.endswith(".tif"):
            heights, mask, *_ = read_raster_dem(args.data / "dems" / name)
            relief = float(np.std(heights[mask]))
            levels = [(f"{f:g} relief", f * relief) for f in args.relief]
        else:
            with warnings_as_notes([]):
                points = dftpcc.read(args.data / "pointclouds" / name, classes=classes).points
                dem = rasterize(points, fit_grid(points, resolution))
            heights, mask = dem.heights, dem.mask
            levels = [(f"{k:g}x floor", dem.gridding_rmse * math.sqrt(k * k - 1)) for k in args.multiple]
        if not mask.all():
            now, same, rich = mask_bits(mask)
            print(f"| {name} | all | mask | {now:,} | {same:,.0f} | {rich:,.0f} | {rich / same:.3f} |")
        for label, target in levels:
            lo, hi = target * 1e-2, target * 1e2
            while hi / lo > 1.01:
                mid = math.sqrt(lo * hi)
                lo, hi = (mid, hi) if code_tiled(heights, mask, max(heights.shape), mid)[1] <= target else (lo, mid)
            now, same, rich = coefficient_bits(heights, mask, lo)
            print(f"| {name} | {label} | coefficients | {now:,} | {same:,.0f} | {rich:,.0f} | {rich / same:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
