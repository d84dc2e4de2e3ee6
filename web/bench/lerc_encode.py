"""LERC blobs of the DEMs web/bench/bench.mjs compressed, at each file's stated maximum error:
``python lerc_encode.py DIR``.

For every ``NAME.dftpc`` in DIR whose source ``NAME.src`` (a text file holding the path of the
GeoTIFF it was made from) is there, writes ``NAME.lerc``: the DEM the compress command read (the
same grid and mask), LERC-encoded with ``maxZErr`` = the file's ``dem_max_error_m`` (LERC's bound
is on every valid cell, as dftpcc's is), so both decoders are timed at equal maximum error. Prints
JSON ``{name: {"lerc_bytes", "max_error_m"}}``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import lerc
import numpy as np

import dftpcc
from dftpcc import files


def main() -> None:
    folder = Path(sys.argv[1])
    out = {}
    for path in sorted(folder.glob("*.dftpc")):
        src = path.with_suffix(".src")
        if not src.is_file():
            continue
        with dftpcc.open(path) as cmap:
            params = cmap.params
            bound = float(cmap.info()["stats"]["dem_max_error_m"])
        dem, _count, _crs = files.read_dem(Path(src.read_text().strip()), params.replace(resolution="auto"))
        heights = np.where(dem.mask, dem.heights + dem.grid.z0, 0.0).astype(np.float64)
        valid = dem.mask.astype(np.uint8)
        result, _n, blob = lerc.encode(heights, 1, True, valid, bound, 1)
        if result != 0:
            raise SystemExit(f"{path.name}: lerc.encode failed ({result})")
        path.with_suffix(".lerc").write_bytes(bytes(blob))
        out[path.stem] = {"lerc_bytes": len(blob), "max_error_m": bound}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
