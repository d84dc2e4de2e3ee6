"""Poses over time: a pose topic read from a bag (Odometry, PoseStamped, PoseWithCovarianceStamped),
interpolated at a scan's stamp (linear translation, spherical rotation), and applied to its points.

A pose maps a point of the child frame into the parent frame, ``p_frame = R @ p_child + t``
(ROS's convention for Odometry and TF). A live node (:mod:`dftpcc.live`) builds a
:class:`PoseStream` from the messages it receives; a bag's comes from :func:`read_poses`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, Callable, Iterator, NamedTuple

import numpy as np

from ..errors import InvalidInputError
from .bag import NS_PER_S, opened, raw_messages, seconds, stamp_ns, topics_text

__all__ = ["POSE_TYPES", "QUATERNION_TOLERANCE", "PoseStream", "PosedScan", "apply_pose", "read_poses",
           "rotation_matrices", "unit_quaternion", "message_where", "pose_stream"]


#: Message types a pose topic may hold (ROS 2 and ROS 1 spellings) -> how the pose is read.
POSE_TYPES = {
    "nav_msgs/msg/Odometry": "odometry", "nav_msgs/Odometry": "odometry",
    "geometry_msgs/msg/PoseStamped": "pose", "geometry_msgs/PoseStamped": "pose",
    "geometry_msgs/msg/PoseWithCovarianceStamped": "pose_covariance",
    "geometry_msgs/PoseWithCovarianceStamped": "pose_covariance",
    "tf2_msgs/msg/TFMessage": "tf", "tf2_msgs/TFMessage": "tf",
}


#: A pose quaternion whose norm is farther than this from 1 is refused (float32 poses stay within 1e-6).
QUATERNION_TOLERANCE = 1e-3


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
                                    f"({seconds(self.stamps_ns[0])} to {seconds(self.stamps_ns[-1])})")
        rotation, t = self._rotations(stamps_ns)
        return rotation_matrices(rotation, t.shape[0]), t

    def coverage(self) -> str:
        """The stamps the stream covers, for a message about the scans it cannot place."""
        return f"poses on {self.topic} cover {seconds(self.stamps_ns[0])} to {seconds(self.stamps_ns[-1])}"

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


def rotation_matrices(rotation: Any, m: int) -> np.ndarray:
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
    reader = opened(path)
    try:
        connections = [c for c in reader.connections if c.topic == pose_topic]
        if not connections:
            raise InvalidInputError(f"{path}: no pose topic {pose_topic!r} in the bag ({topics_text(reader.connections)})")
        kinds = {c.msgtype for c in connections} - set(POSE_TYPES)
        if kinds:
            raise InvalidInputError(
                f"{path}: {pose_topic} holds {', '.join(sorted(kinds))}, not poses; a pose topic holds "
                f"nav_msgs/Odometry, geometry_msgs/PoseStamped, geometry_msgs/PoseWithCovarianceStamped or "
                f"tf2_msgs/TFMessage")
        for index, (connection, _, raw) in enumerate(raw_messages(path, reader, connections)):
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
                where = message_where(path, index, pose_topic, ns)
                t = np.array([position.x, position.y, position.z], dtype=np.float64)
                q = unit_quaternion(lambda: where, t, np.array([orientation.x, orientation.y, orientation.z, orientation.w],
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
    return pose_stream(pose_topic, frame or "", named, stamps, translations, quaternions)


def message_where(path: Path, index: int, topic: str, ns: int) -> str:
    """Which message a bad pose came from: its index on the topic (from 0) and its stamp."""
    return f"{path}: message {index} on {topic} (stamp {seconds(ns)})"


def unit_quaternion(where: Callable[[], str], t: np.ndarray, q: np.ndarray, pose: str, rotation: str) -> np.ndarray:
    """``q`` made a unit quaternion; a NaN or infinite value, or a norm not 1, refused as ``where()``'s."""
    if not (np.isfinite(t).all() and np.isfinite(q).all()):
        raise InvalidInputError(f"{where()}: {pose} has a NaN or infinite value")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUATERNION_TOLERANCE:
        raise InvalidInputError(f"{where()}: {rotation} is not a unit quaternion (norm {norm:.6g})")
    return q / norm


def pose_stream(topic: str, frame: str, child: str | None, stamps: list[int], translations: list[np.ndarray],
            quaternions: list[np.ndarray]) -> PoseStream:
    """Checked poses as a stream, sorted by stamp; of poses sharing a stamp the first is kept (Slerp needs
    increasing times)."""
    order = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
    sorted_stamps = np.asarray(stamps, dtype=np.int64)[order]
    keep = order[np.concatenate([[True], np.diff(sorted_stamps) > 0])]
    return PoseStream(topic, frame, child, np.asarray(stamps, dtype=np.int64)[keep],
                      np.asarray(translations)[keep], np.asarray(quaternions)[keep])

