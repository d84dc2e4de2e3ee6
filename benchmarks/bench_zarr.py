"""Issue 12: dftpcc as a Zarr chunk codec against zarr's default compressor, LERC and SZ3.

Every DEM of ``dems/`` is written to a Zarr store on disk in 256 x 256 chunks
(zarr pads the edge chunks to full size with the fill value) and read back,
once per codec and maximum error E (fractions of the DEM's relief):

- dftpcc: :class:`dftpcc.zarr_codec.DftpccCodec` (format 3, ``max_error=E``),
  fill value NaN for floats and the file's nodata value for integers, so the
  padding and the nodata cells are no data;
- zarr's default: format 3 with zarr's own default codecs (bytes + zstd,
  lossless), the same fill value;
- LERC and SZ3: imagecodecs' numcodecs codecs (``Lerc(level=E)``,
  ``Sz3(mode='abs', abs=E)``) as the compressor of a format 2 array. Neither
  takes a mask through numcodecs, so their fill value is the DEM's median
  height (the padding is a flat plateau, not NaN, which SZ3 codes
  losslessly); SZ3 takes floats only, so integer DEMs are stored as float32
  (exact) and decoded without rounding.

Bytes are the chunk files (metadata left out); the largest error is measured
on the valid cells against the DEM itself and printed PASS/FAIL against E;
the nodata cells must come back as no data. Times are medians of whole-array
writes and reads (zarr runs codecs in threads; dftpcc codes one chunk at a
time per process, see dftpcc.chunkcodec). Nothing here fails.

    .venv/bin/python -m benchmarks.bench_zarr [--quick] [--files mars moon ...]
"""

from __future__ import annotations

import math
import shutil
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from benchmarks.common import finish_run, load_average, markdown_table, median_time, run_arguments

CHUNK = 256
#: Bounds E as fractions of each DEM's relief (max - min height).
RELIEF_FRACTIONS = (0.001, 0.003, 0.01)
QUICK_FRACTIONS = (0.003,)
QUICK_FILES = ("mars_gale_1m.tif", "moon_kepler_lola_48m.tif")
TIMING_REPEATS = 3
#: A codec passes when its largest error is at most E plus this (metres): float64
#: round-off of the check at heights of a few km, far below any float32 spacing.
CHECK_SLACK = 1e-9
#: Chunk files' names: format 3 keeps them under c/, format 2 names them "i.j".
METADATA = {"zarr.json", ".zarray", ".zattrs", ".zgroup", ".zmetadata"}


@dataclass
class Dem:
    name: str
    values: np.ndarray  # as the GeoTIFF stores them
    valid: np.ndarray
    nodata: float | int | None  # what fills the invalid cells in ``values``

    @property
    def relief(self) -> float:
        v = self.values[self.valid].astype(np.float64)
        return float(v.max() - v.min())

    @property
    def median(self) -> float:
        return float(np.median(self.values[self.valid]))


def read_dem(path: Path) -> Dem:
    import rasterio

    with rasterio.open(path) as src:
        values, nodata = src.read(1), src.nodata
    valid = np.ones(values.shape, bool) if nodata is None else values != nodata
    if values.dtype.kind == "f":
        valid &= np.isfinite(values)
        values = np.where(valid, values, np.nan).astype(values.dtype)
        nodata = math.nan
    elif nodata is not None:
        nodata = int(nodata)
    return Dem(path.name, values, valid, nodata)


@dataclass
class Store:
    """One codec's recipe for a Zarr array of a DEM at bound E."""

    label: str
    create: Callable[[Path, Dem, float], Any]  # returns the zarr array to fill
    lossless: bool = False


def _dftpcc(path: Path, dem: Dem, bound: float) -> Any:
    import zarr

    from dftpcc.zarr_codec import DftpccCodec

    return zarr.create_array(path, shape=dem.values.shape, chunks=(CHUNK, CHUNK), dtype=dem.values.dtype,
                             fill_value=dem.nodata if dem.nodata is not None else 0,
                             serializer=DftpccCodec(max_error=bound), compressors=None)


def _zarr_default(path: Path, dem: Dem, _: float) -> Any:
    import zarr

    return zarr.create_array(path, shape=dem.values.shape, chunks=(CHUNK, CHUNK), dtype=dem.values.dtype,
                             fill_value=dem.nodata if dem.nodata is not None else 0)


def _numcodecs_array(path: Path, dem: Dem, codec: Any, dtype: Any) -> Any:
    import zarr

    return zarr.create_array(path, shape=dem.values.shape, chunks=(CHUNK, CHUNK), dtype=dtype, zarr_format=2,
                             fill_value=np.asarray(dem.median).astype(dtype).item(), compressors=codec, filters=None)


