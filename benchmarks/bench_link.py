"""The rover-ground link measured (issue 44): scan latency in the rover, downlink bytes, scan-to-ground time, recovery.

The simulated rover of :mod:`dftpcc.experiments.rover` drives over Mars (Gale
crater floor, 1 m DEM) with a 64-beam lidar (HDL-64E: 64 beams, -24.9 to +2
degrees, 0.17 degree firings, to 120 m) and 50 Hz odometry. Casting a scan
costs about 2 s here, so the drive is replayed at 2 scans a second (the
rover's lidar turns at 10 Hz; the map of every fifth scan is the same ground).

**Rover latency** (wall, the process pinned to one core): the rover's core
(:class:`dftpcc.live.RoverCore`: the scan placed by the odometry around its
stamp, added, the map encoded, written atomically with its state, the new
version handed to the link) on maps pre-filled to 1e5 to 1e7 cells.

**The link** (:mod:`dftpcc.link` over :mod:`dftpcc.linksim`, a simulated
clock, so the figures do not depend on this machine's speed): the versions of
the drive's map, one a second as the rover node makes them, go through a sender within a budget of 2 or 20
kB/s (frames of 1,000 bytes) to a receiver, on a clean link, with 10 % of the
frames lost each way, and with a 60 s outage; each run ends when the ground
holds the rover's last map, compared byte for byte. Not the ROS 2 processes:
those add only the transport (tests/test_ros2.py runs them).

    .venv/bin/python -m benchmarks.bench_link [--quick] [--docs | --no-docs]
"""

from __future__ import annotations

import math
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import finish_run, load_average, markdown_table, run_arguments
from dftpcc import kernels
from dftpcc.experiments import rover as sim
from dftpcc.link import Budget, Receiver, Sender
from dftpcc.linksim import Channel
from dftpcc.live import NS, RoverCore
from dftpcc.mapbuilder import MapBuilder

DEM = "dems/mars_gale_1m.tif"
LIDAR = "hdl64"
SPEED_M_S = 0.5
SCAN_HZ = 2.0  # scans replayed a second (the lidar's 10 Hz, every fifth)
DRIVE_S, QUICK_DRIVE_S = 60.0, 20.0
RESOLUTIONS = (0.1, 0.5)
MAP_CELLS, QUICK_MAP_CELLS = (100_000, 1_000_000, 10_000_000), (100_000, 1_000_000)
SCANS_TIMED, QUICK_SCANS_TIMED = 8, 4
#: The latency drive is cast at the lidar's rate, as the node gets its scans.
LIDAR_HZ = 10.0
LATENCY_S, QUICK_LATENCY_S = 6.0, 3.0
#: Scans of the latency drive not counted: the process loads what it had not, the coder fills its caches.
WARM_SCANS = 10
TILE, CUTOFF, STEP_M = 256, 0.8, 0.01
BUDGETS = (2_000.0, 20_000.0)
FRAME_BYTES = 1_000
#: Seconds between two versions of the map (the rover node's default).
VERSION_EVERY_S = 1.0
TICK_S = 0.05
OUTAGE_START_S = 5.0
OUTAGE_S = 60.0
LOSS = 0.1
#: Seconds after the drive a run may take to bring the ground to the last map.
CATCH_UP_S = 1_800.0
DRACO_BITS = 14
TARGET_MS = 100.0


def surface(data: Path) -> sim.Surface:
    import rasterio

    with rasterio.open(data / DEM) as ds:
        z = ds.read(1).astype(np.float64)
        nodata = ds.nodata
    if nodata is not None:
        z[z == nodata] = np.nan
    return sim.Surface(z - np.nanmean(z), 1.0)


def the_drive(ground: sim.Surface, seconds: float, hz: float = SCAN_HZ):
    """Scans at ``hz`` (stamp s, points in the sensor frame) and 50 Hz odometry (stamp s, 4x4 pose) of a drive."""
    lidar = sim.LIDARS[LIDAR]
    w, d = ground.extent
    start = np.array([0.3 * w, 0.4 * d])
    heading = np.array([math.cos(0.4), math.sin(0.4)])
    route = sim.drive(ground, [start, start + heading * SPEED_M_S * (seconds + 1)], speed=SPEED_M_S, lidar=lidar)
    rng = np.random.default_rng(44)
    scans = []
    for t in np.arange(0.0, seconds, 1.0 / hz):
        k = int(np.argmin(np.abs(route.times - t)))
        pose = route.poses[k]
        world = sim.scan_at(ground, pose, lidar, rng)  # in the map frame
        scans.append((float(route.times[k]), (world - pose[:3, 3]) @ pose[:3, :3]))  # back to the sensor frame
    return scans, route


