"""A large float32 GeoTIFF for hand measurements: Moon Kepler mirrored N x N with 10 m height offsets.

    .venv/bin/python -m benchmarks.mosaic_kepler OUT.tif --copies 25   # 20,100 x 20,100 cells, ~280 MB

Written one copy at a time through rasterio windows (tiled 256, deflate, predictor 3, BigTIFF), so
building it needs one copy in memory. docs/benchmarks.md quotes runs on N = 10 and 25.
"""

from __future__ import annotations

import argparse

import numpy as np
import rasterio
from rasterio.windows import Window

from benchmarks.common import DEFAULT_DATA

#: Height offset between neighbouring copies, metres.
OFFSET_M = 10.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out")
    parser.add_argument("--copies", type=int, default=25, help="copies a side (default 25)")
    args = parser.parse_args()
    with rasterio.open(DEFAULT_DATA / "dems" / "moon_kepler_lola_48m.tif") as ds:
        tile, profile = ds.read(1).astype(np.float32), ds.profile
    h, w = tile.shape
    n = args.copies
    profile.update(height=h * n, width=w * n, dtype="float32", nodata=float("nan"), tiled=True, blockxsize=256,
                   blockysize=256, compress="deflate", predictor=3, BIGTIFF="YES")
    with rasterio.open(args.out, "w", **profile) as out:
        for i in range(n):
            for j in range(n):
                copy = tile[::(-1 if i % 2 else 1), ::(-1 if j % 2 else 1)] + OFFSET_M * (i + j)
                out.write(copy, 1, window=Window(j * w, i * h, w, h))
    print(f"{args.out}: {h * n} x {w * n} cells")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
