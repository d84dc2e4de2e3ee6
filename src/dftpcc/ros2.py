"""ROS 2 nodes of the link: thin adapters over :mod:`dftpcc.live` (``dftpcc ros rover``, ``dftpcc ros ground``).

Everything but the topics lives in the library (:mod:`dftpcc.link`,
:mod:`dftpcc.live`); a mission on another transport reuses it as it is.

Frames travel as ``std_msgs/UInt8MultiArray``: a standard message, so
neither end needs a custom interface built (the PyPI wheels of rclpy ship no
rosidl toolchain), 16 bytes of CDR around the frame, and the frame carries its
own lengths and CRC, so the array's layout is left empty. Both link topics
are best effort: the link resends what the ground reports missing, and a
reliable topic would resend on its own, past the budget.
"""

from __future__ import annotations

import random
import statistics
import time
from types import SimpleNamespace
from typing import Any, Callable

import numpy as np

from ._optional import import_optional
from .errors import InvalidInputError

__all__ = ["require", "run_rover", "run_ground", "DOWNLINK_TOPIC", "ACK_TOPIC", "MAP_TOPIC"]

DOWNLINK_TOPIC = "/dftpcc/downlink"
ACK_TOPIC = "/dftpcc/ack"
MAP_TOPIC = "/dftpcc/map"
#: Seconds between two looks at the link (frames to send, acknowledgements due).
TICK_S = 0.05
#: Seconds between two lines of figures in the node's log.
REPORT_S = 10.0
#: Queue depths: scans (best effort, the newest matter), odometry (many per scan), link frames.
SCAN_DEPTH, POSE_DEPTH, LINK_DEPTH = 5, 100, 200
_FLOAT32 = 7  # sensor_msgs/PointField FLOAT32


def require() -> SimpleNamespace:
    """rclpy and the message modules, or :class:`MissingDependencyError` with the install hint."""
    hint = dict(extra="ros2", needed_for="the ROS 2 nodes")
    rclpy = import_optional("rclpy", **hint)
    qos = import_optional("rclpy.qos", **hint)
    DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data = (
        qos.DurabilityPolicy, qos.HistoryPolicy, qos.QoSProfile, qos.ReliabilityPolicy, qos.qos_profile_sensor_data)
    PoseStamped = import_optional("geometry_msgs.msg", **hint).PoseStamped
    Odometry = import_optional("nav_msgs.msg", **hint).Odometry
    sensor = import_optional("sensor_msgs.msg", **hint)
    PointCloud2, PointField = sensor.PointCloud2, sensor.PointField
    UInt8MultiArray = import_optional("std_msgs.msg", **hint).UInt8MultiArray
    return SimpleNamespace(rclpy=rclpy, PoseStamped=PoseStamped, Odometry=Odometry, QoSProfile=QoSProfile,
                           DurabilityPolicy=DurabilityPolicy, HistoryPolicy=HistoryPolicy,
                           ReliabilityPolicy=ReliabilityPolicy, sensor=qos_profile_sensor_data,
                           PointCloud2=PointCloud2, PointField=PointField, UInt8MultiArray=UInt8MultiArray)


def _qos(ros: SimpleNamespace, depth: int, *, latched: bool = False) -> Any:
    if latched:  # the map: a late subscriber (RViz) gets the last one
        return ros.QoSProfile(depth=1, history=ros.HistoryPolicy.KEEP_LAST, reliability=ros.ReliabilityPolicy.RELIABLE,
                              durability=ros.DurabilityPolicy.TRANSIENT_LOCAL)
    return ros.QoSProfile(depth=depth, history=ros.HistoryPolicy.KEEP_LAST,
                          reliability=ros.ReliabilityPolicy.BEST_EFFORT, durability=ros.DurabilityPolicy.VOLATILE)


def _declare(node: Any, values: dict[str, Any], descriptions: dict[str, str]) -> None:
    from rcl_interfaces.msg import ParameterDescriptor

    for name, value in values.items():
        node.declare_parameter(name, value, ParameterDescriptor(description=descriptions.get(name, "")))


def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _dropper(loss: float, seed: int, outage: tuple[float, float] | None = None) -> Callable[[], bool]:
    """Whether to drop an incoming frame: a bad link for tests and benchmarks, seeded; ``outage``:
    (start, length), seconds from now, during which every frame is dropped."""
    if not 0.0 <= loss < 1.0:
        raise InvalidInputError(f"--loss is a share of frames in [0, 1), got {loss!r}")
    rng = random.Random(seed)
    start = time.monotonic()
    down = None if outage is None else (start + outage[0], start + outage[0] + outage[1])

    def drop() -> bool:
        if down is not None and down[0] <= time.monotonic() < down[1]:
            return True
        return loss > 0 and rng.random() < loss

    return drop