def _lerc(path: Path, dem: Dem, bound: float) -> Any:
    from imagecodecs.numcodecs import Lerc

    return _numcodecs_array(path, dem, Lerc(level=bound), dem.values.dtype)


def _sz3_dtype(dem: Dem) -> np.dtype:
    return dem.values.dtype if dem.values.dtype.kind == "f" else np.dtype(np.float32)


def _sz3(path: Path, dem: Dem, bound: float) -> Any:
    from imagecodecs.numcodecs import Sz3

    dtype = _sz3_dtype(dem)
    return _numcodecs_array(path, dem, Sz3(shape=(CHUNK, CHUNK), dtype=dtype, mode="abs", abs=bound), dtype)


STORES = (Store("dftpcc", _dftpcc), Store("zarr default (zstd)", _zarr_default, lossless=True),
          Store("LERC", _lerc), Store("SZ3", _sz3))


def register() -> None:
    """imagecodecs' numcodecs codecs findable by id when the arrays are reopened (dftpcc's register
    themselves on import, as do zarr's own)."""
    import numcodecs
    from imagecodecs.numcodecs import Lerc, Sz3

    import dftpcc.zarr_codec  # noqa: F401

    for cls in (Lerc, Sz3):
        numcodecs.register_codec(cls)


@dataclass
class Result:
    bytes: int
    max_error: float
    nodata_kept: bool
    write_s: float
    read_s: float


def chunk_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file() and f.name not in METADATA)


def measure(store: Store, dem: Dem, bound: float, work: Path, repeats: int) -> Result:
    import zarr

    path = work / "array.zarr"
    values = dem.values if store.label != "SZ3" else dem.values.astype(_sz3_dtype(dem))

    def write() -> None:
        shutil.rmtree(path, ignore_errors=True)
        store.create(path, dem, bound)[:] = values

    write_s, _ = median_time(write, repeats)
    read_s, back = median_time(lambda: zarr.open_array(path, mode="r")[:], repeats)
    err = np.abs(back.astype(np.float64) - dem.values.astype(np.float64))[dem.valid]
    invalid = ~dem.valid
    if not invalid.any():
        kept = True
    elif dem.values.dtype.kind == "f":
        kept = bool(np.isnan(back[invalid]).all())
    else:
        kept = bool((back[invalid] == dem.nodata).all())
    return Result(chunk_bytes(path), float(err.max()), kept, write_s, read_s)


def _bound_text(bound: float) -> str:
    return f"{bound * 100:.3g} cm" if bound < 0.5 else f"{bound:.3g} m"


def _verdict(r: Result, bound: float, lossless: bool) -> str:
    ok = r.max_error == 0 if lossless else r.max_error <= bound + CHECK_SLACK
    return ("PASS" if ok else "FAIL") + ("" if r.nodata_kept else ", nodata lost")


def report(rows: list[tuple[Dem, float, float, dict[str, Result]]]) -> tuple[str, str]:
    size_rows, time_rows = [], []
    for dem, fraction, bound, results in rows:
        d = results["dftpcc"]
        cells = [dem.name, str(dem.values.dtype), f"{100 * fraction:g} % = {_bound_text(bound)}", f"{d.bytes:,}"]
        for store in STORES[1:]:
            r = results[store.label]
            cells.append(f"{r.bytes:,} ({r.bytes / d.bytes:.2f}x)")
        cells.append(" / ".join(f"{results[s.label].max_error:.5g}" for s in STORES))
        cells.append(" / ".join(_verdict(results[s.label], bound, s.lossless) for s in STORES))
        size_rows.append(cells)
        raw_mb = dem.values.nbytes / 1e6
        time_rows.append([dem.name, _bound_text(bound)] + [
            f"{results[s.label].write_s:.2f} / {results[s.label].read_s:.3f} "
            f"({raw_mb / results[s.label].write_s:.1f} / {raw_mb / results[s.label].read_s:.0f} MB/s)"
            for s in STORES])
    sizes = markdown_table(
        ["DEM", "dtype", "E (of relief)", "dftpcc B", "zarr default B (x dftpcc)", "LERC B (x dftpcc)",
         "SZ3 B (x dftpcc)", "max error m: dftpcc / zstd / LERC / SZ3", "bound"], size_rows)
    times = markdown_table(["DEM", "E"] + [f"{s.label} write / read s (raw MB/s)" for s in STORES], time_rows)
    return sizes, times


