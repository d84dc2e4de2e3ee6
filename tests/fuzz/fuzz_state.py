"""Fuzz the state file of a growing map: any state bytes must resume the map or raise a dftpcc error.

For every mutated state, :meth:`dftpcc.mapbuilder.MapBuilder.from_file` on
the map it belongs to must (docs/growing-maps.md, *Checks on reading*):

* raise nothing but :class:`dftpcc.DftpccError` subclasses (no BadZipFile,
  OverflowError, TypeError, MemoryError ...);
* when it accepts the state, give the very map the seed state gives (its
  :meth:`encode` is compared byte for byte): an accepted state never gives
  another map silently;
* allocate at most :data:`MEMORY_BUDGET_BYTES` (tracemalloc's peak, which
  numpy's arrays report to; measured on every ``trace_every``-th input, as
  tracemalloc triples the time of an input; the process's peak resident
  memory is reported too). The numpy kernels run (``DFTPCC_JIT=0``, the
  same bytes): compiling a numba kernel the first time an input reaches it
  allocates some 20 MB once, which is not the input's doing.

Each input's mode chooses the mutation: the state's bytes damaged blindly
(flips, cuts, inserts: the ZIP CRC and the state's checksum must catch
them), or crafted with every checksum made right again (ZIP CRCs and the
state's SHA-256), so mutations reach the checks behind them: a member's
``.npy`` bytes mutated, a setting replaced by a hostile value, array
entries set to hostile numbers. A third of the inputs start from a state
one update ahead of its map (the interrupted-update path, which codes the
map again from the state).

``python tests/fuzz/fuzz_state.py --iterations 100000 [--seed N] [--trace-every N]``
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import io
import json
import os
import random
import resource
import sys
import tempfile
import time
import tracemalloc
import traceback
import warnings
import zipfile
from pathlib import Path

import numpy as np

if __name__ == "__main__":  # run as a script: the package from the checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "src"))

from dftpcc.errors import DftpccError  # noqa: E402
from dftpcc.mapbuilder import MapBuilder, state_path  # noqa: E402
from dftpcc.mapstate import ARRAYS  # noqa: E402

try:
    from .mutations import blind as _blind
except ImportError:  # run as a script
    from mutations import blind as _blind  # type: ignore[no-redef]  # noqa: E402


def blind(data: bytes, rnd: random.Random) -> bytes:
    """One structure-blind mutation (cuts of up to 4 kB: a state's members are larger than a delta's)."""
    return _blind(data, rnd, longest_cut=4096)

#: No input may make reading a state allocate more (bytes; a seed state is about 60 kB, its
#: map 3 kB, and resuming one takes about 1.3 MB, the interrupted-update path about 2.5 MB).
MEMORY_BUDGET_BYTES = 16 * 2**20
#: Hostile values a crafted setting takes.
HOSTILE_SETTINGS = [None, True, False, 0, -1, 1, 2**31 - 1, 2**63, -(2**63), 2**70, 1e308, -1e308, 5e-324, 1.5,
                    "", "0", "NaN", [], [0, 0], [0, 0, 0], [1e300, 0, 0], [None, 0, 0], {}, {"wkt": 5},
                    {"wkt": "x", "las_vlrs": {}}, "0" * 64, "f" * 63, float("nan"), float("inf")]
#: Hostile numbers crafted array entries take.
HOSTILE_NUMBERS = [0, -1, 1, 2**31 - 1, -(2**31), 2**53, -(2**63), 2**63 - 1, float("inf"), float("-inf"),
                   float("nan"), 1e308, -1e-300, 0.5]
_ORDER = ("settings", *ARRAYS)


def seed_states(folder: Path) -> list[tuple[Path, bytes, bytes]]:
    """(map path, state bytes, the map the state gives) of a small growing map: resumed, and one update ahead."""
    rng = np.random.default_rng(4)

    def patch(cx: float, cy: float, n: int = 1500) -> np.ndarray:
        xy = np.c_[cx, cy] + rng.random((n, 2)) * 6.0
        return np.c_[xy, np.sin(xy[:, 0]) + 0.1 * xy[:, 1]]

    builder = MapBuilder(0.25, tile_size=16, step=0.01, origin=(0.0, 0.0, 0.0))
    resumed = folder / "resumed.dftpc"
    data = builder.add(patch(0, 0)).add(patch(6, 2)).save(resumed)
    ahead = folder / "ahead.dftpc"
    builder.save(ahead)
    newer = builder.add(patch(-3, 4)).save(ahead)
    ahead.write_bytes(data)  # as if killed between the state's rename and the map's
    return [(resumed, state_path(resumed).read_bytes(), data), (ahead, state_path(ahead).read_bytes(), newer)]


def _members(state: bytes) -> dict[str, bytes]:
    with zipfile.ZipFile(io.BytesIO(state)) as archive:
        return {name[:-4]: archive.read(name) for name in archive.namelist()}


def _zip(members: dict[str, bytes]) -> bytes:
    """A state of these ``.npy`` members with the ZIP CRCs and the state's SHA-256 right."""
    digest = hashlib.sha256()
    for name in _ORDER:
        digest.update(members.get(name, b""))
    members = dict(members)
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.frombuffer(digest.digest(), np.uint8))
    members["checksum"] = buf.getvalue()
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as archive:
        for name, raw in members.items():
            archive.writestr(zipfile.ZipInfo(f"{name}.npy", (1980, 1, 1, 0, 0, 0)), raw)
    return out.getvalue()


def _npy(value: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, value, allow_pickle=False)
    return buf.getvalue()


