"""Issue 16: where compress and decompress spend their time, on one core, against DracoPy, LERC and HTJ2K.

Point clouds (forest, field; all points, 0.5 m cells, compact profile at f_c 0.8): the
points are parsed before any clock starts, so compress is points in memory -> ``.dftpc``
bytes and decompress is bytes -> points. Each is timed whole (medians and range over the
repeats), then once more per repeat with every stage function wrapped in a timer, for the
per-stage table. Points per second count the ORIGINAL points for both directions (the
points a file stands for), and the decompressed points (one per occupied cell) as well.
DracoPy (compression level 7, 14 quantization bits, float32 points about a local origin)
codes the same points in the same run.

GeoTIFF DEMs (compact at f_c 0.8 on the DEM's own pixel grid): cells per second of the
whole grid (rows x cols), DEM in memory -> bytes -> DEM, against LERC (float64 heights and
their mask, maxZError = the largest error dftpcc's file has) and HTJ2K (lossless, the
heights quantized to 16-bit steps of twice that error, or coarser when the range needs more
than 16 bits). Every codec runs on one thread (``OMP_NUM_THREADS=1``, scipy.fft with one
worker). Nothing here fails on a timing.

    .venv/bin/python -m benchmarks.bench_speed [--quick] [--repeats N] [--files forest field ...]
"""

from __future__ import annotations

import os

# One core: set before numpy and scipy start their thread pools.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import statistics  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, Callable, Iterator  # noqa: E402

import numpy as np  # noqa: E402

import dftpcc  # noqa: E402
from dftpcc import analysis, coding, decoder, encoder, kernels, mapfile, occupancy, quantizer, spectrum  # noqa: E402
from dftpcc import format as fmt  # noqa: E402
from dftpcc.files import dem_from_geotiff  # noqa: E402

from benchmarks.common import (  # noqa: E402
    finish_run, load_average, markdown_table, numpy_path, run_arguments,
)

#: Point clouds of the issue: (file, cell size in metres).
CLOUDS = (("forest_slope_bcts_2.8M.laz", 0.5), ("field_gentle_ign.laz", 0.5))
CUTOFF = 0.8
REPEATS = 7
QUICK_REPEATS = 3
#: DracoPy setting: the anchors' compression level, a middle quantization.
DRACO_LEVEL = 7
DRACO_BITS = 14
ONE_THREAD = 1
U16_MAX = 65535
#: Targets of issue 16.
MIN_COMPRESS_RATE = 20e6     # original points per second
MIN_DECOMPRESS_RATE = 40e6   # decoded points per second (one per occupied cell: the points a user gets)
MIN_OVER_DRACO = 10.0        # times DracoPy's encoder speed, for compress (decompress's ratio is shown too)

#: Stages timed inside compress: (label, module, attribute, depth). A stage's time
#: includes the stages indented below it.
COMPRESS_STAGES = (
    ("check and survey the points", encoder, "survey", 0),
    ("check heights", encoder, "check_heights", 0),
    ("fit the grid", encoder, "fit_grid", 0),
    ("rasterize", encoder, "rasterize", 0),
    ("analysis", encoder, "Analysis", 0),
    ("fit the plane", analysis, "fit_plane", 1),
    ("evaluate the plane", analysis, "plane_values", 1),
    ("fill empty cells", analysis, "fill_empty", 1),
    ("forward transform", spectrum, "forward", 1),
    ("code the mask", occupancy, "encode_mask", 0),
    ("choose the step", quantizer, "choose_step", 0),
    ("quantize + rebuild (trial)", analysis.Analysis, "trial", 0),
    ("inverse transform", spectrum, "inverse", 1),
    ("entropy-code coefficients", analysis.Analysis, "encode", 0),
    ("statistics + container", encoder._Whole, "pack", 0),
)
DECOMPRESS_STAGES = (
    ("parse the container", mapfile, "unpack_source", 0),
    ("decode the mask", occupancy, "decode_mask", 0),
    ("decode coefficients", coding, "decode_coefficients", 0),
    ("inverse transform", spectrum, "inverse", 0),
    ("add the plane", decoder, "add_plane", 0),
    ("rebuild points", mapfile, "dem_to_points", 0),
)


