"""Issue 3: dftpcc's rate-distortion against point-cloud and raster anchors, in one run.

For each file, every codec is swept over its quality setting; each setting
gives (bits per original point, vertical RMSE of every original point against
the decoded point nearest to it in x, y). The lower convex hull of those
samples (log-log) is each codec's frontier, and the bits it needs at fixed
error levels are read off it by log-log interpolation, as in ANCHORS.md;
the BD-rate of dftpcc compact against each codec averages the gap between
the frontiers. The DEMs are then coded at equal maximum error as well
(benchmarks/max_error.py). Targets are printed as PASS/MISS, bounds as
PASS/FAIL; nothing here fails.

    .venv/bin/python -m benchmarks.bench_anchors [--quick] [--files field mars ...] [--max-error-only]
"""

from __future__ import annotations

import argparse
import io
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
from scipy.spatial import cKDTree

import dftpcc
from dftpcc.grid import rasterize

from benchmarks.common import (
    FIGURES, GROUND, MIN_ERROR, BDRate, Case, Loaded, NearestHeights, bd_rate, bits_at, fmt_bits, load,
    load_average, lower_hull,
    finish_run, library_label, markdown_table, median_time, pick_cases, run_arguments, verdict, warnings_as_notes,
)
from benchmarks import max_error
from benchmarks.rasters import (JPEGXL_EFFORT, ONE_THREAD, RASTER_HEADER_BYTES, U16_MAX, Raster, make_raster,
                               raster_points, to_u16, unit_range, unpack_mask)

CASES = (
    Case("field_gentle_ign.laz", 0.5, (GROUND,), "gentle"),
    Case("coastal_plain_ign.laz", 2.0, (GROUND,), "gentle"),
    Case("mountain_arid_alirt.las", 2.0, None, "rough"),
    Case("redrocks_rough.ply", 5.0, None, "rough"),
    Case("mars_gale_1m.tif", None, None, "gentle"),
    # Alpine valley and peaks, 1.3 km of relief; with Gale and Kepler one of the DEMs of the
    # equal-maximum-error table, so all three have BD-rates too.
    Case("earth_davos_10m.tif", None, None, "rough"),
    # A complex crater with 6.4 km of relief: judged against the rough target.
    Case("moon_kepler_lola_48m.tif", None, None, "rough"),
)

#: Error levels for point clouds, as multiples of the gridding floor.
FLOOR_MULTIPLES = (1.25, 1.5, 3.0)
#: Error levels for a DEM sampled one point per pixel (floor 0), as fractions
#: of its RMS relief (standard deviation of the heights).
RELIEF_FRACTIONS = (0.001, 0.003, 0.01)

#: Targets of issue 3: compact's bits over the best anchor's, over Draco's, over paper's.
MAX_OVER_BEST = {"gentle": 0.7, "rough": 1.0}
MAX_OVER_DRACO = 0.2
MAX_OVER_PAPER = 0.1

#: Sweeps. dftpcc compact: cutoff x quantizer step (step in units of the first error scale).
COMPACT_CUTOFFS = (0.0, 0.2, 0.4, 0.5, 0.6, 0.7, 0.75, 0.8, 0.85, 0.9, 0.93, 0.95, 0.97)
COMPACT_STEPS = tuple(2.0 ** (k / 2) for k in range(-2, 17))        # 0.5 .. 256 units
PAPER_CUTOFFS = (0.0, 0.3, 0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.93, 0.95, 0.97, 0.98, 0.99)
DRACO_BITS = tuple(range(8, 17))
DRACO_LEVEL = 7
JPEG2K_PSNR = tuple(range(40, 81, 5))                                # dB on the 16-bit DEM
#: JPEG XL butteraugli distance (0 would be lossless); libjxl's own range ends at 25.
JPEGXL_DISTANCES = tuple(0.01 * 2.0 ** (k / 2) for k in range(23))   # 0.01 .. 20.5
#: HTJ2K (OpenJPH) irreversible quantization step, relative to the 16-bit range.
HTJ2K_QSTEPS = tuple(1e-5 * 2.0 ** (k / 2) for k in range(31))       # 1e-5 .. 0.33
ERROR_BOUNDS = tuple(2.0 ** (k / 2) for k in range(-4, 13))          # LERC / SZ3, 0.25 .. 64 units
QUICK = dict(compact_cutoffs=(0.0, 0.5, 0.7, 0.8, 0.9, 0.95), compact_steps=tuple(2.0 ** k for k in range(-1, 9)),
             paper_cutoffs=(0.0, 0.5, 0.8, 0.9, 0.95, 0.98), draco_bits=(8, 10, 12, 14, 16),
             jpeg2k_psnr=(40, 50, 60, 70, 80), error_bounds=tuple(2.0 ** k for k in range(-2, 7)),
             jpegxl_distances=tuple(0.01 * 2.0 ** k for k in range(12)),
             htj2k_qsteps=tuple(1e-5 * 2.0 ** k for k in range(16)))

