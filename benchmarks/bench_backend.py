"""Where the compiled kernels pay for their import: a one-shot compress or decompress, numpy against compiled.

A fresh process compresses (or decompresses) one crop of a real cloud, as ``dftpcc compress`` and
``dftpcc decompress`` do once per process; the clock covers the call alone, so the compiled run
includes numba's import and the load of every kernel it uses from numba's cache (warm: compiled
once before the runs), the numpy run none of that. Crops of the forest (2.8 M points) and the field
at 0.5 m cells, a band of the cloud's x range each, keep the density of the survey while the size
grows. The fixed cost of the compiled backend (its import and first calls) and its gain per point
(ns) come from a least-squares line through the differences; their ratio is the size above which
the compiled backend is the faster one-shot choice (:data:`dftpcc.kernels.COMPILED_MIN_POINTS`).

    .venv/bin/python -m benchmarks.bench_backend [--quick] [--repeats N]
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import dftpcc

from benchmarks.common import finish_run, load_average, markdown_table, run_arguments

#: Clouds (file under pointclouds/) and their cell size, metres.
CLOUDS = (("forest_slope_bcts_2.8M.laz", 0.5), ("field_gentle_ign.laz", 0.5))
#: Shares of each cloud's x range cropped, smallest first.
SHARES = (0.01, 0.03, 0.1, 0.3, 1.0)
QUICK_SHARES = (0.03, 0.3, 1.0)
REPEATS = 5
QUICK_REPEATS = 3

#: One timed call in a fresh process: argv[1] "compress" or "decompress", argv[2] the input, argv[3] the
#: resolution; prints the CPU seconds of the call alone (the process's: every thread), then its wall seconds.
_CHILD = r"""
import sys, time, warnings
import numpy as np
import dftpcc
warnings.simplefilter("ignore")
verb, path, resolution = sys.argv[1], sys.argv[2], float(sys.argv[3])
if verb == "compress":
    points = np.load(path)
    params = dftpcc.make_params(resolution=resolution)
    c0, t0 = time.process_time(), time.perf_counter()
    dftpcc.compress(points, params)
else:
    blob = open(path, "rb").read()
    c0, t0 = time.process_time(), time.perf_counter()
    dftpcc.decompress(blob)
print(time.process_time() - c0, time.perf_counter() - t0)
"""


def one_shot(verb: str, path: Path, resolution: float, jit: str) -> float:
    """CPU seconds of one call in a fresh process (on a busy machine the CPU time is the steadier
    figure: the wall time adds whatever else runs)."""
    env = {**os.environ, "DFTPCC_JIT": jit, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", _CHILD, verb, str(path), str(resolution)], env=env, check=True,
                         capture_output=True, text=True)
    return float(out.stdout.split()[-2])


def main() -> None:
    parser = run_arguments("One-shot compress and decompress, numpy against compiled, by size: the threshold "
                           "above which the compiled kernels pay for their import.",
                           f"{len(QUICK_SHARES)} sizes and {QUICK_REPEATS} repeats")
    parser.add_argument("--repeats", type=int, default=None, help=f"fresh processes per timing (default {REPEATS})")
    args = parser.parse_args()
    repeats = args.repeats or (QUICK_REPEATS if args.quick else REPEATS)
    shares = QUICK_SHARES if args.quick else SHARES
    start = time.perf_counter()
    rows, fits = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for name, resolution in CLOUDS:
            if args.files and not any(name.startswith(w) for w in args.files):
                continue
            points = np.ascontiguousarray(dftpcc.read(Path(args.data) / "pointclouds" / name).points)
            x = points[:, 0]
            lo, hi = float(x.min()), float(x.max())
            sizes, gains = [], {"compress": [], "decompress": []}
            for share in shares:
                crop = points[x <= lo + share * (hi - lo)]
                cloud, blob = Path(tmp) / "cloud.npy", Path(tmp) / "map.dftpc"
                np.save(cloud, crop)
                blob.write_bytes(dftpcc.compress(crop, dftpcc.make_params(resolution=resolution)))
                one_shot("compress", cloud, resolution, "1")  # numba's cache warm for these kernels
                one_shot("decompress", blob, resolution, "1")
                row = [name.split("_")[0], f"{crop.shape[0]:,}"]
                for verb, path in (("compress", cloud), ("decompress", blob)):
                    t = {jit: [] for jit in ("0", "1")}
                    for _ in range(repeats):  # interleaved, so both see the same load
                        for jit in ("0", "1"):
                            t[jit].append(one_shot(verb, path, resolution, jit))
                    numpy_s, compiled_s = statistics.median(t["0"]), statistics.median(t["1"])
                    gains[verb].append(numpy_s - compiled_s)
                    row += [f"{1e3 * numpy_s:.0f}", f"{1e3 * compiled_s:.0f}"]
                sizes.append(crop.shape[0])
                rows.append(row)
                print(" | ".join(row), flush=True)
            for verb, gain in gains.items():
                # gain(n) = per_point * n - fixed: the compiled backend's import and first calls against
                # its speed per point.
                per_point, intercept = np.polyfit(np.asarray(sizes, float), np.asarray(gain), 1)
                fixed = -intercept
                fits.append([name.split("_")[0], verb, f"{1e3 * fixed:.0f}", f"{1e9 * per_point:.1f}",
                             f"{fixed / per_point:,.0f}" if per_point > 0 else "never"])
    parts = [f"{repeats} fresh processes per timing, medians; CPU ms of the call alone (the interpreter, "
             "dftpcc's import and the input's read outside the clock); numba's cache warm. "
             + " ".join(__doc__.split("\n\n")[1].split()),
             markdown_table(["cloud", "points", "compress numpy ms", "compiled ms", "decompress numpy ms",
                             "compiled ms"], rows),
             markdown_table(["cloud", "call", "compiled fixed cost ms", "compiled gain ns / point",
                             "break-even points"], fits)]
    for part in parts:
        print(part + "\n")
    finish_run(parts, args, "bench_backend", "The compiled backend's threshold (issue 40)",
               f"Run time {time.perf_counter() - start:.0f} s; {load_average()} at the end.")


if __name__ == "__main__":
    main()
