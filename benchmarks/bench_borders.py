"""Border handling, hole filling, entropy coder: which choices code a map smallest.

The paper's DFT treats the map as periodic, so a sloping or irregular map
"wraps around": its opposite borders meet in a cliff that rings over the
whole spectrum. This script measures, on real terrain and at equal error,
the bytes each remedy needs (rate control picks cutoff and step for a
target DEM RMSE), and draws the error map of the paper's DFT next to the
default's at the same cutoff.

    .venv/bin/python -m benchmarks.bench_borders [--quick] > docs/borders.md

Prints a table (bits per original point at 3 error levels per file and
configuration, and each configuration's ratio to the default) and writes
docs/figures/borders_error_map.png. It never asserts anything.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import scipy.fft as sfft

import dftpcc
from dftpcc.encoder import encode_dem
from dftpcc.fill import fill_empty
from dftpcc.files import dem_from_geotiff
from dftpcc.grid import fit_grid, rasterize

REPO = Path(__file__).resolve().parent.parent
DATA = REPO.parent / "shared" / "data"
FIGURE = REPO / "docs" / "figures" / "borders_error_map.png"

#: file, resolution (None = the GeoTIFF's pixels), LAS classes
FILES = [
    ("pointclouds/field_gentle_ign.laz", 0.5, [2]),
    ("pointclouds/mountain_arid_alirt.las", 2.0, None),
    ("pointclouds/redrocks_rough.ply", 5.0, None),
    ("dems/mars_gale_1m.tif", None, None),
]
#: Vertical RMSE of the points as multiples of the gridding floor (as in
#: ANCHORS.md); a DEM's own pixels have no floor, so there the levels are
#: DEM RMSEs as fractions of the map's RMS relief.
FLOOR_MULTIPLES = (1.25, 1.5, 3.0)
RELIEF_FRACTIONS = (0.002, 0.005, 0.02)
#: Configurations: (label, Params overrides, fill function or None for the library's)
POCS_ITERATIONS = 10


def pocs_fill(heights: np.ndarray, mask: np.ndarray, *, method: str = "smooth") -> np.ndarray:
    """Push-pull, then projections onto convex sets: the fill that makes the DCT sparsest.

    Alternately zero the smallest half of the DCT coefficients and restore the
    known cells; the empty cells drift to whatever the sparse spectrum says.
    """
    g = fill_empty(heights, mask, method="smooth")
    known = g[mask]
    for _ in range(POCS_ITERATIONS):
        c = sfft.dctn(g, norm="ortho")
        c[np.abs(c) < np.median(np.abs(c))] = 0.0
        g = sfft.idctn(c, norm="ortho")
        g[mask] = known
    return g


CONFIGS = [
    ("DFT (paper), no detrend", dict(transform="dft", detrend="none"), None),
    ("DFT + plane", dict(transform="dft", detrend="plane"), None),
    ("DCT (mirrored DFT), no detrend", dict(transform="dct", detrend="none"), None),
    ("DCT + plane [default: consistent fill]", dict(transform="dct", detrend="plane"), None),
    ("DCT + plane, push-pull fill only", dict(transform="dct", detrend="plane", fill="smooth"), None),
    ("DCT + plane, zero fill", dict(transform="dct", detrend="plane", fill="zero"), None),
    ("DCT + plane, sparsifying POCS fill", dict(transform="dct", detrend="plane", fill="smooth"), pocs_fill),
    ("DCT + plane, zstd instead of ANS", dict(transform="dct", detrend="plane", coder="zstd"), None),
]
DEFAULT = 3


def load(name: str, resolution: float | None, classes):
    path = DATA / name
    if resolution is None:
        dem, _ = dem_from_geotiff(path)
        relief = float(np.sqrt(np.mean((dem.heights[dem.mask] - dem.heights[dem.mask].mean()) ** 2)))
        targets = [f * relief for f in RELIEF_FRACTIONS]
        labels = [f"{f:g} relief" for f in RELIEF_FRACTIONS]
        return dem, int(dem.mask.sum()), targets, labels
    points = dftpcc.read(path, classes=classes).points
    dem = rasterize(points, fit_grid(points, resolution))
    floor = dem.gridding_rmse
    # vertical^2 = floor^2 + (point-weighted DEM error)^2: the DEM RMSE for each level
    targets = [floor * math.sqrt(k * k - 1.0) for k in FLOOR_MULTIPLES]
    labels = [f"{k:g}x floor" for k in FLOOR_MULTIPLES]
    return dem, points.shape[0], targets, labels


def encode(dem, overrides, fill, target):
    """The file rate control makes for ``target``: with the library's fill, or with ``fill`` in its place."""
    params = dftpcc.make_params(resolution=dem.grid.resolution, target_rmse=target, **overrides)
    return encode_dem(dem, params, fill=fill)


