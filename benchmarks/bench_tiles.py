"""Issue 12: what coding a map in tiles costs, whether the tiles show, and how fast one tile reads back.

Tiled maps (format 1.1, docs/format.md *Tiles*) against the same map coded
whole (``tile_size=0``), every figure measured in this run:

1. rate cost: bytes of the tiled file over the untiled one at equal DEM RMSE
   (the three levels of bench_anchors, ``target_rmse``) and at equal maximum
   error (``target_max_error``), per tile size, with the error each file
   achieves over the whole map checked against its target;
2. seams: RMSE of the cells within two cells of an internal tile edge over
   the RMSE of the other cells, on every real map of the data folder, at a
   target of each kind (RMSE, maximum error, bits per point);
3. the figure docs/figures/tiles_error_map.png: the error of a tiled map,
   and the tile grid beside it;
4. random access: one tile of a ~10 M-cell mosaic of real DEMs read from a
   file on disk (``read_dem(bbox=...)``): time, and bytes read against the
   tile's own bytes plus the header;
5. compress and decompress speed per tile size at fixed parameters.

    .venv/bin/python -m benchmarks.bench_tiles [--quick] [--files NAME ...] [--docs | --no-docs]

Nothing here fails on a timing or a ratio: targets print as PASS/MISS.
"""

from __future__ import annotations

import math
import statistics
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

import dftpcc
from dftpcc import limits
from dftpcc.dem import TileGrid
from dftpcc.grid import auto_resolution
from dftpcc.params import DEFAULT_CUTOFF

from benchmarks import max_error
from benchmarks.bench_anchors import FLOOR_MULTIPLES, RELIEF_FRACTIONS
from benchmarks.common import (FIGURES, GROUND, Case, Loaded, finish_run, load, load_average, library_label,
                               markdown_table, median_time, rmse, run_arguments, shared_grid,
                               verdict, warnings_as_notes)

__all__ = ["COST_CASES", "TILE_SIZES", "SEAM_BAND", "MAX_SEAM_RATIO", "main"]

#: Maps of the rate-cost tables: bench_anchors' field (ground class, 0.5 m) and DEMs at their
#: pixel size; the forest as bench_codec and bench_ratecontrol take it (0.5 m, every point).
COST_CASES = (
    Case("field_gentle_ign.laz", 0.5, (GROUND,), "gentle"),
    Case("mars_gale_1m.tif", None, None, "gentle"),
    Case("moon_kepler_lola_48m.tif", None, None, "rough"),
    Case("forest_slope_bcts_2.8M.laz", 0.5, None, "rough"),
)
#: bench_anchors' resolution and classes for the point clouds it codes; every other cloud is
#: gridded at the resolution ``resolution='auto'`` picks (``auto`` below), GeoTIFFs at their pixel.
ANCHOR_GRIDS = {
    "field_gentle_ign.laz": (0.5, (GROUND,)),
    "coastal_plain_ign.laz": (2.0, (GROUND,)),
    "mountain_arid_alirt.las": (2.0, None),
    "redrocks_rough.ply": (5.0, None),
    "forest_slope_bcts_2.8M.laz": (0.5, None),
}
#: Point-cloud files that repeat another one's points (the Draco original of redrocks_rough.ply).
SAME_MAP = {"redrocks_rough.drc": "redrocks_rough.ply"}
AUTO = "auto"

#: Tile sides measured (cells); a side whose tile holds the whole map writes it untiled (1 tile).
TILE_SIZES = (128, 256, 512, 1024)
QUICK_TILE_SIZES = (128, 512)
#: The tile side every map's seams are measured at (issue 12), and at which the size target is tried.
SEAM_TILE = 256
#: Cells within this many cells of an internal tile edge are the seam's (issue 12).
SEAM_BAND = 2
#: Issue 12's target for seam RMSE over the RMSE elsewhere.
MAX_SEAM_RATIO = 1.2
#: The middle RMSE level (of bench_anchors' three) gives the size target and the figure.
MIDDLE_LEVEL = 1
#: Maximum-error bound of a map without one in benchmarks/max_error.py: this many
#: times its unit (the gridding floor, or 0.1 % of a DEM's RMS relief), as bench_ratecontrol.
MAX_ERROR_UNITS = 4.0
DEM_UNIT_FRACTION = 1e-3
#: A file passes its target when its error is at most the target plus this (metres, float round-off).
CHECK_SLACK = 1e-9
#: Speed at fixed parameters: medians of this many runs (a quick run: one).
SPEED_REPEATS = 3

#: Random access: Kepler mirrored into a MOSAIC x MOSAIC mosaic, tiles of RA_TILE cells.
MOSAIC = 4
QUICK_MOSAIC = 2
#: Height offset (metres) between neighbouring copies, so no copy repeats another's heights.
MOSAIC_OFFSET_M = 150.0
RA_TILE = 512
#: The mosaic is this run's own file: trusted with the largest grid a reader takes (a whole decode
#: also counts the base layer's frequency pairs, so the grid's own cell count is not enough).
TRUSTED_CELLS = limits.MAX_CELLS
RA_REPEATS = 20
QUICK_RA_REPEATS = 5
#: Issue 12's random-access targets: one tile in under 10 ms, reading under 2x its bytes plus the header.
RA_MAX_SECONDS = 0.010
RA_MAX_BYTES_FACTOR = 2.0
#: The figure: Kepler at T = 128, RMSE level 2.
FIGURE_CASE, FIGURE_TILE = "moon_kepler_lola_48m.tif", 128
#: Seams are listed for every map of the data folder; --quick keeps every QUICK_EVERY-th.
QUICK_EVERY = 3


