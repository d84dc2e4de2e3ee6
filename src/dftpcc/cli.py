"""Command line: a thin shell over the Python API.

Every command parses its flags, calls public functions, prints. Errors the
library raises become one line on stderr and a documented exit code
(docs/errors.md); warnings become one ``dftpcc: warning:`` line each.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import signal
import sys
import time
import traceback
import warnings
from contextlib import contextmanager
from typing import Any, Iterator, Sequence

from . import __version__
from .params import AUTO_TILE_CELLS, CHOICES, DEFAULT_TILE_SIZE, PROFILES, TILE_SIZES, check_cutoff, check_tile_size
from .units import length
from .errors import (
    CorruptFileError,
    DftpccError,
    ClusterError,
    InvalidInputError,
    MissingDependencyError,
    ResourceLimitError,
    UnsupportedFormatError,
    speaking_to_the_command_line,
)

Row = dict[str, Any]

#: Exit status per failure, most specific first (documented in docs/errors.md).
EXIT_CODES: list[tuple[type[BaseException], int]] = [
    (UnsupportedFormatError, 4),
    (InvalidInputError, 3),
    (ResourceLimitError, 8),
    (CorruptFileError, 5),
    (MissingDependencyError, 6),
    (ClusterError, 10),
    (DftpccError, 1),
    (OSError, 7),
    (MemoryError, 9),
]
EXIT_USAGE = 2
#: An exception dftpcc did not raise on purpose: a bug (EX_SOFTWARE).
EXIT_INTERNAL = 70
#: Killed by a signal: 128 + its number (SIGINT 130, SIGTERM 143), as shells report.
EXIT_SIGNAL_BASE = 128
EXIT_INTERRUPTED = EXIT_SIGNAL_BASE + signal.SIGINT
#: Signals that end a run cleanly (temporary files removed) instead of killing it.
_STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))


class _Stopped(BaseException):
    """Raised in the main thread when a stop signal arrives, so ``finally`` blocks run."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _cutoff(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    try:
        return check_cutoff(value)
    except InvalidInputError:
        raise argparse.ArgumentTypeError(f"must be in [0, 1), got {value}") from None


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def _non_negative(text: str) -> float:
    """A number, 0 (none) or more."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value >= 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be 0 or a positive number, got {text}")
    return value


def _outage(text: str) -> tuple[float, float]:
    start, _, length = text.partition(":")
    return _non_negative(start), _positive(length)


def _resolution(text: str) -> float | str:
    return "auto" if text == "auto" else _positive(text)


def _classes(text: str) -> list[int]:
    try:
        values = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated class codes, got {text!r}") from None
    if not values or any(not 0 <= v <= 255 for v in values):
        raise argparse.ArgumentTypeError(f"class codes are 0-255, got {text!r}")
    return values


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {value}")
    return value


@contextmanager
def _progress(enabled: bool, stages: Sequence[str], *, verbose: bool = False) -> Iterator:
    """A progress bar over ``stages`` (on stderr, unless disabled); with ``verbose``, each
    stage's wall time is printed on stderr when it ends."""
    from tqdm import tqdm

    bar = tqdm(total=len(stages), disable=not enabled or None, leave=False, file=sys.stderr,
               bar_format="{desc:<10} {bar} {percentage:3.0f}% [{elapsed}]")
    seen: list[tuple[str, float]] = []

    def report() -> None:
        if verbose and seen:
            name, start = seen[-1]
            bar.write(f"dftpcc: {name}: {time.perf_counter() - start:.2f} s", file=sys.stderr)

    def on_stage(name: str, done: float | None = None) -> None:
        if done is not None:  # within a long stage: move the bar by the fraction done
            bar.n = max(0, len(seen) - 1) + min(max(done, 0.0), 1.0)
            bar.refresh()
            return
        if seen:
            bar.n = len(seen)
            report()
        seen.append((name, time.perf_counter()))
        bar.set_description_str(name)

    try:
        yield on_stage
        report()
    finally:
        bar.close()


#: The stages each long command shows (a bar on a terminal; their times with -v).
RELOC_STAGES = ("read", "simulate", "encode", "relocalize")
DECODE_STAGES = ("decode", "write")
EVALUATE_STAGES = ("read", "decode", "measure")
COMPARE_STAGES = ("read", "code", "draw")
UPDATE_STAGES = ("read", "code", "write")
#: One rule for every output, files and ROS 2 bag folders alike (io.check_output, rosmap.check_bag_output).
FORCE_HELP = ("an existing output (a file, or a ROS 2 bag folder) is replaced; a write-protected one only with "
              "--force")
PROFILE_HELP = "compact (default): detrended DCT, quantized, entropy-coded; paper: the published method"
COMPRESS_STAGES = ("read", "grid", "spectrum", "encode", "container", "write")
MAP_FRAME_HELP = ("ROS bag with --pose-topic /tf: the frame to build the map in (map, odom, ...); default: the root "
                  "of the scans' TF tree")


def _say(args: argparse.Namespace, *lines: str) -> None:
    """Print unless ``--quiet``; on stderr when the output itself goes to standard output."""
    if not args.quiet:
        for line in lines:
            print(line, file=sys.stderr if getattr(args, "output", None) == "-" else sys.stdout)


def _stream(name: str, mode: str, *, binary: bool = True) -> Any:
    """``-`` as standard input (``mode='r'``) or output (``'w'``), as pdal and laszip take it; else the name.

    Binary output is refused on a terminal, as gzip refuses it: it would fill the screen with bytes.
    """
    if name != "-":
        return name
    if mode == "r":
        return sys.stdin.buffer
    if binary and sys.stdout.isatty():
        raise InvalidInputError("refusing to write binary data to a terminal: redirect standard output "
                                "(> out.dftpc) or name an output file")
    return sys.stdout.buffer


def _errors_text(stats: dict[str, Any], unit: str) -> str:
    """The errors a file promises, lengths scaled to their size."""
    text = (f"DEM RMSE {length(stats.get('dem_rmse_m'), unit)}, max {length(stats.get('dem_max_error_m'), unit)}")
    if "vertical_rmse_m" in stats:
        text += (f"; points: vertical RMSE {length(stats['vertical_rmse_m'], unit)} "
                 f"(gridding floor {length(stats.get('gridding_rmse_m'), unit)})")
    return text


def _choice_text(p: dict[str, Any], unit: str, stats: dict[str, Any]) -> str:
    """Which cutoff and step the file uses, and who chose them (``stats``: the file's, for the
    RMSE target a residual layer met)."""
    quantized = p["storage"] == "quantized"
    step = f", step {length(p['step'], unit)}" if quantized else ""
    target = _target_text(p, unit, stats)
    if target:
        chosen = ("step" if p["cutoff_given"] else "cutoff and step" if quantized else "cutoff")
        return f"cutoff {p['cutoff']:g}{step} ({chosen} chosen by rate control for {target})"
    how = ["cutoff given" if p["cutoff_given"] else "default cutoff"]
    if quantized:
        how.append("step given" if p["step_given"] else "automatic step")
    return f"cutoff {p['cutoff']:g}{step} ({', '.join(how)})"