def error_map(out: Path) -> None:
    """|rebuilt - gridded| on the field at f_c = 0.8: the paper's DFT against the default."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = dftpcc.read(DATA / "pointclouds/field_gentle_ign.laz", classes=[2]).points
    dem = rasterize(points, fit_grid(points, 0.5))
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.6), constrained_layout=True)
    for ax, (title, kwargs) in zip(axes, [
        ("paper profile: DFT, f_c = 0.8", dict(profile="paper")),
        ("default: plane + DCT (mirrored DFT), f_c = 0.8", dict()),
    ]):
        data = dftpcc.compress(points, resolution=0.5, cutoff=0.8, **kwargs)
        err = np.abs(dftpcc.open(data).read_dem().heights - dem.heights)
        rmse = math.sqrt(float(np.mean(err[dem.mask] ** 2)))
        im = ax.imshow(np.where(dem.mask, err, np.nan), origin="lower", cmap="magma", vmin=0, vmax=0.3)
        ax.set_title(f"{title}\nDEM RMSE {rmse * 1000:.0f} mm, {8 * len(data) / len(points):.2f} bits/point")
        ax.set_xlabel("column (0.5 m cells)")
        ax.set_ylabel("row")
    fig.colorbar(im, ax=axes, label="|rebuilt - gridded| height (m)", shrink=0.8)
    fig.suptitle("field_gentle_ign.laz (ground): the DFT's wrap-around puts its error on the borders")
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="first two files only")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")  # multi-height notes on vegetation are beside the point here
    files = FILES[:2] if args.quick else FILES
    t0 = time.perf_counter()
    print(f"# Border handling, hole filling and coder at equal error (dftpcc {dftpcc.__version__})\n")
    print("Made by `.venv/bin/python -m benchmarks.bench_borders > docs/borders.md` "
          f"on {time.strftime('%Y-%m-%d')}. Bits per original point; rate control picks cutoff and step "
          "for each target DEM RMSE (in brackets: size relative to the default).\n")
    print("![error maps](figures/borders_error_map.png)\n")
    ratios: dict[str, list[float]] = {label: [] for label, _, _ in CONFIGS}
    for name, resolution, classes in files:
        dem, n_points, targets, labels = load(name, resolution, classes)
        print(f"## {name}  ({dem.grid.rows} x {dem.grid.cols} cells, {n_points:,} points)")
        print("| configuration | " + " | ".join(labels) + " |")
        print("|---|" + "---|" * len(labels))
        sizes = [[len(encode(dem, o, f, t)) for t in targets] for _, o, f in CONFIGS]
        for (label, _, _), row in zip(CONFIGS, sizes):
            cells = [f"{8 * s / n_points:.3f} ({s / d:.2f}x)" for s, d in zip(row, sizes[DEFAULT])]
            ratios[label].extend(s / d for s, d in zip(row, sizes[DEFAULT]))
            print(f"| {label} | " + " | ".join(cells) + " |")
        print()
    print("## Geometric mean of size / default over every file and level")
    for label, values in ratios.items():
        print(f"- {label}: {math.exp(np.mean(np.log(values))):.2f}x")
    error_map(FIGURE)
    print(f"\nwrote {FIGURE.relative_to(REPO)}; {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
