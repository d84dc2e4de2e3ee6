"""Measure stage: how far a rebuilt cloud is from the original, and what it cost.

Pure functions on ``(N, 3)`` float arrays in metres. The codec rebuilds one
point per occupied DEM cell, not one per original point, so every metric
here states how it pairs the two clouds. Nearest-neighbour searches use
``scipy.spatial.cKDTree`` on every core; :func:`evaluate` computes each
search once and shares it between the metrics, and accepts prebuilt search
structures so a sweep over cutoffs builds them once per terrain.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from .errors import InvalidInputError

__all__ = [
    "bits_per_point",
    "build_tree",
    "nearest_distances",
    "paper_rmse",
    "vertical_errors",
    "VerticalErrors",
    "point_to_point",
    "PointToPoint",
    "psnr",
    "chamfer_distance",
    "hausdorff_distance",
    "XYInterpolator",
    "xy_interpolator",
    "evaluate",
]

#: Worker threads for cKDTree queries; -1 uses every core.
KD_WORKERS = -1
#: Percentile reported for the vertical error (per cent).
VERTICAL_PERCENTILE = 95.0
#: Rebuilt points used to interpolate the rebuilt surface at an x, y.
TRIANGLE = 3
#: A triangle whose area is below this fraction of the squared distance to
#: its farthest vertex is treated as degenerate (collinear vertices).
DEGENERATE_AREA = 1e-9
#: Barycentric weights may extrapolate down to minus this; further out the
#: triangle says little about the point and the nearest rebuilt height is used.
MAX_EXTRAPOLATION = 0.5
#: Query points are shifted this far (metres) towards +x, +y before the
#: nearest rebuilt point is looked up, so a point on the edge between two
#: cells goes to the cell ``floor()`` put it in when the DEM was gridded.
TIE_BREAK = 1e-6
#: MPEG D1 PSNR counts the three coordinates: PSNR = 10 log10(3 p^2 / MSE).
D1_PSNR_FACTOR = 3.0


def _cloud(points: Any, name: str) -> np.ndarray:
    """Shared shape/dtype check: a non-empty, finite (N, 3) float64 array."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidInputError(f"{name} must have shape (N, 3), got {arr.shape}")
    if arr.shape[0] == 0:
        raise InvalidInputError(f"{name} is empty")
    if not np.isfinite(arr).all():
        raise InvalidInputError(f"{name} has NaN or infinite coordinates")
    return arr


def build_tree(points: Any) -> cKDTree:
    """A k-d tree on a cloud's x, y, z, for :func:`nearest_distances` and :func:`evaluate`.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Metres.
    """
    # An unbalanced tree builds ~3x faster and queries about as fast on
    # survey data, which is what a sweep rebuilding one tree per cutoff needs.
    return cKDTree(_cloud(points, "points"), balanced_tree=False, compact_nodes=False)


def bits_per_point(n_bytes: int, n_points: int) -> float:
    """Compressed size over original points, in bits per point.

    Parameters
    ----------
    n_bytes : int
        Size of the compressed map in bytes (the whole ``.dftpc`` file).
    n_points : int
        Points of the original cloud (not of the rebuilt one).

    Returns
    -------
    float
        ``8 * n_bytes / n_points`` bits per point.
    """
    if n_points <= 0:
        raise InvalidInputError(f"n_points must be positive, got {n_points}")
    if n_bytes < 0:
        raise InvalidInputError(f"n_bytes must be >= 0, got {n_bytes}")
    return 8.0 * n_bytes / n_points


def nearest_distances(query: Any, reference: Any, *, tree: cKDTree | None = None) -> np.ndarray:
    """Euclidean distance in metres from each query point to its nearest reference point.

    Parameters
    ----------
    query : array_like, shape (N, 3)
    reference : array_like, shape (M, 3)
    tree : cKDTree, optional
        A tree already built on ``reference`` (reused across calls).

    Returns
    -------
    ndarray, shape (N,), float64
        Metres.
    """
    query = _cloud(query, "query")
    if tree is None:
        tree = build_tree(reference)
    dist, _ = tree.query(query, k=1, workers=KD_WORKERS)
    return dist


