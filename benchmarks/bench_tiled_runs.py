"""Issue 43: what each run of a tiled target costs and whether it wins.

A tiled map with a target is coded up to three times (``encoder._Tiles.runs``): the first run
(base layer of one cycle per tile), the map with the covering base layer and the tiles' own
coefficients, and that base layer alone; the encoder keeps the smallest file. For every map of the
data folder larger than one tile and each target level of bench_ratecontrol (RMSE 0.75 and 2
units, a maximum error of 4), this prints each run's bytes and CPU seconds (one core: run under
``taskset``) and which was smallest; then, over all cases, the share of the time each run takes and
the worst size lost if the encoder kept only some of the runs (issue 43's 2 % rule).

    taskset -c 1 .venv/bin/python -m benchmarks.bench_tiled_runs [--files NAME ...] [--tile 256]
"""

from __future__ import annotations

import argparse
import itertools
import math
import time
from pathlib import Path

from dftpcc.encoder import _TILES, no_stage
from dftpcc.params import Params

from benchmarks.bench_ratecontrol import TILE, _tilings
from benchmarks.bench_tiles import all_maps, with_auto
from benchmarks.common import DEFAULT_DATA, library_label, load_average, markdown_table, pick_cases

#: The runs, in the order the encoder makes them.
RUNS = ("first", "covering", "base alone")
#: Issue 43's size rule: a faster path's file within this fraction of today's.
SIZE_RULE = 0.02


def timed_runs(dem, params: Params, point_count: int) -> dict[str, tuple[int, float]]:
    """Each run's file size (bytes) and CPU seconds, by name."""
    out = {}
    runs = _TILES.runs(dem, params, point_count, None, no_stage, None)
    while True:
        t0 = time.process_time()
        run = next(runs, None)
        if run is None:
            return out
        out[run[0]] = (len(run[1]), time.process_time() - t0)


def kept_loss(runs: dict[str, tuple[int, float]], keep: tuple[str, ...]) -> float:
    """How much larger the file is when only the runs ``keep`` are made (0: the same; inf: none made)."""
    kept = [runs[name][0] for name in keep if name in runs]
    return min(kept) / min(size for size, _ in runs.values()) - 1.0 if kept else float("inf")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--files", nargs="+", help="only these maps (file names or stems)")
    ap.add_argument("--tile", type=int, default=TILE, help="tile side (cells)")
    args = ap.parse_args(argv)
    print(f"Measuring dftpcc {library_label()}; {load_average()}.")
    rows, cases = [], []
    for case in pick_cases([with_auto(c, args.data) for c in all_maps(args.data)], args.files):
        loading: list[str] = []
        for dem, n, unit, tile in _tilings(case, args.data, (args.tile,), loading):
            for name, multiple in (("target_rmse", 0.75), ("target_rmse", 2.0), ("target_max_error", 4.0)):
                params = Params().replace(resolution=dem.grid.resolution, tile_size=tile, **{name: multiple * unit})
                runs = timed_runs(dem, params, n)
                won = min(runs, key=lambda name: runs[name][0])
                label = f"{'RMSE' if name == 'target_rmse' else 'max'} {multiple:g}u"
                rows.append([case.stem, label] + [f"{runs[r][0]:,} / {runs[r][1]:.2f} s" if r in runs else "—"
                                                  for r in RUNS] + [won])
                cases.append(runs)
                print(" | ".join(rows[-1]), flush=True)
    print("\n" + markdown_table(["map", "target"] + [f"{r} (bytes / CPU s)" for r in RUNS] + ["smallest"], rows))
    total = sum(sec for runs in cases for _, sec in runs.values())
    for name in RUNS:
        share = sum(runs[name][1] for runs in cases if name in runs) / total if total else 0.0
        wins = sum(1 for runs in cases if min(runs, key=lambda r: runs[r][0]) == name)
        print(f"{name}: {share:.0%} of the time, smallest in {wins} of {len(cases)} cases")
    for keep in itertools.chain.from_iterable(itertools.combinations(RUNS, r) for r in (1, 2)):
        losses = [kept_loss(runs, keep) for runs in cases]
        made = [x for x in losses if math.isfinite(x)]
        over = sum(1 for x in losses if x > SIZE_RULE)
        print(f"keeping only {' + '.join(keep)}: worst {max(made, default=0.0):.1%} larger where "
              f"made ({len(losses) - len(made)} cases without such a run), {over} of {len(cases)} cases over "
              f"{SIZE_RULE:.0%} or without")
    print(f"\nEnd: {load_average()}.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
