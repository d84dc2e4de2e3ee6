"""The rover's and the ground's work on a live link, without any transport: what the ROS 2 nodes adapt.

:class:`RoverCore` places scans at their stamps by the odometry around them,
grows the map (:class:`dftpcc.mapbuilder.MapBuilder`), keeps it on disk and
hands out the frames of :class:`dftpcc.link.Sender` within a budget;
:class:`GroundCore` applies frames (:class:`dftpcc.link.Receiver`) and gives
the rebuilt points. Bad input (a cloud without x/y/z, NaN points, a gap in
the poses, a stamp that jumps back, a bad frame) is counted and reported once
per cause, and never reaches the map.
"""

from __future__ import annotations

import collections
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .errors import DftpccError, InvalidInputError
from .io.poses import PoseStream
from .link import DEFAULT_WINDOW_S, Budget, Receiver, Sender
from .mapbuilder import DEFAULT_GROWING_TILE_SIZE, DEFAULT_STEP_M, MapBuilder, check_bound

__all__ = ["RoverCore", "GroundCore", "Counter", "MAX_POSE_GAP_S", "MAX_POSE_WAIT_S", "POSE_HISTORY_S"]

#: A scan is placed only between two poses at most this far apart (seconds): beyond, the pose is a guess.
MAX_POSE_GAP_S = 0.5
#: A scan waits for the pose after it until a scan this much later (seconds of stamps) arrives.
MAX_POSE_WAIT_S = 1.0
#: Poses kept for placing scans (seconds back from the newest).
POSE_HISTORY_S = 10.0
#: Nanoseconds per second (ROS stamps).
NS = 1_000_000_000
_log = logging.getLogger("dftpcc.live")


class Counter:
    """Counts of refused input by cause, each cause logged the first time only."""

    def __init__(self, log: Callable[[str, str], None] | None = None):
        self.counts: collections.Counter[str] = collections.Counter()
        self._log = log or (lambda cause, message: _log.warning("%s (%s; counted, further ones not logged)",
                                                                message, cause))

    def __call__(self, cause: str, message: str, n: int = 1) -> None:
        self.counts[cause] += n
        if self.counts[cause] == n:
            self._log(cause, message)


@dataclass
class _Scan:
    stamp_ns: int
    points: np.ndarray


