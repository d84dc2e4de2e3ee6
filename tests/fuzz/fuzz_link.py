"""Fuzz the link's two ends: mutated frames must be refused or give exactly the sender's map.

Each input is a change's genuine frames with some of them mutated (flip, set,
cut, insert, duplicate bytes; half of them with the CRC made right again, so
mutations reach the checks behind it), shuffled, fed to a
:class:`dftpcc.link.Receiver` that holds the change's base. The receiver must
never raise, and its map must stay the base or become exactly the target
(every byte). Half the changes carry a preview (item 2^32 - 1): a preview the
receiver takes is display only, and decoding it must give points or refuse with
a dftpcc error, nothing else. Mutated acknowledgements fed to a
:class:`dftpcc.link.Sender` must never make it raise.

``python tests/fuzz/fuzz_link.py --iterations 100000 [--seed N]``
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import random
import sys
import time
from pathlib import Path

if __name__ == "__main__":  # run as a script: the package from the checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "src"))

import numpy as np  # noqa: E402

from dftpcc.encoder import compress  # noqa: E402
from dftpcc.errors import DftpccError  # noqa: E402
from dftpcc.link import Ack, Receiver, Sender, pack_ack  # noqa: E402
from dftpcc.mapfile import decompress  # noqa: E402

try:
    from .fuzz_delta import mutate, recrc, seed_maps
except ImportError:  # run as a script
    from fuzz_delta import mutate, recrc, seed_maps  # type: ignore[no-redef]  # noqa: E402

FRAME = 160  # bytes: small frames, many parts


def seed_changes() -> list[tuple[bytes, bytes, list[bytes], int]]:
    """(base, target, frames, map id) of the delta fuzzer's seed maps, and an acknowledgement's bytes."""
    out = []
    # Each pair of consecutive versions of the delta fuzzer's growing maps (the first from nothing).
    pairs = [(versions[i], versions[i + 1]) for versions in seed_maps() for i in range(len(versions) - 1)]
    rng = np.random.default_rng(0)
    small = compress(np.c_[rng.random((64, 2)) * 8, rng.random(64)], resolution=1.0, step=0.05)  # preview-sized
    for n, (base, target) in enumerate(pairs):
        sender = Sender(max_frame_bytes=FRAME, map_id=1000 + n, preview_over=0 if n % 2 else None)
        if base:
            sender.update(base)
            sender.receive(pack_ack(Ack(0, 1, 1, 1, hashlib.sha256(base).digest(), 0, 0)))
        sender.update(target, preview=lambda: small)
        out.append((base, target, sender.poll(0.0), sender.map_id))
    return out


def _receiver(base: bytes, map_id: int) -> Receiver:
    receiver = Receiver(max_frame_bytes=FRAME, map_id=map_id, log=lambda cause, message: None)
    receiver.data, receiver.sha256, receiver.version = base, hashlib.sha256(base).digest(), 1 if base else 0
    return receiver


def check(base: bytes, target: bytes, frames: list[bytes], map_id: int) -> str:
    """Feed one input; 'applied' or 'refused'; anything else raises."""
    receiver = _receiver(base, map_id)
    for frame in frames:
        receiver.receive(frame)
        if receiver.data not in (base, target):
            raise AssertionError("a mutated frame gave another map than the base or the target")
        receiver.poll(0.0)
    if receiver.preview is not None:
        try:
            decompress(receiver.preview[1])
        except DftpccError:
            pass
    return "applied" if receiver.data == target and target != base else "refused"


def run(iterations: int, *, seed: int = 0) -> dict:
    rnd = random.Random(seed)
    changes = seed_changes()
    outcomes: collections.Counter = collections.Counter()
    acks = [pack_ack(Ack(0, 7, 1, 1, hashlib.sha256(b).digest(), 1, 2, {0: (3, frozenset({0, 2})), 5: (9, frozenset())}))
            for b, _t, _f, _m in changes]
    sender = Sender(max_frame_bytes=FRAME, map_id=1)  # one sender takes every mutated acknowledgement, in turn
    sender.update(changes[0][1])
    t0 = time.perf_counter()
    for _ in range(iterations):
        base, target, frames, map_id = rnd.choice(changes)
        frames = list(frames)
        for _ in range(rnd.randint(1, 3)):
            k = rnd.randrange(len(frames))
            bad = mutate(frames[k], rnd)
            bad = recrc(bad) if rnd.random() < 0.5 else bad
            if rnd.random() < 0.5:
                frames[k] = bad  # the genuine one lost
            else:
                frames.insert(rnd.randrange(len(frames) + 1), bad)
        if rnd.random() < 0.5:
            rnd.shuffle(frames)
        outcomes[check(base, target, frames, map_id)] += 1
        ack = mutate(rnd.choice(acks), rnd)
        sender.receive(recrc(ack) if rnd.random() < 0.5 else ack)
        sender.poll(1.0)
    return {"iterations": iterations, "outcomes": dict(outcomes), "wall_seconds": round(time.perf_counter() - t0, 2)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=20_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    report = run(args.iterations, seed=args.seed)
    print(report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
