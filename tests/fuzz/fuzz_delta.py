"""Fuzz delta application: any delta bytes must give the right map or raise a dftpcc error, within a memory budget.

For every mutated delta, :func:`dftpcc.delta.apply_delta` on a base map must
either raise a :class:`dftpcc.DftpccError` subclass (nothing else: no
IndexError, struct.error, zstd error, MemoryError) or return a map the
campaign knows whose SHA-256 is the one the delta names (a mutation can
never yield another map), and the memory it allocates (traced) must stay
under :func:`budget` of its inputs' sizes, however large the sizes the delta
declares (format.md, *Applying*: every size is checked before anything is
decompressed).

Two kinds of mutation. *Blind* ones flip, set, cut, insert or duplicate bytes
(the mode byte chooses whether the CRC-32 is made right again, so that they
reach the checks behind the checksum). *Structure-aware* ones take the delta
apart (head, SHA-256s, result size, pieces, zstd frame) and change one field
the way an attacker would: a piece's kind, offset or length, a piece added,
dropped or repeated, the result size, the SHA-256s swapped for another
version's, the new data changed and compressed again, its declared size
changed or left out, an RLE zstd bomb declaring up to 4 GiB; then put it
back together with its CRC right. The base is the delta's own most of the
time, else another version of the same growing map (the out-of-order
diagnosis reads the result's head) or junk.

The deltas come from real growing maps: the arid-mountain ALIRT survey
(heights 3,100-3,200 m) driven as four strips, and a small synthetic map
whose first version is a delta from nothing.

``python tests/fuzz/fuzz_delta.py --iterations 100000 [--seed N]``
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import random
import struct
import sys
import time
import tracemalloc
import zlib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import zstandard

if __name__ == "__main__":  # run as a script: the package from the checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "src"))

from dftpcc.format import leb128, read_leb128  # noqa: E402
from dftpcc.delta import (COPY, DATA, DATA_ALLOWANCE, HEAD_LIMIT, MAX_COPY_FACTOR, MAX_DATA_FACTOR,  # noqa: E402
                          apply_delta, make_delta)
from dftpcc.errors import DftpccError  # noqa: E402
from dftpcc.mapbuilder import MapBuilder  # noqa: E402

try:
    from .mutations import blind as mutate
except ImportError:  # run as a script
    from mutations import blind as mutate  # type: ignore[no-redef]  # noqa: E402

#: The real survey the growing map is made of (../shared/data).
SURVEY = Path(__file__).resolve().parents[3] / "shared" / "data" / "pointclouds" / "mountain_arid_alirt.las"
#: Traced bytes an application may take beyond this many times the largest data its sizes allow.
BUDGET_FACTOR = 4
#: ... plus this much (the result's head read to name another version, and the interpreter's small change).
BUDGET_SLACK = HEAD_LIMIT + (8 << 20)
#: The largest new data a bomb declares (4 GiB: what a 131 KB frame of RLE blocks holds).
BOMB_MAX = 1 << 32


def budget(base: bytes, delta: bytes) -> int:
    """Traced bytes applying ``delta`` to ``base`` may allocate at most (format.md, *Applying*):
    the base's copies, the new data the frame may give, and the result, a few times over."""
    data = MAX_DATA_FACTOR * len(delta) + DATA_ALLOWANCE
    return BUDGET_FACTOR * (len(base) + data + MAX_COPY_FACTOR * len(base)) + BUDGET_SLACK


def _survey_versions() -> list[bytes]:
    """Four versions of a growing map of the real arid-mountain survey, each a strip further east."""
    import dftpcc

    points = dftpcc.read(SURVEY).points
    x = points[:, 0]
    edges = np.quantile(x, [0.0, 0.3, 0.5, 0.75, 1.0])
    builder = MapBuilder(2.0, tile_size=16, step=0.01, origin=(float(x.min()), float(points[:, 1].min()), 3000.0))
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        out.append(builder.add(points[(x >= lo) & (x <= hi)]).encode())
    return out


def _synthetic_versions() -> list[bytes]:
    """Three versions of a small synthetic growing map (a scan added, a region grown)."""
    rng = np.random.default_rng(4)

    def patch(cx: float, cy: float, n: int = 1500) -> np.ndarray:
        xy = np.c_[cx, cy] + rng.random((n, 2)) * 6.0
        return np.c_[xy, np.sin(xy[:, 0]) + 0.1 * xy[:, 1]]

    builder = MapBuilder(0.25, tile_size=16, step=0.01, origin=(0.0, 0.0, 0.0))
    first = builder.add(patch(0, 0)).add(patch(6, 2)).encode()
    second = builder.add(patch(3, 1)).encode()
    third = builder.add(patch(-8, 9)).encode()
    return [first, second, third]


def seed_maps() -> list[list[bytes]]:
    """Sequences of versions of growing maps, each starting from nothing (b"")."""
    return [[b"", *_survey_versions()], [b"", *_synthetic_versions()]]