#: A BD-rate whose two frontiers share less than this ratio of RMSE (a factor 2 = 6 dB) is marked:
#: it averages over a sliver of the curves.
BD_NARROW_RATIO = 2.0
#: The codec whose BD-rate against every other is reported.
COMPACT = "dftpcc compact"

#: Draco's local origin (three float64) travels beside the Draco buffer.
DRACO_ORIGIN_BYTES = 3 * 8
#: LAZ reference: coordinates stored at the source's scale, or this (metres) for PLY/GeoTIFF.
LAZ_SCALE = 0.001
TIMING_REPEATS = 3
#: A full run should stay under this (seconds); beyond it the script advises --quick.
RUN_BUDGET_S = 15 * 60

ANCHORS_MD = {  # file -> (Draco, JPEG2000) bits/pt at 1.25x, 1.5x, 3x the floor, from ANCHORS.md
    "field_gentle_ign.laz": ((7.958, 7.255, 4.552), (0.751, 0.251, 0.080)),
    "coastal_plain_ign.laz": ((11.796, 11.034, 8.316), (5.146, 3.907, 1.975)),
    "mountain_arid_alirt.las": ((4.832, 4.091, 4.091), (0.194, 0.170, 0.145)),
    "redrocks_rough.ply": ((4.285, 4.037, 4.037), (0.360, 0.285, 0.285)),
}


# --- codecs: encode(setting) -> (bytes, state); decode(state) -> points ---------------

@dataclass
class Codec:
    """One codec under test: how to encode a cloud at a setting and decode it back."""

    name: str
    settings: list[Any]
    encode: Callable[[Any, bool], tuple[int, Any]]
    decode: Callable[[Any], np.ndarray]
    describe: Callable[[Any], str]
    is_anchor: bool = True
    #: Encoded state -> bytes of {"mask", "coef" (coefficients / codestream), "header"}.
    split: Callable[[Any], dict] | None = None


@dataclass
class Sample:
    setting: Any
    bytes: int
    bpp: float
    err: float
    out_points: int
    extra: dict = field(default_factory=dict)


#: A compact setting ``(TARGET, metres)`` asks the library's rate control for that DEM RMSE.
TARGET = "target_rmse"


#: The compact profile with mask="footprint" (an option, not the default).
FOOTPRINT = "dftpcc compact, footprint mask"


def dftpcc_codec(name: str, profile: str, settings: list[tuple[Any, float]], points: np.ndarray,
                 resolution: float, **extra: Any) -> Codec:
    def encode(setting: tuple[Any, float], fresh: bool) -> tuple[int, Any]:
        cutoff, value = setting
        if cutoff == TARGET:
            blob = dftpcc.compress(points, resolution=resolution, profile=profile, target_rmse=value, **extra)
        else:
            options = {"step": value} if profile == "compact" else {}
            blob = dftpcc.compress(points, resolution=resolution, cutoff=cutoff, profile=profile, **options,
                                   **extra)
        return len(blob), blob

    def describe(setting: tuple[Any, float]) -> str:
        cutoff, value = setting
        if cutoff == TARGET:
            return f"rate control, target_rmse {1000 * value:.3g} mm"
        return f"f_c {cutoff:g}" + (f", step {1000 * value:.3g} mm" if profile == "compact" else "")

    def split(blob: bytes) -> dict:
        stats = dftpcc.open(blob).header.stats
        mask = stats.get("mask_bytes", 0)
        coef = stats.get("coef_bytes", 0) + stats.get("residual_bytes", 0)
        return {"mask": mask, "coef": coef, "header": len(blob) - mask - coef}

    return Codec(name, settings, encode, dftpcc.decompress, describe, is_anchor=False, split=split)


def draco_codec(points: np.ndarray, bits: tuple[int, ...]) -> Codec:
    import DracoPy

    def encode(q: int, fresh: bool) -> tuple[int, Any]:
        origin = points.min(axis=0)
        buf = DracoPy.encode((points - origin).astype(np.float32), quantization_bits=q,
                             compression_level=DRACO_LEVEL)
        return len(buf) + DRACO_ORIGIN_BYTES, (buf, origin)

    def split(state: Any) -> dict:
        return {"mask": 0, "coef": len(state[0]), "header": DRACO_ORIGIN_BYTES}

    def decode(state: Any) -> np.ndarray:
        buf, origin = state
        return np.asarray(DracoPy.decode(buf).points, dtype=np.float64) + origin

    return Codec("Draco", list(bits), encode, decode, lambda q: f"{q} bits", split=split)


