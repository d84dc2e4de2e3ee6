"""Issue 16 probe: would a wavelet transform close the equal-RMSE gap on rough terrain?

At equal RMSE dftpcc compact stays above JPEG2000 on Davos (1.29x / 1.14x at 0.1 / 0.3 % of
the relief, docs/benchmarks.md) while it is below it on every other map. A global DCT spreads a
ridge over every coefficient; a wavelet keeps it local. This probe estimates what a wavelet
codec built on the same tools would need, as a bound rather than a coder: the DEM (plane
removed) through PyWavelets' CDF 9/7 (``bior4.4``, five levels, periodic extension), the
coefficients quantized with dftpcc's dead zone, and their cost counted as the ideal code length
under a two-sided geometric model fitted to each group (8 bits of side information a group, no
other header). Two groupings: one model per subband, and one per subband and class of the
already decoded neighbours' sizes (the activity classes of ``RESD`` kind 5: two per octave of
``2|W| + 2|N| + |NW| + |NE|``). The low band is coded as its horizontal differences.

Each variant sweeps the step, and its bits at each level are read off by log-log interpolation;
dftpcc's figure is the file ``compress(target_rmse=level)`` writes (mask and header included).

    .venv/bin/python -m benchmarks.probes.wavelets [--file earth_davos_10m.tif ...]

Prints a table; nothing here fails.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

import dftpcc
from dftpcc import quantizer
from dftpcc.encoder import encode_dem
from dftpcc.files import dem_from_geotiff
from dftpcc.fill import fill_empty
from dftpcc.params import make_params

from benchmarks.common import DEFAULT_DATA, markdown_table, warnings_as_notes

FILES = ("earth_davos_10m.tif", "mars_gale_1m.tif", "moon_kepler_lola_48m.tif")
#: Error levels as fractions of the RMS relief, as bench_anchors.py gives a DEM's.
LEVELS = (0.001, 0.003, 0.01)
WAVELET, LEVELS_OF_WAVELET, DEADZONE = "bior4.4", 5, 0.1
#: Steps swept, as multiples of the level's RMSE.
STEP_FACTORS = np.geomspace(0.5, 64.0, 22)


def geometric_bits(q: np.ndarray) -> float:
    """Ideal code length (bits) of integers ``q`` under a two-sided geometric fitted to their mean
    size, plus 8 bits for that parameter."""
    a = np.abs(q.ravel())
    mean = float(a.mean()) if a.size else 0.0
    if mean == 0.0:
        return 8.0
    decay = (np.sqrt(1.0 + mean * mean) - 1.0) / mean
    return float(-(np.log2((1 - decay) / (1 + decay)) * a.size + np.log2(decay) * a.sum())) + 8.0


def classes(q: np.ndarray) -> np.ndarray:
    """Kind 5's activity classes of each value from its causal neighbours W, N, NW, NE."""
    a = np.abs(q).astype(np.int64)
    act = np.zeros_like(a)
    act[:, 1:] += 2 * a[:, :-1]
    act[1:, :] += 2 * a[:-1, :]
    act[1:, 1:] += a[:-1, :-1]
    act[1:, :-1] += a[:-1, 1:]
    out = np.zeros_like(act)
    busy = act > 0
    b = np.floor(np.log2(act[busy])).astype(np.int64)
    second = (act[busy] >= (3 << b) >> 1).astype(np.int64)
    out[busy] = np.minimum(63, 2 * b + 1 + second)
    return out


def wavelet_point(pywt, heights: np.ndarray, mask: np.ndarray, step: float) -> tuple[float, float, float]:
    """(RMSE on occupied cells, bits with one model per subband, bits per subband and class)."""
    parts = pywt.wavedec2(heights, WAVELET, mode="periodization", level=LEVELS_OF_WAVELET)
    q0 = quantizer.quantize(parts[0], step, DEADZONE)
    low = geometric_bits(np.diff(q0, axis=1, prepend=0))
    plain = contexts = low
    rebuilt = [quantizer.dequantize(q0, step)]
    for details in parts[1:]:
        level = []
        for band in details:
            q = quantizer.quantize(band, step, DEADZONE)
            plain += geometric_bits(q)
            cls = classes(q)
            contexts += sum(geometric_bits(q[cls == c]) for c in np.unique(cls))
            level.append(quantizer.dequantize(q, step))
        rebuilt.append(tuple(level))
    out = pywt.waverec2(rebuilt, WAVELET, mode="periodization")[: heights.shape[0], : heights.shape[1]]
    err = (out - heights)[mask]
    return float(np.sqrt(np.mean(err * err))), plain, contexts


def at_level(points: list[tuple[float, float]], level: float) -> float:
    """Bits at RMSE ``level`` by log-log interpolation along the cheapest points (nan: out of range)."""
    frontier: list[tuple[float, float]] = []
    for rmse, bits in sorted(points):
        if not frontier or bits < frontier[-1][1]:
            frontier.append((rmse, bits))
    for (r0, b0), (r1, b1) in zip(frontier, frontier[1:]):
        if r0 <= level <= r1:
            t = np.log(level / r0) / np.log(r1 / r0)
            return float(np.exp(np.log(b0) + t * np.log(b1 / b0)))
    return float("nan")


def probe(pywt, name: str) -> list[list[str]]:
    dem, _ = dem_from_geotiff(DEFAULT_DATA / "dems" / name)
    mask, n = dem.mask, int(dem.mask.sum())
    r, c = np.nonzero(mask)
    plane, *_ = np.linalg.lstsq(np.c_[np.ones(r.size), c, r], dem.heights[mask], rcond=None)
    rr, cc = np.mgrid[0:mask.shape[0], 0:mask.shape[1]]
    detrended = fill_empty(dem.heights - (plane[0] + plane[1] * cc + plane[2] * rr), mask, method="smooth")
    relief = float(np.std(dem.heights[mask]))
    rows = []
    for fraction in LEVELS:
        level = fraction * relief
        sweep = [wavelet_point(pywt, detrended, mask, f * level) for f in STEP_FACTORS]
        plain = at_level([(e, b / n) for e, b, _ in sweep], level)
        contexts = at_level([(e, b / n) for e, _, b in sweep], level)
        data = encode_dem(dem, make_params(resolution=dem.grid.resolution, target_rmse=level))
        with dftpcc.open(data) as cmap:
            layout = cmap.info().get("residual_layout")
        ours = 8 * len(data) / n
        rows.append([name, f"{100 * fraction:g} % ({1000 * level:.1f} mm)",
                     f"{ours:.3f}" + (" (predicted map)" if layout else ""),
                     f"{plain:.3f}", f"{contexts:.3f}", f"{contexts / ours:.2f}"])
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--file", nargs="+", default=list(FILES), help="GeoTIFFs under dems/")
    args = parser.parse_args(argv)
    try:
        import pywt
    except ImportError:
        print("probes/wavelets needs PyWavelets: pip install -e '.[compare]'", file=sys.stderr)
        return 2
    rows: list[list[str]] = []
    notes: list[str] = []
    with warnings_as_notes(notes):
        for name in args.file:
            rows += probe(pywt, name)
    print(markdown_table(["DEM", "RMSE level (of relief)", "dftpcc file bits/cell",
                          "CDF 9/7, a model per subband (bound)", "CDF 9/7, per subband and class (bound)",
                          "classes / dftpcc"], rows))
    for note in notes:
        print(f"note: {note}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
