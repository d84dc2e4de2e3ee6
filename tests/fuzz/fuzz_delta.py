"""Fuzz delta application: any delta bytes must give the right map or raise a dftpcc error.

For every mutated delta, :func:`dftpcc.delta.apply_delta` on the base map must
either raise a :class:`dftpcc.DftpccError` subclass (nothing else: no
IndexError, struct.error, zstd error, MemoryError) or return exactly the map
the original delta gives (the result's SHA-256 is checked, so a mutation can
never yield another map).

The mode byte of each input chooses whether the CRC-32 is recomputed after the
mutation (a crafted delta rather than a damaged one, so mutations reach the
checks behind the checksum).

``python tests/fuzz/fuzz_delta.py --iterations 20000 [--seed N]``
"""

from __future__ import annotations

import argparse
import collections
import random
import struct
import sys
import time
import zlib
from pathlib import Path

import numpy as np

if __name__ == "__main__":  # run as a script: the package from the checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "src"))

from dftpcc.delta import apply_delta, make_delta  # noqa: E402
from dftpcc.errors import DftpccError  # noqa: E402
from dftpcc.mapbuilder import MapBuilder  # noqa: E402


def seed_maps() -> list[tuple[bytes, bytes]]:
    """(base, result) pairs of a small growing map: a scan added, a region grown, and a first version."""
    rng = np.random.default_rng(4)

    def patch(cx: float, cy: float, n: int = 1500) -> np.ndarray:
        xy = np.c_[cx, cy] + rng.random((n, 2)) * 6.0
        return np.c_[xy, np.sin(xy[:, 0]) + 0.1 * xy[:, 1]]

    builder = MapBuilder(0.25, tile_size=16, step=0.01, origin=(0.0, 0.0, 0.0))
    first = builder.add(patch(0, 0)).add(patch(6, 2)).encode()
    second = builder.add(patch(3, 1)).encode()
    third = builder.add(patch(-8, 9)).encode()
    return [(first, second), (second, third), (b"", first)]


def mutate(data: bytes, rnd: random.Random) -> bytes:
    """One structure-blind mutation: flip, set, cut, insert or duplicate bytes."""
    buf = bytearray(data)
    for _ in range(rnd.randint(1, 4)):
        choice = rnd.random()
        pos = rnd.randrange(len(buf)) if buf else 0
        if choice < 0.35 and buf:
            buf[pos] ^= 1 << rnd.randrange(8)
        elif choice < 0.55 and buf:
            buf[pos] = rnd.choice((0, 1, 0x7F, 0x80, 0xFF, rnd.randrange(256)))
        elif choice < 0.7:
            del buf[pos:pos + rnd.randint(1, 64)]
        elif choice < 0.85:
            buf[pos:pos] = bytes(rnd.randrange(256) for _ in range(rnd.randint(1, 16)))
        else:
            start = rnd.randrange(len(buf)) if buf else 0
            buf[pos:pos] = buf[start:start + rnd.randint(1, 64)]
    return bytes(buf)


def recrc(data: bytes) -> bytes:
    """The delta with its trailing CRC-32 made right again."""
    if len(data) < 4:
        return data
    return data[:-4] + struct.pack("<I", zlib.crc32(data[:-4]))


def check(base: bytes, delta: bytes, expected: bytes) -> str:
    """Apply one input: 'applied' (the right map), or the name of the dftpcc error; anything else raises."""
    try:
        out = apply_delta(base, delta)
    except DftpccError as exc:
        return type(exc).__name__
    if out != expected:
        raise AssertionError("a mutated delta gave another map than its original")
    return "applied"


def run(iterations: int, *, seed: int = 0) -> dict:
    """Apply ``iterations`` mutated deltas; returns the outcomes counted and the wall time."""
    rnd = random.Random(seed)
    pairs = [(base, result, make_delta(base, result)) for base, result in seed_maps()]
    outcomes: collections.Counter = collections.Counter()
    t0 = time.perf_counter()
    for _ in range(iterations):
        base, result, delta = rnd.choice(pairs)
        crafted = rnd.random() < 0.5
        data = mutate(delta, rnd)
        outcomes[check(base, recrc(data) if crafted else data, result)] += 1
    return {"iterations": iterations, "outcomes": dict(outcomes), "wall_seconds": round(time.perf_counter() - t0, 2)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=20_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(run(args.iterations, seed=args.seed))
    return 0


if __name__ == "__main__":
    sys.exit(main())
