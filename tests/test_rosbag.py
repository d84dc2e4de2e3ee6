"""ROS bags: the PointCloud2 messages of one topic read as one cloud (ROS 1 and ROS 2, whole and in chunks)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

import dftpcc
from dftpcc import files
from dftpcc.cli import main
from dftpcc.errors import InvalidInputError, MissingDependencyError, UnsupportedFormatError

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
    with pytest.raises(UnsupportedFormatError, match="ROS bags are read, not written"):
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
