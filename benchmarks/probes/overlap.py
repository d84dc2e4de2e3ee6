"""Issue 12 probe: the tile overlap against the seams, on the worst cases of bench_tiles.

Each case (a map, a tile side, one of bench_tiles' rate-control targets) is coded twice with
bench_tiles' own ``prepare`` and ``code``: once with every tile's window 8 cells wider than the
tile (``dftpcc.tiles.tile_overlap`` replaced by a constant, the writer before the overlap followed
the cutoff) and once as the writer does now. Prints the seam ratio (RMSE of the cells within two
cells of an internal tile edge over the RMSE elsewhere), the bytes and the cutoff rate control chose.
With ``--fixed``, three DEMs are coded instead at T = 128, fixed cutoffs of 0.9, 0.95 and 0.97
and a fine step (1 mm), so that only the low-pass rings, with the constant overlap and with windows
of 1/(1 - f_c) cells rounded up to a multiple of 8 (what a ringing reach that grows with the cutoff
would ask). Nothing here fails; see docs/benchmarks.md, *The overlap follows the cutoff*.

    .venv/bin/python -m benchmarks.probes.overlap [--overlap 8] [--fixed] [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import math
import warnings
from pathlib import Path

import numpy as np

import dftpcc
from dftpcc import encoder, tiles
from dftpcc.files import read_dem
from dftpcc.params import make_params

from benchmarks import bench_tiles
from benchmarks.common import DEFAULT_DATA, load_average, markdown_table, rmse

#: --fixed: DEMs, tile side, cutoffs and step.
FIXED_DEMS = ("moon_kepler_lola_48m.tif", "mars_gale_1m.tif", "earth_heidelberg_25m.tif")
FIXED_TILE = 128
FIXED_CUTOFFS = (0.9, 0.95, 0.97)
FIXED_STEP_M = 0.001

#: (map file, tile side, target): a target is "max error" or the index of bench_anchors' RMSE levels.
CASES = (
    ("moon_kepler_lola_48m.tif", 512, 0),
    ("moon_kepler_lola_48m.tif", 512, "max error"),
    ("moon_kepler_lola_48m.tif", 512, 2),
    ("field_gentle_ign.laz", 512, 2),
    ("mountain_arid_alirt.las", 128, "max error"),
    ("mountain_arid_alirt.las", 128, 1),
    ("rural_valley_ign.laz", 256, 1),
)


#: The writer's own choice, kept before any swap.
_WRITER = tiles.tile_overlap


def _use(overlap) -> None:
    # The encoder imported the function by name: both references are the writer's.
    tiles.tile_overlap = encoder.tile_overlap = overlap


def _reach(cutoff: float, size: int) -> int:
    """1 / (1 - cutoff) cells rounded up to a multiple of 8, within half a tile."""
    return min(tiles.TILE_OVERLAP * math.ceil(1.0 / (1.0 - cutoff) / tiles.TILE_OVERLAP - 1e-9), size // 2)


def fixed(data: Path, constant: int) -> None:
    rows = []
    for name in FIXED_DEMS:
        dem, n, crs = read_dem(data / "dems" / name, make_params())
        for cutoff in FIXED_CUTOFFS:
            cells = []
            for overlap in (lambda c, size: min(constant, size // 2), _reach):
                _use(overlap)
                blob = encoder.encode_dem(dem, make_params(tile_size=FIXED_TILE, cutoff=cutoff, step=FIXED_STEP_M),
                                          point_count=n, crs=crs)
                with dftpcc.open(blob) as cmap:
                    err = cmap.read_dem().heights - dem.heights
                cells.append(f"{_seam(err, dem.mask, FIXED_TILE):.3f}, {len(blob):,} B")
            rows.append([name, cutoff, *cells])
            print(" | ".join(map(str, rows[-1])), flush=True)
    _use(_WRITER)
    print()
    print(markdown_table(["DEM", "f_c", f"overlap {constant}: seam ratio, bytes", "1/(1 - f_c), multiple of 8"],
                         rows))


def _seam(err: np.ndarray, mask: np.ndarray, size: int) -> float:
    """bench_tiles' seam ratio: RMSE near an internal tile edge over the RMSE elsewhere, interior cells."""
    near, interior = bench_tiles.near_edges(err.shape, size), bench_tiles.interior_of(mask)
    return rmse(err[interior & near]) / rmse(err[interior & ~near])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--overlap", type=int, default=tiles.TILE_OVERLAP, help="the constant overlap compared (cells)")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--fixed", action="store_true", help="fixed cutoffs and a fine step on three DEMs instead")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    if args.fixed:
        fixed(args.data, args.overlap)
        print(f"\n{load_average()}.")
        return 0
    writer = _WRITER
    cases = {c.name: c for c in bench_tiles.all_maps(args.data)}
    rows = []
    for name, tile, which in CASES:
        run = bench_tiles.prepare(bench_tiles.with_auto(cases[name], args.data), args.data)
        target = run.bound if which == "max error" else run.levels[which]
        cells = []
        for overlap in (lambda cutoff, size: min(args.overlap, size // 2), writer):
            _use(overlap)
            run.coded.clear()
            coded = bench_tiles.code(run, target, tile)
            cells.append(f"{coded.seam_ratio:.3f}, {coded.bytes:,} B, f_c {coded.cutoff:g}")
        _use(writer)
        rows.append([name, tile, target.label, *cells])
        print(" | ".join(map(str, rows[-1])), flush=True)
    print()
    print(markdown_table(["map", "T", "target", f"overlap {args.overlap}: seam ratio, bytes, cutoff",
                          "tiles.tile_overlap"], rows))
    print(f"\n{load_average()}.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
