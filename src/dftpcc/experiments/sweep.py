"""The paper's Fig. 5 on any terrain: compress at every cutoff, measure, write sweep.csv and sweep.png.

A sweep grids each input once (read, grid, rasterize) and then, per cutoff,
encodes that DEM with :func:`dftpcc.encoder.encode_dem`, decodes the bytes and
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
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from .. import metrics
from ..encoder import encode_dem, grid_points
from ..dem import DEM
from ..errors import InvalidInputError
from ..files import read_dem
from ..io import read
from ..mapfile import open as open_map
from ..params import make_params
from ..rebuild import dem_to_points
from .figures import plot_sweep

__all__ = ["DEFAULT_CUTOFFS", "SWEEP_COLUMNS", "Terrain", "terrains", "sweep_points", "sweep", "write_csv",
           "read_csv", "run_sweep"]

#: The paper's Fig. 5 range: f_c from 0 to 0.95 in steps of 0.05.
DEFAULT_CUTOFFS: tuple[float, ...] = tuple(round(0.05 * i, 2) for i in range(20))

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
        LAS/LAZ classification codes to keep (2 = ground); other formats refuse them, as compress does.
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


def sweep_points(points: np.ndarray, *, cutoffs: Iterable[float] = DEFAULT_CUTOFFS,
                 resolution: float | str = "auto", profile: str = "compact", label: str = "",
                 source: str = "", on_row: OnRow = _noop, dem: DEM | None = None, crs: dict[str, Any] | None = None,
                 **options: Any) -> list[Row]:
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
    dem : DEM, optional
        The map to code, when the caller has it (:func:`dftpcc.files.read_dem`,
        as compress makes it); default: ``points`` gridded at ``resolution``.
    crs : dict, optional
        Carried in each file, as compress does, so the sizes are those of the files it writes.
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
    params = make_params(resolution=resolution, profile=profile, **options)
    dem = grid_points(points, params) if dem is None else dem
    grid = dem.grid
    tree = metrics.build_tree(points)
    grid_s = time.perf_counter() - t0
    interpolator: metrics.XYInterpolator | None = None
    rebuilt_xy: np.ndarray | None = None
    rows = []
    for cutoff in cutoffs:
        t0 = time.perf_counter()
        data = encode_dem(dem, params.replace(cutoff=cutoff), point_count=int(points.shape[0]), crs=crs)
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
            "terrain": label, "input": source, "profile": profile, "resolution_m": grid.resolution,
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
        # The map compress would code (a GeoTIFF on its own pixels), measured against the points read.
        params = make_params(resolution=terrain.resolution, profile=profile, **options)
        dem, _, crs = read_dem(terrain.path, params, classes=terrain.classes)
        cloud = read(terrain.path, classes=terrain.classes)
        rows.extend(sweep_points(cloud.points, cutoffs=cutoffs, resolution=terrain.resolution, dem=dem, crs=crs,
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
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    rows = sweep(terrains, cutoffs=cutoffs, profile=profile, on_row=on_row, **options)
    csv_path = write_csv(rows, folder / "sweep.csv")
    png_path = plot_sweep(rows, folder / "sweep.png",
                          title=f"bits per point and RMSE against the cutoff ratio ({profile} profile)")
    return rows, csv_path, png_path
