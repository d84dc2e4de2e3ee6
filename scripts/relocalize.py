#!/usr/bin/env python3
"""Can the rover still localize? Writes docs/relocalization.md and docs/figures/reloc_*.png.

    python scripts/relocalize.py            (or: make relocalize; 12-16 min on the shared 2-core box)
    python scripts/relocalize.py --quick    (fewer scans and settings, a few minutes; not for the docs)

Per terrain (Mars Gale, Moon Kepler and Davos scaled to 1 m cells, the IGN
field's ground points), lidar scans are ray-cast on the terrain's bilinear
surface at random poses (fixed seeds), and each is registered with small_gicp
GICP from a guess 0.5 m and 5 degrees off against: the surface itself
(densely sampled, the reference), the DEM's cells as points, and maps rebuilt
by dftpcc at cutoffs 0-0.95 and rate-control targets, on the DEM's own 1 m
cells and on 0.1 m cells, plus the decoded surface densified 2x and 4x.
Every number in the document is measured in this run.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

import dftpcc
from dftpcc.dem import DEM, Grid
from dftpcc.encoder import encode_dem, grid_points
from dftpcc.experiments import relocalize as rl
from dftpcc.experiments import rover
from dftpcc.experiments.figures import _figure, _save
from dftpcc.files import dem_from_geotiff
from dftpcc.fill import fill_empty
from dftpcc.params import Params
from dftpcc.rebuild import dem_to_dense_points, dem_to_points

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
DOC = ROOT / "docs" / "relocalization.md"
FIGURES = ROOT / "docs" / "figures"

#: Side of the square map every setting is built on, metres (local, after scaling).
WINDOW_M = 160.0
#: Side of the square at the window's centre where scan poses are drawn, metres.
POSE_BOX_M = 40.0
#: Scans per terrain, and seeds of the poses and of the initial guesses.
SCANS = 20
SCAN_SEED = 1
GUESS_SEED = 2
#: Spacing of the samples of the true surface used as the reference map, metres (= the GICP voxel).
TRUTH_SPACING_M = 0.25
CUTOFFS = (0.0, 0.5, 0.8, 0.9, 0.95)
TARGETS: tuple[tuple[str, float], ...] = (
    ("target_rmse", 0.01), ("target_rmse", 0.05), ("target_max_error", 0.05), ("target_max_error", 0.2),
    ("target_bpp", 1.0), ("target_bpp", 0.2))
#: Settings tried on 0.1 m cells (each file of a 2.6 M-cell grid costs seconds to make).
FINE_CUTOFFS = (0.0, 0.8, 0.9, 0.95)
FINE_TARGETS: tuple[tuple[str, float], ...] = (("target_rmse", 0.01), ("target_bpp", 0.2))
DENSIFY = (2, 4)
DENSIFY_CUTOFFS = (0.0, 0.8, 0.9, 0.95)
#: Cutoffs at which scans are also cast on the rebuilt map itself.
SELF_CUTOFFS = (0.8, 0.9, 0.95)
#: A fine fixed quantizer step (metres): the low-pass without the quantizer's error.
FINE_STEP_M = 1e-4
#: Cells from the map's edge counted as its border when splitting the rebuilt map's error.
BORDER_CELLS = 10
#: Ray-caster timing: scans per sensor.
TIMING_SCANS = 5


@dataclass
class TerrainCase:
    name: str
    label: str
    surface: rover.Surface
    scaling: str
    native_m: float
    cloud: np.ndarray | None = None  # a real survey's points (local), when the terrain is one


def _dem_case(name: str, label: str, path: Path, cell_m: float = 1.0) -> TerrainCase:
    dem, _ = dem_from_geotiff(path)
    scale = cell_m / dem.grid.resolution
    surface = rover.Surface.from_dem(dem, scale=scale)
    scaling = "none (1 m cells)" if math.isclose(scale, 1.0) else (
        f"all three axes x {scale:.4g} ({dem.grid.resolution:.3g} m cells -> {cell_m:g} m; slopes unchanged)")
    return TerrainCase(name, label, surface, scaling, cell_m)


def _field_case(path: Path, cell_m: float = 1.0) -> TerrainCase:
    pts = dftpcc.read(path, classes=[2]).points
    lo = pts.min(axis=0)
    local = pts - np.array([lo[0], lo[1], pts[:, 2].mean()])
    dem = grid_points(local, Params(resolution=cell_m))
    # Holes inside the footprint (between scan lines) take the push-pull fill,
    # so rays do not vanish into them; outside the footprint stays empty.
    from scipy import ndimage

    inside = ndimage.binary_fill_holes(dem.mask)
    heights = np.where(inside, fill_empty(dem.heights, dem.mask, method="smooth"), np.nan)
    # The surface's nodes are the cell centres, which sit at the grid's x0 + 0.5 cell.
    g = dem.grid
    local[:, 0] -= g.x0
    local[:, 1] -= g.y0
    local[:, 2] -= g.z0
    surface = rover.Surface(heights, cell_m)
    return TerrainCase("field", "IGN field (ground, 1 m grid)", surface, "none (real points, gridded at 1 m)",
                       cell_m, cloud=local)


def terrains() -> list[TerrainCase]:
    return [
        _dem_case("gale", "Mars Gale (HiRISE 1 m)", DATA / "dems" / "mars_gale_1m.tif"),
        _dem_case("kepler", "Moon Kepler (LOLA 47.7 m)", DATA / "dems" / "moon_kepler_lola_48m.tif"),
        _dem_case("davos", "Earth Davos (10 m)", DATA / "dems" / "earth_davos_10m.tif"),
        _field_case(DATA / "pointclouds" / "field_gentle_ign.laz"),
    ]


def _window(case: TerrainCase) -> tuple[float, float, float, float]:
    """The WINDOW_M square around the centroid of the valid nodes (the map every setting is built on)."""
    pts = case.surface.points()
    cx, cy = np.median(pts[:, 0]), np.median(pts[:, 1])
    half = 0.5 * WINDOW_M
    # Snapped to the node lattice, so the DEM's own cells fill the window exactly.
    s = case.surface.spacing
    x_lo = math.floor((cx - half) / s) * s
    y_lo = math.floor((cy - half) / s) * s
    return (x_lo, x_lo + WINDOW_M, y_lo, y_lo + WINDOW_M)


def _in(points: np.ndarray, window: tuple[float, float, float, float]) -> np.ndarray:
    x_lo, x_hi, y_lo, y_hi = window
    keep = (points[:, 0] >= x_lo) & (points[:, 0] < x_hi) & (points[:, 1] >= y_lo) & (points[:, 1] < y_hi)
    return points[keep]


def _native_dem(case: TerrainCase, window: tuple[float, float, float, float]) -> DEM:
    """The DEM's own cells in the window, as a DEM in the local frame (cell centres on the nodes)."""
    s = case.surface.spacing
    x_lo, x_hi, y_lo, y_hi = window
    j0, i0 = int(round(x_lo / s)), int(round(y_lo / s))
    n = int(round(WINDOW_M / s))
    h = case.surface.heights[i0:i0 + n, j0:j0 + n]
    mask = np.isfinite(h)
    grid = Grid(x0=j0 * s, y0=i0 * s, z0=0.0, resolution=s, rows=h.shape[0], cols=h.shape[1])
    return DEM(grid=grid, heights=np.where(mask, h, 0.0), mask=mask)


