"""ROS bags: the ``sensor_msgs/PointCloud2`` messages of one topic, read as one cloud, message by message.

A SLAM system records its map (or its registered scans, already in the map
frame) as PointCloud2 messages; dftpcc reads every message of one topic and
concatenates their points. ROS 1 bags are ``.bag`` files; a ROS 2 bag is a
folder holding ``metadata.yaml`` (a ``.db3`` or ``.mcap`` file inside one
stands for its folder). Reading needs the optional ``rosbags`` package
(``pip install 'dftpcc[ros]'``).

Without a pose topic no transform is applied: the messages must all be in
one frame (their ``header.frame_id``), a map frame (:func:`is_map_frame`),
or the read is refused. A robot records its scans in the sensor frame
instead: with ``pose_topic`` (``nav_msgs/Odometry``,
``geometry_msgs/PoseStamped``, ``geometry_msgs/PoseWithCovarianceStamped``,
or ``tf2_msgs/TFMessage`` on ``/tf``) each scan is placed in the poses' frame
by the pose of the sensor frame interpolated at the scan's
``header.stamp`` (:func:`posed_scans`, :func:`apply_pose`), and scans outside
the pose stream are skipped with a :class:`UnposedScanWarning`.

A TF topic (``/tf``) is read as a robot records it: a tree of transforms,
dynamic edges on ``/tf`` (``map -> odom`` from SLAM, ``odom -> base_link``
from odometry) and fixed extrinsics on ``/tf_static`` (``base_link ->
velodyne``; every message of it is read, whether ROS 1 latched it or ROS 2
offered it transient-local). Each scan is placed by the transforms from its
frame up to the root of its tree, or to ``map_frame`` (``--map-frame``),
composed at its stamp (:func:`read_tf_tree`, :class:`TfChain`): each dynamic
edge interpolated as a pose stream is, each static edge constant. A scan
outside the coverage of any dynamic edge of its chain is skipped and
reported; a frame with two parents, a cycle or a frame not connected to the
map frame is refused. Frame names are compared without a leading ``/``, as
tf2 does.

Points of a message that says ``is_dense: false`` (it may hold invalid
points, as organized lidar scans do for missing returns) and have a NaN or
infinite coordinate are those invalid points and are left out; a dense
message with one is refused like any non-finite cloud.
"""

from __future__ import annotations

import re
import warnings
from array import array
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Callable, ClassVar, Iterator, NamedTuple

import numpy as np

from .._optional import import_optional, install_hint
from ..errors import DftpccWarning, InvalidInputError, MissingFileError
from .reader import Reader

__all__ = ["POINTCLOUD2", "POSE_TYPES", "MAP_FRAME_WORDS", "QUATERNION_TOLERANCE", "BagReader", "PoseStream",
           "PosedScan", "UnposedScanWarning", "bag_folder", "pointcloud2_xyz", "read_bag", "bag_chunks",
           "size_bound", "is_map_frame", "read_poses", "posed_scans", "apply_pose", "stamp_ns", "TF_TYPES",
           "STATIC_SUFFIX", "TfTree", "TfEdge", "TfChain", "read_tf_tree"]

POINTCLOUD2 = ("sensor_msgs/msg/PointCloud2", "sensor_msgs/PointCloud2")
#: Message types a pose topic may hold (ROS 2 and ROS 1 spellings) -> how the pose is read.
POSE_TYPES = {
    "nav_msgs/msg/Odometry": "odometry", "nav_msgs/Odometry": "odometry",
    "geometry_msgs/msg/PoseStamped": "pose", "geometry_msgs/PoseStamped": "pose",
    "geometry_msgs/msg/PoseWithCovarianceStamped": "pose_covariance",
    "geometry_msgs/PoseWithCovarianceStamped": "pose_covariance",
    "tf2_msgs/msg/TFMessage": "tf", "tf2_msgs/TFMessage": "tf",
}
#: Message types of a TF topic (ROS 2 and ROS 1 spellings).
TF_TYPES = frozenset(t for t, kind in POSE_TYPES.items() if kind == "tf")
#: The static TF topic is the TF topic's name and this (``/tf`` -> ``/tf_static``), as tf2 names them.
STATIC_SUFFIX = "_static"
#: Words that make a frame name a map frame (REP 105's map, odom, earth; world; UTM and ENU frames;
#: LOAM and FAST-LIO's camera_init): scans in another frame need a pose topic.
MAP_FRAME_WORDS = frozenset({"map", "world", "odom", "earth", "utm", "enu", "global", "camera_init"})
#: A pose quaternion whose norm is farther than this from 1 is refused (float32 poses stay within 1e-6).
QUATERNION_TOLERANCE = 1e-3
#: Nanoseconds per second, for stamps.
NS_PER_S = 1_000_000_000
#: PointField datatype codes -> numpy types.
_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
INSTALL_HINT = install_hint("ros")
#: Bytes of the smallest point a PointCloud2 holds (float32 x, y, z): a bag's size over it bounds its points.
SMALLEST_POINT_BYTES = 12


