"""Maps larger than memory: peak memory and throughput of coding a 1.6 G-cell GeoTIFF and a 100 M-point LAZ.

Builds in one temporary folder (deleted at the end, also on failure) a float32 GeoTIFF mosaicked
from the real DEMs of ``dems/`` (mirrored, shifted, height-offset copies, written window by
window) and a LAZ of shifted copies of the 2.83 M-point forest cloud laid side by side (written
copy after copy), each at a quarter, a half and the whole of the full size. Each compress and
decompress runs in its own process under ``/usr/bin/time -v`` (else a ``getrusage`` wrapper),
so its peak resident memory is its own, and is set against the peak of a process that only
imports dftpcc, measured in the same run. The GeoTIFF's quarter is also coded and decoded on a
local dask cluster of 1 and of 2 workers and checked byte-identical to the serial run, and read by URL
(1, 4 and 16 tiles fetched by range requests from a loopback HTTP server).

    .venv/bin/python -m benchmarks.bench_big [--quick] [--only raster|cloud|parallel] [--target-max-error M]
        [--parallel-every-size] [--sizes quarter|half|whole ...] [--scheduler ADDRESS] [--cloud-resolution M]
        [--cloud-file PATH] [--check-cloud] [--docs | --no-docs]

``--quick`` runs at a quarter of the full side of the GeoTIFF (10,000 x 10,000 cells at most) and a
quarter of the cloud (9 copies, 25 M points at most): about 7 minutes on the shared 2-core box.
``--sizes`` measures only those sizes (``--sizes whole --only cloud``: the 102 M-point LAZ alone).
``--scheduler tcp://host:port`` codes and decodes the GeoTIFF's first size through a dask scheduler
started in another process (``dask scheduler``, ``dask worker ADDRESS --nthreads 1``; the temporary
folder, ``--tmp``, must be a path every worker sees) instead of local clusters of 1 and 2 workers.
Prints tables; writes its section of docs/benchmarks.md on a full run (not with ``--sizes`` or
``--scheduler`` unless ``--docs``). Never fails on a timing.
"""

from __future__ import annotations

import filecmp
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from benchmarks.common import finish_run, library_label, load_average, markdown_table, run_arguments
from dftpcc import stream

__all__ = ["build_raster", "build_cloud", "measure", "main"]

#: Side of the full GeoTIFF, cells; the quarter and half maps are sqrt(1/4) and sqrt(1/2) of it.
FULL_SIDE = 40_000
#: Copies of the forest cloud in the full LAZ (36 x 2.83 M = 102 M points).
FULL_COPIES = 36
#: Fractions of the full map measured (cells or points).
FRACTIONS = (0.25, 0.5, 1.0)
#: ``--quick`` divides the GeoTIFF's side by this (1/16 of the cells) and the cloud's copies by this.
QUICK_DIVISOR = 4
#: Tile side of the coded maps, cells (the CLI's ``--tile-size``).
TILE_SIZE = 1024
#: Workers of the local dask cluster in the parallel runs.
WORKERS = 2
#: Whether every size is also coded on WORKERS workers (``--parallel-every-size``), not only the first.
PARALLEL_EVERY_SIZE = False
#: A dask scheduler started in another process (``--scheduler``): the first size is coded through it
#: instead of on local clusters.
SCHEDULER: str | None = None
#: Target the peak resident memory of every run should stay under, bytes.
RSS_TARGET = 2 * 1024 ** 3
#: How often the whole process tree's resident memory is sampled, seconds (dask runs).
SAMPLE_S = 0.25
#: One run longer than this is stopped and reported, seconds.
RUN_TIMEOUT_S = 30 * 60

#: The GeoTIFF's layout: square regions of this many cells a side, each a copy of one DEM.
REGION = 5000
#: Pixel size written to the mosaic, metres (the DEMs' own sizes differ; cells are cells here).
PIXEL_M = 10.0
#: Map origin (west, north) and CRS of the mosaic: UTM 32N, as the Heidelberg DEM.
ORIGIN = (300_000.0, 5_600_000.0)
CRS = "EPSG:32632"
#: The regions' heights ride on a plane rising this much across the map, metres, plus a jitter.
RAMP_M = 800.0
JITTER_M = 40.0
#: Rows written per window: one row of 256 x 256 blocks, so no block is written twice.
BLOCK = 256
#: Creation options of the mosaic (the brief's: tiled 256, deflate + floating-point predictor, BigTIFF).
GTIFF_OPTIONS = dict(driver="GTiff", tiled=True, blockxsize=BLOCK, blockysize=BLOCK, compress="deflate",
                     predictor=3, BIGTIFF="YES", NUM_THREADS="2")

