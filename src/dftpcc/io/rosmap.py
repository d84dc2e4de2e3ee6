"""The rebuilt map back to the robot: a ROS 2 bag with a ``sensor_msgs/PointCloud2`` and a ``grid_map_msgs/GridMap``.

The last write of ``dftpcc decompress MAP out_bag/``: one PointCloud2 of the
rebuilt points (one per occupied cell, as :func:`dftpcc.rebuild.dem_to_points`)
on a topic, and optionally the DEM as the ``elevation`` layer of a GridMap, so
RViz and grid_map users can replay it (``ros2 bag play out_bag``). Both are
stamped ``stamp_ns`` in the map frame ``frame_id`` and offered as latched
(transient local) topics, so a subscriber that starts late still gets the map.

A ROS 2 bag is a folder: it is written into a temporary folder beside the
output and renamed into place, so the output appears complete or not at all;
an existing output is replaced as an existing file is (:func:`dftpcc.io.check_output`):
always, unless it is write-protected (then only with ``force``), and only if it is a ROS 2
bag itself (a folder holding ``metadata.yaml``), never another folder.
Writing needs the optional ``rosbags`` package (``pip install 'dftpcc[ros]'``).

GridMap storage (grid_map_core's convention, checked against
``GridMapMath.cpp`` and ``GridMapRosConverter``): the layer is an Eigen
column-major matrix whose row index runs along -x and column index along
-y from the cell at the map's (max x, max y) corner; the message stores it
column by column, ``layout.dim[0]`` ``column_index`` (size = cells along y),
``dim[1]`` ``row_index`` (size = cells along x). For dftpcc's DEM (row 0 at
the smallest y, column 0 at the smallest x) that is ``heights[::-1, ::-1]``
read in C order. Empty cells are NaN, grid_map's "no data".
"""

from __future__ import annotations

import dataclasses
import math
import os
import secrets
import shutil
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..dem import DEM
from .._optional import import_optional
from ..errors import InvalidInputError, advice
from ..rebuild import dem_to_points
from .atomic import writer_errors
from .bag import NS_PER_S

__all__ = ["local_origin", "static_transform_message", "GRID_MAP_MSGS", "DEFAULT_TOPIC", "ELEVATION_LAYER", "FLOAT32_SAFE_M", "is_bag_output",
           "check_bag_output", "grid_map_topic", "map_typestore", "pointcloud2_message", "grid_map_message",
           "write_map_bag"]

#: ROS 2 definitions of grid_map_msgs (rosbags does not ship them), registered with ``get_types_from_msg``.
GRID_MAP_MSGS = {
    "grid_map_msgs/msg/GridMapInfo": (
        "float64 resolution\n"
        "float64 length_x\n"
        "float64 length_y\n"
        "geometry_msgs/Pose pose\n"),
    "grid_map_msgs/msg/GridMap": (
        "std_msgs/Header header\n"
        "grid_map_msgs/GridMapInfo info\n"
        "string[] layers\n"
        "string[] basic_layers\n"
        "std_msgs/Float32MultiArray[] data\n"
        "uint16 outer_start_index\n"
        "uint16 inner_start_index\n"),
}
#: The PointCloud2 topic unless told otherwise.
DEFAULT_TOPIC = "/map"
#: The GridMap's one layer (grid_map's name for heights).
ELEVATION_LAYER = "elevation"
#: Below this coordinate magnitude float32 keeps a millimetre (2**24 steps of 1 mm): the points are
#: written as float32, which every PointCloud2 consumer reads; beyond it (UTM maps) as float64.
FLOAT32_SAFE_M = 16_384.0
#: PointField datatype codes.
_FLOAT32, _FLOAT64 = 7, 8
#: Temporary folders of :func:`write_map_bag`: ``.NAME.PID.TOKEN.tmp``.
_TMP_MARK = ".tmp"
#: The file that makes a folder a ROS 2 bag.
_METADATA = "metadata.yaml"


def is_bag_output(path: str | os.PathLike[str], fmt: str | None = None) -> bool:
    """Whether ``decompress`` writes ``path`` as a ROS 2 bag.

    A bag is a folder, so: ``fmt`` ``rosbag`` (or ``ros2``), a path ending
    in ``/`` (``out_bag/``), or an existing ROS 2 bag folder. A ``.bag``
    name (ROS 1) is not written.
    """
    if fmt:
        return fmt.lower().lstrip(".") in ("rosbag", "ros2")
    text = os.fspath(path)
    return text.endswith(("/", os.sep)) or (Path(text) / _METADATA).is_file()


