"""A TF topic read as a robot records it: a tree of transforms, composed from a scan's frame up.

Dynamic edges on ``/tf`` (``map -> odom`` from SLAM, ``odom -> base_link`` from odometry) are
interpolated as pose streams are (:class:`~dftpcc.io.poses.PoseStream`); fixed extrinsics on
``/tf_static`` (every message of it, whether ROS 1 latched it or ROS 2 offered it
transient-local) are constant. A frame with two parents, a cycle, or a frame not connected to
the map frame is refused. Frame names are compared without a leading ``/``, as tf2 does.
"""

from __future__ import annotations

from array import array
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InvalidInputError
from .bag import opened, raw_messages, seconds, stamp_ns, topics_text
from .poses import POSE_TYPES, PoseStream, message_where, pose_stream, rotation_matrices, unit_quaternion

__all__ = ["TF_TYPES", "STATIC_SUFFIX", "TfEdge", "TfChain", "TfTree", "read_tf_tree", "frame_name"]


#: Message types of a TF topic (ROS 2 and ROS 1 spellings).
TF_TYPES = frozenset(t for t, kind in POSE_TYPES.items() if kind == "tf")


#: The static TF topic is the TF topic's name and this (``/tf`` -> ``/tf_static``), as tf2 names them.
STATIC_SUFFIX = "_static"


def frame_name(frame: str) -> str:
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
        return rotation_matrices(rotation, stamps_ns.size), t

    def coverage(self) -> str:
        """The stamps every dynamic edge covers, and each edge's, for a message about the scans it cannot place."""
        moving = self._moving
        if not moving:
            return f"the transforms on {self.topic} from {self.child_frame!r} to {self.frame!r} are all static"
        each = "; ".join(f"{e.parent} -> {e.child} {seconds(e.poses.stamps_ns[0])} to "
                         f"{seconds(e.poses.stamps_ns[-1])}" for e in moving)
        first = max(int(e.poses.stamps_ns[0]) for e in moving)
        last = min(int(e.poses.stamps_ns[-1]) for e in moving)
        if first > last:
            return f"the dynamic transforms on {self.topic} never cover one stamp together ({each})"
        return f"transforms on {self.topic} cover {seconds(first)} to {seconds(last)} ({each})"


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
            q = unit_quaternion(lambda: message_where(path, index, self.topic, ns), t, row[3:].copy(), what, f"the rotation of {what}")
            stamps.append(ns)
            translations.append(t)
            quaternions.append(q)
        if self.static:  # tf2 keeps the last static transform of an edge
            stamps, translations, quaternions = [stamps[-1]], translations[-1:], quaternions[-1:]
        return TfEdge(self.parent, self.child, pose_stream(self.topic, self.parent, self.child, stamps, translations,
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
        start = frame_name(frame)
        goal = None if map_frame is None else frame_name(map_frame)
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
    reader = opened(path)
    try:
        connections = [c for c in reader.connections if c.topic in (tf_topic, static_topic)]
        if not any(c.topic == tf_topic for c in connections):
            raise InvalidInputError(f"{path}: no pose topic {tf_topic!r} in the bag ({topics_text(reader.connections)})")
        kinds = {f"{c.topic} ({c.msgtype})" for c in connections if c.msgtype not in TF_TYPES}
        if kinds:
            raise InvalidInputError(f"{path}: a TF topic holds tf2_msgs/TFMessage, not {', '.join(sorted(kinds))}")
        topics = tuple(t for t in (tf_topic, static_topic) if any(c.topic == t for c in connections))
        for connection, _, raw in raw_messages(path, reader, connections):
            topic = connection.topic
            index = counts.get(topic, 0)
            counts[topic] = index + 1
            try:
                msg = reader.deserialize(raw, connection.msgtype)
            except Exception as exc:  # noqa: BLE001 - a damaged message
                raise InvalidInputError(f"{path}: cannot decode message {index} on {topic}: {exc}") from None
            static = topic.endswith(STATIC_SUFFIX)
            for tf in msg.transforms:
                parent, child = frame_name(tf.header.frame_id), frame_name(tf.child_frame_id)
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

