"""Issue 2: what each profile costs and how fast it runs, per cutoff, on real maps.

For each file and cutoff f_c: bits per original point, the vertical RMSE of
every original point against the rebuilt height of its own cell (also as a
multiple of the gridding floor), in-memory compress/decompress times (medians)
and throughput, and compact's bits over paper's at the same error. Targets
are printed as PASS/MISS; nothing here fails.

    .venv/bin/python -m benchmarks.bench_codec [--quick] [--files field redrocks ...]
"""

from __future__ import annotations

import time
from pathlib import Path

import dftpcc

from benchmarks.common import (
    GROUND, Case, bits_at, fmt_bits, load, load_average, lower_hull, markdown_table, median_time,
    finish_run, median_times, library_label, pick_cases, rmse, run_arguments, shared_grid, verdict,
    warnings_as_notes,
)

CASES = (
    Case("field_gentle_ign.laz", 0.5, (GROUND,), "gentle"),
    Case("redrocks_rough.ply", 5.0, None, "rough"),
    Case("forest_slope_bcts_2.8M.laz", 0.5, None, "rough"),
)
CUTOFFS = (0.0, 0.5, 0.8, 0.9, 0.95)
QUICK_CUTOFFS = (0.0, 0.8, 0.95)
PROFILES = ("paper", "compact")
REPEATS = 5
QUICK_REPEATS = 3

#: Targets of issue 2.
MAX_COMPACT_OVER_PAPER = 0.1           # compact needs >= 10x fewer bits at the same error
FIELD = "field_gentle_ign.laz"
FIELD_CUTOFF = 0.8
FIELD_MAX_BPP = 0.5                    # bits per original point
FIELD_MAX_FLOOR_MULTIPLE = 2.0         # vertical RMSE / gridding floor
SPEED_FILE = "forest_slope_bcts_2.8M.laz"
MIN_COMPRESS_RATE = 10e6               # input points per second
MIN_DECOMPRESS_RATE = 20e6             # output points per second
DEFAULT_CUTOFF = 0.8                   # dftpcc's default, the one the speed summary quotes


def measure_case(case: Case, data: Path, cutoffs: tuple[float, ...], repeats: int) -> dict:
    """Every (profile, cutoff) run of one file."""
    loaded = load(case, data)
    points, res = loaded.points, loaded.resolution
    classes = list(case.classes) if case.classes else None
    read_s, _ = median_time(lambda: dftpcc.read(case.path(data), classes=classes), repeats)
    _, dem = shared_grid(points, res)
    floor = float(dem.gridding_rmse)
    n = points.shape[0]
    runs = []
    for profile in PROFILES:
        for fc in cutoffs:
            t_c, cpu_c, blob = median_times(
                lambda: dftpcc.compress(points, resolution=res, cutoff=fc, profile=profile), repeats)
            t_d, cpu_d, rebuilt = median_times(lambda: dftpcc.decompress(blob), repeats)
            cmap = dftpcc.open(blob)
            out = cmap.read_dem()
            idx = out.grid.flat_index(points)
            if (idx < 0).any():
                raise RuntimeError(f"{case.name}: {int((idx < 0).sum())} points fall outside the decoded grid")
            err = rmse(points[:, 2] - (out.heights.ravel()[idx] + out.grid.z0))
            stats = cmap.header.stats
            runs.append(dict(profile=profile, cutoff=fc, bytes=len(blob), bpp=8.0 * len(blob) / n, err=err,
                             mask=stats.get("mask_bytes"), coef=stats.get("coef_bytes"),
                             step=cmap.params.step, t_c=t_c, t_d=t_d, cpu_c=cpu_c, cpu_d=cpu_d,
                             out_points=rebuilt.shape[0]))
    paper_hull = lower_hull([(r["bpp"], r["err"]) for r in runs if r["profile"] == "paper"])
    for r in runs:
        if r["profile"] == "compact":
            bits, flag = bits_at(paper_hull, r["err"])
            r["paper_bits"], r["paper_flag"] = bits, flag
    return dict(case=case, loaded=loaded, n=n, floor=floor, read_s=read_s, cells=int(dem.mask.sum()),
                grid=dem.grid.shape, runs=runs)


def ratio_text(r: dict) -> str:
    if r["profile"] != "compact":
        return ""
    if r["paper_bits"] is None:
        return "— (paper never this accurate)"
    ratio = r["bpp"] / r["paper_bits"]
    bound = "≥" if r["paper_flag"] == "cheapest" else ""
    ok = ratio <= MAX_COMPACT_OVER_PAPER
    return f"{bound}{ratio:.3f} {verdict(ok)}"