@dataclass(frozen=True)
class Parts:
    """A delta taken apart (format.md, *Deltas*)."""

    head: bytes  # magic, version and flags (12 bytes)
    base_sha: bytes
    result_sha: bytes
    result_size: int
    pieces: list[tuple[int, int, int]]  # (kind, offset or 0, length)
    data: bytes  # decompressed new data
    frame: bytes  # as found

    def pack(self, *, frame: bytes | None = None, crc: bool = True) -> bytes:
        body = bytearray(self.head + self.base_sha + self.result_sha)
        body += leb128(self.result_size) + leb128(len(self.pieces))
        for kind, offset, length in self.pieces:
            body += bytes([kind]) + (leb128(offset) if kind == COPY else b"") + leb128(length)
        body += self.frame if frame is None else frame
        check = zlib.crc32(body) if crc else random.getrandbits(32)
        return bytes(body + struct.pack("<I", check))


def take_apart(delta: bytes) -> Parts:
    """The parts of a delta ``make_delta`` wrote (trusted: the fuzzer's own seeds)."""
    head, base_sha, result_sha = delta[:12], delta[12:44], delta[44:76]
    result_size, pos = read_leb128(delta, 76, "delta")
    count, pos = read_leb128(delta, pos, "delta")
    pieces = []
    for _ in range(count):
        kind, pos = delta[pos], pos + 1
        offset = 0
        if kind == COPY:
            offset, pos = read_leb128(delta, pos, "delta")
        length, pos = read_leb128(delta, pos, "delta")
        pieces.append((kind, offset, length))
    frame = delta[pos:-4]
    data = zstandard.ZstdDecompressor().decompress(frame) if frame else b""
    return Parts(head, base_sha, result_sha, result_size, pieces, data, frame)


def rle_frame(size: int, value: int = 0, *, declared: int | None = None) -> bytes:
    """A zstd frame of ``size`` bytes of ``value`` in RLE blocks (4 bytes per 128 KiB), declaring ``declared``."""
    block = 1 << 17
    out = b"\x28\xb5\x2f\xfd" + bytes([0xE0]) + (size if declared is None else declared).to_bytes(8, "little")
    full, last = divmod(size, block)
    if full and not last:
        full, last = full - 1, block
    rle = 1 << 1  # block type 1 in bits 1-2; bit 0 marks the last block
    return (out + (((block << 3) | rle).to_bytes(3, "little") + bytes([value])) * full
            + ((last << 3) | rle | 1).to_bytes(3, "little") + bytes([value]))


def _compress(data: bytes, rnd: random.Random, *, content_size: bool = True) -> bytes:
    return zstandard.ZstdCompressor(level=rnd.choice((1, 3)), write_content_size=content_size).compress(data)


def _a_length(rnd: random.Random, near: int) -> int:
    return rnd.choice((0, 1, near - 1, near + 1, 2 * near, near // 2, 1 << 31, 1 << 40, (1 << 64) - 1,
                       rnd.randrange(1 << 20)))