SOURCE_CLOUD = "forest_slope_bcts_2.8M.laz"
#: Gap between copies of the cloud, metres, so copies abut without overlapping.
CLOUD_GAP_M = 1.0
#: Copies a row of the LAZ mosaic: the forest map is 5 times longer (y) than wide (x).
CLOUD_COPIES_PER_ROW = 12
#: Points read per chunk when the LAZ is built, so building it holds one chunk of the source.
CLOUD_CHUNK = 1_000_000
#: The cloud's cell size, metres (``--cloud-resolution``); None: the automatic one (0.426 m, 44 M
#: cells for the whole cloud; 0.25 m gives 127 M).
CLOUD_RESOLUTION: float | None = None
#: Keep each size's LAZ beside this path, ``<stem>_x<copies>.laz`` (``--cloud-file``), and reuse it if there.
CLOUD_FILE: Path | None = None
#: Check each coded cloud against its grid (``--check-cloud``, :func:`check_cloud`): its errors within
#: the promises of its header.
CHECK_CLOUD = False

TIME_BIN = "/usr/bin/time"

#: The child of every run: the command it is given, timed from inside, and its peak (VmHWM) printed.
CHILD = textwrap.dedent("""
    import json, resource, sys, time
    t0 = time.perf_counter()
    import dftpcc
    from dftpcc.files import compress_file, decompress_bands

    def peak():
        with open("/proc/self/status") as fh:
            return next(int(line.split()[1]) * 1024 for line in fh if line.startswith("VmHWM:"))

    job = json.loads(sys.argv[1])
    imported = peak()
    t1 = time.perf_counter()
    out = {}
    if job["op"] == "compress":
        extra = {"chunk_points": job["chunk"]} if job.get("chunk") else {}
        if job.get("resolution"):
            extra["resolution"] = job["resolution"]
        m = compress_file(job["src"], job["dst"], tile_size=job["tile"], workers=job["workers"],
                          scheduler=job.get("scheduler"), **extra, **job.get("target", {}))
        out = {"points": m.header.point_count, "cells": m.header.cell_count, "rows": m.grid.rows,
               "cols": m.grid.cols, "rmse": m.header.stats.get("dem_rmse_m"),
               "max_error": m.header.stats.get("dem_max_error_m"), "resolution": m.grid.resolution}
    elif job["op"] == "decompress":
        out = {"written": decompress_bands(job["src"], job["dst"], workers=job["workers"],
                                           scheduler=job.get("scheduler"))}
    out.update(seconds=time.perf_counter() - t1, total_seconds=time.perf_counter() - t0,
               imported=imported, vmhwm=peak())
    print("BENCH " + json.dumps(out), flush=True)
""")


# -- inputs -----------------------------------------------------------------------------------------

def _reflect(index: np.ndarray, size: int) -> np.ndarray:
    """Indices into an axis of ``size`` of a copy mirrored about each of its ends (continuous)."""
    k = np.mod(index, 2 * size)
    return np.where(k < size, k, 2 * size - 1 - k)


@dataclass(frozen=True)
class _Region:
    dem: int
    flip_rows: bool
    flip_cols: bool
    shift: tuple[int, int]
    offset: float


def _dems(data: Path) -> list[np.ndarray]:
    """The real DEMs as float32 about their median (NaN where they have no data)."""
    import rasterio

    out = []
    for path in sorted((data / "dems").glob("*.tif")):
        with rasterio.open(path) as ds:
            band = ds.read(1, masked=True).astype(np.float32)
        heights = band.filled(np.nan)
        if path.name.startswith("mars_korolev"):
            heights[heights == 0] = np.nan  # its stated nodata (0) is not flagged in every copy
        out.append(heights - np.nanmedian(heights))
    return out


