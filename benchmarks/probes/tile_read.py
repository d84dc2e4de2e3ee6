"""How long one 512-cell tile of bench_tiles' Kepler mosaic takes to decode, alone, quickly.

bench_tiles measures the same read among its other parts (20 minutes of a shared machine); this
probe builds the mosaic, codes it at bench_tiles' fixed parameters and times only the tile, so the
figure can be taken again when the machine is quiet:

    .venv/bin/python -m benchmarks.probes.tile_read [--repeats N]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import dftpcc
from dftpcc import limits
from dftpcc.params import DEFAULT_CUTOFF

from benchmarks.bench_tiles import MOSAIC, RA_TILE, mosaic_tif
from benchmarks.common import DEFAULT_DATA, load_average

#: The tile read: tile row and column of the mosaic's 7 x 7 grid of 512-cell tiles (an inner one).
TILE_AT = 3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="probe_tile_read_") as tmp:
        tif, _ = mosaic_tif(args.data, Path(tmp), MOSAIC)
        out = Path(tmp) / "mosaic.dftpc"
        dftpcc.compress_file(tif, out, tile_size=RA_TILE, cutoff=DEFAULT_CUTOFF, step=1.0, force=True)
        with dftpcc.open(out, max_cells=limits.MAX_CELLS) as cmap:
            g = cmap.header.grid
            r0 = c0 = TILE_AT * RA_TILE
            bbox = (g.x0 + (c0 + 0.5) * g.resolution, g.y0 + (r0 + 0.5) * g.dy,
                    g.x0 + (c0 + RA_TILE - 0.5) * g.resolution, g.y0 + (r0 + RA_TILE - 0.5) * g.dy)
            cmap.read_dem(bbox=bbox)  # the first read builds the caches a reader keeps
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                cmap.read_dem(bbox=bbox)
                times.append(time.perf_counter() - t0)
    print(f"tile ({TILE_AT}, {TILE_AT}) of {RA_TILE} cells, decode alone: median {1e3 * statistics.median(times):.2f} ms "
          f"(range {1e3 * min(times):.2f}-{1e3 * max(times):.2f}) over {args.repeats}; {load_average()}")


if __name__ == "__main__":
    main()
