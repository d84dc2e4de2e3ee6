"""ROS bags: the ``sensor_msgs/PointCloud2`` messages of one topic, read as one cloud, message by message.

A SLAM system records its map (or its registered scans, already in the map
frame) as PointCloud2 messages; dftpcc reads every message of one topic and
concatenates their points. ROS 1 bags are ``.bag`` files; a ROS 2 bag is a
folder holding ``metadata.yaml`` (a ``.db3`` or ``.mcap`` file inside one
stands for its folder). Reading needs the optional ``rosbags`` package
(``pip install 'dftpcc[ros]'``).

No transform tree is applied: the messages must all be in one frame (their
``header.frame_id``), or the read is refused. Points of a message that says
``is_dense: false`` (it may hold invalid points, as organized lidar scans
do for missing returns) and have a NaN or infinite coordinate are those
invalid points and are left out; a dense message with one is refused like any
non-finite cloud.
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Any, ClassVar, Iterator

import numpy as np

from ..errors import InvalidInputError, MissingDependencyError
from .reader import Reader

__all__ = ["POINTCLOUD2", "BagReader", "bag_folder", "pointcloud2_xyz", "read_bag", "bag_chunks", "size_bound"]

POINTCLOUD2 = ("sensor_msgs/msg/PointCloud2", "sensor_msgs/PointCloud2")
#: PointField datatype codes -> numpy types.
_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
INSTALL_HINT = "pip install 'dftpcc[ros]' (the rosbags package)"
#: Bytes of the smallest point a PointCloud2 holds (float32 x, y, z): a bag's size over it bounds its points.
SMALLEST_POINT_BYTES = 12


class BagReader(Reader):
    """A ROS 1 ``.bag`` or a ROS 2 bag folder: the PointCloud2 messages of ``topic``, whole messages per chunk.

    A bag has no point count (:attr:`stored_points` is None); its size over
    :data:`SMALLEST_POINT_BYTES` bounds it (:attr:`points_bound`).
    """

    options: ClassVar[frozenset[str]] = frozenset({"topic"})

    def _locate(self) -> None:
        bag_folder(self.path)  # a file, or a ROS 2 folder

    def _open(self) -> None:
        _any_reader()  # a missing package is said before any work

    @property
    def points_bound(self) -> int | None:
        return size_bound(self.path) // SMALLEST_POINT_BYTES

    def _raw_chunks(self, n: int | None) -> Iterator[np.ndarray]:
        if n is None:
            yield read_bag(self.path, self.topic)
        else:
            yield from bag_chunks(self.path, self.topic, n)


def bag_folder(path: str | Path) -> Path:
    """What rosbags opens for ``path``: a ROS 1 ``.bag`` file, or a ROS 2 bag folder."""
    path = Path(path)
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            raise InvalidInputError(f"{path}: a folder is read as a ROS 2 bag, but it has no metadata.yaml")
        return path
    if path.suffix.lower() in (".db3", ".mcap"):
        if not (path.parent / "metadata.yaml").is_file():
            raise InvalidInputError(f"{path}: a ROS 2 bag is the folder holding this file and its metadata.yaml, "
                                    f"which {path.parent} lacks")
        return path.parent
    if not path.is_file():
        raise InvalidInputError(f"{path}: no such file")
    return path


def size_bound(path: str | Path) -> int:
    """Bytes of the bag (the files of a ROS 2 bag folder), an upper bound of its point data (bytes)."""
    folder = bag_folder(path)
    return sum(f.stat().st_size for f in folder.iterdir() if f.is_file()) if folder.is_dir() else folder.stat().st_size


def _any_reader() -> Any:
    """rosbags' reader of every bag version, or the error saying how to install it."""
    try:
        from rosbags.highlevel import AnyReader
    except ImportError:
        raise MissingDependencyError(
            f"reading ROS bags needs rosbags, which is not installed: {INSTALL_HINT}") from None
    return AnyReader


@contextmanager
def _open(path: Path, topic: str | None) -> Iterator[tuple[Any, list[Any]]]:
    """The reader and the connections of the chosen PointCloud2 topic."""
    try:
        reader = _any_reader()([bag_folder(path)])
        reader.open()
    except InvalidInputError:
        raise
    except Exception as exc:  # noqa: BLE001 - rosbags raises its own errors on bad bags
        raise InvalidInputError(f"{path}: cannot read as a ROS bag: {exc}") from None
    try:
        clouds = sorted({c.topic for c in reader.connections if c.msgtype in POINTCLOUD2})
        if not clouds:
            raise InvalidInputError(f"{path}: the bag has no PointCloud2 topic ({_topics(reader.connections)})")
        if topic is None:
            if len(clouds) != 1:
                raise InvalidInputError(f"{path}: choose the PointCloud2 topic to read with --topic "
                                        f"(PointCloud2 topics in the bag: {', '.join(clouds)})")
            topic = clouds[0]
        elif topic not in clouds:
            raise InvalidInputError(f"{path}: no PointCloud2 topic {topic!r} in the bag "
                                    f"(PointCloud2 topics: {', '.join(clouds)})")
        yield reader, [c for c in reader.connections if c.topic == topic and c.msgtype in POINTCLOUD2]
    finally:
        reader.close()