def report_case(m: dict) -> str:
    case, n, floor = m["case"], m["n"], m["floor"]
    speed_case = case.name == SPEED_FILE
    lines = [f"### {case.label()} — {case.terrain}, {m['loaded'].resolution:g} m",
             "",
             f"{n:,} points, grid {m['grid'][0]} x {m['grid'][1]}, {m['cells']:,} occupied cells, "
             f"gridding floor {1000 * floor:.1f} mm; file parsing {m['read_s']:.3f} s "
             f"({n / m['read_s'] / 1e6:.2f} M points/s, not included below).",
             ""]
    lines += [f"Note: {note}" for note in m["loaded"].notes]
    header = ["profile", "f_c", "bits/pt", "mask / coef / other B", "step mm", "RMSE mm", "× floor",
              "compress s (CPU s)", "M in pts/s", "decompress s (CPU s)", "M out pts/s",
              "compact/paper bits @ same RMSE"]
    rows = []
    for r in m["runs"]:
        c_rate, d_rate = n / r["t_c"], r["out_points"] / r["t_d"]
        c_txt, d_txt = f"{c_rate / 1e6:.2f}", f"{d_rate / 1e6:.2f}"
        if speed_case:
            c_txt += f" {verdict(c_rate >= MIN_COMPRESS_RATE)}"
            d_txt += f" {verdict(d_rate >= MIN_DECOMPRESS_RATE)}"
        other = r["bytes"] - (r["mask"] or 0) - (r["coef"] or 0)
        rows.append([r["profile"], f"{r['cutoff']:g}", fmt_bits(r["bpp"]), f"{r['mask']} / {r['coef']} / {other}",
                     f"{1000 * r['step']:.1f}" if r["profile"] == "compact" else "—",
                     f"{1000 * r['err']:.1f}", f"{r['err'] / floor:.2f}" if floor > 0 else "—",
                     f"{r['t_c']:.3f} ({r['cpu_c']:.3f})", c_txt, f"{r['t_d']:.3f} ({r['cpu_d']:.3f})", d_txt,
                     ratio_text(r)])
    lines += [markdown_table(header, rows), ""]
    return "\n".join(lines)


def targets(measured: list[dict]) -> str:
    out = ["### Targets", ""]
    compact = [(m["case"].name, r) for m in measured for r in m["runs"] if r["profile"] == "compact"]
    judged = [(name, r) for name, r in compact if r["paper_bits"] is not None]
    hits = sum(r["bpp"] / r["paper_bits"] <= MAX_COMPACT_OVER_PAPER for _, r in judged)
    out.append(f"- compact >= {1 / MAX_COMPACT_OVER_PAPER:g}x fewer bits than paper at the same error: "
               f"{verdict(hits == len(judged) if judged else None)} ({hits} of {len(judged)} runs"
               + (f"; {len(compact) - len(judged)} more reach an error paper never does)"
                  if len(compact) > len(judged) else ")"))
    field = next((m for m in measured if m["case"].name == FIELD), None)
    run = next((r for r in field["runs"] if r["profile"] == "compact" and r["cutoff"] == FIELD_CUTOFF),
               None) if field else None
    if run:
        multiple = run["err"] / field["floor"]
        ok = run["bpp"] < FIELD_MAX_BPP and multiple < FIELD_MAX_FLOOR_MULTIPLE
        out.append(f"- field, compact, f_c = {FIELD_CUTOFF}: {run['bpp']:.3f} bits/pt (< {FIELD_MAX_BPP}) at "
                   f"{multiple:.2f}x floor (< {FIELD_MAX_FLOOR_MULTIPLE:g}x): {verdict(ok)}")
    else:
        out.append("- field target: not measured in this run")
    speed = next((m for m in measured if m["case"].name == SPEED_FILE), None)
    if speed:
        for r in speed["runs"]:
            if r["cutoff"] != DEFAULT_CUTOFF:
                continue
            c_rate, d_rate = speed["n"] / r["t_c"], r["out_points"] / r["t_d"]
            c_cpu, d_cpu = speed["n"] / r["cpu_c"], r["out_points"] / r["cpu_d"]
            out.append(f"- {SPEED_FILE}, {r['profile']}, f_c = {DEFAULT_CUTOFF}: compress "
                       f"{c_rate / 1e6:.1f} M input points/s (>= {MIN_COMPRESS_RATE / 1e6:g}) "
                       f"{verdict(c_rate >= MIN_COMPRESS_RATE)}; decompress {d_rate / 1e6:.1f} M output "
                       f"points/s (>= {MIN_DECOMPRESS_RATE / 1e6:g}) {verdict(d_rate >= MIN_DECOMPRESS_RATE)} "
                       f"(per CPU-second: {c_cpu / 1e6:.1f} and {d_cpu / 1e6:.1f} M)")
    else:
        out.append("- speed targets: not measured in this run")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = run_arguments(__doc__.split("\n\n")[0], f"cutoffs {QUICK_CUTOFFS} and {QUICK_REPEATS} repeats")
    ap.add_argument("--repeats", type=int, help="timed runs per measurement (median quoted)")
    args = ap.parse_args(argv)
    cutoffs = QUICK_CUTOFFS if args.quick else CUTOFFS
    repeats = args.repeats or (QUICK_REPEATS if args.quick else REPEATS)
    cases = pick_cases(CASES, args.files)
    t0 = time.perf_counter()
    print(f"Measuring {library_label()}; {load_average()}.", flush=True)
    measured = []
    parts = [f"Times are medians of {repeats} in-memory runs (points already parsed); compact uses the "
             "library's automatic quantizer step. RMSE: every original point against the rebuilt height "
             "of its own cell. Floor: the same for the mean height of each cell (RMSE at f_c = 0 without "
             "quantization). compact/paper: compact's bits over the bits paper's frontier needs for "
             "compact's RMSE (log-log interpolation; ≥ means paper's cheapest run was already more "
             "accurate, so the ratio is a lower bound)."]
    print(parts[0], "\n", flush=True)
    for case in cases:
        notes: list[str] = []
        with warnings_as_notes(notes):
            m = measure_case(case, args.data, cutoffs, repeats)
        m["loaded"].notes.extend(notes)
        measured.append(m)
        parts.append(report_case(m))
        print(parts[-1], flush=True)
    parts.append(targets(measured))
    print(parts[-1])
    elapsed = time.perf_counter() - t0
    finish_run(parts, args, "bench_codec", "Codec: bits, error and speed per cutoff (issue 2)",
               f"Run time {elapsed:.0f} s; {load_average()} at the end (times above are wall-clock medians; "
               "CPU seconds, all threads of this process, in brackets).")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
