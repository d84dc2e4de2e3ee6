"""Fixture files and the Python decoder's answers for the JavaScript decoder's tests.

Run by web/test/*.test.mjs (``PYTHON`` env var, default ``.venv/bin/python``) into a temporary
folder: ``python web/test/fixtures.py OUTDIR [--quick]``. Writes, per case, ``NAME.dftpc`` (the
file the codec writes from ../shared/data), ``NAME.mask.u8`` (the Python decoder's mask, rows x
cols bytes), ``NAME.ref.f64`` (its heights, metres, z0 included, NaN where the mask is 0) and
``NAME.orig.f64`` (the gridded DEM the file was made from, NaN where it has no cell), plus
``manifest.json`` describing every case, the refusals of crafted deltas, and reference values of
the format's float steps (radius order, table decays, inverse DCT).
Nothing here is committed: every run writes it afresh.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np

import dftpcc
from dftpcc import delta as dftpcc_delta
from dftpcc import files, spectrum
from dftpcc.errors import DftpccError

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
DEMS = DATA / "dems"
CLOUDS = DATA / "pointclouds"
LEGACY = Path(__file__).resolve().parents[2] / "tests" / "legacy"


def _save(out: Path, name: str, dem, z0: float, suffix: str) -> None:
    h = np.where(dem.mask, dem.heights + z0, np.nan).astype("<f8")
    h.tofile(out / f"{name}.{suffix}.f64")
    if suffix == "ref":
        dem.mask.astype(np.uint8).tofile(out / f"{name}.mask.u8")


def _case(out: Path, name: str, src: Path, cli: list[str], manifest: list, *, prefixes=(), window=None,
          cutoff=None) -> None:
    dst = out / f"{name}.dftpc"
    subprocess.run([sys.executable, "-m", "dftpcc", "compress", "-q", "--no-warnings", *cli, str(src), str(dst)],
                   check=True)
    data = dst.read_bytes()
    with dftpcc.open(data) as cmap:
        dem = cmap.read_dem()
        info = cmap.info()
        z0 = cmap.grid.z0
        tiled = cmap.tiled
    _save(out, name, dem, z0, "ref")
    # The DEM the file was made from (the compress command's own reading of the input).
    with dftpcc.open(data) as cmap:
        params = cmap.params
    original, _count, _crs = files.read_dem(src, params.replace(resolution="auto") if src.suffix == ".tif" else params)
    same = original.heights.shape == dem.heights.shape
    if same:
        _save(out, name, original, original.grid.z0, "orig")
    entry = {"name": name, "rows": int(dem.heights.shape[0]), "cols": int(dem.heights.shape[1]), "tiled": bool(tiled),
             "z0": float(z0), "bytes": len(data), "orig": bool(same),
             "dem_max_error_m": _find(info, "dem_max_error_m"), "cli": cli}
    for n in prefixes:
        n = int(n * len(data))
        try:
            with dftpcc.open(data, max_bytes=n) as cmap:
                part = cmap.read_dem()
        except DftpccError as exc:
            entry.setdefault("prefix_refused", []).append([n, type(exc).__name__])
            continue
        _save(out, f"{name}.prefix{n}", part, z0, "ref")
        entry.setdefault("prefixes", []).append(n)
    if window is not None:
        with dftpcc.open(dst) as cmap:
            part = cmap.read_window(*window)
        _save(out, f"{name}.window", part, z0, "ref")
        entry["window"] = [list(window[0]), list(window[1])]
    if cutoff is not None:
        with dftpcc.open(data) as cmap:
            part = cmap.read_dem(cutoff=cutoff)
        _save(out, f"{name}.cutoff", part, z0, "ref")
        entry["cutoff"] = cutoff
    manifest.append(entry)
    print(f"{name}: {len(data)} bytes", file=sys.stderr)


def _legacy(out: Path, manifest: dict) -> None:
    """The committed files of versions 1.0 and 1.1 (tests/legacy): the Python decoder's answers."""
    cases = []
    for src in sorted(LEGACY.glob("*.dftpc")):
        name = f"legacy_{src.stem}"
        data = src.read_bytes()
        (out / f"{name}.dftpc").write_bytes(data)
        with dftpcc.open(data) as cmap:
            dem = cmap.read_dem()
            _save(out, name, dem, cmap.grid.z0, "ref")
            cases.append({"name": name, "minor": data[9], "rows": int(dem.heights.shape[0]),
                          "cols": int(dem.heights.shape[1]), "tiled": bool(cmap.tiled)})
    manifest["legacy"] = cases


def _find(info, key):
    if isinstance(info, dict):
        if key in info:
            return info[key]
        for v in info.values():
            got = _find(v, key)
            if got is not None:
                return got
    return None