def prefill(ground: sim.Surface, resolution: float, cells: int, centre: np.ndarray, path: Path) -> None:
    """A map of about ``cells`` cells around ``centre`` (one point a cell, heights clipped to the DEM), saved."""
    side = int(math.sqrt(cells))
    u = (np.arange(side) - side / 2 + 0.5) * resolution
    xx, yy = np.meshgrid(centre[0] + u, centre[1] + u)
    w, d = ground.extent
    lo = 0.5 * ground.spacing
    z = ground.height(np.clip(xx.ravel(), lo, lo + w - 1e-6), np.clip(yy.ravel(), lo, lo + d - 1e-6))
    z = np.where(np.isfinite(z), z, 0.0)
    builder = MapBuilder(resolution, tile_size=TILE, cutoff=CUTOFF, step=STEP_M)
    builder.add(np.c_[xx.ravel(), yy.ravel(), z])
    builder.save(path)


def _quaternion(matrix: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(matrix).as_quat()


def feed(core: RoverCore, scans, route, *, first: int = 0, count: int | None = None) -> None:
    """Odometry up to a little after each scan's stamp, then the scan (as a rover's topics bring them)."""
    end = len(scans) if count is None else first + count
    k = getattr(core, "bench_next_pose", 0)
    for t, points in scans[first:end]:
        while k < len(route.times) and route.times[k] <= t + 0.05:
            pose = route.poses[k]
            core.add_pose(int(round(route.times[k] * NS)) + 1, pose[:3, 3], _quaternion(pose[:3, :3]))
            k += 1
        core.add_scan(int(round(t * NS)) + 1, points, "lidar")
    core.bench_next_pose = k  # type: ignore[attr-defined]


def _timed(core: RoverCore, scans, route) -> tuple[list[float], list[float]]:
    """Each scan fed to ``core`` as its topics bring it (odometry, then the scan): per scan, its CPU ms
    (this thread's, so another process on the core does not count) and its wall ms."""
    cpu, wall = [], []
    for k in range(len(scans)):
        t0, c0 = time.perf_counter(), time.thread_time()
        feed(core, scans, route, first=k, count=1)
        cpu.append(1e3 * (time.thread_time() - c0))
        wall.append(1e3 * (time.perf_counter() - t0))
    return cpu, wall


def latency(ground, scans, route, resolutions, map_cells, timed: int) -> str:
    """Per scan, as the node works: a version a second of 10 Hz scans (each scan's own time: the scan that
    makes a version pays for it); and a version after every scan, the old measure, on a copy of the same map."""
    rows = []
    centre = route.poses[0][:2, 3]
    with tempfile.TemporaryDirectory() as tmp:
        for resolution in resolutions:
            for cells in map_cells:
                path = Path(tmp) / f"map_{resolution}_{cells}.dftpc"
                t0 = time.perf_counter()
                prefill(ground, resolution, cells, centre, path)
                fill_s = time.perf_counter() - t0
                every = Path(tmp) / "every" / path.name
                every.parent.mkdir(exist_ok=True)
                for p in (path, Path(f"{path}.state")):
                    (every.parent / p.name).write_bytes(p.read_bytes())
                core = RoverCore(path, resolution=resolution, rate=BUDGETS[0], max_frame_bytes=FRAME_BYTES,
                                 cutoff=CUTOFF, step=STEP_M, version_every=VERSION_EVERY_S, save_every=math.inf,
                                 log=lambda cause, message: None)
                cpu, wall = _timed(core, scans, route)
                # The first scans also load what the process had not yet, and fill the coder's caches.
                cpu, wall = cpu[WARM_SCANS:], wall[WARM_SCANS:]
                t1 = time.perf_counter()
                core.flush()
                core.save()
                write_ms = 1e3 * (time.perf_counter() - t1)
                each = RoverCore(every, resolution=resolution, rate=BUDGETS[0], max_frame_bytes=FRAME_BYTES,
                                 cutoff=CUTOFF, step=STEP_M, version_every=0.0, save_every=math.inf,
                                 log=lambda cause, message: None)
                each_cpu, each_wall = _timed(each, scans[:WARM_SCANS + timed], route)
                each_cpu, each_wall = each_cpu[WARM_SCANS:], each_wall[WARM_SCANS:]
                versions = [1e3 * s for s in core.version_seconds[1:]] or [math.nan]
                rows.append([f"{resolution:g} m", f"{cells:,}", f"{len(core.builder.tiles)}",
                             f"{path.stat().st_size / 1e3:,.0f}",
                             f"{statistics.median(1e3 * s for s in core.add_seconds[WARM_SCANS:]):.0f}",
                             f"{statistics.median(versions):.0f}",
                             f"{statistics.median(cpu):.0f} / {statistics.mean(cpu):.0f} / {max(cpu):.0f}",
                             f"{statistics.median(wall):.0f} / {statistics.mean(wall):.0f} / {max(wall):.0f}",
                             f"{statistics.median(each_cpu):.0f} / {statistics.median(each_wall):.0f}",
                             f"{write_ms:.0f}", f"{fill_s:.0f}",
                             "yes" if statistics.mean(cpu) < TARGET_MS else "no"])
                print(" | ".join(rows[-1]), flush=True)
                for p in Path(tmp).rglob("*"):
                    if p.is_file():
                        p.unlink()
    return markdown_table(["cell size", "map (cells)", "tiles", "map kB", "add ms (wall, median)",
                           "version ms (wall, median)",
                           f"scan ms, a version a {VERSION_EVERY_S:g} s: CPU median / mean / max",
                           "the same, wall", "scan ms, a version after every scan: CPU / wall, medians",
                           "write ms (map and state)", "prefill s", f"CPU mean under {TARGET_MS:g} ms"], rows)


def versions_of(scans, route, resolution: float) -> tuple[list[tuple[float, float, bytes, bytes]], int]:
    """The map's versions as the rover node makes them (a version a second of scans): (stamp of the first scan it
    holds that the one before did not, stamp of the scan that made it, its bytes, its preview); and the Draco
    bytes of the scans."""
    import DracoPy

    with tempfile.TemporaryDirectory() as tmp:
        core = RoverCore(Path(tmp) / "map.dftpc", resolution=resolution, rate=BUDGETS[0],
                         max_frame_bytes=FRAME_BYTES, cutoff=CUTOFF, step=STEP_M, tile_size=TILE,
                         version_every=VERSION_EVERY_S, log=lambda cause, message: None)
        out, first = [], None
        for k in range(len(scans)):
            before = core.sender.version
            feed(core, scans, route, first=k, count=1)
            first = scans[k][0] if first is None else first
            if k == len(scans) - 1:
                core.flush()
            if core.sender.version != before:
                out.append((first, scans[k][0], core.map_path.read_bytes(), core.builder.preview()))
                first = None
    draco = sum(len(DracoPy.encode(p.astype(np.float32), quantization_bits=DRACO_BITS)) for _t, p in scans)
    return out, draco


def run(versions: list[tuple[float, float, bytes, bytes]], rate: float, scenario: str) -> dict:
    """One link run on a simulated clock: the versions at their times, until the ground holds the last."""
    down_outages = up_outages = ()
    loss = 0.0
    if scenario == "10 % loss":
        loss = LOSS
    elif scenario == "60 s outage":
        down_outages = up_outages = ((OUTAGE_START_S, OUTAGE_START_S + OUTAGE_S),)
    down = Channel(seed=1, loss=loss, delay=0.3, jitter=0.1, rate=None, outages=down_outages)
    up = Channel(seed=2, loss=loss, delay=0.3, jitter=0.1, outages=up_outages)
    budget = Budget(rate)
    sender = Sender(max_frame_bytes=FRAME_BYTES, preview_over=int(rate * budget.window))  # as RoverCore makes it
    receiver = Receiver(max_frame_bytes=FRAME_BYTES)
    number: list[int] = []  # the sender's version of each scan
    applied: list[tuple[int, float]] = []
    shown: list[tuple[int, float]] = []  # (target version, time) of each preview the ground took
    drive_end = versions[-1][1]
    n, now, k = 0, 0.0, 0
    while now <= drive_end + CATCH_UP_S:
        while k < len(versions) and versions[k][1] <= now:
            number.append(sender.update(versions[k][2], preview=lambda p=versions[k][3]: p))
            k += 1
        for f in up.deliver(now):
            sender.receive(f)
        for f in sender.poll(now, budget):
            down.send(f, now)
        for f in down.deliver(now):
            previews = receiver.counts["previews"]
            v = receiver.receive(f, now)
            if v is not None:
                applied.append((v, now))
            elif receiver.counts["previews"] != previews:
                shown.append((receiver.preview[0], now))
        for f in receiver.poll(now):
            up.send(f, now)
        if k == len(versions) and receiver.version == sender.version:
            break
        n += 1
        now = n * TICK_S
    reached, seen = [], []
    for (first, _t, _data, _preview), v in zip(versions, number):
        at = next((when for version, when in applied if version >= v), math.nan)
        coarse = next((when for version, when in shown if version >= v), math.inf)
        reached.append(at - first)
        seen.append(min(at, coarse) - first)
    after_outage = [when for _v, when in applied if when >= OUTAGE_START_S + OUTAGE_S]
    return {"equal": receiver.data == versions[-1][2], "end": now, "drive_end": drive_end, "reached": reached,
            "seen": seen, "previews": len(shown), "preview_bytes": sender.counts["preview bytes"],
            "frames_bytes": down.bytes, "acks_bytes": up.bytes, "versions": len(applied), "resent": sender.counts["resent"],
            "changes": sender.counts["changes"],
            "first_after_outage": (after_outage[0] - OUTAGE_START_S - OUTAGE_S) if after_outage else math.nan}


def link_table(versions, draco: int, resolution: float) -> str:
    rows = []
    drive_s = versions[-1][1] + 1.0 / SCAN_HZ
    per_minute = 60.0 / drive_s
    # Resending the whole map at each version (once a second) instead.
    whole = sum(len(data) for _f, _t, data, _p in versions) * per_minute
    for rate in BUDGETS:
        for scenario in ("clean", "10 % loss", "60 s outage"):
            r = run(versions, rate, scenario)
            lag, seen = np.array(r["reached"]), np.array(r["seen"])
            rows.append([f"{resolution:g} m", f"{rate / 1e3:g}", scenario,
                         f"{r['frames_bytes'] * per_minute / 1e3:,.0f} (all {r['frames_bytes'] / 1e3:,.0f})",
                         f"{whole / 1e3:,.0f}", f"{draco * per_minute / 1e3:,.0f}",
                         f"{np.nanmedian(lag):.1f} / {np.nanmax(lag):.1f}",
                         f"{np.nanmedian(seen):.1f} / {np.nanmax(seen):.1f} ({r['previews']}, "
                         f"{r['preview_bytes'] / 1e3:,.0f} kB)",
                         f"{r['versions']} of {len(versions)}", f"{r['resent']}",
                         f"{r['first_after_outage']:.1f}" if scenario == "60 s outage" else "",
                         f"{r['end'] - r['drive_end']:.1f}", "yes" if r["equal"] else "NO"])
            print(" | ".join(rows[-1]), flush=True)
    return markdown_table(["cell size", "budget kB/s", "link", "sent kB per minute of driving (whole run, kB)",
                           "whole map at each version, kB/min", f"raw scans, Draco {DRACO_BITS}-bit, kB/min ({SCAN_HZ:g} Hz)",
                           "scan to ground s, median / max (per version, from its first scan)",
                           "scan to ground, preview or map, s, median / max (previews taken; bytes of the previews sent, kB)",
                           "versions the ground took", "frames resent",
                           "first version after the outage, s", "ground caught up, s after the drive",
                           "final files equal"], rows)


def one_core() -> int:
    cpu = min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpu})
    return cpu


