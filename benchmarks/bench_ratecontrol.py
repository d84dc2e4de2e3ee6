"""Rate control: what each target gets, how long it takes, and what the consistent fill saves.

For each map and target (``--target-rmse``, ``--target-max-error``,
``--target-bpp``), compresses with the compact profile twice, once with the
push-pull fill alone (``fill='smooth'``) and once with the default
``fill='consistent'`` (the chosen cutoff tried again with the empty cells
refilled from the coded map). Reports the cutoff and step chosen, the file
size, the error the file states, whether the promise holds, and the median
wall time; every figure is measured in this run.

    .venv/bin/python -m benchmarks.bench_ratecontrol [--quick] [--files NAME ...] [--docs | --no-docs]

Targets are set from each map's gridding floor (the RMS distance of its
points to their cell's mean): DEM RMSE 0.75x and 2x the floor (points at
1.25x and about 2.2x the floor), a maximum error of 4x the floor, and
a size target between the two RMSE targets' files. A GeoTIFF's pixels have no
floor; there the unit is 0.1 % of the RMS relief.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

import dftpcc

from benchmarks.common import (GROUND, Case, finish_run, load, load_average, library_label,
                               markdown_table, median_time, pick_cases, run_arguments, shared_grid, verdict,
                               warnings_as_notes)

CASES = (
    Case("field_gentle_ign.laz", 0.5, (GROUND,), "gentle"),
    Case("coastal_plain_ign.laz", 2.0, (GROUND,), "gentle"),
    Case("forest_slope_bcts_2.8M.laz", 0.5, None, "rough"),
    Case("mars_gale_1m.tif", None, None, "gentle"),
)
FILLS = ("smooth", "consistent")
REPEATS = 3
QUICK_REPEATS = 1


def unit_of(loaded, dem) -> tuple[float, str]:
    """The error unit targets are multiples of: the gridding floor, or 0.1 % of a DEM's relief."""
    if loaded.case.is_dem:
        relief = float(np.std(loaded.points[:, 2]))
        return 1e-3 * relief, f"0.1 % of the RMS relief ({1e3 * 1e-3 * relief:.1f} mm)"
    return float(dem.gridding_rmse), f"the gridding floor ({1e3 * dem.gridding_rmse:.1f} mm)"


def run_case(case: Case, data: Path, repeats: int) -> str:
    notes: list[str] = []
    with warnings_as_notes(notes):
        loaded = load(case, data)
        points, res = loaded.points, loaded.resolution
        _, dem = shared_grid(points, res)
        unit, unit_text = unit_of(loaded, dem)
        n = points.shape[0]

        def compress(fill: str, **target: float) -> tuple[float, bytes]:
            return median_time(lambda: dftpcc.compress(points, resolution=res, fill=fill, **target), repeats)

        rmse_targets = [0.75 * unit, 2.0 * unit]
        targets = [dict(target_rmse=t) for t in rmse_targets] + [dict(target_max_error=4.0 * unit)]
        rows, sizes = [], {}
        for target in targets:
            for fill in FILLS:
                seconds, blob = compress(fill, **target)
                sizes[(tuple(target.items()), fill)] = len(blob)
                rows.append(row(target, fill, seconds, blob, n))
        # A size target between the two RMSE targets' smooth-fill files (geometric mean).
        bpp = 8 * np.sqrt(np.prod([sizes[((("target_rmse", t),), "smooth")] for t in rmse_targets])) / n
        for fill in FILLS:
            seconds, blob = compress(fill, target_bpp=bpp)
            rows.append(row(dict(target_bpp=bpp), fill, seconds, blob, n))
    head = (f"### {case.label()}\n\n{n:,} points, grid {dem.grid.rows} x {dem.grid.cols}, "
            f"{int(dem.mask.sum()):,} occupied cells ({100 * dem.mask.mean():.0f} %); targets in units of "
            f"{unit_text}.")
    table = markdown_table(
        ["target", "fill", "f_c", "step mm", "bytes", "consistent / smooth", "bits/pt", "DEM RMSE mm",
         "max error mm", "promise", "time s"],
        with_ratios(rows))
    extra = "".join(f"\n\nNote: {note}" for note in notes + loaded.notes)
    return f"{head}\n\n{table}{extra}"


def row(target: dict, fill: str, seconds: float, blob: bytes, n: int) -> list:
    m = dftpcc.open(blob)
    stats, p = m.header.stats, m.params
    (name, value), = target.items()
    if name == "target_rmse":
        label, held = f"RMSE {1e3 * value:.1f} mm", stats["dem_rmse_m"] <= value
    elif name == "target_max_error":
        label, held = f"max error {1e3 * value:.1f} mm", stats["dem_max_error_m"] <= value
    else:
        label, held = f"{value:.3f} bits/pt", 8 * len(blob) <= value * n
    return [label, fill, f"{p.cutoff:g}", f"{1e3 * p.step:.3g}", len(blob), None, f"{8 * len(blob) / n:.3f}",
            f"{1e3 * stats['dem_rmse_m']:.2f}", f"{1e3 * stats['dem_max_error_m']:.1f}", verdict(held),
            f"{seconds:.2f}"]


def with_ratios(rows: list[list]) -> list[list]:
    """Fill the consistent / smooth column: pairs of rows share a target, smooth first."""
    for smooth, consistent in zip(rows[0::2], rows[1::2]):
        smooth[5] = ""
        consistent[5] = f"{consistent[4] / smooth[4]:.3f}"
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = run_arguments(__doc__.split("\n\n")[0], "one run per measurement instead of a median of 3")
    args = ap.parse_args(argv)
    repeats = QUICK_REPEATS if args.quick else REPEATS
    t0 = time.perf_counter()
    print(f"Measuring {library_label()}; {load_average()}.", flush=True)
    parts = [f"Compact profile, rate control from parsed points to bytes; times are medians of {repeats} runs. "
             "Errors are the ones each file states (DEM against the gridded DEM, occupied cells). "
             "consistent / smooth: the default fill's bytes over the push-pull fill's for the same target (for a size "
             "target, compare the errors instead)."]
    print(parts[0], "\n", flush=True)
    for case in pick_cases(CASES, args.files):
        parts.append(run_case(case, args.data, repeats))
        print(parts[-1], "\n", flush=True)
    finish_run(parts, args, "bench_ratecontrol", "Rate control and the consistent fill (issue 3)",
               f"Run time {time.perf_counter() - t0:.0f} s; {load_average()} at the end.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