def _spin(ros: SimpleNamespace, node: Any, duration: float | None) -> None:
    end = None if duration is None else time.monotonic() + duration
    try:
        while ros.rclpy.ok() and (end is None or time.monotonic() < end):
            ros.rclpy.spin_once(node, timeout_sec=TICK_S)
    finally:
        node.destroy_node()
        if ros.rclpy.ok():
            ros.rclpy.shutdown()


def run_rover(*, map_path: str, points_topic: str, odom_topic: str | None, pose_topic: str | None,
              resolution: float, rate: float, max_frame_bytes: int, cutoff: float, step: float,
              target_max_error: float | None = None, map_frame: str = "map", in_map_frame: bool = False, version_every: float = 1.0,
              save_every: float = 10.0, loss: float = 0.0, seed: int = 0, duration: float | None = None,
              outage: tuple[float, float] | None = None, say: Callable[[str], None] = print) -> int:
    """The rover node: scans and poses in, the map kept on disk, frames out on :data:`DOWNLINK_TOPIC`."""
    from .io.pointcloud2 import pointcloud2_xyz
    from .live import RoverCore

    ros = require()
    ros.rclpy.init(args=None)
    node = ros.rclpy.create_node("dftpcc_rover")
    log = node.get_logger()
    core = RoverCore(map_path, resolution=resolution, rate=rate, max_frame_bytes=max_frame_bytes, cutoff=cutoff,
                     step=step, target_max_error=target_max_error, map_frame=map_frame, in_map_frame=in_map_frame, version_every=version_every,
                     save_every=save_every,
                     log=lambda cause, message: log.warning(f"{message} ({cause}; counted, not logged again)"))
    _declare(node, {"map": str(map_path), "points_topic": points_topic, "odom_topic": odom_topic or "",
                    "pose_topic": pose_topic or "", "resolution": float(resolution), "budget": float(rate),
                    "max_frame_bytes": int(max_frame_bytes), "cutoff": float(cutoff), "step": float(step),
                    "target_max_error": -1.0 if target_max_error is None else float(target_max_error),
                    "map_frame": map_frame},
             {"map": "the growing map kept on disk (.dftpc, with .state and .link beside it)",
              "budget": "downlink bytes per second, averaged over 10 s", "resolution": "cell size of a new map, m",
              "max_frame_bytes": "no frame on the downlink is longer, bytes", "step": "quantizer step, m",
              "cutoff": "cutoff ratio f_c of a new map", "map_frame": "scans in this frame need no pose",
              "target_max_error": "largest error of any occupied cell, m (0: none; -1: the map's own)"})
    drop = _dropper(loss, seed, outage)
    downlink = node.create_publisher(ros.UInt8MultiArray, DOWNLINK_TOPIC, _qos(ros, LINK_DEPTH))

    def on_scan(msg: Any) -> None:
        fields = {name: getattr(msg, name) for name in ("fields", "is_bigendian", "point_step", "width", "height",
                                                         "row_step", "data")}
        try:  # dense on purpose: the NaN points are counted by the core, not dropped unseen
            xyz = pointcloud2_xyz(SimpleNamespace(**fields, is_dense=True))
        except InvalidInputError as exc:
            core.refused("bad cloud", f"a PointCloud2 refused: {exc}")
            return
        last_scan[0] = time.monotonic()
        core.add_scan(_stamp_ns(msg.header.stamp), xyz, msg.header.frame_id)

    def on_pose(stamp: Any, position: Any, orientation: Any) -> None:
        core.add_pose(_stamp_ns(stamp), (position.x, position.y, position.z),
                      (orientation.x, orientation.y, orientation.z, orientation.w))

    node.create_subscription(ros.PointCloud2, points_topic, on_scan, _qos(ros, SCAN_DEPTH))
    if odom_topic:
        node.create_subscription(ros.Odometry, odom_topic, lambda m: on_pose(m.header.stamp, m.pose.pose.position,
                                                                            m.pose.pose.orientation),
                                 _qos(ros, POSE_DEPTH))
    if pose_topic:
        node.create_subscription(ros.PoseStamped, pose_topic, lambda m: on_pose(m.header.stamp, m.pose.position,
                                                                               m.pose.orientation),
                                 _qos(ros, POSE_DEPTH))

    def on_ack(msg: Any) -> None:
        if not drop():
            core.acknowledge(bytes(msg.data))

    node.create_subscription(ros.UInt8MultiArray, ACK_TOPIC, on_ack, _qos(ros, LINK_DEPTH))
    start = time.monotonic()
    last_report, last_scan = [start], [start]

    def tick() -> None:
        now = time.monotonic()
        for frame in core.frames(now - start):
            downlink.publish(ros.UInt8MultiArray(data=frame))
        if now - last_scan[0] >= version_every:
            core.flush()  # the scans of a pause in the drive reach the map and the link
        if now - last_report[0] >= REPORT_S:
            last_report[0] = now
            add = sorted(core.add_seconds[-100:])
            ver = sorted(core.version_seconds[-100:])
            log.info(f"{core.scans} scans, version {core.sender.version}, ground at {core.sender.ground}, "
                     f"{core.sender.counts['bytes']:,} bytes sent; median scan {1e3 * add[len(add) // 2]:.0f} ms, "
                     f"version {1e3 * ver[len(ver) // 2]:.0f} ms" if add and ver else "no scan yet")

    node.create_timer(TICK_S, tick)
    say(f"dftpcc rover: map {map_path}, scans on {points_topic}, frames on {DOWNLINK_TOPIC} within {rate:g} B/s")
    try:
        _spin(ros, node, duration)
    finally:  # stopped (a signal, the duration): the newest map reaches the disk
        core.flush()
        core.save()
        add, ver = core.add_seconds, core.version_seconds
        if add:
            # One line a benchmark reads: wall ms, the scan's own work and its share of the versions.
            say(f"dftpcc rover stopped: {core.scans} scans, {len(ver)} versions, "
                f"{core.sender.counts['bytes']} bytes sent; add median {1e3 * statistics.median(add):.1f} ms, "
                f"version median {1e3 * statistics.median(ver or [0.0]):.1f} ms, "
                f"per scan {1e3 * (sum(add) + sum(ver)) / len(add):.1f} ms")
    return 0


