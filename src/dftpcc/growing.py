"""A growing map's files: open one to append scans (``dftpcc.open(path, "a")``), and ``dftpcc update``.

:class:`~dftpcc.mapbuilder.MapBuilder` grows the map in memory; here it meets the disk: the map's
lock held while a map is open or updated, the map, its state and its delta written in one
transaction, an update read from bags or point files, and an interrupted update finished on a rerun
(docs/growing-maps.md).
"""

from __future__ import annotations

import hashlib
import math
import os
import warnings
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from .errors import DftpccError, InvalidInputError
from .io.atomic import atomic_write_all, check_distinct, check_output
from .io.lock import lock_path, locked
from .mapbuilder import (DEFAULT_GROWING_TILE_SIZE, DEFAULT_STEP_M, MapBuilder, StateRecoveredWarning, same_crs,
                         state_path)
from .params import DEFAULT_CUTOFF

__all__ = ["GrowingMap", "open_growing", "UpdateResult", "update_file"]

class GrowingMap:
    """A growing map opened to add scans: ``dftpcc.open(path, "a")`` resumes one, ``"w"`` starts one.

    Like laspy's appender: :meth:`add` scans (in the map frame, or in the sensor frame with their
    pose), and on :meth:`close` (or leaving ``with``) the map and its state are written, in one
    transaction, if anything was added. An exception inside ``with`` writes nothing. It holds the
    map's lock (``MAP.lock``, as ``dftpcc update`` does) from opening to closing, so an update of
    the same map waits for it. The :class:`MapBuilder` it holds is :attr:`builder`.
    """

    def __init__(self, path: str | os.PathLike[str], builder: MapBuilder, lock: Any = None):
        self.path, self.builder = Path(path), builder
        self._added = False
        self._lock = lock  # an entered ExitStack holding the map's lock

    def _release(self) -> None:
        if self._lock is not None:
            self._lock.close()
            self._lock = None

    def add(self, points: np.ndarray, pose: tuple[np.ndarray, np.ndarray] | None = None) -> "GrowingMap":
        """Add a scan (see :meth:`MapBuilder.add`)."""
        self.builder.add(points, pose)
        self._added = True
        return self

    def close(self) -> None:
        """Write the map and its state if a scan was added since opening, and release the map's lock."""
        try:
            if self._added:
                self.builder.save(self.path)
                self._added = False
        finally:
            self._release()

    def __enter__(self) -> "GrowingMap":
        return self

    def __exit__(self, kind: type | None, *_exc: Any) -> None:
        if kind is None:
            self.close()
        else:
            self._release()

    def __repr__(self) -> str:
        return f"GrowingMap({str(self.path)!r}, {len(self.builder.tiles)} tiles, {self.builder.point_count:,} points)"


def open_growing(path: str | os.PathLike[str], mode: str, **settings: Any) -> GrowingMap:
    """``dftpcc.open(path, "a")``: resume the growing map ``path`` (and its state); ``"w"``: start one there,
    with ``settings`` (``resolution`` required; ``tile_size``, ``cutoff``, ``step``, ``crs``, ``origin``).

    Raises
    ------
    InvalidInputError
        ``"a"`` of a file that is no growing map or has no state, or with settings (they are the
        map's); ``"w"`` without a resolution, or over a write-protected file.
    """
    path = Path(path)
    if mode == "a":
        if settings:
            raise InvalidInputError(f"opening {path} to append takes no settings (they are the map's): "
                                    f"{', '.join(sorted(settings))}")
        if not path.is_file():
            raise InvalidInputError(f"{path}: no such file (open it with mode 'w' to start a growing map)")
    elif "resolution" not in settings:
        raise InvalidInputError("a new growing map needs its cell size: dftpcc.open(path, 'w', resolution=R)")
    else:
        for target in (path, state_path(path)):
            check_output(target, force=True)
    stack = ExitStack()
    stack.enter_context(locked([path]))
    try:
        builder = MapBuilder.from_file(path) if mode == "a" else MapBuilder(settings.pop("resolution"), **settings)
    except BaseException:
        stack.close()
        raise
    return GrowingMap(path, builder, stack)



