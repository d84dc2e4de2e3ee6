"""Digests of the files the codec writes on ../shared/data: what a refactor must not change.

Each real file is compressed through the public API with the default
options, the paper profile, each rate-control target, the footprint
mask and tiled, and a growing map is grown in three parts (each version,
its delta and its state file); the SHA-256 of every ``.dftpc`` (or the error class and message,
when a case is refused) is written to ``tests/digests.json`` with
``--write`` and compared with it otherwise. tests/test_digests.py runs
the same comparison on the smaller files.

    python scripts/digests.py            # compare (exit 1 on any change)
    python scripts/digests.py --write    # record after a deliberate change
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
import warnings
from pathlib import Path

import dftpcc

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
RECORD = ROOT / "tests" / "digests.json"

#: Real files (path under ../shared/data) and whether they are large (over 2 M points).
FILES = {
    "pointclouds/field_gentle_ign.laz": False,
    "pointclouds/mountain_arid_alirt.las": False,
    "pointclouds/redrocks_rough.ply": False,
    "pointclouds/coastal_plain_ign.laz": False,
    "pointclouds/rural_valley_ign.laz": False,
    "pointclouds/urban_autzen.laz": False,
    "pointclouds/forest_hills_topography.laz": False,
    "pointclouds/forest_slope_bcts_2.8M.laz": True,
    "pointclouds/rolling_strip_raleigh_2.3M.laz": True,
    "dems/mars_gale_1m.tif": False,
    "dems/moon_kepler_lola_48m.tif": False,
    "dems/mars_korolev_mola.tif": False,
    "dems/earth_bigtujunga_srtm30.tif": False,
    "dems/earth_davos_10m.tif": False,
    "dems/earth_heidelberg_25m.tif": False,
}

#: Option sets (keyword arguments of dftpcc.compress_file).
CASES = {
    "default": {},
    "paper": {"profile": "paper"},
    "target_rmse": {"target_rmse": 0.05},
    "target_max_error": {"target_max_error": 0.1},
    "target_bpp": {"target_bpp": 1.0},
    "footprint": {"mask": "footprint"},
    # Tiled (docs/format.md, *Tiles*): a map of one tile is written whole, so small maps give
    # their untiled digest; a fixed high cutoff widens the tiles' overlap.
    "tiled_128_rmse": {"tile_size": 128, "target_rmse": 0.05},
    "tiled_256_max_error": {"tile_size": 256, "target_max_error": 0.1},
    "tiled_128_cutoff_0.95": {"tile_size": 128, "cutoff": 0.95},
}


def digest(name: str, options: dict) -> str:
    """SHA-256 of the file ``compress_file`` writes, or ``error: Class: message``."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out.dftpc"
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                dftpcc.compress_file(DATA / name, out, **options)
        except dftpcc.DftpccError as exc:
            return f"error: {type(exc).__name__}: {exc}"
        return hashlib.sha256(out.read_bytes()).hexdigest()


#: A growing map (``MapBuilder``): the field's ground points added in this many parts, west to east;
#: after each, the map, the delta from the one before and the state file are recorded.
GROWING_FILE, GROWING_PARTS = "pointclouds/field_gentle_ign.laz", 3


def growing() -> dict[str, str]:
    """SHA-256 of each version of a growing map, of its delta and of its state file."""
    import numpy as np

    from dftpcc.delta import make_delta
    from dftpcc.mapbuilder import MapBuilder, state_path

    def sha(data: bytes) -> str:
        return hashlib.sha256(data).hexdigest()

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        points = dftpcc.read(DATA / GROWING_FILE, classes=[2]).points
    out, previous = {}, b""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "grown.dftpc"
        builder = MapBuilder(0.5, tile_size=128, step=0.01)
        for i, part in enumerate(np.array_split(points[np.argsort(points[:, 0], kind="stable")], GROWING_PARTS)):
            data = builder.add(part).encode()
            builder.save(path, data=data)
            out[f"{GROWING_FILE}|growing|{i}|map"] = sha(data)
            if previous:
                out[f"{GROWING_FILE}|growing|{i}|delta"] = sha(make_delta(previous, data))
            out[f"{GROWING_FILE}|growing|{i}|state"] = sha(state_path(path).read_bytes())
            previous = data
    return out


def measure(include_large: bool = True) -> dict[str, str]:
    found = {f"{name}|{case}": digest(name, options)
             for name, large in FILES.items() if include_large or not large
             for case, options in CASES.items()}
    return found | growing()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true", help="record the digests instead of comparing")
    parser.add_argument("--small", action="store_true", help="leave out the two files over 2 M points")
    args = parser.parse_args()
    found = measure(include_large=not args.small)
    if args.write:
        RECORD.write_text(json.dumps(found, indent=1, sort_keys=True) + "\n")
        print(f"{len(found)} digests -> {RECORD}")
        return 0
    recorded = json.loads(RECORD.read_text())
    changed = [key for key, value in found.items() if recorded.get(key) != value]
    for key in changed:
        print(f"changed: {key}: {recorded.get(key)} -> {found[key]}")
    print(f"{len(found) - len(changed)} of {len(found)} files unchanged")
    return 1 if changed else 0


if __name__ == "__main__":
    sys.exit(main())
