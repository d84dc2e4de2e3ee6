"""A bad link, simulated in process and seeded: what tests and benchmarks put between :mod:`dftpcc.link`'s two ends.

A :class:`Channel` carries frames one way with loss, duplication,
reordering, delay, a bandwidth cap and outages, on a clock the caller moves
(seconds; no sleeping): the same seed gives the same deliveries.
:func:`run_link` drives a sender and a receiver over two channels, a map
growing on the sender's side, until the ground holds the newest map.
"""

from __future__ import annotations

import hashlib
import heapq
import random
from dataclasses import dataclass, field
from typing import Callable, Sequence

from .errors import InvalidInputError
from .link import Budget, Receiver, Sender

__all__ = ["Channel", "Ends", "run_link", "LinkRun"]


@dataclass
class Channel:
    """One direction of a link.

    Parameters
    ----------
    seed : int
        Seed of every random choice.
    loss, duplicate, reorder : float
        Probabilities per frame: lost, delivered twice, held back by ``reorder_delay`` (so later frames pass it).
    delay, jitter : float
        Seconds: the delivery delay, plus up to ``jitter`` at random.
    rate : float, optional
        Bytes per second the channel carries (frames queue behind each other); unlimited if None.
    outages : sequence of (start, end)
        Seconds during which every frame sent is lost.
    """

    seed: int = 0
    loss: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    reorder_delay: float = 0.5
    delay: float = 0.05
    jitter: float = 0.0
    rate: float | None = None
    outages: Sequence[tuple[float, float]] = ()
    sent: int = 0
    lost: int = 0
    bytes: int = 0
    _queue: list = field(default_factory=list)
    _free_at: float = 0.0
    _n: int = 0

    def __post_init__(self) -> None:
        for name in ("loss", "duplicate", "reorder"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise InvalidInputError(f"{name} is a probability, got {getattr(self, name)!r}")
        self._rng = random.Random(self.seed)

    def down(self, now: float) -> bool:
        """Whether ``now`` falls in an outage."""
        return any(a <= now < b for a, b in self.outages)

    def send(self, frame: bytes, now: float) -> None:
        """Put a frame on the link at ``now``."""
        self.sent += 1
        self.bytes += len(frame)
        start = now if self.rate is None else max(now, self._free_at)
        done = start if self.rate is None else start + len(frame) / self.rate
        self._free_at = done
        if self.down(now) or self._rng.random() < self.loss:
            self.lost += 1
            return
        copies = 2 if self._rng.random() < self.duplicate else 1
        for _ in range(copies):
            at = done + self.delay + self._rng.random() * self.jitter
            if self._rng.random() < self.reorder:
                at += self.reorder_delay
            self._n += 1
            heapq.heappush(self._queue, (at, self._n, frame))

    def deliver(self, now: float) -> list[bytes]:
        """The frames that arrive by ``now``, in arrival order."""
        out = []
        while self._queue and self._queue[0][0] <= now:
            out.append(heapq.heappop(self._queue)[2])
        return out


@dataclass
class Ends:
    """The two ends of a link; an event may replace either (a restart)."""

    sender: Sender
    receiver: Receiver


@dataclass
class LinkRun:
    """What :func:`run_link` saw: the seconds it took, and the ground's versions applied (version, second, SHA-256
    of the ground's map then)."""

    seconds: float
    applied: list[tuple[int, float, bytes]]
    converged: bool


def run_link(ends: Ends, *, downlink: Channel, uplink: Channel, budget: Budget | None,
             events: Sequence[tuple[float, Callable[[], None]]] = (), step: float = 0.05, until: float = 600.0,
             after: float = 0.0) -> LinkRun:
    """Run the two ends over the channels from second 0 until the ground holds the sender's newest map.

    ``events``: (second, action) run once at that second (scans added, a restart); the run ends when
    every event has run, at least ``after`` seconds have passed, and the ground's map is the sender's
    newest, or at ``until`` seconds.
    """
    pending = sorted(events, key=lambda e: e[0])
    applied: list[tuple[int, float, bytes]] = []
    now = 0.0
    n = 0
    while now <= until:
        while pending and pending[0][0] <= now:
            pending.pop(0)[1]()
        sender, receiver = ends.sender, ends.receiver
        for frame in uplink.deliver(now):
            sender.receive(frame)
        for frame in sender.poll(now, budget):
            downlink.send(frame, now)
        for frame in downlink.deliver(now):
            version = receiver.receive(frame, now)
            if version is not None:
                applied.append((version, now, hashlib.sha256(receiver.data).digest()))
        for frame in receiver.poll(now):
            uplink.send(frame, now)
        if (not pending and now >= after and sender.version and receiver.version == sender.version
                and receiver.data == sender._versions.get(sender.version)):
            return LinkRun(now, applied, True)
        n += 1
        now = n * step
    return LinkRun(now, applied, False)