def _topics(connections: Any) -> str:
    """The topics of a bag with their message types, for an error message."""
    topics = sorted({(c.topic, c.msgtype) for c in connections})
    if not topics:
        return "it has no topics at all"
    return "its topics: " + ", ".join(f"{topic} ({msgtype})" for topic, msgtype in topics)


def pointcloud2_xyz(msg: Any) -> np.ndarray:
    """x, y, z of a deserialised ``sensor_msgs/PointCloud2`` as an (n, 3) float64 array.

    Invalid points of a non-dense message (a NaN or infinite coordinate) are left out.
    """
    fields = {f.name: f for f in msg.fields}
    if not {"x", "y", "z"} <= set(fields):
        raise InvalidInputError(f"a PointCloud2 message has no x, y or z field (fields: {', '.join(fields)})")
    order = ">" if msg.is_bigendian else "<"
    step = int(msg.point_step)
    names, formats, offsets = [], [], []
    for name in "xyz":
        f = fields[name]
        if f.datatype not in _FIELD_TYPES:
            raise InvalidInputError(f"PointCloud2 field {name} has unknown datatype {f.datatype}")
        kind = order + _FIELD_TYPES[f.datatype]
        if not 0 <= f.offset <= step - np.dtype(kind).itemsize:
            raise InvalidInputError(f"PointCloud2 field {name} at byte {f.offset} does not fit in a {step}-byte point")
        names.append(name)
        formats.append(kind)
        offsets.append(f.offset)
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    width, height, row_step = int(msg.width), int(msg.height), int(msg.row_step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if width * height == 0:
        return np.zeros((0, 3))
    if step <= 0 or row_step < width * step or data.size < row_step * (height - 1) + width * step:
        raise InvalidInputError(f"a PointCloud2 message is inconsistent: {width} x {height} points of "
                                f"{step} B in rows of {row_step} B need more than its {data.size} B")
    # Rows may be padded: take width points from the start of each row.
    rows = np.lib.stride_tricks.as_strided(data, shape=(height, width * step), strides=(row_step, 1))
    records = np.ascontiguousarray(rows).view(dtype).reshape(-1)
    xyz = np.column_stack([records[n].astype(np.float64) for n in names])
    if not msg.is_dense:
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
    return xyz


def _clouds(path: Path, topic: str | None) -> Iterator[np.ndarray]:
    """The points of each message of the topic, in order; one frame for all or an error."""
    with _open(path, topic) as (reader, connections):
        frame = None
        for connection, _, raw in reader.messages(connections=connections):
            try:
                msg = reader.deserialize(raw, connection.msgtype)
            except Exception as exc:  # noqa: BLE001 - a damaged message
                raise InvalidInputError(f"{path}: cannot decode a message on {connection.topic}: {exc}") from None
            if frame is None:
                frame = msg.header.frame_id
            elif msg.header.frame_id != frame:
                raise InvalidInputError(
                    f"{path}: messages on {connection.topic} are in frames {frame!r} and {msg.header.frame_id!r}; "
                    f"dftpcc applies no transform tree, so a map must be recorded in one frame")
            try:
                yield pointcloud2_xyz(msg)
            except InvalidInputError as exc:
                raise InvalidInputError(f"{path}: {connection.topic}: {exc}") from None


def read_bag(path: str | Path, topic: str | None = None) -> np.ndarray:
    """Every point of the topic's PointCloud2 messages, concatenated: (N, 3) float64."""
    parts = list(_clouds(Path(path), topic))
    return np.concatenate(parts) if parts else np.zeros((0, 3))


def bag_chunks(path: str | Path, topic: str | None, chunk_points: int) -> Iterator[np.ndarray]:
    """The topic's points in chunks of about ``chunk_points`` (whole messages)."""
    pending: list[np.ndarray] = []
    size = 0
    for xyz in _clouds(Path(path), topic):
        pending.append(xyz)
        size += xyz.shape[0]
        if size >= chunk_points:
            yield np.concatenate(pending)
            pending, size = [], 0
    if pending:
        yield np.concatenate(pending)
