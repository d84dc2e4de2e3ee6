"""A built-in terrain so the demo and self-contained tests need no download.

A gentle regolith plain: a long-wavelength undulation, bowl-shaped craters
with raised rims, scattered rocks, and sensor noise, sampled by a rover-like
scan with an irregular (disc-sector) footprint. Deterministic by seed.
"""

from __future__ import annotations

import numpy as np

__all__ = ["regolith_plain"]


def regolith_plain(n_points: int = 200_000, *, size: float = 100.0, craters: int = 12,
                   rocks: int = 150, noise: float = 0.01, seed: int = 0) -> np.ndarray:
    """Points of a synthetic lunar-like plain.

    Parameters
    ----------
    n_points : int
        Points to draw (before the footprint crop keeps about 70 % of them).
    size : float
        Side of the square survey area in metres.
    craters, rocks : int
        How many craters (radius 2-12 m) and rocks (radius 0.2-0.8 m).
    noise : float
        Standard deviation of vertical sensor noise in metres.
    seed : int

    Returns
    -------
    ndarray, shape (N, 3), float64
        x, y, z in metres, in a local frame with its origin at a corner.
    """
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, size, size=(n_points, 2))
    # The rover saw a sector of a disc around its start point: an irregular footprint.
    d = np.hypot(xy[:, 0], xy[:, 1])
    xy = xy[d < size * 1.1]
    x, y = xy[:, 0], xy[:, 1]
    z = 0.02 * x + 0.01 * y  # regional slope (metres per metre)
    z += 0.6 * np.sin(2 * np.pi * x / (0.9 * size)) * np.cos(2 * np.pi * y / (1.3 * size))
    for _ in range(craters):
        cx, cy = rng.uniform(0, size, 2)
        radius = rng.uniform(2.0, 12.0)
        depth = 0.2 * radius
        rho = np.hypot(x - cx, y - cy) / radius
        bowl = np.where(rho < 1.0, depth * (rho**2 - 1.0), 0.0)
        rim = 0.15 * depth * np.exp(-((rho - 1.0) / 0.25) ** 2)
        z += bowl + rim
    for _ in range(rocks):
        cx, cy = rng.uniform(0, size, 2)
        radius = rng.uniform(0.2, 0.8)
        r2 = ((x - cx) ** 2 + (y - cy) ** 2) / radius**2
        z += np.where(r2 < 1.0, 0.6 * radius * np.sqrt(np.clip(1.0 - r2, 0.0, None)), 0.0)
    z += rng.normal(0.0, noise, size=z.shape)
    return np.column_stack([x, y, z])
