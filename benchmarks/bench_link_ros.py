"""The rover and ground ROS 2 nodes as two processes in real time (issue 44), the drive replayed on their topics.

``dftpcc ros ground`` and ``dftpcc ros rover`` (the rover pinned to one core)
run over loopback in a ROS domain of their own; this process replays the
drive of :mod:`benchmarks.bench_link` on ``/points`` and ``/odom`` at its
stamps' pace (wall clock), and listens to ``/dftpcc/map``. Per run: the rover's
own figures (its last log line: wall ms per scan, bytes sent), the time from a
scan's publication to the first map (or preview) on ``/dftpcc/map`` covering
90 % of its ground (2 m cells), the time after an outage to the first map after
it, and whether the ground's file ends byte for byte the rover's.

:mod:`benchmarks.bench_link` runs it on its drive (``make bench-link``), so the drive is made in one
place and this module imports nothing of it.
"""

from __future__ import annotations

import math
import os
import random
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import markdown_table
from dftpcc.mapbuilder import PREVIEW_BLOCK

NS = 1_000_000_000
#: Ground cells (metres) of the coverage test, or a preview's block where that is wider.
COVER_M = 2.0
#: Share of a scan's cells the ground's map must hold for the scan to count as on the ground.
COVER_SHARE = 0.9
#: Seconds a run waits at most after the drive for the ground to hold the rover's newest map.
CATCH_UP_S = 600.0
FRAME_BYTES = 1_000
LOSS = 0.1
#: The outage of the ROS runs (scaled down from the simulated 60 s: seconds into the drive, length).
OUTAGE = (10.0, 20.0)
SRC = str(Path(__file__).resolve().parents[1] / "src")


#: Fast DDS's participants in the benchmark: UDP sockets with buffers of 4 MB (the usual Linux rmem_max)
#: and shared memory of 16 MB segments. With the defaults (sockets of ~200 kB, 0.5 MB segments) a
#: 64-beam scan of 1.4 MB, sent best effort, loses a fragment most of the time and the rover sees a
#: third of the scans; a real rover's DDS is configured for its lidar likewise.
DDS_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<dds xmlns="http://www.eprosima.com">
  <profiles>
    <transport_descriptors>
      <transport_descriptor><transport_id>udp</transport_id><type>UDPv4</type>
        <sendBufferSize>4194304</sendBufferSize><receiveBufferSize>4194304</receiveBufferSize>
      </transport_descriptor>
      <transport_descriptor><transport_id>shm</transport_id><type>SHM</type>
        <segment_size>16777216</segment_size>
      </transport_descriptor>
    </transport_descriptors>
    <participant profile_name="dftpcc_bench" is_default_profile="true">
      <rtps>
        <userTransports><transport_id>shm</transport_id><transport_id>udp</transport_id></userTransports>
        <useBuiltinTransports>false</useBuiltinTransports>
      </rtps>
    </participant>
  </profiles>
