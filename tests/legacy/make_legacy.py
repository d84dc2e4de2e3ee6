"""Write the legacy fixtures: valid maps of format 1.0 and 1.1 (the coefficient order by ``hypot``),
and what reading each gives, so that every later reader is checked against them.

    git archive be9dcac src tests/fuzz | tar -x -C /tmp/legacy      # the last writer of 1.0 and 1.1
    PYTHONPATH=/tmp/legacy/src:/tmp/legacy python tests/legacy/make_legacy.py

Needs a dftpcc that writes 1.0 and 1.1 (before the integer order of 1.2): a current one would
write 1.2 files, which is what these fixtures are not. ``expected.json`` records, per file, its
minor version and the SHA-256 of the points that writer's reader decodes (float64, row-major x,
y, z): tests/test_legacy.py checks today's reader gives the same bits. Besides the fuzz seeds
(small maps of every coding), three maps hold coefficients whose ``hypot`` radii split a tie of
``i² + j²`` (2993 = 17² + 52² = 28² + 47²): where the legacy and integer orders differ; and
``growing.dftpc`` with its state ``growing.dftpc.state`` is a growing map (``dftpcc update``).
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import sys
import warnings
from pathlib import Path

import numpy as np

import dftpcc
from dftpcc.experiments.terrain import regolith_plain
from dftpcc.format import VERSION

HERE = Path(__file__).resolve().parent


def rough(points: np.ndarray) -> np.ndarray:
    """``points`` with 5 cm of white noise on their heights (seeded)."""
    out = points.copy()
    out[:, 2] += np.random.default_rng(3).normal(0, 0.05, len(out))
    return out


def _digest(data: bytes) -> dict:
    points = np.ascontiguousarray(dftpcc.decompress(data), dtype="<f8")
    return {"minor": data[9], "points": int(points.shape[0]),
            "sha256": hashlib.sha256(points.tobytes()).hexdigest()}


def main() -> int:
    if VERSION != (1, 0):
        print(f"this dftpcc writes format {VERSION}: run with a writer of 1.0 and 1.1 (see the docstring)",
              file=sys.stderr)
        return 2
    from tests.fuzz.seeds import seed_files

    files = dict(seed_files())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # Rough (white noise on the terrain) and a fine step: the high frequencies of the tie are not 0.
        square = rough(regolith_plain(12000, size=60.0, craters=3, rocks=10, seed=5))
        files["tie_dct"] = dftpcc.compress(square, resolution=1.0, cutoff=0.3, step=0.002)
        files["tie_dft"] = dftpcc.compress(square, resolution=0.5, cutoff=0.3, transform="dft", step=0.002)
        files["tie_tiled"] = dftpcc.compress(rough(regolith_plain(20000, size=120.0, craters=4, rocks=20, seed=6)),
                                             resolution=1.0, cutoff=0.3, tile_size=64, step=0.002)
    # A growing map (dftpcc update) and its state, after the first scan of tests/test_mapbuilder's drive.
    spec = importlib.util.spec_from_file_location("test_mapbuilder", HERE.parent / "test_mapbuilder.py")
    mapbuilder_tests = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mapbuilder_tests)
    drive, new_builder = mapbuilder_tests.drive, mapbuilder_tests.new_builder

    builder = new_builder()
    for points, pose in drive(6, heading=3.5, speed=2.5)[:1]:
        builder.add(points, pose)
    files["growing"] = builder.save(HERE / "growing.dftpc")
    expected = {}
    for name, data in sorted(files.items()):
        (HERE / f"{name}.dftpc").write_bytes(data)
        expected[f"{name}.dftpc"] = _digest(data)
        print(f"{name}.dftpc: {len(data)} bytes, version 1.{data[9]}")
    (HERE / "expected.json").write_text(json.dumps(expected, indent=1, sort_keys=True) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
