"""The paper's Fig. 6 on any terrain: original and rebuilt maps side by side, with their errors."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from .. import metrics
from ..dem import DEM
from ..encoder import encode_dem, grid_points
from ..files import read_dem
from ..io import read
from ..mapfile import open as open_map
from ..params import make_params
from ..rebuild import dem_to_points
from ..units import length, units_of
from .figures import plot_compare, require_matplotlib

__all__ = ["COMPARE_CUTOFFS", "compare_points", "compare_file"]

#: Fig. 6 of the paper shows these two cutoffs.
COMPARE_CUTOFFS: tuple[float, ...] = (0.8, 0.95)

Row = dict[str, Any]


def compare_points(points: np.ndarray, *, cutoffs: Sequence[float] = COMPARE_CUTOFFS,
                   resolution: float | str = "auto", profile: str = "compact", dem: DEM | None = None,
                   crs: dict[str, Any] | None = None, on_stage: Callable[..., None] | None = None,
                   **options: Any) -> tuple[DEM, dict[float, DEM], dict[float, Row]]:
    """The original DEM and the DEMs a decoder rebuilds at each cutoff.

    ``dem``: the map to code when the caller has it (:func:`dftpcc.files.read_dem`);
    default ``points`` gridded at ``resolution``. ``crs``: the source's, which the file
    carries (several hundred bytes of WKT): the sizes are those of the files ``compress`` writes.
    ``on_stage("code", done)`` is called with the fraction of cutoffs done.

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
    params = make_params(resolution=resolution, profile=profile, **options)
    dem = grid_points(points, params) if dem is None else dem
    rebuilt: dict[float, DEM] = {}
    figures: dict[float, Row] = {}
    interpolator = None
    for k, cutoff in enumerate(cutoffs):
        if on_stage is not None:
            on_stage("code", k / max(len(cutoffs), 1))
        data = encode_dem(dem, params.replace(cutoff=float(cutoff)), point_count=int(points.shape[0]), crs=crs)
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
                 label: str | None = None, on_stage: Callable[..., None] | None = None, **options: Any) -> Path:
    """Fig. 6 of the paper for one file: ``<out>/<name>_compare_<profile>.png``.

    Original and rebuilt maps side by side (hillshaded height colour), a
    close-up window, and the error of each rebuilt DEM against the original
    one (metres). Needs matplotlib. ``on_stage`` is called with each stage's name as it starts
    (``read``, ``code``, ``draw``).
    """
    require_matplotlib()
    name = label or Path(path).stem
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    params = make_params(resolution=resolution, profile=profile, **options)
    stage = on_stage or (lambda *_: None)
    stage("read")
    dem, _, crs = read_dem(path, params, classes=classes)  # what compress codes: a GeoTIFF on its own pixels
    units = units_of(crs)
    cloud = read(path, classes=classes)
    stage("code")
    original, rebuilt, figures = compare_points(cloud.points, cutoffs=cutoffs, resolution=resolution, dem=dem,
                                                crs=crs, profile=profile, on_stage=stage, **options)
    stage("draw")
    return plot_compare(original, rebuilt, folder / f"{name}_compare_{profile}.png", figures=figures, units=units,
                        title=f"{name}: {cloud.points.shape[0]:,} points, "
                              f"{length(original.grid.resolution, units.horizontal)} cells, {profile} profile")