# -- the update of a map file: what `dftpcc update` runs ------------------------------------------------


@dataclass
class UpdateResult:
    """What :func:`update_file` did.

    Attributes
    ----------
    path : Path
        The map written.
    size : int
        Its bytes.
    scans : int
        Scans (or point files) added.
    points : int
        Points added.
    tiles : int
        Tiles the map holds.
    recoded : int
        Tiles coded again.
    delta_size : int or None
        Bytes of the delta written, if one was asked for.
    created : bool
        Whether the map was started by this update.
    """

    path: Path
    size: int
    scans: int
    points: int
    tiles: int
    recoded: int
    delta_size: int | None
    created: bool
    repeated: bool = False
    """The scans were the map's last update already (a rerun of an update): none was added again."""


def _scans(inputs: Iterable[str | os.PathLike[str]], points_topic: str | None, pose_topic: str | None,
           map_frame: str | None = None
           ) -> Iterable[tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None, dict[str, Any]]]:
    """(points, pose, CRS) of every scan: a bag's scans through their poses, a point file whole, in the map frame."""
    from .io import format_of, read

    for path in inputs:
        if format_of(path) == "rosbag":
            from .io.rosbag import posed_scans

            for scan in posed_scans(path, points_topic, pose_topic or "/odom", map_frame=map_frame):
                yield scan.points, (scan.rotation, scan.translation), {}
        else:
            cloud = read(path)
            yield cloud.points, None, cloud.crs or {}


def update_file(map_path: str | os.PathLike[str], inputs: Sequence[str | os.PathLike[str]], *,
                output: str | os.PathLike[str] | None = None, delta: str | os.PathLike[str] | None = None,
                points_topic: str | None = None, pose_topic: str | None = None, resolution: float | None = None,
                tile_size: int | None = None, cutoff: float | None = None, step: float | None = None,
                force: bool = False, map_frame: str | None = None, new: bool = False,
                target_max_error: float | None = None, waiting: Callable[[Path], None] | None = None,
                on_stage: Callable[..., None] | None = None) -> UpdateResult:
    """Add scans to a growing map and write it with its state (``dftpcc update``).

    ``on_stage`` is called with each stage's name as it starts (``read``: the scans, then
    ``code``, ``write``), as :func:`dftpcc.compress_file` calls it.

    Without ``output`` the map is updated in place. The map and its state
    are written only once every scan was read and added: a failing input
    (a truncated bag) leaves everything as it was. A map that does not
    exist yet is started, with ``resolution`` (required) and the other
    settings.

    Two updates of one map at once are serialised: each holds the map's
    lock (``MAP.lock``, :func:`dftpcc.io.lock.locked`; and the output's
    with ``output``) from before it reads the map until its files are
    written, so the second waits, then reads the map the first wrote: both
    runs' scans end up in the map.

    Parameters
    ----------
    map_path : path
        The growing map (and ``MAP.state`` beside it).
    inputs : sequence of path
        ROS bags (scans placed by the poses of ``pose_topic``, default
        ``/odom``; ``/tf``: the TF tree, up to ``map_frame`` or its root) or
        point files (LAS, LAZ, PLY, ...) in the map frame.
    output : path, optional
        Write the new map (and its state) here instead.
    delta : path, optional
        Also write the delta from the old map to the new one (:mod:`dftpcc.delta`).
    resolution, tile_size, cutoff, step : optional
        Settings of a new map; for an existing one they must be its own.
    new : bool
        Start a new map even where ``map_path`` exists (``dftpcc compress --growable``; replacing a
        file needs ``force``).
    target_max_error : float, optional
        Largest error of any occupied cell, metres, from this update on (0: none): every tile coded
        keeps a residual layer within it (:meth:`MapBuilder.encode`). The file states one bound, so a
        bound other than the map's codes every tile again; None keeps the map's.
    waiting : callable, optional
        Called with the lock file's path when another update holds it, before waiting for it.

    Raises
    ------
    InvalidInputError
        Settings or a CRS other than the map's, a map that is no growing map
        or has no state, an unreadable input; nothing is written.
    """
    map_path = Path(map_path)
    out = Path(output) if output is not None else map_path
    read = {f"the map {map_path}": map_path, f"its state {state_path(map_path)}": state_path(map_path),
            f"its lock {lock_path(map_path)}": lock_path(map_path),
            **{f"the input {path}": path for path in inputs}}
    written = {}
    if output is not None:
        read[f"the lock {lock_path(out)}"] = lock_path(out)
        written.update({f"-o {out}": out, f"the new state {state_path(out)}": state_path(out)})
    if delta is not None:
        written[f"--delta {delta}"] = delta
    check_distinct(written, read)
    for target in [out, state_path(out)] + ([Path(delta)] if delta is not None else []):
        check_output(target, force=force)
    with locked([map_path, out], waiting=waiting):
        return _update_locked(map_path, out, inputs, delta=delta, points_topic=points_topic, pose_topic=pose_topic,
                              resolution=resolution, tile_size=tile_size, cutoff=cutoff, step=step,
                              map_frame=map_frame, new=new, target_max_error=target_max_error,
                              stage=on_stage or (lambda *_: None))


