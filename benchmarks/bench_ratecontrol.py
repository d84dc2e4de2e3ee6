"""Rate control: the model against the search, and what the consistent fill saves.

By default, for every DEM and cloud of the data folder, untiled and in tiles of
:data:`TILE` cells (where that tiles the map), and each target level below:
the time of a fixed-parameter encode of the same gridded map, of the target
by today's search (``dftpcc.ratecontrol.method('search')``) and by the model
(the default), their ratios, both files' sizes, how many coefficient streams
and residual layers each entropy-coded and how many maps it rebuilt, and
whether the model fell back to the search. Every file is decoded and checked
against its target. On one core: run it under ``taskset -c 1``.

With ``--fills``, the older table: for each map and target (``--target-rmse``, ``--target-max-error``,
``--target-bpp``), compresses with the compact profile twice, once with the
push-pull fill alone (``fill='smooth'``) and once with the default
``fill='consistent'`` (the chosen cutoff tried again with the empty cells
refilled from the coded map). Reports the cutoff and step chosen, the file
size, the error the file states, whether the promise holds, and the median
wall time; every figure is measured in this run.

    taskset -c 1 .venv/bin/python -m benchmarks.bench_ratecontrol [--quick] [--files NAME ...] [--fills]
        [--json PATH] [--docs | --no-docs]

With ``--speed`` (``make bench-targets``), issue 43's speed table: per map, tiling and target,
the CPU time of a fixed encode and of the target by the model, each run's ratio (medians and
ranges over ``--runs``), untiled the floor (:class:`ChoiceTime`: the target's time if choosing cost
nothing but coding what it chose) over the fixed encode, the file's bytes against the search's
(``--with-search`` runs it once, ``--search-from`` takes an earlier run's), the decoded file's
error against its bound, and the median and worst ratio over the maps.

Targets are set from each map's gridding floor (the RMS distance of its
points to their cell's mean): DEM RMSE 0.75x and 2x the floor (points at
1.25x and about 2.2x the floor), a maximum error of 4x the floor, and
a size target between the two RMSE targets' files. A GeoTIFF's pixels have no
floor; there the unit is 0.1 % of the RMS relief.
"""

from __future__ import annotations

import json
import math
import statistics
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numpy as np

import dftpcc
from dftpcc import ratecontrol, ratemodel
from dftpcc.analysis import Analysis
from dftpcc.encoder import encode_dem
from dftpcc.params import Params
from dftpcc.tiles import TiledAnalysis

from benchmarks.bench_tiles import all_maps, with_auto
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
#: Tile side of the tiled runs (cells); a map no side of which exceeds it is coded untiled only.
TILE = 256
#: Issue 43's goals: a target at most this many times a fixed encode (median), never more than ...
GOAL_MEDIAN_RATIO = 3.0
GOAL_MAX_RATIO = 10.0
#: ... and a file within this fraction of the search's size.
GOAL_SIZE = 0.02


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


# --- the model against the search -----------------------------------------------------------------

class Counts:
    """Entropy codings (coefficient streams and residual layers) and rebuilt maps, counted by
    wrapping the methods that do them; a call inside another counted one (a tile's trial inside
    the map's) is not counted again."""

    def __init__(self) -> None:
        self.encodes = self.trials = 0
        self._depth = 0

    def wrap(self, owner: Any, name: str, kind: str) -> tuple[Any, str, Any]:
        original = getattr(owner, name)

        def counted(*args: Any, **kwargs: Any) -> Any:
            if not self._depth:
                setattr(self, kind, getattr(self, kind) + 1)
            self._depth += 1
            try:
                return original(*args, **kwargs)
            finally:
                self._depth -= 1

        setattr(owner, name, counted)
        return owner, name, original


@contextmanager
def counting() -> Iterator[Counts]:
    counts = Counts()
    saved = [counts.wrap(Analysis, "encode_stream", "encodes"), counts.wrap(TiledAnalysis, "encode_stream", "encodes"),
             counts.wrap(ratecontrol, "encode_residual", "encodes"),
             counts.wrap(ratecontrol, "predicted_residual", "encodes"),
             counts.wrap(ratemodel, "encode_residual", "encodes"),
             counts.wrap(Analysis, "trial", "trials"), counts.wrap(TiledAnalysis, "trial", "trials")]
    try:
        yield counts
    finally:
        for owner, name, original in reversed(saved):
            setattr(owner, name, original)