def _jittered(case: TerrainCase, window: tuple[float, float, float, float], cell: float,
              rng: np.random.Generator) -> np.ndarray:
    """One sample of the true surface at a random spot in every ``cell`` of the window (a lidar-like map)."""
    x_lo, x_hi, y_lo, y_hi = window
    n = int(round(WINDOW_M / cell))
    gx, gy = np.meshgrid(x_lo + cell * np.arange(n), y_lo + cell * np.arange(n))
    x = gx.ravel() + rng.uniform(0, cell, gx.size)
    y = gy.ravel() + rng.uniform(0, cell, gy.size)
    z = case.surface.height(x, y)
    keep = np.isfinite(z)
    return np.column_stack([x[keep], y[keep], z[keep]])


def _embed(surface: rover.Surface, native: DEM, decoded: DEM) -> rover.Surface:
    """The surface of a DEM decoded on the native window grid, in the truth's frame (NaN outside the window)."""
    s = surface.spacing
    i0, j0 = int(round(native.grid.y0 / s)), int(round(native.grid.x0 / s))
    heights = np.full(surface.shape, np.nan)
    heights[i0:i0 + decoded.grid.rows, j0:j0 + decoded.grid.cols] = np.where(
        decoded.mask, decoded.heights + decoded.grid.z0, np.nan)
    return rover.Surface(heights, s)


def _errors_by_band(rebuilt: DEM, truth: rover.Surface) -> tuple[float, float]:
    """RMS height error (metres) of a rebuilt DEM against the true surface: border band, interior."""
    rows, cols = np.nonzero(rebuilt.mask)
    x, y = rebuilt.grid.centres(rows, cols)
    err = rebuilt.heights[rows, cols] + rebuilt.grid.z0 - truth.height(x, y)
    edge = np.minimum.reduce([rows, cols, rebuilt.grid.rows - 1 - rows, rebuilt.grid.cols - 1 - cols])
    ok = np.isfinite(err)
    border = ok & (edge < BORDER_CELLS)
    inner = ok & (edge >= BORDER_CELLS)
    rms = lambda m: float(np.sqrt(np.mean(err[m] ** 2))) if m.any() else float("nan")  # noqa: E731
    return rms(border), rms(inner)