def mutate(state: bytes, rnd: random.Random) -> bytes:
    """A damaged state (kind 0) or a crafted one, every checksum right (kinds 1-3)."""
    kind = rnd.randrange(4)
    if kind == 0:
        return blind(state, rnd)
    members = _members(state)
    members.pop("checksum", None)
    if kind == 1:  # a member's .npy bytes (its header or its values)
        name = rnd.choice(_ORDER)
        members[name] = blind(members[name], rnd) if rnd.random() < 0.7 else members[name][:rnd.randrange(200)]
        if rnd.random() < 0.05:
            del members[rnd.choice(_ORDER)]
    elif kind == 2:  # a setting
        settings = json.loads(str(np.load(io.BytesIO(members["settings"]))))
        key = rnd.choice([*settings, "extra"])
        settings[key] = rnd.choice(HOSTILE_SETTINGS)
        if rnd.random() < 0.1:
            settings.pop(rnd.choice(list(settings)))
        members["settings"] = _npy(np.array(json.dumps(settings)))
    else:  # array entries
        name = rnd.choice(list(ARRAYS))
        values = np.load(io.BytesIO(members[name])).copy()
        flat = values.reshape(-1)
        for _ in range(rnd.randint(1, 3)):
            if flat.size:
                value = rnd.choice(HOSTILE_NUMBERS)
                if values.dtype.kind == "i":
                    value = value if isinstance(value, int) else 0
                    value = int(np.clip(value, np.iinfo(values.dtype).min, np.iinfo(values.dtype).max))
                flat[rnd.randrange(flat.size)] = value
        members[name] = _npy(values)
    return _zip(members)


def check(map_path: Path, state: bytes, expected: bytes, target: Path, *, trace: bool = True) -> tuple[str, int]:
    """Resume the map with one state: ('accepted' or the dftpcc error's name, peak bytes or 0 untraced);
    anything else raises."""
    target.write_bytes(state)
    if trace:
        tracemalloc.start()
        tracemalloc.reset_peak()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the interrupted-update path warns that it recovered
            builder = MapBuilder.from_file(map_path, target)
            given = builder.encode()
    except DftpccError as exc:
        return type(exc).__name__, tracemalloc.get_traced_memory()[1] if trace else 0
    finally:
        peak = tracemalloc.get_traced_memory()[1] if trace else 0
        if trace:
            tracemalloc.stop()
    if given != expected:
        raise AssertionError("an accepted state gave another map")
    return "accepted", peak


def run(iterations: int, *, seed: int = 0, trace_every: int = 1, progress: int = 0) -> dict:
    """Resume the seed maps with ``iterations`` mutated states; the outcomes counted, failures, peak memory."""
    jit = os.environ.get("DFTPCC_JIT")
    os.environ["DFTPCC_JIT"] = "0"
    try:
        return _run(iterations, seed=seed, trace_every=trace_every, progress=progress)
    finally:
        if jit is None:
            del os.environ["DFTPCC_JIT"]
        else:
            os.environ["DFTPCC_JIT"] = jit


def _run(iterations: int, *, seed: int, trace_every: int, progress: int) -> dict:
    rnd = random.Random(seed)
    outcomes: collections.Counter = collections.Counter()
    failures: list[dict] = []
    peak_max = 0
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        seeds = seed_states(folder)
        target = folder / "fuzzed.state"
        for map_path, state, expected in seeds:  # one-time costs (imports, caches) out of the first input's peak
            assert check(map_path, state, expected, target)[0] == "accepted"
        traced = 0
        for n in range(iterations):
            map_path, state, expected = seeds[0 if rnd.random() < 2 / 3 else 1]
            data = mutate(state, rnd)
            trace = n % trace_every == 0
            traced += trace
            try:
                outcome, peak = check(map_path, data, expected, target, trace=trace)
            except Exception as exc:  # noqa: BLE001 - a failure of the reader: kept for the report
                failures.append({"input": n, "error": f"{type(exc).__name__}: {exc}",
                                 "traceback": traceback.format_exc()[-2000:], "state": data.hex()[:400]})
                outcomes["failure"] += 1
                continue
            outcomes[outcome] += 1
            peak_max = max(peak_max, peak)
            if progress and (n + 1) % progress == 0:  # a long campaign stopped early still reports
                print(f"{n + 1} inputs, {time.perf_counter() - t0:.0f} s: {dict(outcomes)}, failures {len(failures)}, "
                      f"peak {peak_max:,} B", file=sys.stderr, flush=True)
            if peak > MEMORY_BUDGET_BYTES:
                failures.append({"input": n, "error": f"peak {peak:,} B over the budget {MEMORY_BUDGET_BYTES:,} B"})
    return {"iterations": iterations, "outcomes": dict(outcomes), "failures": failures, "traced": traced,
            "peak_bytes_max": peak_max, "peak_over_budget_max": round(peak_max / MEMORY_BUDGET_BYTES, 4),
            "process_max_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
            "wall_seconds": round(time.perf_counter() - t0, 1)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=20_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--trace-every", type=int, default=1, help="measure the peak memory of every N-th input")
    parser.add_argument("--progress", type=int, default=5000, help="print the outcomes so far every N inputs")
    args = parser.parse_args()
    report = run(args.iterations, seed=args.seed, trace_every=args.trace_every, progress=args.progress)
    kinds = collections.Counter(f["error"].split(":")[0] for f in report["failures"])
    print(dict(kinds), file=sys.stderr)
    for failure in report["failures"][:5]:
        print(failure.get("traceback", failure["error"]), file=sys.stderr)
    print({k: v for k, v in report.items() if k != "failures"} | {"failures": len(report["failures"])})
    return 1 if report["failures"] else 0


if __name__ == "__main__":
    sys.exit(main())