def raster_codec(name: str, settings: list[Any], cached: Raster, points: np.ndarray, resolution: float,
                 code: Callable[[Raster, Any], tuple[bytes, Any]],
                 uncode: Callable[[Raster, Any], Any], describe: Callable[[Any], str],
                 own_mask: bool = False) -> Codec:
    """A raster codec wrapped to code a cloud: grid + fill + mask, then ``code`` the DEM.

    ``code`` returns the coded bytes and the state ``uncode`` needs (which holds those bytes first).
    ``uncode`` returns the heights, or with ``own_mask`` (a codec that carries the
    occupancy in its codestream, as LERC does) the heights and the mask it decoded;
    such a codec is not charged the separate bitmap.
    """

    def code_bytes(inner: Any) -> bytes:
        first = inner[0] if isinstance(inner, tuple) else inner
        return first.tobytes() if isinstance(first, np.ndarray) else first

    def encode(setting: Any, fresh: bool) -> tuple[int, Any]:
        raster = make_raster(points, resolution) if fresh else cached
        payload, state = code(raster, setting)
        mask_bytes = 0 if own_mask else len(raster.mask_blob)
        return len(payload) + mask_bytes + RASTER_HEADER_BYTES, (raster, state)

    def decode(state: Any) -> np.ndarray:
        raster, inner = state
        if own_mask:
            heights, mask = uncode(raster, inner)
        else:
            heights, mask = uncode(raster, inner), unpack_mask(raster.grid, raster.mask_blob)
        return raster_points(raster.grid, mask, heights)

    def split(state: Any) -> dict:
        raster, inner = state
        return {"mask": 0 if own_mask else len(raster.mask_blob), "coef": len(code_bytes(inner)),
                "header": RASTER_HEADER_BYTES}

    return Codec(name, settings, encode, decode, describe, split=split)


def jpeg2k_code(raster: Raster, psnr: float) -> tuple[bytes, Any]:
    import imagecodecs

    u16, lo, span = to_u16(raster)
    blob = imagecodecs.jpeg2k_encode(u16, level=psnr)
    return blob, (blob, lo, span)


def jpeg2k_uncode(raster: Raster, state: Any) -> np.ndarray:
    import imagecodecs

    blob, lo, span = state
    return imagecodecs.jpeg2k_decode(blob).astype(np.float64) / U16_MAX * span + lo


def htj2k_code(raster: Raster, qstep: float) -> tuple[bytes, Any]:
    import imagecodecs

    u16, lo, span = to_u16(raster)
    blob = imagecodecs.htj2k_encode(u16, level=qstep)
    return blob, (blob, lo, span)


def htj2k_uncode(raster: Raster, state: Any) -> np.ndarray:
    import imagecodecs

    blob, lo, span = state
    return imagecodecs.htj2k_decode(blob).astype(np.float64) / U16_MAX * span + lo


def jpegxl_code(raster: Raster, distance: float) -> tuple[bytes, Any]:
    """Lossy JPEG XL of the float heights: libjxl takes float32 in its nominal range [0, 1].

    (A 16-bit integer input gave the same bytes within 0.3 % and the same error.)
    """
    import imagecodecs

    unit, lo, span = unit_range(raster)
    blob = imagecodecs.jpegxl_encode(unit.astype(np.float32), distance=distance, effort=JPEGXL_EFFORT,
                                     numthreads=ONE_THREAD)
    return blob, (blob, lo, span)


def jpegxl_uncode(raster: Raster, state: Any) -> np.ndarray:
    import imagecodecs

    blob, lo, span = state
    return imagecodecs.jpegxl_decode(blob, numthreads=ONE_THREAD).astype(np.float64) * span + lo


def lerc_code(raster: Raster, max_error: float) -> tuple[bytes, Any]:
    import lerc

    values = raster.heights.astype(np.float32)
    result, nbytes, buf = lerc.encode(values, 1, True, raster.mask.astype(np.uint8), max_error, 1)
    if result != 0:
        raise RuntimeError(f"lerc.encode failed with code {result}")
    blob = bytes(buf)[:nbytes]
    return blob, blob