def mutate_structure(parts: Parts, versions: list[bytes], rnd: random.Random) -> bytes:
    """One structure-aware mutation of a delta's fields, put back together (CRC right most of the time)."""
    p = parts
    pieces = list(p.pieces)
    frame = None
    op = rnd.randrange(12)
    if op == 0 and pieces:  # a piece's length
        i = rnd.randrange(len(pieces))
        kind, offset, length = pieces[i]
        pieces[i] = (kind, offset, max(0, min(_a_length(rnd, length), (1 << 64) - 1)))
    elif op == 1 and pieces:  # a copy's offset
        i = rnd.randrange(len(pieces))
        _, offset, length = pieces[i]
        pieces[i] = (COPY, rnd.choice((0, offset + 1, offset - 1 if offset else 0, 1 << 33, rnd.randrange(1 << 16))),
                     length)
    elif op == 2 and pieces:  # a piece's kind
        i = rnd.randrange(len(pieces))
        _, offset, length = pieces[i]
        pieces[i] = (rnd.choice((COPY, DATA, 2, 0x80, 0xFF)), offset, length)
    elif op == 3:  # a piece added, dropped, repeated or pieces shuffled
        what = rnd.randrange(4)
        if what == 0:
            pieces.insert(rnd.randrange(len(pieces) + 1), (rnd.choice((COPY, DATA)), rnd.randrange(1 << 12),
                                                           rnd.randrange(1 << 12)))
        elif what == 1 and pieces:
            del pieces[rnd.randrange(len(pieces))]
        elif what == 2 and pieces:
            i = rnd.randrange(len(pieces))
            pieces[i:i] = [pieces[i]] * rnd.randint(1, 1000)
        else:
            rnd.shuffle(pieces)
    elif op == 4:  # the result size
        p = replace(p, result_size=_a_length(rnd, p.result_size) % (1 << 64))
    elif op == 5:  # the SHA-256s: another version's, swapped, or random
        shas = [hashlib.sha256(v).digest() for v in versions] + [p.result_sha, p.base_sha, bytes(32)]
        p = replace(p, base_sha=rnd.choice(shas), result_sha=rnd.choice(shas))
    elif op == 6 and p.data:  # the new data changed and compressed again (pieces as they were)
        data = bytearray(p.data)
        for _ in range(rnd.randint(1, 8)):
            data[rnd.randrange(len(data))] ^= 1 << rnd.randrange(8)
        frame = _compress(bytes(data), rnd)
    elif op == 7:  # the new data cut or extended, pieces as they were
        data = p.data[:rnd.randrange(len(p.data) + 1)] if rnd.random() < 0.5 else p.data + bytes(rnd.randint(1, 4096))
        frame = _compress(data, rnd)
    elif op == 8:  # a frame without its content size, or declaring another
        frame = _compress(p.data, rnd, content_size=False) if rnd.random() < 0.5 else \
            rle_frame(min(len(p.data), 1 << 20), declared=_a_length(rnd, len(p.data)) % (1 << 64))
    elif op == 9:  # a bomb: one data piece declaring up to 4 GiB in an RLE frame, sizes consistent
        size = rnd.choice((1 << 20, 1 << 24, 1 << 28, BOMB_MAX, MAX_DATA_FACTOR * 1000 + DATA_ALLOWANCE))
        frame = rle_frame(size, rnd.randrange(256))
        pieces = [(DATA, 0, size)]
        p = replace(p, result_size=size)
    elif op == 10:  # copies of the whole base, many times (the copy cap)
        pieces = [(COPY, 0, rnd.randint(1, 1 << 20))] * rnd.randint(1, 64) + pieces
        p = replace(p, result_size=sum(n for _, _, n in pieces))
    else:  # the version or flags
        head = bytearray(p.head)
        head[rnd.randrange(8, 12)] = rnd.randrange(256)
        p = replace(p, head=bytes(head))
    if op not in (4, 9, 10) and rnd.random() < 0.7:  # mostly keep the result size consistent with the pieces
        p = replace(p, result_size=sum(n for _, _, n in pieces) % (1 << 64))
    return replace(p, pieces=pieces).pack(frame=frame, crc=rnd.random() < 0.95)


def recrc(data: bytes) -> bytes:
    """The delta with its trailing CRC-32 made right again."""
    if len(data) < 4:
        return data
    return data[:-4] + struct.pack("<I", zlib.crc32(data[:-4]))


def check(base: bytes, delta: bytes, known: dict[bytes, bytes]) -> tuple[str, int]:
    """Apply one input: ('applied', traced peak) for a known map named by the delta, or the name of the
    dftpcc error; anything else raises (a traceback, another map, memory beyond :func:`budget`)."""
    tracemalloc.reset_peak()
    before = tracemalloc.get_traced_memory()[0]
    try:
        out = apply_delta(base, delta)
        outcome = "applied"
    except DftpccError as exc:
        out, outcome = None, type(exc).__name__
    peak = tracemalloc.get_traced_memory()[1] - before
    if peak > budget(base, delta):
        raise AssertionError(f"applying a {len(delta):,}-byte delta to a {len(base):,}-byte map took {peak:,} bytes, "
                             f"more than its budget of {budget(base, delta):,} ({outcome})")
    if out is not None and known.get(hashlib.sha256(out).digest()) != out:
        raise AssertionError("a mutated delta gave a map that is not one of the versions")
    return outcome, peak


def run(iterations: int, *, seed: int = 0, maps: list[list[bytes]] | None = None) -> dict:
    """Apply ``iterations`` mutated deltas; returns the outcomes counted, the largest traced peak and the wall time."""
    rnd = random.Random(seed)
    random.seed(seed)  # Parts.pack's wrong CRCs
    sequences = seed_maps() if maps is None else maps
    known = {hashlib.sha256(v).digest(): v for seq in sequences for v in seq}
    pairs = []
    for seq in sequences:
        for base, result in zip(seq[:-1], seq[1:]):
            delta = make_delta(base, result)
            pairs.append((seq, base, delta, take_apart(delta)))
    outcomes: collections.Counter = collections.Counter()
    largest = 0
    junk = bytes(range(256)) * 16
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        for _ in range(iterations):
            seq, base, delta, parts = rnd.choice(pairs)
            if rnd.random() < 0.7:
                data = mutate_structure(parts, seq, rnd)
            else:
                data = mutate(delta, rnd)
                data = recrc(data) if rnd.random() < 0.5 else data
            target = rnd.random()
            on = base if target < 0.8 else (rnd.choice(seq) if target < 0.97 else junk)
            outcome, peak = check(on, data, known)
            outcomes[outcome] += 1
            largest = max(largest, peak)
    finally:
        tracemalloc.stop()
    return {"iterations": iterations, "outcomes": dict(outcomes), "largest_peak_bytes": largest,
            "wall_seconds": round(time.perf_counter() - t0, 2)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=20_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(run(args.iterations, seed=args.seed))
    return 0


if __name__ == "__main__":
    sys.exit(main())