def timed(fn: Any, repeats: int) -> tuple[float, Any]:
    """Median wall time (s) of ``repeats`` calls and the last result."""
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def check(blob: bytes, dem: Any, name: str, value: float, n: int) -> bool:
    """Whether the decoded file meets its target on the gridded map's occupied cells."""
    if name == "target_bpp":
        return 8 * len(blob) <= value * n
    decoded = dftpcc.open(blob).read_dem()
    err = (decoded.heights - dem.heights)[dem.mask]
    if name == "target_rmse":
        return float(np.sqrt(np.mean(err * err))) <= value
    return float(np.abs(err).max()) <= value


def run_method(dem: Any, params: Params, n: int, how: str, repeats: int) -> dict[str, Any]:
    """One target by one rate-control method: time, bytes, counts, fallbacks."""
    with ratecontrol.method(how):
        seconds, _ = timed(lambda: encode_dem(dem, params, point_count=n), repeats)
        with counting() as counts, ratecontrol.tally() as tally:
            blob = encode_dem(dem, params, point_count=n)
    return dict(seconds=seconds, bytes=len(blob), encodes=counts.encodes, trials=counts.trials,
                choices=tally.choices, fallbacks=tally.fallbacks, blob=blob)


def _tilings(case: Case, data: Path, tiles: tuple[int, ...], loading: list[str]
             ) -> Iterator[tuple[Any, int, float, int]]:
    """The map of ``case`` gridded once, at each of ``tiles`` it is larger than (0: untiled): its DEM,
    its point count, its target unit and the tile side; what loading it noted goes to ``loading``."""
    loaded = load(case, data)
    loading.extend(loaded.notes)
    _, dem = shared_grid(loaded.points, loaded.resolution)
    unit, _ = unit_of(loaded, dem)
    for tile in (t for t in tiles if not t or max(dem.grid.shape) > t):
        yield dem, loaded.points.shape[0], unit, tile


def compare_map(case: Case, data: Path, repeats: int, search_repeats: int, tiles: tuple[int, ...],
                cached: dict | None = None) -> list[dict[str, Any]]:
    """Every target level of ``case`` at each of ``tiles`` (0: untiled; a side no side of the map
    exceeds is left out), by the search (or its row in ``cached``) and by the model."""
    notes: list[str] = []
    loading: list[str] = []
    out = []
    with warnings_as_notes(notes):
        for dem, n, unit, tile in _tilings(case, data, tiles, loading):
            base = Params(tile_size=tile)
            fixed, _ = timed(lambda: encode_dem(dem, base, point_count=n), repeats)
            rmse_targets = [0.75 * unit, 2.0 * unit]
            targets: list[tuple[str, float]] = [("target_rmse", t) for t in rmse_targets]
            targets.append(("target_max_error", 4.0 * unit))
            sizes = {}
            for i in range(4):
                if i == 3:  # between the two RMSE targets' files (geometric mean), as the --fills table
                    targets.append(("target_bpp", 8 * math.sqrt(sizes[0] * sizes[1]) / n))
                name, value = targets[i]
                params = base.replace(**{name: value})
                row: dict[str, Any] = dict(map=case.stem, tile=tile, cells=int(dem.grid.size), target=name,
                                           value=value, unit=unit, fixed=fixed)
                try:
                    # The model first: the search would warm the coder's table caches for it.
                    for how, reps in (("model", repeats), ("search", search_repeats)):
                        if how == "search" and cached is not None:
                            row["search"] = cached.get((case.stem, tile, name, round(value, 9)))
                            if row["search"] is None:
                                raise dftpcc.InvalidInputError("no search row in the earlier run")
                            continue
                        got = run_method(dem, params, n, how, reps)
                        got["held"] = check(got.pop("blob"), dem, name, value, n)
                        row[how] = got
                except dftpcc.InvalidInputError as exc:
                    row["unreached"] = str(exc)
                sizes[i] = row["search"]["bytes"] if row.get("search") else 0
                out.append(row)
                print(line_of(row), flush=True)
    for note in notes + loading:
        print(f"  note ({case.stem}): {note}")
    return out


def label_of(name: str, value: float, unit: float) -> str:
    if name == "target_bpp":
        return f"{value:.3f} bits/pt"
    short = {"target_rmse": "RMSE", "target_max_error": "max"}[name]
    return f"{short} {value / unit:g}u"