def cmd_compress(args: argparse.Namespace) -> int:
    from .files import compress_file

    options = dict(aggregate=args.aggregate, frame=args.frame, transform=args.transform,
                   step=args.step, fill=args.fill, detrend=args.detrend, mask=args.mask, coder=args.coder,
                   target_rmse=args.target_rmse, target_max_error=args.target_max_error,
                   target_bpp=args.target_bpp, tile_size=args.tile_size)
    if args.target_reloc is not None:
        return _compress_reloc(args, options)
    if args.growable:
        return _compress_growable(args)
    t0 = time.perf_counter()
    with _progress(not args.quiet, COMPRESS_STAGES, verbose=args.verbose) as on_stage:
        cmap = compress_file(_stream(args.input, "r"), _stream(args.output, "w"), force=args.force,
                             resolution=args.resolution, cutoff=args.cutoff,
                             profile=args.profile, format=args.format, classes=args.classes,
                             drop_nonfinite=args.drop_nonfinite, chunk_points=args.chunk_points, topic=args.topic,
                             workers=args.workers, scheduler=args.scheduler,
                             pose_topic=args.pose_topic, map_frame=args.map_frame, on_stage=on_stage, **options)
    info = cmap.info()
    if args.verbose:
        print(f"dftpcc: parameters {json.dumps(info['params'], sort_keys=True)}", file=sys.stderr)
    unit = info["units"]["horizontal"]
    params = dict(info["params"], cutoff_given=args.cutoff is not None, step_given=args.step is not None)
    _say(args,
         f"{args.output}: {info['bytes']:,} bytes, {info['bits_per_point']:.4g} bits/point "
         f"({info['points_original']:,} points -> {info['points_rebuilt']:,} cells of "
         f"{length(info['grid']['resolution_m'], unit)}) [{time.perf_counter() - t0:.2f} s]",
         f"  {_choice_text(params, info['units']['vertical'], info['stats'])}",
         f"  promises {_errors_text(info['stats'], info['units']['vertical'])}",
         *_coarse_lines(info, args))
    return 0


#: A map whose largest height error exceeds this many cell sizes is called coarse in compress's summary.
COARSE_ERROR_CELLS = 2.0


def _coarse_lines(info: dict[str, Any], args: argparse.Namespace) -> list[str]:
    """A plain line when the defaults made a coarse map (errors of several cells), and what to give instead."""
    cell, worst = info["grid"]["resolution_m"], info["stats"].get("dem_max_error_m") or 0.0
    if info["units"]["geographic"] or worst <= COARSE_ERROR_CELLS * cell or _target_text(info["params"]):
        return []
    unit = info["units"]["vertical"]
    ground = " keep ground points only (--classes 2)," if str(args.input).lower().endswith((".las", ".laz")) else ""
    return [f"  coarse: heights off by up to {length(worst, unit)}, {worst / cell:.1f} cells of "
            f"{length(cell, unit)}; for a finer map{ground} give --target-max-error {cell:.3g} (errors within a "
            f"cell) or --target-rmse, or a finer --resolution"]


def _prefix_decodes(path: str) -> int | None:
    """The size of a damaged ``.dftpc`` at ``path`` when that prefix still decodes (a truncated untiled
    map: its low frequencies come first); else None."""
    from .mapfile import open as open_map

    try:
        size = os.path.getsize(path)
        with open_map(path, max_bytes=size) as cmap:
            cmap.read_dem()
        return size
    except (DftpccError, OSError, MemoryError):
        return None


@contextmanager
def _naming(path: str) -> Iterator[None]:
    """A corrupt or truncated ``.dftpc`` named in the error, with ``--max-bytes`` offered where its prefix decodes."""
    try:
        yield
    except ResourceLimitError:
        raise
    except CorruptFileError as exc:
        text = str(exc)
        if path != "-" and not text.startswith(str(path)):
            text = f"{path}: {text}"
        size = _prefix_decodes(path) if path != "-" and "truncated" in text else None
        if size is not None:
            text += f"; its first {size:,} bytes decode to a coarser map: decompress --max-bytes {size}"
        raise CorruptFileError(text) from None


def cmd_decompress(args: argparse.Namespace) -> int:
    with _naming(args.input):
        return _decompress(args)


def _decompress(args: argparse.Namespace) -> int:
    from .files import decompress_bands, decompress_file, wants_bands
    from .io.rosmap import is_bag_output

    if is_bag_output(args.output, args.format):
        return _decompress_bag(args)
    if wants_bands(args.input, args.output, format=args.format, cog=args.cog, bbox=args.bbox,
                   cutoff=args.cutoff, max_bytes=args.max_bytes):
        # A map larger than memory, or a COG: one band of rows at a time.
        with _progress(not args.quiet, ("decode",), verbose=args.verbose) as on_stage:
            count = decompress_bands(_stream(args.input, "r"), args.output, format=args.format, cog=args.cog,
                                     force=args.force,
                                     max_cells=args.max_cells, workers=args.workers, scheduler=args.scheduler,
                                     on_stage=on_stage, dtype=args.dtype, nodata=args.nodata)
        _say(args, f"{args.output}: {count:,} points, written band by band")
        return 0
    if args.topic or args.grid_map or args.local_origin is not None or args.stamp is not None:
        raise InvalidInputError(f"{args.output}: --topic, --grid-map, --local-origin and --stamp apply to a ROS 2 "
                                f"bag output, a folder: end its name with / (out_bag/) or give --format rosbag")
    text = (args.format or "").lower() in ("xyz", "csv")
    with _progress(not args.quiet, DECODE_STAGES, verbose=args.verbose) as on_stage:
        points = decompress_file(_stream(args.input, "r"), _stream(args.output, "w", binary=not text),
                                 force=args.force, format=args.format, max_bytes=args.max_bytes,
                                 cutoff=args.cutoff, max_cells=args.max_cells, bbox=args.bbox,
                                 workers=args.workers, scheduler=args.scheduler, densify=args.densify,
                                 dtype=args.dtype, nodata=args.nodata, cog=args.cog, on_stage=on_stage)
    if args.output != "-" and (str(args.output).lower().endswith((".tif", ".tiff"))
                               or args.format in ("tif", "tiff")):
        import rasterio

        with rasterio.open(args.output) as written:  # what the user gets, read back from the file
            shape, dtype, nodata = (written.height, written.width), written.dtypes[0], written.nodata
        _say(args, f"{args.output}: a {shape[0]:,} x {shape[1]:,} {dtype} raster, {points.shape[0]:,} valid "
                   f"pixels, nodata {nodata:g}")
    else:
        _say(args, f"{args.output}: {points.shape[0]:,} points")
    return 0


def _decompress_bag(args: argparse.Namespace) -> int:
    """``decompress MAP out_bag/``: the rebuilt map as a ROS 2 bag (PointCloud2, and a GridMap with --grid-map)."""
    import numpy as np

    from .io.bag import NS_PER_S
    from .io.rosmap import DEFAULT_TOPIC, FLOAT32_SAFE_M, check_bag_output, grid_map_topic, local_origin, write_map_bag
    from .mapfile import open as open_map

    if args.densify > 1 or args.dtype is not None or args.nodata is not None or args.cog:
        raise InvalidInputError(f"{args.output}: a ROS 2 bag holds one point per cell (and the GridMap); "
                                f"--densify, --dtype, --nodata and --cog apply to files")
    check_bag_output(args.output, force=args.force)  # before decoding
    with open_map(_stream(args.input, "r"), max_bytes=args.max_bytes, max_cells=args.max_cells) as cmap:
        dem = cmap.read_dem(cutoff=args.cutoff, bbox=args.bbox)
    topic = args.topic or DEFAULT_TOPIC
    origin = None if args.local_origin is None else (local_origin(dem) if args.local_origin == "auto"
                                                     else args.local_origin)
    # The map's time: when its file was written (the stamp ROS tools sort and expire messages by).
    stamp_ns = (int(args.stamp * NS_PER_S) if args.stamp is not None else
                time.time_ns() if args.input == "-" else os.stat(args.input).st_mtime_ns)
    points = write_map_bag(args.output, dem, topic=topic, grid_map=args.grid_map, force=args.force,
                           origin=origin, stamp_ns=stamp_ns)
    grid = f", GridMap {dem.grid.rows:,} x {dem.grid.cols:,} on {grid_map_topic(topic)}" if args.grid_map else ""
    wide = points.size and float(np.abs(points).max()) > FLOAT32_SAFE_M
    fields = ("FLOAT64 fields (coordinates beyond 16 km of the frame's origin; --local-origin auto gives FLOAT32)"
              if wide else "FLOAT32 fields")
    frame = (f", frame map_local at ({origin[0]:g}, {origin[1]:g}, {origin[2]:g}) of map on /tf_static"
             if origin is not None else "")
    _say(args, f"{args.output}: ROS 2 bag, {points.shape[0]:,} points on {topic}{grid}; {fields}{frame}; stamp "
               f"{stamp_ns / NS_PER_S:.3f} s")
    return 0