class RoverCore:
    """The rover's end of the link: scans and odometry in, the map on disk, frames out.

    Parameters
    ----------
    map_path : path
        The growing map, kept current on disk (atomically, with its state and the link's state
        beside it); resumed when it exists.
    resolution : float
        Cell size of a new map, metres.
    rate : float
        The downlink budget, bytes per second averaged over ``window`` seconds.
    max_frame_bytes : int
        No frame is longer.
    cutoff, step, tile_size : optional
        Settings of a new map.
    target_max_error : float, optional
        Largest error (metres) of any occupied cell of every version from now on: each tile coded
        keeps a residual layer within it (0: none; None: the map's own bound, none for a new map).
        A bound other than the resumed map's codes every tile again once (``dftpcc update
        --target-max-error`` does the same).
    map_frame : str
        Scans in this frame are taken as placed; others are placed by the odometry.
    in_map_frame : bool
        Every scan is taken as placed, whatever its frame (no odometry).
    version_every : float
        Seconds (of scan stamps) between two versions of the map (encoded, written, handed to the
        link); 0: after every scan. Scans in between are added to the cells only; :meth:`flush`
        makes a version of them (the node does when no scan came for that long).
    save_every : float
        Seconds (of scan stamps) between two writes of the map and its state (each atomic; the
        state holds every held cell's sums, 20 bytes a cell: 250 MB for 10^7 cells); 0: at every
        version. :meth:`save` writes the newest version now (the node does when it stops). A rover
        restarted after a crash resumes from the last write, and its link sends from there.
    preview : bool
        A change larger than the budget carries in its window brings the map's preview first (a
        coarse whole map, :meth:`MapBuilder.preview`), so the ground sees the whole drive early.
    log : callable, optional
        ``log(cause, message)``, once per cause of refused input.
    """

    def __init__(self, map_path: str | os.PathLike[str], *, resolution: float, rate: float, max_frame_bytes: int,
                 cutoff: float = 0.8, step: float = DEFAULT_STEP_M, tile_size: int = DEFAULT_GROWING_TILE_SIZE,
                 target_max_error: float | None = None, window: float = DEFAULT_WINDOW_S, map_frame: str = "map", in_map_frame: bool = False,
                 version_every: float = 0.0, save_every: float = 0.0, preview: bool = True,
                 log: Callable[[str, str], None] | None = None):
        self.map_path = Path(map_path)
        self.refused = Counter(log)
        self.map_frame, self.in_map_frame = map_frame, in_map_frame
        link_state = Path(f"{self.map_path}.link")
        self.target_max_error = check_bound(target_max_error)
        if self.map_path.exists():
            self.builder = MapBuilder.from_file(self.map_path, target_max_error=self.target_max_error)
        else:
            if link_state.exists():  # a link state without its map: another map's, start afresh
                link_state.unlink()
            self.builder = MapBuilder(resolution, tile_size=tile_size, cutoff=cutoff, step=step)
        if max_frame_bytes > rate * window:
            raise InvalidInputError(f"a frame of {max_frame_bytes:,} bytes does not fit a budget of {rate:g} B/s "
                                    f"over {window:g} s")
        # A change the budget carries in more than its window carries the map's preview first.
        self.sender = Sender(max_frame_bytes=max_frame_bytes, state=link_state,
                             preview_over=int(rate * window) if preview else None)
        self.budget = Budget(rate, window=window)
        if self.map_path.exists():
            self.sender.update(self.map_path.read_bytes(), preview=self.builder.preview)
        self._poses: collections.deque[tuple[int, np.ndarray, np.ndarray]] = collections.deque()
        self._waiting: collections.deque[_Scan] = collections.deque()
        self._last_scan_ns: int | None = None
        self.scans = 0
        if not (math.isfinite(version_every) and version_every >= 0):
            raise InvalidInputError(f"version_every is a number of seconds, 0 or more, got {version_every!r}")
        self.version_every = float(version_every)
        if not save_every >= 0:  # infinity: only when asked (save)
            raise InvalidInputError(f"save_every is a number of seconds, 0 or more, got {save_every!r}")
        self.save_every = float(save_every)
        self._stamp_ns = 0  # of the last scan added
        self._saved_ns: int | None = None  # of the last scan when the map was last written
        self._unsaved: bytes | None = None  # the newest version, when not written yet
        self.saves = 0
        self._versioned_ns: int | None = None  # stamp of the scan that made the last version
        self._unsent = 0  # scans added since
        self.add_seconds: list[float] = []  # per scan added: placing it into the cells
        self.version_seconds: list[float] = []  # per version: encode, write, hand to the link

    # -- input

    def add_pose(self, stamp_ns: int, translation, quaternion) -> None:
        """An odometry pose of the sensor frame in the map frame (x, y, z; quaternion x, y, z, w)."""
        t = np.asarray(translation, dtype=np.float64)
        q = np.asarray(quaternion, dtype=np.float64)
        norm = float(np.linalg.norm(q)) if np.isfinite(q).all() else math.nan
        if not (np.isfinite(t).all() and abs(norm - 1.0) < 1e-3):
            self.refused("bad pose", "a pose that is not finite or whose quaternion is not of unit length")
            return
        if self._poses and stamp_ns <= self._poses[-1][0]:
            self.refused("pose stamp back", f"a pose stamped {stamp_ns / NS:.3f} s, not after the last "
                                            f"({self._poses[-1][0] / NS:.3f} s)")
            return
        self._poses.append((int(stamp_ns), t, q / norm))
        while self._poses and self._poses[0][0] < stamp_ns - POSE_HISTORY_S * NS:
            self._poses.popleft()
        self._place_waiting()

    def add_scan(self, stamp_ns: int, points: np.ndarray, frame: str) -> bool:
        """A scan (n, 3) in ``frame`` at its stamp; returns whether it was added now (else refused or waiting)."""
        if self._last_scan_ns is not None and stamp_ns <= self._last_scan_ns:
            self.refused("scan stamp back", f"a scan stamped {stamp_ns / NS:.3f} s, not after the last "
                                            f"({self._last_scan_ns / NS:.3f} s)")
            return False
        pts = np.asarray(points, dtype=np.float64)
        finite = np.isfinite(pts).all(axis=1)
        if not finite.all():
            self.refused("nan points", f"a scan with {int((~finite).sum())} non-finite points (left out)",
                         int((~finite).sum()))
            pts = pts[finite]
        if pts.shape[0] == 0:
            self.refused("empty scan", "a scan with no finite point")
            return False
        self._last_scan_ns = int(stamp_ns)
        if self.in_map_frame or frame == self.map_frame:
            return self._add(pts, None, int(stamp_ns))
        self._waiting.append(_Scan(int(stamp_ns), pts))
        return self._place_waiting()

    def _place_waiting(self) -> bool:
        added = False
        while self._waiting:
            scan = self._waiting[0]
            stamps = [p[0] for p in self._poses]
            if not stamps or scan.stamp_ns < stamps[0]:
                self._waiting.popleft()
                self.refused("pose gap", f"a scan at {scan.stamp_ns / NS:.3f} s before the poses kept")
                continue
            if scan.stamp_ns > stamps[-1]:
                if (self._last_scan_ns or 0) - scan.stamp_ns <= MAX_POSE_WAIT_S * NS:
                    return added  # the pose after it has not come yet
                self._waiting.popleft()
                self.refused("pose gap", f"a scan at {scan.stamp_ns / NS:.3f} s with no pose after it")
                continue
            self._waiting.popleft()
            after = int(np.searchsorted(stamps, scan.stamp_ns))
            before = max(after - 1, 0) if stamps[after] != scan.stamp_ns else after
            if stamps[after] - stamps[before] > MAX_POSE_GAP_S * NS:
                self.refused("pose gap", f"a scan at {scan.stamp_ns / NS:.3f} s between poses "
                                         f"{(stamps[after] - stamps[before]) / NS:.2f} s apart")
                continue
            window = [self._poses[k] for k in sorted({before, after})]
            stream = PoseStream("odometry", self.map_frame, None, np.array([p[0] for p in window], np.int64),
                                np.array([p[1] for p in window]), np.array([p[2] for p in window]))
            rotation, translation = stream.at(np.array([scan.stamp_ns]))
            added = self._add(scan.points, (rotation[0], translation[0]), scan.stamp_ns) or added
        return added

    def _add(self, points: np.ndarray, pose, stamp_ns: int) -> bool:
        t0 = time.perf_counter()
        try:
            self.builder.add(points, pose)
        except InvalidInputError as exc:
            self.refused("bad scan", f"a scan the map refuses: {exc}")
            return False
        self.scans += 1
        self._unsent += 1
        self.add_seconds.append(time.perf_counter() - t0)
        self._stamp_ns = stamp_ns
        if self._versioned_ns is None or stamp_ns - self._versioned_ns >= self.version_every * NS:
            self._versioned_ns = stamp_ns
            self.flush()
        return True

    def flush(self) -> bool:
        """Encode the map and hand it to the link, and write it with its state when :attr:`save_every` has
        passed, if scans were added since the last time; returns whether it did."""
        if not self._unsent:
            return False
        t0 = time.perf_counter()
        data = self.builder.encode(target_max_error=self.target_max_error)
        self.sender.update(data, preview=self.builder.preview)
        self._unsent = 0
        self._unsaved = data
        if self._saved_ns is None or self._stamp_ns - self._saved_ns >= self.save_every * NS:
            self.save()
        self.version_seconds.append(time.perf_counter() - t0)
        return True

    def save(self) -> bool:
        """Write the newest version and its state (each atomically), if not written yet; returns whether it did."""
        if self._unsaved is None:
            return False
        self.builder.save(self.map_path, data=self._unsaved)
        self._unsaved = None
        self._saved_ns = self._stamp_ns
        self.saves += 1
        return True

    # -- link

    def frames(self, now: float) -> list[bytes]:
        """The frames to send at ``now`` (seconds, monotonic), within the budget."""
        return self.sender.poll(now, self.budget)

    def acknowledge(self, frame: bytes) -> None:
        if not self.sender.receive(frame):
            self.refused("bad ack", "an acknowledgement refused (damaged, stale or of another map)")


