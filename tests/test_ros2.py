"""The ROS 2 nodes (dftpcc ros rover / ground) as separate processes over loopback, with 10 % of frames lost.

Only on this machine's loopback (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) and in a ROS domain of its
own; no assertion on time: the test waits (within a generous bound) until the ground's file is the
rover's, then asserts they are equal byte for byte.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from .test_mapbuilder import drive

ros = pytest.importorskip("rclpy", reason="the ros2 extra is not installed")

#: Seconds the test waits at most for the ground to catch up (a bound on a hang, not a timing check).
WAIT_S = 240.0
SRC = str(Path(__file__).resolve().parents[1] / "src")


def _env(domain: int) -> dict[str, str]:
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain),
               PYTHONPATH=os.pathsep.join([SRC, os.environ.get("PYTHONPATH", "")]), PYTHONUNBUFFERED="1")
    env.pop("ROS_STATIC_PEERS", None)
    return env


def _cloud(msg_types, points: np.ndarray, frame: str, stamp_ns: int, names: str = "xyz"):
    from sensor_msgs.msg import PointCloud2, PointField

    msg = PointCloud2()
    msg.header.frame_id = frame
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg.height, msg.width = 1, int(points.shape[0])
    msg.fields = [PointField(name=n, offset=4 * k, datatype=7, count=1) for k, n in enumerate(names)]
    msg.is_bigendian, msg.point_step, msg.row_step, msg.is_dense = False, 12, 12 * int(points.shape[0]), True
    msg.data = np.ascontiguousarray(points, dtype="<f4").tobytes()
    return msg


def _odom(stamp_ns: int, rotation: np.ndarray, translation: np.ndarray):
    from nav_msgs.msg import Odometry
    from scipy.spatial.transform import Rotation

    msg = Odometry()
    msg.header.frame_id, msg.child_frame_id = "map", "lidar"
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    p, o = msg.pose.pose.position, msg.pose.pose.orientation
    p.x, p.y, p.z = (float(v) for v in translation)
    o.x, o.y, o.z, o.w = (float(v) for v in Rotation.from_matrix(rotation).as_quat())
    return msg


@pytest.fixture()
def nodes(tmp_path, monkeypatch):
    domain = random.Random(os.getpid()).randrange(30, 100)
    env = _env(domain)
    for key in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID"):  # this process's node, the test drive, too
        monkeypatch.setenv(key, env[key])
    common = [sys.executable, "-m", "dftpcc", "ros"]
    logs = {name: open(tmp_path / f"{name}.log", "w") for name in ("rover", "ground")}
    procs = {
        "ground": subprocess.Popen(common + ["ground", "--map", str(tmp_path / "ground.dftpc"), "--loss", "0.1",
                                             "--seed", "2", "--max-frame-bytes", "600"],
                                   env=env, stdout=logs["ground"], stderr=subprocess.STDOUT),
        "rover": subprocess.Popen(common + ["rover", "--points", "/points", "--odom", "/odom", "-r", "0.25",
                                            "--map", str(tmp_path / "map.dftpc"), "--budget", "3000",
                                            "--max-frame-bytes", "600", "--step", "0.005", "--loss", "0.1", "--save-every", "0",
                                            "--seed", "1"],
                                  env=env, stdout=logs["rover"], stderr=subprocess.STDOUT),
    }
    yield tmp_path, procs
    for proc in procs.values():
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
    for proc in procs.values():
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
    for fh in logs.values():
        fh.close()


def test_two_node_processes_over_loopback_with_loss_end_byte_identical(nodes):
    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import UInt8MultiArray

    tmp, procs = nodes
    rclpy.init()
    node = rclpy.create_node("dftpcc_test_drive")
    try:
        best = QoSProfile(depth=50, reliability=ReliabilityPolicy.BEST_EFFORT)
        scans_pub = node.create_publisher(PointCloud2, "/points", best)
        odom_pub = node.create_publisher(__import__("nav_msgs.msg", fromlist=["Odometry"]).Odometry, "/odom", best)
        down_pub = node.create_publisher(UInt8MultiArray, "/dftpcc/downlink", best)
        # Wait for the nodes to be discovered (a bound, not a check).
        end = time.monotonic() + 60
        while time.monotonic() < end and (scans_pub.get_subscription_count() == 0
                                          or down_pub.get_subscription_count() == 0):
            rclpy.spin_once(node, timeout_sec=0.1)
        assert scans_pub.get_subscription_count() and down_pub.get_subscription_count(), "nodes not discovered"
        t0 = 1_000 * 1_000_000_000
        scans = drive(12, heading=0.4, speed=2.0, points=2000)
        # Bad input first, while the rover is idle (a busy rover drops scans from its best-effort queue):
        # small messages, apart. A cloud without x/y/z (twice: logged once), then one with NaN points whose
        # finite points are good.
        few = scans[0][0][:50].copy()
        rotation, translation = scans[0][1]
        for _ in range(2):
            scans_pub.publish(_cloud(None, few, "lidar", t0 - 500_000_000, names="abc"))
            time.sleep(0.3)
        odom_pub.publish(_odom(t0 - 505_000_000, rotation, translation))
        odom_pub.publish(_odom(t0 - 495_000_000, rotation, translation))
        few[::10] = np.nan
        time.sleep(0.05)
        scans_pub.publish(_cloud(None, few, "lidar", t0 - 500_000_000))
        time.sleep(0.3)
        for k, (points, (rotation, translation)) in enumerate(scans):
            stamp = t0 + k * 200_000_000
            odom_pub.publish(_odom(stamp - 5_000_000, rotation, translation))
            odom_pub.publish(_odom(stamp + 5_000_000, rotation, translation))
            time.sleep(0.02)
            scans_pub.publish(_cloud(None, points, "lidar", stamp))
            time.sleep(0.3)
            rclpy.spin_once(node, timeout_sec=0.0)
        # Wait until the ground's file is the rover's.
        end = time.monotonic() + WAIT_S
        rover_map, ground_map = tmp / "map.dftpc", tmp / "ground.dftpc"
        while time.monotonic() < end:
            assert all(p.poll() is None for p in procs.values()), "a node stopped"
            if rover_map.exists() and ground_map.exists() and rover_map.read_bytes() == ground_map.read_bytes():
                break
            time.sleep(0.5)
        assert rover_map.read_bytes() == ground_map.read_bytes()
        # More bad input, the rover idle again: a scan stamped before the last, and bad frames to the ground,
        # each three times (the ground's simulated loss may drop any one: a loss is no refusal).
        scans_pub.publish(_cloud(None, scans[0][0][:50], "lidar", t0 - 1_000_000_000))
        for junk in (b"\x89DL\x01\x01" + bytes(40), b"garbage", bytes(5000)) * 3:
            time.sleep(0.1)
            down_pub.publish(UInt8MultiArray(data=junk))
        # A version the rover made from scans still queued when the files first agreed may be on its
        # way: wait for the ground again. A junk frame applied would leave them apart for good
        # (every change is checked against the rover's SHA-256).
        end = time.monotonic() + WAIT_S
        while time.monotonic() < end and rover_map.read_bytes() != ground_map.read_bytes():
            assert all(p.poll() is None for p in procs.values()), "a node stopped"
            time.sleep(0.5)
        assert rover_map.read_bytes() == ground_map.read_bytes()  # nothing of it reached either map
        # A late subscriber gets the map (transient local), the ground's points as float32 x, y, z.
        got = []
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        node.create_subscription(PointCloud2, "/dftpcc/map", got.append, latched)
        import dftpcc

        expected = dftpcc.decompress(ground_map.read_bytes()).astype(np.float32)
        end = time.monotonic() + 60  # the last version's cloud may follow its file by a moment
        while not (got and got[-1].width == expected.shape[0]) and time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.2)
        assert got, "no map on /dftpcc/map"
        cloud = got[-1]
        assert [f.name for f in cloud.fields] == ["x", "y", "z"] and cloud.header.stamp.sec > 0
        points = np.frombuffer(bytes(cloud.data), dtype="<f4").reshape(-1, 3)
        np.testing.assert_array_equal(points, expected)
    finally:
        node.destroy_node()
        rclpy.shutdown()
    for proc in procs.values():
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
    rover_log = (tmp / "rover.log").read_text()
    ground_log = (tmp / "ground.log").read_text()
    assert "Traceback" not in rover_log + ground_log, rover_log[-3000:] + ground_log[-3000:]
    assert rover_log.count("(bad cloud;") == 1 and rover_log.count("(nan points;") == 1, rover_log[-3000:]
    assert "(scan stamp back;" in rover_log
    assert "(crc;" in ground_log and "(truncated;" in ground_log, ground_log[-3000:]
    assert "(oversized;" in ground_log


def test_without_rclpy_the_nodes_exit_6_with_the_install_hint(tmp_path):
    code = ("import sys; sys.modules['rclpy'] = None; from dftpcc.cli import main; "
            f"sys.exit(main(['ros', 'ground', '--map', {str(tmp_path / 'g.dftpc')!r}]))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                            env=_env(1))
    assert result.returncode == 6, result.stderr
    assert "pip install 'dftpcc[ros2]'" in result.stderr and result.stderr.count("\n") == 1
