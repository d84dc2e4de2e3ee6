"""Experiments on real files: evaluate one map, sweep the cutoff, compare pictures.

The paper's evidence is a sweep of the cutoff ratio (its Fig. 5) and maps
side by side (its Fig. 6); this module runs both on any terrain, through the
real codec, and measures the result with :mod:`dftpcc.metrics`.

A sweep grids each input once (read, grid, rasterize) and then, per cutoff,
encodes that DEM with :func:`dftpcc.codec.encode_dem`, decodes the bytes and
measures them: the sizes in the CSV are those of real ``.dftpc`` files and
the errors those of what a decoder rebuilds. Re-running the fill and the
forward transform per cutoff inside ``encode_dem`` costs about 0.03 s on the
0.7 M-point field map (a 741 x 702 grid), against 0.1-0.5 s for the coding
itself, so reusing the spectrum would buy almost nothing and would need a
second copy of the encoder to stay exact. What is reused across cutoffs is
what costs: the DEM, the k-d tree of the original cloud and the x, y
interpolation weights (the occupied cells do not depend on the cutoff).
"""

from __future__ import annotations

import csv
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from . import metrics
from .codec import encode_dem, resolve_params
from .container import MAGIC
from .container import open as open_map
from .errors import InvalidInputError
from .formats import PointCloud, format_of, read
from .grid import DEM, fit_grid, rasterize
from .rebuild import dem_to_points

__all__ = [
    "DEFAULT_CUTOFFS",
    "SWEEP_COLUMNS",
    "Terrain",
    "parse_cutoffs",
    "load_points",
    "is_compressed",
    "evaluate_files",
    "sweep_points",
    "sweep",
    "write_csv",
    "read_csv",
    "run_sweep",
    "compare_points",
    "compare_file",
    "terrains",
    "format_row",
    "format_metrics",
    "jsonable",
]

#: The paper's Fig. 5 range: f_c from 0 to 0.95 in steps of 0.05.
DEFAULT_CUTOFFS: tuple[float, ...] = tuple(round(0.05 * i, 2) for i in range(20))
#: Fig. 6 of the paper shows these two cutoffs.
COMPARE_CUTOFFS: tuple[float, ...] = (0.8, 0.95)
#: Cutoffs closer than this are the same cutoff (parsing "0,0.1,...,0.9").
CUTOFF_TOLERANCE = 1e-9

#: Columns of sweep.csv, in order. Lengths in metres, sizes in bytes, times in seconds.
SWEEP_COLUMNS: tuple[str, ...] = (
    "terrain", "input", "profile", "resolution_m", "cutoff",
    "points_original", "points_rebuilt", "grid_rows", "grid_cols", "coef_count",
    "bytes", "mask_bytes", "coef_bytes", "bits_per_point", "step_m",
    "paper_rmse_m", "paper_rmse_3d_m", "vertical_rmse_m", "vertical_max_m", "vertical_p95_m",
    "d1_rmse_m", "d1_rmse_forward_m", "d1_rmse_backward_m", "d1_psnr_db", "psnr_peak_m",
    "chamfer_m", "hausdorff_m", "dem_rmse_m", "gridding_rmse_m",
    "grid_s", "encode_s", "decode_s", "metrics_s",
)
#: Columns that hold text; every other one is a number.
_TEXT_COLUMNS = {"terrain", "input", "profile"}

Row = dict[str, Any]
OnRow = Callable[[Row], None]


def _noop(_: Row) -> None:
    pass


@dataclass(frozen=True)
class Terrain:
    """One input of a sweep and how to grid it.

    Attributes
    ----------
    path : str or Path
        Any file :func:`dftpcc.read` reads (a GeoTIFF becomes a cloud of its pixel centres).
    resolution : float or 'auto'
        DEM cell size in metres.
    classes : tuple of int, optional
        LAS/LAZ classification codes to keep (2 = ground); ignored for other formats.
    label : str, optional
        Name in the CSV and the legend; default the file name without extension.
    """

    path: str | os.PathLike[str]
    resolution: float | str = "auto"
    classes: tuple[int, ...] | None = None
    label: str | None = None

    @property
    def name(self) -> str:
        return self.label or Path(self.path).stem


