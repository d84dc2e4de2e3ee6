"""Bounds on the work a call does, for tests that must not depend on the machine's speed.

A test that asserts "under one second" fails on a loaded or slow machine and
passes a decoder that is merely fast at doing too much. These measures count
work instead, the same on every machine:

* ``events``: Python function calls and executed lines inside the block
  (``sys.settrace``). A loop over a count a crafted file chose (lines of a
  mask, chunks, records) shows here, whatever it costs in seconds. With
  ``max_events`` the block is stopped by :class:`WorkLimitExceeded` at the
  limit, so an endless loop ends deterministically instead of hanging.
* ``peak_bytes``: the peak of traced allocation (``tracemalloc``), which
  bounds what compiled code (numpy, zstd, the FFT) can be asked to do: a
  decompression bomb or a huge grid has to allocate it first.

Counts depend on the code under test and, a little, on the numpy and Python
versions, so a bound is set to a few times the value measured, stated beside it.
"""

from __future__ import annotations

import sys
import tracemalloc
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

__all__ = ["Work", "WorkLimitExceeded", "measure_work"]


class WorkLimitExceeded(BaseException):
    """Raised into the measured code at its ``max_events``-th event.

    A BaseException (like KeyboardInterrupt), so the code's own
    ``except Exception`` handlers cannot turn it into an ordinary error.
    """


@dataclass
class Work:
    """What a block did: see the module docstring."""

    events: int = 0
    peak_bytes: int = 0
    exceeded: bool = False


@contextmanager
def measure_work(max_events: int | None = None, *, trace_memory: bool = True) -> Iterator[Work]:
    """Count the events and peak allocation of the ``with`` block (see the module docstring)."""
    work = Work()

    def tracer(frame, event, arg):  # noqa: ARG001 - the settrace signature
        work.events += 1
        if max_events is not None and work.events > max_events:
            work.exceeded = True
            raise WorkLimitExceeded(f"more than {max_events:,} Python events")
        return tracer

    previous = sys.gettrace()
    tracing_memory = trace_memory and not tracemalloc.is_tracing()
    if tracing_memory:
        tracemalloc.start()
    elif trace_memory:
        tracemalloc.reset_peak()
    sys.settrace(tracer)
    try:
        yield work
    finally:
        sys.settrace(previous)
        if trace_memory:
            work.peak_bytes = tracemalloc.get_traced_memory()[1]
        if tracing_memory:
            tracemalloc.stop()