def main() -> None:
    ap = run_arguments(__doc__.splitlines()[0], f"a {QUICK_DRIVE_S:g} s drive, maps of 1e5 and 1e6 cells, "
                                                f"{QUICK_SCANS_TIMED} scans timed")
    args = ap.parse_args()
    cpu = one_core()
    compiled = kernels.load()
    t0 = time.perf_counter()
    ground = surface(Path(args.data))
    drive_s = QUICK_DRIVE_S if args.quick else DRIVE_S
    scans, route = the_drive(ground, drive_s)
    cast_s = time.perf_counter() - t0
    latency_s = QUICK_LATENCY_S if args.quick else LATENCY_S
    fast, fast_route = the_drive(ground, latency_s, LIDAR_HZ)
    points = statistics.median(p.shape[0] for _t, p in scans)
    parts = [
        f"The simulated rover (`dftpcc.experiments.rover`) on `{DEM}`: {LIDAR} (64 beams, {points:,.0f} points a "
        f"scan), {SPEED_M_S:g} m/s, a {drive_s:g} s drive replayed at {SCAN_HZ:g} scans a second with 50 Hz "
        f"odometry ({len(scans)} scans cast in {cast_s:.0f} s); tiles of {TILE} cells, cutoff {CUTOFF}, step "
        f"{STEP_M} m; CPU {cpu} alone; compiled kernels {'in use' if compiled else 'NOT installed'}; "
        f"{load_average()}.",
        f"**Rover latency per scan** (ms; a {latency_s:g} s drive cast at the lidar's {LIDAR_HZ:g} Hz, "
        f"{len(fast)} scans, the first {WARM_SCANS} not counted: the process loads the kernels and fills the "
        "coder's caches), on maps pre-filled around the drive (one point a cell), the rover's core as the node "
        "runs it: each scan placed by the odometry around its stamp and added to the cells (*add*); a "
        f"version a {VERSION_EVERY_S:g} s of stamps (the node's `--version-every`): the tiles the scans changed "
        "coded once, the file assembled and handed to the link (*version*), paid by the scan that makes it. "
        "*CPU*: this thread's time, what the scan costs the core; *wall*: with the other processes of this "
        "machine on the same core. *A version after every scan*: `--version-every 0`, on a copy of the map. "
        "*Write*: the map and its state, atomically (the node writes every 10 s, `--save-every`: the state is "
        f"20 bytes a cell). Target: under {TARGET_MS:g} ms a scan at 0.1 m, not growing with the map.",
        latency(ground, fast, fast_route, RESOLUTIONS, QUICK_MAP_CELLS if args.quick else MAP_CELLS,
                QUICK_SCANS_TIMED if args.quick else SCANS_TIMED),
        f"**The link** (simulated clock; frames of {FRAME_BYTES:,} bytes; 0.3 s delay and up to 0.1 s jitter each "
        f"way; a version of the map a second; budgets averaged over 10 s). *Sent*: the frames' bytes "
        "per minute of driving, resends and the catch-up after the drive counted. *Scan to ground*: from a "
        "scan's stamp to the ground applying a version that holds it. *10 % loss*: each way; *60 s outage*: "
        f"both ways, from {OUTAGE_START_S:g} s. Acknowledgements travel on the uplink and are not counted.",
    ]
    for resolution in RESOLUTIONS:
        versions, draco = versions_of(scans, route, resolution)
        parts.append(link_table(versions, draco, resolution))
    try:
        import rclpy  # noqa: F401
    except ImportError:
        parts.append("**The ROS 2 nodes in real time**: not run (the ros2 extra is not installed).")
    else:
        from benchmarks.bench_link_ros import COVER_M, COVER_SHARE, OUTAGE, ros_table

        parts.append(
            f"**The ROS 2 nodes in real time** (`benchmarks/bench_link_ros.py`): `dftpcc ros ground` and `dftpcc ros "
            f"rover` (pinned to one core) as two processes over loopback (a ROS domain of their own, Fast DDS with "
            f"4 MB socket buffers and shared memory for the 1.4 MB scans), the same {drive_s:g} s drive replayed "
            f"on `/points` and `/odom` at its stamps' pace (wall clock; {SCAN_HZ:g} scans a second, 50 Hz "
            f"odometry); frames of {FRAME_BYTES:,} bytes; the node's defaults otherwise (a version a second, a "
            f"write every 10 s). *Rover ms*: from the rover's own last line (wall, on its core shared with this "
            f"machine's other processes). *Scan to ground*: from a scan's publication to the first cloud on "
            f"`/dftpcc/map` (a map or a preview) holding {COVER_SHARE:.0%} of the scan's {COVER_M:g} m cells (at 0.5 m, "
            f"the preview's 4 m blocks). "
            f"*10 % loss*: each node drops 10 % of the link frames it receives; *outage*: both drop every frame "
            f"for {OUTAGE[1]:g} s from about {OUTAGE[0]:g} s into the drive (counted from the nodes' start; "
            f"scaled down from 60 s to keep the run short; the simulated runs above have the 60 s). Equality: the rover's file (written when it "
            f"stops) against the ground's.")
        parts.append(ros_table(scans, route, quick=args.quick))
    finish_run(parts, args, "bench-link", "The rover-ground link (issue 44)",
               f"Run time {time.perf_counter() - t0:.0f} s.")


if __name__ == "__main__":
    main()