def terrains(paths: Sequence[str | os.PathLike[str]], resolutions: Sequence[float | str], *,
             classes: Sequence[int] | None = None) -> list[Terrain]:
    """One :class:`Terrain` per path: one resolution for all, or one per path.

    Raises
    ------
    InvalidInputError
        As many resolutions as paths are needed when more than one is given.
    """
    if not paths:
        raise InvalidInputError("no input file given")
    if len(resolutions) == 1:
        resolutions = list(resolutions) * len(paths)
    if len(resolutions) != len(paths):
        raise InvalidInputError(f"give one resolution, or one per input: {len(resolutions)} resolutions "
                                f"for {len(paths)} inputs")
    keep = tuple(classes) if classes is not None else None
    stems = [Path(p).stem for p in paths]
    # Two inputs named alike in different folders must stay apart in the CSV and the legend.
    labels = [f"{Path(p).parent.name}/{stem}" if stems.count(stem) > 1 else stem for p, stem in zip(paths, stems)]
    return [Terrain(path, res, keep, label) for path, res, label in zip(paths, resolutions, labels)]


def parse_cutoffs(text: str) -> tuple[float, ...]:
    """Cutoff ratios from ``"0,0.5,0.8"``; ``"0,0.1,...,0.9"`` expands the progression.

    An item ``...`` continues the arithmetic progression of the two values
    before it up to the value after it (which is included).

    Returns
    -------
    tuple of float
        Sorted, unique, each in [0, 1).

    Raises
    ------
    InvalidInputError
        Not numbers, a value outside [0, 1), or a ``...`` without two values
        before it and one after it.
    """
    items = [t.strip() for t in text.split(",") if t.strip()]
    values: list[float] = []
    i = 0
    while i < len(items):
        item = items[i]
        if item in ("...", "\u2026"):
            if len(values) < 2 or i + 1 >= len(items):
                raise InvalidInputError(f"'...' needs two cutoffs before it and one after: {text!r}")
            step = values[-1] - values[-2]
            stop = _cutoff_value(items[i + 1], text)
            if step <= 0:
                raise InvalidInputError(f"'...' needs increasing cutoffs before it: {text!r}")
            count = int(math.floor((stop - values[-1]) / step + CUTOFF_TOLERANCE))
            start = values[-1]
            values.extend(round(start + step * k, 10) for k in range(1, count + 1))
            i += 1
            continue
        values.append(_cutoff_value(item, text))
        i += 1
    if not values:
        raise InvalidInputError("no cutoff given")
    unique: list[float] = []
    for v in sorted(values):
        if not unique or v - unique[-1] > CUTOFF_TOLERANCE:
            unique.append(v)
    return tuple(unique)


def _cutoff_value(item: str, text: str) -> float:
    try:
        value = float(item)
    except ValueError:
        raise InvalidInputError(f"cutoffs must be numbers separated by commas, got {text!r}") from None
    if not 0.0 <= value < 1.0:
        raise InvalidInputError(f"a cutoff ratio is in [0, 1), got {value}")
    return value


def load_points(path: str | os.PathLike[str], *, classes: Sequence[int] | None = None) -> PointCloud:
    """Read a cloud, keeping ``classes`` when the file is LAS/LAZ (other formats have none)."""
    keep = classes if classes is not None and format_of(path) in ("las", "laz") else None
    return read(path, classes=keep)