def _target_text(p: dict, unit: str = "m", stats: dict | None = None) -> str:
    """The rate-control target of parameters ``p``, or '' when there is none. An RMSE target met by a
    residual layer is in the file's ``stats`` (``target_rmse_m``; its parameters state the layer's bound)."""
    asked = (stats or {}).get("target_rmse_m") or 0
    if asked > 0 and (p.get("target_max_error") or 0) > 0:
        return (f"DEM RMSE <= {length(asked, unit)}, met by a residual layer of max error "
                f"<= {length(p['target_max_error'], unit)}")
    if (p.get("target_rmse") or 0) > 0:
        return f"DEM RMSE <= {length(p['target_rmse'], unit)}"
    if (p.get("target_max_error") or 0) > 0:
        return f"max error <= {length(p['target_max_error'], unit)}"
    if (p.get("target_bpp") or 0) > 0:
        return f"<= {p['target_bpp']:g} bits/point"
    return ""


def _coordinate(value: float, unit: str) -> str:
    """A coordinate to about a millimetre (a millionth of a degree on a geographic grid)."""
    return f"{value:.6f}°" if unit == "°" else f"{value:,.3f} {unit}"


#: How ``dftpcc info`` describes a residual layer's layout (docs/format.md, ``RESD``).
RESIDUAL_LAYOUTS = {"chunks": "chunks", "sparse": "sparse: the cells that need a correction",
                    "predicted": "predicted from decoded neighbours"}


def cmd_info(args: argparse.Namespace) -> int:
    from .mapfile import open as open_map

    truncated = ""
    try:
        with _naming(args.input), open_map(_stream(args.input, "r"), max_cells=args.max_cells) as cmap:
            info = cmap.info()
    except CorruptFileError as exc:
        # The header of a truncated file may still be whole: show it, and what is missing.
        size = _prefix_decodes(args.input) if args.input != "-" and "truncated" in str(exc) else None
        if size is None:
            raise
        with open_map(args.input, max_cells=args.max_cells, max_bytes=size) as cmap:
            info = cmap.info()
        truncated = str(exc)
    # The header was read and checked: the exit status says whether the whole file is valid.
    damaged = dict(EXIT_CODES)[CorruptFileError] if truncated else 0
    if truncated:
        print(f"dftpcc: error: {truncated}", file=sys.stderr)
    if args.quiet:
        return damaged
    if args.json:
        print(json.dumps(dict(info, damaged=truncated) if truncated else info, indent=2, sort_keys=True))
        return damaged
    g, p, s, u = info["grid"], info["params"], info["stats"], info["units"]
    h, v = u["horizontal"], u["vertical"]
    cells = f"{length(g['resolution_m'], h)}"
    if g.get("resolution_y_m"):
        cells = f"{length(g['resolution_m'], h)} x {length(g['resolution_y_m'], h)}"
    if u["geographic"]:
        cells += " of longitude x latitude"
    target = _target_text(p, v, s)
    rows = [
        ("file", f"{info['file']} ({info['bytes']:,} bytes, format {info['format_version']})"),
        ("points", f"{info['points_original']:,} original, {info['points_rebuilt']:,} rebuilt"),
        ("bits/point", f"{info['bits_per_point']:.4g}"),
        ("grid", f"{g['rows']:,} x {g['cols']:,} cells of {cells}, angle {g['angle_rad']:.4g} rad"),
        ("origin", f"x {_coordinate(g['origin'][0], h)}, y {_coordinate(g['origin'][1], h)}; "
                   f"heights about z0 {g['z0_m']:,.3f} {v}"),
        ("profile", f"{p['profile']} (transform {p['transform']}, storage {p['storage']}, "
                    f"detrend {p['detrend']}, fill {p['fill']})"),
        ("cutoff", "no spectrum (residual layer only)" if not info["coefficients"] or info.get("spectrum_empty") else
                   f"{p['cutoff']:g}" + (f", step {length(p['step'], v)}" if p["storage"] == "quantized" else "")),
        ("target", f"{target} (cutoff and step chosen by rate control)" if target else "none (cutoff and step as given)"),
        ("errors", _errors_text(s, v)),
        ("sections", f"mask {s.get('mask_bytes'):,} B, coefficients {s.get('coef_bytes'):,} B "
                     f"({info['coefficients']:,} values{', all 0' if info.get('spectrum_empty') else ''})"
                     + (f", residual {s['residual_bytes']:,} B" if s.get("residual_bytes") else "")
                     + (f" ({RESIDUAL_LAYOUTS[info['residual_layout']]})" if "residual_layout" in info else "")),
        ("CRS", u["crs"] or "none"),
    ]
    if "source_dtype" in s:
        from .dem import RasterSource

        source = RasterSource.from_stats(s)
        if source is not None:
            rows.append(("source", f"{source.dtype} raster" + (f", nodata {source.nodata:g}" if source.nodata is not None
                                                              else ", no nodata value")))
    if "tiles" in info:
        t = info["tiles"]
        per = [x["bytes"] for x in t["tiles"]]
        rows.append(("tiles", f"{t['tile_rows']} x {t['tile_cols']} tiles of {t['size']} cells, {t['occupied']} "
                              f"occupied; {min(per):,} to {max(per):,} B a tile (--json lists each, with its errors)"))
    if truncated:
        rows.append(("damaged", truncated))
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")
    return damaged


def _reloc_params(args: argparse.Namespace, options: dict[str, Any]) -> Any:
    from .params import make_params

    fields = {k: v for k, v in options.items() if v is not None}
    return make_params(resolution=args.resolution, cutoff=args.cutoff, profile=args.profile, **fields)


def _reloc_lines(chosen: Any, target: float) -> list[str]:
    p = chosen.params
    return [f"  cutoff {p.cutoff:g}, step {p.step:g} m: {chosen.bits_per_point:.4g} bits/point; "
            f"{100 * chosen.success:.0f} % of simulated scans relocalized within {target:g} m and 1 deg "
            f"(95th percentile {chosen.p95_m:.3g} m)",
            "  tried (smallest file first): " + ", ".join(
                f"f_c {r['cutoff']:g} {r['bits_per_point']:.3g} b/pt {100 * r['success']:.0f} %" for r in chosen.tried)]


def _compress_reloc(args: argparse.Namespace, options: dict[str, Any]) -> int:
    """compress --target-reloc: the smallest file that still relocalizes simulated scans (slam extra)."""
    from .experiments.relocalize import compress_file_reloc

    if (args.output == "-" or args.input == "-" or args.chunk_points or args.drop_nonfinite or args.workers
            or args.scheduler):
        raise InvalidInputError("--target-reloc reads and writes whole files on this machine (no '-', "
                                "--chunk-points, --drop-nonfinite, --workers or --scheduler)")
    if args.map_frame is not None:
        raise InvalidInputError("--target-reloc places a bag's scans in the root of their TF tree: it does not "
                                "take --map-frame")
    t0 = time.perf_counter()
    with _progress(not args.quiet, RELOC_STAGES, verbose=args.verbose) as on_stage:
        chosen = compress_file_reloc(args.input, args.output, args.target_reloc, _reloc_params(args, options),
                                     force=args.force, format=args.format, classes=args.classes, topic=args.topic,
                                     pose_topic=args.pose_topic, scans=args.reloc_scans, seed=args.reloc_seed,
                                     on_stage=on_stage)
    _say(args, f"{args.output}: {len(chosen.data):,} bytes [{time.perf_counter() - t0:.2f} s]",
         *_reloc_lines(chosen, args.target_reloc))
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    from .viewer import serve

    return serve(args.input, port=args.port, original=args.original, follow=args.follow, max_cells=args.max_cells,
                 on_ready=lambda url: print(f"dftpcc view: {url} (Ctrl-C stops)", flush=True))


