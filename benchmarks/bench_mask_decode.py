"""The occupancy mask's decoder, compiled (numba) against numpy/constriction: decode times, first calls.

Masks: 16 lidar-ring masks of 256 x 256 cells (one stripe, as a tile's) and a 1000 x 900 blob with
a few holes (64-line stripes, seeds). Each is coded once by ``occupancy.encode_mask`` (context coder)
and decoded by ``occupancy.decode_mask`` on both paths, which must give the same mask; medians and
ranges of the repeats, one process (pin it: ``taskset -c 1``). Then a fresh process's import,
``kernels.load()`` and first decode, with an empty and with a warm ``NUMBA_CACHE_DIR``.

    taskset -c 1 .venv/bin/python -m benchmarks.bench_mask_decode [--repeats N]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

from dftpcc import kernels, occupancy


def lidar_masks(count: int = 16, size: int = 256) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:size, :size]
    out = []
    for _ in range(count):
        cy, cx = rng.uniform(0, size, 2)
        out.append((np.mod(np.hypot(xx - cx, yy - cy), 7) < 1) & (rng.random((size, size)) < 0.6))
    return out


def blob_mask(rows: int = 1000, cols: int = 900) -> np.ndarray:
    rng = np.random.default_rng(1)
    y, x = np.mgrid[0:rows, 0:cols]
    r = np.hypot((y - rows / 2) / rows, (x - cols / 2) / cols)
    return (r < 0.4 + 0.05 * np.sin(x / 7.0)) & (rng.random((rows, cols)) > 0.02)


def timed(blobs: list[tuple[bytes, np.ndarray]], repeats: int) -> tuple[list[float], list[np.ndarray]]:
    """Wall ms of decoding all the blobs, per repeat (one warm-up first), and the masks."""
    masks = [occupancy.decode_mask(b, m.shape) for b, m in blobs]
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for b, m in blobs:
            occupancy.decode_mask(b, m.shape)
        times.append(1e3 * (time.perf_counter() - t0))
    return times, masks


def row(label: str, times: list[float]) -> str:
    return f"{label}: median {statistics.median(times):.2f} ms, range {min(times):.2f}-{max(times):.2f} ms ({len(times)} runs)"


FIRST = """
import sys, time
t0 = time.perf_counter()
import numpy as np
from dftpcc import kernels, occupancy
t1 = time.perf_counter()
assert kernels.load()
t2 = time.perf_counter()
saved = np.load(sys.argv[1])
blob, mask = saved["blob"].tobytes(), saved["mask"]
if sys.argv[2].startswith("pull first"):  # numba's own first call (its runtime), apart from the decoder's
    t = time.perf_counter()
    kernels.compiled_module().pull(np.ones((2, 2)), np.ones((2, 2), bool))
    print(f"a 2x2 pull first {1e3 * (time.perf_counter() - t):.0f} ms,", end=" ")
t3 = time.perf_counter()
assert np.array_equal(occupancy.decode_mask(blob, mask.shape), mask)
t4 = time.perf_counter()
occupancy.decode_mask(blob, mask.shape)
t5 = time.perf_counter()
print(f"import {1e3 * (t1 - t0):.0f} ms, kernels.load() {1e3 * (t2 - t1):.0f} ms, first decode_mask "
      f"{1e3 * (t4 - t3):.1f} ms, second {1e3 * (t5 - t4):.2f} ms")
"""


def first_calls(mask: np.ndarray) -> None:
    """A fresh process decoding ``mask`` (context-coded) before anything else: the decoder compiled,
    or read from numba's cache."""
    blob = occupancy.encode_mask(mask)
    assert blob[0] == occupancy.KIND_CONTEXT
    with tempfile.TemporaryDirectory() as tmp:
        saved = os.path.join(tmp, "mask.npz")
        np.savez(saved, blob=np.frombuffer(blob, np.uint8), mask=mask)
        cache = os.path.join(tmp, "numba")
        env = {**os.environ, "NUMBA_CACHE_DIR": cache, "DFTPCC_JIT": "1"}
        for label in ("empty cache", "warm cache", "warm cache again", "pull first", "pull first, pull cached"):
            out = subprocess.run([sys.executable, "-c", FIRST, saved, label], env=env, check=True,
                                 capture_output=True, text=True)
            print(f"fresh process, {label}: {out.stdout.strip()}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=31)
    args = ap.parse_args()
    assert kernels.load(), "numba is not installed"
    print(f"CPUs allowed: {sorted(os.sched_getaffinity(0))}, load average {os.getloadavg()[0]:.2f}")
    sets = {"16 lidar-ring masks 256 x 256": lidar_masks(), "1000 x 900 blob": [blob_mask()]}
    for name, masks in sets.items():
        blobs = [(occupancy.encode_mask(m), m) for m in masks]
        kinds = {b[0] for b, _ in blobs}
        assert kinds == {occupancy.KIND_CONTEXT}, kinds
        res = {}
        for label, env in (("compiled", None), ("numpy", "0")):
            if env is None:
                os.environ.pop("DFTPCC_JIT", None)
            else:
                os.environ["DFTPCC_JIT"] = env
            res[label] = timed(blobs, args.repeats)
        os.environ.pop("DFTPCC_JIT", None)
        assert all(np.array_equal(a, b) and np.array_equal(a, m)
                   for a, b, (_, m) in zip(res["compiled"][1], res["numpy"][1], blobs))
        cells = sum(m.size for m in masks)
        size = sum(len(b) for b, _ in blobs)
        print(f"{name} ({cells} cells, {size} bytes coded), decode_mask of all of them:")
        for label in ("compiled", "numpy"):
            print("  " + row(label, res[label][0]))
        print(f"  speed-up (medians): {statistics.median(res['numpy'][0]) / statistics.median(res['compiled'][0]):.1f}x")
    first_calls(sets["16 lidar-ring masks 256 x 256"][0])


if __name__ == "__main__":
    main()
