"""A robot's TF tree (dftpcc.io.rosbag): /tf and /tf_static composed from the scans' frame up to the map frame."""

from __future__ import annotations

import numpy as np
import pytest

import dftpcc
from dftpcc import files
from dftpcc.cli import main
from dftpcc.errors import InvalidInputError

rosbags = pytest.importorskip("rosbags", reason="the 'ros' extra is not installed")

from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from dftpcc.io import rosbag as rb  # noqa: E402
from dftpcc.io.tf import read_tf_tree  # noqa: E402

from .test_rosbag import _message, _stamp, _std_header  # noqa: E402

MS = 1_000_000  # nanoseconds per millisecond
#: SLAM corrects odometry at 2 Hz (map -> odom), odometry runs at 20 Hz (odom -> base_link): other
#: rates and phases than the scans', so every scan needs both edges interpolated.
MAP_ODOM_STAMPS = [807 * MS + k * 500 * MS for k in range(3)]  # 0.807 to 1.807 s
ODOM_BASE_STAMPS = [950 * MS + k * 50 * MS for k in range(14)]  # 0.95 to 1.6 s
SCANS = 6
SCAN_STAMPS = [1013 * MS + k * 100 * MS for k in range(SCANS)]  # 1.013 to 1.513 s, at 10 Hz
#: The lidar's extrinsics on /tf_static: rotated (mounted sideways, pitched) and offset, metres.
BASE_VELODYNE = (Rotation.from_euler("xyz", [0.03, -0.2, 1.1]), np.array([0.4, -0.1, 1.2]))
BASE_IMU = (Rotation.identity(), np.array([0.0, 0.0, 0.2]))
#: The rover's body turns about a tilted axis: a constant rate about a fixed axis, so slerp is exact.
BODY_AXIS = np.array([0.05, -0.08, 1.0]) / np.linalg.norm([0.05, -0.08, 1.0])


def map_odom(ns: int) -> tuple[Rotation, np.ndarray]:
    """SLAM's correction of odometry, drifting slowly: 0.02 rad/s of yaw, a few cm/s."""
    s = ns / 1e9
    return Rotation.from_rotvec([0.0, 0.0, 0.02 * s]), np.array([2.0 + 0.05 * s, 1.0 - 0.03 * s, 0.002 * s])


def odom_base(ns: int) -> tuple[Rotation, np.ndarray]:
    """The rover driving at 1.2 m/s and turning at 0.4 rad/s."""
    s = ns / 1e9
    return Rotation.from_rotvec(BODY_AXIS * 0.4 * s), np.array([1.2 * s, 0.4 * s, 0.3 + 0.01 * s])


def map_velodyne(ns: int) -> tuple[Rotation, np.ndarray]:
    """The true pose of the lidar in the map: map -> odom -> base_link -> velodyne."""
    (r1, t1), (r2, t2), (r3, t3) = map_odom(ns), odom_base(ns), BASE_VELODYNE
    return r1 * r2 * r3, r1.apply(r2.apply(t3) + t2) + t1


def tf_messages(*, odom_stamps=MAP_ODOM_STAMPS, base_stamps=ODOM_BASE_STAMPS, extra=()):
    """Each /tf message of the drive (one transform each, as separate nodes publish them), by stamp:
    (stamp ns, parent, child, rotation, translation)."""
    msgs = ([(ns, "map", "odom", *map_odom(ns)) for ns in odom_stamps]
            + [(ns, "odom", "base_link", *odom_base(ns)) for ns in base_stamps] + list(extra))
    return sorted(msgs, key=lambda m: m[0])


def _typestore(ros1: bool):
    if not ros1:
        return get_typestore(Stores.ROS2_HUMBLE)
    ts = get_typestore(Stores.ROS1_NOETIC)  # rosbags' ROS 1 store lacks tf2_msgs: register it
    ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return ts