def cmd_recommend(args: argparse.Namespace) -> int:
    from .experiments.relocalize import recommend_file

    with _progress(not args.quiet, RELOC_STAGES, verbose=args.verbose) as on_stage:
        chosen = recommend_file(args.input, args.target_reloc, _reloc_params(args, {"fill": args.fill}),
                                format=args.format, classes=args.classes, topic=args.topic,
                                pose_topic=args.pose_topic, scans=args.reloc_scans, seed=args.reloc_seed,
                                on_stage=on_stage)
    if args.json:
        print(json.dumps({"params": json.loads(chosen.params.to_json()) | chosen.notes, "bytes": len(chosen.data),
                          "bits_per_point": chosen.bits_per_point, "success": chosen.success,
                          "p95_m": chosen.p95_m, "tried": chosen.tried}, indent=2, sort_keys=True))
        return 0
    _say(args, f"{args.input}: for relocalization within {args.target_reloc:g} m",
         *_reloc_lines(chosen, args.target_reloc),
         f"  make it with: dftpcc compress {args.input} OUT.dftpc --cutoff {chosen.params.cutoff:g}"
         + (f" --resolution {args.resolution}" if args.resolution != "auto" else ""))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from .experiments.demo import run_demo

    run_demo(n_points=args.points, resolution=args.resolution, out=args.out, seed=args.seed,
             show=(lambda _line: None) if args.quiet else print)
    return 0


# -- growing maps: update and patch ---------------------------------------------------------------


def _compress_growable(args: argparse.Namespace) -> int:
    """``compress --growable``: the map written as a growing map with its state, so ``update`` can grow it."""
    from .growing import update_file

    fixed = {"--target-rmse": args.target_rmse, "--target-max-error": args.target_max_error,
             "--target-bpp": args.target_bpp, "--profile": None if args.profile == "compact" else args.profile,
             "--aggregate": args.aggregate, "--coder": args.coder, "--transform": args.transform,
             "--detrend": args.detrend, "--fill": args.fill, "--mask": args.mask, "--frame": args.frame,
             "--workers": args.workers, "--scheduler": args.scheduler, "--classes": args.classes,
             "--chunk-points": args.chunk_points}
    given = [flag for flag, value in fixed.items() if value is not None]
    if given:
        raise InvalidInputError(f"--growable writes a growing map (tiles at a fixed cutoff and step, no plane): it "
                                f"takes no {', '.join(given)}")
    if not isinstance(args.resolution, float):
        raise InvalidInputError("--growable needs a cell size: give --resolution R (metres)")
    if args.input == "-" or args.output == "-":
        raise InvalidInputError("--growable writes a map and its state beside it: give file names, not '-'")
    tile = args.tile_size if isinstance(args.tile_size, int) and args.tile_size else None
    result = update_file(args.output, [args.input], new=True, resolution=args.resolution, tile_size=tile,
                         cutoff=args.cutoff, step=args.step, force=args.force, points_topic=args.topic,
                         pose_topic=args.pose_topic or "/odom", map_frame=args.map_frame)
    _say(args, f"{result.path}: {result.size:,} bytes, {result.points:,} points in {result.tiles} tiles, a growing "
               f"map ('dftpcc update {result.path} SCANS' adds to it; its state: {result.path}.state)")
    return 0


def cmd_update(args: argparse.Namespace) -> int:
    from .growing import update_file

    with _progress(not args.quiet, UPDATE_STAGES, verbose=args.verbose) as on_stage:
        result = update_file(args.map, args.input, output=args.output, delta=args.delta, points_topic=args.topic,
                             pose_topic=args.pose_topic, resolution=args.resolution, tile_size=args.tile_size,
                             cutoff=args.cutoff, step=args.step, force=args.force, map_frame=args.map_frame,
                             target_max_error=args.target_max_error,
                             waiting=lambda lock: _say(args, f"{args.map}: another update holds {lock}; waiting for it"),
                             on_stage=on_stage)
    delta = f"; delta {args.delta}: {result.delta_size:,} bytes" if result.delta_size is not None else ""
    if result.repeated:
        _say(args, f"{result.path}: {result.size:,} bytes, {result.tiles} tiles: its last update added these "
                   f"{result.scans} scan(s) already; nothing added again{delta}")
        return 0
    _say(args, f"{result.path}: {result.size:,} bytes, {result.tiles} tiles ({result.recoded} coded again) "
               f"{'started' if result.created else 'updated'} with {result.scans} scan(s), "
               f"{result.points:,} points{delta}")
    return 0


def cmd_patch(args: argparse.Namespace) -> int:
    from .delta import patch_file

    size = patch_file(args.map, args.delta, output=args.output, force=args.force)
    _say(args, f"{args.output or args.map}: {size:,} bytes")
    return 0


def _add_growing_parsers(sub: Any, common: argparse.ArgumentParser) -> None:
    """``update`` and ``patch``: a map grown scan by scan, and the deltas a rover sends of it."""
    p = sub.add_parser("update", parents=[common], help="add scans to a growing map, re-coding only the tiles they change",
                       description="Add scans to a growing map (MAP and its state MAP.state), in place unless -o. "
                                   "Only the tiles the scans change are coded again; the others keep their bytes. "
                                   "A MAP that does not exist is started (give --resolution). Two updates of "
                                   "one map at once do not lose a scan: the second waits for the first (a lock "
                                   "on MAP.lock, released when the first ends or dies), then adds its scans to "
                                   "the map the first wrote. An output (-o, --delta) that is an input, the map or "
                                   "its state, even through a link, is refused before anything is written. The delta, "
                                   "state and map are written together, so an update that was killed can be run "
                                   "again as it was: it finishes the update, and scans that were the map's last "
                                   "update are not added twice.")
    p.add_argument("map", help="the growing map (.dftpc, with MAP.state beside it)")
    p.add_argument("input", nargs="+", help="scans: ROS bags (placed by --pose-topic) or point files in the map frame")
    p.add_argument("--output", "-o", help="write the new map (and its state) here instead of in place")
    p.add_argument("--delta", metavar="FILE", help="also write the delta from the old map to the new one")
    p.add_argument("--topic", "--points-topic", dest="topic",
                   help="ROS bag: the sensor_msgs/PointCloud2 topic (default: the only one)")
    p.add_argument("--pose-topic", metavar="TOPIC", default="/odom",
                   help="ROS bag: the poses of the scans' frame (default /odom), or /tf: the TF tree with "
                        "/tf_static, composed from the scans' frame up")
    p.add_argument("--map-frame", metavar="FRAME", help=MAP_FRAME_HELP)
    p.add_argument("--resolution", "-r", type=_positive, help="cell size in metres (a new map; else must be the map's)")
    p.add_argument("--tile-size", type=_positive_int, metavar="CELLS", help="tile side of a new map (default 256)")
    p.add_argument("--cutoff", "-c", type=_cutoff, help="cutoff ratio of a new map (default 0.8)")
    p.add_argument("--step", type=_positive, help="quantizer step of a new map in metres (default 0.01)")
    p.add_argument("--target-max-error", type=_non_negative, metavar="METRES",
                   help="largest error of any occupied cell from this update on (0: none; default: the map's): "
                        "every tile coded keeps a residual layer within it; a bound other than the map's codes "
                        "every tile again")
    p.add_argument("--force", "-f", action="store_true", help=FORCE_HELP)
    p.set_defaults(func=cmd_update)

    p = sub.add_parser("patch", parents=[common], help="apply a delta of 'dftpcc update' to the map it was made from",
                       description="Rebuild, byte for byte, the map a delta gives from the map it was made from; "
                                   "another map, a delta applied twice or out of order is refused.")
    p.add_argument("map", help="the map the delta was made from")
    p.add_argument("delta", help="the delta file (dftpcc update --delta)")
    p.add_argument("--output", "-o", help="write the new map here instead of in place")
    p.add_argument("--force", "-f", action="store_true", help=FORCE_HELP)
    p.set_defaults(func=cmd_patch)