def cloud_message(ros: SimpleNamespace, points: np.ndarray, frame_id: str, stamp: Any) -> Any:
    """A ``sensor_msgs/PointCloud2`` of x, y, z as FLOAT32, dense, one row."""
    msg = ros.PointCloud2()
    msg.header.frame_id = frame_id
    msg.header.stamp = stamp
    msg.height, msg.width = 1, int(points.shape[0])
    msg.fields = [ros.PointField(name=n, offset=4 * k, datatype=_FLOAT32, count=1) for k, n in enumerate("xyz")]
    msg.is_bigendian, msg.point_step, msg.row_step, msg.is_dense = False, 12, 12 * int(points.shape[0]), True
    msg.data = np.ascontiguousarray(points, dtype="<f4").tobytes()
    return msg


def run_ground(*, map_path: str, frame_id: str = "map", max_frame_bytes: int | None = None, new_maps: str = "refuse",
               loss: float = 0.0, seed: int = 0, duration: float | None = None,
               outage: tuple[float, float] | None = None, say: Callable[[str], None] = print) -> int:
    """The ground node: frames in, the map on disk and on :data:`MAP_TOPIC` (latched), acknowledgements out."""
    from .live import GroundCore

    ros = require()
    ros.rclpy.init(args=None)
    node = ros.rclpy.create_node("dftpcc_ground")
    log = node.get_logger()
    core = GroundCore(map_path, max_frame_bytes=max_frame_bytes, new_maps=new_maps,
                      log=lambda cause, message: log.warning(f"{message} ({cause}; counted, not logged again)"))
    _declare(node, {"map": str(map_path), "frame_id": frame_id, "new_maps": new_maps},
             {"map": "the ground's map (.dftpc), byte for byte the rover's at each version applied",
              "frame_id": "frame of the published points: the frame the rover placed its scans in",
              "new_maps": "frames of another map id (a new mission): refuse, or archive (keep the map held "
                          "beside the file, take the new one once a whole version of it verifies)"})
    drop = _dropper(loss, seed, outage)
    cloud = node.create_publisher(ros.PointCloud2, MAP_TOPIC, _qos(ros, 1, latched=True))
    acks = node.create_publisher(ros.UInt8MultiArray, ACK_TOPIC, _qos(ros, LINK_DEPTH))
    start = time.monotonic()

    def publish_map() -> None:
        cloud.publish(cloud_message(ros, core.points(), frame_id, node.get_clock().now().to_msg()))

    def on_frame(msg: Any) -> None:
        if drop():
            return
        previews = core.receiver.counts["previews"]
        version = core.frame(bytes(msg.data), time.monotonic() - start)
        if version is not None:
            log.info(f"version {version} applied: {len(core.receiver.data):,} bytes")
            publish_map()
        elif core.receiver.counts["previews"] != previews:
            # The coarse whole map of the change on its way: shown until the change is applied.
            coarse = core.preview_points()
            if coarse is not None:
                log.info(f"preview of version {core.receiver.preview[0]}: {coarse.shape[0]:,} points")
                cloud.publish(cloud_message(ros, coarse, frame_id, node.get_clock().now().to_msg()))

    node.create_subscription(ros.UInt8MultiArray, DOWNLINK_TOPIC, on_frame, _qos(ros, LINK_DEPTH))

    def tick() -> None:
        for frame in core.acks(time.monotonic() - start):
            acks.publish(ros.UInt8MultiArray(data=frame))

    node.create_timer(TICK_S, tick)
    if core.receiver.data:
        publish_map()
    say(f"dftpcc ground: map {map_path} (version {core.receiver.version}), frames on {DOWNLINK_TOPIC}, "
        f"points on {MAP_TOPIC}")
    _spin(ros, node, duration)
    return 0
