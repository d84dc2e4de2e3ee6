"""Shared pieces of the benchmark scripts: test files, timing, the error metric, RD curves.

The scripts measure, they never assert: targets are printed as PASS/MISS.
Everything here uses only dftpcc's public API (``read``, ``grid.fit_grid``,
``grid.rasterize``, the ``dem.Grid`` and ``dem.DEM`` types) plus numpy/scipy.
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import re
import statistics
import sys
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np
from scipy.spatial import cKDTree

import dftpcc
from dftpcc.dem import DEM, Grid
from dftpcc.grid import fit_grid, rasterize

REPO = Path(__file__).resolve().parent.parent
#: Real data lives beside the checkout (CI layout: ../shared/data); never copied into the repo.
DEFAULT_DATA = Path(os.environ.get("DFTPCC_DATA", REPO.parent / "shared" / "data"))
DOC = REPO / "docs" / "benchmarks.md"
FIGURES = REPO / "docs" / "figures"

#: LAS classification code of ground points.
GROUND = 2
#: A DEM sampled at pixel centres puts every point exactly on a cell edge of a
#: grid anchored at the first point, and rounding then drops some into the
#: neighbouring cell (17% of the Moon DEM's cells collide at the exact pixel
#: width). A cell this much (relative) smaller than the pixel keeps each point
#: inside its own cell, far enough from the edge that its nearest decoded cell
#: centre is its own even at UTM-size coordinates.
LATTICE_SHRINK = 1e-6
#: Errors below this (metres) count as this in log-log interpolation.
MIN_ERROR = 1e-9


@dataclass(frozen=True)
class Case:
    """One test file and how to grid it.

    Attributes
    ----------
    name : str
        File name under the data folder's ``pointclouds/`` or ``dems/``.
    resolution : float or None
        DEM cell size in metres; None for a GeoTIFF = its pixel size.
    classes : tuple of int or None
        LAS classes to keep (None = every point).
    terrain : str
        ``gentle`` or ``rough``: which target applies.
    """

    name: str
    resolution: float | None
    classes: tuple[int, ...] | None
    terrain: str

    @property
    def is_dem(self) -> bool:
        return self.name.endswith((".tif", ".tiff"))

    @property
    def stem(self) -> str:
        return Path(self.name).stem

    def path(self, data: Path) -> Path:
        return data / ("dems" if self.is_dem else "pointclouds") / self.name

    def label(self) -> str:
        what = " (ground class)" if self.classes == (GROUND,) else ""
        return f"{self.name}{what}"


@dataclass
class Loaded:
    """A case read into memory.

    Attributes
    ----------
    points : ndarray, shape (N, 3), float64, metres
    resolution : float
        Cell size actually used, metres.
    read_seconds : float
        Wall time of the file parsing (not part of any codec's time).
    notes : list of str
        Anything the reader of the table must know about this file.
    las_header : object or None
        laspy header of a LAS/LAZ source (scales/offsets for the LAZ reference).
    """

    case: Case
    points: np.ndarray
    resolution: float
    read_seconds: float
    notes: list[str]
    las_header: Any = None


def pick_cases(cases: Sequence[Case], wanted: Sequence[str] | None) -> list[Case]:
    """The cases whose file name starts with one of ``wanted`` (all when None)."""
    if not wanted:
        return list(cases)
    chosen = []
    for w in wanted:
        hits = [c for c in cases if c.name.startswith(w) or c.stem == w]
        if not hits:
            sys.exit(f"unknown file {w!r}; known: {', '.join(c.name for c in cases)}")
        chosen += [c for c in hits if c not in chosen]
    return chosen


def _sample_dem(path: Path) -> np.ndarray:
    """One point per valid pixel at its centre, as ``dftpcc.read`` does (metres)."""
    geotiff = dftpcc.io.geotiff  # the library's own GeoTIFF reading, imported on first use
    heights, valid, transform, _ = geotiff.read_raster_dem(path)
    return geotiff.pixel_centres(heights, valid, transform)


def _pixel_width(path: Path) -> float:
    """Width of a GeoTIFF's pixels in metres (its x step)."""
    import rasterio

    with rasterio.open(path) as src:
        return float(abs(src.transform.a))


def load(case: Case, data: Path) -> Loaded:
    """Read a case; GeoTIFFs become one point per valid pixel at the pixel size."""
    path = case.path(data)
    notes: list[str] = []
    header = None
    t0 = time.perf_counter()
    if case.is_dem:
        try:
            points = dftpcc.read(path).points
        except dftpcc.InvalidInputError as exc:
            # Same convention as dftpcc.read (pixel centres), so the benchmark can run.
            points = _sample_dem(path)
            notes.append(f"dftpcc.read failed ({exc}); pixels sampled with rasterio instead, "
                         "same pixel-centre convention")
        seconds = time.perf_counter() - t0
        pixel = _pixel_width(path)
        resolution = pixel * (1.0 - LATTICE_SHRINK)
        notes.append(f"DEM sampled to points: one point per valid pixel at its centre; "
                     f"resolution = pixel width {pixel:.4f} m (x (1 - {LATTICE_SHRINK:g}) so that no "
                     f"point rounds into its neighbour's cell)")
    else:
        if case.name.endswith((".las", ".laz")):
            import laspy

            with laspy.open(path) as fh:
                header = fh.header
        classes = list(case.classes) if case.classes else None
        points = dftpcc.read(path, classes=classes).points
        seconds = time.perf_counter() - t0
        resolution = float(case.resolution)
    return Loaded(case, points, resolution, seconds, notes, header)


@contextmanager
def warnings_as_notes(notes: list[str]) -> Iterator[None]:
    """Collect each distinct warning once into ``notes`` instead of printing it per call."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    for w in caught:
        text = f"{w.category.__name__}: {w.message}"
        if text not in notes:
            notes.append(text)


def shared_grid(points: np.ndarray, resolution: float) -> tuple[Grid, DEM]:
    """The axis-aligned grid dftpcc uses and the mean-height DEM on it."""
    grid = fit_grid(points, resolution)
    return grid, rasterize(points, grid)


def median_time(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    """Median wall time in seconds of ``repeats`` calls, and the last result."""
    wall, _, result = median_times(fn, repeats)
    return wall, result


def median_times(fn: Callable[[], Any], repeats: int) -> tuple[float, float, Any]:
    """Median wall and CPU (this process, all threads) seconds of ``repeats`` calls, and the last result.

    On a shared machine the wall time grows with other people's load; the CPU
    time much less, so both are worth quoting.
    """
    walls, cpus, result = [], [], None
    for _ in range(max(1, repeats)):
        c0, t0 = time.process_time(), time.perf_counter()
        result = fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return statistics.median(walls), statistics.median(cpus), result


@contextmanager
def numpy_path():
    """Inside: the codec on the numpy backend (``kernels.use``), the anchor of the compiled kernels."""
    from dftpcc import kernels

    with kernels.use(kernels.Backend.NUMPY):
        yield


def load_average() -> str:
    """The machine's 1-minute load average and core count, to read the timings by."""
    try:
        return f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    except OSError:
        return f"{os.cpu_count()} cores"


def rmse(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if values.size else 0.0


class NearestHeights:
    """Vertical RMSE of the original points against the decoded point nearest in x, y.

    The KD-tree and the match of each original point are cached per decoded
    x, y layout: every DEM codec decodes to the same occupied-cell centres, so
    the tree is built once per grid, not once per setting.
    """

    def __init__(self, points: np.ndarray):
        self.points = points
        self._xy: np.ndarray | None = None
        self._match: np.ndarray | None = None

    def rmse(self, decoded: np.ndarray) -> float:
        """RMS of ``z - z_nearest`` in metres over all original points."""
        xy = np.ascontiguousarray(decoded[:, :2])
        if self._xy is None or self._xy.shape != xy.shape or not np.array_equal(self._xy, xy):
            _, match = cKDTree(xy).query(self.points[:, :2], workers=-1)
            self._xy, self._match = xy, match
        return rmse(self.points[:, 2] - decoded[self._match, 2])


# --- rate-distortion curves ---------------------------------------------------------

def lower_hull(samples: Sequence[tuple[float, float]]) -> list[tuple[float, float]]:
    """Efficient frontier of (bits per point, RMSE metres) samples.

    The lower-left convex hull in the (bits, mean squared error) plane: the
    points no mix of two other settings beats (coding part of a map with one
    setting and the rest with another averages both the bits and the squared
    error). Returned from the smallest error to the cheapest point, i.e. by
    increasing error and decreasing bits. (A hull taken in log-log space would
    be wrong: a codec whose bits grow linearly with log-error, like Draco's,
    is concave there and would lose every point but its two ends.)
    """
    pts = sorted({(b, e * e, e) for b, e in samples if b > 0 and math.isfinite(e)})
    hull: list[tuple[float, float, float]] = []
    for b, mse, e in pts:
        if hull and hull[-1][0] == b:
            continue  # same bits, larger error (sorted)
        while len(hull) >= 2:
            (b1, m1, _), (b2, m2, _) = hull[-2], hull[-1]
            if (b2 - b1) * (mse - m1) - (m2 - m1) * (b - b1) <= 0:
                hull.pop()  # hull[-1] lies on or above the chord to this point
            else:
                break
        hull.append((b, mse, e))
    if not hull:
        return []
    best = min(range(len(hull)), key=lambda k: hull[k][1])
    return [(b, e) for b, _, e in reversed(hull[: best + 1])]


def bits_at(hull: Sequence[tuple[float, float]], error: float) -> tuple[float | None, str]:
    """Bits per point the frontier needs for a vertical RMSE of ``error`` metres.

    Log-log interpolation between the two hull points around ``error`` (the
    method of ANCHORS.md). Returns ``(None, 'unreached')`` when no setting got
    that low, and the cheapest point's bits with flag ``'cheapest'`` when even
    the cheapest setting is already better than ``error`` (an upper bound).
    """
    if not hull:
        return None, "unreached"
    if error < hull[0][1] * (1 - 1e-12):
        return None, "unreached"
    if error >= hull[-1][1]:
        return hull[-1][0], ("cheapest" if error > hull[-1][1] * (1 + 1e-9) else "")
    for (b0, e0), (b1, e1) in zip(hull, hull[1:]):
        if e0 <= error <= e1:
            if e1 == e0:
                return b0, ""
            e0 = max(e0, MIN_ERROR)
            t = math.log(error / e0) / math.log(e1 / e0)
            return math.exp(math.log(b0) + t * math.log(b1 / b0)), ""
    return None, "unreached"


@dataclass(frozen=True)
class BDRate:
    """Bjøntegaard delta rate of a test codec against a reference.

    Attributes
    ----------
    rate : float
        Mean relative difference in bits of the test codec over the
        reference at equal error (-0.2: the test needs 20 % fewer bits).
    low, high : float
        The error range (vertical RMSE, metres) both frontiers cover, over
        which the average is taken.
    """

    rate: float
    low: float
    high: float


def bd_rate(reference: Sequence[tuple[float, float]], test: Sequence[tuple[float, float]]) -> BDRate | None:
    """Bjøntegaard delta rate of ``test`` against ``reference``, two frontiers of (bits, RMSE metres).

    Each frontier's log bits is interpolated against log RMSE by a
    piecewise-cubic Hermite (PCHIP, monotone) curve through its points, the
    two curves are integrated over the RMSE range both cover, and the rate is
    ``exp(mean log-bits difference) - 1``. Log RMSE is PSNR up to a scale and
    an offset, so this is the piecewise-cubic form of Bjøntegaard's metric
    (VCEG-M33 fitted one cubic polynomial through four points, which swings
    between the many points of a frontier). None when the frontiers share
    no range or either has fewer than two points with a positive error.
    """
    from scipy.interpolate import PchipInterpolator

    curves = []
    for hull in (reference, test):
        cheapest: dict[float, float] = {}  # log RMSE -> least log bits (PCHIP needs distinct x)
        for b, e in hull:
            if b > 0 and e > MIN_ERROR:
                x = math.log(e)
                cheapest[x] = min(cheapest.get(x, math.inf), math.log(b))
        pts = sorted(cheapest.items())
        if len(pts) < 2:
            return None
        x, y = np.array(pts).T
        curves.append((PchipInterpolator(x, y), x[0], x[-1]))
    low, high = max(curves[0][1], curves[1][1]), min(curves[0][2], curves[1][2])
    if high <= low:
        return None
    (ref, _, _), (tst, _, _) = curves
    mean = (tst.integrate(low, high) - ref.integrate(low, high)) / (high - low)
    return BDRate(float(math.expm1(mean)), math.exp(low), math.exp(high))


# --- printing ------------------------------------------------------------------------

def fmt_bits(value: float | None, flag: str = "") -> str:
    if value is None:
        return "—"
    text = f"{value:.3f}" if value < 100 else f"{value:.1f}"
    return text + ("*" if flag == "cheapest" else "")


def verdict(ok: bool | None) -> str:
    return "n/a" if ok is None else ("PASS" if ok else "MISS")


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def command_line() -> str:
    """The command that ran this benchmark, as typed from the repository root."""
    args = [a if re.fullmatch(r"[\w./=,:@+-]+", a) else repr(a) for a in sys.argv[1:]]
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    if spec is not None and spec.name:  # python -m benchmarks.NAME
        script = ["-m", spec.name]
    else:
        script = [os.path.relpath(sys.argv[0], REPO) if os.path.isabs(sys.argv[0]) else sys.argv[0]]
    env = [f"PYTHONPATH={os.environ['PYTHONPATH']}"] if os.environ.get("PYTHONPATH") else []
    return " ".join([*env, ".venv/bin/python", *script, *args])


def library_label() -> str:
    """Which dftpcc was measured: the commit of this checkout, or the path it was imported from."""
    import subprocess

    where = Path(dftpcc.__file__).resolve().parent
    if REPO / "src" in where.parents:
        def git(*args: str) -> str:
            return subprocess.run(["git", "-C", str(REPO), *args], capture_output=True, text=True).stdout.strip()

        dirty = git("status", "--porcelain", "--", "src")
        return f"dftpcc {dftpcc.__version__} at commit {git('rev-parse', '--short', 'HEAD')}" + \
            (" + uncommitted changes in src/" if dirty else "")
    return f"dftpcc {dftpcc.__version__} imported from {where}"


def run_arguments(description: str, quick_help: str) -> argparse.ArgumentParser:
    """The options every benchmark that writes a docs section shares: --quick, --files, --data, --docs."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--quick", action="store_true", help=quick_help)
    ap.add_argument("--files", nargs="+", metavar="NAME", help="file names (or prefixes) to run")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder holding pointclouds/ and dems/")
    docs = ap.add_mutually_exclusive_group()
    docs.add_argument("--docs", action="store_true", default=None,
                      help="rewrite this script's section of docs/benchmarks.md (default: only on a full run)")
    docs.add_argument("--no-docs", dest="docs", action="store_false")
    return ap


def finish_run(parts: list[str], args: argparse.Namespace, key: str, title: str, run_time_note: str) -> None:
    """End a benchmark: print its run-time line, and write its docs section on a full
    run (neither --quick nor --files) or when --docs asks for it."""
    parts.append(run_time_note)
    print("\n" + parts[-1])
    write = args.docs if args.docs is not None else (not args.quick and not args.files)
    if write:
        write_doc_section(key, title, "\n\n".join(parts))
        print(f"wrote docs/benchmarks.md ({key} section)")


def write_doc_section(key: str, title: str, body: str, path: Path = DOC) -> None:
    """Replace (or append) the section between this key's markers in docs/benchmarks.md."""
    begin, end = f"<!-- {key}:begin -->", f"<!-- {key}:end -->"
    stamp = datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    block = (f"{begin}\n## {title}\n\nRegenerated {stamp} with `{command_line()}` "
             f"({library_label()}).\n\n"
             f"{body.strip()}\n{end}")
    text = path.read_text() if path.exists() else DOC_HEAD
    if begin in text and end in text:
        text = text[: text.index(begin)] + block + text[text.index(end) + len(end):]
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


DOC_HEAD = """# Benchmarks

Measured on the shared 2-core machine (noisy: times are medians over repeats,
compare ratios rather than absolute speeds). Data: `../shared/data` (never copied
into the repository). Each section below is rewritten by the script named in it;
edit the text outside the markers only.
"""