def summary(rows: list[tuple[Dem, float, float, dict[str, Result]]]) -> str:
    """Each anchor's bytes over dftpcc's, as a range and median over every DEM and bound,
    and the bounds any codec missed, by how much."""
    lines = []
    for store in STORES[1:]:
        ratios = sorted(r[store.label].bytes / r["dftpcc"].bytes for *_, r in rows)
        lines.append(f"{store.label} {ratios[0]:.2f}-{ratios[-1]:.2f}x (median {float(np.median(ratios)):.2f}x)")
    text = f"Bytes of each codec over dftpcc's, {len(rows)} DEM x bound cases: " + "; ".join(lines) + "."
    misses = [f"{s.label} on {dem.name} ({dem.values.dtype}) at E = {bound:.6g} m: {r.max_error:.6g} m, "
              f"{(r.max_error - bound) * 1e3:.3g} mm over"
              for dem, _, bound, results in rows for s in STORES
              if not s.lossless and (r := results[s.label]).max_error > bound + CHECK_SLACK]
    if misses:
        text += (" Bounds missed: " + "; ".join(misses) + ". (A float32 array holds its heights to a "
                 "spacing of 0.49 mm at 4 km: a codec whose bound ignores the rounding to float32 can exceed "
                 "it by up to half of that; dftpcc codes to a bound tightened by that half step.)")
    return text


def main(argv: list[str] | None = None) -> int:
    ap = run_arguments(__doc__.splitlines()[0], f"one bound (0.3 % of relief) on {', '.join(QUICK_FILES)}, one repeat")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    register()
    names = sorted(p.name for p in (args.data / "dems").glob("*.tif"))
    if args.files:
        names = [n for n in names if any(n.startswith(w) for w in args.files)]
    elif args.quick:
        names = [n for n in names if n in QUICK_FILES]
    fractions = QUICK_FRACTIONS if args.quick else RELIEF_FRACTIONS
    repeats = 1 if args.quick else TIMING_REPEATS
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_zarr_") as tmp, warnings.catch_warnings():
        # zarr warns that imagecodecs' numcodecs are not in the Zarr spec: known, and said above.
        warnings.simplefilter("ignore", UserWarning)
        for name in names:
            dem = read_dem(args.data / "dems" / name)
            for fraction in fractions:
                bound = fraction * dem.relief
                results = {s.label: measure(s, dem, bound, Path(tmp), repeats) for s in STORES}
                rows.append((dem, fraction, bound, results))
                d = results["dftpcc"]
                print(f"{name} E={_bound_text(bound)}: " + ", ".join(
                    f"{k} {r.bytes:,} B err {r.max_error:.4g}" for k, r in results.items()) +
                    f" (dftpcc write {d.write_s:.1f} s)", flush=True)
    sizes, times = report(rows)
    print("\n" + sizes + "\n\n" + summary(rows) + "\n\n" + times)
    parts = [
        f"Each DEM of `dems/` in a Zarr store on disk, {CHUNK} x {CHUNK} chunks (edge chunks padded by zarr), at "
        f"maximum errors E of {', '.join(f'{100 * f:g} %' for f in fractions)} of its relief. dftpcc: "
        "`DftpccCodec(max_error=E)` (format 3); fill value NaN (floats) or the file's nodata value (integers), "
        "so padding and nodata are no data. zarr default: format 3 with zarr's default codecs (bytes + zstd, "
        "lossless). LERC, SZ3: imagecodecs' numcodecs codecs `Lerc(level=E)`, `Sz3(mode='abs', abs=E)` as a "
        "format 2 compressor, fill value the median height (no mask through numcodecs: padding is a plateau, "
        "and Korolev's nodata cells, value 0, are coded as heights); SZ3 takes floats only, so int16 DEMs "
        "are stored as float32 and not rounded on reading. Bytes: the chunk files (metadata left out). Max "
        "error: on the valid cells, measured against the DEM; `bound` says PASS when it is within E (0 for "
        "zstd), and whether nodata came back.",
        sizes,
        summary(rows),
        f"Write and read: medians of {repeats} whole-array writes and reads (seconds, and raw MB/s). zarr "
        "runs codecs in threads on the 2 cores; dftpcc codes one chunk at a time per process (the encoder "
        "shares zstd compressors between calls), so its times are serial.",
        times,
    ]
    finish_run(parts, args, "bench_zarr", "Zarr chunk codec: bytes at equal maximum error",
               f"Run time {time.perf_counter() - t0:.0f} s; {load_average()} at the end.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