@contextmanager
def timed(stages: tuple, spent: dict[str, float]) -> Iterator[None]:
    """Wrap each stage function so that its wall time adds to ``spent[label]``."""
    saved = []
    for label, owner, name, _ in stages:
        original = owner.__dict__[name] if isinstance(owner, type) else getattr(owner, name)

        def wrapper(*args: Any, _f: Callable = original, _label: str = label, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return _f(*args, **kwargs)
            finally:
                spent[_label] = spent.get(_label, 0.0) + time.perf_counter() - t0

        saved.append((owner, name, original))
        # A static method stays one (a layout's pack is called on its instance).
        setattr(owner, name, staticmethod(wrapper) if isinstance(original, staticmethod) else wrapper)
    try:
        yield
    finally:
        for owner, name, original in reversed(saved):
            setattr(owner, name, original)


#: CPU seconds of the last :func:`walls` call's repeats (this process, all threads): on a
#: shared machine the wall time also counts other people's load, the CPU time much less.
LAST_CPU: list[float] = []


def walls(fn: Callable[[], Any], repeats: int) -> tuple[list[float], Any]:
    """Wall times in seconds of ``repeats`` calls, and the last result (CPU times in LAST_CPU)."""
    out, result = [], None
    LAST_CPU.clear()
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        result = fn()
        out.append(time.perf_counter() - t0)
        LAST_CPU.append(time.process_time() - c0)
    return out, result


def staged(fn: Callable[[], Any], stages: tuple, repeats: int) -> dict[str, list[float]]:
    """Per stage, its seconds in each of ``repeats`` wrapped calls; ``total`` the whole call."""
    runs: dict[str, list[float]] = {label: [] for label, *_ in stages}
    runs["total"] = []
    for _ in range(repeats):
        spent: dict[str, float] = {}
        with timed(stages, spent):
            t0 = time.perf_counter()
            fn()
            runs["total"].append(time.perf_counter() - t0)
        for label, *_ in stages:
            runs[label].append(spent.get(label, 0.0))
    return runs


def med(values: list[float]) -> float:
    return statistics.median(values)


def span(values: list[float], scale: float = 1000.0) -> str:
    """Median and range of seconds, in milliseconds."""
    return f"{scale * med(values):.1f} ({scale * min(values):.1f}-{scale * max(values):.1f})"


def stage_table(runs: dict[str, list[float]], stages: tuple, n: int) -> str:
    rows = []
    top = 0.0
    for label, _, _, depth in stages:
        t = runs[label]
        if depth == 0:
            top += med(t)
        rows.append([("&nbsp;&nbsp;" * 2 * depth) + label, span(t), f"{100 * med(t) / med(runs['total']):.0f}",
                     f"{1e9 * med(t) / n:.1f}"])
    rows.append(["other (outside the stages above)", f"{1000 * (med(runs['total']) - top):.1f}", "", ""])
    rows.append(["**total (with timers)**", span(runs["total"]), "100", f"{1e9 * med(runs['total']) / n:.1f}"])
    return markdown_table(["stage", "ms median (range)", "% of total", "ns / original point"], rows)


def draco(points: np.ndarray, repeats: int) -> tuple[list[float], list[float], int, tuple[list[float], list[float]]]:
    """DracoPy's encode and decode wall times (s), its bytes, and the CPU times of both."""
    import DracoPy

    origin = points.min(axis=0)
    local = (points - origin).astype(np.float32)  # outside the clock, like the parsing of the points
    enc, buf = walls(lambda: DracoPy.encode(local, quantization_bits=DRACO_BITS,
                                            compression_level=DRACO_LEVEL), repeats)
    cpu_enc = list(LAST_CPU)
    dec, _ = walls(lambda: np.asarray(DracoPy.decode(buf).points, dtype=np.float64) + origin, repeats)
    return enc, dec, len(buf), (cpu_enc, list(LAST_CPU))


def cloud_section(name: str, resolution: float, data: Path, repeats: int) -> tuple[str, list[str]]:
    points = np.ascontiguousarray(dftpcc.read(data / "pointclouds" / name).points)
    n = points.shape[0]
    params = dftpcc.make_params(resolution=resolution, cutoff=CUTOFF)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the forest's MultiHeightWarning: noted in the doc already
        compress = lambda: dftpcc.compress(points, params)  # noqa: E731
        with numpy_path():
            compress()  # warm caches (coefficient order, table models) as a long-running process has them
            t_c, blob = walls(compress, repeats)
            cpu_c = list(LAST_CPU)
            t_d, out = walls(lambda: dftpcc.decompress(blob), repeats)
            cpu_d = list(LAST_CPU)
            c_stages = staged(compress, COMPRESS_STAGES, repeats)
            d_stages = staged(lambda: dftpcc.decompress(blob), DECOMPRESS_STAGES, repeats)
        jit = None
        if kernels.Backend.default(n) is kernels.Backend.COMPILED:  # the same calls on the default backend
            compress()
            tj_c, blob_j = walls(compress, repeats)
            cpuj_c = list(LAST_CPU)
            tj_d, out_j = walls(lambda: dftpcc.decompress(blob_j), repeats)
            cpuj_d = list(LAST_CPU)
            same = blob_j == blob and np.array_equal(out_j, out)
            cj_stages = staged(compress, COMPRESS_STAGES, repeats)
            dj_stages = staged(lambda: dftpcc.decompress(blob_j), DECOMPRESS_STAGES, repeats)
            jit = ["dftpcc, default backend (compiled)", span(tj_c), f"{1000 * med(cpuj_c):.1f}", f"{n / med(tj_c) / 1e6:.2f}",
                   span(tj_d), f"{1000 * med(cpuj_d):.1f}", f"{n / med(tj_d) / 1e6:.2f}",
                   f"{out.shape[0] / med(tj_d) / 1e6:.2f}" + ("" if same else " (FILES DIFFER)")]
    e_draco, d_draco, draco_bytes, cpu_draco = draco(points, repeats)
    m = out.shape[0]
    rate_c, rate_d = n / med(t_c), n / med(t_d)
    over_c, over_d = med(e_draco) / med(t_c), med(d_draco) / med(t_d)
    lines = [
        f"### {name}: {n:,} points, {resolution:g} m cells, f_c {CUTOFF:g}",
        "",
        f"{len(blob):,} B ({8 * len(blob) / n:.3f} bits/pt), {m:,} points decoded (occupied cells). "
        f"DracoPy ({DRACO_BITS} bits, level {DRACO_LEVEL}): {draco_bytes:,} B.",
        "",
        markdown_table(
            ["codec", "compress ms median (range)", "CPU ms", "M original pts/s", "decompress ms median (range)",
             "CPU ms", "M original pts/s", "M decoded pts/s"],
            [["dftpcc", span(t_c), f"{1000 * med(cpu_c):.1f}", f"{rate_c / 1e6:.2f}", span(t_d),
              f"{1000 * med(cpu_d):.1f}", f"{rate_d / 1e6:.2f}", f"{m / med(t_d) / 1e6:.2f}"],
             ["DracoPy", span(e_draco), f"{1000 * med(cpu_draco[0]):.1f}", f"{n / med(e_draco) / 1e6:.2f}",
              span(d_draco), f"{1000 * med(cpu_draco[1]):.1f}", f"{n / med(d_draco) / 1e6:.2f}",
              f"{n / med(d_draco) / 1e6:.2f}"],
             ["dftpcc / DracoPy speed", "", "", f"{over_c:.1f}x", "", "", f"{over_d:.1f}x", ""]]
            + ([jit, ["compiled / numpy time", "", "", f"{med(tj_c) / med(t_c):.2f}", "", "",
                      f"{med(tj_d) / med(t_d):.2f}", ""]] if jit else [])),
        "",
        "Compress, per stage:",
        "",
        stage_table(c_stages, COMPRESS_STAGES, n),
        "",
        "Decompress, per stage:",
        "",
        stage_table(d_stages, DECOMPRESS_STAGES, n),
        "",
    ]
    if jit:
        lines += ["Compress, per stage, compiled kernels:", "", stage_table(cj_stages, COMPRESS_STAGES, n), "",
                  "Decompress, per stage, compiled kernels:", "", stage_table(dj_stages, DECOMPRESS_STAGES, n), ""]

    def verdict(path: str, t_comp: list[float], t_dec: list[float]) -> str:
        rate, decoded, over = n / med(t_comp), m / med(t_dec), med(e_draco) / med(t_comp)
        return (f"{name}, {path}: compress {rate / 1e6:.1f} M pts/s (>= {MIN_COMPRESS_RATE / 1e6:g}) "
                f"{'PASS' if rate >= MIN_COMPRESS_RATE else 'MISS'}; decompress {decoded / 1e6:.1f} M decoded pts/s "
                f"(>= {MIN_DECOMPRESS_RATE / 1e6:g}) {'PASS' if decoded >= MIN_DECOMPRESS_RATE else 'MISS'} "
                f"({n / med(t_dec) / 1e6:.1f} M original pts/s); compress {over:.1f}x DracoPy's encoder "
                f"(>= {MIN_OVER_DRACO:g}x) {'PASS' if over >= MIN_OVER_DRACO else 'MISS'}; decompress "
                f"{med(d_draco) / med(t_dec):.1f}x its decoder")

    verdicts = [verdict("numpy backend", t_c, t_d)] + ([verdict("default backend (compiled)", tj_c, tj_d)] if jit else [])
    return "\n".join(lines), verdicts


@contextmanager
def cores(n: int | None) -> Iterator[None]:
    """Inside: one map's coding on ``n`` cores (1: every stage in this thread and scipy.fft on one
    worker, as the one-core tables; None: the library's defaults, every core the process may use:
    the mask's coder beside the spectrum, scipy.fft on the cores left)."""
    saved = kernels.CORES, spectrum.FFT_WORKERS
    kernels.CORES, spectrum.FFT_WORKERS = (1, ONE_THREAD) if n == 1 else (None, -1)
    try:
        yield
    finally:
        kernels.CORES, spectrum.FFT_WORKERS = saved


def two_core_rows(data: Path, repeats: int, clouds: list[str], *, dems: bool = True) -> list[list[str]]:
    """Per input, compiled kernels: compress and decompress on one core and on two, the repeats of
    the two settings interleaved (so that both see the same load), their bytes and points compared."""
    inputs: list[tuple[str, Callable[[], bytes], Callable[[bytes], Any], int, str]] = []
    for name, resolution in CLOUDS:
        if name not in clouds:
            continue
        points = np.ascontiguousarray(dftpcc.read(data / "pointclouds" / name).points)
        params = dftpcc.make_params(resolution=resolution, cutoff=CUTOFF)
        inputs.append((name, lambda p=points, q=params: dftpcc.compress(p, q), dftpcc.decompress,
                       points.shape[0], "pts"))
    for path in sorted((data / "dems").glob("*.tif")) if dems else ():
        dem, _ = dem_from_geotiff(path)
        params = dftpcc.make_params(cutoff=CUTOFF)
        inputs.append((path.name, lambda d=dem, q=params: encoder.encode_dem(d, q),
                       lambda b: decoder.decode_dem(*fmt.reader.unpack(b)).heights, dem.grid.size, "cells"))
    rows = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name, encode, decode, count, unit in inputs:
            t: dict[tuple[str, int | None], list[float]] = {}
            out: dict[int | None, tuple[bytes, Any]] = {}
            for n in (1, None):
                with cores(n):
                    blob = encode()  # warm caches, outside the clocks
                    out[n] = blob, decode(blob)
            for _ in range(repeats):
                for n in (1, None):
                    with cores(n):
                        for what, fn in (("compress", encode), ("decompress", lambda: decode(out[n][0]))):
                            t0 = time.perf_counter()
                            fn()
                            t.setdefault((what, n), []).append(time.perf_counter() - t0)
            same = out[1][0] == out[None][0] and np.array_equal(out[1][1], out[None][1])
            decoded = out[1][1].shape[0] if unit == "pts" else count

            def ratio(what: str) -> str:
                return f"{med(t[(what, 1)]) / med(t[(what, None)]):.2f}x"

            rows.append([name, f"{count:,} {unit}", span(t[("compress", 1)]), span(t[("compress", None)]),
                         ratio("compress"), span(t[("decompress", 1)]), span(t[("decompress", None)]),
                         ratio("decompress"),
                         f"{count / med(t[('compress', None)]) / 1e6:.1f} / {decoded / med(t[('decompress', None)]) / 1e6:.1f}",
                         "yes" if same else "NO"])
    return rows


def dem_path_rows(data: Path, repeats: int, compiled: bool) -> list[list[str]]:
    """Each DEM's row on the numpy path, then (``compiled``) with the kernels, the anchors timed again."""
    with numpy_path():
        rows = [["numpy", *row] for row in dem_rows(data, repeats)]
    if compiled:
        rows += [["compiled", *row] for row in dem_rows(data, repeats)]
    return rows


def dem_rows(data: Path, repeats: int) -> list[list[str]]:
    import imagecodecs
    import lerc

    rows = []
    for path in sorted((data / "dems").glob("*.tif")):
        dem, _ = dem_from_geotiff(path)
        cells = dem.grid.size
        params = dftpcc.make_params(cutoff=CUTOFF)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            encode = lambda: encoder.encode_dem(dem, params)  # noqa: E731
            encode()
            t_c, blob = walls(encode, repeats)
            t_d, _ = walls(lambda: decoder.decode_dem(*fmt.reader.unpack(blob)), repeats)
        bound = float(dftpcc.open(blob).header.stats["dem_max_error_m"])
        heights, valid = dem.heights, dem.mask.astype(np.uint8)

        def lerc_encode() -> bytes:
            result, nbytes, buf = lerc.encode(heights, 1, True, valid, bound, 1)
            if result != 0:
                raise RuntimeError(f"lerc.encode failed with code {result}")
            return bytes(buf)[:nbytes]

        t_le, lerc_blob = walls(lerc_encode, repeats)
        t_ld, _ = walls(lambda: lerc.decode(lerc_blob), repeats)
        lo = float(heights[dem.mask].min())
        step = max(2.0 * bound, (float(heights[dem.mask].max()) - lo) / U16_MAX)
        filled = np.where(dem.mask, heights, lo)
        quantize = lambda: np.round((filled - lo) / step).astype(np.uint16)  # noqa: E731
        t_he, hblob = walls(lambda: imagecodecs.htj2k_encode(quantize()), repeats)
        t_hd, _ = walls(lambda: imagecodecs.htj2k_decode(hblob).astype(np.float64) * step + lo, repeats)

        def rate(t: list[float]) -> str:
            return f"{cells / med(t) / 1e6:.1f}"

        rows.append([path.name, f"{dem.grid.rows} x {dem.grid.cols}", f"{1000 * bound:.3g}",
                     f"{len(blob):,} / {len(lerc_blob):,} / {len(hblob):,}",
                     f"{rate(t_c)} / {rate(t_le)} / {rate(t_he)}", f"{rate(t_d)} / {rate(t_ld)} / {rate(t_hd)}",
                     f"{med(t_le) / med(t_c):.2f} / {med(t_he) / med(t_c):.2f}",
                     f"{med(t_ld) / med(t_d):.2f} / {med(t_hd) / med(t_d):.2f}"])
    return rows


def transform_rows(data: Path, repeats: int) -> list[list[str]]:
    """Per DEM: the DCT alone (scipy.fft, float64, one worker) against LERC at dftpcc's bound, in
    M cells/s: what a codec built on one transform of the whole grid cannot beat. A decoder runs
    at least one 1-D inverse pass over every output cell (the other axis's pass may skip the zero
    rows of a low-passed spectrum), the faster of the two axes' passes; an encoder that states
    the error of its file, at least one forward and one such inverse pass."""
    import lerc
    import scipy.fft

    rows = []
    for path in sorted((data / "dems").glob("*.tif")):
        dem, _ = dem_from_geotiff(path)
        cells = dem.grid.size
        heights, valid = dem.heights, dem.mask.astype(np.uint8)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            blob = encoder.encode_dem(dem, dftpcc.make_params(cutoff=CUTOFF))
        bound = float(dftpcc.open(blob).header.stats["dem_max_error_m"])
        coefs = scipy.fft.dctn(heights, norm="ortho", workers=ONE_THREAD)
        t_f, _ = walls(lambda: scipy.fft.dctn(heights, norm="ortho", workers=ONE_THREAD), repeats)
        t_i, _ = walls(lambda: scipy.fft.idctn(coefs, norm="ortho", workers=ONE_THREAD), repeats)
        t_pass, t_fpass = (min((walls(lambda a=axis: fn(x, norm="ortho", axis=a, workers=ONE_THREAD), repeats)[0]
                                for axis in (0, 1)), key=med)
                           for fn, x in ((scipy.fft.idct, coefs), (scipy.fft.dct, heights)))
        _, _, lerc_buf = lerc.encode(heights, 1, True, valid, bound, 1)
        t_le, _ = walls(lambda: lerc.encode(heights, 1, True, valid, bound, 1), repeats)
        t_ld, _ = walls(lambda: lerc.decode(bytes(lerc_buf)), repeats)

        def rate(t: list[float]) -> str:
            return f"{cells / med(t) / 1e6:.1f}"

        rows.append([path.name, f"{dem.grid.rows} x {dem.grid.cols}", rate(t_f), rate(t_i), rate(t_pass),
                     rate(t_le), rate(t_ld), f"{(med(t_fpass) + med(t_pass)) / med(t_le):.2f}",
                     f"{2 * med(t_pass) / med(t_ld):.2f}"])
    return rows


#: Start-up commands timed in fresh processes: the library's import and the CLI's help.
STARTUP = (("import dftpcc", ("-c", "import dftpcc")), ("dftpcc --help", ("-m", "dftpcc", "--help")))


def startup_rows(repeats: int) -> list[list[str]]:
    """Median and range (ms) of each start-up command over ``repeats`` fresh interpreters."""
    import subprocess
    import sys

    rows = []
    for label, argv in STARTUP:
        t, _ = walls(lambda: subprocess.run([sys.executable, *argv], check=True, capture_output=True), repeats)
        rows.append([f"`{label}`", span(t)])
    return rows


def main() -> None:
    parser = run_arguments("Per-stage speed on one core against DracoPy, LERC and HTJ2K, and on two cores apart (issue 16).",
                           f"{QUICK_REPEATS} repeats instead of {REPEATS}")
    parser.add_argument("--repeats", type=int, default=None, help=f"repeats per timing (default {REPEATS})")
    parser.add_argument("--no-dems", action="store_true", help="skip the GeoTIFF DEMs (a partial run: the docs section is kept unless --docs)")
    args = parser.parse_args()
    if args.no_dems and args.docs is None:
        args.docs = False  # a run without the DEMs is partial: it would drop their tables from the docs
    repeats = args.repeats or (QUICK_REPEATS if args.quick else REPEATS)
    data = Path(args.data)
    # One core, as every anchor here: scipy.fft on one worker, no stage beside another.
    spectrum.FFT_WORKERS, kernels.CORES = ONE_THREAD, 1
    compiled = kernels.load()  # numba's import and first calls happen here, outside every clock
    start = time.perf_counter()
    wanted = args.files or [name for name, _ in CLOUDS]
    sections, verdicts = [], []
    for name, resolution in CLOUDS:
        if any(name.startswith(w) for w in wanted):
            text, v = cloud_section(name, resolution, data, repeats)
            sections.append(text)
            verdicts += v
    parts = [f"{repeats} repeats; times are wall-clock medians with the range over the repeats in brackets. "
             + " ".join(__doc__.split("\n\n")[1].split())]
    parts.append("The rows `dftpcc` are the numpy backend (`backend='numpy'`, or `DFTPCC_JIT=0`); "
                 + ("the rows `dftpcc, default backend (compiled)` the same calls with no backend named, which "
                    "take the numba kernels (`dftpcc[fast]`) here, loaded before the clocks start (a one-shot "
                    "`dftpcc compress` loads them in its call when the cloud has at least "
                    f"{kernels.COMPILED_MIN_POINTS:,} points: benchmarks/bench_backend.py), their files "
                    "compared with the numpy backend's. Stage tables and DEM rows: each backend's own. "
                    "The targets are judged on each path, decompress on the decoded points."
                    if compiled else "numba is not installed here, so there is no compiled row."))
    parts += sections
    if not args.no_dems:
        parts.append("### GeoTIFF DEMs: M cells/s, dftpcc / LERC / HTJ2K\n\n" + " ".join(__doc__.split("\n\n")[2].split())
                     + "\n\n" + markdown_table(
                         ["dftpcc path", "DEM", "cells", "max error mm", "bytes dftpcc / LERC / HTJ2K",
                          "encode M cells/s", "decode M cells/s", "encode time LERC / HTJ2K over dftpcc",
                          "decode time LERC / HTJ2K over dftpcc"], dem_path_rows(data, repeats, compiled)))
        parts.append("### GeoTIFF DEMs: the transform alone against LERC\n\n" + " ".join(
            transform_rows.__doc__.split()) + " Ratios above 1: the transform alone is slower than the "
            "goal (LERC's encode; half LERC's decode).\n\n" + markdown_table(
                ["DEM", "cells", "forward DCT M cells/s", "inverse DCT M cells/s", "one inverse pass M cells/s",
                 "LERC encode M cells/s", "LERC decode M cells/s", "a forward and an inverse pass time / LERC encode time",
                 "one inverse pass time / half LERC decode time"], transform_rows(data, repeats)))
    usable = kernels.available_cores()
    two_cores = ("### Two cores: the mask beside the spectrum (compiled kernels)\n\n"
                 "Reported apart from the one-core figures above. One core: every stage in one thread and "
                 "scipy.fft on one worker (the tables above). Two cores: the library's defaults on this "
                 "2-core machine, the occupancy mask coded (or decoded) on a second thread while the spectrum "
                 "is transformed, quantized and coded (`kernels.Side`, grids of at least "
                 f"{kernels.SIDE_MIN_CELLS:,} cells), scipy.fft on the core left meanwhile and on both "
                 "otherwise. The two settings' repeats alternate, so both see the same load; 'same' compares "
                 "their files and decoded points. Rates: original points (or grid cells) per second for "
                 "compress, decoded points (cells) per second for decompress.\n\n")
    if not compiled:
        parts.append(two_cores + "numba is not installed here, so nothing runs beside the spectrum.")
    elif usable < 2:
        parts.append(two_cores + f"Not measured: this process may use {usable} core (run it without taskset).")
    else:
        parts.append(two_cores + markdown_table(
            ["input", "size", "compress ms, one core", "two cores", "speed-up", "decompress ms, one core",
             "two cores", "speed-up", "two cores: M compressed / M decoded per s", "same"],
            two_core_rows(data, repeats, [n for n, _ in CLOUDS if any(n.startswith(w) for w in wanted)],
                          dems=not args.no_dems)))
    parts.append("### Start-up\n\nWall time of a fresh interpreter running each command (the interpreter's own "
                 "start included).\n\n" + markdown_table(["command", "ms median (range)"], startup_rows(repeats)))
    parts.append("### Targets\n\n" + "\n".join(f"- {v}" for v in verdicts))
    for part in parts:
        print(part + "\n")
    finish_run(parts, args, "bench_speed", "Speed on one core, and on two (issue 16)",
               f"Run time {time.perf_counter() - start:.0f} s; {load_average()} at the end.")

if __name__ == "__main__":
    main()
