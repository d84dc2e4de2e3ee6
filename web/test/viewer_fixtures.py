"""Maps and the Python decoder's answers for the viewer's browser tests (web/test/viewer.test.mjs).

``python web/test/viewer_fixtures.py OUTDIR`` writes, from ../shared/data: ``gale.dftpc`` (untiled),
``davos_tiled.dftpc`` (tiles of 128 cells), ``korolev.dftpc`` (degrees of
longitude and latitude, 22 % of the grid empty), ``damaged.dftpc`` (gale with bytes flipped in its
coefficients), ``notamap.dftpc`` (text), per map ``NAME.ref.f32`` (the Python decoder's heights,
metres, NaN where empty) and ``NAME.info.json`` (``dftpcc info --json``), and ``manifest.json``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

import dftpcc

DEMS = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "dems"
MAPS = {"gale": (DEMS / "mars_gale_1m.tif", []),
        "davos_tiled": (DEMS / "earth_davos_10m.tif", ["--tile-size", "128"]),
        "korolev": (DEMS / "mars_korolev_mola.tif", [])}


def main(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    manifest = {}
    for name, (src, cli) in MAPS.items():
        dst = out / f"{name}.dftpc"
        subprocess.run([sys.executable, "-m", "dftpcc", "compress", "-q", "--no-warnings", *cli, str(src), str(dst)],
                       check=True)
        info = subprocess.run([sys.executable, "-m", "dftpcc", "info", "--json", str(dst)], check=True,
                              capture_output=True, text=True).stdout
        (out / f"{name}.info.json").write_text(info)
        with dftpcc.open(dst) as cmap:
            dem = cmap.read_dem()
            bounds = cmap.bounds()
            z0 = cmap.grid.z0
        np.where(dem.mask, dem.heights + z0, np.nan).astype("<f4").tofile(out / f"{name}.ref.f32")
        manifest[name] = {"map": str(dst), "source": str(src.resolve()), "rows": int(dem.mask.shape[0]),
                          "cols": int(dem.mask.shape[1]), "bounds": list(bounds)}
    data = bytearray((out / "gale.dftpc").read_bytes())
    for k in range(len(data) // 2, len(data) // 2 + 16):
        data[k] ^= 0x5A
    (out / "damaged.dftpc").write_bytes(bytes(data))
    (out / "notamap.dftpc").write_text("this is not a map\n")
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