def is_compressed(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a ``.dftpc`` file (by its magic bytes, not its name)."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(f"{path}: no such file")
    with path.open("rb") as fh:
        return fh.read(len(MAGIC)) == MAGIC


def evaluate_files(original: str | os.PathLike[str], candidate: str | os.PathLike[str], *,
                   classes: Sequence[int] | None = None) -> Row:
    """Every metric of :func:`dftpcc.metrics.evaluate` between two files.

    Parameters
    ----------
    original : path
        The reference cloud.
    candidate : path
        A ``.dftpc`` file (decoded here; bits per point from its size over
        the original's points) or any point cloud file (a rebuilt map).
    classes : sequence of int, optional
        LAS/LAZ classes of the original to keep (use what was compressed).

    Returns
    -------
    dict
        The metrics (metres, dB, bits per point) plus ``original``,
        ``candidate`` and, for a ``.dftpc``, ``points_in_header``: the point
        count the file was made from.
    """
    ref = load_points(original, classes=classes).points
    extra: Row = {"original": str(original), "candidate": str(candidate)}
    if is_compressed(candidate):
        with open_map(candidate) as cmap:
            rebuilt = cmap.read_points()
            size = cmap.size
            extra["points_in_header"] = cmap.header.point_count
        result = metrics.evaluate(ref, rebuilt, compressed_bytes=size)
    else:
        result = metrics.evaluate(ref, read(candidate).points)
    return {**extra, **result}


def sweep_points(points: np.ndarray, *, cutoffs: Iterable[float] = DEFAULT_CUTOFFS,
                 resolution: float | str = "auto", profile: str = "compact", label: str = "",
                 source: str = "", on_row: OnRow = _noop, **options: Any) -> list[Row]:
    """Compress one cloud at every cutoff and measure each result.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Metres.
    cutoffs : iterable of float
        Cutoff ratios f_c in [0, 1).
    resolution : float or 'auto'
        DEM cell size in metres.
    profile : {'compact', 'paper'}
    label, source : str
        Terrain name and input path written in each row.
    on_row : callable, optional
        Called with each row as soon as it is measured (progress display).
    **options
        Other :class:`~dftpcc.params.Params` fields.

    Returns
    -------
    list of dict
        One row per cutoff with the keys of :data:`SWEEP_COLUMNS`.
    """
    cutoffs = [float(c) for c in cutoffs]
    if not cutoffs:
        raise InvalidInputError("no cutoff given")
    t0 = time.perf_counter()
    points = np.asarray(points, dtype=np.float64)
    params = resolve_params(points, resolution=resolution, cutoff=cutoffs[0], profile=profile, **options)
    grid = fit_grid(points, params.resolution, frame=params.frame)
    dem = rasterize(points, grid, aggregate=params.aggregate)
    tree = metrics.build_tree(points)
    grid_s = time.perf_counter() - t0
    interpolator: metrics.XYInterpolator | None = None
    rebuilt_xy: np.ndarray | None = None
    rows = []
    for cutoff in cutoffs:
        t0 = time.perf_counter()
        data = encode_dem(dem, params.replace(cutoff=cutoff), point_count=int(points.shape[0]))
        t1 = time.perf_counter()
        cmap = open_map(data)
        rebuilt = dem_to_points(cmap.read_dem())
        t2 = time.perf_counter()
        if rebuilt_xy is None or not np.array_equal(rebuilt_xy, rebuilt[:, :2]):
            rebuilt_xy = rebuilt[:, :2].copy()
            interpolator = metrics.xy_interpolator(rebuilt_xy, points)
        measured = metrics.evaluate(points, rebuilt, compressed_bytes=len(data), original_tree=tree,
                                    interpolator=interpolator)
        t3 = time.perf_counter()
        header = cmap.header
        row: Row = {
            "terrain": label, "input": source, "profile": profile, "resolution_m": params.resolution,
            "cutoff": cutoff, "grid_rows": grid.rows, "grid_cols": grid.cols,
            "coef_count": header.coef_count, "mask_bytes": header.stats.get("mask_bytes"),
            "coef_bytes": header.stats.get("coef_bytes"), "step_m": header.params.step,
            "dem_rmse_m": header.stats.get("dem_rmse_m"),
            "gridding_rmse_m": dem.gridding_rmse,  # exact; the header rounds its statistics
            "grid_s": grid_s, "encode_s": t1 - t0, "decode_s": t2 - t1, "metrics_s": t3 - t2,
            **measured,
        }
        rows.append({key: row.get(key) for key in SWEEP_COLUMNS})
        on_row(rows[-1])
    return rows


def sweep(terrains: Iterable[Terrain], *, cutoffs: Iterable[float] = DEFAULT_CUTOFFS,
          profile: str = "compact", on_row: OnRow = _noop, **options: Any) -> list[Row]:
    """:func:`sweep_points` on each terrain in turn; the rows of all of them."""
    cutoffs = tuple(cutoffs)
    rows: list[Row] = []
    for terrain in terrains:
        cloud = load_points(terrain.path, classes=terrain.classes)
        rows.extend(sweep_points(cloud.points, cutoffs=cutoffs, resolution=terrain.resolution,
                                 profile=profile, label=terrain.name, source=str(terrain.path),
                                 on_row=on_row, **options))
    return rows


def write_csv(rows: Sequence[Row], path: str | os.PathLike[str]) -> Path:
    """Write sweep rows with the columns of :data:`SWEEP_COLUMNS` (full float precision)."""
    path = Path(path)
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=SWEEP_COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in SWEEP_COLUMNS})
    return path