class GroundCore:
    """The ground's end: frames in, the map on disk byte for byte the rover's, its points and acknowledgements out.

    Parameters
    ----------
    map_path : path
        The ground's map, written atomically at each version applied; read back on start.
    max_frame_bytes : int, optional
        Longer frames are refused.
    new_maps : {"refuse", "archive"}
        Frames of another map id (a new mission): refused, or taken once a whole version verifies,
        the map held so far kept beside the file (:class:`dftpcc.link.Receiver`).
    """

    def __init__(self, map_path: str | os.PathLike[str], *, max_frame_bytes: int | None = None,
                 new_maps: str = "refuse", log: Callable[[str, str], None] | None = None):
        self.counter = Counter(log)
        self.receiver = Receiver(map_path, max_frame_bytes=max_frame_bytes, new_maps=new_maps, log=self.counter)

    @property
    def refused(self) -> collections.Counter[str]:
        return self.receiver.refused

    def frame(self, data: bytes, now: float) -> int | None:
        """Apply a frame; returns the version it completed, if any."""
        return self.receiver.receive(data, now)

    def acks(self, now: float) -> list[bytes]:
        return self.receiver.poll(now)

    def preview_points(self) -> np.ndarray | None:
        """The points (n, 3, float32) of the preview of the change in progress, when it is newer than the
        map held (a coarse whole map, ahead of the tiles' detail); else None."""
        from .mapfile import decompress

        if self.receiver.preview is None:
            return None
        target, data, map_id = self.receiver.preview
        if map_id == self.receiver.map_id and target <= self.receiver.version:
            return None  # the map held is as new: its detail is there
        try:
            return decompress(data).astype(np.float32)
        except DftpccError as exc:
            self.counter("undecodable preview", f"a preview that does not decode: {exc}")
            self.receiver.preview = None
            return None

    def points(self) -> np.ndarray:
        """The rebuilt map's points (n, 3), metres, float32, in the frame the rover placed its scans in."""
        from .mapfile import decompress

        if not self.receiver.data:
            return np.zeros((0, 3), np.float32)
        try:
            return decompress(self.receiver.data).astype(np.float32)
        except DftpccError as exc:  # a verified map always decodes; say so if one does not
            self.counter("undecodable map", f"the map applied does not decode: {exc}")
            return np.zeros((0, 3), np.float32)