def _regions(side: int, count: int, seed: int = 12) -> list[list[_Region]]:
    """The layout of a map of ``side`` cells: one DEM copy per region, chosen by a fixed seed."""
    rng = np.random.default_rng(seed)
    n = -(-side // REGION)
    full = -(-FULL_SIDE // REGION)
    layout = [[_Region(int(rng.integers(count)), bool(rng.integers(2)), bool(rng.integers(2)),
                       (int(rng.integers(10_000)), int(rng.integers(10_000))),
                       float(RAMP_M * (i + j) / (2 * full) + rng.normal(0.0, JITTER_M)))
               for j in range(full)] for i in range(full)]
    return [row[:n] for row in layout[:n]]  # a smaller map is the top-left crop of the full one


def build_raster(data: Path, dst: Path, side: int, cols: int | None = None) -> int:
    """Write a ``side`` x ``side`` (or ``cols`` wide) float32 GeoTIFF mosaic of the real DEMs, one row of blocks at a time.

    Returns
    -------
    int
        Valid (non-NaN) cells written.
    """
    import rasterio
    from rasterio.transform import from_origin
    from rasterio.windows import Window

    dems = _dems(data)
    cols = side if cols is None else cols
    layout = _regions(max(side, cols), len(dems))
    valid = 0
    with rasterio.open(dst, "w", height=side, width=cols, count=1, dtype="float32", nodata=float("nan"),
                       transform=from_origin(*ORIGIN, PIXEL_M, PIXEL_M), crs=CRS, **GTIFF_OPTIONS) as out:
        for r0 in range(0, side, BLOCK):
            rows = np.arange(r0, min(side, r0 + BLOCK))
            band = np.empty((rows.size, cols), dtype=np.float32)
            for ri in np.unique(rows // REGION):
                sel = rows // REGION == ri
                for cj, region in enumerate(layout[ri][:-(-cols // REGION)]):
                    c0, c1 = cj * REGION, min(cols, (cj + 1) * REGION)
                    dem = dems[region.dem]
                    dem = dem[::-1] if region.flip_rows else dem
                    dem = dem[:, ::-1] if region.flip_cols else dem
                    i = _reflect(rows[sel] + region.shift[0], dem.shape[0])
                    j = _reflect(np.arange(c0, c1) + region.shift[1], dem.shape[1])
                    band[np.nonzero(sel)[0][:, None], np.arange(c0, c1)[None, :]] = dem[np.ix_(i, j)] + region.offset
            valid += int(np.isfinite(band).sum())
            out.write(band, 1, window=Window(0, r0, cols, rows.size))
    return valid


def build_cloud(data: Path, dst: Path, copies: int) -> int:
    """Write a LAZ of ``copies`` shifted copies of the forest cloud side by side, copy after copy.

    Returns
    -------
    int
        Points written.
    """
    import laspy

    src = data / "pointclouds" / SOURCE_CLOUD
    with laspy.open(src) as reader:
        head = reader.header
        width = float(head.maxs[0] - head.mins[0]) + CLOUD_GAP_M
        height = float(head.maxs[1] - head.mins[1]) + CLOUD_GAP_M
        header = laspy.LasHeader(point_format=head.point_format.id, version=head.version)
        header.scales, header.offsets = head.scales, head.offsets
        for vlr in head.vlrs:  # the CRS
            header.vlrs.append(vlr)
    written = 0
    with laspy.open(dst, mode="w", header=header) as out:
        for k in range(copies):
            dx, dy = (k % CLOUD_COPIES_PER_ROW) * width, (k // CLOUD_COPIES_PER_ROW) * height
            with laspy.open(src) as reader:
                for chunk in reader.chunk_iterator(CLOUD_CHUNK):
                    part = laspy.ScaleAwarePointRecord.zeros(len(chunk), header=header)
                    part.x, part.y, part.z = np.asarray(chunk.x) + dx, np.asarray(chunk.y) + dy, chunk.z
                    part.classification = chunk.classification
                    part.return_number, part.number_of_returns = chunk.return_number, chunk.number_of_returns
                    part.intensity = chunk.intensity
                    out.write_points(part)
                    written += len(chunk)
    return written


# -- measuring --------------------------------------------------------------------------------------

#: Without /usr/bin/time: a wrapper that runs the child and prints its peak from getrusage.
RUSAGE_WRAPPER = textwrap.dedent("""
    import resource, subprocess, sys
    rc = subprocess.run(sys.argv[1:]).returncode
    print(f"Maximum resident set size (kbytes): {resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}",
          file=sys.stderr)
    sys.exit(rc)
""")
PEAK_LINE = re.compile(r"Maximum resident set size \(kbytes\): (\d+)")


class _TreeSampler(threading.Thread):
    """The largest summed resident memory of a process and its descendants (dask workers), sampled."""

    def __init__(self, pid: int):
        super().__init__(daemon=True)
        self.pid, self.peak, self.done = pid, 0, threading.Event()

    def run(self) -> None:
        import psutil

        try:
            root = psutil.Process(self.pid)
        except psutil.Error:
            return
        while not self.done.wait(SAMPLE_S):
            total = 0
            try:
                for proc in [root, *root.children(recursive=True)]:
                    try:
                        total += proc.memory_info().rss
                    except psutil.Error:
                        pass
            except psutil.Error:
                return
            self.peak = max(self.peak, total)


def measure(job: dict[str, Any]) -> dict[str, Any]:
    """Run one job in a fresh process; its result, wall time and peak resident memory (bytes).

    ``peak``: the largest resident set of the run's processes (``/usr/bin/time -v``, i.e. the
    kernel's ``ru_maxrss`` of the child and the descendants it waited for); ``tree``: the largest
    sum over the process tree, sampled every :data:`SAMPLE_S`. A failed or timed-out run returns
    ``error`` with the end of its standard error.
    """
    child = [sys.executable, "-c", CHILD, json.dumps(job)]
    cmd = [TIME_BIN, "-v", *child] if os.access(TIME_BIN, os.X_OK) else [sys.executable, "-c", RUSAGE_WRAPPER, *child]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    sampler = _TreeSampler(proc.pid)
    sampler.start()
    try:
        out, err = proc.communicate(timeout=RUN_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, 9)
        out, err = proc.communicate()
        err += f"\ntimed out after {RUN_TIMEOUT_S} s"
    except BaseException:
        os.killpg(proc.pid, 9)  # an interrupted benchmark leaves no run behind
        proc.wait()
        raise
    finally:
        sampler.done.set()
        sampler.join()
    wall = time.perf_counter() - t0
    peak = PEAK_LINE.search(err)
    result: dict[str, Any] = {"wall": wall, "tree": sampler.peak, "peak": int(peak.group(1)) * 1024 if peak else 0}
    line = next((ln for ln in out.splitlines() if ln.startswith("BENCH ")), None)
    if proc.returncode != 0 or line is None:
        # The child's own last lines: /usr/bin/time's report (which repeats the command) starts at "Command being timed".
        own = err.split("\tCommand being timed:")[0] if "\tCommand being timed:" in err else err
        tail = [ln for ln in own.splitlines() if not ln.startswith("\t")][-3:]
        result["error"] = f"exit {proc.returncode}: " + " / ".join(ln.strip() for ln in tail if ln.strip())
        return result
    result.update(json.loads(line[len("BENCH "):]))
    return result


# -- the run ----------------------------------------------------------------------------------------

def _mb(n: float) -> str:
    return f"{n / 1e6:,.0f}"


def _fraction(f: float) -> str:
    return {0.25: "quarter", 0.5: "half", 1.0: "whole"}.get(f, f"{f:g}")


class _Report:
    """Rows of the tables, printed as they come."""

    HEAD = ["map", "size", "op", "workers", "time s", "throughput", "peak RSS MB", "growth MB",
            "growth / quarter", "tree peak MB", "output MB", "bits", "< 2 GB"]

    def __init__(self, baseline: int):
        self.baseline, self.rows, self.failures, self.first = baseline, [], [], {}
        self.parallel: list[list[str]] = []
        self.grids: list[list[str]] = []
        self.remote: list[list[str]] = []
        self.seconds: dict[tuple[str, str, int], float] = {}

    def add(self, kind: str, size: str, op: str, workers: int | str, m: dict[str, Any], units: float, unit: str,
            out_bytes: int, coded_bytes: int, per: float, per_unit: str) -> None:
        if "error" in m:
            self.failures.append(f"{kind} {size} {op} (workers {workers}): {m['error']}")
            self.rows.append([kind, size, op, str(workers), f"{m['wall']:.0f}", "failed", _mb(m["peak"]),
                              "", "", _mb(m["tree"]), "", "", ""])
            print(" | ".join(self.rows[-1]), "|", m["error"], flush=True)
            return
        growth = m["peak"] - self.baseline
        key = (kind, op, workers)
        self.first.setdefault(key, growth)
        self.rows.append([kind, size, op, str(workers), f"{m['seconds']:.0f}",
                          f"{units / m['seconds'] / 1e6:.2f} M {unit}/s", _mb(m["peak"]), _mb(growth),
                          f"{growth / self.first[key]:.2f}", _mb(m["tree"]), f"{out_bytes / 1e6:,.1f}",
                          f"{8 * coded_bytes / per:.3f} b/{per_unit}", "PASS" if m["peak"] < RSS_TARGET else "MISS"])
        print(" | ".join(self.rows[-1]), flush=True)


#: The compress target of every run (``--target-max-error``): none by default (the default cutoff and step).
TARGET: dict[str, float] = {}


def _job(op: str, src: Path, dst: Path, workers: int | str | None, **extra: Any) -> dict[str, Any]:
    """A run's job; ``workers``: None (serial), a local cluster's size, or ``"scheduler"`` (:data:`SCHEDULER`)."""
    if workers == "scheduler":
        return {"op": op, "src": str(src), "dst": str(dst), "tile": TILE_SIZE, "workers": None,
                "scheduler": SCHEDULER, "target": TARGET, **extra}
    return {"op": op, "src": str(src), "dst": str(dst), "tile": TILE_SIZE, "workers": workers, "target": TARGET,
            **extra}


def _scheduler_workers(address: str) -> int:
    """Workers connected to the scheduler at ``address`` now."""
    import distributed

    with distributed.Client(address, timeout=10) as client:
        return len(client.scheduler_info()["workers"])


def _runs(first: bool) -> list[int | str | None]:
    """Serial, then (on the first size, or every size with PARALLEL_EVERY_SIZE) the clusters."""
    if not (first or PARALLEL_EVERY_SIZE):
        return [None]
    return [None, "scheduler"] if SCHEDULER else [None, 1, WORKERS]


def run_raster(data: Path, tmp: Path, fractions: Sequence[float], full_side: int, report: _Report,
               inputs: list[list[str]]) -> None:
    """Build, compress and decompress the GeoTIFF mosaic at each fraction; 2 workers on the first."""
    for n, f in enumerate(fractions):
        side = int(round(full_side * math.sqrt(f)))
        src, coded, back = tmp / f"mosaic_{side}.tif", tmp / f"mosaic_{side}.dftpc", tmp / f"mosaic_{side}_back.tif"
        t0 = time.perf_counter()
        valid = build_raster(data, src, side)
        inputs.append(["GeoTIFF", _fraction(f), f"{side:,} x {side:,}", f"{side * side:,} cells ({valid:,} valid)",
                       f"{src.stat().st_size / 1e6:,.0f}", f"{time.perf_counter() - t0:.0f}"])
        print(" | ".join(inputs[-1]), flush=True)
        size = f"{_fraction(f)} ({side:,}²)"
        cells = side * side
        for workers in _runs(n == 0):
            dst = coded if workers is None else coded.with_suffix(f".w{workers}.dftpc")
            label = _label(workers)
            m = measure(_job("compress", src, dst, workers))
            nbytes = dst.stat().st_size if dst.exists() else 0
            report.add("GeoTIFF", size, "compress", label, m, cells, "cells", nbytes, nbytes,
                       m.get("cells") or 1, "cell")
            if workers is not None:
                _parallel(report, "compress", size, label, m, coded, dst)
            if not coded.exists():
                break
            if n == 0 and workers is None:
                report.remote += remote_reads(coded)
            out = back if workers is None else back.with_suffix(f".w{workers}.tif")
            m = measure(_job("decompress", coded, out, workers))
            obytes = out.stat().st_size if out.exists() else 0
            report.add("GeoTIFF", size, "decompress", label, m, cells, "cells", obytes,
                       coded.stat().st_size, m.get("written") or 1, "cell")
            if workers is not None:
                _parallel(report, "decompress", size, label, m, back, out)
                out.unlink(missing_ok=True)
                dst.unlink(missing_ok=True)
        back.unlink(missing_ok=True)
        coded.unlink(missing_ok=True)
        src.unlink(missing_ok=True)


def _label(workers: int | str | None) -> str:
    if workers == "scheduler":
        assert SCHEDULER is not None
        return f"{_scheduler_workers(SCHEDULER)} at {SCHEDULER}"
    return "serial" if workers is None else str(workers)


def _parallel(report: "_Report", op: str, size: str, workers: str, m: dict[str, Any], serial: Path,
              parallel: Path) -> None:
    """A row of the parallel table: the serial run's time (the last serial row of ``op`` at ``size``),
    this run's on ``workers`` workers, the speed-ups, and whether the outputs are byte-identical."""
    one = next((r for r in reversed(report.rows) if r[1] == size and r[2] == op and r[3] == "serial"), None)
    if "error" in m or one is None or one[5] == "failed":
        report.parallel.append([op, size, workers, one[4] if one else "", f"{m['wall']:.0f}", "failed",
                                "", "", ""])
        return
    same = serial.exists() and parallel.exists() and filecmp.cmp(serial, parallel, shallow=False)
    report.seconds[(op, size, workers)] = m["seconds"]
    single = report.seconds.get((op, size, "1"))
    report.parallel.append([op, size, workers, one[4], f"{m['seconds']:.0f}",
                            f"{float(one[4]) / m['seconds']:.2f}",
                            f"{single / m['seconds']:.2f}" if single and workers != "1" else "",
                            "yes" if same else "NO", _mb(m["tree"])])


#: Regions read by URL from the coded quarter map: this many tiles a side, from its middle.
REMOTE_TILES = (1, 2, 4)


def remote_reads(coded: Path) -> list[list[str]]:
    """Bytes fetched to decode 1, 4 and 16 tiles of ``coded`` by URL (a loopback HTTP server with byte
    ranges, in this process), against the file's size: what a bbox read over the network costs."""
    import http.server

    import dftpcc

    class Ranges(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args: Any) -> None:
            pass

        def do_GET(self) -> None:  # noqa: N802 - http.server's name
            data = Path(self.translate_path(self.path)).read_bytes()
            found = re.fullmatch(r"bytes=(\d+)-(\d*)", self.headers.get("Range", ""))
            start, end = (int(found[1]), min(int(found[2]) + 1 if found[2] else len(data), len(data))) \
                if found else (0, len(data))
            self.send_response(206 if found else 200)
            if found:
                self.send_header("Content-Range", f"bytes {start}-{end - 1}/{len(data)}")
            self.send_header("Content-Length", str(end - start))
            self.end_headers()
            self.wfile.write(data[start:end])
            self.server.sent += end - start  # type: ignore[attr-defined]

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0),
                                             lambda *a, **k: Ranges(*a, directory=str(coded.parent), **k))
    server.sent = 0  # type: ignore[attr-defined]
    threading.Thread(target=server.serve_forever, daemon=True).start()
    url = f"http://127.0.0.1:{server.server_address[1]}/{coded.name}"
    size = coded.stat().st_size
    rows = []
    try:
        for k in REMOTE_TILES:
            server.sent = 0  # type: ignore[attr-defined]
            t0 = time.perf_counter()
            with dftpcc.open(url) as cmap:
                g, tile = cmap.grid, cmap.block
                r0 = (g.rows // tile // 2 - k // 2) * tile
                c0 = (g.cols // tile // 2 - k // 2) * tile
                dem = cmap.read_window((r0, r0 + k * tile), (c0, c0 + k * tile))
                fetched = cmap.bytes_read
            rows.append([f"{k * k}", f"{k * tile:,}²", f"{int(dem.mask.sum()):,}", f"{fetched / 1e6:,.2f}",
                         f"{server.sent / 1e6:,.2f}",  # type: ignore[attr-defined]
                         f"{size / 1e6:,.1f}", f"{100 * fetched / size:.1f} %", f"{time.perf_counter() - t0:.1f}"])
            print(" | ".join(rows[-1]), flush=True)
    finally:
        server.shutdown()
        server.server_close()
    return rows


def run_cloud(data: Path, tmp: Path, copies: Sequence[int], report: _Report, inputs: list[list[str]],
              fractions: Sequence[float]) -> None:
    """Build, compress (read in chunks) and decompress (to LAZ) the cloud mosaic at each size."""
    for f, k in zip(fractions, copies):
        src, coded, back = tmp / f"forest_x{k}.laz", tmp / f"forest_x{k}.dftpc", tmp / f"forest_x{k}_back.laz"
        if CLOUD_FILE is not None:
            src = CLOUD_FILE.with_name(f"{CLOUD_FILE.stem}_x{k}{CLOUD_FILE.suffix}")
        t0 = time.perf_counter()
        if CLOUD_FILE is not None and src.exists():  # built by an earlier run, kept
            import laspy

            with laspy.open(src) as fh:
                points = int(fh.header.point_count)
        else:
            points = build_cloud(data, src, k)
        inputs.append(["LAZ", _fraction(f), f"{k} copies", f"{points:,} points", f"{src.stat().st_size / 1e6:,.0f}",
                       f"{time.perf_counter() - t0:.0f}"])
        print(" | ".join(inputs[-1]), flush=True)
        size = f"{_fraction(f)} ({points / 1e6:.0f} M)"
        m = measure(_job("compress", src, coded, None, chunk=CLOUD_CHUNK, resolution=CLOUD_RESOLUTION))
        nbytes = coded.stat().st_size if coded.exists() else 0
        report.add("LAZ", size, "compress", "serial", m, points, "points", nbytes, nbytes, points, "point")
        if "error" not in m:
            report.grids.append([size, f"{m['rows']:,} x {m['cols']:,}", f"{m['rows'] * m['cols']:,}",
                                 f"{m['cells']:,}", f"{m['resolution']:.3f}"])
            if CHECK_CLOUD:
                c = check_cloud(src, coded, CLOUD_RESOLUTION, tmp)
                report.grids[-1] += [f"{c['max_error']:.3g} ({_promise(c['promised_max'])})",
                                     f"{c['rmse']:.3g} ({_promise(c['promised_rmse'])})",
                                     "yes" if c["holds"] else "NO"]
                print(" | ".join(report.grids[-1]), flush=True)
            d = measure(_job("decompress", coded, back, None))
            obytes = back.stat().st_size if back.exists() else 0
            report.add("LAZ", size, "decompress", "serial", d, d.get("written") or 1, "points", obytes, nbytes, points,
                       "point")
        for path in (back, coded) if CLOUD_FILE is not None else (back, coded, src):
            path.unlink(missing_ok=True)


#: Columns of the decoded map compared with the cloud's grid at a time (check_cloud).
CHECK_COLS = 4096


def check_cloud(src: Path, coded: Path, resolution: float | None, tmp: Path) -> dict[str, Any]:
    """The coded cloud's errors against its grid, in bounded memory: the cloud gridded again band by band
    (the compress's own gridding, ``files._fit`` and ``grid.rasterize_bands``, into ``tmp``) and the map
    decoded a window of a band of tiles by :data:`CHECK_COLS` columns at a time. Returns the largest
    error and the RMSE over the occupied cells (metres), the promises of the file's header, whether
    the occupancy is the grid's, and whether the promises hold."""
    import dftpcc
    from dftpcc import files
    from dftpcc.encoder import params_of
    from dftpcc.grid import rasterize_bands
    from dftpcc.io import open_reader

    with dftpcc.open(coded) as cmap:
        options = {"tile_size": TILE_SIZE, **({"resolution": resolution} if resolution else {})}
        params = params_of(None, options)
        folder = Path(tempfile.mkdtemp(prefix="check-", dir=tmp))
        try:
            with open_reader(src, chunk_points=CLOUD_CHUNK) as reader:
                cloud = files._fit(reader, params, lambda *_: None, bands=folder)
                bands = rasterize_bands(cloud.segments(), cloud.grid, folder, band_rows=cmap.block)
            g = cmap.grid
            assert (g.rows, g.cols) == bands.grid.shape, (g.shape, bands.grid.shape)
            worst, squares, cells, same = 0.0, 0.0, 0, True
            for r0 in range(0, g.rows, cmap.block):
                r1 = min(g.rows, r0 + cmap.block)
                for c0 in range(0, g.cols, CHECK_COLS):
                    c1 = min(g.cols, c0 + CHECK_COLS)
                    dem = cmap.read_window((r0, r1), (c0, c1))
                    mask = bands.mask(r0, r1, c0, c1)
                    same &= bool(np.array_equal(mask, dem.mask))
                    err = (dem.heights + dem.grid.z0 - bands.heights(r0, r1, c0, c1) - bands.grid.z0)[mask]
                    if err.size:
                        worst = max(worst, float(np.abs(err).max()))
                        squares += float(np.sum(err * err))
                        cells += err.size
        finally:
            shutil.rmtree(folder, ignore_errors=True)
        stats = cmap.header.stats
    rmse = math.sqrt(squares / max(cells, 1))
    promised_max, promised_rmse = stats.get("dem_max_error_m"), stats.get("dem_rmse_m")
    holds = same and (promised_max is None or worst <= promised_max) and \
        (promised_rmse is None or rmse <= promised_rmse * (1 + 1e-6))
    return {"max_error": worst, "rmse": rmse, "promised_max": promised_max, "promised_rmse": promised_rmse,
            "occupied": cells, "same_mask": same, "holds": holds}


def _promise(value: float | None) -> str:
    return "none" if value is None else f"{value:.3g}"


def _free_bytes(path: Path) -> int:
    return shutil.disk_usage(path).free


def main(argv: list[str] | None = None) -> int:
    ap = run_arguments(__doc__.splitlines()[0], f"a quarter of the full side ({FULL_SIDE // QUICK_DIVISOR:,}² cells) "
                                                f"and {FULL_COPIES // QUICK_DIVISOR} copies of the cloud")
    ap.add_argument("--only", choices=("raster", "cloud", "parallel"),
                    help="measure one of the two maps, or only the GeoTIFF's quarter with 1 and 2 workers")
    ap.add_argument("--target-max-error", type=float, metavar="METRES",
                    help="compress at this max-error target (rate control on the map's middle) instead of the "
                         "default cutoff and step")
    ap.add_argument("--parallel-every-size", action="store_true",
                    help=f"code every size on {WORKERS} workers too, not only the first")
    ap.add_argument("--sizes", nargs="+", choices=[_fraction(f) for f in FRACTIONS], metavar="SIZE",
                    help="measure only these sizes (quarter, half, whole) of each map")
    ap.add_argument("--scheduler", metavar="ADDRESS",
                    help="code the GeoTIFF's first size through this running dask scheduler (started in another "
                         "process; --tmp on a path every worker sees) instead of local clusters")
    ap.add_argument("--cloud-resolution", type=float, metavar="METRES",
                    help="grid the cloud at this cell size (0.25: 127 M cells for the whole cloud) instead of "
                         "the automatic one")
    ap.add_argument("--cloud-file", type=Path, metavar="PATH",
                    help="keep each size's LAZ as PATH's stem + _x<copies>.laz (outside the temporary folder) and "
                         "reuse it when it is there: the 102 M-point LAZ is built once")
    ap.add_argument("--check-cloud", action="store_true",
                    help="check each coded cloud against its grid, gridded again band by band: the largest error "
                         "and the RMSE within what its header promises (one more pass over the LAZ)")
    ap.add_argument("--tmp", type=Path, default=Path(tempfile.gettempdir()), help="where the temporary folder goes")
    args = ap.parse_args(argv)
    if not sys.platform.startswith("linux"):
        sys.exit("bench_big reads peak memory from /proc: Linux only")
    global PARALLEL_EVERY_SIZE, SCHEDULER, CLOUD_RESOLUTION, CHECK_CLOUD, CLOUD_FILE
    CHECK_CLOUD, CLOUD_FILE = args.check_cloud, args.cloud_file
    PARALLEL_EVERY_SIZE = args.parallel_every_size
    SCHEDULER = args.scheduler
    CLOUD_RESOLUTION = args.cloud_resolution
    if args.docs is None and (args.sizes or args.scheduler or args.cloud_resolution or args.cloud_file):
        args.docs = False  # a part of the run does not replace the full run's section
    fractions = [f for f in FRACTIONS if args.sizes is None or _fraction(f) in args.sizes]
    if args.target_max_error:
        TARGET["target_max_error"] = args.target_max_error
    divisor = QUICK_DIVISOR if args.quick else 1
    full_side = FULL_SIDE // divisor
    copies = [max(1, round(FULL_COPIES * f / divisor)) for f in fractions]
    # The full run's largest files: the mosaic (~2.2 GB), its decoded copy (~3.6 GB) and the LAZ (~0.4 GB).
    need = 8e9 / divisor ** 2
    if _free_bytes(args.tmp) < need:
        sys.exit(f"bench_big needs about {need / 1e9:.0f} GB free in {args.tmp}; "
                 f"{_free_bytes(args.tmp) / 1e9:.1f} GB are")
    import signal

    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # so the temporary folder is removed on a kill
    t0 = time.perf_counter()
    print(f"Measuring {library_label()}; {load_average()}; peak memory by "
          f"{'/usr/bin/time -v' if os.access(TIME_BIN, os.X_OK) else 'getrusage(RUSAGE_CHILDREN)'}.", flush=True)
    tmp = Path(tempfile.mkdtemp(prefix="dftpcc-bench-big-", dir=args.tmp))
    inputs: list[list[str]] = []
    try:
        base = measure({"op": "import"})
        report = _Report(base["peak"])
        print(f"baseline (python + import dftpcc): peak RSS {_mb(base['peak'])} MB", flush=True)
        if args.only in (None, "cloud"):
            run_cloud(args.data, tmp, copies, report, inputs, fractions)
        if args.only in (None, "raster"):
            run_raster(args.data, tmp, fractions, full_side, report, inputs)
        if args.only == "parallel":
            run_raster(args.data, tmp, fractions[:1], full_side, report, inputs)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    parts = _tables(report, inputs, base, full_side, copies)
    print("\n" + "\n\n".join(parts))
    finish_run(parts, args, "bench_big", "Maps larger than memory",
               f"Run time {time.perf_counter() - t0:.0f} s; {load_average()} at the end.")
    return 0


def _tables(report: _Report, inputs: list[list[str]], base: dict[str, Any], full_side: int,
            copies: Sequence[int]) -> list[str]:
    parts = [f"Inputs, built in one temporary folder (deleted after the run): a float32 GeoTIFF mosaic of the six "
             f"real DEMs of `dems/` ({REGION:,}-cell regions, each a mirrored, shifted copy of one DEM "
             f"reflected about its edges, heights about its median on a ramp of {RAMP_M:g} m; tiled "
             f"{BLOCK} x {BLOCK}, deflate + predictor 3, BigTIFF; written one row of blocks at a time), and a LAZ "
             f"of shifted copies of `{SOURCE_CLOUD}` laid side by side ({CLOUD_COPIES_PER_ROW} a row), "
             f"written copy after copy. The quarter and half maps are built the same way.",
             markdown_table(["map", "size", "shape", "content", "file MB", "build s"], inputs),
             f"Each run is a fresh process (`compress_file(..., tile_size={TILE_SIZE}"
             f"{''.join(f', {k}={v:g}' for k, v in TARGET.items())})`, the cloud with "
             f"`chunk_points={CLOUD_CHUNK:,}`"
             f"{f', resolution={CLOUD_RESOLUTION:g}' if CLOUD_RESOLUTION else ''}; `decompress_bands` to `.tif` / `.laz`; a band is coded and a "
             f"GeoTIFF decoded in column blocks of `stream.BLOCK_TILES` = {stream.BLOCK_TILES} tiles, with "
             f"GDAL's cache at `stream.GDAL_CACHE_BYTES` = {stream.GDAL_CACHE_BYTES / 2 ** 20:.0f} MiB). Peak RSS: "
             f"`/usr/bin/time -v` (the raw maximum resident set of the largest process, the run's own; "
             f"dask workers are separate processes); growth: above the {_mb(base['peak'])} MB of a process "
             "that only imports dftpcc; tree peak: the summed RSS of the process and its dask workers, sampled "
             f"every {SAMPLE_S} s; time: the call, without start-up and import; throughput: grid cells "
             "(the raster) or points read / written (the cloud) per second; bits per valid cell or per point "
             "read, of the .dftpc file. One run each.",
             markdown_table(_Report.HEAD, report.rows)]
    if report.parallel:
        clusters = (f"a dask scheduler started in another process (`scheduler={SCHEDULER!r}`; workers: those "
                    "connected when the run began; its workers' memory is not in the tree peak)" if SCHEDULER else
                    f"local dask clusters of 1 and {WORKERS} workers (`workers=1`, `workers={WORKERS}`)")
        parts += [f"Serial (this process) against {clusters}, on "
                  f"{'every size of the GeoTIFF' if PARALLEL_EVERY_SIZE else 'the GeoTIFF first size measured'}; "
                  "each worker reads its own windows of the file (the first pass too); identical: the output "
                  "compared byte for byte with the serial run's. The machine's load is stated above and below: "
                  "on a shared box a speed-up is only as good as the cores that were free.",
                  markdown_table(["op", "size", "workers", "serial s", "cluster s", "speed-up vs serial",
                                  "vs 1 worker", "identical", "tree peak MB"], report.parallel)]
    if report.remote:
        parts += [f"The quarter map read by URL (`dftpcc.open(url).read_window`, a loopback HTTP server with "
                  f"byte ranges, in the benchmark's process): the tiles from its middle, {', '.join(str(k * k) for k in REMOTE_TILES)} "
                  "of them; fetched: the bytes the reader asked for (its header, index and tiles); served: what "
                  "the server sent.",
                  markdown_table(["tiles", "region", "cells", "fetched MB", "served MB", "file MB", "share of file",
                                  "time s"], report.remote)]
    if report.grids:
        checked = ["max error m (promised)", "RMSE m (promised)", "holds"] if CHECK_CLOUD else []
        parts += [f"The cloud's grid ({f'{CLOUD_RESOLUTION:g} m cells' if CLOUD_RESOLUTION else 'automatic resolution'}); "
                  "one over `stream.STREAM_CELLS` is gridded band by band into files beside the output and coded from "
                  "them (`grid.rasterize_bands`, `stream.compress_bands`), memory holding a band of tile rows"
                  + ("; checked: the decoded map against the cloud gridded again, its errors over the occupied cells "
                     "and the header's promises (`check_cloud`)" if CHECK_CLOUD else "") + ":",
                  markdown_table(["size", "grid", "cells", "occupied", "resolution m", *checked], report.grids)]
    if report.failures:
        parts.append("Failures:\n\n" + "\n".join(f"- {f}" for f in report.failures))
    return parts


if __name__ == "__main__":
    raise SystemExit(main())