def _row(case: TerrainCase, series: str, cell: float, setting: str, points: np.ndarray, scans: list[rl.Scan],
         *, data: bytes | None = None, count: int | None = None, rebuilt: DEM | None = None,
         extra: dict[str, Any] | None = None) -> dict[str, Any]:
    t0 = time.perf_counter()
    outcome = rl.relocalize_map(points, scans, seed=GUESS_SEED)
    row: dict[str, Any] = {"terrain": case.name, "series": series, "cell_m": cell, "setting": setting,
                           "map_points": int(points.shape[0]), **outcome.summary(),
                           "bytes": len(data) if data is not None else None,
                           "bpp": 8.0 * len(data) / count if data is not None and count else None,
                           "reg_s": (time.perf_counter() - t0) / len(scans)}
    if rebuilt is not None:
        row["border_rmse_m"], row["inner_rmse_m"] = _errors_by_band(rebuilt, case.surface)
    if extra:
        row.update(extra)
    return row


def _settings(cutoffs: tuple[float, ...], targets: tuple[tuple[str, float], ...]) -> list[tuple[str, dict[str, Any]]]:
    out = [(f"f_c {c:g}", {"cutoff": c}) for c in cutoffs]
    out += [(f"{name.replace('target_', '--target-').replace('_', '-')} {value:g}", {name: value})
            for name, value in targets]
    return out


def run_terrain(case: TerrainCase, *, quick: bool, show: Callable[[str], None]) -> tuple[list[dict[str, Any]], dict]:
    window = _window(case)
    x_lo, x_hi, y_lo, y_hi = window
    cx, cy = 0.5 * (x_lo + x_hi), 0.5 * (y_lo + y_hi)
    box = (cx - POSE_BOX_M / 2, cx + POSE_BOX_M / 2, cy - POSE_BOX_M / 2, cy + POSE_BOX_M / 2)
    n_scans = 6 if quick else SCANS
    t0 = time.perf_counter()
    scans = rl.simulate_scans(case.surface, n_scans, lidar=rover.LIDARS["vlp16"], seed=SCAN_SEED, window=box)
    meta = {"window": window, "scans": n_scans, "scan_points": float(np.mean([s.points.shape[0] for s in scans])),
            "simulate_s": time.perf_counter() - t0, "scaling": case.scaling, "label": case.label}
    rows: list[dict[str, Any]] = []

    def add(row: dict[str, Any]) -> None:
        rows.append(row)
        show(f"  {case.name:7s} {row['series']:12s} {row['cell_m']:<5g} {row['setting']:24s} "
             f"bpp {row['bpp'] if row['bpp'] is not None else float('nan'):8.4f}  success {100 * row['success']:5.1f} %"
             f"  coarse {100 * row['coarse']:5.1f} %  median {1000 * row['median_m']:8.1f} mm "
             f"{row['median_deg']:.3f} deg")

    add(_row(case, "reference", TRUTH_SPACING_M, "true surface, 0.25 m samples",
             case.surface.sample(TRUTH_SPACING_M, window=window), scans))
    add(_row(case, "reference", case.native_m, "DEM cells as points", _in(case.surface.points(), window), scans))
    if case.cloud is not None:
        add(_row(case, "reference", 0.0, "survey's ground points", _in(case.cloud, window), scans))

    # Grids: the native 1 m cells (a DEM's own, or the field's points gridded at 1 m), and 0.1 m (DEMs) or
    # 0.5 m (the field, which has about 5 points per square metre).
    rng = np.random.default_rng(SCAN_SEED)
    fine_cell = 0.5 if case.cloud is not None else 0.1
    grids: list[tuple[str, float, DEM, int]] = []
    if case.cloud is not None:
        pts = _in(case.cloud, window)
        for cell in (case.native_m, fine_cell):
            grids.append(("grid", cell, grid_points(pts, Params(resolution=cell)), pts.shape[0]))
    else:
        native = _native_dem(case, window)
        grids.append(("grid", case.native_m, native, int(native.mask.sum())))
        if not quick:
            pts = _jittered(case, window, fine_cell, rng)
            grids.append(("grid", fine_cell, grid_points(pts, Params(resolution=fine_cell)), pts.shape[0]))
    for _, cell, dem, count in grids:
        fine = cell < case.native_m - 1e-9
        add(_row(case, "grid only", cell, "no codec", dem_to_points(dem), scans, rebuilt=dem))
        settings = (_settings(FINE_CUTOFFS, FINE_TARGETS) if fine else _settings(CUTOFFS, TARGETS))
        if quick:
            settings = settings[2:4]
        for setting, options in settings:
            t = time.perf_counter()
            data = encode_dem(dem, Params(**options), point_count=count)
            encode_s = time.perf_counter() - t
            cmap = dftpcc.open(data)
            decoded = cmap.read_dem()
            extra = {"encode_s": encode_s, "cutoff_used": cmap.params.cutoff, "step_m": cmap.params.step,
                     "dem_rmse_m": cmap.header.stats.get("dem_rmse_m")}
            add(_row(case, "dftpcc", cell, setting, dem_to_points(decoded), scans, data=data, count=count,
                     rebuilt=decoded, extra=extra))
            if not fine and "cutoff" in options and options["cutoff"] in DENSIFY_CUTOFFS and not quick:
                for k in DENSIFY:
                    add(_row(case, f"densify {k}", cell, setting, dem_to_dense_points(decoded, k), scans,
                             data=data, count=count, extra=extra))
            if not fine and options.get("cutoff") in SELF_CUTOFFS and case.cloud is None and not quick:
                # Scans cast on the rebuilt map itself, registered against it: a test that cannot see
                # what the codec changed (a hypothesis for the first prototype's small errors).
                rebuilt_surface = _embed(case.surface, dem, decoded)
                own = rl.simulate_scans(rebuilt_surface, len(scans), lidar=rover.LIDARS["vlp16"], seed=SCAN_SEED,
                                        window=box)
                add(_row(case, "self-scans", cell, setting, dem_to_points(decoded), own, data=data, count=count,
                         extra=extra))
            if not fine and options.get("cutoff") == 0.9 and not quick:
                data = encode_dem(dem, Params(cutoff=0.9, step=FINE_STEP_M), point_count=count)
                decoded = dftpcc.open(data).read_dem()
                add(_row(case, "fine step", cell, f"f_c 0.9, step {1000 * FINE_STEP_M:g} mm", dem_to_points(decoded),
                         scans, data=data, count=count, rebuilt=decoded))
    return rows, meta