def grid_map_topic(topic: str) -> str:
    """The GridMap's topic beside the PointCloud2 ``topic``: ``/map`` -> ``/map/grid_map``."""
    return f"{topic.rstrip('/')}/grid_map"


def check_bag_output(path: str | os.PathLike[str], *, force: bool = False) -> Path:
    """Refuse, before any work, a bag folder that :func:`write_map_bag` could not create.

    Raises
    ------
    InvalidInputError
        A ``.bag`` name (dftpcc writes ROS 2 bags), a missing parent folder,
        a write-protected bag without ``force`` (the rule for files), or an existing
        path that is not a ROS 2 bag (never replaced, even with ``force``).
    OSError
        The parent folder refuses a new entry (naming ``path``).
    MissingDependencyError
        rosbags is not installed.
    """
    path = Path(path)
    if path.suffix.lower() == ".bag":
        raise InvalidInputError(f"{path}: dftpcc writes ROS 2 bags, which are folders (ROS 1 reached its end of "
                                f"life with Noetic in May 2025): name it without .bag, e.g. {path.with_suffix('')}/; "
                                f"for ROS 1, convert that bag with rosbags-convert --src {path.with_suffix('')} "
                                f"--dst {path}")
    _rosbags()
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise InvalidInputError(f"{path}: folder {parent} does not exist")
    if path.exists() or path.is_symlink():
        if not (path.is_dir() and (path / _METADATA).is_file()):
            raise InvalidInputError(f"{path}: exists and is not a ROS 2 bag; dftpcc replaces only a bag folder "
                                    f"(with --force): choose a new name")
        if not path.stat().st_mode & 0o222 and not force:  # the rule for files (io.check_output)
            raise InvalidInputError(f"{path}: the bag is write-protected; use {advice('force=True', '--force')} "
                                    f"to replace it")
    probe = parent / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}{_TMP_MARK}"
    try:
        probe.mkdir()
        probe.rmdir()
    except OSError as exc:
        raise OSError(exc.errno, f"cannot create the bag: {exc.strerror}", str(path)) from exc
    return path


def _rosbags() -> Any:
    import_optional("rosbags.rosbag2", "ros", needed_for="writing ROS bags")
    import_optional("rosbags.typesys", "ros", needed_for="writing ROS bags")
    return sys.modules["rosbags"]


def map_typestore() -> Any:
    """ROS 2 Humble's typestore with :data:`GRID_MAP_MSGS` registered."""
    _rosbags()
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name, text in GRID_MAP_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def _header(store: Any, frame_id: str, stamp_ns: int) -> Any:
    t = store.types
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
                                    frame_id=frame_id)


def pointcloud2_message(store: Any, points: np.ndarray, *, frame_id: str = "map", stamp_ns: int = 0) -> Any:
    """A ``sensor_msgs/msg/PointCloud2`` of ``points`` (n, 3), metres: x, y, z, one row, dense.

    float32 fields when every coordinate is within :data:`FLOAT32_SAFE_M`
    (a millimetre kept), else float64.
    """
    t = store.types
    points = np.asarray(points, dtype=np.float64)
    wide = points.size and float(np.abs(points).max()) > FLOAT32_SAFE_M
    kind, code = ("<f8", _FLOAT64) if wide else ("<f4", _FLOAT32)
    size = np.dtype(kind).itemsize
    fields = [t["sensor_msgs/msg/PointField"](name=name, offset=k * size, datatype=code, count=1)
              for k, name in enumerate("xyz")]
    data = np.ascontiguousarray(points.astype(kind)).view(np.uint8).reshape(-1)
    return t["sensor_msgs/msg/PointCloud2"](
        header=_header(store, frame_id, stamp_ns), height=1, width=points.shape[0], fields=fields,
        is_bigendian=False, point_step=3 * size, row_step=3 * size * points.shape[0], data=data, is_dense=True)