def cmd_ros_rover(args: argparse.Namespace) -> int:
    from .ros2 import run_rover

    if (args.odom is None) == (args.pose is None) and not args.in_map_frame:
        raise InvalidInputError("give the scans' poses: --odom TOPIC (nav_msgs/Odometry) or --pose TOPIC "
                                "(geometry_msgs/PoseStamped), or --in-map-frame for scans placed already")
    return run_rover(map_path=args.map, points_topic=args.points, odom_topic=args.odom, pose_topic=args.pose,
                     resolution=args.resolution, rate=args.budget, max_frame_bytes=args.max_frame_bytes,
                     cutoff=args.cutoff, step=args.step, target_max_error=args.target_max_error,
                     map_frame=args.map_frame, in_map_frame=args.in_map_frame,
                     version_every=args.version_every, save_every=args.save_every,
                     loss=args.loss, seed=args.seed, outage=args.outage,
                     duration=args.duration, say=(lambda _l: None) if args.quiet else print)


def cmd_ros_ground(args: argparse.Namespace) -> int:
    from .ros2 import run_ground

    return run_ground(map_path=args.map, frame_id=args.frame_id, max_frame_bytes=args.max_frame_bytes,
                      new_maps=args.new_maps, loss=args.loss, seed=args.seed, duration=args.duration,
                      outage=args.outage,
                      say=(lambda _l: None) if args.quiet else print)


def _add_ros_parsers(sub: Any, common: argparse.ArgumentParser) -> None:
    """``ros rover`` and ``ros ground``: the link's two ends as ROS 2 nodes (the ros2 extra)."""
    ros = sub.add_parser("ros", help="ROS 2 nodes: a rover that grows and sends the map, a ground that rebuilds it",
                         description="The rover-ground link as ROS 2 nodes (pip install 'dftpcc[ros2]').")
    nodes = ros.add_subparsers(dest="node", metavar="NODE")
    nodes.required = True
    test_flags = argparse.ArgumentParser(add_help=False)
    test_flags.add_argument("--loss", type=float, default=0.0,
                            help="drop this share of incoming link frames at random (a bad link, for tests)")
    test_flags.add_argument("--seed", type=int, default=0, help="seed of --loss")
    test_flags.add_argument("--duration", type=_positive, help="stop after this many seconds (default: run on)")
    test_flags.add_argument("--outage", type=_outage, metavar="START:SECONDS",
                            help="drop every incoming link frame for SECONDS from START seconds after the node "
                                 "starts (a link down, for tests and benchmarks)")
    p = nodes.add_parser("rover", parents=[common, test_flags], help="grow the map from scans and send it within a budget",
                         description="Subscribe to sensor_msgs/PointCloud2 scans and their poses, grow the map "
                                     "(kept current in MAP), and publish link frames on /dftpcc/downlink within "
                                     "--budget bytes per second (averaged over 10 s); acknowledgements on /dftpcc/ack.")
    p.add_argument("--points", default="/points", help="the PointCloud2 topic (default /points)")
    p.add_argument("--odom", metavar="TOPIC", help="nav_msgs/Odometry of the scans' frame in the map frame")
    p.add_argument("--pose", metavar="TOPIC", help="geometry_msgs/PoseStamped of the scans' frame, instead of --odom")
    p.add_argument("--in-map-frame", action="store_true", help="scans come in --map-frame already: no poses")
    p.add_argument("--map-frame", default="map", help="frame id of scans placed already (default map)")
    p.add_argument("--resolution", "-r", type=_positive, required=True, help="cell size of a new map, metres")
    p.add_argument("--map", required=True, help="the growing map (.dftpc), resumed if it exists")
    p.add_argument("--budget", type=_positive, required=True, help="downlink bytes per second")
    p.add_argument("--max-frame-bytes", type=_positive_int, default=1000, help="longest frame, bytes (default 1000)")
    p.add_argument("--cutoff", "-c", type=_cutoff, default=0.8, help="cutoff ratio of a new map (default 0.8)")
    p.add_argument("--step", type=_positive, default=0.01, help="quantizer step of a new map, metres (default 0.01)")
    p.add_argument("--target-max-error", type=_non_negative, metavar="METRES",
                   help="largest error of any occupied cell of every version (0: none; default: the map's own, "
                        "none for a new map): each tile coded keeps a residual layer within it")
    p.add_argument("--version-every", type=float, default=1.0, metavar="SECONDS",
                   help="seconds between two versions of the map (encoded and sent); 0: every scan (default 1)")
    p.add_argument("--save-every", type=float, default=10.0, metavar="SECONDS",
                   help="seconds between two writes of the map and its state, and when the node stops; 0: every "
                        "version (default 10: the state holds 20 bytes a cell)")
    p.set_defaults(func=cmd_ros_rover)
    p = nodes.add_parser("ground", parents=[common, test_flags], help="rebuild the map from the rover's frames",
                         description="Apply the rover's frames to MAP (atomically; byte for byte the rover's at each "
                                     "version), publish its points on /dftpcc/map (transient local) and "
                                     "acknowledgements on /dftpcc/ack.")
    p.add_argument("--map", required=True, help="the ground's map (.dftpc), resumed if it exists")
    p.add_argument("--frame-id", default="map", help="frame id of the published points (default map)")
    p.add_argument("--max-frame-bytes", type=_positive_int, help="refuse longer frames (default: any)")
    p.add_argument("--new-maps", choices=("refuse", "archive"), default="refuse",
                   help="frames of another map id (a rover started a new mission): refuse them (default, one "
                        "logged line), or archive: keep the map held as MAP's stem.<old map id>.dftpc and take the "
                        "new map once a whole version of it verifies")
    p.set_defaults(func=cmd_ros_ground)


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage mistake is one line like every other error."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(EXIT_USAGE, f"dftpcc: error: {message} (see '{self.prog} --help')\n")


def _add_cluster_flags(p: argparse.ArgumentParser, verb: str) -> None:
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=_positive_int, metavar="N",
                       help=f"{verb} a tiled map's tiles on a local dask cluster of N processes (dftpcc[dask])")
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help=f"{verb} a tiled map's tiles on the running dask scheduler at ADDRESS (tcp://host:8786)")