def time_raycaster(case: TerrainCase) -> dict[str, dict[str, float]]:
    """Median and range of the per-scan ray-casting time per sensor, seconds."""
    out = {}
    rng = np.random.default_rng(0)
    window = _window(case)
    for name in ("vlp16", "hdl32", "hdl64"):
        lidar = rover.LIDARS[name]
        x_lo, x_hi, y_lo, y_hi = window
        cx, cy = 0.5 * (x_lo + x_hi), 0.5 * (y_lo + y_hi)
        times, counts = [], []
        for k in range(TIMING_SCANS):
            pose = rover.sensor_pose(case.surface, cx + 3.0 * k, cy, 0.4 * k, mount_height=lidar.mount_height)
            # CPU time of this process (the ray-caster is single-threaded numpy): other jobs on a
            # shared machine inflate the wall time, not this.
            t = time.process_time()
            pts = rover.cast_scan(case.surface, pose, lidar, rng=rng)
            times.append(time.process_time() - t)
            counts.append(pts.shape[0])
        out[name] = {"rays": int(lidar.directions().shape[0]), "returns": float(np.mean(counts)),
                     "load": os.getloadavg()[0],
                     "median_s": float(np.median(times)), "min_s": float(min(times)), "max_s": float(max(times))}
    return out


def check_64(case: TerrainCase) -> list[dict[str, Any]]:
    """Gale with a 64-beam sensor: does the denser scan change the picture?"""
    window = _window(case)
    x_lo, x_hi, y_lo, y_hi = window
    cx, cy = 0.5 * (x_lo + x_hi), 0.5 * (y_lo + y_hi)
    box = (cx - POSE_BOX_M / 2, cx + POSE_BOX_M / 2, cy - POSE_BOX_M / 2, cy + POSE_BOX_M / 2)
    scans = rl.simulate_scans(case.surface, 10, lidar=rover.LIDARS["hdl64"], seed=SCAN_SEED, window=box)
    rows = [_row(case, "reference", TRUTH_SPACING_M, "true surface, 0.25 m samples",
                 case.surface.sample(TRUTH_SPACING_M, window=window), scans)]
    native = _native_dem(case, window)
    for c in (0.0, 0.8, 0.9):
        data = encode_dem(native, Params(cutoff=c))
        decoded = dftpcc.open(data).read_dem()
        rows.append(_row(case, "dftpcc", 1.0, f"f_c {c:g}", dem_to_points(decoded), scans, data=data,
                         count=int(native.mask.sum())))
        rows.append(_row(case, "densify 4", 1.0, f"f_c {c:g}", dem_to_dense_points(decoded, 4), scans, data=data,
                         count=int(native.mask.sum())))
    return rows


#: Georeferenced origins the pitfall check moves Gale to: its own (Mars equirectangular) and the field's (Lambert-93).
GEOREFERENCED_ORIGINS = {"Gale's own": (8142406.0, -276792.0, -4455.9), "Lambert-93": (484649.0, 6632629.0, 100.0)}


