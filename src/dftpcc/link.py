"""The rover-ground link: a growing map sent as changes cut into frames of at most N bytes (docs/format.md, *Link frames*).

The stage after the map builder on a rover: :class:`Sender` holds the versions
of the map (the bytes :meth:`dftpcc.mapbuilder.MapBuilder.encode` gives) and
emits frames carrying what changed since the version the ground confirmed;
:class:`Receiver` reassembles and verifies them, and its map is byte for byte
the sender's at every version it applies. No transport here: a ROS 2 topic,
a radio or files carry the frames as they are (:mod:`dftpcc.linksim` simulates
a bad link for tests and benchmarks).
"""

from __future__ import annotations

import collections
import hashlib
import json
import logging
import math
import os
import secrets
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import zstandard

from .format import leb128, read_leb128, tile_sections
from .errors import CorruptFileError, DftpccError, InvalidInputError
from .io.atomic import atomic_write

__all__ = ["Sender", "Receiver", "Budget", "DataFrame", "Ack", "FrameError", "Plan", "read_frame", "pack_data",
           "pack_ack", "make_change", "read_plan", "join_change", "MAGIC", "LAYOUT", "DATA", "ACK", "DATA_OVERHEAD",
           "ACK_OVERHEAD", "MIN_FRAME_BYTES", "MAX_PARTS", "MAX_MAP_BYTES", "COPY", "REST", "TILE"]

#: The first bytes of every frame (a high byte, like a map's, then D L for dftpcc link).
MAGIC = b"\x89DL"
#: Layout version of the frames.
LAYOUT = 1
#: Frame kinds: data (rover to ground), acknowledgement (ground to rover).
DATA, ACK = 1, 2
#: Plan piece kinds: bytes of the base, the next bytes of the plan's rest, a whole tile item.
COPY, REST, TILE = 0, 1, 2
_HEAD = struct.Struct("<3sBBQ")  # magic, layout, kind, map id
_DATA = struct.Struct("<II8sIHH")  # base version, target version, base check, item, part index, part count
_ACK = struct.Struct("<III32sII")  # epoch, sequence, version, map SHA-256, change base version, change target version
_CRC = struct.Struct("<I")
#: Bytes of a data frame besides its payload, and of an acknowledgement without reports.
DATA_OVERHEAD = _HEAD.size + _DATA.size + _CRC.size
ACK_OVERHEAD = _HEAD.size + _ACK.size + 1 + _CRC.size
#: The smallest frame a sender accepts to write (bytes): below it the head is most of every frame.
MIN_FRAME_BYTES = 64
#: Parts an item may have (a u16 count).
MAX_PARTS = 0xFFFF
#: The item number of a change's preview (docs/format.md, *Link frames*): never a tile's.
PREVIEW_ITEM = 0xFFFFFFFF
#: A preview is sent only when it is under this share of the change's tile items.
PREVIEW_SHARE = 0.25
#: Largest map a receiver rebuilds unless told otherwise (bytes): a plan claiming more is refused unread.
MAX_MAP_BYTES = 1 << 30
#: The base check of a frame: the first bytes of the base's SHA-256.
CHECK_BYTES = 8
#: A plan may declare at most this many times its own bytes, or the floor if more, and never more than the largest
#: map and its head: a frame of a few bytes must not make a receiver allocate a gigabyte.
PLAN_MAX_RATIO = 1024
PLAN_FLOOR_BYTES = 1 << 20
PLAN_HEAD_BYTES = 64  # target size, SHA-256 and piece count
#: zstd level of a plan: the head's section table and tile index compress well, and a plan is small.
PLAN_ZSTD_LEVEL = 19
#: Seconds a part sent and not confirmed waits before it is sent again.
DEFAULT_RETRY_S = 3.0
#: Seconds without an acknowledgement after which the sender takes the link as down and resends at most one
#: part per retry time (a probe) instead of the budget's worth: an outage must not spend the budget into the void.
DEFAULT_SILENCE_S = 12.0
#: A part is taken as lost when an acknowledgement of its change, arriving this many of the shortest round
#: trips seen after it went out, does not report it (the trips: from a part's sending to the first
#: acknowledgement reporting it, the last TRIP_SAMPLES of them).
LOST_AFTER_TRIPS = 1.5
TRIP_SAMPLES = 256
#: The receiver acknowledges at most this often (seconds), and at least every keep-alive when idle.
DEFAULT_ACK_INTERVAL_S = 1.0
DEFAULT_KEEPALIVE_S = 5.0
#: What a receiver does with frames of another map id (:class:`Receiver`'s ``new_maps``).
NEW_MAPS = ("refuse", "archive")
#: Window over which the budget is kept (seconds).
DEFAULT_WINDOW_S = 10.0
#: The sender's and receiver's link state beside the map: ``MAP`` + this (JSON), and the ground's
#: confirmed map the sender keeps as a base: ``MAP`` + this + ``.base``.
LINK_SUFFIX = ".link"
_EMPTY_SHA = hashlib.sha256(b"").digest()
_log = logging.getLogger("dftpcc.link")


class FrameError(CorruptFileError):
    """A frame that does not verify; ``cause`` names why in a word or two (what the counters count)."""

    def __init__(self, cause: str, message: str):
        super().__init__(message)
        self.cause = cause


# -- frames ------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DataFrame:
    """A data frame: part ``part`` of ``parts`` of item ``item`` of the change ``base_version`` -> ``target_version``."""

    map_id: int
    base_version: int
    target_version: int
    base_check: bytes
    item: int
    part: int
    parts: int
    payload: bytes

    @property
    def change(self) -> tuple[int, int, bytes]:
        return self.base_version, self.target_version, self.base_check