@dataclass(frozen=True)
class XYInterpolator:
    """Where each query x, y falls on the surface of a rebuilt cloud.

    The surface at ``(x, y)`` is the plane through the :data:`TRIANGLE`
    rebuilt points nearest in x, y, evaluated by barycentric weights: a
    facet of a local triangulation. It is exact on planes and, on a gridded
    map (one point per cell centre), the three nearest centres always form
    a half-cell triangle containing the point, so it equals linear
    interpolation of the DEM. Where the triangle is degenerate or lies far
    from the point, the nearest rebuilt height is used.

    Attributes
    ----------
    index : ndarray, shape (N, TRIANGLE), int
        Rebuilt points used for each query point; column 0 is the nearest in x, y.
    weights : ndarray, shape (N, TRIANGLE), float64
        Barycentric weights, each row summing to 1.
    """

    index: np.ndarray
    weights: np.ndarray

    @property
    def nearest(self) -> np.ndarray:
        """Index of the rebuilt point nearest in x, y to each query point."""
        return self.index[:, 0]

    def __call__(self, z: np.ndarray) -> np.ndarray:
        """Heights (metres) of the surface at the query points, from rebuilt heights ``z``."""
        return np.einsum("ij,ij->i", self.weights, np.asarray(z, dtype=np.float64)[self.index])


def xy_interpolator(rebuilt_xy: Any, query_xy: Any) -> XYInterpolator:
    """Build the :class:`XYInterpolator` of ``query_xy`` on a rebuilt cloud's x, y.

    Parameters
    ----------
    rebuilt_xy : array_like, shape (M, 2)
        Horizontal positions of the rebuilt points, metres.
    query_xy : array_like, shape (N, 2)
        Where to evaluate the surface, metres.

    Notes
    -----
    Depends only on x, y, so it is built once for every cutoff of a sweep
    (the occupied cells, hence the rebuilt x, y, do not change with the cutoff).
    """
    ref = np.asarray(rebuilt_xy, dtype=np.float64)[:, :2]
    qxy = np.asarray(query_xy, dtype=np.float64)[:, :2]
    k = min(TRIANGLE, ref.shape[0])
    tree = cKDTree(ref, balanced_tree=False, compact_nodes=False)
    _, idx = tree.query(qxy + TIE_BREAK, k=k, workers=KD_WORKERS)
    idx = idx.reshape(qxy.shape[0], k)
    weights = np.zeros((qxy.shape[0], TRIANGLE))
    index = np.zeros((qxy.shape[0], TRIANGLE), dtype=np.int64)
    index[:, :k] = idx
    index[:, k:] = idx[:, :1]
    weights[:, 0] = 1.0
    if k < TRIANGLE:
        return XYInterpolator(index, weights)
    a, b, c = ref[idx[:, 0]], ref[idx[:, 1]], ref[idx[:, 2]]
    e1, e2, d = b - a, c - a, qxy - a
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    scale = np.maximum((e1 * e1).sum(axis=1), (e2 * e2).sum(axis=1))
    ok = np.abs(det) > DEGENERATE_AREA * scale
    safe = np.where(ok, det, 1.0)
    wb = (d[:, 0] * e2[:, 1] - d[:, 1] * e2[:, 0]) / safe
    wc = (e1[:, 0] * d[:, 1] - e1[:, 1] * d[:, 0]) / safe
    wa = 1.0 - wb - wc
    bary = np.column_stack([wa, wb, wc])
    ok &= bary.min(axis=1) >= -MAX_EXTRAPOLATION
    weights[ok] = bary[ok]
    return XYInterpolator(index, weights)


def paper_rmse(original: Any, rebuilt: Any, *, include_horizontal: bool = False,
               interpolator: XYInterpolator | None = None) -> float:
    """The paper's RMSE (its eq. 4-5), in metres.

    ``RMSE = sqrt(mean_i |p_i - p'_i|^2)`` over the N original points. The
    paper needs a partner ``p'_i`` for every original point, but the rebuilt
    map has one point per occupied cell. We pair each original point with
    the rebuilt point nearest to it in x, y; on a dftpcc map that is the
    point rebuilt from the point's own cell (its centre is the closest),
    i.e. the cell that point was averaged into.

    By default only the vertical part of ``p_i - p'_i`` counts: the DEM puts
    every rebuilt point at its cell centre whatever the cutoff, so the
    horizontal offset is the same at every cutoff (about 0.41 x resolution
    RMS for points spread evenly in a cell) and would only add a floor set
    by the resolution, hiding what the cutoff does. Pass
    ``include_horizontal=True`` for the literal 3D norm.

    Parameters
    ----------
    original : array_like, shape (N, 3)
        Metres.
    rebuilt : array_like, shape (M, 3)
        Metres.
    include_horizontal : bool, keyword-only
        Count the x, y offset to the partner too (3D distance).
    interpolator : XYInterpolator, keyword-only, optional
        Prebuilt by :func:`xy_interpolator` from ``rebuilt`` and ``original``.

    Returns
    -------
    float
        Metres.
    """
    original = _cloud(original, "original")
    rebuilt = _cloud(rebuilt, "rebuilt")
    if interpolator is None:
        interpolator = xy_interpolator(rebuilt, original)
    partner = rebuilt[interpolator.nearest]
    diff = (original - partner) if include_horizontal else (original[:, 2:] - partner[:, 2:])
    return float(np.sqrt(np.mean(np.einsum("ij,ij->i", diff, diff))))