# --- one map, one file ------------------------------------------------------------------------

@dataclass
class Target:
    """One rate-control target: the Params field, its value, and its label in the tables."""

    name: str
    value: float
    label: str

    @property
    def kind(self) -> str:
        return {"target_rmse": "RMSE", "target_max_error": "max error", "target_bpp": "bits/pt"}[self.name]


@dataclass
class Coded:
    """One file of a map at one target and tile side, decoded and measured against the gridded DEM."""

    target: Target
    tile: int                 # side asked for, 0 = untiled
    tiled: bool               # whether the file holds tiles (False when one tile holds the map)
    bytes: int
    seconds: float            # wall time of the compress, rate control included (one run)
    rmse: float               # metres, occupied cells of the whole map
    max_error: float
    seam_ratio: float | None  # seam RMSE / RMSE elsewhere; None when untiled
    seam_cells: int = 0
    params: str = ""
    cutoff: float = 0.0
    step: float = 0.0
    blob: bytes = b""
    #: The error map (metres, 0 on empty cells) of an untiled file: the control of the seam ratio.
    err: np.ndarray | None = None

    @property
    def held(self) -> bool:
        if self.target.name == "target_rmse":
            return self.rmse <= self.target.value + CHECK_SLACK
        if self.target.name == "target_max_error":
            return self.max_error <= self.target.value + CHECK_SLACK
        return True  # a size target: checked on the bytes by the caller


@dataclass
class MapRun:
    """A map read and gridded once, its files measured at every target and tile side."""

    loaded: Loaded
    truth: np.ndarray          # absolute heights of the cells, metres (0 where empty)
    mask: np.ndarray
    interior: np.ndarray       # occupied cells at least SEAM_BAND + 1 cells from the map's border
    floor: float
    unit: float
    levels: list[Target]
    bound: Target
    coded: dict[tuple[str, float, int], Coded] = field(default_factory=dict)
    #: Why a target could not be reached at a tile side (a size target under what the tiles' masks need).
    unreached: dict[tuple[str, float, int], str] = field(default_factory=dict)
    #: Tile sides the seams were asked at (a side that does not tile the map lists as 1 tile).
    seam_tiles: tuple[int, ...] = ()
    notes: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return self.loaded.case.name

    @property
    def shape(self) -> tuple[int, int]:
        return self.mask.shape

    def get(self, target: Target, tile: int) -> Coded | None:
        return self.coded.get((target.name, target.value, tile))


