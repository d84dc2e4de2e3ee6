"""Issue 43 item 3: a map's decode against one inverse DCT of its grid, on a mosaic of over 1 M cells.

The mosaic is two shared DEMs in one GeoTIFF (Big Tujunga's 643 x 1197 above Heidelberg's
713 x 1041, raised 1500 m, the rest nodata: 1356 x 1197 = 1.62 M cells, 93 % valid), written to
a temporary folder. It is coded twice: at the default fixed settings (no residual layer) and at a
maximum error (``--bound``, a residual layer on every map). Each file is decoded (bytes ->
rebuilt DEM, ``dftpcc.open(blob).read_dem()``) on each backend, each decode right after one
``scipy.fft.idctn`` of a grid of the same shape (float64, orthonormal, one worker): CPU seconds of
this process, the median and range of the per-run ratio, and M cells/s of the whole grid. The
goals: a decode at most twice the transform, at least 25 M cells/s. Then (``--dem-bound``, 0: not)
each shared DEM the writer gives a predicted residual layer at that maximum error (RESD kind 5:
the layer decoded cell by cell from its decoded neighbours), the mosaic's halves among them,
measured the same way.

    taskset -c 0 .venv/bin/python -m benchmarks.bench_decode [--runs 15] [--bound 2.0] [--dem-bound 1.0]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

import dftpcc  # noqa: E402
from dftpcc import kernels  # noqa: E402

from benchmarks.common import DEFAULT_DATA, library_label, load_average, markdown_table  # noqa: E402

#: The issue's goals: decode at most this many inverse transforms, at least this many cells a second.
GOAL_RATIO = 2.0
GOAL_RATE = 25e6
#: Heidelberg is raised by this much (metres) so the two halves do not share heights.
RAISE = 1500.0


def mosaic(data: Path, folder: Path) -> Path:
    """The mosaic GeoTIFF described in the module's docstring."""
    import rasterio
    from rasterio.transform import from_origin

    with rasterio.open(data / "dems" / "earth_bigtujunga_srtm30.tif") as f:
        top = f.read(1).astype(np.float32)
    with rasterio.open(data / "dems" / "earth_heidelberg_25m.tif") as f:
        bottom = f.read(1).astype(np.float32) + np.float32(RAISE)
    nodata = np.float32(-9999.0)
    out = np.full((top.shape[0] + bottom.shape[0], max(top.shape[1], bottom.shape[1])), nodata, dtype=np.float32)
    out[:top.shape[0], :top.shape[1]] = top
    out[top.shape[0]:, :bottom.shape[1]] = bottom
    path = folder / "mosaic.tif"
    with rasterio.open(path, "w", driver="GTiff", width=out.shape[1], height=out.shape[0], count=1, dtype="float32",
                       nodata=float(nodata), crs="EPSG:32611", transform=from_origin(0, 0, 30, 30)) as f:
        f.write(out, 1)
    return path


def measure(blob: bytes, backend: kernels.Backend, runs: int) -> dict[str, list[float]]:
    import scipy.fft

    rows, cols = dftpcc.open(blob).header.grid.shape
    grid = np.random.default_rng(0).standard_normal((rows, cols))
    transform, decode = [], []
    with kernels.use(backend):
        dftpcc.open(blob).read_dem()  # the tables' caches and the compiled kernels warm
        for _ in range(runs):
            t0 = time.process_time()
            scipy.fft.idctn(grid, type=2, norm="ortho", workers=1)
            transform.append(time.process_time() - t0)
            t0 = time.process_time()
            dftpcc.open(blob).read_dem()
            decode.append(time.process_time() - t0)
    return dict(transform=transform, decode=decode, cells=[float(rows * cols)])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--runs", type=int, default=15)
    ap.add_argument("--bound", type=float, default=2.0, help="the residual file's maximum error (m)")
    ap.add_argument("--dem-bound", type=float, default=1.0,
                    help="each shared DEM at this maximum error (m), where its layer is predicted (0: none)")
    args = ap.parse_args(argv)
    print(f"Measuring {library_label()}; {load_average()}.", flush=True)
    table = []
    with tempfile.TemporaryDirectory() as tmp:
        source = mosaic(args.data, Path(tmp))
        files = [("mosaic, fixed (default)", source, {}),
                 (f"mosaic, max error {args.bound:g} m", source, dict(target_max_error=args.bound))]
        if args.dem_bound > 0:
            files += [(f"{dem.stem}, max error {args.dem_bound:g} m", dem, dict(target_max_error=args.dem_bound))
                      for dem in sorted((args.data / "dems").glob("*.tif"))]
        for label, path, options in files:
            out = Path(tmp) / "map.dftpc"
            dftpcc.compress_file(path, out, **options)
            blob = out.read_bytes()
            if not label.startswith("mosaic") and dftpcc.open(blob).info().get("residual_layout") != "predicted":
                continue  # a DEM whose layer is sparse (or none) at that bound: the mosaic's case
            for backend in kernels.Backend.detect_available():
                got = measure(blob, backend, args.runs)
                ratio = [d / t for d, t in zip(got["decode"], got["transform"])]
                cells = got["cells"][0]
                rate = cells / statistics.median(got["decode"])
                held = statistics.median(ratio) <= GOAL_RATIO and rate >= GOAL_RATE
                table.append([label, f"{len(blob):,}", backend.value,
                              f"{1e3 * statistics.median(got['transform']):.1f}",
                              f"{1e3 * statistics.median(got['decode']):.1f} ({1e3 * min(got['decode']):.1f}-"
                              f"{1e3 * max(got['decode']):.1f})",
                              f"{statistics.median(ratio):.2f} ({min(ratio):.2f}-{max(ratio):.2f})",
                              f"{rate / 1e6:.1f}", "yes" if held else "no"])
                print(" | ".join(table[-1]), flush=True)
    print()
    print(markdown_table(["file", "bytes", "backend", "idct ms", "decode ms (range)", "decode / idct (range)",
                          "M cells/s", f"goals (<= {GOAL_RATIO:g}x, >= {GOAL_RATE / 1e6:g} M/s)"], table))
    print(f"\nCPU time, {args.runs} runs, medians; {load_average()} at the end.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
