"""The anchors at equal maximum error: every occupied cell of a DEM within E.

Part of bench_anchors' run, on the same raster. For each DEM and bound E,
dftpcc's ``target_max_error`` against LERC with its valid mask, SZ3 with an
absolute bound, and lossless JPEG XL, JPEG2000 and HTJ2K on the heights
quantized to steps of 2E. Every codec's largest error is measured against the
DEM's own heights, not taken on trust: one beyond E prints FAIL.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

import dftpcc

from benchmarks.common import Loaded, markdown_table, median_time
from benchmarks.rasters import JPEGXL_EFFORT, ONE_THREAD, RASTER_HEADER_BYTES, U16_MAX, Raster

__all__ = ["MAX_ERRORS", "Bounded", "bounded", "codecs", "measure", "report"]

#: Bounds E (metres) per DEM. Gale and Davos: 1, 5 and 20 cm. Kepler's heights
#: are whole metres (LOLA, int16) over 6.4 km of relief, so any E under 0.5 m
#: asks for the integers themselves: 0.5 m (quantizing to steps of 1 m keeps
#: them exactly), then 1 m and 5 m (under 0.1 % of the relief).
MAX_ERRORS = {
    "mars_gale_1m.tif": (0.01, 0.05, 0.20),
    "earth_davos_10m.tif": (0.01, 0.05, 0.20),
    "moon_kepler_lola_48m.tif": (0.5, 1.0, 5.0),
}
#: A codec passes when its largest error is at most E plus this (metres): the
#: float64 round-off of heights of a few km, 1e-12 m, and not a float32 ulp.
CHECK_SLACK = 1e-9
#: The quantized codecs' step is 2E less this fraction, so that rounding stays
#: inside E in floating point (as dftpcc's residual layer does).
QUANT_MARGIN = 1e-6
TIMING_REPEATS = 3
#: Bounds below this (metres) print in centimetres.
CM_BELOW = 0.5

#: A previous hand measurement (ANCHORS.md, bytes): dftpcc, LERC, SZ3, JPEG XL
#: and JPEG2000 on the heights quantized to 2E.
HAND_CODECS = ("dftpcc", "LERC", "SZ3", "JPEG XL lossless, 2E steps", "JPEG2000 lossless, 2E steps")
HAND_MEASURED = {
    ("mars_gale_1m.tif", 0.01): (22_496, 104_121, 27_714, 27_278, 30_637),
    ("mars_gale_1m.tif", 0.05): (8_238, 71_299, 9_614, 14_434, 20_218),
    ("mars_gale_1m.tif", 0.20): (3_414, 45_157, 3_290, 7_277, 14_836),
    ("earth_davos_10m.tif", 0.01): (288_231, 408_211, 299_100, 258_650, 267_499),
    ("earth_davos_10m.tif", 0.05): (198_997, 328_745, 200_147, 175_333, 185_347),
    ("earth_davos_10m.tif", 0.20): (126_314, 261_097, 125_260, 109_568, 118_466),
}


@dataclass
class Bounded:
    """A DEM as the bounded codecs see it.

    Attributes
    ----------
    points : ndarray (N, 3), metres
        The cloud dftpcc compresses (one point per pixel of the DEM).
    resolution : float
        Cell size, metres.
    raster : Raster
        The grid, mask and bitmap of the RMSE sweep's raster anchors.
    truth : ndarray (rows, cols), float64
        Absolute height of every occupied cell (metres), empty cells filled
        from the nearest occupied one; errors are measured against it.
    float32 : bool
        Whether ``truth`` holds float32 values exactly (a float32 or int16
        GeoTIFF), so that LERC on float32 sees the DEM itself.
    """

    points: np.ndarray
    resolution: float
    raster: Raster
    truth: np.ndarray
    float32: bool
    notes: list[str] = field(default_factory=list)

    @property
    def cells(self) -> int:
        return int(self.raster.mask.sum())


def bounded(loaded: Loaded, raster: Raster) -> Bounded:
    """The DEM of ``loaded`` on ``raster``'s grid, with its cells' exact heights."""
    grid, mask, points = raster.grid, raster.mask, loaded.points
    flat = grid.flat_index(points)
    notes = []
    if np.bincount(flat, minlength=grid.size).max() == 1:
        exact = np.zeros(grid.size)
        exact[flat] = points[:, 2]  # the source's own values, without the z0 round trip
        exact = exact.reshape(grid.shape)
    else:
        exact = raster.heights + grid.z0
        notes.append("some cells hold several points: each cell's height is their mean")
    truth = np.where(mask, exact, raster.filled + grid.z0)
    float32 = bool(np.array_equal(truth[mask].astype(np.float32).astype(np.float64), truth[mask]))
    return Bounded(points, loaded.resolution, raster, truth, float32, notes)


# --- codecs: encode(DEM, E) -> (bytes charged, state); decode(state) -> absolute heights --------

@dataclass
class BoundedCodec:
    """A codec asked for every occupied cell within E."""

    name: str
    encode: Callable[[Bounded, float], tuple[int, Any]]
    decode: Callable[[Bounded, Any], np.ndarray]
    #: What the encoded state says about the setting used (e.g. the cutoff dftpcc chose).
    describe: Callable[[Any], str]
    #: Why the codec cannot code this DEM at this bound, or None.
    unable: Callable[[Bounded, float], str | None] = lambda dem, bound: None
    is_anchor: bool = True


def _dftpcc_encode(dem: Bounded, bound: float) -> tuple[int, Any]:
    blob = dftpcc.compress(dem.points, resolution=dem.resolution, target_max_error=bound)
    return len(blob), blob


def _dftpcc_decode(dem: Bounded, blob: bytes) -> np.ndarray:
    with dftpcc.open(blob) as cmap:
        out = cmap.read_dem()
    if out.grid.shape != dem.raster.grid.shape:
        raise RuntimeError(f"dftpcc rebuilt a {out.grid.shape} grid for a {dem.raster.grid.shape} DEM")
    return out.heights + out.grid.z0


def _dftpcc_describe(blob: bytes) -> str:
    with dftpcc.open(blob) as cmap:
        params, stats = cmap.params, cmap.header.stats
    return (f"f_c {params.cutoff:g}, step {1000 * params.step:.3g} mm, residual layer "
            f"{stats.get('residual_bytes', 0):,} B")


def _lerc(dtype: type) -> tuple[Callable, Callable]:
    def encode(dem: Bounded, bound: float) -> tuple[int, Any]:
        import lerc

        values = dem.truth.astype(dtype)
        result, nbytes, buf = lerc.encode(values, 1, True, dem.raster.mask.astype(np.uint8), bound, 1)
        if result != 0:
            raise RuntimeError(f"lerc.encode failed with code {result}")
        blob = bytes(buf)[:nbytes]
        return len(blob) + RASTER_HEADER_BYTES, blob  # the codestream carries the mask

    def decode(dem: Bounded, blob: bytes) -> np.ndarray:
        import lerc

        result, values, _valid = lerc.decode(blob)
        if result != 0:
            raise RuntimeError(f"lerc.decode failed with code {result}")
        return np.asarray(values, dtype=np.float64)

    return encode, decode


def _sz3_encode(dem: Bounded, bound: float) -> tuple[int, Any]:
    from pysz import sz, szConfig, szErrorBoundMode

    config = szConfig(dem.truth.shape)
    config.errorBoundMode = szErrorBoundMode.ABS
    config.absErrorBound = bound
    packed, _ratio = sz.compress(dem.truth, config)
    return packed.nbytes + len(dem.raster.mask_blob) + RASTER_HEADER_BYTES, packed


def _sz3_decode(dem: Bounded, packed: Any) -> np.ndarray:
    from pysz import sz

    values, _config = sz.decompress(packed, np.float64, dem.truth.shape)
    return np.asarray(values, dtype=np.float64)


def quantized(dem: Bounded, bound: float) -> tuple[np.ndarray, float, float]:
    """The heights as integers on steps of 2E from their minimum: (q, minimum metres, step metres)."""
    lo = float(dem.truth.min())
    step = 2.0 * bound * (1.0 - QUANT_MARGIN)
    return np.round((dem.truth - lo) / step), lo, step


def _too_many_levels(dem: Bounded, bound: float) -> str | None:
    levels = float(np.ptp(dem.truth)) / (2.0 * bound * (1.0 - QUANT_MARGIN))
    return f"needs {math.ceil(levels) + 1:,} levels, more than 16 bits" if levels > U16_MAX else None


def _lossless(code: Callable[[np.ndarray], bytes], uncode: Callable[[bytes], np.ndarray]) -> tuple[Callable, Callable]:
    def encode(dem: Bounded, bound: float) -> tuple[int, Any]:
        q, lo, step = quantized(dem, bound)
        blob = code(q.astype(np.uint16))
        return len(blob) + len(dem.raster.mask_blob) + RASTER_HEADER_BYTES, (blob, lo, step)

    def decode(dem: Bounded, state: Any) -> np.ndarray:
        blob, lo, step = state
        return lo + uncode(blob).astype(np.float64) * step

    return encode, decode


def codecs() -> list[BoundedCodec]:
    import imagecodecs

    lerc64, lerc32 = _lerc(np.float64), _lerc(np.float32)
    jxl = _lossless(lambda q: imagecodecs.jpegxl_encode(q, lossless=True, effort=JPEGXL_EFFORT,
                                                        numthreads=ONE_THREAD),
                    lambda b: imagecodecs.jpegxl_decode(b, numthreads=ONE_THREAD))
    j2k = _lossless(lambda q: imagecodecs.jpeg2k_encode(q, level=0, reversible=True, numthreads=ONE_THREAD),
                    lambda b: imagecodecs.jpeg2k_decode(b, numthreads=ONE_THREAD))
    htj2k = _lossless(lambda q: imagecodecs.htj2k_encode(q, reversible=True), imagecodecs.htj2k_decode)
    same = lambda _: ""  # noqa: E731 - the anchors' setting is E itself
    return [
        BoundedCodec("dftpcc", _dftpcc_encode, _dftpcc_decode, _dftpcc_describe, is_anchor=False),
        BoundedCodec("LERC", *lerc64, lambda _: "float64 heights"),
        BoundedCodec("LERC float32", *lerc32, lambda _: "float32 heights, as the GeoTIFF stores them",
                     unable=lambda dem, _: None if dem.float32 else "the heights are not float32 values"),
        BoundedCodec("SZ3", _sz3_encode, _sz3_decode, lambda _: "float64 heights, absolute bound"),
        BoundedCodec("JPEG XL lossless, 2E steps", *jxl, same, unable=_too_many_levels),
        BoundedCodec("JPEG2000 lossless, 2E steps", *j2k, same, unable=_too_many_levels),
        BoundedCodec("HTJ2K lossless, 2E steps", *htj2k, same, unable=_too_many_levels),
    ]


# --- measuring ------------------------------------------------------------------------

@dataclass
class Result:
    """One codec on one DEM at one bound."""

    codec: BoundedCodec
    bound: float
    bytes: int | None = None
    max_error: float = math.nan
    encode_s: float = math.nan
    decode_s: float = math.nan
    setting: str = ""
    unable: str | None = None

    @property
    def ok(self) -> bool:
        return self.bytes is not None and self.max_error <= self.bound + CHECK_SLACK


def measure(loaded: Loaded, raster: Raster, *, dftpcc_repeats: int = TIMING_REPEATS) -> dict:
    """Every codec at every bound of ``MAX_ERRORS`` for this DEM.

    The dftpcc encode is its rate control's search (what ``--target-max-error``
    runs), several seconds, so it is repeated ``dftpcc_repeats`` times; the
    anchors and every decode ``TIMING_REPEATS`` times. Times are medians.
    """
    dem = bounded(loaded, raster)
    mask = raster.mask
    rows = []
    for bound in MAX_ERRORS[loaded.case.name]:
        for codec in codecs():
            r = Result(codec, bound, unable=codec.unable(dem, bound))
            if r.unable is None:
                repeats = TIMING_REPEATS if codec.is_anchor else dftpcc_repeats
                r.encode_s, (size, state) = median_time(lambda: codec.encode(dem, bound), repeats)
                r.decode_s, heights = median_time(lambda: codec.decode(dem, state), TIMING_REPEATS)
                r.bytes, r.setting = size, codec.describe(state)
                r.max_error = float(np.abs(heights - dem.truth)[mask].max())
            rows.append(r)
    return dict(name=loaded.case.name, dem=dem, rows=rows)


# --- reporting ------------------------------------------------------------------------

def fmt_length(metres: float) -> str:
    """0.01 -> '1 cm', 0.2 -> '20 cm', 0.5 -> '0.5 m'."""
    return f"{100 * metres:g} cm" if metres < CM_BELOW else f"{metres:g} m"


def _check(r: Result) -> str:
    if r.bytes is None:
        return "n/a"
    if r.ok:
        return "PASS"
    return f"FAIL (+{1e6 * (r.max_error - r.bound):.3g} µm)"


def _best(rows: list[Result]) -> Result | None:
    passing = [r for r in rows if r.codec.is_anchor and r.ok]
    return min(passing, key=lambda r: r.bytes) if passing else None


def report(measured: list[dict]) -> str:
    """The equal-maximum-error section: bytes with ratios, the details, and the hand measurement re-checked."""
    if not measured:
        return ""
    anchors = [c.name for c in codecs() if c.is_anchor]
    wide, detail, hand = [], [], []
    for m in measured:
        dem = m["dem"]
        by_bound: dict[float, list[Result]] = {}
        for r in m["rows"]:
            by_bound.setdefault(r.bound, []).append(r)
        for bound, rows in by_bound.items():
            ours = rows[0]
            cells = [m["name"], fmt_length(bound), f"{ours.bytes:,}" + ("" if ours.ok else " FAIL")]
            for r in rows[1:]:
                if r.bytes is None:
                    cells.append("n/a")
                    continue
                cells.append(f"{r.bytes:,} ({ours.bytes / r.bytes:.2f})" + ("" if r.ok else " FAIL"))
            best = _best(rows)
            cells += [best.codec.name if best else "—", f"{ours.bytes / best.bytes:.2f}" if best else "—"]
            wide.append(cells)
            for r in rows:
                if r.bytes is None:
                    detail.append([m["name"], fmt_length(bound), r.codec.name, "n/a", "", "", "", "", "", r.unable])
                    continue
                detail.append([m["name"], fmt_length(bound), r.codec.name, f"{r.bytes:,}",
                               f"{8 * r.bytes / dem.cells:.3f}", f"{ours.bytes / r.bytes:.2f}",
                               f"{1000 * r.max_error:.4g}", _check(r),
                               f"{dem.cells / r.encode_s / 1e6:.3g} / {dem.cells / r.decode_s / 1e6:.3g}",
                               r.setting])
            ref = HAND_MEASURED.get((m["name"], bound))
            if ref:
                got = {r.codec.name: r.bytes for r in rows}
                hand.append([m["name"], fmt_length(bound)] +
                            [f"{got[name]:,} / {was:,} ({got[name] / was:.3f}×)" if got.get(name) else "n/a"
                             for name, was in zip(HAND_CODECS, ref)])
        for note in dem.notes:
            detail.append([m["name"], "", "", "", "", "", "", "", "", f"note: {note}"])
    out = [
        "### At equal maximum error (every occupied cell within E)",
        "",
        "Bytes each codec needs so that every occupied cell of the DEM is within E of its height, each "
        "codec's largest error measured against the DEM's own heights (PASS: at most E, + "
        f"{1e9 * CHECK_SLACK:g} nm for float64 round-off; FAIL: beyond, by how much). dftpcc: "
        "`compress(points, target_max_error=E)` on the DEM's pixels as points, one per cell, its rate control "
        "choosing cutoff and step and a residual layer bringing every cell within E. LERC: the float64 "
        "heights and their valid mask, maxZError E; 'LERC float32' is the same on the float32 values the "
        "GeoTIFF stores. SZ3 (pysz): float64 heights, absolute bound E. JPEG XL (libjxl effort "
        f"{JPEGXL_EFFORT}), JPEG2000 (OpenJPEG) and HTJ2K (OpenJPH), all lossless (reversible), on the "
        f"heights quantized to 16-bit integer steps of 2E (less {QUANT_MARGIN:g} of it, so that rounding "
        "stays inside E) from their minimum. Raster anchors are charged "
        f"{RASTER_HEADER_BYTES} B of grid/offset header and, but LERC, the zstd-19 occupancy bitmap, with "
        "empty cells filled from the nearest occupied one (the three DEMs here have none). E for the Moon: "
        "its heights are whole metres over 6.4 km, so an E below 0.5 m asks for the integers themselves; "
        "0.5 m (steps of 1 m keep them exactly), 1 m and 5 m. Ratios: dftpcc's bytes over the codec's "
        "(below 1: dftpcc is smaller); best anchor: the smallest that passes. Speeds: median M cells/s "
        f"encode / decode of {TIMING_REPEATS} in-memory runs, the float DEM to bytes and back (quantization "
        "included), one thread; dftpcc's encode is its whole rate-control search, from the points.",
        "",
        markdown_table(["DEM", "E", "dftpcc bytes"] + [f"{name} (dftpcc / it)" for name in anchors]
                       + ["best anchor", "dftpcc / best"], wide),
        "",
        markdown_table(["DEM", "E", "codec", "bytes", "bits/cell", "dftpcc / it", "max error mm", "≤ E",
                        "M cells/s enc / dec", "setting"], detail),
    ]
    if hand:
        out += ["", "This run against the hand measurement of ANCHORS.md (bytes, this run / then):", "",
                markdown_table(["DEM", "E", *HAND_CODECS], hand)]
    return "\n".join(out) + "\n"
