"""Issue 3 probe: would rate-distortion optimised rounding or a per-band step beat the dead-zone quantizer?

For one map and cutoff, find the quantizer step that brings the rebuilt DEM to
a target RMSE (occupied cells) under each rounding rule, then code the
coefficients with the library's coder and compare sizes:

* ``dead zone d``: ``floor(|c|/step + 0.5 - d)`` (the library's rule, d = 0.1);
* ``RDO l``: plain rounding, then each nonzero value moves one step toward 0
  when the squared error it adds (in steps^2) is below ``l`` times the bits
  it saves under a Laplace model per frequency ring (two passes);
* ``band step a``: a step growing with frequency, ``step * (1 + a * radius /
  largest radius)``, dead zone 0.1 (what a per-band step would do; the coder
  is given the integers as they are, so its size is what such a file would
  need apart from the per-band step table).

    .venv/bin/python -m benchmarks.probes.rdo [--file field_gentle_ign.laz --resolution 0.5 --classes 2]
        [--cutoff 0.2 --multiple 1.25]

The target is the DEM error that makes the points' vertical RMSE ``multiple``
times the gridding floor: ``floor * sqrt(multiple**2 - 1)``. Prints a table;
nothing here fails.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

import dftpcc
from dftpcc import coding, quantizer
from dftpcc.analysis import Analysis
from dftpcc.encoder import grid_points

from benchmarks.common import DEFAULT_DATA, warnings_as_notes

RULES = (("dead zone", 0.0), ("dead zone", 0.1), ("dead zone", 0.2), ("dead zone", 0.3),
         ("RDO", 0.05), ("RDO", 0.1), ("RDO", 0.2), ("band step", 0.5), ("band step", 1.0), ("band step", -0.3))


def _laplace_bits(q: np.ndarray, bands: np.ndarray):
    """Bits of each value under a discrete Laplace fitted per band (mean |q|)."""
    n = int(bands.max()) + 1
    mean = np.bincount(bands, weights=np.abs(q), minlength=n) / np.maximum(np.bincount(bands, minlength=n), 1)
    t = np.exp(-1.0 / np.maximum(mean[bands], 0.05))
    return lambda v: -np.log2((1 - t) / (1 + t)) - np.abs(v) * np.log2(t)


def steps_of(step: float, rule: str, value: float, radius: np.ndarray) -> np.ndarray | float:
    """The step of each coefficient."""
    if rule == "band step":
        return step * (1 + value * radius / max(float(radius.max()), 1e-12))
    return step


def quantize(x: np.ndarray, step: float, rule: str, value: float, bands: np.ndarray,
             radius: np.ndarray) -> np.ndarray:
    if rule == "dead zone":
        return quantizer.quantize(x, step, value)
    if rule == "band step":
        per = steps_of(step, rule, value, radius)
        return (np.sign(x) * np.floor(np.abs(x) / per + 0.4)).astype(np.int64)
    q = quantizer.quantize(x, step, 0.0)
    a = np.abs(x) / step
    for _ in range(2):
        bits = _laplace_bits(q, bands)
        toward = q - np.sign(q)
        added = (a - np.abs(toward)) ** 2 - (a - np.abs(q)) ** 2
        q = np.where((q != 0) & (added < value * (bits(q) - bits(toward))), toward, q)
    return q


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--file", default="field_gentle_ign.laz")
    ap.add_argument("--resolution", type=float, default=0.5)
    ap.add_argument("--classes", type=int, nargs="*", default=[2])
    ap.add_argument("--cutoff", type=float, default=0.2)
    ap.add_argument("--multiple", type=float, default=1.25)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    args = ap.parse_args()
    with warnings_as_notes([]):
        points = dftpcc.read(args.data / "pointclouds" / args.file, classes=args.classes or None).points
        params = dftpcc.make_params(resolution=args.resolution, cutoff=args.cutoff)
        dem = grid_points(points, params)
    spec = Analysis(dem, params, searching=False)
    n = spec.count(args.cutoff)
    x, radius, angle = spec.reals(n), spec.radius[:n], spec.angle[:n]
    bands = coding.band_ids(radius, angle, 0)
    target = dem.gridding_rmse * math.sqrt(args.multiple ** 2 - 1)

    def dem_rmse(q: np.ndarray, step: np.ndarray | float) -> float:
        err = (spec.synthesise(q * step) - dem.heights)[dem.mask]
        return math.sqrt(float(np.mean(err * err)))

    if dem_rmse(quantizer.quantize(x, 1e-9, 0.0), 1e-9) > target:
        print(f"f_c {args.cutoff} alone exceeds the target {1e3 * target:.1f} mm: choose a lower cutoff")
        return 1
    print(f"{args.file}, f_c {args.cutoff}, {n:,} coefficients; target DEM RMSE {1e3 * target:.2f} mm "
          f"({args.multiple}x the {1e3 * dem.gridding_rmse:.1f} mm floor on the points)\n")
    print("| rounding | parameter | step mm | DEM RMSE mm | coefficient bytes | vs dead zone 0.1 |")
    print("|---|---|---|---|---|---|")
    rows = []
    for rule, value in RULES:
        lo, hi = target * 1e-3, target * 1e3
        while hi / lo > 1.003:
            mid = math.sqrt(lo * hi)
            q = quantize(x, mid, rule, value, bands, radius)
            lo, hi = (mid, hi) if dem_rmse(q, steps_of(mid, rule, value, radius)) <= target else (lo, mid)
        q = quantize(x, lo, rule, value, bands, radius)
        rows.append((rule, value, lo, dem_rmse(q, steps_of(lo, rule, value, radius)),
                     len(coding.encode_coefficients(q, radius=radius, angle=angle))))
    base = next(r[4] for r in rows if r[:2] == ("dead zone", 0.1))
    for rule, value, step, err, size in rows:
        print(f"| {rule} | {value:g} | {1e3 * step:.2f} | {1e3 * err:.2f} | {size:,} | {size / base:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