class UnposedScanWarning(DftpccWarning):
    """Scans whose stamp falls outside the pose stream were skipped (how many, which stamps)."""


class BagReader(Reader):
    """A ROS 1 ``.bag`` or a ROS 2 bag folder: the PointCloud2 messages of ``topic``, whole messages per chunk.

    With ``pose_topic`` each message is a scan in the sensor frame, placed
    in the poses' frame (:func:`posed_scans`; of a TF topic, in ``map_frame``
    or the root of the scans' tree); the poses are read once, when the
    reader opens, and every pass reuses them. A bag has no point count
    (:attr:`stored_points` is None); its size over :data:`SMALLEST_POINT_BYTES`
    bounds it (:attr:`points_bound`).
    """

    options: ClassVar[frozenset[str]] = frozenset({"topic", "pose_topic", "map_frame"})

    def _locate(self) -> None:
        bag_folder(self.path)  # a file, or a ROS 2 folder

    def _open(self) -> None:
        _any_reader()  # a missing package is said before any work
        self.poses: PoseStream | TfChain | None = None
        self._warned = False
        if self.pose_topic is not None:
            self.poses = _scan_poses(self.path, self.pose_topic, _first_frame(self.path, self.topic), self.map_frame)
        elif self.map_frame is not None:
            raise InvalidInputError(f"{self.path}: a map frame applies to scans placed by a TF topic; give "
                                    f"--pose-topic /tf (pose_topic=) with --map-frame (map_frame=)")

    @property
    def points_bound(self) -> int | None:
        return size_bound(self.path) // SMALLEST_POINT_BYTES

    def _raw_chunks(self, n: int | None) -> Iterator[np.ndarray]:
        if self.poses is None:
            if n is None:
                yield read_bag(self.path, self.topic)
            else:
                yield from bag_chunks(self.path, self.topic, n)
            return
        # Every pass places the same scans; say once which were skipped.
        clouds = (apply_pose(s.points, s.rotation, s.translation)
                  for s in _placed(self.path, self.topic, self.poses, warn=not self._warned))
        yield from _grouped(clouds, n)
        self._warned = True


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
        raise MissingFileError(path)
    return path


def size_bound(path: str | Path) -> int:
    """Bytes of the bag (the files of a ROS 2 bag folder), an upper bound of its point data (bytes)."""
    folder = bag_folder(path)
    return sum(f.stat().st_size for f in folder.iterdir() if f.is_file()) if folder.is_dir() else folder.stat().st_size


def _any_reader() -> Any:
    """rosbags' reader of every bag version, or the error saying how to install it."""
    return import_optional("rosbags.highlevel", "ros", needed_for="reading ROS bags").AnyReader


def _default_typestore() -> Any:
    """ROS 2 Humble's types, for ROS 2 bags that do not store their message definitions (before version 9)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _opened(path: Path) -> Any:
    """A rosbags reader of ``path``, opened; a bag rosbags cannot read is one InvalidInputError."""
    try:
        reader = _any_reader()([bag_folder(path)], default_typestore=_default_typestore())
        reader.open()
    except InvalidInputError:
        raise
    except Exception as exc:  # noqa: BLE001 - rosbags raises its own errors on bad bags
        raise InvalidInputError(f"{path}: cannot read as a ROS bag: {exc}") from None
    return reader


@contextmanager
def _open(path: Path, topic: str | None) -> Iterator[tuple[Any, list[Any]]]:
    """The reader and the connections of the chosen PointCloud2 topic."""
    reader = _opened(path)
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


def _messages(path: Path, topic: str | None) -> Iterator[tuple[str, Any, Any]]:
    """(topic, connections of the bag, deserialised message) of each PointCloud2 message of the topic, in order."""
    with _open(path, topic) as (reader, connections):
        for connection, _, raw in _records(path, reader, connections):
            try:
                msg = reader.deserialize(raw, connection.msgtype)
            except Exception as exc:  # noqa: BLE001 - a damaged message
                raise InvalidInputError(f"{path}: cannot decode a message on {connection.topic}: {exc}") from None
            yield connection.topic, reader.connections, msg


def _records(path: Path, reader: Any, connections: list[Any]) -> Iterator[tuple[Any, int, bytes]]:
    """rosbags' raw messages of ``connections``; a bag that breaks part way (truncated) is one clear error."""
    records = reader.messages(connections=connections)
    while True:
        try:
            record = next(records)
        except StopIteration:
            return
        except Exception as exc:  # noqa: BLE001 - sqlite3, mcap and rosbag1 each raise their own
            raise InvalidInputError(f"{path}: cannot read as a ROS bag: {' '.join(str(exc).split())}") from None
        yield record


def _xyz(path: Path, topic: str, msg: Any) -> np.ndarray:
    try:
        return pointcloud2_xyz(msg)
    except InvalidInputError as exc:
        raise InvalidInputError(f"{path}: {topic}: {exc}") from None


