"""ROS bags opened with rosbags: every bag version, its topics, its raw messages, stamps.

The one place that talks to the optional ``rosbags`` package (``pip install 'dftpcc[ros]'``):
:mod:`dftpcc.io.rosbag` (point clouds), :mod:`dftpcc.io.poses` and :mod:`dftpcc.io.tf` read
their messages through it. A bag rosbags cannot read, or one that breaks part way, is one
:class:`~dftpcc.errors.InvalidInputError`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator

from .._optional import import_optional, install_hint
from ..errors import InvalidInputError, MissingFileError

__all__ = ["NS_PER_S", "bag_folder", "size_bound", "any_reader", "opened", "raw_messages", "topics_text", "stamp_ns",
           "seconds"]


#: Nanoseconds per second, for stamps.
NS_PER_S = 1_000_000_000


INSTALL_HINT = install_hint("ros")


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


def any_reader() -> Any:
    """rosbags' reader of every bag version, or the error saying how to install it."""
    return import_optional("rosbags.highlevel", "ros", needed_for="reading ROS bags").AnyReader


def _default_typestore() -> Any:
    """ROS 2 Humble's types, for ROS 2 bags that do not store their message definitions (before version 9)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def opened(path: Path) -> Any:
    """A rosbags reader of ``path``, opened; a bag rosbags cannot read is one InvalidInputError."""
    try:
        reader = any_reader()([bag_folder(path)], default_typestore=_default_typestore())
        reader.open()
    except InvalidInputError:
        raise
    except Exception as exc:  # noqa: BLE001 - rosbags raises its own errors on bad bags
        raise InvalidInputError(f"{path}: cannot read as a ROS bag: {exc}") from None
    return reader


def topics_text(connections: Any) -> str:
    """The topics of a bag with their message types, for an error message."""
    topics = sorted({(c.topic, c.msgtype) for c in connections})
    if not topics:
        return "it has no topics at all"
    return "its topics: " + ", ".join(f"{topic} ({msgtype})" for topic, msgtype in topics)


def raw_messages(path: Path, reader: Any, connections: list[Any]) -> Iterator[tuple[Any, int, bytes]]:
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


def stamp_ns(stamp: Any) -> int:
    """A ``builtin_interfaces/Time`` (ROS 1 and ROS 2 alike in rosbags) as integer nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def seconds(ns: int) -> str:
    return f"{ns / NS_PER_S:.9f} s"

