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

Points of a message that says ``is_dense: false`` (it may hold invalid
points, as organized lidar scans do for missing returns) and have a NaN or
infinite coordinate are those invalid points and are left out; a dense
message with one is refused like any non-finite cloud.
"""

from __future__ import annotations

import re
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, ClassVar, Iterator, NamedTuple

import numpy as np

from ..errors import DftpccWarning, InvalidInputError, MissingDependencyError
from .reader import Reader

__all__ = ["POINTCLOUD2", "POSE_TYPES", "MAP_FRAME_WORDS", "QUATERNION_TOLERANCE", "BagReader", "PoseStream",
           "PosedScan", "UnposedScanWarning", "bag_folder", "pointcloud2_xyz", "read_bag", "bag_chunks",
           "size_bound", "is_map_frame", "read_poses", "posed_scans", "apply_pose", "stamp_ns"]

POINTCLOUD2 = ("sensor_msgs/msg/PointCloud2", "sensor_msgs/PointCloud2")
#: Message types a pose topic may hold (ROS 2 and ROS 1 spellings) -> how the pose is read.
POSE_TYPES = {
    "nav_msgs/msg/Odometry": "odometry", "nav_msgs/Odometry": "odometry",
    "geometry_msgs/msg/PoseStamped": "pose", "geometry_msgs/PoseStamped": "pose",
    "geometry_msgs/msg/PoseWithCovarianceStamped": "pose_covariance",
    "geometry_msgs/PoseWithCovarianceStamped": "pose_covariance",
    "tf2_msgs/msg/TFMessage": "tf", "tf2_msgs/TFMessage": "tf",
}
#: Words that make a frame name a map frame (REP 105's map, odom, earth; world; UTM and ENU frames;
#: LOAM and FAST-LIO's camera_init): scans in another frame need a pose topic.
MAP_FRAME_WORDS = frozenset({"map", "world", "odom", "earth", "utm", "enu", "global", "camera_init"})
#: A pose quaternion whose norm is farther than this from 1 is refused (float32 poses stay within 1e-6).
QUATERNION_TOLERANCE = 1e-3
#: Nanoseconds per second, for stamps.
NS_PER_S = 1_000_000_000
#: PointField datatype codes -> numpy types.
_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
INSTALL_HINT = "pip install 'dftpcc[ros]' (the rosbags package)"
#: Bytes of the smallest point a PointCloud2 holds (float32 x, y, z): a bag's size over it bounds its points.
SMALLEST_POINT_BYTES = 12


class UnposedScanWarning(DftpccWarning):
    """Scans whose stamp falls outside the pose stream were skipped (how many, which stamps)."""


class BagReader(Reader):
    """A ROS 1 ``.bag`` or a ROS 2 bag folder: the PointCloud2 messages of ``topic``, whole messages per chunk.

    With ``pose_topic`` each message is a scan in the sensor frame, placed
    in the poses' frame (:func:`posed_scans`); the poses are read once, when
    the reader opens, and every pass reuses them. A bag has no point count
    (:attr:`stored_points` is None); its size over :data:`SMALLEST_POINT_BYTES`
    bounds it (:attr:`points_bound`).
    """

    options: ClassVar[frozenset[str]] = frozenset({"topic", "pose_topic"})

    def _locate(self) -> None:
        bag_folder(self.path)  # a file, or a ROS 2 folder

    def _open(self) -> None:
        _any_reader()  # a missing package is said before any work
        self.poses: PoseStream | None = None
        self._warned = False
        if self.pose_topic is not None:
            self.poses = read_poses(self.path, self.pose_topic, child_frame=_first_frame(self.path, self.topic))

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
        wanted = (stamps_ns - self.stamps_ns[0]) / NS_PER_S
        if self.stamps_ns.size == 1:  # one pose covers its own stamp only
            return (np.repeat(self._interpolator.as_matrix().reshape(1, 3, 3), wanted.size, axis=0),
                    np.repeat(self.translations, wanted.size, axis=0))
        t = np.column_stack([np.interp(wanted, self._times, self.translations[:, k]) for k in range(3)])
        return self._interpolator(wanted).as_matrix().reshape(-1, 3, 3), t

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
                where = f"{path}: message {index} on {pose_topic} (stamp {_seconds(stamp_ns(stamp))})"
                t = np.array([position.x, position.y, position.z], dtype=np.float64)
                q = np.array([orientation.x, orientation.y, orientation.z, orientation.w], dtype=np.float64)
                if not (np.isfinite(t).all() and np.isfinite(q).all()):
                    raise InvalidInputError(f"{where}: the pose has a NaN or infinite value")
                norm = float(np.linalg.norm(q))
                if abs(norm - 1.0) > QUATERNION_TOLERANCE:
                    raise InvalidInputError(f"{where}: the orientation is not a unit quaternion (norm {norm:.6g})")
                if frame is None:
                    frame = parent
                elif parent != frame:
                    raise InvalidInputError(f"{where}: a pose in frame {parent!r} after poses in frame {frame!r}; "
                                            f"the poses must all be in one map frame")
                stamps.append(stamp_ns(stamp))
                translations.append(t)
                quaternions.append(q / norm)
    finally:
        reader.close()
    if not stamps:
        if children:
            raise InvalidInputError(f"{path}: no transform on {pose_topic} has child frame {child_frame!r}, the "
                                    f"scans' frame (child frames there: {', '.join(sorted(children))})")
        raise InvalidInputError(f"{path}: no pose on {pose_topic}")
    # Sorted by stamp; of poses sharing a stamp the first is kept (Slerp needs increasing times).
    order = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
    sorted_stamps = np.asarray(stamps, dtype=np.int64)[order]
    keep = order[np.concatenate([[True], np.diff(sorted_stamps) > 0])]
    return PoseStream(pose_topic, frame or "", named, np.asarray(stamps, dtype=np.int64)[keep],
                      np.asarray(translations)[keep], np.asarray(quaternions)[keep])


def _first_frame(path: Path, topic: str | None) -> str:
    """The frame of the topic's first PointCloud2 message (the scans' sensor frame)."""
    for _, _, msg in _messages(path, topic):
        return msg.header.frame_id
    raise InvalidInputError(f"{path}: no message on the PointCloud2 topic")


def _placed(path: Path, topic: str | None, poses: PoseStream, *, warn: bool) -> Iterator[PosedScan]:
    """The scans of ``topic`` within ``poses``, each with its pose; the others skipped, then reported."""
    skipped: list[int] = []
    placed = 0
    frame = poses.child_frame
    for index, (name, _, msg) in enumerate(_messages(path, topic)):
        if frame is None:
            frame = msg.header.frame_id
        if msg.header.frame_id != frame:
            raise InvalidInputError(
                f"{path}: scan {index} on {name} is in frame {msg.header.frame_id!r}, but the poses on "
                f"{poses.topic} are those of frame {frame!r}; dftpcc applies no other transform")
        stamp = stamp_ns(msg.header.stamp)
        if not poses.covers(np.array([stamp]))[0]:
            skipped.append(stamp)
            continue
        rotation, translation = poses.at(np.array([stamp]))
        placed += 1
        yield PosedScan(stamp, _xyz(path, name, msg), rotation[0], translation[0])
    span = f"poses on {poses.topic} cover {_seconds(poses.stamps_ns[0])} to {_seconds(poses.stamps_ns[-1])}"
    if skipped and not placed:
        raise InvalidInputError(f"{path}: none of the {len(skipped)} scans falls within the poses "
                                f"(scans stamped {_seconds(min(skipped))} to {_seconds(max(skipped))}; {span})")
    if skipped and warn:
        warnings.warn(f"{path}: skipped {len(skipped)} of {len(skipped) + placed} scans whose stamps lie outside "
                      f"the poses (stamps {_seconds(min(skipped))} to {_seconds(max(skipped))}; {span})",
                      UnposedScanWarning, stacklevel=2)


def posed_scans(path: str | Path, points_topic: str | None = None, pose_topic: str = "/odom") -> Iterator[PosedScan]:
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
        The poses of the scans' frame (see :func:`read_poses`).

    Yields
    ------
    PosedScan
        ``(stamp_ns, points (n, 3) in the sensor frame, rotation (3, 3), translation (3,))``.

    Raises
    ------
    InvalidInputError
        As :func:`read_poses`; a scan in another frame than the poses', or
        no scan within the poses.
    """
    path = Path(path)
    poses = read_poses(path, pose_topic, child_frame=_first_frame(path, points_topic))
    yield from _placed(path, points_topic, poses, warn=True)