def _bbox(text: str) -> tuple[float, float, float, float]:
    """XMIN,YMIN,XMAX,YMAX as four finite numbers (their order is the library's to check, against the map)."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected four numbers XMIN,YMIN,XMAX,YMAX, got {text!r}")
    return values  # type: ignore[return-value]


def _origin(text: str) -> str | tuple[float, float, float]:
    if text == "auto":
        return text
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected 'auto' or three numbers X,Y,Z, got {text!r}")
    return values  # type: ignore[return-value]


def _nodata(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None


def _tile_size(text: str) -> int | str:
    if text == "auto":
        return text
    try:
        value = int(text)
        check_tile_size(value)
    except (ValueError, InvalidInputError):
        raise argparse.ArgumentTypeError(f"expected 'auto', 0 or a whole number of cells from {TILE_SIZES[0]} "
                                         f"to {TILE_SIZES[1]}, got {text!r}") from None
    return value


def _cutoffs(text: str) -> tuple[float, ...]:
    try:
        return parse_cutoffs(text)
    except InvalidInputError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _resolutions(text: str) -> list[float | str]:
    return [_resolution(t.strip()) for t in text.split(",") if t.strip()]


def cmd_evaluate(args: argparse.Namespace) -> int:
    from .experiments.evaluate import evaluate_files

    with _progress(not args.quiet, EVALUATE_STAGES, verbose=args.verbose) as on_stage:
        result = evaluate_files(args.original, args.candidate, classes=args.classes, max_cells=args.max_cells,
                                on_stage=on_stage)
    _say(args, json.dumps(jsonable(result), indent=2, sort_keys=True) if args.json else format_metrics(result))
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    from .experiments.sweep import run_sweep, terrains

    inputs = terrains(args.input, args.resolution, classes=args.classes)
    show = (lambda row: None) if args.quiet else (lambda row: print(format_row(row), flush=True))
    rows, csv_path, png_path = run_sweep(inputs, out=args.out, cutoffs=args.cutoffs, profile=args.profile,
                                         on_row=show)
    if not args.quiet:
        print(f"{len(rows)} rows -> {csv_path}, {png_path}")
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    from .experiments.compare import compare_file

    with _progress(not args.quiet, COMPARE_STAGES, verbose=args.verbose) as on_stage:
        path = compare_file(args.original, out=args.out, cutoffs=args.cutoffs, resolution=args.resolution,
                            profile=args.profile, classes=args.classes, on_stage=on_stage)
    _say(args, str(path))
    return 0


#: Cutoffs closer than this are the same cutoff (parsing "0,0.1,...,0.9").
CUTOFF_TOLERANCE = 1e-9


def parse_cutoffs(text: str) -> tuple[float, ...]:
    """Cutoff ratios from ``"0,0.5,0.8"``; ``"0,0.1,...,0.9"`` expands the progression.

    An item ``...`` continues the arithmetic progression of the two values
    before it up to the value after it (which is included).

    Returns
    -------
    tuple of float
        Sorted, unique, each in [0, 1).

    Raises
    ------
    InvalidInputError
        Not numbers, a value outside [0, 1), or a ``...`` without two values
        before it and one after it.
    """
    items = [t.strip() for t in text.split(",") if t.strip()]
    values: list[float] = []
    i = 0
    while i < len(items):
        item = items[i]
        if item in ("...", "\u2026"):
            if len(values) < 2 or i + 1 >= len(items):
                raise InvalidInputError(f"'...' needs two cutoffs before it and one after: {text!r}")
            step = values[-1] - values[-2]
            stop = _cutoff_value(items[i + 1], text)
            if step <= 0:
                raise InvalidInputError(f"'...' needs increasing cutoffs before it: {text!r}")
            count = int(math.floor((stop - values[-1]) / step + CUTOFF_TOLERANCE))
            start = values[-1]
            values.extend(round(start + step * k, 10) for k in range(1, count + 1))
            i += 1
            continue
        values.append(_cutoff_value(item, text))
        i += 1
    if not values:
        raise InvalidInputError("no cutoff given")
    unique: list[float] = []
    for v in sorted(values):
        if not unique or v - unique[-1] > CUTOFF_TOLERANCE:
            unique.append(v)
    return tuple(unique)


def _cutoff_value(item: str, text: str) -> float:
    try:
        value = float(item)
    except ValueError:
        raise InvalidInputError(f"cutoffs must be numbers separated by commas, got {text!r}") from None
    if not 0.0 <= value < 1.0:
        raise InvalidInputError(f"a cutoff ratio is in [0, 1), got {value}")
    return value


def format_row(row: Row) -> str:
    """One line of progress for a sweep row."""
    return (f"{row['terrain']:<24} f_c {row['cutoff']:<5g} {row['bytes']:>11,} B "
            f"{row['bits_per_point']:>9.4f} bits/pt  RMSE {row['paper_rmse_m']:.4f} m  "
            f"D1 {row['d1_rmse_m']:.4f} m  [{row['encode_s'] + row['decode_s'] + row['metrics_s']:.2f} s]")


#: How :func:`format_metrics` shows each metric: label, unit, scale.
_TABLE = (
    ("points_original", "original points", "", None),
    ("points_rebuilt", "rebuilt points", "", None),
    ("points_in_header", "points the file was made from", "", None),
    ("bytes", "compressed size", "bytes", None),
    ("bits_per_point", "bits per point", "bits", ".4f"),
    ("paper_rmse_m", "paper RMSE (own cell, vertical)", "m", ".4f"),
    ("paper_rmse_3d_m", "paper RMSE (own cell, 3D)", "m", ".4f"),
    ("vertical_rmse_m", "vertical error RMSE", "m", ".4f"),
    ("vertical_p95_m", "vertical error 95th percentile", "m", ".4f"),
    ("vertical_max_m", "vertical error max", "m", ".4f"),
    ("d1_rmse_m", "D1 point-to-point RMSE (symmetric)", "m", ".4f"),
    ("d1_rmse_forward_m", "  original -> rebuilt", "m", ".4f"),
    ("d1_rmse_backward_m", "  rebuilt -> original", "m", ".4f"),
    ("d1_psnr_db", "D1 PSNR", "dB", ".2f"),
    ("psnr_peak_m", "  PSNR peak (bounding-box diagonal)", "m", ".3f"),
    ("chamfer_m", "Chamfer distance", "m", ".4f"),
    ("hausdorff_m", "Hausdorff distance", "m", ".4f"),
)


def format_metrics(result: Row) -> str:
    """The result of :func:`evaluate_files` as an aligned table, one metric a line."""
    lines = []
    width = max(len(label) for _, label, _, _ in _TABLE)
    for key, label, unit, fmt in _TABLE:
        if key not in result:
            continue
        value = result[key]
        text = f"{value:,}" if fmt is None else format(value, fmt)
        lines.append(f"{label:<{width}}  {text:>14} {unit}".rstrip())
    if "note" in result:
        lines.append(f"note: {result['note']}")
    return "\n".join(lines)


def jsonable(result: Row) -> Row:
    """A copy with non-finite numbers (an infinite PSNR) as None, for strict JSON."""
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in result.items()}


def _common_flags() -> argparse.ArgumentParser:
    """Flags every command takes."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--quiet", "-q", action="store_true", help="print nothing but errors (no progress or summary)")
    common.add_argument("--verbose", "-v", action="store_true",
                        help="also print the parameters used and the time of each stage on stderr")
    common.add_argument("--no-warnings", action="store_true",
                        help="do not print warnings (a result that is valid but may not be what you expect)")
    return common