def line_of(row: dict[str, Any]) -> str:
    cells = table_row(row)
    return " | ".join(str(c) for c in cells)


def table_row(row: dict[str, Any]) -> list[Any]:
    head = [row["map"], row["tile"] or "whole", label_of(row["target"], row["value"], row["unit"]),
            f"{row['fixed']:.3f}"]
    if "unreached" in row:
        return head + ["unreached: " + row["unreached"][:60]] + [""] * 8
    s, m = row["search"], row["model"]
    searched = f"{s['encodes']}/{s['trials']}" if s.get("encodes") is not None else "—"
    held = m["held"] if s.get("held") is None else s["held"] and m["held"]
    return head + [f"{s['seconds']:.3f}", f"{m['seconds']:.3f}", f"{s['seconds'] / row['fixed']:.1f}",
                   f"{m['seconds'] / row['fixed']:.2f}", s["bytes"], m["bytes"],
                   f"{m['bytes'] / s['bytes'] - 1:+.2%}",
                   searched, f"{m['encodes']}/{m['trials']}" + (" fallback" if m["fallbacks"] else ""),
                   verdict(held)]


HEADER = ["map", "tiles", "target", "fixed s", "search s", "model s", "search / fixed", "model / fixed",
          "search bytes", "model bytes", "model vs search", "search enc/rebuilt", "model enc/rebuilt", "held"]


def summary(rows: list[dict[str, Any]]) -> str:
    done = [r for r in rows if "unreached" not in r]
    if not done:
        return "No target was reached."
    ratio = [r["model"]["seconds"] / r["fixed"] for r in done]
    before = [r["search"]["seconds"] / r["fixed"] for r in done]
    size = [r["model"]["bytes"] / r["search"]["bytes"] - 1 for r in done]
    fall = sum(r["model"]["fallbacks"] for r in done)
    choices = sum(r["model"]["choices"] for r in done)
    held = all(r["model"]["held"] and r["search"].get("held") is not False for r in done)
    worst = max(done, key=lambda r: r["model"]["seconds"] / r["fixed"])
    big = max(done, key=lambda r: r["model"]["bytes"] / r["search"]["bytes"])
    return (f"{len(done)} cases ({len(rows) - len(done)} unreached). Model / fixed encode: median "
            f"{statistics.median(ratio):.2f}x (goal {GOAL_MEDIAN_RATIO:g}x), max {max(ratio):.2f}x (goal "
            f"{GOAL_MAX_RATIO:g}x; {worst['map']} {worst['tile'] or 'whole'} {worst['target']}); search / fixed: "
            f"median {statistics.median(before):.1f}x, max {max(before):.1f}x. Model size vs search: median "
            f"{statistics.median(size):+.2%}, min {min(size):+.2%}, max {max(size):+.2%} (goal within "
            f"{GOAL_SIZE:.0%}; {big['map']} {big['tile'] or 'whole'} {big['target']}); over {GOAL_SIZE:.0%} larger: "
            f"{sum(v > GOAL_SIZE for v in size)}. Fallback to the search: {fall} of {choices} rate-control "
            f"choices. Every file meets its target (decoded and checked): {verdict(held)}.")