def grid_map_message(store: Any, dem: DEM, *, frame_id: str = "map", stamp_ns: int = 0) -> Any:
    """A ``grid_map_msgs/msg/GridMap`` with the DEM as its ``elevation`` layer (metres, NaN where empty).

    Raises
    ------
    InvalidInputError
        A grid grid_map cannot represent: rotated (``frame='oriented'``;
        grid_map's maps are aligned with their frame) or with non-square cells.
    """
    g = dem.grid
    if g.angle != 0.0:
        raise InvalidInputError(f"a GridMap is aligned with its frame, but this map's grid is rotated by "
                                f"{g.angle:.6g} rad: compress with --frame axis for a grid map")
    if g.resolution_y is not None and g.resolution_y != g.resolution:
        raise InvalidInputError(f"a GridMap has square cells, but this map's are {g.resolution:g} x "
                                f"{g.resolution_y:g}")
    t = store.types
    length_x, length_y = g.cols * g.resolution, g.rows * g.resolution
    centre = t["geometry_msgs/msg/Point"](x=g.x0 + length_x / 2, y=g.y0 + length_y / 2, z=0.0)
    pose = t["geometry_msgs/msg/Pose"](position=centre,
                                       orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    info = t["grid_map_msgs/msg/GridMapInfo"](resolution=g.resolution, length_x=length_x, length_y=length_y,
                                              pose=pose)
    heights = np.where(dem.mask, dem.heights + g.z0, np.nan).astype(np.float32)
    # grid_map's matrix M (x along rows from max x, y along columns from max y) column by column
    # is our DEM flipped on both axes, row by row.
    values = np.ascontiguousarray(heights[::-1, ::-1]).reshape(-1)
    dim = t["std_msgs/msg/MultiArrayDimension"]
    layout = t["std_msgs/msg/MultiArrayLayout"](
        dim=[dim(label="column_index", size=g.rows, stride=g.rows * g.cols),
             dim(label="row_index", size=g.cols, stride=g.cols)], data_offset=0)
    layer = t["std_msgs/msg/Float32MultiArray"](layout=layout, data=values)
    return t["grid_map_msgs/msg/GridMap"](header=_header(store, frame_id, stamp_ns), info=info,
                                          layers=[ELEVATION_LAYER], basic_layers=[ELEVATION_LAYER], data=[layer],
                                          outer_start_index=0, inner_start_index=0)


def _latched() -> list[Any]:
    """The QoS a map is offered with: reliable, transient local, the last message kept (as map servers do)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    never = QosTime(sec=0, nsec=0)  # 0 = no deadline, lifespan or lease: rmw's defaults
    return [Qos(history=QosHistory.KEEP_LAST, depth=1, reliability=QosReliability.RELIABLE,
                durability=QosDurability.TRANSIENT_LOCAL, deadline=never, lifespan=never,
                liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=never,
                avoid_ros_namespace_conventions=False)]


def local_origin(dem: DEM) -> tuple[float, float, float]:
    """A round origin near the middle of a map (whole metres): in a frame about it, FLOAT32 fields
    keep a millimetre over :data:`FLOAT32_SAFE_M` each way."""
    g = dem.grid
    xs = (g.x0, g.x0 + g.cols * g.resolution)
    ys = (g.y0, g.y0 + g.rows * g.dy)
    return float(round(sum(xs) / 2)), float(round(sum(ys) / 2)), float(round(g.z0))


def static_transform_message(store: Any, parent: str, child: str, origin: Sequence[float], *,
                             stamp_ns: int = 0) -> Any:
    """A ``tf2_msgs/msg/TFMessage`` placing frame ``child`` at ``origin`` (metres) in ``parent``, unrotated."""
    t = store.types
    transform = t["geometry_msgs/msg/Transform"](
        translation=t["geometry_msgs/msg/Vector3"](x=float(origin[0]), y=float(origin[1]), z=float(origin[2])),
        rotation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    stamped = t["geometry_msgs/msg/TransformStamped"](header=_header(store, parent, stamp_ns), child_frame_id=child,
                                                      transform=transform)
    return t["tf2_msgs/msg/TFMessage"](transforms=[stamped])


def write_map_bag(path: str | os.PathLike[str], dem: DEM, *, topic: str = DEFAULT_TOPIC,
                  grid_map: str | bool = False, frame_id: str = "map", stamp_ns: int = 0,
                  storage: str = "sqlite3", force: bool = False, origin: Sequence[float] | None = None,
                  local_frame: str | None = None) -> np.ndarray:
    """Write the rebuilt map as a ROS 2 bag folder: a PointCloud2 on ``topic``, a GridMap if asked.

    Parameters
    ----------
    path : path
        The bag folder to create.
    dem : DEM
        The decoded map (:meth:`dftpcc.CompressedMap.read_dem`).
    topic : str
        The PointCloud2 topic.
    grid_map : bool or str
        Also write the DEM as a GridMap ``elevation`` layer: True on
        :func:`grid_map_topic` of ``topic``, a string on that topic.
    frame_id : str
        ``header.frame_id`` of both messages: the frame the map was built in.
    stamp_ns : int
        Their stamp and bag time, nanoseconds (default 0: a map has no time).
    storage : str
        ``sqlite3`` (ROS 2's default) or ``mcap``.
    origin : (x, y, z), optional
        Write the map in a local frame about this point (metres of ``frame_id``; see
        :func:`local_origin`): coordinates minus ``origin``, in frame ``local_frame``
        (default ``<frame_id>_local``), which a ``/tf_static`` transform places at ``origin``.
        Far from their frame's origin (beyond :data:`FLOAT32_SAFE_M`) points need FLOAT64
        fields to keep a millimetre; in a local frame FLOAT32 keeps it, as PCL's PointXYZ
        and RViz expect.
    force : bool
        Replace an existing bag at ``path``.

    Returns
    -------
    ndarray, shape (cells, 3)
        The points written, metres.

    Raises
    ------
    InvalidInputError
        As :func:`check_bag_output`; a grid a GridMap cannot hold; an unknown storage.
    OSError
        The file system refused (naming ``path``).
    """
    path = check_bag_output(path, force=force)
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugins = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}
    if storage not in plugins:
        raise InvalidInputError(f"unknown bag storage {storage!r}; known: {', '.join(plugins)}")
    store = map_typestore()
    messages = []
    if origin is not None:
        ox, oy, oz = (float(v) for v in origin)
        if not all(math.isfinite(v) for v in (ox, oy, oz)):
            raise InvalidInputError(f"a local origin is three finite numbers, got {origin!r}")
        child = local_frame or f"{frame_id}_local"
        messages.append(("/tf_static", "tf2_msgs/msg/TFMessage",
                         static_transform_message(store, frame_id, child, (ox, oy, oz), stamp_ns=stamp_ns)))
        g = dem.grid
        dem = dataclasses.replace(dem, grid=dataclasses.replace(g, x0=g.x0 - ox, y0=g.y0 - oy, z0=g.z0 - oz))
        frame_id = child
    points = dem_to_points(dem)
    messages.append((topic, "sensor_msgs/msg/PointCloud2",
                     pointcloud2_message(store, points, frame_id=frame_id, stamp_ns=stamp_ns)))
    if grid_map:
        messages.append((grid_map if isinstance(grid_map, str) else grid_map_topic(topic), "grid_map_msgs/msg/GridMap",
                         grid_map_message(store, dem, frame_id=frame_id, stamp_ns=stamp_ns)))
    if len({name for name, _, _ in messages}) != len(messages):
        raise InvalidInputError(f"the PointCloud2 and the GridMap need two topics, both are {topic!r}")
    parent = path.parent if str(path.parent) else Path(".")
    # rosbags names the storage file after the bag folder: write it under its own name in a hidden
    # folder beside, then move it into place.
    tmp = parent / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}{_TMP_MARK}"
    old = tmp.with_name(tmp.name + ".old")
    try:
        tmp.mkdir()
        with writer_errors(path, "a ROS 2 bag"):
            with Writer(tmp / path.name, version=9, storage_plugin=plugins[storage]) as writer:
                for name, msgtype, msg in messages:
                    connection = writer.add_connection(name, msgtype, typestore=store,
                                                       offered_qos_profiles=_latched())
                    writer.write(connection, int(stamp_ns), store.serialize_cdr(msg, msgtype))
        for file in (tmp / path.name).iterdir():
            with file.open("rb+") as fh:
                os.fsync(fh.fileno())
        if path.exists():  # checked above: a bag, and force
            os.replace(path, old)
        try:
            os.replace(tmp / path.name, path)
        except OSError:
            if old.exists():
                os.replace(old, path)  # the previous bag stays rather than none at all
            raise
    except OSError as exc:
        raise OSError(exc.errno, f"cannot write the bag: {exc.strerror or exc}", str(path)) from exc
    finally:
        for leftover in (tmp, old):
            if leftover.exists():
                shutil.rmtree(leftover, ignore_errors=True)
    return points
