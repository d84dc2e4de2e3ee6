"""A bounded fuzz run of the decoder, in CI (the long campaign is in docs/errors.md).

Bounded by work, never by the clock, so a slow or loaded machine cannot fail
it: a fixed number of inputs (no time budget), each stopped as "runaway"
past a number of Python events (an endless loop is a failure, not a hang)
and checked against the allocation the container allows for its grid (a
decompression bomb is a failure). A hang inside compiled code would stall
the run rather than fail it: every size such code works on is bounded by
the same grid and allocation checks.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from .fuzz_decoder import check, run
from .seeds import legacy_files, seed_files

#: Inputs per CI run: all of them are decoded (39 s on the shared 2-core machine with the tiled seeds).
CI_INPUTS = 6_000
#: Python events (calls and lines) one input may take: 14,248 at most with
#: CI_SEED when written, a sound seed map 4,000-14,000; a loop over a count an
#: input chose takes far more.
CI_MAX_EVENTS = 50_000
#: Fixed seed: CI replays the same inputs every time; change it to explore.
CI_SEED = 5


@pytest.fixture(scope="module")
def report():
    return run(CI_INPUTS, seed=CI_SEED, time_limit=None, max_events=CI_MAX_EVENTS, watchdog=None)


def test_no_crash_no_runaway_allocation_no_nonfinite_output(report):
    print(f"\nfuzz: {report['iterations']} inputs in {report['wall_seconds']} s, outcomes {report['outcomes']}, "
          f"max events {report['python_events_max']}, peak/allowed {report['peak_over_allowed_max']}")
    assert report["iterations"] == CI_INPUTS
    assert report["failures"] == 0, report["failure_details"][0]
    assert report["outcomes"]["decoded"] + report["outcomes"]["refused"] == CI_INPUTS
    assert report["outcomes"]["decoded"] > 0 and report["outcomes"]["refused"] > 0
    assert 0 < report["peak_over_allowed_max"] <= 1


def test_no_input_runs_away(report):
    runaway = [f for f in report["failure_details"] if f["kind"] == "runaway"]
    assert not runaway, runaway
    assert 0 < report["python_events_max"] <= CI_MAX_EVENTS


def test_every_seed_decodes():
    legacy = legacy_files()  # the 1.0 and 1.1 maps are fuzzed too, tiled and not
    assert len(legacy) >= 20 and "legacy_tiled_map_residual" in legacy and "legacy_paper_dft" in legacy
    for name, data in (seed_files() | legacy_files()).items():
        outcome = check(bytes([0]) + data)
        assert outcome.kind == "decoded", (name, outcome.detail)


def test_the_atheris_harness_runs():
    pytest.importorskip("atheris")
    harness = Path(__file__).with_name("fuzz_decoder.py")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(harness.parents[2] / "src"), os.environ.get("PYTHONPATH", "")]))
    result = subprocess.run([sys.executable, str(harness), "--atheris", "-atheris_runs=300", "-timeout=5"],
                            capture_output=True, text=True, timeout=300, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "Done 300 " in result.stderr


def test_an_input_past_the_event_bound_is_a_runaway_failure():
    data = bytes([0]) + seed_files()["compact_dct"]
    assert check(data, time_limit=None, max_events=CI_MAX_EVENTS, watchdog=None).kind == "decoded"
    outcome = check(data, time_limit=None, max_events=100, watchdog=None)
    assert outcome.kind == "runaway" and outcome.failed, outcome
    assert outcome.events == 101
