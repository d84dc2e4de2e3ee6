"""Structure-blind mutations the fuzzers share: flip, set, cut, insert or duplicate bytes."""

from __future__ import annotations

import random


def blind(data: bytes, rnd: random.Random, *, longest_cut: int = 64) -> bytes:
    """One structure-blind mutation of ``data``: one to four byte flips, interesting values, cuts
    (of up to ``longest_cut`` bytes), random inserts or duplicated runs."""
    buf = bytearray(data)
    for _ in range(rnd.randint(1, 4)):
        choice = rnd.random()
        pos = rnd.randrange(len(buf)) if buf else 0
        if choice < 0.35 and buf:
            buf[pos] ^= 1 << rnd.randrange(8)
        elif choice < 0.55 and buf:
            buf[pos] = rnd.choice((0, 1, 0x7F, 0x80, 0xFF, rnd.randrange(256)))
        elif choice < 0.7:
            del buf[pos:pos + rnd.randint(1, longest_cut)]
        elif choice < 0.85:
            buf[pos:pos] = bytes(rnd.randrange(256) for _ in range(rnd.randint(1, 16)))
        else:
            start = rnd.randrange(len(buf)) if buf else 0
            buf[pos:pos] = buf[start:start + rnd.randint(1, 64)]
    return bytes(buf)