def pitfalls(case: TerrainCase) -> list[dict[str, Any]]:
    """The registration choices the document warns about, measured on Gale against the true surface (10 scans):
    GICP, point-to-plane ICP and point-to-point ICP in the local frame, and GICP in georeferenced coordinates."""
    sg = rl.require_small_gicp()
    window = _window(case)
    x_lo, x_hi, y_lo, y_hi = window
    cx, cy = 0.5 * (x_lo + x_hi), 0.5 * (y_lo + y_hi)
    box = (cx - POSE_BOX_M / 2, cx + POSE_BOX_M / 2, cy - POSE_BOX_M / 2, cy + POSE_BOX_M / 2)
    scans = rl.simulate_scans(case.surface, 10, lidar=rover.LIDARS["vlp16"], seed=SCAN_SEED, window=box)
    truth_map = case.surface.sample(TRUTH_SPACING_M, window=window)
    g = rl.Gicp()
    variants = [("GICP", "local", (0.0, 0.0, 0.0)), ("PLANE_ICP", "local", (0.0, 0.0, 0.0)),
                ("ICP", "local", (0.0, 0.0, 0.0))]
    variants += [("GICP", name, origin) for name, origin in GEOREFERENCED_ORIGINS.items()]
    out = []
    for kind, frame, origin in variants:
        shift = np.array(origin)
        target, tree = sg.preprocess_points(truth_map + shift, downsampling_resolution=g.voxel,
                                            num_neighbors=g.neighbours)
        rng = np.random.default_rng(GUESS_SEED)
        errors = []
        for scan in scans:
            truth = scan.pose.copy()
            truth[:3, 3] += shift
            T = rl.perturb(truth, rng)
            source, _ = sg.preprocess_points(scan.points, downsampling_resolution=g.voxel, num_neighbors=g.neighbours)
            for distance in g.correspondence:
                T = sg.align(target, source, tree, init_T_target_source=T, registration_type=kind,
                             max_correspondence_distance=distance, max_iterations=g.iterations).T_target_source
            errors.append(rl.pose_error(T, truth))
        t, r = (np.array(e) for e in zip(*errors))
        o = rl.Outcome(t, r)
        out.append({"method": kind, "frame": frame, **o.summary()})
    return out


# ---------------------------------------------------------------- the document

def _pct(x: float) -> str:
    return f"{100 * x:.0f} %"


def _mm(x: float) -> str:
    if x < 0.01:
        return f"{1000 * x:.1f} mm"
    return f"{1000 * x:.0f} mm" if x < 10 else f"{x:.1f} m"


def _bpp(x: float | None) -> str:
    return "-" if x is None else f"{x:.3g}"


def add_areas(rows: list[dict[str, Any]]) -> None:
    """Bits per square metre of map (file bits over the area of its occupied cells) and the shortest
    wavelength a cutoff keeps, 2 x cell / (1 - f_c) metres, for every row made from a file."""
    cells = {(r["terrain"], r["cell_m"]): r["map_points"] for r in rows if r["series"] == "grid only"}
    for r in rows:
        n = cells.get((r["terrain"], r["cell_m"]))
        if r.get("bytes") is not None and n:
            r["bits_m2"] = 8.0 * r["bytes"] / (n * r["cell_m"] ** 2)
        cutoff = r.get("cutoff_used")
        if cutoff is None and r["setting"].startswith("f_c "):
            cutoff = float(r["setting"].split()[1].rstrip(","))
        if cutoff is not None and r["cell_m"]:
            r["wavelength_m"] = 2.0 * r["cell_m"] / (1.0 - cutoff)