def build_parser() -> argparse.ArgumentParser:
    common = _common_flags()
    parser = _Parser(
        prog="dftpcc",
        description="Compress terrain point cloud maps by low-pass filtering the DFT of their DEM.")
    parser.add_argument("--version", action="version", version=f"dftpcc {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    p = sub.add_parser("compress", parents=[common], help="point cloud -> .dftpc", description=(
        "Grid a point cloud into a DEM, low-pass its spectrum and write a .dftpc file. "
        "Inputs: .las .laz .ply .pcd .xyz .txt .csv .npy .drc .tif, and ROS bags (.bag, or a ROS 2 bag folder)"))
    p.add_argument("input", help="the point cloud or GeoTIFF DEM to compress ('-': standard input, with --format; "
                                 "a URL (https://, s3://...): a GeoTIFF, LAS or LAZ is read by range requests, "
                                 "another format downloaded first)")
    p.add_argument("output", help="the .dftpc file to write ('-': standard output)")
    p.add_argument("--force", "-f", action="store_true",
                   help=FORCE_HELP + "; also write under another format's extension")
    p.add_argument("--resolution", "-r", type=_resolution, default="auto",
                   help="DEM cell size in metres, or 'auto' (default: about 4 points per cell; "
                        "a GeoTIFF keeps its own pixels)")
    p.add_argument("--cutoff", "-c", type=_cutoff,
                   help="cutoff ratio f_c = 1 - r/r_M in [0, 1) (default 0.8; with a --target-*, chosen for you)")
    target = p.add_mutually_exclusive_group()
    target.add_argument("--target-rmse", type=_positive, metavar="METRES",
                        help="smallest file whose rebuilt DEM is within this RMSE of the gridded one")
    target.add_argument("--target-max-error", type=_positive, metavar="METRES",
                        help="every occupied cell within this error (adds a residual layer)")
    target.add_argument("--target-bpp", type=_positive, metavar="BITS",
                        help="most accurate file of at most this many bits per original point")
    target.add_argument("--target-reloc", type=_positive, metavar="METRES",
                        help="smallest file whose rebuilt map still relocalizes lidar scans simulated on the map "
                             "within this error (GICP; needs dftpcc[slam]; see docs/relocalization.md)")
    p.add_argument("--reloc-scans", type=_positive_int, default=20, metavar="N",
                   help="--target-reloc: scans to simulate (default 20)")
    p.add_argument("--reloc-seed", type=int, default=0, metavar="SEED", help="--target-reloc: seed of the scans")
    p.add_argument("--profile", choices=tuple(PROFILES), default="compact", help=PROFILE_HELP)
    p.add_argument("--classes", type=_classes, help="LAS/LAZ: keep only these classification codes, e.g. 2 for ground")
    p.add_argument("--aggregate", choices=CHOICES["aggregate"], help="cell height from its points (default mean)")
    p.add_argument("--frame", choices=CHOICES["frame"], help="axis-aligned or minimum-area rotated grid (default axis)")
    p.add_argument("--transform", choices=CHOICES["transform"], help="override the profile's transform")
    p.add_argument("--detrend", choices=CHOICES["detrend"], help="override the profile's detrending")
    p.add_argument("--fill", choices=CHOICES["fill"],
                   help="how empty cells are filled before the transform (compact default: consistent)")
    p.add_argument("--step", type=_positive, help="quantizer step in metres (default: automatic)")
    p.add_argument("--mask", choices=CHOICES["mask"],
                   help="exact (default): rebuild occupied cells only; footprint: also the gaps the map encloses")
    p.add_argument("--coder", choices=CHOICES["coder"], help="entropy coder of the coefficients (default ans)")
    p.add_argument("--tile-size", type=_tile_size, metavar="CELLS",
                   help=f"code the map in tiles of CELLS x CELLS that decode on their own (--bbox); 0: whole; "
                        f"default auto: tiles of {DEFAULT_TILE_SIZE} only for grids over {AUTO_TILE_CELLS:,} cells")
    p.add_argument("--growable", action="store_true",
                   help="write a growing map with its state (MAP.state) beside it, so 'dftpcc update' can add scans "
                        "to it: tiles (default 256) at a fixed --cutoff (default 0.8) and --step (default 0.01 m), no "
                        "plane and no rate control, so larger than a compressed map (docs/guide.md); needs --resolution")
    p.add_argument("--drop-nonfinite", action="store_true",
                   help="drop points with NaN or infinite coordinates instead of refusing the file")
    p.add_argument("--topic", "--points-topic", dest="topic",
                   help="ROS bag: the sensor_msgs/PointCloud2 topic to read (default: the only one)")
    p.add_argument("--pose-topic", metavar="TOPIC",
                   help="ROS bag of scans in the sensor frame: the topic of their poses (nav_msgs/Odometry, "
                        "geometry_msgs/PoseStamped or /tf), interpolated at each scan's stamp; the map is "
                        "built in the poses' frame. /tf is read with /tf_static as a tree (map -> odom -> "
                        "base_link -> sensor), each scan placed by the transforms from its frame up, composed "
                        "at its stamp")
    p.add_argument("--map-frame", metavar="FRAME", help=MAP_FRAME_HELP)
    p.add_argument("--chunk-points", type=_positive_int, metavar="N",
                   help="read LAS/LAZ/PLY/NPY N points at a time, so memory holds the grid and one chunk "
                        "(automatic when the cloud would not fit in half the available memory)")
    p.add_argument("--format", help="input format if the extension does not tell")
    _add_cluster_flags(p, "code")
    p.set_defaults(func=cmd_compress)

    p = sub.add_parser("decompress", parents=[common], help=".dftpc -> point cloud or GeoTIFF DEM", description=(
        "Rebuild the map. Output format from the extension: .las .laz .ply .pcd .xyz .txt .csv .npy, "
        "or .tif for the rebuilt DEM; a name ending in / (out_bag/) writes a ROS 2 bag."))
    p.add_argument("input", help="the .dftpc file to decode ('-': standard input)")
    p.add_argument("output", help="the point cloud or GeoTIFF (.tif) file to write ('-': standard output, with --format)")
    p.add_argument("--force", "-f", action="store_true", help=FORCE_HELP)
    p.add_argument("--max-bytes", type=_positive_int, help="decode only the first N bytes (a coarser map)")
    p.add_argument("--cutoff", type=_cutoff, help="decode at a larger cutoff than the file's")
    p.add_argument("--densify", type=_positive_int, default=1, metavar="K",
                   help="K x K samples of the rebuilt surface per cell instead of one point: a denser map "
                        "for scan registration (docs/relocalization.md)")
    p.add_argument("--cog", action="store_true",
                   help="write the DEM as a Cloud Optimized GeoTIFF (.tif), band by band")
    p.add_argument("--dtype", choices=("int8", "uint8", "int16", "uint16", "int32", "uint32", "float32", "float64"),
                   help="GeoTIFF output: sample type (default: the source raster's where the file's error bound "
                        "rounds back to its values, else float32; an integer type rounds the heights)")
    p.add_argument("--nodata", type=_nodata, metavar="VALUE",
                   help="GeoTIFF output: value of empty cells (default: the source raster's, else NaN)")
    p.add_argument("--bbox", type=_bbox, metavar="XMIN,YMIN,XMAX,YMAX",
                   help="only this region, in the map's units and CRS (of a tiled map, only its tiles are read)")
    p.add_argument("--max-cells", type=_positive_int, metavar="N",
                   help="decode a trusted file whose grid is larger than a file of its size may ask for")
    p.add_argument("--topic", help="ROS 2 bag output (a folder: out_bag/, or --format rosbag): the "
                                   "sensor_msgs/PointCloud2 topic of the map (default /map)")
    p.add_argument("--local-origin", type=_origin, metavar="auto|X,Y,Z",
                   help="ROS 2 bag output: the map in a frame map_local about this point (auto: the map's middle, "
                        "whole metres), placed by a /tf_static transform, so FLOAT32 fields (PCL's PointXYZ, RViz) "
                        "keep a millimetre; default: the map's own frame, FLOAT64 beyond 16 km")
    p.add_argument("--stamp", type=float, metavar="SECONDS",
                   help="ROS 2 bag output: the messages' stamp, seconds since 1970 (default: when the .dftpc "
                        "was written)")
    p.add_argument("--grid-map", action="store_true",
                   help="ROS 2 bag output: also the DEM as a grid_map_msgs/GridMap elevation layer on TOPIC/grid_map")
    p.add_argument("--format", help="output format if the extension does not tell")
    _add_cluster_flags(p, "decode")
    p.set_defaults(func=cmd_decompress)

    p = sub.add_parser("info", parents=[common], help="header, parameters and sizes, without decoding",
                       description="Show how a .dftpc file was made, what it holds and the errors it promises, "
                                   "without decoding its map.")
    p.add_argument("input", help="the .dftpc file")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--max-cells", type=_positive_int, metavar="N",
                   help="read a trusted file whose grid is larger than a file of its size may ask for")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("recommend", parents=[common], help="the cutoff that still lets a rover relocalize",
                       description="Simulate lidar scans on the map (fixed seed), register them with GICP against "
                                   "the map rebuilt at each cutoff, smallest file first, and report the first that "
                                   "keeps 95 % of scans within --target-reloc metres and 1 degree (dftpcc[slam]).")
    p.add_argument("input", help="the point cloud or GeoTIFF DEM to be compressed")
    p.add_argument("--target-reloc", type=_positive, required=True, metavar="METRES",
                   help="largest translation error of a relocalized scan, metres")
    p.add_argument("--resolution", "-r", type=_resolution, default="auto", help="DEM cell size in metres, or 'auto'")
    p.add_argument("--profile", choices=tuple(PROFILES), default="compact", help=PROFILE_HELP)
    p.add_argument("--fill", choices=CHOICES["fill"], help="how empty cells are filled before the transform")
    p.add_argument("--classes", type=_classes, help="LAS/LAZ: keep only these classes, e.g. 2 for ground")
    p.add_argument("--topic", help="ROS bag: the PointCloud2 topic to read")
    p.add_argument("--pose-topic", metavar="TOPIC",
                   help="ROS bag of scans in the sensor frame: the poses that place them (as compress takes it)")
    p.add_argument("--format", help="input format if the extension does not tell")
    p.add_argument("--reloc-scans", type=_positive_int, default=20, metavar="N", help="scans to simulate (default 20)")
    p.add_argument("--reloc-seed", type=int, default=0, metavar="SEED", help="seed of the scans and guesses")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=cmd_recommend, cutoff=None)

    p = sub.add_parser("demo", parents=[common], help="run the whole pipeline on a built-in terrain and print a table",
                       description="Generate a synthetic regolith plain, compress it at several cutoffs and "
                                   "rate-control targets, decode it and print sizes and errors.")
    p.add_argument("--points", type=_positive_int, default=300_000, help="points to generate (default 300000)")
    p.add_argument("--resolution", type=_positive, default=0.25, help="cell size in metres (default 0.25)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", help="folder to write the demo cloud and its .dftpc files to")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("evaluate", parents=[common], help="every error metric between an original and a compressed or rebuilt map",
                       description="Compare ORIGINAL with a .dftpc file (decoded here; bits per point from its "
                                   "size) or any rebuilt point cloud file. Distances in metres.")
    p.add_argument("original", help="the point cloud that was compressed")
    p.add_argument("candidate", metavar="COMPRESSED_OR_REBUILT", help="a .dftpc file, or a rebuilt point cloud")
    p.add_argument("--classes", type=_classes, help="LAS/LAZ: keep only these classes of ORIGINAL (as compressed)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--max-cells", type=_positive_int, metavar="N",
                   help="read a trusted file whose grid is larger than a file of its size may ask for")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("sweep", parents=[common], help="compress at many cutoffs: sweep.csv and sweep.png (the paper's Fig. 5)",
                       description="Compress each input at every cutoff, decode, measure, and write sweep.csv "
                                   "and sweep.png (bits per point and RMSE against the cutoff).")
    p.add_argument("input", nargs="+", help="point clouds or GeoTIFF DEMs")
    p.add_argument("--cutoffs", type=_cutoffs, default="0,0.05,...,0.95",
                   help="comma-separated cutoff ratios; '0,0.1,...,0.9' continues a progression "
                        "(default 0,0.05,...,0.95)")
    p.add_argument("--resolution", "-r", type=_resolutions, default=["auto"],
                   help="DEM cell size in metres (or 'auto'): one for all inputs, or comma-separated, one per input")
    p.add_argument("--profile", choices=tuple(PROFILES), default="compact", help=PROFILE_HELP)
    p.add_argument("--classes", type=_classes, help="LAS/LAZ inputs: keep only these classes, e.g. 2 for ground")
    p.add_argument("--out", "-o", required=True, help="folder for sweep.csv and sweep.png")
    p.set_defaults(func=cmd_sweep)

    p = sub.add_parser("compare", parents=[common], help="original and rebuilt maps side by side (the paper's Fig. 6)",
                       description="Draw the original map and the maps rebuilt at each cutoff, with their errors, "
                                   "into one PNG.")
    p.add_argument("original", help="a point cloud or GeoTIFF DEM")
    p.add_argument("--cutoffs", type=_cutoffs, default="0.8,0.95", help="cutoff ratios to show (default 0.8,0.95)")
    p.add_argument("--resolution", "-r", type=_resolution, default="auto", help="DEM cell size in metres, or 'auto'")
    p.add_argument("--profile", choices=tuple(PROFILES), default="compact", help=PROFILE_HELP)
    p.add_argument("--classes", type=_classes, help="LAS/LAZ: keep only these classes, e.g. 2 for ground")
    p.add_argument("--out", "-o", required=True, help="folder for the PNG")
    p.set_defaults(func=cmd_compare)
    _add_growing_parsers(sub, common)
    _add_ros_parsers(sub, common)

    p = sub.add_parser("view", parents=[common], help="see the map in a browser (3D terrain, served on 127.0.0.1)",
                       description="Serve a page that decodes the map in the browser and shows it as 3D terrain, "
                                   "with its header and the height under the cursor; add ?rate=BYTES_PER_S to the "
                                   "address to watch it refine as over a thin link.")
    p.add_argument("input", help="the .dftpc file")
    p.add_argument("--port", type=int, default=8765, help="TCP port on 127.0.0.1 (default 8765; 0: any free one)")
    p.add_argument("--original", help="the cloud the map was made from: the page can colour by decoded minus original")
    p.add_argument("--follow", action="store_true", help="reload the map in the page whenever its file changes")
    p.add_argument("--max-cells", type=_positive_int, metavar="N",
                   help="grid the original for a trusted map whose grid is larger than a file of its size may ask for")
    p.set_defaults(func=cmd_view)
    return parser


