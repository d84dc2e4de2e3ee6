"""Digests of what a growing map writes on real data: the maps, their states and the deltas.

A small growing map of ../shared/data/pointclouds/forest_hills_topography.laz (its points in
four strips along x, each a scan; 2 m cells, 64-cell tiles) is started with the first strip and
updated three times with ``--delta``, through the command line. Prints the size and SHA-256 of
every map, state and delta, so a change can show which bytes moved (scripts/digests.py guards the
one-shot compressor's files, not these).

    python scripts/growing_digests.py OUT_FOLDER
"""

from __future__ import annotations

import hashlib
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

import dftpcc

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "pointclouds" / "forest_hills_topography.laz"


def main() -> int:
    out = Path(sys.argv[1])
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    pts = dftpcc.read(DATA).points
    for k, part in enumerate(np.array_split(pts[np.argsort(pts[:, 0], kind="stable")], 4)):
        np.save(out / f"scan{k}.npy", part)
    cli = [sys.executable, "-m", "dftpcc", "update"]
    m = out / "m.dftpc"
    subprocess.run(cli + [str(m), str(out / "scan0.npy"), "-r", "2", "--tile-size", "64", "-q"], check=True)
    for k in (1, 2, 3):
        shutil.copy(m, out / f"m{k - 1}.dftpc")
        shutil.copy(f"{m}.state", out / f"m{k - 1}.dftpc.state")
        subprocess.run(cli + [str(m), str(out / f"scan{k}.npy"), "--delta", str(out / f"d{k}.dftpd"), "-q"],
                       check=True)
    for path in sorted(out.iterdir()):
        if path.suffix != ".npy":
            print(path.name, path.stat().st_size, hashlib.sha256(path.read_bytes()).hexdigest())
    return 0


if __name__ == "__main__":
    sys.exit(main())