def lerc_uncode(raster: Raster, blob: bytes) -> tuple[np.ndarray, np.ndarray]:
    import lerc

    result, values, valid = lerc.decode(blob)
    if result != 0:
        raise RuntimeError(f"lerc.decode failed with code {result}")
    values = np.asarray(values, dtype=np.float64)
    # lerc returns no mask when every pixel is valid.
    mask = np.ones(values.shape, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    return values, mask


def sz3_code(raster: Raster, bound: float) -> tuple[bytes, Any]:
    from pysz import sz, szConfig, szErrorBoundMode

    values = raster.filled.astype(np.float32)
    config = szConfig(values.shape)
    config.errorBoundMode = szErrorBoundMode.ABS
    config.absErrorBound = bound
    packed, _ratio = sz.compress(values, config)
    return packed.tobytes(), (packed, values.shape)


def sz3_uncode(raster: Raster, state: Any) -> np.ndarray:
    from pysz import sz

    packed, shape = state
    values, _config = sz.decompress(packed, np.float32, shape)
    return np.asarray(values, dtype=np.float64)


def laz_codec(loaded: Loaded) -> Codec:
    import laspy

    points = loaded.points
    src = loaded.las_header

    def split(data: bytes) -> dict:
        return {"mask": 0, "coef": len(data), "header": 0}

    def encode(_: Any, fresh: bool) -> tuple[int, Any]:
        header = laspy.LasHeader(point_format=0, version="1.2")
        if src is not None:
            header.scales, header.offsets = np.asarray(src.scales), np.asarray(src.offsets)
        else:
            header.scales = np.full(3, LAZ_SCALE)
            header.offsets = np.floor(points.min(axis=0))
        las = laspy.LasData(header)
        las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
        out = io.BytesIO()
        las.write(out, do_compress=True, laz_backend=laspy.LazBackend.Lazrs)
        data = out.getvalue()
        return len(data), data

    def decode(data: bytes) -> np.ndarray:
        las = laspy.read(io.BytesIO(data))
        return np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)]).astype(np.float64)

    scale = "source scale" if src is not None else f"{LAZ_SCALE * 1000:g} mm"
    return Codec("LAZ (lossless)", [None], encode, decode, lambda _: f"point format 0, {scale}", split=split)


# --- one file -------------------------------------------------------------------------

def error_levels(loaded: Loaded, floor: float) -> tuple[list[tuple[str, float]], float, str]:
    """(label, metres) error levels, the unit of the sweeps, and how the levels were chosen."""
    if loaded.case.is_dem:
        relief = float(np.std(loaded.points[:, 2]))
        levels = [(f"{100 * f:g}% relief ({1000 * f * relief:.1f} mm)", f * relief) for f in RELIEF_FRACTIONS]
        how = (f"one point per pixel, so the gridding floor is {1000 * floor:.3g} mm; error levels are "
               f"fractions of the RMS relief (standard deviation of the heights, {relief:.2f} m)")
        return levels, levels[0][1], how
    levels = [(f"{k:g}× floor ({1000 * k * floor:.1f} mm)", k * floor) for k in FLOOR_MULTIPLES]
    return levels, floor, f"error levels are multiples of the gridding floor {1000 * floor:.1f} mm"


def rate_control_available() -> bool:
    """Whether this dftpcc's compress takes ``target_rmse`` (rate control)."""
    import dataclasses

    return TARGET in {f.name for f in dataclasses.fields(dftpcc.Params)}


def sweep(codec: Codec, matcher: NearestHeights, n: int) -> list[Sample]:
    samples = []
    for setting in codec.settings:
        try:
            size, state = codec.encode(setting, False)
        except dftpcc.InvalidInputError:
            if isinstance(setting, tuple) and setting[0] == TARGET:
                continue  # a target rate control cannot reach is a missing sample, not a failure
            raise
        decoded = codec.decode(state)
        extra = codec.split(state) if codec.split else {}
        samples.append(Sample(setting, size, 8.0 * size / n, matcher.rmse(decoded), decoded.shape[0], extra))
    return samples


def time_codec(codec: Codec, setting: Any, n: int) -> tuple[float, float]:
    """Median encode rate (input points/s) and decode rate (output points/s), from the points."""
    t_enc, (_, state) = median_time(lambda: codec.encode(setting, True), TIMING_REPEATS)
    t_dec, decoded = median_time(lambda: codec.decode(state), TIMING_REPEATS)
    return n / t_enc, decoded.shape[0] / t_dec


