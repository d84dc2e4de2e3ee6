"""The Python decoder's time on the files web/bench/bench.mjs wrote: ``python py_decode.py DIR REPEATS``.

Prints JSON ``{name: {"cells": rows*cols, "seconds": median CPU seconds (time.process_time) of
dftpcc.open(bytes).read_dem()}}``: CPU time, so that other work on a shared machine does not count.
"""

from __future__ import annotations

import json
import statistics
import sys
import time
from pathlib import Path

import dftpcc


def main() -> None:
    folder, repeats = Path(sys.argv[1]), int(sys.argv[2])
    out = {}
    for path in sorted(folder.glob("*.dftpc")):
        data = path.read_bytes()
        with dftpcc.open(data) as cmap:
            dem = cmap.read_dem()  # warm: imports, caches of the coefficient order
        times = []
        for _ in range(repeats):
            t0 = time.process_time()
            with dftpcc.open(data) as cmap:
                cmap.read_dem()
            times.append(time.process_time() - t0)
        out[path.stem] = {"cells": int(dem.heights.size), "seconds": statistics.median(times)}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