def _update_locked(map_path: Path, out: Path, inputs: Sequence[str | os.PathLike[str]], *,
                   delta: str | os.PathLike[str] | None, points_topic: str | None, pose_topic: str | None,
                   resolution: float | None, tile_size: int | None, cutoff: float | None, step: float | None,
                   map_frame: str | None, new: bool = False, target_max_error: float | None = None,
                   stage: Callable[..., None] = lambda *_: None) -> UpdateResult:
    """:func:`update_file` once the map is locked and the outputs checked."""
    from .delta import make_delta

    created = new or not map_path.exists()
    if created:
        if resolution is None:
            raise InvalidInputError(f"{map_path} does not exist: give --resolution (and --step, --cutoff, "
                                    f"--tile-size if not the defaults) to start a growing map")
        if delta is not None:
            raise InvalidInputError("a delta needs a map to start from: the first update of a map writes none")
        base = b""
        builder = MapBuilder(resolution, tile_size=DEFAULT_GROWING_TILE_SIZE if tile_size is None else tile_size,
                             cutoff=DEFAULT_CUTOFF if cutoff is None else cutoff, step=DEFAULT_STEP_M if step is None else step)
    else:
        base = map_path.read_bytes()
        builder = MapBuilder.from_file(map_path, target_max_error=target_max_error)
        _check_settings(map_path, builder, resolution, tile_size, cutoff, step)
    last_update = builder.update_sha256
    stage("read")
    scans = points = 0
    record = hashlib.sha256()
    for pts, pose, crs in _scans(inputs, points_topic, pose_topic, map_frame):
        if crs:
            if created and scans == 0:
                builder.crs = dict(crs)
            elif not same_crs(crs, builder.crs):
                raise InvalidInputError(f"the scans' CRS is not the map's ({_crs_name(crs)} against "
                                        f"{_crs_name(builder.crs)}): reproject them to the map's CRS first")
        builder.add(pts, pose)
        _record_scan(record, pts, pose)
        scans += 1
        points += int(pts.shape[0])
    if scans == 0:
        raise InvalidInputError("no scan to add")
    if not created and out == map_path and record.hexdigest() == last_update:
        with warnings.catch_warnings():  # the map was recovered from its state once already, and said so
            warnings.simplefilter("ignore", StateRecoveredWarning)
            again = MapBuilder.from_file(map_path, target_max_error=target_max_error)
        return _finish_update(map_path, base, again, delta, scans, points)
    builder.update_sha256 = record.hexdigest()
    # A bound other than the map's codes every tile again (encode checks the value).
    rebound = target_max_error is not None and target_max_error != builder.params.target_max_error
    recoded = len(builder.tiles) if rebound else len(builder.changed_tiles())
    stage("code")
    data = builder.encode(target_max_error=target_max_error)
    patch = make_delta(base, data) if delta is not None else None
    stage("write")
    # One transaction, renamed delta first: a kill after it leaves the old map and state (a rerun
    # writes the same delta again) or the new state (a rerun finishes the update: _finish_update).
    builder.save(out, data=data, before=[] if patch is None or delta is None else [(Path(delta), patch)])
    return UpdateResult(out, len(data), scans, points, len(builder.tiles), recoded,
                        None if patch is None else len(patch), created)