def read_csv(path: str | os.PathLike[str]) -> list[Row]:
    """Rows of a ``sweep.csv``, numbers as float (empty cells as None)."""
    with Path(path).open(newline="") as fh:
        return [{k: (v if k in _TEXT_COLUMNS else (float(v) if v != "" else None)) for k, v in row.items()}
                for row in csv.DictReader(fh)]


def run_sweep(terrains: Sequence[Terrain], *, out: str | os.PathLike[str],
              cutoffs: Iterable[float] = DEFAULT_CUTOFFS, profile: str = "compact",
              on_row: OnRow = _noop, **options: Any) -> tuple[list[Row], Path, Path]:
    """Sweep, then write ``sweep.csv`` and ``sweep.png`` (the paper's Fig. 5) into ``out``.

    The CSV is written before the picture, so it survives a missing matplotlib
    (:class:`~dftpcc.errors.MissingDependencyError` is raised after it).

    Returns
    -------
    rows, csv_path, png_path
    """
    from .figures import plot_sweep

    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    rows = sweep(terrains, cutoffs=cutoffs, profile=profile, on_row=on_row, **options)
    csv_path = write_csv(rows, folder / "sweep.csv")
    png_path = plot_sweep(rows, folder / "sweep.png",
                          title=f"bits per point and RMSE against the cutoff ratio ({profile} profile)")
    return rows, csv_path, png_path


def compare_points(points: np.ndarray, *, cutoffs: Sequence[float] = COMPARE_CUTOFFS,
                   resolution: float | str = "auto", profile: str = "compact",
                   **options: Any) -> tuple[DEM, dict[float, DEM], dict[float, Row]]:
    """The original DEM and the DEMs a decoder rebuilds at each cutoff.

    Returns
    -------
    original : DEM
        The cloud gridded at ``resolution`` (what every rebuilt map is compared to).
    rebuilt : dict
        Cutoff -> decoded DEM.
    figures : dict
        Cutoff -> ``bytes``, ``bits_per_point``, ``paper_rmse_m`` (metres).
    """
    points = np.asarray(points, dtype=np.float64)
    params = resolve_params(points, resolution=resolution, profile=profile, **options)
    dem = rasterize(points, fit_grid(points, params.resolution, frame=params.frame),
                    aggregate=params.aggregate)
    rebuilt: dict[float, DEM] = {}
    figures: dict[float, Row] = {}
    interpolator = None
    for cutoff in cutoffs:
        data = encode_dem(dem, params.replace(cutoff=float(cutoff)), point_count=int(points.shape[0]))
        rebuilt[cutoff] = open_map(data).read_dem()
        cloud = dem_to_points(rebuilt[cutoff])
        interpolator = interpolator or metrics.xy_interpolator(cloud, points)
        figures[cutoff] = {"bytes": len(data),
                           "bits_per_point": metrics.bits_per_point(len(data), points.shape[0]),
                           "paper_rmse_m": metrics.paper_rmse(points, cloud, interpolator=interpolator)}
    return dem, rebuilt, figures