def measure(loaded: Loaded, sweeps: dict) -> dict:
    points, res = loaded.points, loaded.resolution
    n = points.shape[0]
    raster = make_raster(points, res)
    dem = rasterize(points, raster.grid)
    floor = float(dem.gridding_rmse)
    levels, unit, how = error_levels(loaded, floor)
    if loaded.case.is_dem and (floor > 0 or int(raster.mask.sum()) != n):
        loaded.notes.append(f"the grid does not hold one point per cell ({int(raster.mask.sum())} cells for "
                            f"{n} points, floor {1000 * floor:.1f} mm)")
    if loaded.case.is_dem:
        # Pixel centres sit near cell edges: check each one's nearest decoded centre is its own cell's.
        rows, cols = np.nonzero(raster.mask)
        centres = np.column_stack(raster.grid.centres(rows, cols))
        _, nearest = cKDTree(centres).query(points[:, :2])
        rank = np.cumsum(raster.mask.ravel()) - 1
        stray = int(np.count_nonzero(rank[raster.grid.flat_index(points)] != nearest))
        if stray:
            loaded.notes.append(f"{stray} points are nearer another cell's centre than their own")
    compact_settings: list[tuple[Any, float]] = [
        (c, s * unit) for c in sweeps["compact_cutoffs"] for s in sweeps["compact_steps"]]
    if rate_control_available():
        # The cell RMSE that, added to the floor in quadrature, makes each level.
        compact_settings += [(TARGET, math.sqrt(e * e - floor * floor)) for _, e in levels if e > floor]
    paper_settings = [(c, 0.0) for c in sweeps["paper_cutoffs"]]
    bounds = [b * unit for b in sweeps["error_bounds"]]
    codecs = [
        dftpcc_codec(COMPACT, "compact", compact_settings, points, res),
        dftpcc_codec("dftpcc paper", "paper", paper_settings, points, res),
        # Not the default: also rebuilds the gaps the map encloses, so its mask costs far less.
        dftpcc_codec(FOOTPRINT, "compact", compact_settings, points, res, mask="footprint"),
        draco_codec(points, sweeps["draco_bits"]),
        raster_codec("JPEG2000", list(sweeps["jpeg2k_psnr"]), raster, points, res, jpeg2k_code, jpeg2k_uncode,
                     lambda db: f"PSNR {db} dB"),
        raster_codec("JPEG XL", list(sweeps["jpegxl_distances"]), raster, points, res, jpegxl_code,
                     jpegxl_uncode, lambda d: f"distance {d:.3g}"),
        raster_codec("HTJ2K", list(sweeps["htj2k_qsteps"]), raster, points, res, htj2k_code, htj2k_uncode,
                     lambda q: f"qstep {q:.3g}"),
        raster_codec("LERC", bounds, raster, points, res, lerc_code, lerc_uncode,
                     lambda e: f"maxZError {1000 * e:.3g} mm", own_mask=True),
        raster_codec("SZ3", bounds, raster, points, res, sz3_code, sz3_uncode,
                     lambda e: f"abs bound {1000 * e:.3g} mm"),
        laz_codec(loaded),
    ]
    matcher = NearestHeights(points)
    results = {}
    for codec in codecs:
        t0 = time.perf_counter()
        samples = sweep(codec, matcher, n)
        hull = lower_hull([(s.bpp, s.err) for s in samples])
        on_hull = [s for s in samples if (s.bpp, s.err) in set(hull)]
        # Time the frontier setting closest (in log error) to the middle level; a rate-controlled
        # file is left out, since its time is the search's, not the codec's.
        middle = levels[len(levels) // 2][1]
        fixed = [s for s in (on_hull or samples) if not (isinstance(s.setting, tuple) and s.setting[0] == TARGET)]
        timed = min(fixed or samples, key=lambda s: abs(math.log(max(s.err, MIN_ERROR) / middle)))
        enc_rate, dec_rate = time_codec(codec, timed.setting, n)
        results[codec.name] = dict(codec=codec, samples=samples, hull=hull, on_hull=on_hull, timed=timed,
                                   enc_rate=enc_rate, dec_rate=dec_rate,
                                   bits=[bits_at(hull, e) for _, e in levels],
                                   seconds=time.perf_counter() - t0)
    bd = {name: bd_rate(r["hull"], results[COMPACT]["hull"]) for name, r in results.items() if name != COMPACT}
    return dict(loaded=loaded, n=n, floor=floor, levels=levels, how=how, raster=raster, results=results, bd=bd)


# --- reporting ------------------------------------------------------------------------

def best_anchor(results: dict, level: int) -> tuple[float | None, str, str]:
    best: tuple[float | None, str, str] = (None, "", "")
    for name, r in results.items():
        if not r["codec"].is_anchor:
            continue
        bits, flag = r["bits"][level]
        if bits is not None and (best[0] is None or bits < best[0]):
            best = (bits, name, flag)
    return best


def fmt_bd(bd: BDRate | None, *, with_range: bool = False) -> str:
    """A BD-rate as a signed percentage; † when the shared RMSE range is narrow, — when there is none."""
    if bd is None:
        return "—"
    narrow = "†" if bd.high < BD_NARROW_RATIO * bd.low else ""
    text = f"{100 * bd.rate:+.1f} %{narrow}"
    return text + (f" ({1000 * bd.low:.3g}–{1000 * bd.high:.3g})" if with_range else "")


def bd_table(measured: list[dict]) -> str:
    """BD-rate of dftpcc compact against every other codec, one row per map."""
    names = [name for name in measured[0]["results"] if name != COMPACT]
    rows = [[m["loaded"].case.label()] + [fmt_bd(m["bd"].get(name)) for name in names] for m in measured]
    return ("### BD-rate of dftpcc compact against each codec\n\n"
            "Mean difference in bits of dftpcc compact over the codec at equal vertical RMSE, over the RMSE "
            "range both frontiers cover (negative: compact needs fewer bits). Bjøntegaard's delta rate with "
            "piecewise-cubic interpolation: log bits against log RMSE (PSNR up to scale and offset) through "
            "each frontier's points by a monotone cubic Hermite (PCHIP) curve, integrated over the shared "
            f"range; not VCEG-M33's single cubic polynomial. †: the shared range is under a factor "
            f"{BD_NARROW_RATIO:g} of RMSE; —: no shared range (the lossless LAZ has one point). The ranges are "
            "in each file's table.\n\n"
            + markdown_table(["file"] + names, rows))


def ratio_cell(num: tuple[float | None, str], den: tuple[float | None, str], limit: float) -> str:
    """compact / other, with a bound sign when either side is clamped at its cheapest setting."""
    (a, fa), (b, fb) = num, den
    if a is None or b is None:
        return "n/a (" + ("compact" if a is None else "anchor") + " never this accurate)"
    ratio = a / b
    sign = "≤" if fa == "cheapest" and fb != "cheapest" else ("≥" if fb == "cheapest" and fa != "cheapest" else "")
    if fa == "cheapest" and fb == "cheapest":
        sign = "~"
    return f"{sign}{ratio:.2f} {verdict(ratio <= limit)}"


def report(m: dict) -> str:
    loaded, n, results, levels = m["loaded"], m["n"], m["results"], m["levels"]
    case = loaded.case
    g = m["raster"].grid
    out = [f"### {case.label()} — {case.terrain}, {loaded.resolution:.4g} m",
           "",
           f"{n:,} points; grid {g.rows} x {g.cols}, {int(m['raster'].mask.sum()):,} occupied cells; "
           f"{m['how']}. Figure: `docs/figures/bench_rd_{case.stem}.png`.", ""]
    out += [f"Note: {note}" for note in loaded.notes]
    if loaded.notes:
        out.append("")
    header = ["codec"] + [f"bits/pt @ {label}" for label, _ in levels] + \
        ["BD-rate of compact vs it (RMSE range mm)", "settings", "encode M pts/s", "decode M pts/s", "timed at"]
    rows = []
    for name, r in results.items():
        codec = r["codec"]
        bd = "" if name == COMPACT else fmt_bd(m["bd"].get(name), with_range=True)
        rows.append([name] + [fmt_bits(b, f) for b, f in r["bits"]] + [bd] +
                    [f"{len(r['samples'])}", f"{r['enc_rate'] / 1e6:.2f}", f"{r['dec_rate'] / 1e6:.2f}",
                     codec.describe(r["timed"].setting)])
    best = [best_anchor(results, i) for i in range(len(levels))]
    blank = ["", "", "", "", ""]
    rows.append(["**best anchor**"] + [f"{fmt_bits(b, f)} {name}" if b is not None else "—" for b, name, f in best]
                + blank)
    compact = results[COMPACT]["bits"]
    limit = MAX_OVER_BEST[case.terrain]
    rows.append([f"compact / best anchor (≤ {limit:g})"] +
                [ratio_cell(compact[i], (best[i][0], best[i][2]), limit) for i in range(len(levels))]
                + blank)
    rows.append([f"compact / Draco (≤ {MAX_OVER_DRACO:g})"] +
                [ratio_cell(compact[i], results["Draco"]["bits"][i], MAX_OVER_DRACO) for i in range(len(levels))]
                + blank)
    rows.append([f"compact / paper (≤ {MAX_OVER_PAPER:g})"] +
                [ratio_cell(compact[i], results["dftpcc paper"]["bits"][i], MAX_OVER_PAPER)
                 for i in range(len(levels))] + blank)
    out += [markdown_table(header, rows), ""]
    out.append(split_table(m))
    return "\n".join(out)


def split_table(m: dict) -> str:
    """Where the bytes go, for compact and the best anchor, at the frontier setting that just meets each level."""
    n, results = m["n"], m["results"]
    rows = []
    for i, (label, level) in enumerate(m["levels"]):
        for name in (COMPACT, best_anchor(results, i)[1] or "JPEG2000"):
            r = results[name]
            ok = [s for s in r["on_hull"] if s.err <= level]
            if not ok:
                rows.append([label, name, "never this accurate", "", "", "", "", ""])
                continue
            s = min(ok, key=lambda s: s.bpp)
            x = s.extra
            rows.append([label, name, r["codec"].describe(s.setting), f"{1000 * s.err:.1f}", fmt_bits(s.bpp),
                         fmt_bits(8.0 * x["mask"] / n), fmt_bits(8.0 * x["coef"] / n),
                         fmt_bits(8.0 * x["header"] / n)])
    header = ["level", "codec", "setting (cheapest frontier point meeting the level)", "RMSE mm", "bits/pt",
              "mask", "coefficients / codestream", "header & framing"]
    return ("Where the bits go (bits/pt; LERC keeps its mask inside its codestream; dftpcc's "
            "coefficients include its residual layer, stats['residual_bytes']; its header & framing = file size - "
            "stats['mask_bytes'] - stats['coef_bytes'] - stats['residual_bytes']):\n\n"
            + markdown_table(header, rows) + "\n\n")


def anchors_md_check(measured: list[dict]) -> str:
    rows = []
    for m in measured:
        ref = ANCHORS_MD.get(m["loaded"].case.name)
        if not ref:
            continue
        for i, (label, _) in enumerate(m["levels"]):
            cells = [m["loaded"].case.name, label.split(" (")[0]]
            for codec, refs in zip(("Draco", "JPEG2000"), ref):
                bits, flag = m["results"][codec]["bits"][i]
                cells.append(f"{fmt_bits(bits, flag)} / {refs[i]:.3f}"
                             + (f" ({bits / refs[i]:.3f}×)" if bits else ""))
            rows.append(cells)
    if not rows:
        return ""
    return ("### Anchors re-measured against ANCHORS.md\n\nThis run / ANCHORS.md, bits per point.\n\n"
            + markdown_table(["file", "level", "Draco", "JPEG2000"], rows))


def plot(m: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 5.2))
    colours = {COMPACT: "C3", FOOTPRINT: "C8", "dftpcc paper": "C1", "Draco": "C0", "JPEG2000": "C2", "LERC": "C4",
               "SZ3": "C5", "JPEG XL": "C6", "HTJ2K": "C9", "LAZ (lossless)": "0.4"}
    for name, r in m["results"].items():
        c = colours.get(name)
        if name.startswith("LAZ"):
            ax.axhline(r["samples"][0].bpp, color=c, ls=":", lw=1, label=f"{name} {r['samples'][0].bpp:.1f}")
            continue
        errs = np.array([max(s.err, 1e-6) for s in r["samples"]]) * 1000
        bpps = np.array([s.bpp for s in r["samples"]])
        ax.scatter(errs, bpps, s=6, color=c, alpha=0.35, lw=0)
        hb = np.array([b for b, _ in r["hull"]])
        he = np.array([max(e, 1e-6) for _, e in r["hull"]]) * 1000
        ax.plot(he, hb, "-o", ms=3, color=c, label=name, lw=1.5 if name.startswith("dftpcc compact") else 1)
    for label, e in m["levels"]:
        ax.axvline(e * 1000, color="k", ls="--", lw=0.6)
        ax.text(e * 1000, 0.02, " " + label.split(" (")[0], transform=ax.get_xaxis_transform(), ha="right",
                va="bottom", rotation=90, fontsize=7)
    if m["floor"] > 0:
        ax.axvline(m["floor"] * 1000, color="k", lw=0.8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("vertical RMSE to nearest decoded point (mm)")
    ax.set_ylabel("bits per original point")
    loaded = m["loaded"]
    ax.set_title(f"{loaded.case.label()}, {loaded.resolution:.4g} m, {m['n']:,} points", fontsize=9)
    ax.grid(True, which="both", lw=0.3, alpha=0.5)
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def max_error_only(args: argparse.Namespace) -> int:
    """The equal-maximum-error table alone, on the DEMs it names (or those of ``--files``)."""
    t0 = time.perf_counter()
    print(f"Measuring {library_label()}; {load_average()}.", flush=True)
    cases = [c for c in pick_cases(CASES, args.files) if c.name in max_error.MAX_ERRORS]
    bounded = []
    for case in cases:
        loaded = load(case, args.data)
        with warnings_as_notes(loaded.notes):
            bounded.append(max_error.measure(loaded, make_raster(loaded.points, loaded.resolution),
                                             dftpcc_repeats=1 if args.quick else max_error.TIMING_REPEATS))
    print(max_error.report(bounded))
    print(f"Run time {time.perf_counter() - t0:.0f} s; {load_average()} at the end.")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = run_arguments(__doc__.split("\n\n")[0], "coarser sweeps (about a quarter of the settings)")
    ap.add_argument("--no-figures", action="store_true", help="do not write docs/figures/bench_rd_*.png")
    ap.add_argument("--max-error-only", action="store_true",
                    help="only the equal-maximum-error table, on its DEMs (a minute or two; writes no docs)")
    args = ap.parse_args(argv)
    if args.max_error_only:
        return max_error_only(args)
    sweeps = dict(compact_cutoffs=COMPACT_CUTOFFS, compact_steps=COMPACT_STEPS, paper_cutoffs=PAPER_CUTOFFS,
                  draco_bits=DRACO_BITS, jpeg2k_psnr=JPEG2K_PSNR, error_bounds=ERROR_BOUNDS,
                  jpegxl_distances=JPEGXL_DISTANCES, htj2k_qsteps=HTJ2K_QSTEPS)
    if args.quick:
        sweeps.update(QUICK)
    cases = pick_cases(CASES, args.files)
    t0 = time.perf_counter()
    print(f"Measuring {library_label()}; {load_average()}.", flush=True)
    intro = (
        "Bits per ORIGINAL point each codec needs for a vertical RMSE (every original point against the "
        "decoded point nearest to it in x, y) at the given level, read off each codec's frontier (the "
        "lower convex hull of its sweep in the bits x squared-error plane, i.e. what mixing two settings "
        "could reach) by log-log interpolation between frontier points (ANCHORS.md). `*`: the codec's cheapest setting "
        "is already more accurate than the level, so the figure is an upper bound; `—`: no setting got "
        "that accurate. Ratios: `≥`/`≤` when one side is such a bound. Floor: RMSE of the points against "
        "the mean height of their own cell. Speeds: medians of "
        f"{TIMING_REPEATS} in-memory runs at the frontier setting closest to the middle level, from parsed "
        "points to bytes (raster anchors include gridding, fill and mask) and back to points.\n\n"
        "Anchors: Draco (DracoPy, compression level 7, quantization 8–16 bits, float32 points about a "
        f"local origin, + {DRACO_ORIGIN_BYTES} B for that origin); JPEG2000 (imagecodecs, 16-bit DEM "
        "scaled over its range, empty cells filled from the nearest occupied one, PSNR 40–80 dB); JPEG XL "
        f"(imagecodecs/libjxl, effort {JPEGXL_EFFORT}, lossy on the filled float heights scaled to [0, 1] "
        "over their range, float32 being libjxl's float input and that its nominal range, butteraugli "
        f"distance {min(sweeps['jpegxl_distances']):.3g}–{max(sweeps['jpegxl_distances']):.3g}); HTJ2K "
        "(imagecodecs/OpenJPH, the 16-bit DEM of JPEG2000, irreversible, quantization step "
        f"{min(sweeps['htj2k_qsteps']):.3g}–{max(sweeps['htj2k_qsteps']):.3g} of the range); LERC "
        "(float32 DEM + its valid mask, maxZError sweep); SZ3 (pysz, float32 filled DEM, absolute bound "
        "sweep); the raster anchors are charged the zstd-19 occupancy bitmap (but LERC, whose codestream "
        f"carries its mask) and {RASTER_HEADER_BYTES} B of grid/scale header; codecs with a thread option "
        "run on one thread; LAZ (laspy + lazrs, x y z "
        "only) is the lossless reference. dftpcc compact sweeps f_c x step "
        f"({len(sweeps['compact_cutoffs'])} x {len(sweeps['compact_steps'])}, plus one rate-controlled file "
        "per level when the library offers `target_rmse`), paper sweeps f_c "
        f"({len(sweeps['paper_cutoffs'])} values). '{FOOTPRINT}' is the same sweep with the option "
        "`mask='footprint'` (it also rebuilds the empty cells the map encloses, so every original point "
        "still finds its own cell; not the default, which rebuilds occupied cells only). Targets: "
        "compact ≤ 0.7x the best anchor on gentle "
        "terrain, ≤ 1.0x on rough, ≤ 0.2x Draco, ≤ 0.1x paper, at every level.")
    print(intro, "\n", flush=True)
    measured, bounded, parts = [], [], [intro]
    # The dftpcc encode at a max-error target is a search of seconds: timed once in a quick run.
    dftpcc_repeats = 1 if args.quick else max_error.TIMING_REPEATS
    for case in cases:
        t_case = time.perf_counter()
        loaded = load(case, args.data)
        with warnings_as_notes(loaded.notes):
            m = measure(loaded, sweeps)
        measured.append(m)
        bound_s = 0.0
        if case.name in max_error.MAX_ERRORS:
            t_bound = time.perf_counter()
            with warnings_as_notes(loaded.notes):
                bounded.append(max_error.measure(loaded, m["raster"], dftpcc_repeats=dftpcc_repeats))
            bound_s = time.perf_counter() - t_bound
        if not args.no_figures:
            plot(m, FIGURES / f"bench_rd_{case.stem}.png")
        text = report(m)
        secs = {name: r["seconds"] for name, r in m["results"].items()}
        text += (f"Time for this file: {time.perf_counter() - t_case:.0f} s ("
                 + ", ".join(f"{k} {v:.0f} s" for k, v in secs.items())
                 + (f"; the equal-maximum-error table {bound_s:.0f} s" if bound_s else "") + ").\n")
        parts.append(text)
        print(text, flush=True)
    if measured:
        table = bd_table(measured)
        parts.append(table)
        print(table, "\n", flush=True)
    if bounded:
        table = max_error.report(bounded)
        parts.append(table)
        print(table, flush=True)
    check = anchors_md_check(measured)
    if check:
        parts.append(check)
        print(check)
    elapsed = time.perf_counter() - t0
    over = " (over the ~15 min budget: use --quick)" if elapsed > RUN_BUDGET_S else ""
    finish_run(parts, args, "bench_anchors", "Rate-distortion against the anchors (issue 3)",
               f"{'Quick run (--quick: coarser sweeps, dftpcc max-error encode timed once)' if args.quick else 'Full run'}"
               f"; run time {elapsed:.0f} s{over}; {load_average()} at the end.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