def _deltas(out: Path, manifest: dict) -> None:
    """A growing map updated by a second half of a cloud, its delta, and crafted deltas' refusals."""
    from dftpcc.io import read
    cloud = read(CLOUDS / "mountain_arid_alirt.las")
    xyz = np.asarray(cloud.points)
    cut = np.median(xyz[:, 0])
    np.save(out / "half1.npy", xyz[xyz[:, 0] < cut])
    np.save(out / "half2.npy", xyz[xyz[:, 0] >= cut])
    run = [sys.executable, "-m", "dftpcc", "update", "-q", "--no-warnings"]
    subprocess.run([*run, str(out / "grow1.dftpc"), str(out / "half1.npy"), "-r", "2", "--tile-size", "32"], check=True)
    subprocess.run([*run, str(out / "grow1.dftpc"), str(out / "half2.npy"), "-o", str(out / "grow2.dftpc"),
                    "--delta", str(out / "grow.dftpcd")], check=True)
    base = (out / "grow1.dftpc").read_bytes()
    result = (out / "grow2.dftpc").read_bytes()
    delta = (out / "grow.dftpcd").read_bytes()
    assert dftpcc_delta.apply_delta(base, delta) == result
    with dftpcc.open(result) as cmap:
        dem = cmap.read_dem()
        _save(out, "grow2", dem, cmap.grid.z0, "ref")
        rows, cols = dem.heights.shape
    # A delta between two unrelated files (format.md: any two files have a delta).
    other = (out / "gale_default.dftpc").read_bytes()
    (out / "cross.dftpcd").write_bytes(dftpcc_delta.make_delta(base, other))
    crafted = {
        "wrong_base": (other, delta),
        "applied_twice": (result, delta),
        "cut": (base, delta[:-7]),
        "flipped": (base, delta[:40] + bytes([delta[40] ^ 1]) + delta[41:]),
        "newer": (base, delta[:9] + b"\x01" + delta[10:]),
    }
    refusals = {}
    for key, (b, d) in crafted.items():
        (out / f"delta_{key}.base").write_bytes(b)
        (out / f"delta_{key}.dftpcd").write_bytes(d)
        try:
            dftpcc_delta.apply_delta(b, d)
            refusals[key] = None
        except DftpccError as exc:
            refusals[key] = type(exc).__name__
    manifest["delta"] = {"rows": int(rows), "cols": int(cols), "refusals": refusals}


def _orders(manifest: dict) -> None:
    """The writer's coefficient order for a few shapes: version 1.2's integer order, and the legacy one
    (ties decided by hypot's last bits) of 1.0 and 1.1 files."""
    cases = []
    for rows, cols, transform, storage, cutoff in [(741, 702, "dct", "quantized", 0.5), (337, 348, "dct", "quantized", 0.0),
                                                   (300, 301, "dft", "quantized", 0.3), (128, 96, "dft", "complex64", 0.2),
                                                   (1024, 1024, "dct", "quantized", 0.6), (10, 10, "dct", "quantized", 0.8)]:
        for legacy in (False, True):
            lay = spectrum.layout(transform, storage, (rows, cols), legacy=legacy)
            order, radius, angle = spectrum.kept_order(lay, cutoff)
            cases.append({"rows": rows, "cols": cols, "transform": transform, "storage": storage, "cutoff": cutoff,
                          "legacy": legacy, "order": [int(x) for x in order], "angle": [float(x) for x in angle],
                          "radius": [float(x) for x in radius]})
    manifest["orders"] = cases
    import decimal
    decays = []
    for code in range(256):
        with decimal.localcontext() as ctx:
            ctx.prec = 50
            b = max(decimal.Decimal(2) ** (decimal.Decimal(code - 128) / 8), decimal.Decimal("0.05"))
            decays.append(int(((1 + b * b).sqrt() - 1) / b * 65536))
    manifest["decays"] = decays
    from scipy import fft
    rng = np.random.default_rng(5)
    c = rng.normal(size=(37, 53))
    c[:, 20:] = 0
    c[15:, :] = 0
    manifest["idct"] = {"coefs": c.ravel().tolist(), "rows": 37, "cols": 53,
                        "heights": fft.idctn(c, type=2, norm="ortho").ravel().tolist()}


def main() -> None:
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    cases: list = []
    gale, davos, korolev = DEMS / "mars_gale_1m.tif", DEMS / "earth_davos_10m.tif", DEMS / "mars_korolev_mola.tif"
    tujunga = DEMS / "earth_bigtujunga_srtm30.tif"
    _case(out, "gale_default", gale, [], cases, prefixes=(0.15, 0.3, 0.5, 0.8, 0.99), cutoff=0.9)
    _case(out, "gale_rmse", gale, ["--target-rmse", "0.05"], cases)
    _case(out, "gale_maxerr", gale, ["--target-max-error", "0.1"], cases, prefixes=(0.5, 0.9))
    _case(out, "gale_maxerr_coarse", gale, ["--target-max-error", "1.5"], cases)
    _case(out, "gale_bpp", gale, ["--target-bpp", "0.5"], cases)
    _case(out, "gale_reloc", gale, ["--target-reloc", "1.0", "--reloc-scans", "3"], cases)
    _case(out, "gale_paper", gale, ["--profile", "paper"], cases, prefixes=(0.5,))
    _case(out, "gale_dft", gale, ["--transform", "dft"], cases, prefixes=(0.5,))
    _case(out, "gale_zstd", gale, ["--coder", "zstd", "--cutoff", "0.6"], cases)
    _case(out, "korolev", korolev, [], cases, prefixes=(0.4,))
    _case(out, "tujunga_maxerr", tujunga, ["--target-max-error", "3"], cases)
    _case(out, "davos_tiled", davos, ["--tile-size", "128"], cases, window=((100, 300), (200, 420)))
    _case(out, "davos_tiled_maxerr", davos, ["--tile-size", "128", "--target-max-error", "0.5"], cases)
    _case(out, "davos_tiled_rmse", davos, ["--tile-size", "64", "--target-rmse", "0.5"], cases)
    _case(out, "alirt_exact", CLOUDS / "mountain_arid_alirt.las", ["-r", "2"], cases)
    _case(out, "field_footprint", CLOUDS / "field_gentle_ign.laz", ["-r", "1", "--mask", "footprint"], cases)
    _case(out, "field_oriented", CLOUDS / "field_gentle_ign.laz", ["-r", "2", "--frame", "oriented", "--tile-size", "64"], cases)
    manifest: dict = {"cases": cases}
    _deltas(out, manifest)
    _orders(manifest)
    _legacy(out, manifest)
    (out / "manifest.json").write_text(json.dumps(manifest))


if __name__ == "__main__":
    main()