def prepare(case: Case, data: Path) -> MapRun:
    """Read, grid and set the targets of one map (bench_anchors' levels, a maximum-error bound)."""
    loaded = load(case, data)
    with warnings_as_notes(loaded.notes):
        grid, dem = shared_grid(loaded.points, loaded.resolution)
    mask = dem.mask
    truth = np.where(mask, dem.heights + grid.z0, 0.0)
    floor = float(dem.gridding_rmse)
    relief = float(np.std(loaded.points[:, 2]))
    if case.is_dem:
        unit = DEM_UNIT_FRACTION * relief
        levels = [Target("target_rmse", f * relief, f"RMSE {100 * f:g}% relief ({fmt_m(f * relief)})")
                  for f in RELIEF_FRACTIONS]
    else:
        unit = floor
        # The DEM RMSE that, with the floor in quadrature, makes the points' error k x the floor.
        levels = [Target("target_rmse", floor * math.sqrt(k * k - 1),
                         f"RMSE {k:g}x floor (DEM {fmt_m(floor * math.sqrt(k * k - 1))})")
                  for k in FLOOR_MULTIPLES]
    bounds = max_error.MAX_ERRORS.get(case.name)
    if bounds:
        e = bounds[len(bounds) // 2]
        bound = Target("target_max_error", e, f"max error {max_error.fmt_length(e)}")
    else:
        e = MAX_ERROR_UNITS * unit
        bound = Target("target_max_error", e, f"max error {MAX_ERROR_UNITS:g} units ({fmt_m(e)})")
    return MapRun(loaded, truth, mask, interior_of(mask), floor, unit, levels, bound)


def interior_of(mask: np.ndarray) -> np.ndarray:
    """The occupied cells more than SEAM_BAND cells from the map's border (the grid's edge and its
    empty cells), which costs errors of its own: the cells both sides of the seam ratio count."""
    size = 2 * SEAM_BAND + 1
    return ndimage.binary_erosion(mask, structure=np.ones((size, size), bool), border_value=0)


def near_edges(shape: tuple[int, int], tile: int) -> np.ndarray:
    """Cells within SEAM_BAND cells of an internal tile edge (the edges at multiples of ``tile``)."""
    def band(n: int) -> np.ndarray:
        idx = np.arange(n)
        # Distance of a cell's centre to the nearest internal edge, in cells (edges at k*tile, 0 < k*tile < n).
        edges = np.arange(tile, n, tile)
        if edges.size == 0:
            return np.zeros(n, bool)
        d = np.abs(idx[:, None] + 0.5 - edges[None, :]).min(axis=1)
        return d < SEAM_BAND
    rows, cols = band(shape[0]), band(shape[1])
    return rows[:, None] | cols[None, :]


def seam_ratio(run: MapRun, err: np.ndarray, tile: int) -> tuple[float | None, int]:
    near = near_edges(run.shape, tile)
    seam, rest = run.interior & near, run.interior & ~near
    if not seam.any() or not rest.any():
        return None, int(seam.sum())
    other = rmse(err[rest])
    return (rmse(err[seam]) / other if other > 0 else math.nan), int(seam.sum())


def code(run: MapRun, target: Target, tile: int, *, keep: bool = False) -> Coded | None:
    """Compress ``run``'s map at ``target`` with tile side ``tile`` (0: whole), decode, measure.

    None when rate control cannot reach the target (the reason is kept in ``run.unreached``).
    """
    loaded = run.loaded
    with warnings_as_notes(run.notes):
        t0 = time.perf_counter()
        try:
            blob = dftpcc.compress(loaded.points, resolution=loaded.resolution, tile_size=tile,
                                   **{target.name: target.value})
        except dftpcc.InvalidInputError as exc:
            if target.name != "target_bpp":
                raise
            # A size target the tiles' masks and index alone exceed is a finding, not a failure.
            run.unreached[(target.name, target.value, tile)] = str(exc)
            return None
        seconds = time.perf_counter() - t0
        with dftpcc.open(blob) as cmap:
            dem = cmap.read_dem()
            tiled, p = cmap.tiled, cmap.params
    if dem.grid.shape != run.shape:
        raise RuntimeError(f"{run.name}: dftpcc rebuilt a {dem.grid.shape} grid for a {run.shape} DEM")
    err = np.where(run.mask, dem.heights + dem.grid.z0 - run.truth, 0.0)
    ratio, cells = seam_ratio(run, err, tile) if tiled else (None, 0)
    coded = Coded(target, tile, tiled, len(blob), seconds, rmse(err[run.mask]),
                  float(np.abs(err[run.mask]).max()), ratio, cells,
                  f"f_c {p.cutoff:g}, step {fmt_m(p.step)}", p.cutoff, p.step, blob if keep else b"", None if tiled else err)
    run.coded[(target.name, target.value, tile)] = coded
    return coded


def fmt_m(metres: float) -> str:
    """A height error: in mm below a metre, else in m."""
    return f"{1e3 * metres:.4g} mm" if metres < 1 else f"{metres:.4g} m"


def tiled_at(run: MapRun, tile: int) -> bool:
    return max(run.shape) > tile


# --- 1. rate cost -------------------------------------------------------------------------------

def cost_runs(run: MapRun, tiles: tuple[int, ...], levels: list[Target]) -> None:
    """Every target (``levels`` and the bound) untiled and at every tile side that tiles the map."""
    for target in levels + [run.bound]:
        code(run, target, 0)
        for tile in tiles:
            if tiled_at(run, tile):
                code(run, target, tile, keep=(run.name == FIGURE_CASE and tile == FIGURE_TILE
                                              and target is run.levels[MIDDLE_LEVEL]))
        print(f"  {run.name} {target.label}: done", flush=True)


def fmt_ratio(tiled: Coded | None, whole: Coded | None, one_tile: bool) -> str:
    if one_tile:
        return "1 tile: 1.000"
    if tiled is None or whole is None:
        return "—"
    return f"{tiled.bytes / whole.bytes:.3f}"


def cost_tables(runs: list[MapRun], tiles: tuple[int, ...], levels_of: dict[str, list[Target]]) -> str:
    out = []
    for tile in tiles:
        rows = []
        for run in runs:
            for target in levels_of[run.name] + [run.bound]:
                whole, tiled = run.get(target, 0), run.get(target, tile)
                one = not tiled_at(run, tile)
                tgrid = TileGrid(*run.shape, tile)
                cells = [run.name, "1 tile" if one else f"{tgrid.tile_rows} x {tgrid.tile_cols}", target.label,
                         f"{whole.bytes:,}" if whole else "—", "—" if one or not tiled else f"{tiled.bytes:,}",
                         fmt_ratio(tiled, whole, one)]
                c = whole if one else tiled
                if c is not None:
                    got = c.rmse if target.name == "target_rmse" else c.max_error
                    cells += [fmt_m(c.rmse), fmt_m(c.max_error),
                              f"{fmt_m(got)} ≤ {fmt_m(target.value)} {verdict(c.held)}", c.params]
                rows.append(cells)
        out.append(f"#### T = {tile}\n\n" + markdown_table(
            ["map", "tiles", "target", "untiled bytes", "tiled bytes", "tiled / untiled", "RMSE",
             "max error", "target held", "tiled file's setting"], rows))
    return "\n\n".join(out)


def cost_summary(runs: list[MapRun], tiles: tuple[int, ...], levels_of: dict[str, list[Target]]) -> str:
    """Geometric mean of tiled / untiled per tile side, over the maps it tiles and every target."""
    rows = []
    for tile in tiles:
        per_map, all_ratios = [], []
        for run in runs:
            ratios = [run.get(t, tile).bytes / run.get(t, 0).bytes
                      for t in levels_of[run.name] + [run.bound] if run.get(t, tile) and run.get(t, 0)]
            if not tiled_at(run, tile):
                per_map.append(f"{run.name.split('_')[0]} 1 tile")
            elif ratios:
                per_map.append(f"{run.name.split('_')[0]} {gmean(ratios):.3f}")
                all_ratios += ratios
        rows.append([tile, f"{gmean(all_ratios):.3f}" if all_ratios else "—",
                     f"{max(all_ratios):.3f}" if all_ratios else "—", "; ".join(per_map)])
    return markdown_table(["T", "geometric mean tiled / untiled (maps it tiles)", "worst", "per map (geometric mean "
                           "over its targets)"], rows)


def gmean(values: list[float]) -> float:
    return math.exp(statistics.fmean(math.log(v) for v in values))


# --- 2. seams -------------------------------------------------------------------------------------

def all_maps(data: Path) -> list[Case]:
    """Every real map of the data folder, gridded as bench_anchors does or at the 'auto' resolution."""
    cases = []
    for path in sorted((data / "dems").glob("*.tif")):
        cases.append(Case(path.name, None, None, "dem"))
    for path in sorted((data / "pointclouds").iterdir()):
        if path.name in SAME_MAP or path.suffix.lower() not in (".las", ".laz", ".ply", ".drc"):
            continue
        resolution, classes = ANCHOR_GRIDS.get(path.name, (AUTO, None))
        cases.append(Case(path.name, resolution, classes, "cloud"))
    return cases


def with_auto(case: Case, data: Path) -> Case:
    if case.resolution != AUTO:
        return case
    points = dftpcc.read(case.path(data), classes=list(case.classes) if case.classes else None).points
    return Case(case.name, float(auto_resolution(points)), case.classes, case.terrain)


def seam_runs(run: MapRun, tiles: tuple[int, ...]) -> list[Target]:
    """The size target (the untiled file's bits at the middle RMSE level), and each target at ``tiles``."""
    middle = run.levels[MIDDLE_LEVEL]
    whole = run.get(middle, 0) or code(run, middle, 0)
    n = run.loaded.points.shape[0]
    bpp = 8.0 * whole.bytes / n
    size = Target("target_bpp", bpp, f"{bpp:.4g} bits/pt (untiled at {middle.label.split(' (')[0]})")
    for tile in tiles:
        if not tiled_at(run, tile):
            continue
        for target in (middle, run.bound, size):
            if run.get(target, tile) is None:
                code(run, target, tile)
    return [middle, run.bound, size]


def seam_table(runs: list[MapRun], targets_of: dict[str, list[Target]]) -> tuple[str, str]:
    rows, worst = [], None
    for run in runs:
        n = run.loaded.points.shape[0]
        for target in targets_of[run.name]:
            tiles = sorted({t for (name, value, t) in list(run.coded) + list(run.unreached)
                            if (name, value) == (target.name, target.value) and t})
            for tile in tiles:
                c = run.get(target, tile)
                if c is None:
                    tg = TileGrid(*run.shape, tile)
                    rows.append([run.name, f"{run.shape[0]} x {run.shape[1]}", tile, f"{tg.tile_rows} x {tg.tile_cols}",
                                 target.label, "", "", "", "—", "",
                                 "unreachable: " + run.unreached[(target.name, target.value, tile)]])
                    continue
                if not c.tiled:
                    continue
                whole = run.get(run.levels[MIDDLE_LEVEL] if target.name == "target_bpp" else target, 0)
                extra = ""
                if target.name == "target_bpp":
                    held = 8 * c.bytes <= target.value * n
                    extra = (f"bits {8 * c.bytes / n:.4g} {verdict(held)}; RMSE tiled / untiled "
                             f"{c.rmse / whole.rmse:.3f}" if whole else f"bits {8 * c.bytes / n:.4g} {verdict(held)}")
                elif whole:
                    extra = f"bytes tiled / untiled {c.bytes / whole.bytes:.3f}"
                ratio = c.seam_ratio
                text = "—" if ratio is None else f"{ratio:.3f} {verdict(ratio <= MAX_SEAM_RATIO)}"
                # The same cells of the untiled file at the same target: what the terrain alone gives.
                same = run.get(target, 0)
                control = seam_ratio(run, same.err, tile)[0] if same is not None and same.err is not None else None
                tg = TileGrid(*run.shape, tile)
                rows.append([run.name, f"{run.shape[0]} x {run.shape[1]}", tile, f"{tg.tile_rows} x {tg.tile_cols}",
                             target.label, fmt_m(c.rmse), fmt_m(c.max_error), f"{c.seam_cells:,}",
                             text, "—" if control is None else f"{control:.3f}", extra])
                if ratio is not None and (worst is None or ratio > worst[0]):
                    worst = (ratio, f"{run.name}, T = {tile}, {target.label}"
                             + ("" if control is None else f"; the untiled file's ratio on the same cells: {control:.3f}"))
        for tile in run.seam_tiles:
            if not tiled_at(run, tile):
                rows.append([run.name, f"{run.shape[0]} x {run.shape[1]}", tile, "1 tile", "", "", "", "", "—", "",
                             "one tile holds the map: no seam"])
    if worst is None:
        summary = "No tiled file: no seam measured."
    else:
        summary = (f"Worst seam ratio: **{worst[0]:.3f}** ({worst[1]}); target ≤ {MAX_SEAM_RATIO:g} "
                   f"{verdict(worst[0] <= MAX_SEAM_RATIO)} over {sum(r[8] != '—' for r in rows)} tiled files; "
                   f"{sum(r[8].endswith('MISS') for r in rows)} over {MAX_SEAM_RATIO:g}.")
    table = markdown_table(["map", "grid", "T", "tiles", "target", "RMSE", "max error", "seam cells",
                            f"seam RMSE / other (≤ {MAX_SEAM_RATIO:g})", "same cells, untiled file",
                            "vs untiled"], rows)
    return table, summary


# --- 3. figure ---------------------------------------------------------------------------------

def figure(run: MapRun, path: Path) -> str:
    """|error| of the tiled file (Kepler, T = 128, level 2), the same with the tile grid, and RMS error by distance to an edge."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    target = run.levels[MIDDLE_LEVEL]
    c = run.get(target, FIGURE_TILE)
    if c is None or not c.blob:
        return ""
    with dftpcc.open(c.blob) as cmap:
        dem = cmap.read_dem()
    err = np.abs(np.where(run.mask, dem.heights + dem.grid.z0 - run.truth, np.nan))
    rows, cols = run.shape
    vmax = float(np.nanpercentile(err, 99))
    fig, axes = plt.subplots(1, 3, figsize=(15, 5), gridspec_kw=dict(width_ratios=[1, 1, 0.9]),
                             constrained_layout=True)
    for ax, grid_lines in zip(axes[:2], (False, True)):
        im = ax.imshow(err, origin="lower", cmap="magma", vmin=0, vmax=vmax, interpolation="nearest")
        if grid_lines:
            for e in range(FIGURE_TILE, rows, FIGURE_TILE):
                ax.axhline(e - 0.5, color="c", lw=0.6, alpha=0.5)
            for e in range(FIGURE_TILE, cols, FIGURE_TILE):
                ax.axvline(e - 0.5, color="c", lw=0.6, alpha=0.5)
        ax.set_title(("the tile grid (T = %d) drawn over it" % FIGURE_TILE) if grid_lines else
                     "|error| of the tiled map, no grid drawn", fontsize=9)
        ax.set_xlabel("column (cells)")
        ax.set_ylabel("row (cells)")
    fig.colorbar(im, ax=axes[1], shrink=0.8, label="|decoded - DEM| (m)")
    # RMS error by distance of a cell to its nearest internal tile edge (rows and columns).
    r = np.arange(rows)[:, None] + 0.5
    q = np.arange(cols)[None, :] + 0.5

    def dist(idx: np.ndarray, n: int) -> np.ndarray:
        edges = np.arange(FIGURE_TILE, n, FIGURE_TILE)
        return np.abs(idx[..., None] - edges).min(axis=-1)
    d = np.minimum(np.broadcast_to(dist(r, rows), run.shape), np.broadcast_to(dist(q, cols), run.shape))
    band = np.floor(d).astype(int)
    e2 = np.where(run.interior, np.nan_to_num(err) ** 2, np.nan)
    xs = np.arange(FIGURE_TILE // 2)
    ys = [math.sqrt(np.nanmean(e2[band == k])) if np.any((band == k) & run.interior) else np.nan for k in xs]
    axes[2].plot(xs + 0.5, ys, "-o", ms=2)
    axes[2].axvspan(0, SEAM_BAND, color="c", alpha=0.2, label=f"seam band ({SEAM_BAND} cells)")
    axes[2].set_ylim(0, 1.3 * np.nanmax(ys))
    axes[2].set_xlabel("distance to the nearest internal tile edge (cells)")
    axes[2].set_ylabel("RMS error (m)")
    axes[2].set_title("RMS error by distance to a tile edge", fontsize=9)
    axes[2].legend(fontsize=8)
    fig.suptitle(f"{run.name}, T = {FIGURE_TILE}, {target.label}: file {c.bytes:,} B, RMSE {c.rmse:.3g} m, "
                 f"seam ratio {c.seam_ratio:.3f}", fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return (f"Figure `docs/figures/{path.name}`: {run.name} at T = {FIGURE_TILE}, {target.label}: the "
            f"|error| of every cell (left), the same with the tile grid drawn (middle), and the RMS error by "
            f"distance to the nearest internal tile edge (right).")


# --- 4. random access -----------------------------------------------------------------------------

def mosaic_tif(data: Path, folder: Path, copies: int) -> tuple[Path, tuple[int, int]]:
    """Kepler ``copies`` x ``copies`` times as one float32 GeoTIFF: mirrored so the copies meet edge
    to edge without a step, each copy raised by its own offset (a gentle ramp between copies)."""
    import rasterio

    with rasterio.open(data / "dems" / "moon_kepler_lola_48m.tif") as src:
        dem = src.read(1).astype(np.float32)
        transform = src.transform
    h, w = dem.shape
    out = np.empty((copies * h, copies * w), np.float32)
    for i in range(copies):
        for j in range(copies):
            part = dem[::-1 if i % 2 else 1, ::-1 if j % 2 else 1]
            out[i * h:(i + 1) * h, j * w:(j + 1) * w] = part + MOSAIC_OFFSET_M * (i + j)
    path = folder / f"kepler_mosaic_{copies}x{copies}.tif"
    with rasterio.open(path, "w", driver="GTiff", width=out.shape[1], height=out.shape[0], count=1,
                       dtype="float32", transform=transform, tiled=True) as dst:
        dst.write(out, 1)
    return path, out.shape


def random_access(data: Path, copies: int, repeats: int, speed_repeats: int) -> str:
    with tempfile.TemporaryDirectory(prefix="bench_tiles_") as tmp:
        folder = Path(tmp)
        t0 = time.perf_counter()
        tif, shape = mosaic_tif(data, folder, copies)
        cells = shape[0] * shape[1]
        build_s = time.perf_counter() - t0
        # Fixed parameters (no rate-control search over 10 M cells): the default cutoff and a step of
        # 1 m, Kepler's own height quantum.
        settings = dict(cutoff=DEFAULT_CUTOFF, step=1.0)
        files, rows = {}, []
        for tile in (0, RA_TILE):
            out = folder / f"mosaic_T{tile}.dftpc"
            seconds, _ = median_time(lambda: dftpcc.compress_file(tif, out, tile_size=tile, force=True, **settings),
                                     speed_repeats)
            files[tile] = (out, seconds)
        tiled, whole = files[RA_TILE][0], files[0][0]
        with dftpcc.open(tiled) as cmap:
            info = cmap.info()
            header_bytes = cmap.bytes_read
            g = cmap.grid
        tiles = info["tiles"]
        # The tile in the middle of the map: all its neighbours exist, so its coded window is full.
        ti, tj = tiles["tile_rows"] // 2, tiles["tile_cols"] // 2
        entry = next(t for t in tiles["tiles"] if (t["row"], t["col"]) == (ti, tj))
        r0, c0 = ti * RA_TILE, tj * RA_TILE
        r1, c1 = min(g.rows, r0 + RA_TILE), min(g.cols, c0 + RA_TILE)
        # The centres of the tile's first and last cells: the box touches that tile only.
        bbox = (g.x0 + (c0 + 0.5) * g.resolution, g.y0 + (r0 + 0.5) * g.dy,
                g.x0 + (c1 - 0.5) * g.resolution, g.y0 + (r1 - 0.5) * g.dy)
        measured = {}
        for tile, path in ((RA_TILE, tiled), (0, whole)):
            def open_decode() -> tuple[Any, int]:
                with dftpcc.open(path, max_cells=TRUSTED_CELLS) as cmap:
                    dem = cmap.read_dem(bbox=bbox)
                    return dem, cmap.bytes_read
            both_s, (dem, read) = median_time(open_decode, repeats)
            with dftpcc.open(path, max_cells=TRUSTED_CELLS) as cmap:
                decode_s, _ = median_time(lambda: cmap.read_dem(bbox=bbox), repeats)
            with dftpcc.open(path, max_cells=TRUSTED_CELLS) as cmap:
                whole_s, full = median_time(lambda: cmap.read_dem(), speed_repeats)
            measured[tile] = dict(both=both_s, decode=decode_s, read=read, cells=int(dem.mask.sum()),
                                  whole=whole_s, size=path.stat().st_size, full=full)
        # The tile read alone equals the same cells of the whole decode.
        same = np.allclose(measured[RA_TILE]["full"].heights[r0:r1, c0:c1], dem_heights(tiled, bbox),
                           rtol=0, atol=1e-9)
        t, u = measured[RA_TILE], measured[0]
        budget = RA_MAX_BYTES_FACTOR * entry["bytes"] + header_bytes
        rows = [
            ["map", f"Kepler mirrored {copies} x {copies} with {MOSAIC_OFFSET_M:g} m offsets: {shape[0]} x "
                    f"{shape[1]} = {cells / 1e6:.1f} M cells, float32 GeoTIFF (built in {build_s:.1f} s)", ""],
            ["setting", f"f_c {settings['cutoff']:g}, step {settings['step']:g} m; tiled: T = {RA_TILE}, "
                        f"{tiles['tile_rows']} x {tiles['tile_cols']} tiles", ""],
            ["file bytes (tiled / untiled)", f"{t['size']:,} / {u['size']:,} ({t['size'] / u['size']:.3f})", ""],
            ["compress wall s (tiled / untiled, from the GeoTIFF)",
             f"{files[RA_TILE][1]:.2f} / {files[0][1]:.2f} ({cells / files[RA_TILE][1] / 1e6:.2f} / "
             f"{cells / files[0][1] / 1e6:.2f} M cells/s)", ""],
            [f"tile ({ti}, {tj}), {r1 - r0} x {c1 - c0} cells: open + decode, median of {repeats}",
             f"{1e3 * t['both']:.2f} ms (untiled file, same bbox: {1e3 * u['both']:.1f} ms)",
             f"< {1e3 * RA_MAX_SECONDS:g} ms {verdict(t['both'] < RA_MAX_SECONDS)}"],
            ["decode alone (file already open), median of %d" % repeats,
             f"{1e3 * t['decode']:.2f} ms (untiled: {1e3 * u['decode']:.1f} ms)",
             f"< {1e3 * RA_MAX_SECONDS:g} ms {verdict(t['decode'] < RA_MAX_SECONDS)}"],
            ["bytes read (open + one tile), `bytes_read`",
             f"{t['read']:,} = header and base layer {header_bytes:,} + {t['read'] - header_bytes:,}; the tile's own "
             f"bytes (`info()['tiles']`) {entry['bytes']:,}; untiled file: {u['read']:,}",
             f"< 2 x {entry['bytes']:,} + {header_bytes:,} = {budget:,.0f} {verdict(t['read'] < budget)}"],
            ["cells returned", f"{t['cells']:,} (equal to the whole decode's: {same})", ""],
            [f"whole decode, median of {speed_repeats}",
             f"tiled {t['whole']:.2f} s = {cells / t['whole'] / 1e6:.2f} M cells/s; untiled {u['whole']:.2f} s = "
             f"{cells / u['whole'] / 1e6:.2f} M cells/s (tiled / untiled time {t['whole'] / u['whole']:.2f})", ""],
        ]
    return markdown_table(["", "measured", "target"], rows)


def dem_heights(path: Path, bbox: tuple[float, ...]) -> np.ndarray:
    with dftpcc.open(path, max_cells=TRUSTED_CELLS) as cmap:
        return cmap.read_dem(bbox=bbox).heights


# --- 5. speed per tile side ----------------------------------------------------------------------

def speed_table(runs: list[MapRun], tiles: tuple[int, ...], repeats: int) -> str:
    """Compress and decompress at the parameters the untiled file chose at the middle level."""
    rows = []
    for run in runs:
        middle = run.levels[MIDDLE_LEVEL]
        whole = run.get(middle, 0)
        if whole is None:
            continue
        cutoff, step = whole.cutoff, whole.step
        cells = run.shape[0] * run.shape[1]
        base = None
        for tile in (0,) + tiles:
            if tile and not tiled_at(run, tile):
                rows.append([run.name, tile, "1 tile", "", "", "", "", ""])
                continue
            with warnings_as_notes(run.notes):
                enc, blob = median_time(lambda: dftpcc.compress(run.loaded.points, resolution=run.loaded.resolution,
                                                                cutoff=cutoff, step=step, tile_size=tile), repeats)
                dec, _ = median_time(lambda: dftpcc.open(blob).read_dem(), repeats)
            rc = run.get(middle, tile)
            base = base or (enc, dec)
            rows.append([run.name, tile or "untiled", f"{len(blob):,}", f"{enc:.2f} ({enc / base[0]:.2f})",
                         f"{cells / enc / 1e6:.2f}", f"{dec:.3f} ({dec / base[1]:.2f})", f"{cells / dec / 1e6:.2f}",
                         f"{rc.seconds:.1f}" if rc else ""])
    return markdown_table(["map", "T", "bytes", "compress s (/ untiled)", "compress M cells/s",
                           "decompress s (/ untiled)", "decompress M cells/s",
                           "rate-controlled compress s (one run, middle RMSE level)"], rows)


# --- the run ------------------------------------------------------------------------------------

def main(argv: list[str] | None = None) -> int:
    ap = run_arguments(__doc__.split("\n\n")[0],
                       "Gale and Kepler at T = 128 and 512 for the rate cost, a third of the maps for the seams, "
                       "a 2 x 2 mosaic, one run per timing")
    ap.add_argument("--no-figures", action="store_true", help="do not write docs/figures/tiles_error_map.png")
    ap.add_argument("--no-random-access", action="store_true", help="skip the mosaic (point 4)")
    args = ap.parse_args(argv)
    quick = args.quick
    tiles = QUICK_TILE_SIZES if quick else TILE_SIZES
    speed_repeats = 1 if quick else SPEED_REPEATS
    t_start = time.perf_counter()
    print(f"Measuring {library_label()}; {load_average()}.", flush=True)
    cost_cases = [c for c in COST_CASES if not quick or c.is_dem]
    maps = all_maps(args.data)
    if quick:
        cost_names = {c.name for c in cost_cases}
        maps = [c for c in maps if c.name in cost_names] + \
            [c for c in maps if c.name not in cost_names][::QUICK_EVERY]
    if args.files:
        # Unlike pick_cases, a name may be in one list only (a seam map is no rate-cost map).
        wanted = tuple(args.files)
        cost_cases = [c for c in cost_cases if c.name.startswith(wanted)]
        maps = [c for c in maps if c.name.startswith(wanted)]
    cost_names = [c.name for c in cost_cases]
    parts = [intro(tiles, quick)]
    print(parts[0], "\n", flush=True)

    # 1. rate cost (and the seams of these maps, from the same files)
    t0 = time.perf_counter()
    runs: dict[str, MapRun] = {}
    levels_of: dict[str, list[Target]] = {}
    for case in cost_cases:
        run = prepare(case, args.data)
        runs[case.name] = run
        levels_of[case.name] = [run.levels[MIDDLE_LEVEL]] if quick else run.levels
        cost_runs(run, tiles, levels_of[case.name])
    cost_s = time.perf_counter() - t0
    cost = [runs[n] for n in cost_names]
    if cost:
        text = ("### Rate cost of the tiles\n\n" + cost_preamble(cost) + "\n\n" + cost_summary(cost, tiles, levels_of)
                + "\n\n" + cost_tables(cost, tiles, levels_of) + f"\n\nTime for the rate-cost files: {cost_s:.0f} s.")
        parts.append(text)
        print(text, "\n", flush=True)

    # 2. seams on every map
    t0 = time.perf_counter()
    targets_of: dict[str, list[Target]] = {}
    seam_order = []
    for case in maps:
        if case.name in runs:
            run = runs[case.name]
            seam_tiles = (SEAM_TILE,)
        else:
            run = prepare(with_auto(case, args.data), args.data)
            runs[case.name] = run
            # A map one 256-cell tile holds is tried at 128 as well, so that every map shows its seams.
            seam_tiles = (SEAM_TILE,) if tiled_at(run, SEAM_TILE) else (min(TILE_SIZES), SEAM_TILE)
        seam_order.append(case.name)
        run.seam_tiles = seam_tiles
        if case.name in levels_of:  # the rate-cost files are measured for seams too, at every T
            size = seam_runs(run, seam_tiles)[-1]
            targets_of[case.name] = levels_of[case.name] + [run.bound, size]
        else:
            targets_of[case.name] = seam_runs(run, seam_tiles)
        print(f"  seams: {case.name} {run.shape} done ({time.perf_counter() - t0:.0f} s)", flush=True)
    seam_s = time.perf_counter() - t0
    if seam_order:
        table, summary = seam_table([runs[n] for n in seam_order], targets_of)
        text = ("### Seams\n\n" + seam_preamble(runs, seam_order) + "\n\n" + summary + "\n\n" + table
                + f"\n\nTime for the seam files: {seam_s:.0f} s.")
        parts.append(text)
        print(text, "\n", flush=True)

    # 3. figure
    if not args.no_figures and FIGURE_CASE in runs and FIGURE_TILE in tiles:
        caption = figure(runs[FIGURE_CASE], FIGURES / "tiles_error_map.png")
        if caption:
            parts.append(caption)
            print(caption, "\n", flush=True)

    # 4. random access
    if not args.no_random_access and not args.files:
        t0 = time.perf_counter()
        table = random_access(args.data, QUICK_MOSAIC if quick else MOSAIC,
                              QUICK_RA_REPEATS if quick else RA_REPEATS, speed_repeats)
        text = ("### Random access\n\nOne tile read from a file on disk by `dftpcc.open(path).read_dem(bbox=...)`, "
                "the bbox spanning the centres of the tile's corner cells (so it touches that tile only); times "
                "are wall medians on the shared machine. 'open + decode' opens the file (preamble, section table, "
                "tile 0: GEOM, PARM, STAT, TIDX, BASE) and decodes; 'decode alone' reuses one opened map. "
                "Bytes read: `CompressedMap.bytes_read` after opening and decoding the tile once.\n\n"
                + table + f"\n\nTime for the random-access part: {time.perf_counter() - t0:.0f} s.")
        parts.append(text)
        print(text, "\n", flush=True)

    # 5. speed
    if cost:
        t0 = time.perf_counter()
        text = ("### Speed per tile size\n\nFrom parsed points to bytes and back to the DEM (in memory), at the "
                "cutoff and step the untiled file chose for the middle RMSE level (no rate-control search), "
                f"wall medians of {speed_repeats} run(s); M cells/s of the whole grid (rows x cols). The last column "
                "is the rate-controlled compress of the rate-cost table (one run).\n\n"
                + speed_table(cost, tiles, speed_repeats) + f"\n\nTime for the speed table: {time.perf_counter() - t0:.0f} s.")
        parts.append(text)
        print(text, "\n", flush=True)

    notes = sorted({n for run in runs.values() for n in run.notes + run.loaded.notes if "MultiHeight" not in n})
    multi = [name for name, run in runs.items() if any("MultiHeight" in n for n in run.notes + run.loaded.notes)]
    if notes or multi:
        text = "Notes:\n\n" + "\n".join(f"- {n}" for n in notes)
        if multi:
            text += (f"\n- MultiHeightWarning (points more than a cell above or below their cell's height: the "
                     f"DEM keeps one height per cell) on {', '.join(multi)}.")
        parts.append(text)
    elapsed = time.perf_counter() - t_start
    finish_run(parts, args, "bench_tiles", "Tiled maps (issue 12)",
               f"{'Quick run (--quick)' if quick else 'Full run'}; run time {elapsed:.0f} s; "
               f"{load_average()} at the end.")
    return 0


def intro(tiles: tuple[int, ...], quick: bool) -> str:
    return (
        "Tiled maps (format 1.1) against the same map coded whole (`tile_size=0`), all measured in this run "
        f"with the compact profile's rate control. Tile sides T = {', '.join(map(str, tiles))} cells; "
        "a side whose tile holds the whole map writes it untiled, as format 1.0 ('1 tile', ratio 1.000). "
        "Errors are measured here, not read from the file: the decoded DEM (`read_dem()`) against the "
        "gridded DEM (mean height per cell) on every occupied cell of the whole map. "
        "DEMs are coded on their pixel grid, point clouds at bench_anchors' resolution "
        "(field 0.5 m ground class, coastal 2 m ground, mountain 2 m, redrocks 5 m), the forest at 0.5 m "
        "with every point (as bench_codec), every other cloud at the resolution `resolution='auto'` picks. "
        "RMSE levels: bench_anchors' (points at 1.25, 1.5, 3 x the gridding floor, i.e. a DEM RMSE of "
        "floor x sqrt(k² - 1); a DEM at 0.1, 0.3, 1 % of its RMS relief). Maximum error: "
        "benchmarks/max_error.py's middle bound (Gale 5 cm, Kepler 1 m, Davos 5 cm), else "
        f"{MAX_ERROR_UNITS:g} units (the gridding floor, or 0.1 % of the RMS relief) as bench_ratecontrol."
        + (" Quick run: fewer maps, tile sides, levels and repeats." if quick else ""))


def cost_preamble(runs: list[MapRun]) -> str:
    lines = [f"{r.name}: grid {r.shape[0]} x {r.shape[1]}, {int(r.mask.sum()):,} occupied cells, "
             f"{r.loaded.points.shape[0]:,} points, floor {fmt_m(r.floor)}" for r in runs]
    return ("Bytes of the tiled file over the untiled file at the same target, per tile side; "
            "'target held': the error this run measures over the whole map against the target "
            "(RMSE for an RMSE target, maximum error for a bound). The first table sums up.\n\n"
            + "\n".join(f"- {line}" for line in lines))


def seam_preamble(runs: dict[str, MapRun], order: list[str]) -> str:
    grids = "; ".join(f"{n} {runs[n].loaded.resolution:.4g} m" for n in order)
    return (f"Seam ratio: RMSE of the cells within {SEAM_BAND} cells of an internal tile edge (a cell whose "
            f"centre lies under {SEAM_BAND} cells from a row or column edge at a multiple of T) over the "
            "RMSE of the other cells. Both sides keep only the interior: occupied cells more than "
            f"{SEAM_BAND} cells from the grid's edge and from any empty cell (the map's own border has "
            f"errors of its own). Target ≤ {MAX_SEAM_RATIO:g} (issue 12). Each map at T = {SEAM_TILE} (and "
            f"at {min(TILE_SIZES)} when one {SEAM_TILE}-cell tile holds it; the rate-cost maps at every T), "
            "at three targets: the middle RMSE level, the maximum error, and a size target of the bits per "
            "point the untiled file takes at the middle RMSE level (its 'vs untiled' column: the tiled "
            f"file's RMSE over the untiled file's at equal size). 'Same cells, untiled file': the ratio on the same cells of the untiled file at the same target, where this run made one: what the terrain and the coding give without any tile edge there. {', '.join(SAME_MAP)} repeats "
            f"{', '.join(SAME_MAP.values())}'s points and is left out. Resolutions: {grids}.")


if __name__ == "__main__":
    raise SystemExit(main())
