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
from contextlib import contextmanager
from pathlib import Path
from typing import Any, ClassVar, Iterator

import numpy as np

from ..errors import DftpccWarning, InvalidInputError
from .bag import any_reader, bag_folder, opened, raw_messages, seconds, size_bound, stamp_ns, topics_text
from .pointcloud2 import POINTCLOUD2, pointcloud2_xyz
from .poses import POSE_TYPES, PosedScan, PoseStream, apply_pose, read_poses
from .reader import Reader
from .tf import TF_TYPES, TfChain, frame_name, read_tf_tree

__all__ = ["BagReader", "UnposedScanWarning", "MAP_FRAME_WORDS", "SMALLEST_POINT_BYTES", "read_bag", "bag_chunks",
           "is_map_frame", "posed_scans"]

#: Words that make a frame name a map frame (REP 105's map, odom, earth; world; UTM and ENU frames;
#: LOAM and FAST-LIO's camera_init): scans in another frame need a pose topic.
MAP_FRAME_WORDS = frozenset({"map", "world", "odom", "earth", "utm", "enu", "global", "camera_init"})
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
        any_reader()  # a missing package is said before any work
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


@contextmanager
def _open(path: Path, topic: str | None) -> Iterator[tuple[Any, list[Any]]]:
    """The reader and the connections of the chosen PointCloud2 topic."""
    reader = opened(path)
    try:
        clouds = sorted({c.topic for c in reader.connections if c.msgtype in POINTCLOUD2})
        if not clouds:
            raise InvalidInputError(f"{path}: the bag has no PointCloud2 topic ({topics_text(reader.connections)})")
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


def _messages(path: Path, topic: str | None) -> Iterator[tuple[str, Any, Any]]:
    """(topic, connections of the bag, deserialised message) of each PointCloud2 message of the topic, in order."""
    with _open(path, topic) as (reader, connections):
        for connection, _, raw in raw_messages(path, reader, connections):
            try:
                msg = reader.deserialize(raw, connection.msgtype)
            except Exception as exc:  # noqa: BLE001 - a damaged message
                raise InvalidInputError(f"{path}: cannot decode a message on {connection.topic}: {exc}") from None
            yield connection.topic, reader.connections, msg


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
        f"name the topic of their poses with --pose-topic (pose_topic=); {found}; {topics_text(connections)}")


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




# -- TF: a tree of transforms, composed from the scans' frame up to the map frame ----------------------


def _scan_poses(path: Path, pose_topic: str, scan_frame: str, map_frame: str | None) -> PoseStream | TfChain:
    """What places scans in ``scan_frame``: a TF topic's chain up to the map frame, or the pose stream."""
    reader = opened(path)
    try:
        types = {c.msgtype for c in reader.connections if c.topic == pose_topic}
    finally:
        reader.close()
    if types and types <= TF_TYPES:
        return read_tf_tree(path, pose_topic).chain(scan_frame, map_frame)
    poses = read_poses(path, pose_topic, child_frame=scan_frame)
    if map_frame is not None and frame_name(map_frame) != frame_name(poses.frame):
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
                                f"(scans stamped {seconds(min(skipped))} to {seconds(max(skipped))}; {span})")
    if skipped and warn:
        warnings.warn(f"{path}: skipped {len(skipped)} of {len(skipped) + placed} scans whose stamps lie outside "
                      f"the poses (stamps {seconds(min(skipped))} to {seconds(max(skipped))}; {span})",
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