def _clouds(path: Path, topic: str | None) -> Iterator[np.ndarray]:
    """The points of each message of the topic, in order; one map frame for all or an error."""
    frame = None
    for name, connections, msg in _messages(path, topic):
        if frame is None:
            frame = msg.header.frame_id
            if not is_map_frame(frame):
                raise _unplaced_error(path, name, frame, connections)
        elif msg.header.frame_id != frame:
            raise InvalidInputError(
                f"{path}: messages on {name} are in frames {frame!r} and {msg.header.frame_id!r}; "
                f"without a pose topic dftpcc applies no transform tree, so a map must be recorded in one frame")
        yield _xyz(path, name, msg)


def _unplaced_error(path: Path, topic: str, frame: str, connections: Any) -> InvalidInputError:
    """Scans in a sensor frame and no pose topic: say which topics could place them."""
    poses = sorted({(c.topic, c.msgtype) for c in connections if c.msgtype in POSE_TYPES})
    found = ("pose topics in the bag: " + ", ".join(f"{t} ({m})" for t, m in poses) if poses
             else "the bag has no pose topic (nav_msgs/Odometry, geometry_msgs/PoseStamped, /tf)")
    return InvalidInputError(
        f"{path}: the scans on {topic} are in frame {frame!r}, not a map frame, and no pose topic was given: "
        f"name the topic of their poses with --pose-topic (pose_topic=); {found}; {_topics(connections)}")


def is_map_frame(frame: str) -> bool:
    """Whether ``frame`` names a map frame: a word of :data:`MAP_FRAME_WORDS` in it (``map``, ``odom_combined``).

    An empty frame says nothing and is taken as the map's, as before poses
    were read; a sensor frame (``lidar``, ``velodyne``, ``os_sensor``) is not.
    """
    name = frame.strip("/").lower()
    if not name or name in MAP_FRAME_WORDS:
        return True
    return any(word in MAP_FRAME_WORDS for word in re.split(r"[^a-z0-9]+", name))


def _grouped(clouds: Iterator[np.ndarray], chunk_points: int | None) -> Iterator[np.ndarray]:
    """Clouds joined into chunks of about ``chunk_points`` (whole messages); None: one chunk of them all."""
    pending: list[np.ndarray] = []
    size = 0
    for xyz in clouds:
        pending.append(xyz)
        size += xyz.shape[0]
        if chunk_points is not None and size >= chunk_points:
            yield np.concatenate(pending)
            pending, size = [], 0
    if pending or chunk_points is None:
        yield np.concatenate(pending) if pending else np.zeros((0, 3))


def read_bag(path: str | Path, topic: str | None = None) -> np.ndarray:
    """Every point of the topic's PointCloud2 messages (in a map frame), concatenated: (N, 3) float64."""
    return next(_grouped(_clouds(Path(path), topic), None))


def bag_chunks(path: str | Path, topic: str | None, chunk_points: int) -> Iterator[np.ndarray]:
    """The topic's points in chunks of about ``chunk_points`` (whole messages)."""
    return _grouped(_clouds(Path(path), topic), chunk_points)


# -- scans in the sensor frame, placed by their poses ----------------------------------------------


