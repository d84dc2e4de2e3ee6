"""Issue 16 probe: what would close the gap to JPEG XL at equal maximum error?

At a maximum-error target dftpcc codes a low-passed, quantized DCT and a residual layer
(``RESD``): one integer per cell, the remaining error on steps of 2E, coded as independent
values (one two-sided geometric per chunk, no spatial context). On rough terrain (Davos) the
residual is most of the file and JPEG XL, lossless on the heights quantized to the same 2E
steps, is 11-15 % smaller. Two ways to close that, estimated here as entropy bounds (the
empirical entropy with the statistics known in advance: no learning, no table cost, so a real
coder pays somewhat more):

- **a context model for the residual as it is**: each value given the activity of its causal
  neighbours (``2|W| + 2|N| + |NW| + |NE| + |WW| + |NN|`` of the residual, in 12 classes of
  equal population);
- **predictive coding of the quantized heights** (what lossless image coders do): the heights on
  steps of 2E from their minimum, each predicted from its causal neighbours (planar ``W + N - NW``,
  LOCO-I's median predictor, and a linear predictor of seven neighbours whose weights are fitted
  by least squares over the map, or per activity class), the prediction error coded alone and given the local gradient
  activity ``|W - WW| + |N - NW| + |N - NE| + |W - NW| + |N - NN| + |NE - NNE|`` in 12 classes.

(The predictive layer these estimates argued for is now built: docs/format.md, ``RESD`` kind 5,
its errors coded given the neighbours' errors; docs/benchmarks.md has what it gives.)

JPEG XL (libjxl, effort 7, one thread) on the same quantized heights is measured in the same run,
as benchmarks/max_error.py charges it (its bytes plus the raster anchors' 64-byte header and
occupancy bitmap). The DEMs and bounds are max_error.py's.

    .venv/bin/python -m benchmarks.probes.residual [--files earth_davos_10m.tif ...]

Prints a table; nothing here fails.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import dftpcc
from benchmarks import max_error
from benchmarks.bench_anchors import CASES
from benchmarks.common import DEFAULT_DATA, library_label, load, load_average, markdown_table, pick_cases
from benchmarks.rasters import make_raster
from dftpcc.format.reader import _sections
from dftpcc.residual import decode_residual

#: Classes of context activity, each holding the same share of the cells.
CLASSES = 12


def entropy_bytes(values: np.ndarray) -> float:
    """Empirical order-0 entropy of integers, bytes."""
    _, counts = np.unique(values, return_counts=True)
    p = counts / counts.sum()
    return float(-(counts * np.log2(p)).sum() / 8)


def conditional_bytes(values: np.ndarray, activity: np.ndarray) -> float:
    """Entropy of ``values`` given ``activity`` cut into :data:`CLASSES` classes of equal population."""
    edges = np.unique(np.quantile(activity, np.linspace(0, 1, CLASSES + 1)[1:-1]))
    classes = np.searchsorted(edges, activity, side="right")
    return sum(entropy_bytes(values[classes == k]) for k in np.unique(classes))


def adaptive_bytes(values: np.ndarray, activity: np.ndarray) -> float:
    """What an adaptive coder pays for ``values`` given ``activity`` in :data:`CLASSES` classes: each
    class learns its own counts from nothing (the Krichevsky-Trofimov estimator, a count of 1/2 for
    each of the values that occur anywhere), so the cost of learning the statistics is counted;
    the code length does not depend on the order of the values (scipy's ``gammaln``)."""
    from scipy.special import gammaln

    edges = np.unique(np.quantile(activity, np.linspace(0, 1, CLASSES + 1)[1:-1]))
    classes = np.searchsorted(edges, activity, side="right")
    alphabet = np.unique(values)
    nats = 0.0
    for k in np.unique(classes):
        counts = np.bincount(np.searchsorted(alphabet, values[classes == k]), minlength=alphabet.size)
        nats += (gammaln(counts.sum() + 0.5 * alphabet.size) - gammaln(0.5 * alphabet.size)
                 - float(np.sum(gammaln(counts + 0.5) - gammaln(0.5))))
    return nats / np.log(2) / 8


def neighbours(a: np.ndarray) -> dict[str, np.ndarray]:
    """The causal neighbours of every cell (raster order), edges replicated."""
    p = np.pad(a, 2, mode="edge")
    rows, cols = a.shape

    def at(dy: int, dx: int) -> np.ndarray:  # the cell dy rows up and dx columns left
        return p[2 - dy:2 - dy + rows, 2 - dx:2 - dx + cols]

    return {"W": at(0, 1), "N": at(1, 0), "NW": at(1, 1), "NE": at(1, -1), "WW": at(0, 2), "NN": at(2, 0),
            "NNE": at(2, -1)}


def residual_of(blob: bytes) -> tuple[np.ndarray, np.ndarray, int]:
    """The residual integers of a max-error file on its grid (0 off the mask), the mask, RESD bytes."""
    with dftpcc.open(blob) as cmap:
        mask = cmap.read_dem().mask
    sections, _ = _sections(memoryview(blob), allow_truncated_coef=False)
    resd = bytes(sections[b"RESD"])
    grid = np.zeros(mask.shape, dtype=np.int64)
    grid[mask] = decode_residual(resd, mask)
    return grid, mask, len(resd)


def residual_estimates(q: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """Order-0 and context-conditioned entropy of the residual, bytes."""
    a = np.abs(q)
    n = neighbours(a)
    activity = 2 * n["W"] + 2 * n["N"] + n["NW"] + n["NE"] + n["WW"] + n["NN"]
    return entropy_bytes(q[mask]), conditional_bytes(q[mask], activity[mask])


def predictive_estimates(levels: np.ndarray, mask: np.ndarray) -> dict[str, tuple[float, float]]:
    """Per predictor: order-0 and activity-conditioned entropy of the prediction error, and an adaptive coder's cost given activity, bytes."""
    n = neighbours(levels)
    w, north, nw = n["W"], n["N"], n["NW"]
    activity = (np.abs(w - n["WW"]) + np.abs(north - nw) + np.abs(north - n["NE"]) + np.abs(w - nw)
                + np.abs(north - n["NN"]) + np.abs(n["NE"] - n["NNE"]))
    median = np.where(nw >= np.maximum(w, north), np.minimum(w, north),
                      np.where(nw <= np.minimum(w, north), np.maximum(w, north), w + north - nw))
    edges = np.unique(np.quantile(activity[mask], np.linspace(0, 1, CLASSES + 1)[1:-1]))
    classes = np.searchsorted(edges, activity, side="right")
    out = {}
    for name, prediction in (("planar", w + north - nw), ("median", median),
                             ("least squares", least_squares_prediction(levels, mask, n)),
                             ("least squares per class", least_squares_prediction(levels, mask, n, classes))):
        error = (levels - prediction)[mask]
        out[name] = (entropy_bytes(error), conditional_bytes(error, activity[mask]),
                     adaptive_bytes(error, activity[mask]))
    return out


#: The causal neighbours a least-squares predictor weighs.
LS_NEIGHBOURS = ("W", "N", "NW", "NE", "WW", "NN", "NNE")


def least_squares_prediction(levels: np.ndarray, mask: np.ndarray, n: dict[str, np.ndarray],
                             classes: np.ndarray | None = None) -> np.ndarray:
    """Each level predicted as the rounded weighted sum of its :data:`LS_NEIGHBOURS`, the weights
    fitted by least squares over the occupied cells of the whole map, or of each activity class
    (``classes``: one per cell); a file would carry the weights, whose bytes are not counted."""
    x = np.stack([n[k].astype(np.float64) for k in LS_NEIGHBOURS], axis=-1)
    groups = np.zeros(levels.shape, dtype=np.int64) if classes is None else classes
    prediction = np.zeros(levels.shape)
    for g in np.unique(groups[mask]):
        fit = mask & (groups == g)
        weights, *_ = np.linalg.lstsq(x[fit], levels[fit].astype(np.float64), rcond=None)
        at = groups == g
        prediction[at] = x[at] @ weights
    return np.rint(prediction).astype(np.int64)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--files", nargs="*", help="DEMs of max_error.MAX_ERRORS (default: all)")
    ap.add_argument("--data", default=DEFAULT_DATA)
    args = ap.parse_args()
    t0 = time.perf_counter()
    print(f"Measuring {library_label()}; {load_average()}.", flush=True)
    jxl = next(c for c in max_error.codecs() if c.name.startswith("JPEG XL"))
    rows = []
    for case in [c for c in pick_cases(CASES, args.files) if c.name in max_error.MAX_ERRORS]:
        loaded = load(case, args.data)
        dem = max_error.bounded(loaded, make_raster(loaded.points, loaded.resolution))
        for bound in max_error.MAX_ERRORS[case.name]:
            size, blob = max_error._dftpcc_encode(dem, bound)
            q, mask, resd = residual_of(blob)
            r0, rctx = residual_estimates(q, mask)
            levels = max_error.quantized(dem, bound)[0].astype(np.int64)
            pred = predictive_estimates(levels, mask)
            jxl_bytes = jxl.encode(dem, bound)[0] if jxl.unable(dem, bound) is None else None
            # The file with the residual coded at the context bound: what a context model could reach.
            with_context = size - resd + rctx
            best_pred = min(v[1] for v in pred.values())
            rows.append([case.name, max_error.fmt_length(bound), f"{size:,}", f"{resd:,}", f"{r0:,.0f}",
                         f"{rctx:,.0f} ({(rctx - resd) / size:+.1%} of the file)",
                         f"{pred['planar'][0]:,.0f} / {pred['planar'][1]:,.0f}",
                         f"{pred['median'][0]:,.0f} / {pred['median'][1]:,.0f}",
                         f"{pred['least squares'][0]:,.0f} / {pred['least squares'][1]:,.0f}",
                         f"{pred['least squares per class'][0]:,.0f} / {pred['least squares per class'][1]:,.0f}",
                         f"{pred['least squares'][2]:,.0f}" + (f" ({pred['least squares'][2] / jxl_bytes:.3f})"
                                                               if jxl_bytes else ""),
                         f"{jxl_bytes:,}" if jxl_bytes else "—",
                         f"{size / jxl_bytes:.3f}" if jxl_bytes else "—",
                         f"{with_context / jxl_bytes:.3f}" if jxl_bytes else "—",
                         f"{best_pred / jxl_bytes:.3f}" if jxl_bytes else "—"])
            print(" | ".join(rows[-1]), flush=True)
    print()
    print(markdown_table(
        ["DEM", "E", "dftpcc bytes", "RESD bytes", "RESD order-0 bound", "RESD given context (bound)",
         "planar prediction: order-0 / given activity", "median prediction: order-0 / given activity",
         "least-squares prediction (7 neighbours): order-0 / given activity",
         "least squares per activity class: order-0 / given activity",
         "least squares, an adaptive coder given activity (/ JPEG XL)",
         "JPEG XL lossless, 2E steps", "dftpcc / JPEG XL", "with RESD at its context bound / JPEG XL",
         "best prediction bound / JPEG XL"], rows))
    print(f"\nRun time {time.perf_counter() - t0:.0f} s; {load_average()} at the end.")


if __name__ == "__main__":
    main()