def model_main(args: Any, repeats: int) -> int:
    t0 = time.perf_counter()
    print(f"Measuring {library_label()}; {load_average()}.", flush=True)
    cases = [with_auto(c, args.data) for c in all_maps(args.data)]
    if args.files:
        cases = pick_cases(cases, args.files)
    search_repeats = 1 if args.quick else args.search_repeats
    cached = None
    if args.search_from:  # the search's rows of an earlier run (it takes an hour on every map, tiled)
        cached = {(r["map"], r["tile"], r["target"], round(r["value"], 9)): r["search"]
                  for r in json.loads(Path(args.search_from).read_text()) if r.get("search")}
    tiles = tuple(args.tiles)
    rows: list[dict[str, Any]] = []
    print(" | ".join(HEADER), flush=True)
    for case in cases:
        rows += compare_map(case, args.data, repeats, search_repeats, tiles, cached)
    where = ", ".join("untiled" if t == 0 else f"in {t}-cell tiles" for t in tiles)
    source = (f"the search's figures are those of an earlier run ({args.search_from})" if cached else
              f"the search's of {search_repeats}")
    intro = (f"Rate control by the model against today's search (issue 43), encode_dem of each gridded map, default "
             f"profile, {where}; times are medians of {repeats} runs ({source}), one core. Targets in units u of the gridding floor (0.1 % of the RMS relief for a "
             f"GeoTIFF): RMSE 0.75u and 2u, a maximum error of 4u, and a size between the two RMSE files. "
             f"enc/rebuilt: coefficient streams and residual layers entropy-coded / maps rebuilt by the choice.")
    parts = [intro, summary(rows), markdown_table(HEADER, [table_row(r) for r in rows])]
    print("\n" + parts[1], flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    finish_run(parts, args, "bench_ratecontrol_model", "Rate control: the model against the search (issue 43)",
               f"Run time {time.perf_counter() - t0:.0f} s; {load_average()} at the end.")
    return 0


# --- a target's cost against one fixed encode (issue 43's speed goals) ------------------------------

def cpu(fn: Any) -> tuple[float, Any]:
    """CPU seconds of this process for one call of ``fn`` (one core: other people's load on a
    shared machine leaves it alone, where wall time grows with it), and the result."""
    t0 = time.process_time()
    out = fn()
    return time.process_time() - t0, out


class ChoiceTime:
    """CPU seconds a target spends choosing (inside ``ratemodel.choose``) and, of those, coding
    (coefficient streams and residual layers coded inside it): the target less its choice, plus
    those codings, is the floor any rate control meets on this map, the time a target would take
    if its search for a choice cost nothing but the coding of what it chose (an upper bound of the
    floor where a choice codes more than one candidate)."""

    def __init__(self) -> None:
        self.choosing = self.coding = 0.0
        self._inside = False

    def wrap(self, owner: Any, name: str, field: str) -> tuple[Any, str, Any]:
        original = getattr(owner, name)

        def timed_call(*args: Any, **kwargs: Any) -> Any:
            if (field == "coding") != self._inside:  # codings inside a choice; choices not nested
                return original(*args, **kwargs)
            self._inside = field == "choosing"
            t0 = time.process_time()
            try:
                return original(*args, **kwargs)
            finally:
                setattr(self, field, getattr(self, field) + time.process_time() - t0)
                self._inside = field == "coding"

        setattr(owner, name, timed_call)
        return owner, name, original


@contextmanager
def choice_time() -> Iterator[ChoiceTime]:
    times = ChoiceTime()
    saved = [times.wrap(ratemodel, "choose", "choosing")]
    for owner, name in ((Analysis, "encode_stream"), (TiledAnalysis, "encode_stream"),
                        (ratecontrol, "encode_residual"), (ratecontrol, "predicted_residual"),
                        (ratemodel, "encode_residual")):
        saved.append(times.wrap(owner, name, "coding"))
    try:
        yield times
    finally:
        for owner, name, original in reversed(saved):
            setattr(owner, name, original)


def achieved(blob: bytes, dem: Any, name: str, n: int) -> float:
    """The decoded file's error (metres, occupied cells) or bits per point, as the target counts it."""
    if name == "target_bpp":
        return 8 * len(blob) / n
    err = (dftpcc.open(blob).read_dem().heights - dem.heights)[dem.mask]
    return float(np.sqrt(np.mean(err * err))) if name == "target_rmse" else float(np.abs(err).max())


def speed_map(case: Case, data: Path, runs: int, tiles: tuple[int, ...], searched: dict | None,
              with_search: bool) -> list[dict[str, Any]]:
    """Each target of ``case`` (as :func:`compare_map`) by the model, ``runs`` times, each run
    timed against a fixed encode of the same map right before it; the file decoded and its error
    measured; its size against the search's (run once with ``with_search``, or from ``searched``)."""
    notes: list[str] = []
    loading: list[str] = []
    out = []
    with warnings_as_notes(notes):
        for dem, n, unit, tile in _tilings(case, data, tiles, loading):
            base = Params(tile_size=tile)
            encode_dem(dem, base, point_count=n)  # warm the coder's caches, as for every target after it
            targets: list[tuple[str, float]] = [("target_rmse", 0.75 * unit), ("target_rmse", 2.0 * unit),
                                                ("target_max_error", 4.0 * unit)]
            sizes: list[int] = []
            for i in range(4):
                if i == 3:  # between the two RMSE targets' files (geometric mean), as compare_map
                    targets.append(("target_bpp", 8 * math.sqrt(sizes[0] * sizes[1]) / n))
                name, value = targets[i]
                params = base.replace(**{name: value})
                row: dict[str, Any] = dict(map=case.stem, tile=tile, cells=int(dem.grid.size), target=name,
                                           value=value, unit=unit, fixed=[], model=[], floor=[])
                try:
                    with ratecontrol.tally() as tally:
                        for _ in range(runs):
                            row["fixed"].append(cpu(lambda: encode_dem(dem, base, point_count=n))[0])
                            with choice_time() as chosen:
                                seconds, blob = cpu(lambda: encode_dem(dem, params, point_count=n))
                            row["model"].append(seconds)
                            if not tile:  # a tiled map's runs each choose and code: no one floor
                                row["floor"].append(seconds - chosen.choosing + chosen.coding)
                    row.update(bytes=len(blob), fallbacks=tally.fallbacks, choices=tally.choices,
                               error=achieved(blob, dem, name, n))
                    key = (case.stem, tile, name, round(value, 9))
                    if searched is not None and key in searched:
                        row["search_bytes"] = searched[key]["bytes"]
                    elif with_search:
                        with ratecontrol.method("search"):
                            row["search_bytes"] = len(encode_dem(dem, params, point_count=n))
                except dftpcc.InvalidInputError as exc:
                    row["unreached"] = str(exc)
                sizes.append(row.get("bytes", 0))
                out.append(row)
                print(" | ".join(str(c) for c in speed_row(row)), flush=True)
    for note in notes + loading:
        print(f"  note ({case.stem}): {note}")
    return out


def _span(values: list[float], fmt: str) -> str:
    return f"{format(statistics.median(values), fmt)} ({format(min(values), fmt)}-{format(max(values), fmt)})"


def ratios(row: dict[str, Any], of: str = "model") -> list[float]:
    """Each run's target time (``of='floor'``: its floor, :class:`ChoiceTime`) over the fixed
    encode timed right before it."""
    return [m / f for m, f in zip(row[of], row["fixed"])]


def speed_row(row: dict[str, Any]) -> list[Any]:
    head = [row["map"], row["tile"] or "whole", label_of(row["target"], row["value"], row["unit"])]
    if "unreached" in row:
        return head + ["unreached: " + row["unreached"][:60]] + [""] * 7
    name, bound = row["target"], row["value"]
    unit = "bits/pt" if name == "target_bpp" else "m"
    size = f"{row['bytes'] / row['search_bytes'] - 1:+.2%}" if row.get("search_bytes") else "—"
    held = row["error"] <= bound
    return head + [_span(row["fixed"], ".3f"), _span(row["model"], ".3f"), _span(ratios(row), ".1f"),
                   _span(ratios(row, "floor"), ".1f") if row["floor"] else "—", row["bytes"], size,
                   f"{row['error']:.4g} / {bound:.4g} {unit} ({verdict(held)})", f"{row['fallbacks']}/{row['choices']}"]


SPEED_HEADER = ["map", "tiles", "target", "fixed encode s", "target s", "target / fixed",
                "floor / fixed (choosing free; untiled)", "bytes", "vs search", "achieved / bound", "fallbacks"]


def speed_summary(rows: list[dict[str, Any]], runs: int) -> str:
    done = [r for r in rows if "unreached" not in r]
    if not done:
        return "No target was reached."
    per_row = [statistics.median(ratios(r)) for r in done]
    # The median and the worst over the cases, in each run: their range over the runs.
    by_run = [[ratios(r)[k] for r in done] for k in range(runs)]
    medians = [statistics.median(v) for v in by_run]
    worsts = [max(v) for v in by_run]
    worst = max(done, key=lambda r: statistics.median(ratios(r)))
    sized = [r["bytes"] / r["search_bytes"] - 1 for r in done if r.get("search_bytes")]
    held = all(r["error"] <= r["value"] for r in done)
    parts = [f"{len(done)} cases ({len(rows) - len(done)} unreached), {runs} runs each. Target / fixed encode "
             f"(CPU time): median over the cases {statistics.median(per_row):.2f}x (per run "
             f"{min(medians):.2f}-{max(medians):.2f}x; goal {GOAL_MEDIAN_RATIO:g}x), worst "
             f"{max(per_row):.1f}x ({worst['map']} {worst['tile'] or 'whole'} {label_of(worst['target'], worst['value'], worst['unit'])}; "
             f"per run {min(worsts):.1f}-{max(worsts):.1f}x; goal {GOAL_MAX_RATIO:g}x); over {GOAL_MAX_RATIO:g}x: "
             f"{sum(v > GOAL_MAX_RATIO for v in per_row)} cases."]
    floors = [statistics.median(ratios(r, "floor")) for r in done if r.get("floor")]
    if floors:
        parts.append(f"Untiled, the floor (the target less its choice, plus the codings inside the choice: what a "
                 f"target would cost if choosing cost nothing but coding what it chose) over the fixed encode: median "
                     f"{statistics.median(floors):.2f}x, worst {max(floors):.1f}x; above {GOAL_MEDIAN_RATIO:g}x: "
                     f"{sum(v > GOAL_MEDIAN_RATIO for v in floors)} of {len(floors)} cases.")
    if sized:
        parts.append(f"Size against the search's ({len(sized)} cases): median {statistics.median(sized):+.2%}, "
                     f"min {min(sized):+.2%}, max {max(sized):+.2%}; over {GOAL_SIZE:.0%} larger: "
                     f"{sum(v > GOAL_SIZE for v in sized)}.")
    parts.append(f"Fallbacks to the search: {sum(r['fallbacks'] for r in done)} of "
                 f"{sum(r['choices'] for r in done)} choices. Every file meets its target (decoded and measured): "
                 f"{verdict(held)}.")
    return " ".join(parts)


def speed_main(args: Any) -> int:
    t0 = time.perf_counter()
    print(f"Measuring {library_label()}; {load_average()}.", flush=True)
    cases = [with_auto(c, args.data) for c in all_maps(args.data)]
    if args.files:
        cases = pick_cases(cases, args.files)
    runs = 1 if args.quick else args.runs
    searched = None
    if args.search_from:
        searched = {(r["map"], r["tile"], r["target"], round(r["value"], 9)): r["search"]
                    for r in json.loads(Path(args.search_from).read_text()) if r.get("search")}
    rows: list[dict[str, Any]] = []
    print(" | ".join(SPEED_HEADER), flush=True)
    for case in cases:
        rows += speed_map(case, args.data, runs, tuple(args.tiles), searched, args.with_search)
    intro = (f"A target's cost against one fixed encode of the same gridded map (issue 43: a median of at most "
             f"{GOAL_MEDIAN_RATIO:g}x, no case above {GOAL_MAX_RATIO:g}x), encode_dem, default profile, "
             f"{', '.join('untiled' if t == 0 else f'in {t}-cell tiles' for t in args.tiles)}; CPU seconds of one "
             f"process on one core, {runs} runs, each target timed right after a fixed encode: medians (range). "
             f"Targets in units u of the gridding floor (0.1 % of the RMS relief for a GeoTIFF): RMSE 0.75u and 2u, "
             f"a maximum error of 4u, a size between the two RMSE files. Achieved: the decoded file's error on the "
             f"occupied cells (or its bits per point).")
    parts = [intro, speed_summary(rows, runs), markdown_table(SPEED_HEADER, [speed_row(r) for r in rows])]
    print("\n" + parts[1], flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    finish_run(parts, args, "bench_ratecontrol_speed", "Rate control: a target against one fixed encode (issue 43)",
               f"Run time {time.perf_counter() - t0:.0f} s; {load_average()} at the end.")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = run_arguments(__doc__.split("\n\n")[0], "one run per measurement instead of a median of 3")
    ap.add_argument("--fills", action="store_true", help="the consistent against the smooth fill, four maps")
    ap.add_argument("--json", metavar="PATH", help="also write the model-against-search rows here")
    ap.add_argument("--search-repeats", type=int, default=1, help="runs of today's (slow) search per target")
    ap.add_argument("--tiles", type=int, nargs="+", default=[0, TILE], help="tile sides (0: untiled)")
    ap.add_argument("--search-from", metavar="JSON", help="take the search's rows from an earlier --json output")
    ap.add_argument("--speed", action="store_true",
                    help="each target's CPU time against a fixed encode, run by run, and its achieved error")
    ap.add_argument("--runs", type=int, default=REPEATS, help="--speed: runs of each target (ranges over them)")
    ap.add_argument("--with-search", action="store_true", help="--speed: also run the (slow) search once per target")
    args = ap.parse_args(argv)
    repeats = QUICK_REPEATS if args.quick else REPEATS
    if args.speed:
        return speed_main(args)
    if not args.fills:
        return model_main(args, repeats)
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
