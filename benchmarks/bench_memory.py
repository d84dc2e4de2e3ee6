"""Peak memory and time of compressing a large cloud, read whole and in chunks.

Builds LAZ files of k copies of the 2.83 M-point forest map (heights jittered
by 5 cm, same footprint, so the grid stays the same and only the points grow)
in a temporary folder, never in the repository. Each compression runs in a
fresh process that reports its own peak resident memory (VmHWM, Linux) above
what it held after importing dftpcc.

    .venv/bin/python -m benchmarks.bench_memory [--quick] [--copies 1 4 8] [--docs | --no-docs]

Prints a table; writes its section of docs/benchmarks.md on a full run.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

from benchmarks.common import finish_run, library_label, load_average, markdown_table, run_arguments

SOURCE = "forest_slope_bcts_2.8M.laz"
RESOLUTION = 0.5
COPIES = (1, 4, 8)
QUICK_COPIES = (1, 2)
CHUNKS = (None, 1_000_000, 250_000)

CHILD = textwrap.dedent("""
    import json, sys, time, warnings
    from dftpcc.files import compress_file

    def peak():
        with open("/proc/self/status") as fh:
            return next(int(line.split()[1]) * 1024 for line in fh if line.startswith("VmHWM:"))

    warnings.simplefilter("ignore")
    before = peak()
    t0 = time.perf_counter()
    m = compress_file(sys.argv[1], sys.argv[2], resolution=float(sys.argv[3]), chunk_points=int(sys.argv[4]) or None)
    print(json.dumps({"seconds": time.perf_counter() - t0, "growth": peak() - before, "bytes": m.header.stats["coef_bytes"],
                      "points": m.header.point_count, "cells": m.grid.size}))
""")


def make_copies(src: Path, dst: Path, copies: int) -> int:
    """A LAZ of ``copies`` copies of ``src`` with jittered heights; returns its point count."""
    import laspy

    cloud = laspy.read(src)
    header = laspy.LasHeader(point_format=cloud.header.point_format.id, version=cloud.header.version)
    header.scales, header.offsets = cloud.header.scales, cloud.header.offsets
    rng = np.random.default_rng(0)
    with laspy.open(dst, mode="w", header=header) as out:
        for _ in range(copies):
            part = laspy.ScaleAwarePointRecord.zeros(len(cloud.points), header=header)
            part.x, part.y = cloud.x, cloud.y
            part.z = np.asarray(cloud.z) + rng.normal(0.0, 0.05, len(cloud.points))
            out.write_points(part)
    return copies * len(cloud.points)


def measure(path: Path, chunk: int | None) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, str(path), str(path.with_suffix(".dftpc")), str(RESOLUTION),
                          str(chunk or 0)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def main(argv: list[str] | None = None) -> int:
    ap = run_arguments(__doc__.splitlines()[0], f"copies {QUICK_COPIES}")
    ap.add_argument("--copies", type=int, nargs="+", help=f"copies of the forest map per file (default {COPIES})")
    args = ap.parse_args(argv)
    if not sys.platform.startswith("linux"):
        sys.exit("bench_memory reads peak memory from /proc: Linux only")
    copies = args.copies or (QUICK_COPIES if args.quick else COPIES)
    source = args.data / "pointclouds" / SOURCE
    t0 = time.perf_counter()
    print(f"Measuring {library_label()}; {load_average()}.", flush=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in copies:
            path = Path(tmp) / f"forest_x{k}.laz"
            n = make_copies(source, path, k)
            whole = None
            for chunk in CHUNKS:
                m = measure(path, chunk)
                whole = whole or m
                rows.append([f"{n / 1e6:.1f} M", "whole" if chunk is None else f"chunks of {chunk:,}",
                             f"{m['growth'] / 1e6:,.0f}", f"{m['growth'] / n:.1f}",
                             f"{m['growth'] / whole['growth']:.2f}", f"{m['seconds']:.1f}",
                             f"{m['seconds'] / whole['seconds']:.2f}", f"{m['cells']:,}"])
                print(" | ".join(rows[-1]), flush=True)
    parts = [f"LAZ files of k copies of {SOURCE} (heights jittered, same footprint: the grid stays "
             f"{rows[0][-1]} cells at {RESOLUTION} m, only the points grow), compressed with the default "
             "profile from the file, each in a fresh process. Peak: its resident-memory high-water mark above "
             "what it held after importing dftpcc. One run each (bytes are deterministic, times are not).",
             markdown_table(["points", "read", "peak MB", "peak B/point", "peak / whole", "time s",
                             "time / whole", "cells"], rows)]
    finish_run(parts, args, "bench_memory", "Memory: clouds read whole and in chunks",
               f"Run time {time.perf_counter() - t0:.0f} s; {load_average()} at the end.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
