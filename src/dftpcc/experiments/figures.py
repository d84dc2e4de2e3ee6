"""Pictures of the measure stage: the paper's Fig. 5 (sweep) and Fig. 6 (maps side by side).

matplotlib is an optional dependency (``pip install 'dftpcc[plot]'``). The
figures are drawn on matplotlib's Agg canvas directly, without pyplot, so
importing this module never changes the caller's plotting backend.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from scipy import ndimage

from ..dem import DEM
from .._optional import import_optional, install_hint
from ..errors import InvalidInputError
from ..fill import fill_empty
from ..units import Units

__all__ = ["require_matplotlib", "plot_sweep", "plot_compare", "choose_window"]

INSTALL_HINT = install_hint("plot")
#: Resolution of the PNG files, dots per inch (the map pictures are large: fewer dots).
DPI = 120
COMPARE_DPI = 100
#: Light for the hillshade: from the north-west, 45 degrees above the horizon.
LIGHT_AZIMUTH_DEG = 315.0
LIGHT_ALTITUDE_DEG = 45.0
#: The close-up window covers this fraction of the smaller side of the map ...
WINDOW_FRACTION = 0.2
#: ... but at least this many cells across.
MIN_WINDOW_CELLS = 16
#: A window must be at least this fraction occupied to be chosen.
MIN_WINDOW_OCCUPANCY = 0.5
#: Error colour scale: symmetric, up to this percentile of |error| (per cent),
#: so one bad cell does not wash out the map.
ERROR_SCALE_PERCENTILE = 99.0
#: Sweep plot: which metric is drawn as RMSE.
SWEEP_RMSE_KEY = "paper_rmse_m"


def require_matplotlib() -> Any:
    """Import matplotlib or raise :class:`MissingDependencyError` with an install hint."""
    import_optional("matplotlib.backends.backend_agg", "plot", needed_for="drawing pictures")  # the canvas _figure draws on
    return import_optional("matplotlib", "plot", needed_for="drawing pictures")


def _figure(width: float, height: float) -> Any:
    require_matplotlib()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Any, path: str | os.PathLike[str], *, dpi: int = DPI) -> Path:
    path = Path(path)
    fig.savefig(path, dpi=dpi)
    return path


#: Axis labels of the sweep's error columns (metres).
ERROR_LABELS = {"paper_rmse_m": "RMSE, own-cell pairing (m)", "d1_rmse_m": "D1 point-to-point RMSE (m)",
                "vertical_rmse_m": "vertical RMSE (m)", "dem_rmse_m": "DEM RMSE (m)", "chamfer_m": "Chamfer distance (m)",
                "hausdorff_m": "Hausdorff distance (m)"}
#: Errors of the original points, which gridding alone already makes (the floor line is drawn for them).
FLOORED_ERRORS = ("paper_rmse_m", "vertical_rmse_m")


def plot_sweep(rows: Sequence[Mapping[str, Any]], path: str | os.PathLike[str], *,
               rmse_key: str = SWEEP_RMSE_KEY, title: str | None = None) -> Path:
    """The paper's Fig. 5: bits per point and RMSE against the cutoff ratio, one line per terrain.

    Parameters
    ----------
    rows : sequence of mapping
        Sweep rows (:func:`dftpcc.sweep.sweep`) with ``terrain``, ``cutoff``,
        ``bits_per_point`` and ``rmse_key``.
    path : path
        PNG file to write.
    rmse_key : str, keyword-only
        Which error column to draw (metres); default the paper's RMSE.
    title : str, keyword-only, optional

    Returns
    -------
    Path
    """
    if not rows:
        raise InvalidInputError("no sweep rows to plot")
    fig = _figure(11.0, 4.2)
    ax_bits, ax_rmse = fig.subplots(1, 2)
    terrains = list(dict.fromkeys(str(r["terrain"]) for r in rows))
    for name in terrains:
        mine = sorted((r for r in rows if str(r["terrain"]) == name), key=lambda r: float(r["cutoff"]))
        fc = [float(r["cutoff"]) for r in mine]
        res = float(mine[0]["resolution_m"])
        label = f"{name} ({res:g} m)"
        ax_bits.plot(fc, [float(r["bits_per_point"]) for r in mine], marker="o", ms=3, label=label)
        (line,) = ax_rmse.plot(fc, [float(r[rmse_key]) for r in mine], marker="o", ms=3, label=label)
        floor = float(mine[0].get("gridding_rmse_m") or 0.0)
        if floor > 0 and rmse_key in FLOORED_ERRORS:
            # What gridding alone costs, before any coding: an error at f_c 0 reaching it is not the codec's.
            ax_rmse.axhline(floor, color=line.get_color(), ls="--", lw=1, label=f"{name}: gridding floor")
    ax_bits.set(xlabel="cutoff ratio $f_c$", ylabel="bits per point", yscale="log",
                title="(a) size: compressed bits / original points")
    ax_rmse.set(xlabel="cutoff ratio $f_c$", ylabel=ERROR_LABELS.get(rmse_key, rmse_key.replace("_", " ")),
                yscale="log",
                title="(b) error (paper's RMSE, own-cell pairing)" if rmse_key == SWEEP_RMSE_KEY else "(b) error")
    from matplotlib.ticker import FuncFormatter

    plain = FuncFormatter(lambda value, _: f"{value:g}")
    for ax in (ax_bits, ax_rmse):
        ax.grid(True, which="both", alpha=0.3)
        ax.set_xlim(0.0, 1.0)
        ax.yaxis.set_major_formatter(plain)
    ax_rmse.legend(fontsize=8, loc="upper left")
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def choose_window(error: np.ndarray, mask: np.ndarray, *, size: int | None = None) -> tuple[int, int, int]:
    """A square close-up window where the error is largest.

    Parameters
    ----------
    error : ndarray, shape (rows, cols)
        Error per cell in metres (only occupied cells count).
    mask : ndarray of bool, same shape
        Occupied cells.
    size : int, keyword-only, optional
        Side in cells; default :data:`WINDOW_FRACTION` of the smaller side.

    Returns
    -------
    (row0, col0, size)
        Lower-left cell of the window and its side, in cells.
    """
    rows, cols = mask.shape
    if size is None:
        size = max(MIN_WINDOW_CELLS, int(WINDOW_FRACTION * min(rows, cols)))
    size = max(1, min(size, rows, cols))
    occupied = ndimage.uniform_filter(mask.astype(float), size, mode="constant")
    energy = ndimage.uniform_filter(np.where(mask, error * error, 0.0), size, mode="constant")
    mean_sq = np.divide(energy, occupied, out=np.zeros_like(energy), where=occupied > 0)
    half = size // 2
    # A window centred at (r, c) spans r - half .. r - half + size - 1: keep it inside the map.
    valid = np.zeros_like(mask)
    valid[half:rows - (size - half) + 1, half:cols - (size - half) + 1] = True
    candidates = valid & (occupied >= MIN_WINDOW_OCCUPANCY)
    if not candidates.any():
        candidates = valid
    r, c = np.unravel_index(int(np.argmax(np.where(candidates, mean_sq, -1.0))), mask.shape)
    return int(r - half), int(c - half), size


def _shade(heights: np.ndarray, mask: np.ndarray, resolution: float, vmin: float, vmax: float) -> np.ndarray:
    """RGBA hillshade coloured by height; empty cells transparent."""
    from matplotlib import colormaps
    from matplotlib.colors import LightSource

    filled = fill_empty(heights, mask, method="smooth")
    light = LightSource(azdeg=LIGHT_AZIMUTH_DEG, altdeg=LIGHT_ALTITUDE_DEG)
    rgba = light.shade(filled, cmap=colormaps["gist_earth"], blend_mode="soft", vmin=vmin, vmax=vmax,
                       dx=resolution, dy=resolution)
    rgba[..., 3] = mask
    return rgba


def plot_compare(original: DEM, rebuilt: Mapping[float, DEM], path: str | os.PathLike[str], *,
                 figures: Mapping[float, Mapping[str, float]] | None = None,
                 window: tuple[int, int, int] | None = None, title: str | None = None,
                 units: Units = Units()) -> Path:
    """The paper's Fig. 6: the original and rebuilt maps side by side.

    ``units``: what the axes (``units.horizontal``) and heights (``units.vertical``) are in.

    Columns: the original DEM, then one per cutoff. Rows: the whole map
    (hillshaded, coloured by height, one colour scale), a close-up window
    (boxed in the first row), and the error of each rebuilt DEM against the
    original DEM per occupied cell (metres, one symmetric scale).

    Parameters
    ----------
    original : DEM
        The cloud gridded at the map's resolution.
    rebuilt : mapping
        Cutoff ratio -> decoded DEM on the same grid.
    path : path
        PNG file to write.
    figures : mapping, keyword-only, optional
        Cutoff -> ``bits_per_point`` and ``paper_rmse_m`` for the titles.
    window : (row0, col0, size), keyword-only, optional
        Close-up window in cells; default where the error at the largest
        cutoff is largest (:func:`choose_window`).
    title : str, keyword-only, optional

    Returns
    -------
    Path
    """
    if not rebuilt:
        raise InvalidInputError("no rebuilt map to compare")
    grid, mask = original.grid, original.mask
    for dem in rebuilt.values():
        if dem.grid.shape != grid.shape:
            raise InvalidInputError("rebuilt maps must share the original's grid")
    res = grid.resolution
    cutoffs = sorted(rebuilt)
    errors = {fc: np.where(mask, rebuilt[fc].heights - original.heights, 0.0) for fc in cutoffs}
    if window is None:
        window = choose_window(errors[cutoffs[-1]], mask)
    r0, c0, size = window
    z = original.heights[mask]
    vmin, vmax = float(z.min()), float(z.max())
    all_err = np.concatenate([np.abs(e[mask]) for e in errors.values()])
    elim = float(np.percentile(all_err, ERROR_SCALE_PERCENTILE)) or 1e-3
    extent = (0.0, grid.cols * res, 0.0, grid.rows * res)
    zoom = (c0 * res, (c0 + size) * res, r0 * res, (r0 + size) * res)

    ncol = 1 + len(cutoffs)
    fig = _figure(3.6 * ncol, 10.5)
    axes = fig.subplots(3, ncol, squeeze=False)
    from matplotlib.patches import Rectangle

    panels = [("original DEM", original.heights)] + [
        (_caption(fc, (figures or {}).get(fc)), rebuilt[fc].heights) for fc in cutoffs]
    inside = (slice(r0, r0 + size), slice(c0, c0 + size))
    # The close-up gets its own colour range to show detail: every panel's heights inside the box, so
    # that no rebuilt height falls off the colour scale (clipped to black).
    zw = np.concatenate([h[inside][mask[inside]] for _, h in panels])
    wmin, wmax = (float(zw.min()), float(zw.max())) if zw.size else (vmin, vmax)
    # ... and the whole maps' range likewise.
    zall = np.concatenate([h[mask] for _, h in panels])
    vmin, vmax = float(zall.min()), float(zall.max())
    for col, (caption, heights) in enumerate(panels):
        ax = axes[0, col]
        ax.imshow(_shade(heights, mask, res, vmin, vmax), origin="lower", extent=extent, interpolation="nearest")
        ax.add_patch(Rectangle((zoom[0], zoom[2]), size * res, size * res, fill=False, ec="red", lw=1.2))
        ax.set_title(caption, fontsize=9)
        close = axes[1, col]
        close.imshow(_shade(heights[inside], mask[inside], res, wmin, wmax), origin="lower", extent=zoom,
                     interpolation="nearest")
        close.set_title("close-up (red box)", fontsize=9)
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    for row, (lo, hi) in ((0, (vmin, vmax)), (1, (wmin, wmax))):
        scale = ScalarMappable(Normalize(lo + grid.z0, hi + grid.z0), colormaps["gist_earth"])
        fig.colorbar(scale, ax=list(axes[row, :]), shrink=0.8, label=f"height ({units.vertical})")
    info = axes[2, 0]
    info.axis("off")
    info.text(0.0, 1.0, _legend_text(original, cutoffs, figures, vmin, vmax, units), va="top", fontsize=8,
              family="monospace", transform=info.transAxes)
    image = None
    for col, fc in enumerate(cutoffs, start=1):
        err = np.ma.masked_where(~mask, errors[fc])
        ax = axes[2, col]
        image = ax.imshow(err, origin="lower", extent=extent, cmap="RdBu_r", vmin=-elim, vmax=elim,
                          interpolation="nearest")
        ax.set_title(f"error, $f_c$ = {fc:g}: rebuilt - original ({units.vertical})", fontsize=9)
    if image is not None:
        fig.colorbar(image, ax=list(axes[2, 1:]), shrink=0.8, label=f"height error ({units.vertical})")
    for ax in axes.ravel():
        if ax is not info:
            ax.set_xlabel(f"x - x0 ({units.horizontal})", fontsize=8)
            ax.set_ylabel(f"y - y0 ({units.horizontal})", fontsize=8)
            ax.tick_params(labelsize=7)
    if title:
        fig.suptitle(title)
    return _save(fig, path, dpi=COMPARE_DPI)


def _caption(cutoff: float, figures: Mapping[str, float] | None) -> str:
    text = f"rebuilt, $f_c$ = {cutoff:g}"
    if figures:
        text += f"\n{figures['bits_per_point']:.3g} bits/point, RMSE {figures['paper_rmse_m']:.3g} m"
    return text


def _legend_text(original: DEM, cutoffs: Sequence[float], figures: Mapping[float, Mapping[str, float]] | None,
                 vmin: float, vmax: float, units: Units = Units()) -> str:
    g = original.grid
    lines = [f"grid {g.rows} x {g.cols} cells of {g.resolution:g}{'' if units.horizontal == '°' else ' '}"
             f"{units.horizontal}",
             f"occupied {int(original.mask.sum()):,} cells",
             f"height {vmin + g.z0:.1f} .. {vmax + g.z0:.1f} {units.vertical}",
             "colour: height; shading: light",
             f"from the NW at {LIGHT_ALTITUDE_DEG:g} deg", ""]
    for fc in cutoffs:
        f = (figures or {}).get(fc)
        if f:
            lines.append(f"f_c {fc:<5g} {f['bits_per_point']:8.3f} bits/pt")
            lines.append(f"{'':9} RMSE {f['paper_rmse_m']:.4f} m")
    return "\n".join(lines)
