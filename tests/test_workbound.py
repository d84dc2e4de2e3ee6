"""The work counter of tests/workbound.py: it counts, it stops runaway loops, nothing swallows the stop."""

from __future__ import annotations

import numpy as np
import pytest

from .workbound import WorkLimitExceeded, measure_work


def _loop(n: int) -> int:
    total = 0
    for i in range(n):
        total += i
    return total


def test_events_grow_with_the_loop_and_not_with_compiled_work():
    with measure_work() as small:
        _loop(10)
    with measure_work() as large:
        _loop(1000)
    assert large.events - small.events == pytest.approx(2 * 990, abs=10)  # two lines per iteration
    with measure_work() as numeric:
        np.arange(1_000_000).sum()
    assert numeric.events < 100


def test_an_endless_loop_is_stopped_and_cannot_be_swallowed():
    def swallowing():
        try:
            while True:
                pass
        except Exception:  # noqa: BLE001 - what a decoder's own handler would do
            return "swallowed"

    with pytest.raises(WorkLimitExceeded):
        with measure_work(max_events=1000) as work:
            swallowing()
    assert work.exceeded and work.events == 1001


def test_peak_allocation_is_measured():
    with measure_work() as work:
        block = np.ones(1 << 20)  # 8 MiB
        del block
    assert 8 << 20 <= work.peak_bytes < 9 << 20