def _finish_update(map_path: Path, base: bytes, builder: MapBuilder, delta: str | os.PathLike[str] | None,
                   scans: int, points: int) -> UpdateResult:
    """The scans of an in-place update are the map's last update already: write what that update did not.

    Its state was written; the map too unless it was killed before (then
    ``builder`` recovered it from the state, and ``base`` is the older map).
    The delta was renamed before the state, so it is on disk already unless
    this run asks for it under another name.
    """
    from .delta import make_delta, read_delta

    data = builder.encode()
    digest = hashlib.sha256(data).hexdigest()
    written = hashlib.sha256(base).hexdigest() == digest
    files: list[tuple[Path, bytes]] = []
    patch = None
    if delta is not None:
        start = base if not written else None
        try:
            known = read_delta(Path(delta).read_bytes())
            if known.result_sha256.hex() == digest and known.base_sha256.hex() == (
                    hashlib.sha256(start).hexdigest() if start is not None else builder._previous_sha256):
                patch = Path(delta).read_bytes()
        except (OSError, DftpccError):
            pass
        if patch is None:
            if start is None:
                raise InvalidInputError(f"{map_path}: its last update added these very scans (nothing added again), "
                                        f"and its delta can no longer be made: the map it started from is gone. "
                                        f"Send the delta that update wrote")
            patch = make_delta(start, data)
            files.append((Path(delta), patch))
    if not written:
        files.append((map_path, data))
    atomic_write_all(files)
    return UpdateResult(map_path, len(data), scans, points, len(builder.tiles), 0,
                        None if patch is None else len(patch), False, repeated=True)


def _record_scan(record: Any, points: np.ndarray, pose: tuple[np.ndarray, np.ndarray] | None) -> None:
    """Add a scan to the SHA-256 of an update's scans (docs/growing-maps.md, *The update's record*)."""
    record.update(np.ascontiguousarray(points, dtype="<f8").tobytes())
    if pose is None:
        record.update(b"none")
    else:
        record.update(np.ascontiguousarray(pose[0], dtype="<f8").tobytes()
                      + np.ascontiguousarray(pose[1], dtype="<f8").tobytes())


def _crs_name(crs: dict[str, Any]) -> str:
    if not crs:
        return "none"
    wkt = crs.get("wkt") or ""
    return (wkt.split('"')[1] if wkt.count('"') >= 2 else "a LAS CRS record") if wkt or crs.get("las_vlrs") else "none"


def _check_settings(path: Path, builder: MapBuilder, resolution: float | None, tile_size: int | None,
                    cutoff: float | None, step: float | None) -> None:
    """Refuse an update asking for other settings than the map's: a growing map keeps its own."""
    asked = {"resolution": (resolution, builder.resolution), "tile size": (tile_size, builder.tile_size),
             "cutoff": (cutoff, builder.params.cutoff), "step": (step, builder.params.step)}
    for name, (want, have) in asked.items():
        if want is not None and not math.isclose(float(want), float(have), rel_tol=1e-9):
            raise InvalidInputError(f"{path}: the map's {name} is {have:g}, not {want:g}: a growing map keeps the "
                                    f"settings it was started with (start another map for another {name})")