@dataclass(frozen=True)
class VerticalErrors:
    """Vertical error of the original points against the rebuilt surface, metres.

    Attributes
    ----------
    rmse : float
        Root mean square, metres.
    max : float
        Largest absolute error, metres.
    p95 : float
        95th percentile of the absolute error, metres.
    """

    rmse: float
    max: float
    p95: float


def vertical_errors(original: Any, rebuilt: Any, *,
                    interpolator: XYInterpolator | None = None) -> VerticalErrors:
    """Height difference between each original point and the rebuilt surface at its x, y.

    The surface is the rebuilt cloud linearly interpolated (see
    :class:`XYInterpolator`), so a point on a slope is not charged for lying
    off its cell centre, unlike :func:`paper_rmse`.

    Parameters
    ----------
    original : array_like, shape (N, 3)
        Metres.
    rebuilt : array_like, shape (M, 3)
        Metres.
    interpolator : XYInterpolator, keyword-only, optional
        Prebuilt by :func:`xy_interpolator` from ``rebuilt`` and ``original``.

    Returns
    -------
    VerticalErrors
        RMSE, max and 95th percentile of ``|z - surface(x, y)|``, metres.
    """
    original = _cloud(original, "original")
    rebuilt = _cloud(rebuilt, "rebuilt")
    if interpolator is None:
        interpolator = xy_interpolator(rebuilt, original)
    err = np.abs(original[:, 2] - interpolator(rebuilt[:, 2]))
    return VerticalErrors(rmse=float(np.sqrt(np.mean(err * err))), max=float(err.max()),
                          p95=float(np.percentile(err, VERTICAL_PERCENTILE)))


@dataclass(frozen=True)
class PointToPoint:
    """MPEG D1 (point-to-point) geometry error, both directions.

    Attributes
    ----------
    rmse_forward : float
        RMS distance from each original point to its nearest rebuilt point, metres.
    rmse_backward : float
        RMS distance from each rebuilt point to its nearest original point, metres.
    rmse : float
        Symmetric D1: the larger of the two, metres (MPEG takes the worse direction).
    psnr : float
        ``10 log10(3 peak^2 / rmse^2)`` in dB; infinite for identical clouds.
    peak : float
        Peak value used for the PSNR, metres.
    """

    rmse_forward: float
    rmse_backward: float
    rmse: float
    psnr: float
    peak: float


def _default_peak(original: np.ndarray) -> float:
    return float(np.linalg.norm(np.ptp(original, axis=0)))


def psnr(mse: float, peak: float) -> float:
    """D1 PSNR in dB from a mean squared point distance (m^2) and a peak (m).

    ``10 log10(3 peak^2 / mse)`` as in MPEG's ``pc_error``: the factor 3 makes
    the peak a per-coordinate value. Infinite when ``mse`` is 0.
    """
    if peak <= 0:
        raise InvalidInputError(f"peak must be positive, got {peak}")
    if mse < 0:
        raise InvalidInputError(f"mse must be >= 0, got {mse}")
    return math.inf if mse == 0 else 10.0 * math.log10(D1_PSNR_FACTOR * peak * peak / mse)


def _d1(forward: np.ndarray, backward: np.ndarray, peak: float) -> PointToPoint:
    mse_f = float(np.mean(forward * forward))
    mse_b = float(np.mean(backward * backward))
    mse = max(mse_f, mse_b)
    return PointToPoint(rmse_forward=math.sqrt(mse_f), rmse_backward=math.sqrt(mse_b),
                        rmse=math.sqrt(mse), psnr=psnr(mse, peak), peak=peak)


def point_to_point(original: Any, rebuilt: Any, *, peak: float | None = None) -> PointToPoint:
    """Symmetric point-to-point (D1) RMSE and PSNR of the MPEG PCC metrics.

    Each point of one cloud is paired with its nearest neighbour in the
    other (3D, Euclidean), in both directions; the symmetric value is the
    worse direction.

    Parameters
    ----------
    original : array_like, shape (N, 3)
        Metres.
    rebuilt : array_like, shape (M, 3)
        Metres.
    peak : float, keyword-only, optional
        PSNR peak in metres; default the diagonal of the original's bounding box.

    Returns
    -------
    PointToPoint
    """
    original = _cloud(original, "original")
    rebuilt = _cloud(rebuilt, "rebuilt")
    peak = _default_peak(original) if peak is None else float(peak)
    return _d1(nearest_distances(original, rebuilt), nearest_distances(rebuilt, original), peak)