</dds>
"""


def _env(domain: int, profile: Path) -> dict[str, str]:
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain),
               PYTHONPATH=os.pathsep.join([SRC, os.environ.get("PYTHONPATH", "")]), PYTHONUNBUFFERED="1",
               FASTDDS_DEFAULT_PROFILES_FILE=str(profile))
    env.pop("ROS_STATIC_PEERS", None)
    return env


def _cells(points: np.ndarray, side: float) -> set[tuple[int, int]]:
    k = np.unique(np.floor(points[:, :2] / side).astype(np.int64), axis=0)
    return set(map(tuple, k.tolist()))


def run(scans, route, *, resolution: float, rate: float, scenario: str, cpu: int, tmp: Path) -> dict:
    """One real-time run of both nodes; ``scans``: (stamp s, points in the sensor frame), ``route``: the odometry."""
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from scipy.spatial.transform import Rotation
    from sensor_msgs.msg import PointCloud2, PointField

    cover = max(COVER_M, PREVIEW_BLOCK * resolution)  # a preview's point spacing
    domain = random.Random(os.getpid() + int(rate) + len(scenario)).randrange(100, 200)
    profile = tmp / "dds.xml"
    profile.write_text(DDS_PROFILE)
    env = _env(domain, profile)
    os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID",
                                           "FASTDDS_DEFAULT_PROFILES_FILE")})
    bad = []
    if scenario == "10 % loss":
        bad = ["--loss", str(LOSS), "--seed", "3"]
    discovery_s = 15.0  # the outage is counted from the nodes' start: the drive starts about this late
    if scenario.endswith("outage"):
        bad = ["--outage", f"{discovery_s + OUTAGE[0]:g}:{OUTAGE[1]:g}"]
    rover_map, ground_map = tmp / "rover.dftpc", tmp / "ground.dftpc"
    common = [sys.executable, "-m", "dftpcc", "ros"]
    logs = {name: open(tmp / f"{name}.log", "w") for name in ("rover", "ground")}
    procs = {
        "ground": subprocess.Popen(common + ["ground", "--map", str(ground_map), "--max-frame-bytes",
                                             str(FRAME_BYTES), *bad], env=env, stdout=logs["ground"],
                                   stderr=subprocess.STDOUT),
        "rover": subprocess.Popen(common + ["rover", "--points", "/points", "--odom", "/odom", "-r", str(resolution),
                                            "--map", str(rover_map), "--budget", str(rate), "--max-frame-bytes",
                                            str(FRAME_BYTES), *bad], env=env, stdout=logs["rover"],
                                  stderr=subprocess.STDOUT, preexec_fn=lambda: os.sched_setaffinity(0, {cpu})),
    }
    started = time.monotonic()
    # The nodes' clocks start when they are up (their first line): the outage is counted from there.
    ready = None
    while ready is None and time.monotonic() < started + 120:
        time.sleep(0.1)
        if all(f"dftpcc {name}:" in (tmp / f"{name}.log").read_text() for name in ("rover", "ground")):
            ready = time.monotonic()
    rclpy.init()
    node = rclpy.create_node("dftpcc_bench_drive")
    clouds: list[tuple[float, np.ndarray]] = []
    try:
        best = QoSProfile(depth=50, reliability=ReliabilityPolicy.BEST_EFFORT)
        scan_pub = node.create_publisher(PointCloud2, "/points", best)
        odom_pub = node.create_publisher(Odometry, "/odom", QoSProfile(depth=200,
                                                                       reliability=ReliabilityPolicy.BEST_EFFORT))
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        # A cloud counts from its stamp (the ground's clock when it applied the version or took the
        # preview: the same machine's), not from when this process got round to taking it.
        offset = time.time() - time.monotonic()
        late: list[float] = []

        def on_cloud(m) -> None:
            stamped = m.header.stamp.sec + m.header.stamp.nanosec / NS - offset
            late.append(time.monotonic() - stamped)
            clouds.append((stamped, np.frombuffer(bytes(m.data), dtype="<f4").reshape(-1, 3)))

        node.create_subscription(PointCloud2, "/dftpcc/map", on_cloud, latched)
        while time.monotonic() < started + discovery_s:
            rclpy.spin_once(node, timeout_sec=0.1)
        if not scan_pub.get_subscription_count():
            raise RuntimeError("the rover node was not discovered")
        t0 = 1_000 * NS
        drive_start = time.monotonic()
        published, cells, k = [], [], 0
        for t, points in scans:
            while time.monotonic() < drive_start + t:
                rclpy.spin_once(node, timeout_sec=0.01)
            while k < len(route.times) and route.times[k] <= t + 0.05:
                pose = route.poses[k]
                msg = Odometry()
                msg.header.frame_id, msg.child_frame_id = "map", "lidar"
                msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t0 + int(round(route.times[k] * NS)), NS)
                p, o = msg.pose.pose.position, msg.pose.pose.orientation
                p.x, p.y, p.z = (float(v) for v in pose[:3, 3])
                o.x, o.y, o.z, o.w = (float(v) for v in Rotation.from_matrix(pose[:3, :3]).as_quat())
                odom_pub.publish(msg)
                k += 1
            msg = PointCloud2()
            msg.header.frame_id = "lidar"
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t0 + int(round(t * NS)), NS)
            msg.height, msg.width = 1, int(points.shape[0])
            msg.fields = [PointField(name=n, offset=4 * j, datatype=7, count=1) for j, n in enumerate("xyz")]
            msg.is_bigendian, msg.point_step, msg.row_step, msg.is_dense = False, 12, 12 * points.shape[0], True
            msg.data = np.ascontiguousarray(points, dtype="<f4").tobytes()
            scan_pub.publish(msg)
            published.append(time.monotonic())
            j = int(np.argmin(np.abs(route.times - t)))
            cells.append(_cells(points @ route.poses[j][:3, :3].T + route.poses[j][:3, 3], cover))
        drive_end = time.monotonic()
        # The ground holds the rover's newest version when its file's SHA-256 is the one the rover's link names.
        import hashlib
        import json

        link = Path(f"{rover_map}.link")
        end = drive_end + CATCH_UP_S
        caught = math.nan
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.2)
            try:
                newest = json.loads(link.read_text())["sha256"]
                held = hashlib.sha256(ground_map.read_bytes()).hexdigest()
            except (OSError, ValueError, KeyError):
                continue
            if newest == held and time.monotonic() > drive_end + 2.0:  # the last version made after the drive
                caught = time.monotonic() - drive_end
                break
        for _ in range(20):
            rclpy.spin_once(node, timeout_sec=0.1)
    finally:
        node.destroy_node()
        rclpy.shutdown()
        for proc in procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in procs.values():
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
        for fh in logs.values():
            fh.close()
    seen = []
    covered: set[tuple[int, int]] = set()
    views = [(when, _cells(points.astype(np.float64), cover)) for when, points in clouds]
    for when_pub, need in zip(published, cells):
        at = next((when for when, have in views if when >= when_pub and len(need & have) >= COVER_SHARE * len(need)),
                  math.nan)
        seen.append(at - when_pub)
    outage_end = (ready or started) + discovery_s + OUTAGE[0] + OUTAGE[1]
    after = [when for when, _ in clouds if when >= outage_end]
    line = (tmp / "rover.log").read_text()
    stats = re.search(r"rover stopped: (\d+) scans, (\d+) versions, (\d+) bytes sent; add median ([\d.]+) ms, "
                      r"version median ([\d.]+) ms, per scan ([\d.]+) ms", line)
    drive_s = drive_end - drive_start
    result = {"equal": rover_map.is_file() and ground_map.is_file() and rover_map.read_bytes() == ground_map.read_bytes(),
              "seen": np.array(seen), "caught": caught, "clouds": len(clouds), "drive_s": drive_s,
              "first_after_outage": (after[0] - outage_end) if after else math.nan,
              "map_kB": rover_map.stat().st_size / 1e3 if rover_map.is_file() else math.nan,
              "late_s": max(late, default=math.nan)}
    if stats:
        scans_n, versions, sent, add, ver, per = stats.groups()
        result.update(scans=int(scans_n), versions=int(versions), sent=int(sent), add_ms=float(add),
                      version_ms=float(ver), per_scan_ms=float(per))
    keep = Path(tempfile.gettempdir()) / "bench_link_ros"  # the nodes' logs of the last runs, to read
    keep.mkdir(exist_ok=True)
    for name in ("rover", "ground"):
        (keep / f"{name}_{resolution:g}m_{rate:g}_{scenario.replace(' ', '_')}.log").write_text(
            (tmp / f"{name}.log").read_text())
    for p in tmp.iterdir():
        p.unlink()
    return result


RUNS = ((0.5, 2_000.0, "clean"), (0.5, 2_000.0, "10 % loss"), (0.5, 2_000.0, "20 s outage"),
        (0.1, 20_000.0, "clean"), (0.1, 20_000.0, "10 % loss"), (0.1, 2_000.0, "clean"))
QUICK_RUNS = ((0.5, 2_000.0, "10 % loss"), (0.1, 20_000.0, "clean"))


def ros_table(scans, route, *, quick: bool) -> str:
    rows = []
    # The nodes inherit this process's CPUs: all of them again (a benchmark pins itself to one), the
    # rover then pinned to the last one.
    every = set(range(os.cpu_count() or 1))
    os.sched_setaffinity(0, every)
    cpu = max(every)
    with tempfile.TemporaryDirectory() as tmp:
        for resolution, rate, scenario in QUICK_RUNS if quick else RUNS:
            r = run(scans, route, resolution=resolution, rate=rate, scenario=scenario, cpu=cpu, tmp=Path(tmp))
            per_min = 60.0 / r["drive_s"]
            seen = r["seen"]
            rows.append([f"{resolution:g} m", f"{rate / 1e3:g}", scenario, f"{r.get('scans', 0)}",
                         f"{r.get('add_ms', math.nan):.0f} / {r.get('version_ms', math.nan):.0f} / "
                         f"{r.get('per_scan_ms', math.nan):.0f}",
                         f"{r.get('sent', 0) * per_min / 1e3:,.0f}", f"{r['map_kB']:,.0f}",
                         f"{np.nanmedian(seen):.1f} / {np.nanmax(seen):.1f} ({int(np.isnan(seen).sum())} never)"
                         if np.isfinite(seen).any() else "none",
                         f"{r['first_after_outage']:.1f}" if scenario.endswith("outage") else "",
                         f"{r['caught']:.1f}", "yes" if r["equal"] else "NO"])
            print(" | ".join(rows[-1]), f"(clouds taken up to {r['late_s']:.1f} s after their stamps)", flush=True)
    return markdown_table(["cell size", "budget kB/s", "link", "scans the rover took",
                           "rover wall ms: add / version / per scan (medians; per scan: mean of add and versions)",
                           "sent kB per minute of driving (during the run)", "rover's map kB",
                           f"scan to ground s, median / max (a map or preview on /dftpcc/map holding "
                           f"{COVER_SHARE:.0%} of its {COVER_M:g} m cells, or {PREVIEW_BLOCK} cells')",
                           "first map after the outage ends, s", "ground holds the newest map, s after the drive",
                           "final files equal"], rows)