def _show_warning(message: Any, category: type[Warning], filename: str, lineno: int,
                  file: Any = None, line: str | None = None) -> None:
    print(f"dftpcc: warning: {message}", file=sys.stderr)


def _on_stop_signal(signum: int, _frame: Any) -> None:
    raise _Stopped(signum)


@contextmanager
def _stop_signals_raise() -> Iterator[None]:
    """SIGTERM and SIGHUP unwind the stack like Ctrl-C, so no temporary file is left."""
    previous = {}
    try:
        for sig in _STOP_SIGNALS:
            previous[sig] = signal.signal(sig, _on_stop_signal)
    except ValueError:  # not the main thread: leave signals alone
        pass
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # The codec loads on first use (dftpcc/__init__.py), so --help and usage errors skip it; a
    # command loads it here, before a stop signal can land inside an import (numpy's C extension
    # then fails to load and the run ends as an internal error instead of a clean stop).
    importlib.import_module("dftpcc.files")
    # Remedies named as flags (--force), not as Python arguments (force=True), while the command runs.
    previous = speaking_to_the_command_line(True)
    try:
        return _run(args)
    finally:
        speaking_to_the_command_line(previous)


def _run(args: argparse.Namespace) -> int:
    with warnings.catch_warnings(), _stop_signals_raise():
        warnings.showwarning = _show_warning
        if args.no_warnings or args.quiet:  # -q promises nothing but errors
            warnings.simplefilter("ignore")
        try:
            return args.func(args)
        except KeyboardInterrupt:
            print("dftpcc: interrupted", file=sys.stderr)
            return EXIT_INTERRUPTED
        except _Stopped as stop:
            print(f"dftpcc: stopped by signal {signal.Signals(stop.signum).name}", file=sys.stderr)
            return EXIT_SIGNAL_BASE + stop.signum
        except BrokenPipeError:
            # The reader of our output went away (`dftpcc info --json f | head`):
            # stop quietly, as a SIGPIPE would, and keep Python's exit-time flush quiet too.
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return EXIT_SIGNAL_BASE + signal.SIGPIPE
        except MemoryError:
            print("dftpcc: error: out of memory; try a coarser --resolution", file=sys.stderr)
            return dict(EXIT_CODES)[MemoryError]
        except (DftpccError, OSError) as exc:
            code = next(c for kind, c in EXIT_CODES if isinstance(exc, kind))
            print(f"dftpcc: error: {exc}", file=sys.stderr)
            return code
        except Exception as exc:  # noqa: BLE001 - a bug: keep the traceback for the report
            traceback.print_exc()
            print(f"dftpcc: internal error: {type(exc).__name__}: {exc} (a bug in dftpcc; please report it "
                  f"with the traceback above)", file=sys.stderr)
            return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())