def _table(rows: list[dict[str, Any]]) -> list[str]:
    out = ["| map | cell | setting | bits/pt | bits/m² | shortest kept λ | success 10 cm/1° | coarse 2 m/5° | "
           "median error | median rot. | DEM RMSE border / interior |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        band = (f"{_mm(r['border_rmse_m'])} / {_mm(r['inner_rmse_m'])}" if "border_rmse_m" in r else "")
        cell = "-" if not r["cell_m"] else f"{r['cell_m']:g} m"
        lam = f"{r['wavelength_m']:.3g} m" if r.get("wavelength_m") else ""
        out.append(f"| {r['series']} | {cell} | {r['setting']} | {_bpp(r['bpp'])} | {_bpp(r.get('bits_m2'))} | "
                   f"{lam} | {_pct(r['success'])} | {_pct(r['coarse'])} | {_mm(r['median_m'])} | "
                   f"{r['median_deg']:.3f}° | {band} |")
    return out


def _smallest_passing(rows: list[dict[str, Any]], fraction: float = 0.95) -> dict[str, Any] | None:
    ok = [r for r in rows if r["bpp"] is not None and r["success"] >= fraction]
    return min(ok, key=lambda r: r["bpp"]) if ok else None


def plot(rows: list[dict[str, Any]], names: list[str]) -> list[Path]:
    paths = []
    for key, ylabel, fname, log in (("success", "scans within 10 cm and 1° (%)", "reloc_success.png", False),
                                    ("median_m", "median translation error (m)", "reloc_error.png", True)):
        fig = _figure(11, 3.2)
        axes = fig.subplots(1, len(names), sharey=True)
        for ax, name in zip(np.atleast_1d(axes), names):
            mine = [r for r in rows if r["terrain"] == name]
            for series, cell, style in (("dftpcc", None, "o-"), ("densify 2", None, "s--"), ("densify 4", None, "^--")):
                cells = sorted({r["cell_m"] for r in mine if r["series"] == series})
                for c in cells:
                    pts = sorted([(r["bpp"], r[key]) for r in mine if r["series"] == series and r["cell_m"] == c
                                  and r["setting"].startswith("f_c")])
                    if pts:
                        x, y = zip(*pts)
                        y = [100 * v for v in y] if key == "success" else y
                        ax.plot(x, y, style, ms=4, label=f"{series}, {c:g} m cells")
            ref = next(r for r in mine if r["series"] == "reference")
            ax.axhline(100 * ref[key] if key == "success" else ref[key], color="k", lw=0.8, ls=":",
                       label="true surface")
            ax.set_xscale("log")
            if log:
                ax.set_yscale("log")
            ax.set_title(name)
            ax.set_xlabel("bits per point")
            ax.legend(fontsize=5)
        np.atleast_1d(axes)[0].set_ylabel(ylabel)
        paths.append(_save(fig, FIGURES / fname))
    fig = _figure(11, 3.2)
    axes = fig.subplots(1, len(names), sharey=True)
    for ax, name in zip(np.atleast_1d(axes), names):
        for cell, style in sorted({(r["cell_m"], "o-") for r in rows if r["terrain"] == name and r["series"] == "dftpcc"}):
            pts = sorted((r["wavelength_m"], 100 * r["success"]) for r in rows if r["terrain"] == name
                         and r["series"] == "dftpcc" and r["cell_m"] == cell and r.get("wavelength_m")
                         and r["setting"].startswith("f_c"))
            if pts:
                x, y = zip(*pts)
                ax.plot(x, y, style, ms=4, label=f"{cell:g} m cells")
        ax.set_xscale("log")
        ax.set_title(name)
        ax.set_xlabel("shortest kept λ = 2 cell / (1 - f_c) (m)", fontsize=7)
        ax.legend(fontsize=6)
    np.atleast_1d(axes)[0].set_ylabel("scans within 10 cm and 1° (%)")
    paths.append(_save(fig, FIGURES / "reloc_wavelength.png"))
    return paths


def write_doc(rows: list[dict[str, Any]], metas: dict[str, dict], timing: dict[str, Any], rows64: list[dict],
              elapsed: float, command: str, pits: list[dict[str, Any]] | None = None) -> None:
    names = list(metas)
    lines = ["# Can the rover still localize?", "",
             f"Generated by `{command}` (`make relocalize`) in {elapsed / 60:.1f} min on {platform.machine()} "
             f"({platform.python_version()}, numpy {np.__version__}); every number below is measured in that run.",
             "", "## What is measured", "",
             f"- **Terrain.** Each DEM is the truth: its bilinear surface (`dftpcc.experiments.rover.Surface`), in a "
             f"local frame (metres from the DEM's corner, heights about its mean). Kepler and Davos are scaled to "
             f"rover size, all three axes by one factor so slopes stay: "
             + "; ".join(f"{metas[n]['label']}: {metas[n]['scaling']}" for n in names) + ". "
             f"The field's truth is its ground points (class 2) gridded at 1 m, holes inside the footprint filled.",
             f"- **Map.** A {WINDOW_M:g} m square around the middle of the valid ground; every map below covers "
             f"exactly it.",
             f"- **Scans.** {SCANS} per terrain (seed {SCAN_SEED}) at random positions and headings in the central "
             f"{POSE_BOX_M:g} m square, a VLP-16 (16 beams, ±15°, 0.2° steps, 100 m, 3 cm range noise) "
             f"1.5 m above the ground, rolled and pitched with it; scans are instantaneous.",
             f"- **Registration.** small_gicp GICP (`relocalize.Gicp`: scans and maps voxel-downsampled to 0.25 m, "
             f"covariances from 20 neighbours, correspondence distance 5 m, then 2 m, then 1 m, 30 iterations "
             f"each), in a local frame, from an initial guess {rl.OFFSET_M:g} m (random 3-D direction) and "
             f"{rl.OFFSET_DEG:g}° (random axis) off (seed {GUESS_SEED}: the same guesses for every map). GICP "
             f"because point-to-plane and point-to-point ICP barely leave the initial guess (measured at the end; "
             f"KISS-ICP, an odometry that drifts, was not tried). "
             f"Success: within {rl.SUCCESS_M * 100:g} cm and {rl.SUCCESS_DEG:g}°; coarse: within "
             f"{rl.COARSE_M:g} m and {rl.COARSE_DEG:g}°.",
             "- **Maps.** *reference*: the true surface sampled every 0.25 m (what GICP can do at best), the DEM's "
             "cells as points, and for the field its survey points. *grid only*: the gridded DEM, one point per "
             "cell, no codec. *dftpcc*: `encode_dem` at a cutoff (automatic step) or a rate-control target, decoded, "
             "one point per cell (`dem_to_points`, what `dftpcc decompress` writes). *densify K*: the same files "
             "rebuilt with `dem_to_dense_points(dem, K)`, K x K bilinear samples of the decoded surface per cell. "
             f"*self-scans*: scans cast on the rebuilt map itself and registered against it (which cannot see what "
             f"the codec changed). *fine step*: f_c 0.9 with a {1000 * FINE_STEP_M:g} mm step, the low-pass without the quantizer. "
             f"Cells: the DEMs' own 1 m cells, and 0.1 m cells gridded from one sample of the true surface at a "
             f"random spot in each cell; the field at 1 m and 0.5 m from its points. Bits per point: file bytes x 8 "
             f"over the points (cells, or survey points) the map was made from. DEM RMSE against the true surface, "
             f"in the outer {BORDER_CELLS} cells of the map and inside.",
             "", "## Ray-caster speed", "",
             "All rays of a scan march together over the surface: each advances by its height above the ground "
             "over the surface's slope bound (a step that cannot pass under the ground), at least half a cell; "
             "the step that ends below the ground is refined by 14 bisections and a linear interpolation "
             "(noise-free returns lie within 1e-6 m of the surface); a ray flying above the highest ground within "
             "32, 8 or 2 cells (a max filter of the DEM) skips that far at once. CPU time per scan (one thread), "
             f"median (range) of {TIMING_SCANS} scans at the middle of each map, measured with "
             "`--from-json ... --retime`; the last column is the machine's 1-minute load average then (2 cores, "
             "shared with other jobs):", "",
             "| terrain | " + " | ".join(f"{k} ({timing[names[0]][k]['rays']:,} rays)" for k in timing[names[0]])
             + " | load |",
             "|---|" + "---|" * len(timing[names[0]]) + "---|"]
    for n in names:
        lines.append(f"| {n} | " + " | ".join(
            f"{1000 * v['median_s']:.0f} ms ({1000 * v['min_s']:.0f}-{1000 * v['max_s']:.0f}), {v['returns']:,.0f} returns"
            for v in timing[n].values()) + f" | {max(v.get('load', float('nan')) for v in timing[n].values()):.1f} |")
    lines += ["", "The numpy prototype took 0.3 s per 16-beam and 1.6 s per 64-beam scan (its ray counts were not "
              "recorded). `write_bag` reports the wall time it spends ray-casting, and "
              "`python -m dftpcc.experiments.rover` prints it per scan.", ""]

    lines += ["## What keeps 95 % of scans within 10 cm and 1°", "",
              "The smallest file among the settings tried (plain rebuild, one point per cell) per terrain and cell "
              "size, with the reference for comparison:", "",
              "| terrain | true surface | cells | smallest setting with >= 95 % | bits/pt | bits/m² | shortest kept λ | "
              "median error | next smaller setting tried |", "|---|---|---|---|---|---|---|---|---|"]
    for n in names:
        mine = [r for r in rows if r["terrain"] == n]
        ref = next(r for r in mine if r["series"] == "reference")
        for cell in sorted({r["cell_m"] for r in mine if r["series"] == "dftpcc"}, reverse=True):
            series = [r for r in mine if r["series"] == "dftpcc" and r["cell_m"] == cell]
            best = _smallest_passing(series)
            smaller = sorted((r for r in series if best is None or r["bpp"] < best["bpp"]), key=lambda r: -r["bpp"])
            nxt = (f"{smaller[0]['setting']}: {_pct(smaller[0]['success'])} at {smaller[0]['bpp']:.3g} bits/pt"
                   if smaller else "-")
            if best:
                lam = f"{best['wavelength_m']:.3g} m" if best.get("wavelength_m") else ""
                lines.append(f"| {n} | {_pct(ref['success'])}, {_mm(ref['median_m'])} | {cell:g} m | {best['setting']} | "
                             f"{best['bpp']:.3g} | {best.get('bits_m2', float('nan')):.3g} | {lam} | "
                             f"{_mm(best['median_m'])} | {nxt} |")
            else:
                top = max(series, key=lambda r: r["success"])
                lines.append(f"| {n} | {_pct(ref['success'])}, {_mm(ref['median_m'])} | {cell:g} m | none (best: "
                             f"{top['setting']}, {_pct(top['success'])}) | | | | | |")
    lines += ["", "## Results per terrain", "",
              "![success](figures/reloc_success.png)", "", "![error](figures/reloc_error.png)", "",
              "![wavelength](figures/reloc_wavelength.png)", ""]
    for n in names:
        mine = [r for r in rows if r["terrain"] == n]
        m = metas[n]
        lines += [f"### {m['label']}", "",
                  f"{m['scans']} scans, {m['scan_points']:,.0f} returns each on average.", ""]
        lines += _table(mine)
        lines.append("")
        for cell in sorted({r["cell_m"] for r in mine if r["series"] == "dftpcc"}):
            for series in ("dftpcc", "densify 2", "densify 4"):
                best = _smallest_passing([r for r in mine if r["series"] == series and r["cell_m"] == cell])
                if best:
                    lines.append(f"- {cell:g} m cells, {series}: 95 % of scans within 10 cm and 1° down to "
                                 f"**{best['setting']}** at **{best['bpp']:.3g} bits/point** ({best.get('bits_m2', float('nan')):.3g} bits/m²).")
                elif any(r["series"] == series and r["cell_m"] == cell for r in mine):
                    lines.append(f"- {cell:g} m cells, {series}: no setting keeps 95 % of scans within 10 cm and 1°.")
        lines.append("")
    if rows64:
        lines += ["### Gale with a 64-beam sensor (HDL-64E, 10 scans)", ""] + _table(rows64) + [""]
    if pits:
        lines += ["### Registration pitfalls (Gale, true surface, 10 scans, same guesses)", "",
                  "The same three rounds of small_gicp with each method; \"georeferenced\": the map and poses moved "
                  "to the given origin before registering, as a map in its CRS would be. Translation error before "
                  f"registration: {rl.OFFSET_M:g} m.", "",
                  "| method | frame | success 10 cm/1° | median error | median rot. |", "|---|---|---|---|---|"]
        lines += [f"| {p['method']} | {p['frame']} | {_pct(p['success'])} | {_mm(p['median_m'])} | "
                  f"{p['median_deg']:.3f}° |" for p in pits]
        lines.append("")
    DOC.write_text("\n".join(lines) + "\n" + ANALYSIS_MARKER + "\n")


#: The hand-written analysis below this line in the document is kept when the tables are regenerated.
ANALYSIS_MARKER = "<!-- analysis: written from the tables above; kept by scripts/relocalize.py -->"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer scans and settings; writes to --out only")
    parser.add_argument("--out", type=Path, help="also write the measured rows as JSON here")
    parser.add_argument("--only", help="comma-separated terrain names (gale,kepler,davos,field)")
    parser.add_argument("--from-json", type=Path,
                        help="rewrite the document and figures from the rows a run saved with --out (no measuring)")
    parser.add_argument("--retime", action="store_true",
                        help="with --from-json: measure the ray-caster again (on a quiet machine)")
    parser.add_argument("--pitfalls", action="store_true",
                        help="with --from-json: measure the registration pitfalls again (done once when missing)")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    cases = terrains()
    if args.only:
        cases = [c for c in cases if c.name in args.only.split(",")]
    if args.from_json:
        saved = json.loads(args.from_json.read_text())
        rows, metas, timing, rows64 = saved["rows"], saved["metas"], saved["timing"], saved["rows64"]
        elapsed = saved.get("elapsed_s", 0.0)
        if args.retime:
            timing = {case.name: time_raycaster(case) for case in cases}
            saved["timing"] = timing
        if args.pitfalls or "pitfalls" not in saved:
            saved["pitfalls"] = pitfalls(next(c for c in cases if c.name == "gale"))
        args.from_json.write_text(json.dumps(saved, indent=1, default=float))
        return _write_all(rows, metas, timing, rows64, elapsed, saved["pitfalls"])
    rows = []
    metas = {}
    timing = {}
    for case in cases:
        print(f"{case.name}: {case.surface.shape} nodes of {case.surface.spacing:g} m", flush=True)
        timing[case.name] = time_raycaster(case)
        r, meta = run_terrain(case, quick=args.quick, show=lambda line: print(line, flush=True))
        rows += r
        metas[case.name] = meta
    gale = next((c for c in cases if c.name == "gale"), None)
    rows64 = [] if args.quick or gale is None else check_64(gale)
    pits = [] if args.quick or gale is None else pitfalls(gale)
    for r in rows64:
        print(f"  hdl64 {r['series']} {r['setting']} success {r['success']:.2f} median {r['median_m']:.4f}")
    elapsed = time.perf_counter() - t0
    if args.out:
        args.out.write_text(json.dumps({"rows": rows, "metas": metas, "timing": timing, "rows64": rows64,
                                        "pitfalls": pits, "elapsed_s": elapsed}, indent=1, default=float))
    if args.quick:
        print(f"quick run: {elapsed:.0f} s; docs not written")
        return 0
    return _write_all(rows, metas, timing, rows64, elapsed, pits)


def _write_all(rows: list[dict[str, Any]], metas: dict[str, dict], timing: dict[str, Any], rows64: list[dict],
               elapsed: float, pits: list[dict[str, Any]]) -> int:
    add_areas(rows)
    add_areas(rows64)
    analysis = ""
    if DOC.exists() and ANALYSIS_MARKER in DOC.read_text():
        analysis = DOC.read_text().split(ANALYSIS_MARKER, 1)[1]
    FIGURES.mkdir(parents=True, exist_ok=True)
    plot(rows, list(metas))
    write_doc(rows, metas, timing, rows64, elapsed, "python scripts/relocalize.py", pits)
    if analysis:
        DOC.write_text(DOC.read_text() + analysis.lstrip("\n"))
    print(f"{DOC} written in {elapsed / 60:.1f} min")
    return 0


if __name__ == "__main__":
    sys.exit(main())