def compare_file(path: str | os.PathLike[str], *, out: str | os.PathLike[str],
                 cutoffs: Sequence[float] = COMPARE_CUTOFFS, resolution: float | str = "auto",
                 profile: str = "compact", classes: Sequence[int] | None = None,
                 label: str | None = None, **options: Any) -> Path:
    """Fig. 6 of the paper for one file: ``<out>/<name>_compare_<profile>.png``.

    Original and rebuilt maps side by side (hillshaded height colour), a
    close-up window, and the error of each rebuilt DEM against the original
    one (metres). Needs matplotlib.
    """
    from .figures import plot_compare, require_matplotlib

    require_matplotlib()
    name = label or Path(path).stem
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    cloud = load_points(path, classes=classes)
    original, rebuilt, figures = compare_points(cloud.points, cutoffs=cutoffs, resolution=resolution,
                                                profile=profile, **options)
    return plot_compare(original, rebuilt, folder / f"{name}_compare_{profile}.png", figures=figures,
                        title=f"{name}: {cloud.points.shape[0]:,} points, "
                              f"{original.grid.resolution:g} m cells, {profile} profile")


def format_row(row: Row) -> str:
    """One line of progress for a sweep row."""
    return (f"{row['terrain']:<24} f_c {row['cutoff']:<5g} {row['bytes']:>11,} B "
            f"{row['bits_per_point']:>9.4f} bits/pt  RMSE {row['paper_rmse_m']:.4f} m  "
            f"D1 {row['d1_rmse_m']:.4f} m  [{row['encode_s'] + row['decode_s'] + row['metrics_s']:.2f} s]")


#: How :func:`format_metrics` shows each metric: label, unit, scale.
_TABLE = (
    ("points_original", "original points", "", None),
    ("points_rebuilt", "rebuilt points", "", None),
    ("points_in_header", "points the file was made from", "", None),
    ("bytes", "compressed size", "bytes", None),
    ("bits_per_point", "bits per point", "bits", ".4f"),
    ("paper_rmse_m", "paper RMSE (own cell, vertical)", "m", ".4f"),
    ("paper_rmse_3d_m", "paper RMSE (own cell, 3D)", "m", ".4f"),
    ("vertical_rmse_m", "vertical error RMSE", "m", ".4f"),
    ("vertical_p95_m", "vertical error 95th percentile", "m", ".4f"),
    ("vertical_max_m", "vertical error max", "m", ".4f"),
    ("d1_rmse_m", "D1 point-to-point RMSE (symmetric)", "m", ".4f"),
    ("d1_rmse_forward_m", "  original -> rebuilt", "m", ".4f"),
    ("d1_rmse_backward_m", "  rebuilt -> original", "m", ".4f"),
    ("d1_psnr_db", "D1 PSNR", "dB", ".2f"),
    ("psnr_peak_m", "  PSNR peak (bounding-box diagonal)", "m", ".3f"),
    ("chamfer_m", "Chamfer distance", "m", ".4f"),
    ("hausdorff_m", "Hausdorff distance", "m", ".4f"),
)


def format_metrics(result: Row) -> str:
    """The result of :func:`evaluate_files` as an aligned table, one metric a line."""
    lines = []
    width = max(len(label) for _, label, _, _ in _TABLE)
    for key, label, unit, fmt in _TABLE:
        if key not in result:
            continue
        value = result[key]
        text = f"{value:,}" if fmt is None else format(value, fmt)
        lines.append(f"{label:<{width}}  {text:>14} {unit}".rstrip())
    return "\n".join(lines)


def jsonable(result: Row) -> Row:
    """A copy with non-finite numbers (an infinite PSNR) as None, for strict JSON."""
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in result.items()}
