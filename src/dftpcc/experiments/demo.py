"""The demo: the whole pipeline on the built-in terrain, as a table."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np

from ..mapfile import decompress
from ..encoder import compress
from ..mapfile import open as open_map
from .terrain import regolith_plain

__all__ = ["run_demo"]

DEMO_CUTOFFS = (0.0, 0.5, 0.8, 0.9, 0.95)
#: The rate-control example asks for a DEM RMSE of this many gridding floors.
DEMO_TARGET_FLOORS = 1.0
#: Fractions of the file the progressive-decoding example reads.
DEMO_PREFIXES = (0.1, 0.25, 0.5, 1.0)


def run_demo(*, n_points: int = 300_000, resolution: float = 0.25, out: str | None = None, seed: int = 0,
             show: Callable[[str], None] = print) -> list[dict]:
    """Compress the built-in regolith plain with both profiles at several cutoffs; print a table.

    Returns the rows printed (one dict per profile and cutoff).
    """
    points = regolith_plain(n_points, seed=seed)
    show(f"built-in terrain: regolith plain, {points.shape[0]:,} points, {resolution} m cells "
          f"(seed {seed})")
    header = (f"{'profile':<8} {'f_c':>5} {'bytes':>10} {'bits/pt':>8} {'vert RMSE mm':>12} "
              f"{'x floor':>7} {'enc ms':>7} {'dec ms':>7}")
    show(header)
    show("-" * len(header))
    rows = []
    folder = Path(out) if out else None
    if folder:
        folder.mkdir(parents=True, exist_ok=True)
        np.save(folder / "demo_terrain.npy", points)
    for profile in ("paper", "compact"):
        for cutoff in DEMO_CUTOFFS:
            t0 = time.perf_counter()
            data = compress(points, resolution=resolution, cutoff=cutoff, profile=profile)
            t1 = time.perf_counter()
            decompress(data)
            t2 = time.perf_counter()
            stats = open_map(data).header.stats
            row = dict(profile=profile, cutoff=cutoff, bytes=len(data), bpp=8 * len(data) / points.shape[0],
                       vertical_rmse_m=stats["vertical_rmse_m"], floor_m=stats["gridding_rmse_m"],
                       encode_s=t1 - t0, decode_s=t2 - t1)
            rows.append(row)
            show(f"{profile:<8} {cutoff:>5.2f} {len(data):>10,} {row['bpp']:>8.3f} "
                  f"{row['vertical_rmse_m'] * 1000:>12.1f} {row['vertical_rmse_m'] / row['floor_m']:>7.2f} "
                  f"{row['encode_s'] * 1000:>7.0f} {row['decode_s'] * 1000:>7.0f}")
            if folder:
                (folder / f"demo_{profile}_fc{cutoff:.2f}.dftpc").write_bytes(data)
    show("vert RMSE: each point against its cell's rebuilt height; floor: against its cell's mean "
          "(the best any DEM at this resolution can do).")

    floor = rows[0]["floor_m"]
    target = DEMO_TARGET_FLOORS * floor
    t0 = time.perf_counter()
    data = compress(points, resolution=resolution, target_rmse=target)
    m = open_map(data)
    stats = m.header.stats
    layer = (f" and a residual layer of max error {m.params.target_max_error * 1000:.1f} mm"
             if stats.get("residual_bytes") else "")
    show(f"\nrate control, --target-rmse {target * 1000:.1f} mm: chose f_c {m.params.cutoff}, step "
          f"{m.params.step * 1000:.1f} mm{layer} -> {len(data):,} bytes ({8 * len(data) / points.shape[0]:.3f} "
          f"bits/pt), DEM RMSE {stats['dem_rmse_m'] * 1000:.1f} mm [{time.perf_counter() - t0:.1f} s]")
    full = m.read_dem()
    coef_bytes, resd_bytes = stats["coef_bytes"], stats.get("residual_bytes", 0)
    # Everything before the coefficients (mask included) must arrive; a residual layer comes last.
    head = len(data) - coef_bytes - resd_bytes
    show("progressive decoding of that file: header and mask, then a part of the coefficients, as if "
          "the rest had not arrived:")
    prefixes = [(head + int(coef_bytes * f), f"{f:4.0%} of the coefficients") for f in DEMO_PREFIXES]
    if resd_bytes:
        prefixes.append((len(data), "and the residual layer"))
    for n, what in prefixes:
        dem = open_map(data, max_bytes=n).read_dem()
        err = (dem.heights - full.heights)[full.mask]
        show(f"  first {n:>7,} bytes ({what}): RMSE {np.sqrt(np.mean(err * err)) * 1000:7.1f} mm from the full decode")
    return rows
