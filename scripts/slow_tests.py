"""Write tests/slow.txt from a pytest run's ``--durations=0`` report: the tests (by function, their
parametrized cases together) whose setup, call and teardown took over --slow-s seconds (0.7: the
rest then ran in under a minute on the shared 2-core box).

    python -m pytest -q --durations=0 > durations.txt
    python scripts/slow_tests.py durations.txt [--slow-s 0.7]
"""

from __future__ import annotations

import argparse
import re
import sys
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("durations", type=Path)
    parser.add_argument("--slow-s", type=float, default=0.7, help="a test function over this many seconds is slow")
    args = parser.parse_args()
    per_function: dict[str, float] = defaultdict(float)
    for line in args.durations.read_text().splitlines():
        found = re.match(r"\s*([\d.]+)s (setup|call|teardown)\s+(\S+)", line)
        if found:
            per_function[found[3].split("[")[0]] += float(found[1])
    if not per_function:
        print(f"{args.durations}: no durations (run pytest with --durations=0)", file=sys.stderr)
        return 1
    slow = sorted(name for name, seconds in per_function.items() if seconds > args.slow_s)
    (ROOT / "tests" / "slow.txt").write_text("\n".join(slow) + "\n")
    fast = sum(s for name, s in per_function.items() if name not in slow)
    print(f"{len(slow)} of {len(per_function)} test functions slow; the rest took {fast:.0f} s in that run")
    return 0


if __name__ == "__main__":
    sys.exit(main())