def chamfer_distance(a: Any, b: Any) -> float:
    """Chamfer distance in metres: ``mean_a d(a, B) + mean_b d(b, A)``.

    Sum of the two mean nearest-neighbour distances (not squared); symmetric.
    """
    a, b = _cloud(a, "a"), _cloud(b, "b")
    return float(nearest_distances(a, b).mean() + nearest_distances(b, a).mean())


def hausdorff_distance(a: Any, b: Any) -> float:
    """Hausdorff distance in metres: ``max(max_a d(a, B), max_b d(b, A))``; symmetric."""
    a, b = _cloud(a, "a"), _cloud(b, "b")
    return float(max(nearest_distances(a, b).max(), nearest_distances(b, a).max()))


def evaluate(original: Any, rebuilt: Any, *, compressed_bytes: int | None = None,
             peak: float | None = None, original_tree: cKDTree | None = None,
             interpolator: XYInterpolator | None = None, vertical_only: bool = False) -> dict[str, float]:
    """Every metric of this module at once, each nearest-neighbour search done once.

    Parameters
    ----------
    original : array_like, shape (N, 3)
        Metres.
    rebuilt : array_like, shape (M, 3)
        Metres.
    compressed_bytes : int, keyword-only, optional
        Size of the compressed map; adds ``bytes`` and ``bits_per_point``.
    peak : float, keyword-only, optional
        D1 PSNR peak in metres (default: the original's bounding-box diagonal).
    original_tree : cKDTree, keyword-only, optional
        Tree on ``original``, reused across calls with the same original.
    interpolator : XYInterpolator, keyword-only, optional
        From :func:`xy_interpolator`, reused while the rebuilt x, y are the same.
    vertical_only : bool, keyword-only
        Only the metrics that compare heights at the same x, y (``paper_rmse_m`` and the
        ``vertical_*``): where x and y are degrees of longitude and latitude and z metres, a
        3D distance (D1, PSNR, Chamfer, Hausdorff) adds degrees to metres and means nothing.

    Returns
    -------
    dict
        ``points_original``, ``points_rebuilt``, ``paper_rmse_m``,
        ``paper_rmse_3d_m``, ``vertical_rmse_m``, ``vertical_max_m``,
        ``vertical_p95_m``, ``d1_rmse_m``, ``d1_rmse_forward_m``,
        ``d1_rmse_backward_m``, ``d1_psnr_db``, ``psnr_peak_m``,
        ``chamfer_m``, ``hausdorff_m`` and, with ``compressed_bytes``,
        ``bytes`` and ``bits_per_point``. Distances in metres.
    """
    original = _cloud(original, "original")
    rebuilt = _cloud(rebuilt, "rebuilt")
    if interpolator is None:
        interpolator = xy_interpolator(rebuilt, original)
    if vertical_only:
        vert = vertical_errors(original, rebuilt, interpolator=interpolator)
        out = {"points_original": int(original.shape[0]), "points_rebuilt": int(rebuilt.shape[0]),
               "paper_rmse_m": paper_rmse(original, rebuilt, interpolator=interpolator),
               "vertical_rmse_m": vert.rmse, "vertical_max_m": vert.max, "vertical_p95_m": vert.p95}
        if compressed_bytes is not None:
            out["bytes"] = int(compressed_bytes)
            out["bits_per_point"] = bits_per_point(compressed_bytes, original.shape[0])
        return out
    if original_tree is None:
        original_tree = build_tree(original)
    forward = nearest_distances(original, rebuilt)
    backward = nearest_distances(rebuilt, original, tree=original_tree)
    d1 = _d1(forward, backward, _default_peak(original) if peak is None else float(peak))
    vert = vertical_errors(original, rebuilt, interpolator=interpolator)
    out: dict[str, float] = {
        "points_original": int(original.shape[0]),
        "points_rebuilt": int(rebuilt.shape[0]),
        "paper_rmse_m": paper_rmse(original, rebuilt, interpolator=interpolator),
        "paper_rmse_3d_m": paper_rmse(original, rebuilt, include_horizontal=True, interpolator=interpolator),
        "vertical_rmse_m": vert.rmse,
        "vertical_max_m": vert.max,
        "vertical_p95_m": vert.p95,
        "d1_rmse_m": d1.rmse,
        "d1_rmse_forward_m": d1.rmse_forward,
        "d1_rmse_backward_m": d1.rmse_backward,
        "d1_psnr_db": d1.psnr,
        "psnr_peak_m": d1.peak,
        "chamfer_m": float(forward.mean() + backward.mean()),
        "hausdorff_m": float(max(forward.max(), backward.max())),
    }
    if compressed_bytes is not None:
        out["bytes"] = int(compressed_bytes)
        out["bits_per_point"] = bits_per_point(compressed_bytes, original.shape[0])
    return out