@dataclass(frozen=True)
class Ack:
    """An acknowledgement: the ground's map (version, SHA-256) and the parts it holds of the change in progress.

    ``reports`` maps an item to its part count and the set of parts held.
    """

    map_id: int
    epoch: int
    sequence: int
    version: int
    sha256: bytes
    base_version: int
    target_version: int
    reports: dict[int, tuple[int, frozenset[int]]] = field(default_factory=dict)


def _sealed(body: bytes | bytearray) -> bytes:
    return bytes(body) + _CRC.pack(zlib.crc32(body))


def pack_data(frame: DataFrame) -> bytes:
    """The bytes of a data frame."""
    return _sealed(_HEAD.pack(MAGIC, LAYOUT, DATA, frame.map_id) + _DATA.pack(
        frame.base_version, frame.target_version, frame.base_check, frame.item, frame.part, frame.parts)
        + frame.payload)


def pack_ack(ack: Ack, *, max_bytes: int | None = None) -> bytes:
    """The bytes of an acknowledgement; reports that would take it past ``max_bytes`` are left out."""
    reports = []
    size = ACK_OVERHEAD + 8  # a wider report count
    for item in sorted(ack.reports):
        count, held = ack.reports[item]
        if len(held) == count:
            report = leb128(item) + leb128(count) + b"\x00"
        else:
            bits = bytearray((count + 7) // 8)
            for i in held:
                bits[i >> 3] |= 1 << (i & 7)
            report = leb128(item) + leb128(count) + b"\x01" + bytes(bits)
        if max_bytes is not None and size + len(report) > max_bytes:
            break
        reports.append(report)
        size += len(report)
    return _sealed(_HEAD.pack(MAGIC, LAYOUT, ACK, ack.map_id) + _ACK.pack(
        ack.epoch, ack.sequence, ack.version, ack.sha256, ack.base_version, ack.target_version)
        + leb128(len(reports)) + b"".join(reports))


def read_frame(data: bytes, *, max_bytes: int | None = None) -> DataFrame | Ack:
    """Parse and check a frame (docs/format.md, *Link frames*).

    Raises
    ------
    FrameError
        Oversized, cut, failing its CRC, another layout or kind, or fields that disagree.
    """
    data = bytes(data)
    if max_bytes is not None and len(data) > max_bytes:
        raise FrameError("oversized", f"a frame of {len(data):,} bytes, more than the {max_bytes:,} allowed")
    if len(data) < _HEAD.size + _CRC.size:
        raise FrameError("truncated", f"a frame of {len(data)} bytes is shorter than a frame's head")
    if zlib.crc32(data[:-_CRC.size]) != _CRC.unpack_from(data, len(data) - _CRC.size)[0]:
        raise FrameError("crc", "a frame fails its CRC-32 (damaged or cut)")
    magic, layout, kind, map_id = _HEAD.unpack_from(data, 0)
    if magic != MAGIC:
        raise FrameError("magic", "not a dftpcc link frame (no frame magic)")
    if layout != LAYOUT:
        raise FrameError("layout", f"a frame of layout {layout}; this dftpcc reads layout {LAYOUT}")
    end = len(data) - _CRC.size
    if kind == DATA:
        if len(data) < DATA_OVERHEAD:
            raise FrameError("truncated", f"a data frame of {len(data)} bytes is shorter than its head")
        base, target, check, item, part, parts = _DATA.unpack_from(data, _HEAD.size)
        if map_id == 0 or target <= base or parts == 0 or part >= parts:
            raise FrameError("fields", f"a data frame with map id {map_id}, versions {base} -> {target}, part "
                                       f"{part} of {parts}")
        return DataFrame(map_id, base, target, check, item, part, parts, data[_HEAD.size + _DATA.size:end])
    if kind == ACK:
        if len(data) < ACK_OVERHEAD:
            raise FrameError("truncated", f"an acknowledgement of {len(data)} bytes is shorter than its head")
        epoch, sequence, version, sha, base, target = _ACK.unpack_from(data, _HEAD.size)
        if (target or base) and target <= base:
            raise FrameError("fields", f"an acknowledgement of a change {base} -> {target}")
        try:
            pos = _HEAD.size + _ACK.size
            count, pos = read_leb128(data[:end], pos, "acknowledgement")
            reports: dict[int, tuple[int, frozenset[int]]] = {}
            for _ in range(count):
                item, pos = read_leb128(data[:end], pos, "acknowledgement")
                parts, pos = read_leb128(data[:end], pos, "acknowledgement")
                if pos >= end or not 1 <= parts <= MAX_PARTS or item in reports:
                    raise FrameError("fields", "an acknowledgement's report is cut, repeated or counts no part")
                mode, pos = data[pos], pos + 1
                if mode == 0:
                    held = frozenset(range(parts))
                elif mode == 1:
                    width = (parts + 7) // 8
                    if pos + width > end:
                        raise FrameError("truncated", "an acknowledgement's bitmap is cut")
                    bits = int.from_bytes(data[pos:pos + width], "little")
                    if bits >> parts:
                        raise FrameError("fields", "an acknowledgement's bitmap sets parts past its count")
                    held = frozenset(i for i in range(parts) if bits >> i & 1)
                    pos += width
                else:
                    raise FrameError("fields", f"an acknowledgement's report of mode {mode}")
                reports[item] = (parts, held)
        except FrameError:
            raise
        except CorruptFileError as exc:
            raise FrameError("truncated", str(exc)) from None
        if pos != end:
            raise FrameError("fields", "bytes after an acknowledgement's reports")
        return Ack(map_id, epoch, sequence, version, sha, base, target, reports)
    raise FrameError("kind", f"a frame of kind {kind}")


# -- the plan of a change ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Plan:
    """A parsed plan: the target's size and SHA-256, its pieces, the rest bytes; ``tiles`` the items it needs, by length."""

    size: int
    sha256: bytes
    pieces: list[tuple[int, int, int]]  # (COPY, base offset, length), (REST, rest offset, length), (TILE, item, length)
    rest: bytes
    tiles: dict[int, int]


def _tile_blocks(data: bytes) -> list[tuple[int, int, int]]:
    """(tile, start, end) of every tile of a tiled map whose sections lie together, by start; none for other bytes."""
    try:
        tiles = tile_sections(data)
    except DftpccError:  # not a map dftpcc reads: sent whole, as the plan's rest
        return []
    blocks = []
    for k, sections in tiles.items():
        spans = sorted((start, start + length) for start, length, _crc in sections.values())
        if spans and sum(e - s for s, e in spans) == spans[-1][1] - spans[0][0]:
            blocks.append((k, spans[0][0], spans[-1][1]))
    blocks.sort(key=lambda b: b[1])
    # Blocks that overlap (never in a file dftpcc writes) are left to the rest.
    return [b for n, b in enumerate(blocks) if n == 0 or blocks[n - 1][2] <= b[1]]


def make_change(base: bytes, target: bytes) -> tuple[bytes, dict[int, bytes]]:
    """The plan (zstd) and tile items that turn ``base`` (may be empty) into ``target``.

    Every tile of ``target`` found byte for byte among the tiles of ``base``
    is a copy; the others are tile items, keyed by their tile number in ``target``.
    """
    found: dict[tuple[int, bytes], int] = {}
    for _k, start, end in _tile_blocks(base):
        found.setdefault((end - start, hashlib.sha1(base[start:end]).digest()), start)
    pieces: list[tuple[int, int, int]] = []
    rest = bytearray()
    items: dict[int, bytes] = {}
    pos = 0

    def put(kind: int, a: int, n: int) -> None:
        if n == 0:
            return
        if pieces and pieces[-1][0] == kind and kind != TILE:
            k0, a0, n0 = pieces[-1]
            if kind == REST or a0 + n0 == a:
                pieces[-1] = (kind, a0, n0 + n)
                return
        pieces.append((kind, a, n))

    for k, start, end in _tile_blocks(target):
        rest += target[pos:start]
        put(REST, 0, start - pos)
        block = target[start:end]
        at = found.get((end - start, hashlib.sha1(block).digest()))
        if at is not None and base[at:at + end - start] == block:
            put(COPY, at, end - start)
        else:
            items[k] = block
            put(TILE, k, end - start)
        pos = end
    rest += target[pos:]
    put(REST, 0, len(target) - pos)
    body = bytearray(leb128(len(target)) + hashlib.sha256(target).digest() + leb128(len(pieces)))
    for kind, a, n in pieces:
        body += bytes([kind]) + (leb128(n) if kind == REST else leb128(a) + leb128(n))
    body += rest
    plan = zstandard.ZstdCompressor(level=PLAN_ZSTD_LEVEL, write_content_size=True).compress(bytes(body))
    return plan, items


def read_plan(plan: bytes, *, base_size: int, max_map_bytes: int = MAX_MAP_BYTES) -> Plan:
    """Parse and check a plan against the size of the base it applies to.

    Raises
    ------
    FrameError
        A plan that does not decompress within ``max_map_bytes`` or whose pieces do not add up.
    """
    try:
        declared = zstandard.frame_content_size(plan)
        allowed = min(max_map_bytes + PLAN_HEAD_BYTES, max(PLAN_FLOOR_BYTES, PLAN_MAX_RATIO * len(plan)))
        if declared < 0 or declared > allowed:  # -1: not stated
            raise FrameError("plan", f"a plan of {len(plan):,} bytes declaring {declared:,} (stated, at most "
                                     f"{allowed:,})")
        body = zstandard.ZstdDecompressor().decompress(plan, max_output_size=declared) if declared else b""
    except zstandard.ZstdError as exc:
        raise FrameError("plan", f"a plan that does not decompress: {exc}") from None
    if len(body) != declared:
        raise FrameError("plan", "a plan shorter than it declares")
    try:
        size, pos = read_leb128(body, 0, "plan")
        sha = body[pos:pos + 32]
        count, pos = read_leb128(body, pos + 32, "plan")
        if len(sha) != 32 or size > max_map_bytes or count > len(body) - pos:
            raise FrameError("plan", f"a plan of a {size:,}-byte map in {count:,} pieces")
        pieces, tiles, rest_used, total = [], {}, 0, 0
        for _ in range(count):
            if pos >= len(body):
                raise FrameError("plan", "a plan cut in its pieces")
            kind, pos = body[pos], pos + 1
            if kind == REST:
                n, pos = read_leb128(body, pos, "plan")
                pieces.append((REST, rest_used, n))
                rest_used += n
            elif kind in (COPY, TILE):
                a, pos = read_leb128(body, pos, "plan")
                n, pos = read_leb128(body, pos, "plan")
                if kind == COPY and a + n > base_size:
                    raise FrameError("plan", f"a plan copying bytes {a:,} to {a + n:,} of a {base_size:,}-byte base")
                if kind == TILE:
                    if a == 0 or a in tiles or a >= PREVIEW_ITEM:
                        raise FrameError("plan", f"a plan naming tile {a} as an item twice, as tile 0 or as the "
                                                 f"preview")
                    tiles[a] = n
                pieces.append((kind, a, n))
            else:
                raise FrameError("plan", f"a plan piece of kind {kind}")
            total += n
    except CorruptFileError as exc:
        if isinstance(exc, FrameError):
            raise
        raise FrameError("plan", str(exc)) from None
    if total != size or rest_used != len(body) - pos:
        raise FrameError("plan", f"a plan whose pieces add up to {total:,} bytes ({rest_used:,} of the rest) for a "
                                 f"{size:,}-byte map ({len(body) - pos:,} of the rest)")
    return Plan(size, bytes(sha), pieces, bytes(body[pos:]), tiles)


def join_change(plan: Plan, base: bytes, items: dict[int, bytes]) -> bytes:
    """The target of a change, checked against the plan's SHA-256.

    Raises
    ------
    FrameError
        An item of another length than its piece, or a result that is not the target the plan names.
    """
    out = bytearray()
    for kind, a, n in plan.pieces:
        if kind == COPY:
            out += base[a:a + n]
        elif kind == REST:
            out += plan.rest[a:a + n]
        else:
            if len(items[a]) != n:
                raise FrameError("item", f"tile item {a} holds {len(items[a]):,} bytes, its plan says {n:,}")
            out += items[a]
    if hashlib.sha256(out).digest() != plan.sha256:
        raise FrameError("result", "a change's result is not the map its plan names (SHA-256)")
    return bytes(out)


# -- pacing ---------------------------------------------------------------------------------------------------------


class Budget:
    """A byte budget: at most ``rate`` x ``window`` bytes in any ``window`` seconds.

    Parameters
    ----------
    rate : float
        Bytes per second, averaged over ``window``.
    window : float
        Seconds.
    """

    def __init__(self, rate: float, *, window: float = DEFAULT_WINDOW_S):
        if not (rate > 0 and window > 0):
            raise InvalidInputError(f"a budget is a positive rate (bytes/s) over a positive window (s), got {rate!r}, "
                                    f"{window!r}")
        self.rate, self.window = float(rate), float(window)
        self.limit = int(self.rate * self.window)
        self._sent: collections.deque[tuple[float, int]] = collections.deque()
        self._total = 0

    def _expire(self, now: float) -> None:
        while self._sent and self._sent[0][0] <= now - self.window:
            self._total -= self._sent.popleft()[1]

    def fits(self, now: float, size: int) -> bool:
        """Whether ``size`` bytes may be sent at ``now`` (seconds)."""
        self._expire(now)
        return self._total + size <= self.limit

    def spend(self, now: float, size: int) -> None:
        self._expire(now)
        self._sent.append((now, size))
        self._total += size


# -- the sender ------------------------------------------------------------------------------------------------------


@dataclass
class _Change:
    base_version: int
    target_version: int
    base_check: bytes
    parts: dict[tuple[int, int], bytes]  # (item, part) -> frame bytes
    order: list[tuple[int, int]]
    held: set[tuple[int, int]] = field(default_factory=set)
    sent_at: dict[tuple[int, int], float] = field(default_factory=dict)
    next: int = 0  # index in order of the next part never sent
    lost: set[tuple[int, int]] = field(default_factory=set)  # parts an acknowledgement sent after them lacks
    resent: set[tuple[int, int]] = field(default_factory=set)


class Sender:
    """The rover's end: versions of a growing map, and the frames that bring the ground to the newest.

    Parameters
    ----------
    max_frame_bytes : int
        No frame is longer (bytes; at least :data:`MIN_FRAME_BYTES`).
    map_id : int, optional
        The map's id (u64, not 0); default a random one (or the one of ``state``).
    state : path, optional
        Where the link state is kept (JSON, and the ground's confirmed map as ``STATE.base``) so a
        restarted sender resumes from what the ground confirmed; nothing is written without it.
    retry_after : float
        Seconds before a part sent and not confirmed is sent again.
    silence_after : float
        Seconds without an acknowledgement after which resends slow to one part per ``retry_after``.
    preview_over : int, optional
        Bytes: a change whose tile items add up to more carries the newest version's preview (given
        to :meth:`update`) right after its plan, when the preview is under :data:`PREVIEW_SHARE` of
        them; None: never (docs/format.md, *Link frames*, the preview).
    """

    def __init__(self, *, max_frame_bytes: int, map_id: int | None = None, state: str | os.PathLike[str] | None = None,
                 retry_after: float = DEFAULT_RETRY_S, silence_after: float = DEFAULT_SILENCE_S,
                 preview_over: int | None = None):
        if not (isinstance(max_frame_bytes, int) and max_frame_bytes >= MIN_FRAME_BYTES):
            raise InvalidInputError(f"max_frame_bytes must be a whole number of bytes, at least {MIN_FRAME_BYTES}, "
                                    f"got {max_frame_bytes!r}")
        self.max_frame_bytes = max_frame_bytes
        self.preview_over = preview_over
        self._preview: Callable[[], bytes] | None = None  # of the newest version
        self.retry_after, self.silence_after = float(retry_after), float(silence_after)
        self._clock = 0.0  # the last poll's time: when an acknowledgement is taken
        self._heard = 0.0  # when the last acknowledgement was taken
        self._probed = -math.inf  # when the last resend during a silence went
        self._trips: collections.deque[float] = collections.deque(maxlen=TRIP_SAMPLES)  # seconds, upper bounds
        self.state = None if state is None else Path(state)
        self.map_id = map_id or (secrets.randbits(64) or 1)
        self.version = 0  # of the newest map
        self._versions: dict[int, bytes] = {}
        self._sha: dict[int, bytes] = {0: _EMPTY_SHA}
        self._first_seen: dict[bytes, int] = {}  # a tile's bytes (SHA-1) -> the version it first appeared in
        self.ground: int | None = None  # the version the ground holds, when known
        self._epochs: dict[int, int] = {}  # epoch -> highest sequence taken
        self._epoch: int | None = None
        self.change: _Change | None = None
        self.counts: collections.Counter[str] = collections.Counter()
        self._resumed_sha: str | None = None
        #: After a restart: the version the last change before it went to, kept (with its bytes, from
        #: ``STATE.target``) until the ground says what it holds: it may have applied that change.
        self._in_flight: int | None = None
        self._on_disk: dict[Path, bytes] = {}  # SHA-256 of what STATE.base and STATE.target hold
        #: (base version, target version) of every change started.
        self.history: list[tuple[int, int]] = []
        if self.state is not None and self.state.is_file():
            self._resume()

    # -- versions

    def update(self, data: bytes, *, preview: Callable[[], bytes] | None = None) -> int:
        """Take ``data`` (the map's bytes) as the newest version; returns its number (the same if unchanged).

        ``preview``: makes that version's preview (a small ``.dftpc`` file of the map at a coarser
        cell, :meth:`dftpcc.mapbuilder.MapBuilder.preview`), called only when a change to this
        version starts and is large enough to carry one (``preview_over``).
        """
        data = bytes(data)
        if self.version and data == self._versions.get(self.version):
            if preview is not None:
                self._preview = preview
            return self.version
        self._preview = preview
        if not (self.version and self.version not in self._versions
                and self._resumed_sha == hashlib.sha256(data).hexdigest()):
            self.version += 1  # else the map the state names, after a restart: its number again
        self._versions[self.version] = data
        self._sha[self.version] = hashlib.sha256(data).digest()
        seen = {}
        for _k, start, end in _tile_blocks(data):
            key = hashlib.sha1(data[start:end]).digest()
            seen[key] = self._first_seen.get(key, self.version)
        self._first_seen = seen
        self._prune()
        self._save()
        return self.version

    def _prune(self) -> None:
        keep = {self.version, self.ground, self._in_flight}
        if self.change is not None:
            keep |= {self.change.base_version, self.change.target_version}
        for v in [v for v in self._versions if v not in keep]:
            del self._versions[v]
            self._sha.pop(v, None)

    # -- acknowledgements

    def receive(self, frame: bytes) -> bool:
        """Take an acknowledgement; returns whether it was taken (not another map's, stale or damaged)."""
        try:
            ack = read_frame(frame)
        except FrameError as exc:
            self.counts[exc.cause] += 1
            return False
        if not isinstance(ack, Ack):
            self.counts["kind"] += 1
            return False
        if ack.map_id not in (0, self.map_id):
            self.counts["another map"] += 1
            return False
        if ack.epoch in self._epochs and (ack.epoch != self._epoch or ack.sequence <= self._epochs[ack.epoch]):
            self.counts["stale"] += 1
            return False
        self._epochs[ack.epoch] = ack.sequence
        self._epoch = ack.epoch
        self._heard = self._clock
        held = next((v for v, sha in self._sha.items() if sha == ack.sha256 and (v in self._versions or v == 0)),
                    None)
        ground = 0 if held is None else held
        moved = ground != self.ground or self._in_flight is not None
        self.ground = ground
        self._in_flight = None
        change = self.change
        if change is not None:
            if ground == change.target_version:
                self.change = None  # done
            elif ground != change.base_version:
                self.change = None  # the ground cannot use it: start again from what it holds
                self.counts["restarted change"] += 1
            else:
                # The ground's parts are those it reports now: a restarted ground lost the ones it had.
                ours = (ack.base_version, ack.target_version) == (change.base_version, change.target_version)
                held = {(item, part) for item, (_count, parts) in ack.reports.items() for part in parts
                        if (item, part) in change.parts} if ours else set()
                for key in held - change.held:  # the round trip is at most the time since it was sent
                    if key in change.sent_at and key not in change.resent:  # (which copy came is unknown)
                        self._trips.append(self._clock - change.sent_at[key])
                change.held = held
                if ours and self._trips:
                    # An acknowledgement arriving a round trip (the shortest seen, with a margin) after a
                    # part went out has seen it arrive, unless it was lost: send it again at once.
                    trip = LOST_AFTER_TRIPS * min(self._trips)
                    change.lost = {k for k, t in change.sent_at.items() if k not in held and t <= self._clock - trip}
        if moved:
            self._prune()
            self._save()
        return True

    # -- frames

    def _start(self) -> None:
        base_version = self.ground if self.ground in self._versions else 0
        base = self._versions.get(base_version, b"")
        target = self._versions[self.version]
        plan, items = make_change(base, target)
        payload = self.max_frame_bytes - DATA_OVERHEAD
        check = self._sha[base_version][:CHECK_BYTES]
        parts: dict[tuple[int, int], bytes] = {}
        order = []
        age = {k: self._first_seen.get(hashlib.sha1(b).digest(), self.version) for k, b in items.items()}
        first = [(0, plan)]
        detail = sum(map(len, items.values()))
        if self._preview is not None and self.preview_over is not None and detail > self.preview_over:
            preview = self._preview()
            if len(preview) < PREVIEW_SHARE * detail:
                first.append((PREVIEW_ITEM, preview))
                self.counts["previews"] += 1
                self.counts["preview bytes"] += len(preview)
        for item, data in first + sorted(items.items(), key=lambda kv: (-age[kv[0]], kv[0])):
            count = max(1, -(-len(data) // payload))
            if count > MAX_PARTS:
                raise InvalidInputError(f"an item of {len(data):,} bytes needs more than {MAX_PARTS} frames of "
                                        f"{self.max_frame_bytes} bytes: allow larger frames")
            for i in range(count):
                parts[item, i] = pack_data(DataFrame(self.map_id, base_version, self.version, check, item, i, count,
                                                     data[i * payload:(i + 1) * payload]))
                order.append((item, i))
        self.change = _Change(base_version, self.version, check, parts, order)
        self._save(target=True)
        self.counts["changes"] += 1
        self.history.append((base_version, self.version))

    def poll(self, now: float, budget: Budget | None = None) -> list[bytes]:
        """The frames to send at ``now`` (seconds): new parts in order, then resends due; within ``budget``."""
        out: list[bytes] = []
        self._clock = now
        if self.change is None:
            if not self.version or self.ground == self.version:
                return out
            self._start()
        silent = now - self._heard > self.silence_after
        change = self.change
        assert change is not None
        while True:
            key = None
            while change.next < len(change.order) and change.order[change.next] in change.held:
                change.next += 1
            if change.next < len(change.order):
                key = change.order[change.next]
            else:
                due = [(t, k) for k, t in change.sent_at.items()
                       if k not in change.held and (k in change.lost or t <= now - self.retry_after)]
                if due and (not silent or now - self._probed >= self.retry_after):
                    key = min(due)[1]
                    if silent:
                        self._probed = now
                        self.counts["probes"] += 1
            if key is None:
                return out
            frame = change.parts[key]
            if budget is not None:
                if not budget.fits(now, len(frame)):
                    return out
                budget.spend(now, len(frame))
            if change.next < len(change.order) and change.order[change.next] == key:
                change.next += 1
            else:
                self.counts["resent"] += 1
                change.resent.add(key)
            change.sent_at[key] = now
            change.lost.discard(key)
            self.counts["frames"] += 1
            self.counts["bytes"] += len(frame)
            out.append(frame)

    # -- state on disk

    def _save(self, *, target: bool = False) -> None:
        """Write the link state; the ground's confirmed map as ``STATE.base`` when it moved, and with
        ``target`` the map the change just started goes to as ``STATE.target``: a rover that restarts
        before hearing the ground applied it still holds it, and sends from it rather than the whole map."""
        if self.state is None:
            return
        ground = self.ground if self.ground in self._versions else None
        if ground:
            self._keep(Path(f"{self.state}.base"), ground)
        change = self.change
        flight = change.target_version if change is not None else self._in_flight
        if target and change is not None:
            self._keep(Path(f"{self.state}.target"), change.target_version)
        doc = {"map_id": self.map_id, "version": self.version,
               "sha256": self._sha[self.version].hex() if self.version else None,
               "ground": ground, "ground_sha256": self._sha[ground].hex() if ground else None}
        if flight and flight in self._versions and flight != ground:
            doc.update(target=flight, target_sha256=self._sha[flight].hex())
        atomic_write(self.state, lambda tmp: Path(tmp).write_text(json.dumps(doc)))

    def _keep(self, path: Path, version: int) -> None:
        """``path`` holds the map of ``version`` (written when it holds another; what it holds is
        remembered, so a version does not read and hash the file again)."""
        sha = self._sha[version]
        if self._on_disk.get(path) == sha:
            return
        if not path.is_file() or hashlib.sha256(path.read_bytes()).digest() != sha:
            atomic_write(path, self._versions[version])
        self._on_disk[path] = sha

    def _resume(self) -> None:
        assert self.state is not None
        try:
            doc = json.loads(self.state.read_text())
            self.map_id = int(doc["map_id"])
            self.version = int(doc["version"])
            ground, ground_sha = doc.get("ground"), doc.get("ground_sha256")
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise CorruptFileError(f"{self.state}: not a readable link state ({exc})") from None
        if not (0 < self.map_id < 1 << 64):
            raise CorruptFileError(f"{self.state}: a link state with map id {self.map_id}")
        for name, version, sha in (("base", ground, ground_sha), ("target", doc.get("target"), doc.get("target_sha256"))):
            path = Path(f"{self.state}.{name}")
            if version and sha and path.is_file():
                data = path.read_bytes()
                if hashlib.sha256(data).hexdigest() == sha:
                    self._versions[int(version)] = data
                    self._sha[int(version)] = bytes.fromhex(sha)
                    if name == "base":
                        self.ground = int(version)
                    else:
                        self._in_flight = int(version)
        # The newest map before the restart is not kept: the next update numbers the map after it.
        self._resumed_sha = doc.get("sha256")


# -- the receiver ---------------------------------------------------------------------------------------------------


@dataclass
class _Pending:
    change: tuple[int, int, bytes]
    map_id: int
    items: dict[int, tuple[int, dict[int, bytes]]] = field(default_factory=dict)  # item -> (parts, part -> payload)
    plan: Plan | None = None


class Receiver:
    """The ground's end: frames in, a map byte for byte the sender's at each version, acknowledgements out.

    Parameters
    ----------
    path : path, optional
        The ground's map file, written atomically at each version applied, with its link state
        (``PATH.link``, JSON: map id and version); read back on start. In memory only without it.
    map_id : int
        The map to take frames of; 0: the one of ``path``'s state, else the first frame that verifies.
    max_frame_bytes : int, optional
        Longer frames are refused; acknowledgements are kept within it.
    max_map_bytes : int
        Largest map rebuilt (bytes).
    ack_interval, keepalive : float
        Seconds: acknowledgements at most this often, and at least every ``keepalive``.
    new_maps : {"refuse", "archive"}
        Frames of a map other than the one held (a rover started a new mission: a new map id):
        ``"refuse"`` counts and logs them (``another map``, one line naming this option);
        ``"archive"`` takes the other map once a whole first version of it verifies (a change from
        nothing, every frame of it), then keeps the map held so far beside ``path`` as
        ``STEM.<its map id, 16 hex digits>SUFFIX`` (with its link state) and holds the new one at ``path``.
        Until then the map held stays as it was. A map once put aside is not taken again (an old
        rover still sending would make the ground go back and forth).
    log : callable, optional
        ``log(cause, message)``, called once per cause of refusal; default a warning on the ``dftpcc.link`` logger.
    """

    def __init__(self, path: str | os.PathLike[str] | None = None, *, map_id: int = 0,
                 max_frame_bytes: int | None = None, max_map_bytes: int = MAX_MAP_BYTES,
                 ack_interval: float = DEFAULT_ACK_INTERVAL_S, keepalive: float = DEFAULT_KEEPALIVE_S,
                 new_maps: str = "refuse", log: Callable[[str, str], None] | None = None):
        if new_maps not in NEW_MAPS:
            raise InvalidInputError(f"new_maps is one of {', '.join(NEW_MAPS)}, got {new_maps!r}")
        self.new_maps = new_maps
        self.path = None if path is None else Path(path)
        self.map_id = int(map_id)
        self.max_frame_bytes = max_frame_bytes
        self.max_map_bytes = int(max_map_bytes)
        self.ack_interval, self.keepalive = float(ack_interval), float(keepalive)
        self._log = log or (lambda cause, message: _log.warning("link: %s (%s; counted, further ones not logged)",
                                                                message, cause))
        self.data = b""
        self.version = 0
        self.archived: list[int] = []  # map ids put aside for a new mission's, oldest first
        #: The preview of the change in progress or last applied: (its target version, its bytes, map id).
        self.preview: tuple[int, bytes, int] | None = None
        self.epoch = secrets.randbits(32)
        self.sequence = 0
        self.refused: collections.Counter[str] = collections.Counter()
        self.counts: collections.Counter[str] = collections.Counter()
        self.pending: _Pending | None = None
        self._last_ack: float | None = None
        self._due = True  # acknowledge at the first poll: a restarted ground says what it holds
        self._urgent = False
        if self.path is not None and self.path.is_file():
            self._load()
        self.sha256 = hashlib.sha256(self.data).digest()

    def _load(self) -> None:
        assert self.path is not None
        self.data = self.path.read_bytes()
        state = Path(f"{self.path}{LINK_SUFFIX}")
        try:
            doc = json.loads(state.read_text())
            if doc.get("sha256") == hashlib.sha256(self.data).hexdigest():
                self.version = int(doc["version"])
            if not self.map_id:
                self.map_id = int(doc["map_id"])
            self.archived = [int(v) for v in doc.get("archived", [])]
        except (OSError, ValueError, KeyError, TypeError):
            pass  # no state or another map's: the sender finds the map by its SHA-256 or sends it whole

    def _refuse(self, cause: str, message: str) -> None:
        self.refused[cause] += 1
        if self.refused[cause] == 1:
            self._log(cause, message)

    def receive(self, frame: bytes, now: float = 0.0) -> int | None:
        """Take a frame; returns the version applied if it completed one, else None (refusals are counted)."""
        try:
            f = read_frame(frame, max_bytes=self.max_frame_bytes)
        except FrameError as exc:
            self._refuse(exc.cause, str(exc))
            return None
        if not isinstance(f, DataFrame):
            self._refuse("kind", "an acknowledgement on the downlink")
            return None
        newcomer = bool(self.map_id) and f.map_id != self.map_id
        if newcomer and self.new_maps == "refuse":
            self._refuse("another map", f"a frame of map {f.map_id:016x}, not of this ground's map {self.map_id:016x} "
                                        f"(a new mission's map? new_maps='archive', 'dftpcc ros ground --new-maps "
                                        f"archive', keeps this map beside the file and takes the new one)")
            return None
        if newcomer and f.map_id in self.archived:
            self._refuse("another map", f"a frame of map {f.map_id:016x}, which this ground put aside for map "
                                        f"{self.map_id:016x} (an earlier mission's rover still sending?)")
            return None
        if newcomer and f.base_version:
            # A change from a map of the other id, which this ground does not hold: only a whole first
            # version of the new map can start it.
            self._refuse("another map", f"a change of map {f.map_id:016x} from its version {f.base_version}, "
                                        f"which this ground does not hold (it holds map {self.map_id:016x})")
            return None
        if not newcomer:
            self.map_id = f.map_id
        self._due = True
        if not newcomer and f.target_version <= self.version:
            self.counts["already applied"] += 1
            return None
        if f.base_version and f.base_check != self.sha256[:CHECK_BYTES]:
            self._refuse("wrong base", f"a change from version {f.base_version}, which is not the map held "
                                       f"(version {self.version})")
            return None
        pending = self.pending
        if pending is not None and (pending.change != f.change or pending.map_id != f.map_id):
            if f.target_version < pending.change[1] and pending.map_id == f.map_id:
                self.counts["stale"] += 1
                return None
            pending = None
        if pending is None:
            pending = self.pending = _Pending(f.change, f.map_id)
        count, parts = pending.items.setdefault(f.item, (f.parts, {}))
        if count != f.parts:
            self._refuse("fields", f"item {f.item} of a change in {f.parts} parts and in {count}")
            return None
        if f.part in parts:
            self.counts["duplicate"] += 1
            return None
        parts[f.part] = f.payload
        if pending.plan is None and f.item == 0 and len(parts) == count:
            try:
                pending.plan = read_plan(self._joined(0), base_size=len(self._base(f)),
                                         max_map_bytes=self.max_map_bytes)
            except FrameError as exc:
                self._refuse(exc.cause, str(exc))
                self.pending = None
                return None
            for item in [k for k in pending.items if k and k != PREVIEW_ITEM and k not in pending.plan.tiles]:
                self._refuse("item", f"a frame of item {item}, which the change's plan does not name")
                del pending.items[item]  # a stray item costs itself, not the change
        elif f.item == PREVIEW_ITEM:
            return self._preview_part(pending, f)
        elif pending.plan is not None and f.item and f.item not in pending.plan.tiles:
            self._refuse("item", f"a frame of item {f.item}, which the change's plan does not name")
            del pending.items[f.item]
            return None
        return self._complete(f, now)

    def _preview_part(self, pending: _Pending, f: DataFrame) -> int | None:
        """A part of the change's preview: kept; the whole preview taken for display (never the map)."""
        count, parts = pending.items[PREVIEW_ITEM]
        if len(parts) == count and (self.preview is None or self.preview[0] != f.target_version
                                    or self.preview[2] != f.map_id):
            data = self._joined(PREVIEW_ITEM)
            if len(data) > self.max_map_bytes:
                self._refuse("preview", f"a preview of {len(data):,} bytes")
                del pending.items[PREVIEW_ITEM]
                return None
            self.preview = (f.target_version, data, f.map_id)
            self.counts["previews"] += 1
        return None

    def _base(self, f: DataFrame) -> bytes:
        return self.data if f.base_version else b""

    def _joined(self, item: int) -> bytes:
        assert self.pending is not None
        count, parts = self.pending.items[item]
        return b"".join(parts[i] for i in range(count))

    def _complete(self, f: DataFrame, now: float) -> int | None:
        pending = self.pending
        assert pending is not None
        plan = pending.plan
        if plan is None:
            return None
        for item in plan.tiles:
            count, parts = pending.items.get(item, (1, {}))
            if len(parts) != count:
                return None
        try:
            data = join_change(plan, self._base(f), {k: self._joined(k) for k in plan.tiles})
        except FrameError as exc:
            self._refuse(exc.cause, str(exc))
            self.pending = None
            return None
        self._apply(data, f.target_version, f.map_id)
        return f.target_version

    def _apply(self, data: bytes, version: int, map_id: int) -> None:
        if map_id != self.map_id and self.map_id and self.path is not None and self.path.is_file():
            kept = self.path.with_name(f"{self.path.stem}.{self.map_id:016x}{self.path.suffix}")
            os.replace(self.path, kept)  # the map first: a crash after it leaves a state naming no map held
            state = Path(f"{self.path}{LINK_SUFFIX}")
            if state.is_file():
                os.replace(state, Path(f"{kept}{LINK_SUFFIX}"))
            self._log("new map", f"map {map_id:016x} taken (a new mission); map {self.map_id:016x} kept as {kept}")
            self.counts["new maps"] += 1
        if map_id != self.map_id and self.map_id:
            self.archived.append(self.map_id)
        if self.path is not None:
            state = {"map_id": map_id, "version": version, "sha256": hashlib.sha256(data).hexdigest(),
                     **({"archived": self.archived} if self.archived else {})}
            # The map first, then the state naming it: a state naming another map is ignored on start.
            atomic_write(self.path, data)
            atomic_write(Path(f"{self.path}{LINK_SUFFIX}"), lambda tmp: Path(tmp).write_text(json.dumps(state)))
        self.data, self.version, self.map_id = data, version, map_id
        self.sha256 = hashlib.sha256(data).digest()
        self.pending = None
        self.counts["versions"] += 1
        self._urgent = True

    def poll(self, now: float) -> list[bytes]:
        """The acknowledgement to send at ``now`` (seconds), if one is due."""
        since = None if self._last_ack is None else now - self._last_ack
        if not (self._urgent or since is None or since >= self.keepalive or (self._due and since >= self.ack_interval)):
            return []
        self._urgent = self._due = False
        self._last_ack = now
        self.sequence += 1
        pending = self.pending
        reports = {}
        base_v = target_v = 0
        map_id, version, sha = self.map_id, self.version, self.sha256
        if pending is not None:
            base_v, target_v = pending.change[0], pending.change[1]
            reports = {item: (count, frozenset(parts)) for item, (count, parts) in pending.items.items()}
            if pending.map_id != self.map_id:  # to the new map's sender: nothing of its map held, these parts
                map_id, version, sha = pending.map_id, 0, _EMPTY_SHA
        ack = Ack(map_id, self.epoch, self.sequence, version, sha, base_v, target_v, reports)
        self.counts["acks"] += 1
        return [pack_ack(ack, max_bytes=self.max_frame_bytes)]