def _tf_message(ts, transforms, *, slash=False, bad=None):
    """A TFMessage of (stamp, parent, child, rotation, translation); ``bad`` spoils the first transform."""
    T = ts.types
    out = []
    for k, (ns, parent, child, rotation, t) in enumerate(transforms):
        q = rotation.as_quat()
        t = np.array(t, dtype=float)
        if bad == "nan" and k == 0:
            t[0] = np.nan
        if bad == "scale" and k == 0:
            q = 0.9 * q
        name = (lambda f: "/" + f) if slash else (lambda f: f)  # ROS 1's tf wrote /odom
        out.append(T["geometry_msgs/msg/TransformStamped"](
            header=_std_header(ts, ns, name(parent)), child_frame_id=name(child),
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
                rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))))
    return T["tf2_msgs/msg/TFMessage"](transforms=out)


def _latched():
    """ROS 2's QoS of /tf_static: transient local, so a late subscriber (the recorder) gets it."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    never = QosTime(sec=0, nsec=0)
    return [Qos(history=QosHistory.KEEP_LAST, depth=1, reliability=QosReliability.RELIABLE,
                durability=QosDurability.TRANSIENT_LOCAL, deadline=never, lifespan=never,
                liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=never,
                avoid_ros_namespace_conventions=False)]


def tf_bag(path, terrain, *, kind="ros2", scan_frame="velodyne", tf=None, static=None, bad=None,
           static_bad=None, extra_scans=(), slash=False, stale=None):
    """A robot's bag: /points in ``scan_frame``, /tf (map -> odom, odom -> base_link), /tf_static (extrinsics).

    The terrain is split into one part per scan of :data:`SCAN_STAMPS`, each seen from the true lidar pose
    at its stamp; ``extra_scans`` are stamps of further scans (of a few points). ``bad`` = (index, "nan" or
    "scale") spoils message ``index`` on /tf, ``static_bad`` the /tf_static message; ``stale`` transforms are
    recorded on /tf_static before it (a driver that restarted with other extrinsics).
    """
    ros1 = kind == "ros1"
    ts = _typestore(ros1)
    if ros1:
        from rosbags.rosbag1 import Writer

        writer, serialize = Writer(path), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer, serialize = Writer(path, version=9, storage_plugin=plugin), ts.serialize_cdr
    tfmsg = "tf2_msgs/msg/TFMessage"
    tf = tf_messages() if tf is None else tf
    static = [(0, "base_link", "velodyne", *BASE_VELODYNE), (0, "base_link", "imu", *BASE_IMU)] \
        if static is None else static
    parts = np.array_split(terrain, SCANS)
    with writer:
        cloud = writer.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        dynamic = writer.add_connection("/tf", tfmsg, typestore=ts)
        if static:
            fixed = (writer.add_connection("/tf_static", tfmsg, typestore=ts, latching=1) if ros1 else
                     writer.add_connection("/tf_static", tfmsg, typestore=ts, offered_qos_profiles=_latched()))
            if stale:
                writer.write(fixed, 400 * MS, serialize(_tf_message(ts, stale), tfmsg))
            # Recorded once, at the start, with every extrinsic in one message (as robot_state_publisher does).
            writer.write(fixed, 500 * MS, serialize(_tf_message(ts, static, slash=slash, bad=static_bad), tfmsg))
        for i, message in enumerate(tf):
            spoil = bad[1] if bad is not None and bad[0] == i else None
            writer.write(dynamic, message[0], serialize(_tf_message(ts, [message], slash=slash, bad=spoil), tfmsg))
        for k, ns in enumerate(SCAN_STAMPS + list(extra_scans)):
            rotation, t = map_velodyne(ns)
            world = parts[k] if k < SCANS else terrain[:10]
            msg = _message(ts, rotation.inv().apply(world - t), dtype="<f8", frame=scan_frame)  # p = R^T (p_map - t)
            msg.header.stamp = _stamp(ts, ns)
            writer.write(cloud, ns, serialize(msg, "sensor_msgs/msg/PointCloud2"))
    return path


@pytest.fixture()
def terrain(small_terrain):
    return small_terrain[:12_000]


def _name(tmp_path, kind, name="run"):
    return tmp_path / (f"{name}.bag" if kind == "ros1" else name)


@pytest.mark.parametrize("kind", ["ros2", "mcap", "ros1"])
def test_scans_are_placed_through_the_tree_into_its_root(tmp_path, terrain, kind):
    bag = tf_bag(_name(tmp_path, kind), terrain, kind=kind, slash=kind == "ros1")
    np.testing.assert_allclose(dftpcc.read(bag, topic="/points", pose_topic="/tf").points, terrain, rtol=0, atol=1e-9)
    scans = list(rb.posed_scans(bag, "/points", "/tf"))
    assert [s.stamp_ns for s in scans] == SCAN_STAMPS
    for scan in scans:  # two edges interpolated between their own stamps, one static: the true pose
        rotation, t = map_velodyne(scan.stamp_ns)
        np.testing.assert_allclose(scan.rotation, rotation.as_matrix(), rtol=0, atol=1e-12)
        np.testing.assert_allclose(scan.translation, t, rtol=0, atol=1e-12)


def test_the_map_frame_can_be_any_frame_above_the_scans(tmp_path, terrain):
    bag = tf_bag(tmp_path / "run", terrain)
    np.testing.assert_allclose(dftpcc.read(bag, pose_topic="/tf", map_frame="/map").points, terrain, atol=1e-9)
    # In odom: the world points seen through the inverse of SLAM's correction at each scan's stamp.
    expected = np.concatenate([map_odom(ns)[0].inv().apply(part - map_odom(ns)[1])
                               for ns, part in zip(SCAN_STAMPS, np.array_split(terrain, SCANS))])
    np.testing.assert_allclose(dftpcc.read(bag, pose_topic="/tf", map_frame="odom").points, expected,
                               rtol=0, atol=1e-9)
    # The scans' own frame: nothing to compose, the points as recorded.
    assert not list(read_tf_tree(bag).chain("velodyne", "velodyne").edges)
    raw = dftpcc.read(bag, pose_topic="/tf", map_frame="velodyne").points
    first = map_velodyne(SCAN_STAMPS[0])
    np.testing.assert_allclose(raw[:100], first[0].inv().apply(terrain[:100] - first[1]), atol=1e-9)


def test_compress_whole_in_chunks_and_from_the_cli_and_update(tmp_path, terrain, capsys):
    bag = tf_bag(tmp_path / "run", terrain, kind="mcap")
    a = files.compress_file(bag, tmp_path / "a.dftpc", resolution=0.5, pose_topic="/tf")
    b = files.compress_file(bag, tmp_path / "b.dftpc", resolution=0.5, pose_topic="/tf", map_frame="map",
                            chunk_points=3_000)
    assert a.header.point_count == b.header.point_count == terrain.shape[0]
    np.testing.assert_array_equal(a.read_dem().mask, b.read_dem().mask)
    npy = tmp_path / "world.npy"
    np.save(npy, terrain)
    truth = files.compress_file(npy, tmp_path / "t.dftpc", resolution=0.5)
    np.testing.assert_array_equal(a.read_dem().mask, truth.read_dem().mask)
    assert main(["compress", str(bag), str(tmp_path / "c.dftpc"), "-r", "0.5", "--points-topic", "/points",
                 "--pose-topic", "/tf", "--map-frame", "map", "-q"]) == 0
    assert (tmp_path / "c.dftpc").read_bytes() == (tmp_path / "a.dftpc").read_bytes()
    # update takes the same options: the growing map is the one of the world points.
    from dftpcc.mapbuilder import MapBuilder

    assert main(["update", str(tmp_path / "g.dftpc"), str(bag), "-r", "0.5", "--points-topic", "/points",
                 "--pose-topic", "/tf", "--map-frame", "map", "-q"]) == 0
    grown = MapBuilder(0.5)
    for part in np.array_split(terrain, SCANS):
        grown.add(part)
    reference = MapBuilder(0.5)
    for scan in rb.posed_scans(bag, "/points", "/tf"):
        reference.add(scan.points, (scan.rotation, scan.translation))
    assert (tmp_path / "g.dftpc").read_bytes() == reference.encode() == grown.encode()
    assert main(["update", str(tmp_path / "h.dftpc"), str(bag), "-r", "0.5", "--pose-topic", "/tf",
                 "--map-frame", "earth", "-q"]) == 3
    assert "not connected to the map frame 'earth'" in capsys.readouterr().err
    assert not (tmp_path / "h.dftpc").exists()


FRAMES = r"\(frames there: base_link, imu, map, odom, velodyne\)"


def test_a_frame_not_connected_to_the_map_frame_is_refused_naming_the_frames(tmp_path, terrain, capsys):
    bag = tf_bag(tmp_path / "run", terrain)
    with pytest.raises(InvalidInputError, match=r"the scans' frame 'velodyne' is not connected to the map frame "
                                                r"'earth' on /tf and /tf_static: its tree goes velodyne -> "
                                                r"base_link -> odom -> map and ends there " + FRAMES):
        dftpcc.read(bag, pose_topic="/tf", map_frame="earth")
    camera = tf_bag(tmp_path / "camera", terrain, scan_frame="camera")
    with pytest.raises(InvalidInputError, match=r"no transform on /tf and /tf_static has child frame 'camera', "
                                                r"the scans' frame, so nothing places them " + FRAMES):
        dftpcc.read(camera, pose_topic="/tf")
    # Without /tf_static the lidar hangs from nothing: the extrinsics are missing.
    bare = tf_bag(tmp_path / "bare", terrain, static=[])
    with pytest.raises(InvalidInputError, match=r"no transform on /tf has child frame 'velodyne'.*"
                                                r"\(frames there: base_link, map, odom\)"):
        dftpcc.read(bare, pose_topic="/tf")
    assert main(["compress", str(bag), str(tmp_path / "m.dftpc"), "--pose-topic", "/tf", "--map-frame", "earth",
                 "-q"]) == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not connected to the map frame 'earth'" in err
    assert not (tmp_path / "m.dftpc").exists()


def test_two_parents_and_cycles_are_refused_on_the_chain_only(tmp_path, terrain):
    footprint = (1_234 * MS, "base_footprint", "base_link", Rotation.identity(), np.zeros(3))
    two = tf_bag(tmp_path / "two", terrain, tf=tf_messages(extra=[footprint]))
    index = [m[2] for m in tf_messages(extra=[footprint])].index("base_link", 0)  # base_link's first message
    with pytest.raises(InvalidInputError, match=rf"frame 'base_link' has 2 parents, 'odom' on /tf \(from message "
                                                rf"{index}\), 'base_footprint' on /tf \(from message \d+\); TF "
                                                rf"allows one parent per frame"):
        dftpcc.read(two, pose_topic="/tf")
    # The same extrinsic moving on /tf and fixed on /tf_static is two parents too.
    both = tf_bag(tmp_path / "both", terrain, tf=tf_messages(extra=[(1_234 * MS, "base_link", "velodyne",
                                                                     *BASE_VELODYNE)]))
    with pytest.raises(InvalidInputError, match=r"frame 'velodyne' has 2 parents, 'base_link' on /tf_static "
                                                r"\(from message 0\), 'base_link' on /tf"):
        dftpcc.read(both, pose_topic="/tf")
    loop = tf_bag(tmp_path / "loop", terrain, tf=tf_messages(extra=[(1_234 * MS, "base_link", "map",
                                                                     Rotation.identity(), np.zeros(3))]))
    with pytest.raises(InvalidInputError, match=r"the transforms on /tf and /tf_static form a cycle, "
                                                r"base_link -> odom -> map -> base_link; TF frames must form a tree"):
        dftpcc.read(loop, pose_topic="/tf")
    # Of an extrinsic given twice on /tf_static the last holds, as in tf2.
    stale = tf_bag(tmp_path / "stale", terrain, stale=[(0, "base_link", "velodyne", Rotation.identity(), np.ones(3))])
    np.testing.assert_allclose(dftpcc.read(stale, pose_topic="/tf").points, terrain, atol=1e-9)
    # A broken branch the lidar does not hang from is no reason to refuse the bag.
    imu = tf_bag(tmp_path / "imu", terrain, tf=tf_messages(extra=[(1_234 * MS, "odom", "imu", Rotation.identity(),
                                                                   np.zeros(3))]))
    np.testing.assert_allclose(dftpcc.read(imu, pose_topic="/tf").points, terrain, atol=1e-9)


@pytest.mark.parametrize("bad,expected", [("nan", "has a NaN or infinite value"),
                                          ("scale", r"is not a unit quaternion \(norm 0\.9\)")], ids=["nan", "non-unit"])
def test_bad_transforms_are_refused_with_their_message_index(tmp_path, terrain, bad, expected, capsys):
    ns, parent, child = tf_messages()[3][:3]
    bag = tf_bag(tmp_path / "run", terrain, bad=(3, bad))
    with pytest.raises(InvalidInputError, match=rf"message 3 on /tf \(stamp {ns / 1e9:.9f} s\): (the rotation of )?"
                                                rf"the transform {parent} -> {child} {expected}"):
        dftpcc.read(bag, pose_topic="/tf")
    assert main(["compress", str(bag), str(tmp_path / "m.dftpc"), "--pose-topic", "/tf", "-q"]) == 3
    assert "message 3 on /tf" in capsys.readouterr().err
    static = tf_bag(tmp_path / "static", terrain, static_bad=bad)
    with pytest.raises(InvalidInputError, match=rf"message 0 on /tf_static \(stamp 0\.000000000 s\): "
                                                rf"(the rotation of )?the transform base_link -> velodyne {expected}"):
        dftpcc.read(static, pose_topic="/tf")


def test_scans_outside_a_dynamic_edge_are_skipped_and_reported(tmp_path, terrain):
    early, late = 900 * MS, 1_700 * MS  # before odom -> base_link starts (0.95 s), after it ends (1.6 s)
    bag = tf_bag(tmp_path / "run", terrain, extra_scans=(early, late))
    with pytest.warns(rb.UnposedScanWarning, match=r"skipped 2 of 8 scans .*stamps 0\.900000000 s to 1\.700000000 s; "
                                                   r"transforms on /tf cover 0\.950000000 s to 1\.600000000 s "
                                                   r"\(odom -> base_link 0\.950000000 s to 1\.600000000 s; "
                                                   r"map -> odom 0\.807000000 s to 1\.807000000 s\)"):
        pts = dftpcc.read(bag, pose_topic="/tf").points
    np.testing.assert_allclose(pts, terrain, atol=1e-9)  # none of their points placed
    # Odometry and SLAM that never overlap place nothing.
    apart = tf_bag(tmp_path / "apart", terrain, tf=tf_messages(odom_stamps=[100 * MS, 200 * MS]))
    with pytest.raises(InvalidInputError, match=r"none of the 6 scans falls within the poses .*the dynamic "
                                                r"transforms on /tf never cover one stamp together"):
        dftpcc.read(apart, pose_topic="/tf")


def test_the_map_frame_option_is_refused_where_it_cannot_apply(tmp_path, terrain):
    from .test_rosbag import odometry, rover_bag

    odom = rover_bag(tmp_path / "odom", terrain, make_pose=odometry)
    np.testing.assert_allclose(dftpcc.read(odom, pose_topic="/odom", map_frame="map").points, terrain, atol=1e-9)
    with pytest.raises(InvalidInputError, match=r"the poses on /odom are in frame 'map', not the map frame 'odom' "
                                                r"asked for; only a TF topic"):
        dftpcc.read(odom, pose_topic="/odom", map_frame="odom")
    with pytest.raises(InvalidInputError, match=r"a map frame applies to scans placed by a TF topic"):
        dftpcc.read(odom, map_frame="map")
    np.save(tmp_path / "t.npy", terrain)
    with pytest.raises(InvalidInputError, match=r"a map frame can only be chosen in ROS bags"):
        dftpcc.read(tmp_path / "t.npy", map_frame="map")
