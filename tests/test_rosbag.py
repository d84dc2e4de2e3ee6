"""ROS bags: the PointCloud2 messages of one topic read as one cloud (ROS 1 and ROS 2, whole and in chunks)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import dftpcc
from dftpcc import files
from dftpcc.cli import main
from dftpcc.errors import InvalidInputError, MissingDependencyError, UnsupportedFormatError

from .conftest import data_file

rosbags = pytest.importorskip("rosbags", reason="the 'ros' extra is not installed")

from rosbags.typesys import Stores, get_typestore  # noqa: E402


def _message(ts, pts: np.ndarray, *, frame: str = "map", dtype: str = "<f4", dense: bool = True,
             width: int | None = None, pad_row: int = 0):
    """A PointCloud2 of ``pts`` (x, y, z of ``dtype`` plus a 4-byte intensity), rows padded by ``pad_row`` B."""
    t = ts.types
    size = np.dtype(dtype).itemsize
    code = {4: 7, 8: 8}[size]
    fields = [t["sensor_msgs/msg/PointField"](name=n, offset=k * size, datatype=code, count=1)
              for k, n in enumerate("xyz")]
    fields.append(t["sensor_msgs/msg/PointField"](name="intensity", offset=3 * size, datatype=7, count=1))
    step = 3 * size + 4
    record = np.dtype({"names": ["x", "y", "z", "i"], "formats": [dtype, dtype, dtype, "<f4"],
                       "offsets": [0, size, 2 * size, 3 * size], "itemsize": step})
    width = width or pts.shape[0]
    height = pts.shape[0] // width
    rec = np.zeros(pts.shape[0], dtype=record)
    rec["x"], rec["y"], rec["z"], rec["i"] = pts[:, 0], pts[:, 1], pts[:, 2], 7.0
    rows = rec.view(np.uint8).reshape(height, width * step)
    data = np.concatenate([rows, np.zeros((height, pad_row), np.uint8)], axis=1).ravel()
    extra = {"seq": 0} if "seq" in t["std_msgs/msg/Header"].__dataclass_fields__ else {}  # ROS 1 headers count
    header = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id=frame,
                                      **extra)
    return t["sensor_msgs/msg/PointCloud2"](header=header, height=height, width=width, fields=fields,
                                            is_bigendian=dtype.startswith(">"), point_step=step,
                                            row_step=width * step + pad_row, data=data, is_dense=dense)


def write_bag(path, topics: dict, *, ros2: bool = True):
    """A bag with, per topic, the given PointCloud2 messages (made by a callable of the typestore)."""
    if ros2:
        from rosbags.rosbag2 import Writer

        ts = get_typestore(Stores.ROS2_HUMBLE)
        writer, serialize = Writer(path, version=9), ts.serialize_cdr
    else:
        from rosbags.rosbag1 import Writer

        ts = get_typestore(Stores.ROS1_NOETIC)
        writer, serialize = Writer(path), ts.serialize_ros1
    msgtype = "sensor_msgs/msg/PointCloud2"
    with writer:
        for topic, make in topics.items():
            conn = writer.add_connection(topic, msgtype, typestore=ts)
            for i, msg in enumerate(make(ts)):
                writer.write(conn, 10**9 * (i + 1), serialize(msg, msgtype))
    return path


@pytest.fixture()
def terrain(small_terrain):
    return small_terrain[:12_000]


@pytest.mark.parametrize("ros2", [True, False], ids=["ros2", "ros1"])
def test_every_message_of_the_topic_is_read(tmp_path, terrain, ros2):
    parts = np.array_split(terrain, 3)
    bag = write_bag(tmp_path / ("map" if ros2 else "map.bag"),
                    {"/map": lambda ts: [_message(ts, p) for p in parts]}, ros2=ros2)
    pts = dftpcc.read(bag).points
    np.testing.assert_allclose(pts, terrain.astype(np.float32), rtol=0, atol=0)  # float32 in the messages
    # Whole or in chunks of about 3,000 points (whole messages): the same map.
    a = files.compress_file(bag, tmp_path / "a.dftpc", resolution=0.5)
    b = files.compress_file(bag, tmp_path / "b.dftpc", resolution=0.5, chunk_points=3_000)
    assert a.header.point_count == b.header.point_count == terrain.shape[0]
    np.testing.assert_array_equal(a.read_dem().mask, b.read_dem().mask)


def test_big_endian_float64_padded_rows_and_a_db3_path(tmp_path, terrain):
    bag = write_bag(tmp_path / "bag", {"/cloud": lambda ts: [_message(ts, terrain, dtype=">f8", width=100,
                                                                        pad_row=12)]})
    np.testing.assert_array_equal(dftpcc.read(bag).points, terrain)
    db3 = next(bag.glob("*.db3"))  # the storage file inside a ROS 2 bag stands for its folder
    np.testing.assert_array_equal(dftpcc.read(db3).points, terrain)


def test_invalid_points_of_a_non_dense_message_are_left_out(tmp_path, terrain):
    holes = terrain.copy()
    holes[[5, 6, 70], 2] = np.nan
    bag = write_bag(tmp_path / "sparse", {"/scan": lambda ts: [_message(ts, holes, dense=False)]})
    assert dftpcc.read(bag).points.shape[0] == terrain.shape[0] - 3
    # A message that claims to be dense is held to it.
    lying = write_bag(tmp_path / "lying", {"/scan": lambda ts: [_message(ts, holes, dense=True)]})
    with pytest.raises(InvalidInputError, match="3 of .* point\\(s\\) have NaN"):
        files.compress_file(lying, tmp_path / "x.dftpc", resolution=0.5)
    assert files.compress_file(lying, tmp_path / "x.dftpc", resolution=0.5,
                               drop_nonfinite=True).header.point_count == terrain.shape[0] - 3


def test_the_topic_must_be_chosen_among_several(tmp_path, terrain, capsys):
    bag = write_bag(tmp_path / "two", {"/map": lambda ts: [_message(ts, terrain[:100])],
                                        "/scan": lambda ts: [_message(ts, terrain[100:300])]})
    with pytest.raises(InvalidInputError, match=r"choose the PointCloud2 topic .*/map, /scan"):
        dftpcc.read(bag)
    assert dftpcc.read(bag, topic="/scan").points.shape[0] == 200
    with pytest.raises(InvalidInputError, match="no PointCloud2 topic '/odom'"):
        dftpcc.read(bag, topic="/odom")
    assert main(["compress", str(bag), str(tmp_path / "m.dftpc"), "-r", "0.5", "--topic", "/map", "-q"]) == 0
    assert main(["compress", str(bag), str(tmp_path / "n.dftpc"), "-r", "0.5", "-q"]) == 3
    assert "choose the PointCloud2 topic" in capsys.readouterr().err
    assert not (tmp_path / "n.dftpc").exists()


def test_a_bag_without_pointcloud2_says_so_and_lists_its_topics(tmp_path):
    # It used to suggest --topic, which cannot help: there is no cloud to choose.
    from rosbags.rosbag2 import Writer

    ts = get_typestore(Stores.ROS2_HUMBLE)
    path = tmp_path / "chatter"
    with Writer(path, version=9) as writer:
        for topic, msgtype, msg in (("/chatter", "std_msgs/msg/String", ts.types["std_msgs/msg/String"](data="hi")),
                                    ("/count", "std_msgs/msg/Int32", ts.types["std_msgs/msg/Int32"](data=3))):
            conn = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(conn, 10**9, ts.serialize_cdr(msg, msgtype))
    expected = (r"the bag has no PointCloud2 topic \(its topics: /chatter \(std_msgs/msg/String\), "
                r"/count \(std_msgs/msg/Int32\)\)$")
    for topic in (None, "/chatter"):
        with pytest.raises(InvalidInputError, match=expected) as refused:
            dftpcc.read(path, topic=topic)
        assert "--topic" not in str(refused.value)


def test_messages_in_different_frames_are_refused(tmp_path, terrain):
    bag = write_bag(tmp_path / "frames", {"/cloud": lambda ts: [_message(ts, terrain[:50], frame="map"),
                                                                 _message(ts, terrain[50:99], frame="velodyne")]})
    with pytest.raises(InvalidInputError, match="frames 'map' and 'velodyne'.*no transform tree"):
        dftpcc.read(bag)


def test_bag_mistakes_fail_clearly(tmp_path, terrain, monkeypatch):
    folder = tmp_path / "notabag"
    folder.mkdir()
    with pytest.raises(InvalidInputError, match="no metadata.yaml"):
        dftpcc.read(folder, format="rosbag")
    with pytest.raises(InvalidInputError, match="topic can only be chosen in ROS bags"):
        npy = tmp_path / "t.npy"
        np.save(npy, terrain)
        dftpcc.read(npy, topic="/map")
    with pytest.raises(UnsupportedFormatError, match="ROS bags are read, not written as files.*write_map_bag"):
        dftpcc.write(tmp_path / "out.bag", terrain)
    bag = write_bag(tmp_path / "ok", {"/map": lambda ts: [_message(ts, terrain[:10])]})
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)  # as if the extra were not installed
    with pytest.raises(MissingDependencyError, match=r"dftpcc\[ros\]"):
        dftpcc.read(bag)


def test_inconsistent_messages_fail_clearly(tmp_path, terrain):
    def short_data(ts):
        msg = _message(ts, terrain[:100])
        msg.data = msg.data[:-7]  # fewer bytes than width x point_step
        return [msg]

    def field_outside_the_point(ts):
        msg = _message(ts, terrain[:100])
        msg.fields[2].offset = msg.point_step  # z beyond the record
        return [msg]

    for name, make in (("short", short_data), ("outside", field_outside_the_point)):
        bag = write_bag(tmp_path / name, {"/map": make})
        expected = r"/map: (a PointCloud2 message is inconsistent|PointCloud2 field z at byte 16 does not fit)"
        with pytest.raises(InvalidInputError, match=expected):
            dftpcc.read(bag)
        with pytest.raises(InvalidInputError):
            files.compress_file(bag, tmp_path / f"{name}.dftpc", resolution=0.5, chunk_points=50)
        assert not (tmp_path / f"{name}.dftpc").exists()


def test_a_large_bag_is_read_in_chunks_by_itself(tmp_path, terrain, monkeypatch):
    bag = write_bag(tmp_path / "run", {"/map": lambda ts: [_message(ts, p) for p in np.array_split(terrain, 4)]})
    # A bag has no point count; its size over 12 B a point bounds it.
    assert files.stored_point_count(bag) >= terrain.shape[0]
    monkeypatch.setattr(dftpcc.limits, "available_memory", lambda: 10 ** 12)
    assert not files.reads_in_chunks(bag)
    monkeypatch.setattr(dftpcc.limits, "available_memory", lambda: terrain.shape[0] * dftpcc.limits.IN_MEMORY_BYTES_PER_POINT)
    assert files.reads_in_chunks(bag)
    assert files.compress_file(bag, tmp_path / "m.dftpc", resolution=0.5).header.point_count == terrain.shape[0]


# -- a rover's bag: scans in the sensor frame, poses beside them ---------------------------------------

from dftpcc.io import rosbag as rb  # noqa: E402
from dftpcc.io import rosmap  # noqa: E402

#: The rover drives 1 m/s along x and turns 0.2 rad/s: translation linear and yaw at a constant
#: rate, so linear interpolation and slerp give the true pose at any stamp.
SPEED_M_S, YAW_RATE = (1.0, 0.5, 0.0), 0.2
POSE_PERIOD_NS = 100_000_000  # poses at 10 Hz
SCAN_OFFSET_NS = 35_000_000  # scans 35 ms after a pose: between two of them


def true_pose(stamp_ns: int):
    from scipy.spatial.transform import Rotation

    s = stamp_ns / 1e9
    rotation = Rotation.from_euler("xyz", [0.05, -0.03, YAW_RATE * s])  # a tilted lidar, turning
    return rotation, np.array(SPEED_M_S) * s + np.array([0.0, 0.0, 1.5])


def _stamp(ts, ns):
    return ts.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def _std_header(ts, ns, frame):
    extra = {"seq": 0} if "seq" in ts.types["std_msgs/msg/Header"].__dataclass_fields__ else {}
    return ts.types["std_msgs/msg/Header"](stamp=_stamp(ts, ns), frame_id=frame, **extra)


def _pose_parts(ts, ns, *, nan=False, scale=1.0):
    rotation, t = true_pose(ns)
    q = rotation.as_quat() * scale
    T = ts.types
    position = T["geometry_msgs/msg/Point"](x=float("nan") if nan else t[0], y=t[1], z=t[2])
    return t, T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]), position


def odometry(ts, ns, *, child="lidar", **bad):
    T = ts.types
    t, q, position = _pose_parts(ts, ns, **bad)
    cov = np.zeros(36)
    pose = T["geometry_msgs/msg/PoseWithCovariance"](pose=T["geometry_msgs/msg/Pose"](position=position,
                                                                                      orientation=q), covariance=cov)
    zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    twist = T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
                                                       covariance=cov)
    return T["nav_msgs/msg/Odometry"](header=_std_header(ts, ns, "map"), child_frame_id=child, pose=pose, twist=twist)


def pose_stamped(ts, ns, **bad):
    T = ts.types
    _, q, position = _pose_parts(ts, ns, **bad)
    return T["geometry_msgs/msg/PoseStamped"](header=_std_header(ts, ns, "map"),
                                              pose=T["geometry_msgs/msg/Pose"](position=position, orientation=q))


def tf(ts, ns, *, child="lidar", **bad):
    T = ts.types
    _, q, p = _pose_parts(ts, ns, **bad)
    moved = T["geometry_msgs/msg/TransformStamped"](
        header=_std_header(ts, ns, "map"), child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](x=p.x, y=p.y, z=p.z),
                                                   rotation=q))
    static = T["geometry_msgs/msg/TransformStamped"](  # another branch of the tree, to be ignored
        header=_std_header(ts, ns, "map"), child_frame_id="imu",
        transform=T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](x=9.0, y=9.0, z=9.0),
                                                   rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0,
                                                                                              w=1.0)))
    return T["tf2_msgs/msg/TFMessage"](transforms=[moved, static])


POSE_MSGTYPES = {odometry: "nav_msgs/msg/Odometry", pose_stamped: "geometry_msgs/msg/PoseStamped",
                 tf: "tf2_msgs/msg/TFMessage"}


def scan_stamp(k: int) -> int:
    return 10**9 + k * 2 * POSE_PERIOD_NS + SCAN_OFFSET_NS


def rover_bag(path, terrain, *, kind="ros2", make_pose=odometry, pose_topic="/odom", scans=5, poses=None,
              scan_frame=lambda k: "lidar", bad_pose=None, extra_scans=()):
    """A rover bag as the simulator writes it: ``/points`` in frame ``lidar`` and poses map -> lidar.

    The terrain is split into ``scans`` parts, each seen from the pose at its scan's stamp;
    ``extra_scans`` are stamps of further scans (of a few points) outside the poses.
    """
    if kind == "ros1":
        from rosbags.rosbag1 import Writer

        ts = get_typestore(Stores.ROS1_NOETIC)
        writer, serialize = Writer(path), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        ts = get_typestore(Stores.ROS2_HUMBLE)
        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer, serialize = Writer(path, version=9, storage_plugin=plugin), ts.serialize_cdr
    parts = np.array_split(terrain, scans)
    pose_stamps = poses if poses is not None else [10**9 + i * POSE_PERIOD_NS for i in range(2 * scans + 1)]
    with writer:
        cloud = writer.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        posed = writer.add_connection(pose_topic, POSE_MSGTYPES[make_pose], typestore=ts)
        for i, ns in enumerate(pose_stamps):
            msg = make_pose(ts, ns, **(bad_pose if bad_pose and i == 3 else {}))
            writer.write(posed, ns, serialize(msg, POSE_MSGTYPES[make_pose]))
        stamps = [scan_stamp(k) for k in range(scans)] + list(extra_scans)
        for k, ns in enumerate(stamps):
            rotation, t = true_pose(ns)
            world = parts[k] if k < scans else terrain[:10]
            sensor = rotation.inv().apply(world - t)  # p_sensor = R^T (p_map - t)
            msg = _message(ts, sensor, dtype="<f8", frame=scan_frame(k))
            msg.header.stamp = _stamp(ts, ns)
            writer.write(cloud, ns, serialize(msg, "sensor_msgs/msg/PointCloud2"))
    return path


@pytest.mark.parametrize("kind", ["ros2", "mcap", "ros1"])
def test_scans_are_placed_by_their_interpolated_poses(tmp_path, terrain, kind):
    bag = rover_bag(tmp_path / ("run.bag" if kind == "ros1" else "run"), terrain, kind=kind)
    np.testing.assert_allclose(dftpcc.read(bag, topic="/points", pose_topic="/odom").points, terrain, atol=1e-9)
    scans = list(rb.posed_scans(bag, "/points", "/odom"))
    assert [s.stamp_ns for s in scans] == [scan_stamp(k) for k in range(5)]
    for scan in scans:  # 35 ms between poses: the interpolated pose is the true one
        rotation, t = true_pose(scan.stamp_ns)
        np.testing.assert_allclose(scan.rotation, rotation.as_matrix(), atol=1e-12)
        np.testing.assert_allclose(scan.translation, t, atol=1e-12)
        assert scan.points.shape[1] == 3


@pytest.mark.parametrize("make_pose,topic", [(tf, "/tf"), (pose_stamped, "/pose")], ids=["tf", "posestamped"])
def test_tf_and_posestamped_place_scans_too(tmp_path, terrain, make_pose, topic):
    bag = rover_bag(tmp_path / "run", terrain, make_pose=make_pose, pose_topic=topic)
    np.testing.assert_allclose(dftpcc.read(bag, pose_topic=topic).points, terrain, atol=1e-9)


def test_posed_compress_is_the_same_whole_or_in_chunks_and_from_the_cli(tmp_path, terrain):
    bag = rover_bag(tmp_path / "run", terrain)
    a = files.compress_file(bag, tmp_path / "a.dftpc", resolution=0.5, pose_topic="/odom")
    b = files.compress_file(bag, tmp_path / "b.dftpc", resolution=0.5, pose_topic="/odom", chunk_points=3_000)
    assert a.header.point_count == b.header.point_count == terrain.shape[0]
    np.testing.assert_array_equal(a.read_dem().mask, b.read_dem().mask)
    assert main(["compress", str(bag), str(tmp_path / "c.dftpc"), "-r", "0.5", "--points-topic", "/points",
                 "--pose-topic", "/odom", "-q"]) == 0
    assert dftpcc.open(tmp_path / "c.dftpc").header.point_count == terrain.shape[0]


def test_scans_outside_the_poses_are_skipped_and_reported(tmp_path, terrain):
    early, late = 500_000_000, 9 * 10**9  # before the first pose (1 s) and after the last (2 s)
    bag = rover_bag(tmp_path / "run", terrain, extra_scans=(early, late))
    with pytest.warns(rb.UnposedScanWarning, match=r"skipped 2 of 7 scans .*stamps 0\.500000000 s to "
                                                   r"9\.000000000 s; poses on /odom cover 1\.000000000 s to "
                                                   r"2\.000000000 s"):
        pts = dftpcc.read(bag, pose_topic="/odom").points
    assert pts.shape[0] == terrain.shape[0]  # none of their points placed
    # Compressing in chunks passes over the bag several times, but says it once.
    with pytest.warns(rb.UnposedScanWarning) as said:
        files.compress_file(bag, tmp_path / "m.dftpc", resolution=0.5, pose_topic="/odom", chunk_points=3_000)
    assert len([w for w in said if w.category is rb.UnposedScanWarning]) == 1
    none = rover_bag(tmp_path / "none", terrain, poses=[20 * 10**9, 21 * 10**9])
    with pytest.raises(InvalidInputError, match="none of the 5 scans falls within the poses"):
        dftpcc.read(none, pose_topic="/odom")


def test_sensor_frame_scans_without_a_pose_topic_are_refused_naming_the_topics(tmp_path, terrain, capsys):
    bag = rover_bag(tmp_path / "run", terrain)
    assert main(["compress", str(bag), str(tmp_path / "m.dftpc"), "-r", "0.5", "-q"]) == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert ("scans on /points are in frame 'lidar', not a map frame" in err and "--pose-topic" in err
            and "pose topics in the bag: /odom (nav_msgs/msg/Odometry)" in err
            and "its topics: /odom (nav_msgs/msg/Odometry), /points (sensor_msgs/msg/PointCloud2)" in err)
    assert not (tmp_path / "m.dftpc").exists()
    alone = write_bag(tmp_path / "alone", {"/points": lambda ts: [_message(ts, terrain[:50], frame="velodyne")]})
    with pytest.raises(InvalidInputError, match=r"the bag has no pose topic .*its topics: /points"):
        dftpcc.read(alone)


@pytest.mark.parametrize("bad,expected", [({"nan": True}, "the pose has a NaN or infinite value"),
                                          ({"scale": 0.9}, r"the orientation is not a unit quaternion \(norm 0\.9\)")],
                         ids=["nan", "non-unit"])
def test_bad_poses_are_refused_with_their_message_index(tmp_path, terrain, bad, expected, capsys):
    bag = rover_bag(tmp_path / "run", terrain, bad_pose=bad)
    with pytest.raises(InvalidInputError, match=rf"message 3 on /odom \(stamp 1\.300000000 s\): {expected}"):
        dftpcc.read(bag, pose_topic="/odom")
    assert main(["compress", str(bag), str(tmp_path / "m.dftpc"), "--pose-topic", "/odom", "-q"]) == 3
    assert "message 3 on /odom" in capsys.readouterr().err
    assert not (tmp_path / "m.dftpc").exists()


def test_scans_in_another_frame_than_the_poses_child_are_refused(tmp_path, terrain):
    bag = rover_bag(tmp_path / "odom", terrain, scan_frame=lambda k: "velodyne")
    with pytest.raises(InvalidInputError, match=r"message 0 on /odom poses frame 'lidar' \(child_frame_id\) but "
                                                r"the scans are in frame 'velodyne'"):
        dftpcc.read(bag, pose_topic="/odom")
    bag = rover_bag(tmp_path / "tf", terrain, make_pose=tf, pose_topic="/tf", scan_frame=lambda k: "velodyne")
    with pytest.raises(InvalidInputError, match=r"no transform on /tf has child frame 'velodyne'.*imu, lidar"):
        dftpcc.read(bag, pose_topic="/tf")
    later = rover_bag(tmp_path / "later", terrain, scan_frame=lambda k: "lidar" if k < 2 else "camera")
    with pytest.raises(InvalidInputError, match=r"scan 2 on /points is in frame 'camera'.*frame 'lidar'"):
        dftpcc.read(later, pose_topic="/odom")
    with pytest.raises(InvalidInputError, match=r"/points holds sensor_msgs/msg/PointCloud2, not poses"):
        dftpcc.read(bag, pose_topic="/points")
    with pytest.raises(InvalidInputError, match=r"no pose topic '/gps' in the bag"):
        dftpcc.read(bag, pose_topic="/gps")
    with pytest.raises(InvalidInputError, match="poses can only be read from ROS bags"):
        np.save(tmp_path / "t.npy", terrain)
        dftpcc.read(tmp_path / "t.npy", pose_topic="/odom")


@pytest.mark.parametrize("kind", ["ros2", "mcap", "ros1"])
def test_a_truncated_bag_is_one_line_and_nothing_written(tmp_path, terrain, kind, capsys):
    bag = rover_bag(tmp_path / ("run.bag" if kind == "ros1" else "run"), terrain, kind=kind)
    data = bag if kind == "ros1" else next(f for f in bag.iterdir() if f.suffix in (".db3", ".mcap"))
    data.write_bytes(data.read_bytes()[: data.stat().st_size * 2 // 3])
    code = main(["compress", str(bag), str(tmp_path / "m.dftpc"), "--pose-topic", "/odom", "-q"])
    err = capsys.readouterr().err
    assert code == 3 and err.count("\n") == 1 and err.startswith(f"dftpcc: error: {bag}")
    assert not (tmp_path / "m.dftpc").exists()


# -- back to the robot: a ROS 2 bag with the map ------------------------------------------------------


@pytest.fixture()
def compressed(tmp_path, terrain):
    npy = tmp_path / "t.npy"
    np.save(npy, terrain)
    return files.compress_file(npy, tmp_path / "m.dftpc", resolution=0.5), tmp_path / "m.dftpc"


def _bag_messages(path):
    from rosbags.highlevel import AnyReader

    with AnyReader([path], default_typestore=rosmap.map_typestore()) as reader:
        return {c.topic: (c.msgtype, reader.deserialize(raw, c.msgtype), c)
                for c, _, raw in reader.messages()}


def test_decompress_writes_a_ros2_bag_with_the_map_and_its_grid_map(tmp_path, compressed):
    cmap, path = compressed
    out = tmp_path / "out_bag"
    assert main(["decompress", str(path), f"{out}/", "--topic", "/terrain", "--grid-map", "-q"]) == 0
    from dftpcc.rebuild import dem_to_points

    dem = cmap.read_dem()
    expected = dem_to_points(dem)
    # The PointCloud2 reads back through dftpcc's own reader (frame 'map'), a millimetre or better.
    np.testing.assert_allclose(dftpcc.read(out, topic="/terrain").points, expected, atol=1e-3)
    msgs = _bag_messages(out)
    assert set(msgs) == {"/terrain", "/terrain/grid_map"}
    assert "durability: transient_local" in (out / "metadata.yaml").read_text()  # latched: late subscribers get it
    msgtype, gm, _ = msgs["/terrain/grid_map"]
    assert msgtype == "grid_map_msgs/msg/GridMap" and gm.header.frame_id == "map"
    g = dem.grid
    assert gm.layers == ["elevation"] and gm.info.resolution == g.resolution
    assert (gm.info.length_x, gm.info.length_y) == (g.cols * g.resolution, g.rows * g.resolution)
    layout = gm.data[0].layout.dim
    assert [(d.label, d.size) for d in layout] == [("column_index", g.rows), ("row_index", g.cols)]
    values = np.asarray(gm.data[0].data)
    assert np.isnan(values).sum() == (~dem.mask).sum()
    # grid_map's cell (r, c), stored at c * rows_x + r, lies at x = px + lx/2 - (r + 1/2) res, likewise y.
    m = values.reshape(layout[0].size, layout[1].size).T  # M[r, c], r along x
    px, py = gm.info.pose.position.x, gm.info.pose.position.y
    heights = dem.heights + g.z0
    rows, cols = np.nonzero(dem.mask)
    x, y = g.centres(rows, cols)
    r = np.rint((px + gm.info.length_x / 2 - x) / g.resolution - 0.5).astype(int)
    c = np.rint((py + gm.info.length_y / 2 - y) / g.resolution - 0.5).astype(int)
    np.testing.assert_array_equal(m[r, c], heights[rows, cols].astype(np.float32))
    np.testing.assert_array_equal(m, np.where(dem.mask, heights, np.nan).astype(np.float32)[::-1, ::-1].T)


def test_bag_outputs_are_checked_first_and_written_atomically(tmp_path, compressed, capsys, monkeypatch):
    _, path = compressed
    out = tmp_path / "out_bag"
    assert main(["decompress", str(path), f"{out}/", "-q"]) == 0
    assert "/map" in _bag_messages(out)
    before = sorted(p.name for p in out.iterdir())
    # One rule for files and bags: an existing bag is replaced, a write-protected one only with --force.
    assert main(["decompress", str(path), str(out), "--grid-map", "-q"]) == 0  # an existing bag folder
    assert sorted(p.name for p in out.iterdir()) == before and "/map/grid_map" in _bag_messages(out)
    out.chmod(0o555)
    assert main(["decompress", str(path), f"{out}/", "-q"]) == 3
    assert "the bag is write-protected; use --force" in capsys.readouterr().err
    assert main(["decompress", str(path), f"{out}/", "--grid-map", "--force", "-q"]) == 0
    assert sorted(p.name for p in out.iterdir()) == before and "/map/grid_map" in _bag_messages(out)
    other = tmp_path / "photos"
    other.mkdir()
    (other / "keep.jpg").write_bytes(b"x")
    assert main(["decompress", str(path), f"{other}/", "--force", "-q"]) == 3  # never a folder that is not a bag
    assert "is not a ROS 2 bag" in capsys.readouterr().err and (other / "keep.jpg").exists()
    assert main(["decompress", str(path), str(tmp_path / "m.ply"), "--topic", "/map", "-q"]) == 3
    assert "apply to a ROS 2 bag output" in capsys.readouterr().err
    assert main(["decompress", str(path), str(tmp_path / "m.bag"), "--format", "rosbag", "-q"]) == 3
    assert "dftpcc writes ROS 2 bags, which are folders" in capsys.readouterr().err
    # A writer failing part way leaves nothing: no bag, no temporary folder.
    from rosbags.rosbag2 import Writer

    def broken(self, *a, **k):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(Writer, "write", broken)
    assert main(["decompress", str(path), str(tmp_path / "new_bag") + "/", "-q"]) == 3
    assert "cannot write as a ROS 2 bag: disk on fire" in capsys.readouterr().err
    assert not (tmp_path / "new_bag").exists() and not list(tmp_path.glob(".new_bag*"))
    # ... and a failing replacement keeps the previous bag.
    assert main(["decompress", str(path), f"{out}/", "--force", "-q"]) == 3
    assert sorted(p.name for p in out.iterdir()) == before and not list(tmp_path.glob(".out_bag*"))


def test_grid_map_refuses_a_rotated_grid_and_an_mcap_bag_is_written_too(tmp_path, terrain):
    npy = tmp_path / "t.npy"
    np.save(npy, terrain)
    rotated = files.compress_file(npy, tmp_path / "r.dftpc", resolution=0.5, frame="oriented").read_dem()
    assert rotated.grid.angle != 0.0
    with pytest.raises(InvalidInputError, match="rotated .* --frame axis"):
        rosmap.write_map_bag(tmp_path / "r_bag", rotated, grid_map=True)
    assert not (tmp_path / "r_bag").exists()
    dem = files.compress_file(npy, tmp_path / "a.dftpc", resolution=0.5).read_dem()
    rosmap.write_map_bag(tmp_path / "m_bag", dem, storage="mcap", grid_map="/elevation")
    assert any(f.suffix == ".mcap" for f in (tmp_path / "m_bag").iterdir())
    assert set(_bag_messages(tmp_path / "m_bag")) == {"/map", "/elevation"}


def test_writing_a_bag_without_rosbags_says_how_to_install(tmp_path, compressed, monkeypatch):
    _, path = compressed
    monkeypatch.setitem(sys.modules, "rosbags.rosbag2", None)
    with pytest.raises(MissingDependencyError, match=r"dftpcc\[ros\]"):
        rosmap.check_bag_output(tmp_path / "out_bag")


def test_a_map_far_from_its_origin_in_a_local_frame_keeps_float32(tmp_path):
    """Stamps were 0, and a UTM map's fields FLOAT64 (beyond 16,384 m), which PCL's PointXYZ and most
    RViz users do not expect: the map's time is written, and --local-origin gives FLOAT32 fields in a
    frame about a stated origin, published on /tf_static; ROS 1 .bag output says why it is refused."""
    import os

    from dftpcc.rebuild import dem_to_points

    las = data_file("pointclouds/mountain_arid_alirt.las")
    path = tmp_path / "m.dftpc"
    cmap = files.compress_file(las, path, classes=[2])
    expected = dem_to_points(cmap.read_dem())
    far, near = tmp_path / "far_bag", tmp_path / "near_bag"
    assert main(["decompress", str(path), f"{far}/", "-q"]) == 0
    msgtype, cloud, _ = _bag_messages(far)["/map"]
    assert cloud.fields[0].datatype == 8  # FLOAT64: UTM coordinates
    assert cloud.header.stamp.sec == os.stat(path).st_mtime_ns // 10**9
    result = subprocess.run([sys.executable, "-m", "dftpcc", "decompress", str(path), f"{near}/", "--local-origin",
                             "auto", "--stamp", "1700000000.5"], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0 and "FLOAT32 fields" in result.stdout, result.stdout + result.stderr
    messages = _bag_messages(near)
    _, cloud, _ = messages["/map"]
    assert cloud.fields[0].datatype == 7 and cloud.header.frame_id == "map_local"
    assert (cloud.header.stamp.sec, cloud.header.stamp.nanosec) == (1700000000, 500000000)
    _, tf, _ = messages["/tf_static"]
    (t,) = tf.transforms
    assert (t.header.frame_id, t.child_frame_id) == ("map", "map_local")
    origin = np.array([t.transform.translation.x, t.transform.translation.y, t.transform.translation.z])
    local = np.frombuffer(bytes(cloud.data), dtype="<f4").reshape(-1, 3).astype(np.float64)
    assert np.abs(local + origin - expected).max() < 1e-3  # a millimetre kept
    refused = subprocess.run([sys.executable, "-m", "dftpcc", "decompress", str(path), str(tmp_path / "m.bag"),
                              "--format", "rosbag"], capture_output=True, text=True, timeout=300)
    assert refused.returncode == 3 and "end of life" in refused.stderr and "rosbags-convert" in refused.stderr
