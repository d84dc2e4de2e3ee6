"""Conditioning before the transform: remove the trend, fill the empty cells.

Part of the spectrum stage: the transform sees the DEM minus a least-squares
plane (:func:`fit_plane`), with empty cells filled smoothly (:func:`fill_empty`)
so it meets no artificial cliff; :func:`footprint` says which empty cells a
``mask='footprint'`` map rebuilds.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .dem import DEM
from .errors import InvalidInputError

__all__ = ["fit_plane", "plane_values", "fill_empty", "footprint"]


def fit_plane(dem: DEM) -> tuple[float, float, float]:
    """Least-squares plane ``a + b*col + c*row`` (metres) through the occupied cells."""
    rows, cols = np.nonzero(dem.mask)
    if rows.size < 3:
        return (float(dem.heights[dem.mask].mean()) if rows.size else 0.0, 0.0, 0.0)
    # Normal equations on centred coordinates: 3 x 3, well conditioned, and
    # a few passes over the cells instead of a least-squares solve on them.
    x, y, z = cols.astype(float), rows.astype(float), dem.heights[rows, cols]
    mx, my, mz = x.mean(), y.mean(), z.mean()
    x -= mx
    y -= my
    z = z - mz
    normal = np.array([[x @ x, x @ y], [x @ y, y @ y]])
    rhs = np.array([x @ z, y @ z])
    try:
        b, c = np.linalg.solve(normal, rhs)
    except np.linalg.LinAlgError:  # all cells on one line: fit along it only
        b, c = np.linalg.lstsq(normal, rhs, rcond=None)[0]
    return float(mz - b * mx - c * my), float(b), float(c)


def plane_values(plane: tuple[float, float, float], shape: tuple[int, int]) -> np.ndarray:
    """The plane of :func:`fit_plane` evaluated on a grid of ``shape``."""
    a, b, c = plane
    rows = np.arange(shape[0], dtype=float)[:, None]
    cols = np.arange(shape[1], dtype=float)[None, :]
    return a + b * cols + c * rows


def fill_empty(heights: np.ndarray, mask: np.ndarray, *, method: str = "smooth") -> np.ndarray:
    """Heights with empty cells filled, occupied cells untouched.

    ``zero`` leaves 0 (the projection plane). ``smooth`` is push-pull
    interpolation: occupied cells are averaged down a pyramid, and each
    level's empty cells take the bilinearly upsampled coarser level, so a
    hole is bridged by a smooth surface and adds little high-frequency
    energy to the spectrum.

    Parameters
    ----------
    heights : ndarray, shape (rows, cols)
    mask : ndarray of bool, same shape
    method : {'smooth', 'zero'}
    """
    out = np.where(mask, heights, 0.0)
    if method == "zero" or mask.all() or not mask.any():
        return out
    if method != "smooth":
        raise InvalidInputError(f"fill must be 'smooth' or 'zero', got {method!r}")
    return _push_pull(out, mask.astype(np.float64))


def _upsample2(a: np.ndarray, axis: int) -> np.ndarray:
    """Linear 2x upsampling along ``axis`` with cell-centred samples, edges clamped."""
    a = np.moveaxis(a, axis, 0)
    before = np.concatenate([a[:1], a[:-1]])
    after = np.concatenate([a[1:], a[-1:]])
    out = np.empty((2 * a.shape[0],) + a.shape[1:])
    out[0::2] = 0.75 * a + 0.25 * before
    out[1::2] = 0.75 * a + 0.25 * after
    return np.moveaxis(out, 0, axis)


def _push_pull(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    if weights.min() >= 1.0:
        return values  # nothing to fill at this level (coarse levels of a dense map)
    if min(values.shape) <= 1 and values.size <= 2:
        total = weights.sum()
        mean = (values * weights).sum() / total if total else 0.0
        return np.where(weights > 0, values, mean)
    # Pull: average the known values over 2x2 blocks (pad odd sizes by edge).
    r, c = values.shape
    pr, pc = r % 2, c % 2
    v = np.pad(values * weights, ((0, pr), (0, pc)))
    w = np.pad(weights, ((0, pr), (0, pc)))
    wsum = w.reshape(v.shape[0] // 2, 2, v.shape[1] // 2, 2).sum(axis=(1, 3))
    vsum = v.reshape(v.shape[0] // 2, 2, v.shape[1] // 2, 2).sum(axis=(1, 3))
    coarse_v = np.divide(vsum, wsum, out=np.zeros_like(vsum), where=wsum > 0)
    coarse = _push_pull(coarse_v, np.minimum(wsum, 1.0))
    # Push: bilinear upsampling of the filled coarse level back to this size.
    up = _upsample2(_upsample2(coarse, 0), 1)[:r, :c]
    wc = np.minimum(weights, 1.0)
    return wc * values + (1.0 - wc) * up



def footprint(mask: np.ndarray) -> np.ndarray:
    """Occupied cells plus the empty ones the map encloses (one-cell gaps closed, holes filled)."""
    closed = ndimage.binary_closing(mask, structure=np.ones((3, 3), bool), border_value=0) | mask
    return ndimage.binary_fill_holes(closed)