def stamp_ns(stamp: Any) -> int:
    """A ``builtin_interfaces/Time`` (ROS 1 and ROS 2 alike in rosbags) as integer nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def _seconds(ns: int) -> str:
    return f"{ns / NS_PER_S:.9f} s"


@dataclass(frozen=True)
class PoseStream:
    """The poses of one frame (``child_frame``) in another (``frame``) over time, to interpolate.

    A pose maps a point of the child frame into the parent frame:
    ``p_frame = R @ p_child + t`` (ROS's convention for Odometry and TF).

    Attributes
    ----------
    topic : str
        Where the poses came from.
    frame : str
        The parent frame (``header.frame_id`` of the poses): the map's frame.
    child_frame : str or None
        The frame the poses move: Odometry's ``child_frame_id``, the TF
        child; None for a ``PoseStamped``, which does not name it.
    stamps_ns : ndarray, shape (k,), int64
        Strictly increasing stamps, nanoseconds.
    translations : ndarray, shape (k, 3), float64
        ``t`` of each pose, metres.
    quaternions : ndarray, shape (k, 4), float64
        The rotation ``R`` of each pose, unit quaternions (x, y, z, w), ROS's order.
    """

    topic: str
    frame: str
    child_frame: str | None
    stamps_ns: np.ndarray
    translations: np.ndarray
    quaternions: np.ndarray

    def covers(self, stamps_ns: np.ndarray) -> np.ndarray:
        """Which stamps (ns) lie within the stream, ends included: (m,) bool."""
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        return (stamps_ns >= self.stamps_ns[0]) & (stamps_ns <= self.stamps_ns[-1])

    def at(self, stamps_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The poses at ``stamps_ns`` (within the stream): linear in translation, slerp in rotation.

        Returns
        -------
        rotations : ndarray, shape (m, 3, 3)
        translations : ndarray, shape (m, 3), metres

        Raises
        ------
        InvalidInputError
            A stamp outside the stream (see :meth:`covers`).
        """
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        if not self.covers(stamps_ns).all():
            raise InvalidInputError(f"{self.topic}: a stamp lies outside the poses "
                                    f"({_seconds(self.stamps_ns[0])} to {_seconds(self.stamps_ns[-1])})")
        rotation, t = self._rotations(stamps_ns)
        return _matrices(rotation, t.shape[0]), t

    def coverage(self) -> str:
        """The stamps the stream covers, for a message about the scans it cannot place."""
        return f"poses on {self.topic} cover {_seconds(self.stamps_ns[0])} to {_seconds(self.stamps_ns[-1])}"

    def _rotations(self, stamps_ns: np.ndarray) -> tuple[Any, np.ndarray]:
        """scipy Rotation(s) and (m, 3) translations at the stamps, unchecked; one pose: that pose for any stamp."""
        wanted = (stamps_ns - self.stamps_ns[0]) / NS_PER_S
        if self.stamps_ns.size == 1:  # one pose covers its own stamp only (a static edge: every stamp)
            return self._interpolator, np.repeat(self.translations, wanted.size, axis=0)
        t = np.column_stack([np.interp(wanted, self._times, self.translations[:, k]) for k in range(3)])
        return self._interpolator(wanted), t

    @cached_property
    def _times(self) -> np.ndarray:
        # Seconds from the first pose: exact to the nanosecond for 104 days of float64.
        return (self.stamps_ns - self.stamps_ns[0]) / NS_PER_S

    @cached_property
    def _interpolator(self) -> Any:
        """scipy's Slerp over the stream (built once: each scan asks for one pose), or the one Rotation."""
        from scipy.spatial.transform import Rotation, Slerp

        rotations = Rotation.from_quat(self.quaternions)  # ROS and scipy both put w last
        return rotations[0] if self.stamps_ns.size == 1 else Slerp(self._times, rotations)


def _matrices(rotation: Any, m: int) -> np.ndarray:
    """(m, 3, 3) matrices of a scipy Rotation holding m rotations, or one rotation repeated m times."""
    matrices = rotation.as_matrix().reshape(-1, 3, 3)
    return np.repeat(matrices, m, axis=0) if matrices.shape[0] == 1 else matrices


class PosedScan(NamedTuple):
    """One scan and the pose of its sensor frame at its stamp.

    Attributes
    ----------
    stamp_ns : int
        ``header.stamp`` of the scan, nanoseconds.
    points : ndarray, shape (n, 3), float64
        The scan in the sensor frame, metres.
    rotation : ndarray, shape (3, 3)
    translation : ndarray, shape (3,)
        The sensor pose in the map frame, metres: ``p_map = rotation @ p + translation``
        (:func:`apply_pose`).
    """

    stamp_ns: int
    points: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray


def apply_pose(points: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Points of the sensor frame in the map frame: ``rotation @ p + translation`` for each row.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Metres, in the sensor frame.
    rotation : ndarray, shape (3, 3)
    translation : ndarray, shape (3,)
        Metres.

    Returns
    -------
    ndarray, shape (n, 3), float64
    """
    return np.asarray(points, dtype=np.float64) @ np.asarray(rotation, dtype=np.float64).T + np.asarray(translation)


def _pose_fields(kind: str, msg: Any) -> Iterator[tuple[Any, str, str | None, Any, Any]]:
    """(stamp, parent frame, child frame, translation, quaternion) of each pose a message holds."""
    if kind == "tf":
        for tf in msg.transforms:
            yield tf.header.stamp, tf.header.frame_id, tf.child_frame_id, tf.transform.translation, \
                tf.transform.rotation
        return
    pose = {"odometry": lambda m: m.pose.pose, "pose": lambda m: m.pose,
            "pose_covariance": lambda m: m.pose.pose}[kind](msg)
    child = msg.child_frame_id if kind == "odometry" else None
    yield msg.header.stamp, msg.header.frame_id, child, pose.position, pose.orientation


def read_poses(path: str | Path, pose_topic: str, *, child_frame: str | None = None) -> PoseStream:
    """The pose stream of ``pose_topic``: every pose of ``child_frame``, checked, sorted by stamp.

    Parameters
    ----------
    path : path
        The bag.
    pose_topic : str
        A ``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped``,
        ``geometry_msgs/PoseWithCovarianceStamped`` or ``tf2_msgs/TFMessage`` topic.
    child_frame : str, optional
        The frame whose poses are wanted (the scans' frame). A TF topic
        keeps the transforms of this child; an Odometry topic must move it
        (its ``child_frame_id``). A PoseStamped does not say which frame it
        poses and is taken as the pose of ``child_frame``.

    Raises
    ------
    InvalidInputError
        No such topic, a type that holds no pose, no pose (of the child
        frame), a pose with a NaN or infinite value or a quaternion whose
        norm is not 1 within :data:`QUATERNION_TOLERANCE` (named by its
        message index on the topic, from 0), poses in several parent frames,
        or an Odometry child frame other than ``child_frame``.
    """
    path = Path(path)
    stamps, translations, quaternions = [], [], []
    frame: str | None = None
    named: str | None = None  # the child frame the poses name (Odometry, TF); a PoseStamped names none
    children: set[str] = set()
    reader = _opened(path)
    try:
        connections = [c for c in reader.connections if c.topic == pose_topic]
        if not connections:
            raise InvalidInputError(f"{path}: no pose topic {pose_topic!r} in the bag ({_topics(reader.connections)})")
        kinds = {c.msgtype for c in connections} - set(POSE_TYPES)
        if kinds:
            raise InvalidInputError(
                f"{path}: {pose_topic} holds {', '.join(sorted(kinds))}, not poses; a pose topic holds "
                f"nav_msgs/Odometry, geometry_msgs/PoseStamped, geometry_msgs/PoseWithCovarianceStamped or "
                f"tf2_msgs/TFMessage")
        for index, (connection, _, raw) in enumerate(_records(path, reader, connections)):
            try:
                msg = reader.deserialize(raw, connection.msgtype)
            except Exception as exc:  # noqa: BLE001 - a damaged message
                raise InvalidInputError(f"{path}: cannot decode message {index} on {pose_topic}: {exc}") from None
            kind = POSE_TYPES[connection.msgtype]
            for stamp, parent, child, position, orientation in _pose_fields(kind, msg):
                if kind == "tf":
                    children.add(child)
                    if child != child_frame and child_frame is not None:
                        continue
                elif kind == "odometry" and child != (child_frame if child_frame is not None else named or child):
                    raise InvalidInputError(
                        f"{path}: message {index} on {pose_topic} poses frame {child!r} (child_frame_id) but the "
                        f"scans are in frame {child_frame if child_frame is not None else named!r}; dftpcc applies "
                        f"no sensor extrinsics, so the poses must be those of the scans' frame")
                named = child
                ns = stamp_ns(stamp)
                where = _where(path, index, pose_topic, ns)
                t = np.array([position.x, position.y, position.z], dtype=np.float64)
                q = _unit(lambda: where, t, np.array([orientation.x, orientation.y, orientation.z, orientation.w],
                                             dtype=np.float64), "the pose", "the orientation")
                if frame is None:
                    frame = parent
                elif parent != frame:
                    raise InvalidInputError(f"{where}: a pose in frame {parent!r} after poses in frame {frame!r}; "
                                            f"the poses must all be in one map frame")
                stamps.append(ns)
                translations.append(t)
                quaternions.append(q)
    finally:
        reader.close()
    if not stamps:
        if children:
            raise InvalidInputError(f"{path}: no transform on {pose_topic} has child frame {child_frame!r}, the "
                                    f"scans' frame (child frames there: {', '.join(sorted(children))})")
        raise InvalidInputError(f"{path}: no pose on {pose_topic}")
    return _stream(pose_topic, frame or "", named, stamps, translations, quaternions)


def _where(path: Path, index: int, topic: str, ns: int) -> str:
    """Which message a bad pose came from: its index on the topic (from 0) and its stamp."""
    return f"{path}: message {index} on {topic} (stamp {_seconds(ns)})"


def _unit(where: Callable[[], str], t: np.ndarray, q: np.ndarray, pose: str, rotation: str) -> np.ndarray:
    """``q`` made a unit quaternion; a NaN or infinite value, or a norm not 1, refused as ``where()``'s."""
    if not (np.isfinite(t).all() and np.isfinite(q).all()):
        raise InvalidInputError(f"{where()}: {pose} has a NaN or infinite value")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUATERNION_TOLERANCE:
        raise InvalidInputError(f"{where()}: {rotation} is not a unit quaternion (norm {norm:.6g})")
    return q / norm


def _stream(topic: str, frame: str, child: str | None, stamps: list[int], translations: list[np.ndarray],
            quaternions: list[np.ndarray]) -> PoseStream:
    """Checked poses as a stream, sorted by stamp; of poses sharing a stamp the first is kept (Slerp needs
    increasing times)."""
    order = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
    sorted_stamps = np.asarray(stamps, dtype=np.int64)[order]
    keep = order[np.concatenate([[True], np.diff(sorted_stamps) > 0])]
    return PoseStream(topic, frame, child, np.asarray(stamps, dtype=np.int64)[keep],
                      np.asarray(translations)[keep], np.asarray(quaternions)[keep])


# -- TF: a tree of transforms, composed from the scans' frame up to the map frame ----------------------


def _frame_name(frame: str) -> str:
    """A frame as tf2 compares it: without a leading ``/`` (ROS 1's tf wrote ``/base_link``)."""
    return frame[1:] if frame.startswith("/") else frame


@dataclass(frozen=True)
class TfEdge:
    """One edge of a TF tree: the pose of ``child`` in ``parent`` over time, or fixed.

    Attributes
    ----------
    parent, child : str
        The frames, without a leading ``/``.
    poses : PoseStream
        Its transforms (``p_parent = R @ p_child + t``), checked and sorted;
        a static edge holds one, the last it was given (as tf2 keeps it).
    static : bool
        Whether it came from the static topic (``/tf_static``): the same at every stamp.
    """

    parent: str
    child: str
    poses: PoseStream
    static: bool

    def _at(self, stamps_ns: np.ndarray) -> tuple[Any, np.ndarray]:
        """scipy Rotation(s) and (m, 3) translations, metres, at the stamps (covered ones, for a dynamic edge)."""
        return self.poses._rotations(stamps_ns)


@dataclass(frozen=True)
class TfChain:
    """The transforms from a scan's frame up to the map frame, composed at each stamp.

    Placing a point: ``p_map = T_1 @ T_2 @ ... @ T_n @ p_scan`` where ``T_n``
    is the edge from the scan's frame to its parent and ``T_1`` the edge into
    the map frame; each dynamic edge is interpolated at the stamp (translation
    linear, rotation slerp), each static edge constant. It stands where a
    :class:`PoseStream` does (:meth:`covers`, :meth:`at`).

    Attributes
    ----------
    topic : str
        The TF topic (``/tf``).
    frame : str
        The map frame: the root of the scans' tree, or the frame asked for.
    child_frame : str
        The scans' frame, as their messages name it.
    edges : tuple of TfEdge
        From the scans' frame up; empty when the scans are in the map frame.
    """

    topic: str
    frame: str
    child_frame: str
    edges: tuple[TfEdge, ...]

    @property
    def _moving(self) -> list[TfEdge]:
        return [e for e in self.edges if not e.static]

    def covers(self, stamps_ns: np.ndarray) -> np.ndarray:
        """Which stamps (ns) every dynamic edge of the chain covers, ends included: (m,) bool."""
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        covered = np.ones(stamps_ns.shape, dtype=bool)
        for edge in self._moving:
            covered &= edge.poses.covers(stamps_ns)
        return covered

    def at(self, stamps_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The composed transforms at ``stamps_ns`` (covered ones, see :meth:`covers`).

        Returns
        -------
        rotations : ndarray, shape (m, 3, 3)
        translations : ndarray, shape (m, 3), metres

        Raises
        ------
        InvalidInputError
            A stamp outside a dynamic edge.
        """
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        if not self.covers(stamps_ns).all():
            raise InvalidInputError(f"{self.topic}: a stamp lies outside the transforms ({self.coverage()})")
        if not self.edges:
            return np.repeat(np.eye(3)[None], stamps_ns.size, axis=0), np.zeros((stamps_ns.size, 3))
        rotation, t = self.edges[0]._at(stamps_ns)
        for edge in self.edges[1:]:  # one edge up: p_parent = R_e (R p + t) + t_e
            r, te = edge._at(stamps_ns)
            rotation, t = r * rotation, r.apply(t).reshape(-1, 3) + te
        return _matrices(rotation, stamps_ns.size), t

    def coverage(self) -> str:
        """The stamps every dynamic edge covers, and each edge's, for a message about the scans it cannot place."""
        moving = self._moving
        if not moving:
            return f"the transforms on {self.topic} from {self.child_frame!r} to {self.frame!r} are all static"
        each = "; ".join(f"{e.parent} -> {e.child} {_seconds(e.poses.stamps_ns[0])} to "
                         f"{_seconds(e.poses.stamps_ns[-1])}" for e in moving)
        first = max(int(e.poses.stamps_ns[0]) for e in moving)
        last = min(int(e.poses.stamps_ns[-1]) for e in moving)
        if first > last:
            return f"the dynamic transforms on {self.topic} never cover one stamp together ({each})"
        return f"transforms on {self.topic} cover {_seconds(first)} to {_seconds(last)} ({each})"


@dataclass
class _Records:
    """Every transform of one edge as the bag holds it, unchecked: only the edges scans need are checked."""

    topic: str
    parent: str
    child: str
    static: bool
    first: int  # index of its first message on the topic, to name it
    stamps: array = field(default_factory=lambda: array("q"))  # ns
    indices: array = field(default_factory=lambda: array("q"))  # of the message on the topic, from 0
    values: array = field(default_factory=lambda: array("d"))  # x, y, z (m), qx, qy, qz, qw of each

    def edge(self, path: Path) -> TfEdge:
        """The checked edge; a NaN or infinite value or a non-unit rotation refused, naming its message."""
        rows = np.frombuffer(self.values, dtype=np.float64).reshape(-1, 7)
        what = f"the transform {self.parent} -> {self.child}"
        stamps, translations, quaternions = [], [], []
        for ns, index, row in zip(self.stamps, self.indices, rows):
            t = row[:3].copy()  # fresh arrays, as read_poses makes them: the same norms to the bit
            q = _unit(lambda: _where(path, index, self.topic, ns), t, row[3:].copy(), what, f"the rotation of {what}")
            stamps.append(ns)
            translations.append(t)
            quaternions.append(q)
        if self.static:  # tf2 keeps the last static transform of an edge
            stamps, translations, quaternions = [stamps[-1]], translations[-1:], quaternions[-1:]
        return TfEdge(self.parent, self.child, _stream(self.topic, self.parent, self.child, stamps, translations,
                                                       quaternions), self.static)


class TfTree:
    """The TF tree of a bag: every edge parent -> child on the TF topic and on its static topic.

    Built by :func:`read_tf_tree`; :meth:`chain` composes the edges that
    place one frame in the map frame. Only the edges of a chain are checked,
    so a broken branch the scans do not hang from does not refuse the bag.

    Attributes
    ----------
    path : Path
        The bag.
    topic : str
        The TF topic (``/tf``).
    topics : tuple of str
        The topics read: the TF topic and, if the bag has it, its static topic.
    frames : tuple of str
        Every frame the transforms name, without a leading ``/``, sorted.
    """

    def __init__(self, path: Path, topic: str, topics: tuple[str, ...], records: list[_Records]):
        self.path, self.topic, self.topics = path, topic, topics
        self._parents: dict[str, list[_Records]] = {}
        for record in records:
            self._parents.setdefault(record.child, []).append(record)
        self.frames = tuple(sorted({r.child for r in records} | {r.parent for r in records}))

    def chain(self, frame: str, map_frame: str | None = None) -> TfChain:
        """The edges from ``frame`` up to ``map_frame`` (default: the root of its tree), checked.

        Raises
        ------
        InvalidInputError
            ``frame`` in no transform, not connected to ``map_frame``, a
            frame of the chain with two parents, a cycle, or a transform of
            the chain with a NaN or infinite value or a non-unit quaternion
            (named by its message index on its topic, from 0).
        """
        start = _frame_name(frame)
        goal = None if map_frame is None else _frame_name(map_frame)
        where = " and ".join(self.topics)
        known = f"frames there: {', '.join(self.frames)}" if self.frames else "it holds no transform"
        if start != goal and start not in self.frames:
            raise InvalidInputError(f"{self.path}: no transform on {where} has child frame {frame!r}, the scans' "
                                    f"frame, so nothing places them ({known})")
        edges: list[TfEdge] = []
        seen = [start]
        while seen[-1] != goal:
            records = self._parents.get(seen[-1], [])
            if not records:
                if goal is None:  # the root of the tree
                    break
                raise InvalidInputError(
                    f"{self.path}: the scans' frame {frame!r} is not connected to the map frame {map_frame!r} on "
                    f"{where}: its tree goes {' -> '.join(seen)} and ends there ({known})")
            if len(records) > 1:
                parents = ", ".join(f"{r.parent!r} on {r.topic} (from message {r.first})" for r in records)
                raise InvalidInputError(
                    f"{self.path}: frame {seen[-1]!r} has {len(records)} parents, {parents}; TF allows one parent "
                    f"per frame, moving on {self.topic} or fixed on {self.topic}{STATIC_SUFFIX}")
            record = records[0]
            if record.parent in seen:
                cycle = seen[seen.index(record.parent):] + [record.parent]
                raise InvalidInputError(f"{self.path}: the transforms on {where} form a cycle, "
                                        f"{' -> '.join(cycle)}; TF frames must form a tree")
            edges.append(record.edge(self.path))
            seen.append(record.parent)
        return TfChain(self.topic, seen[-1], frame, tuple(edges))


def read_tf_tree(path: str | Path, tf_topic: str = "/tf") -> TfTree:
    """The TF tree of a bag: the transforms on ``tf_topic`` and on its static topic (``/tf_static``), if present.

    Every message of the static topic is read (ROS 1 records it latched,
    ROS 2 with transient-local QoS, often once at the start); its edges are
    constant. A ``tf_topic`` that is itself static (``/tf_static``) gives a
    tree of static edges.

    Parameters
    ----------
    path : path
        The bag.
    tf_topic : str
        The ``tf2_msgs/TFMessage`` topic of the dynamic transforms.

    Raises
    ------
    InvalidInputError
        No such topic, or it (or its static topic) holds another type.
    """
    path = Path(path)
    static_topic = tf_topic + STATIC_SUFFIX
    records: dict[tuple[str, str, bool], _Records] = {}
    counts: dict[str, int] = {}
    reader = _opened(path)
    try:
        connections = [c for c in reader.connections if c.topic in (tf_topic, static_topic)]
        if not any(c.topic == tf_topic for c in connections):
            raise InvalidInputError(f"{path}: no pose topic {tf_topic!r} in the bag ({_topics(reader.connections)})")
        kinds = {f"{c.topic} ({c.msgtype})" for c in connections if c.msgtype not in TF_TYPES}
        if kinds:
            raise InvalidInputError(f"{path}: a TF topic holds tf2_msgs/TFMessage, not {', '.join(sorted(kinds))}")
        topics = tuple(t for t in (tf_topic, static_topic) if any(c.topic == t for c in connections))
        for connection, _, raw in _records(path, reader, connections):
            topic = connection.topic
            index = counts.get(topic, 0)
            counts[topic] = index + 1
            try:
                msg = reader.deserialize(raw, connection.msgtype)
            except Exception as exc:  # noqa: BLE001 - a damaged message
                raise InvalidInputError(f"{path}: cannot decode message {index} on {topic}: {exc}") from None
            static = topic.endswith(STATIC_SUFFIX)
            for tf in msg.transforms:
                parent, child = _frame_name(tf.header.frame_id), _frame_name(tf.child_frame_id)
                record = records.get((child, parent, static))
                if record is None:
                    record = records[child, parent, static] = _Records(topic, parent, child, static, index)
                t, q = tf.transform.translation, tf.transform.rotation
                record.stamps.append(stamp_ns(tf.header.stamp))
                record.indices.append(index)
                record.values.extend((t.x, t.y, t.z, q.x, q.y, q.z, q.w))
    finally:
        reader.close()
    return TfTree(path, tf_topic, topics, list(records.values()))


def _scan_poses(path: Path, pose_topic: str, scan_frame: str, map_frame: str | None) -> PoseStream | TfChain:
    """What places scans in ``scan_frame``: a TF topic's chain up to the map frame, or the pose stream."""
    reader = _opened(path)
    try:
        types = {c.msgtype for c in reader.connections if c.topic == pose_topic}
    finally:
        reader.close()
    if types and types <= TF_TYPES:
        return read_tf_tree(path, pose_topic).chain(scan_frame, map_frame)
    poses = read_poses(path, pose_topic, child_frame=scan_frame)
    if map_frame is not None and _frame_name(map_frame) != _frame_name(poses.frame):
        raise InvalidInputError(f"{path}: the poses on {pose_topic} are in frame {poses.frame!r}, not the map frame "
                                f"{map_frame!r} asked for; only a TF topic (/tf) composes transforms into another "
                                f"frame")
    return poses


def _first_frame(path: Path, topic: str | None) -> str:
    """The frame of the topic's first PointCloud2 message (the scans' sensor frame)."""
    for _, _, msg in _messages(path, topic):
        return msg.header.frame_id
    raise InvalidInputError(f"{path}: no message on the PointCloud2 topic")


def _placed(path: Path, topic: str | None, poses: PoseStream | TfChain, *, warn: bool) -> Iterator[PosedScan]:
    """The scans of ``topic`` within ``poses``, each with its pose; the others skipped, then reported."""
    skipped: list[int] = []
    placed = 0
    frame = poses.child_frame
    for index, (name, _, msg) in enumerate(_messages(path, topic)):
        if frame is None:
            frame = msg.header.frame_id
        if msg.header.frame_id != frame:
            why = ("the transforms were composed for the first scan's frame: the scans of a topic share one frame"
                   if isinstance(poses, TfChain) else "dftpcc applies no other transform")
            raise InvalidInputError(
                f"{path}: scan {index} on {name} is in frame {msg.header.frame_id!r}, but the poses on "
                f"{poses.topic} are those of frame {frame!r}; {why}")
        stamp = stamp_ns(msg.header.stamp)
        if not poses.covers(np.array([stamp]))[0]:
            skipped.append(stamp)
            continue
        rotation, translation = poses.at(np.array([stamp]))
        placed += 1
        yield PosedScan(stamp, _xyz(path, name, msg), rotation[0], translation[0])
    span = poses.coverage()
    if skipped and not placed:
        raise InvalidInputError(f"{path}: none of the {len(skipped)} scans falls within the poses "
                                f"(scans stamped {_seconds(min(skipped))} to {_seconds(max(skipped))}; {span})")
    if skipped and warn:
        warnings.warn(f"{path}: skipped {len(skipped)} of {len(skipped) + placed} scans whose stamps lie outside "
                      f"the poses (stamps {_seconds(min(skipped))} to {_seconds(max(skipped))}; {span})",
                      UnposedScanWarning, stacklevel=2)


def posed_scans(path: str | Path, points_topic: str | None = None, pose_topic: str = "/odom", *,
                map_frame: str | None = None) -> Iterator[PosedScan]:
    """The scans of a bag recorded in the sensor frame, each with its pose at its stamp, in bag order.

    The next stage (a map builder) consumes these; :func:`apply_pose` places
    a scan. Scans outside the pose stream are skipped and reported at the
    end by one :class:`UnposedScanWarning` (how many, their stamps).

    Parameters
    ----------
    path : path
        A ROS 1 ``.bag`` or a ROS 2 bag folder (sqlite3 or MCAP).
    points_topic : str, optional
        The PointCloud2 topic (default: the bag's only one).
    pose_topic : str
        The poses of the scans' frame (see :func:`read_poses`), or a TF topic
        (``/tf``): its tree, with the static topic (``/tf_static``), composed
        from the scans' frame up (:func:`read_tf_tree`, :meth:`TfTree.chain`).
    map_frame : str, optional
        TF only: the frame to place the scans in (default: the root of their tree).

    Yields
    ------
    PosedScan
        ``(stamp_ns, points (n, 3) in the sensor frame, rotation (3, 3), translation (3,))``.

    Raises
    ------
    InvalidInputError
        As :func:`read_poses` and :meth:`TfTree.chain`; a scan in another
        frame than the poses', no scan within the poses, or a ``map_frame``
        other than the frame of poses that are not TF.
    """
    path = Path(path)
    poses = _scan_poses(path, pose_topic, _first_frame(path, points_topic), map_frame)
    yield from _placed(path, points_topic, poses, warn=True)
