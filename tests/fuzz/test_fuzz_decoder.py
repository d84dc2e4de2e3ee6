"""A bounded fuzz run of the decoder, in CI (the long campaign is in docs/errors.md)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from .fuzz_decoder import check, run
from .seeds import seed_files

#: Inputs per CI run and the time it may take at most (seconds).
CI_INPUTS = 6_000
CI_BUDGET_S = 30.0
#: Fixed seed: CI replays the same inputs every time; change it to explore.
CI_SEED = 5


@pytest.fixture(scope="module")
def report():
    return run(CI_INPUTS, seed=CI_SEED, time_budget=CI_BUDGET_S)


def test_no_crash_no_runaway_allocation_no_nonfinite_output(report):
    print(f"\nfuzz: {report['iterations']} inputs in {report['wall_seconds']} s, outcomes {report['outcomes']}, "
          f"max decode {report['decode_seconds_max']} s, peak/allowed {report['peak_over_allowed_max']}")
    assert report["iterations"] >= CI_INPUTS // 3  # the time budget cut it short on a loaded machine at worst
    failures = [f for f in report["failure_details"] if f["kind"] != "slow"]
    assert not failures, failures[0]["detail"]
    assert report["outcomes"].get("decoded", 0) > 0 and report["outcomes"].get("refused", 0) > 0


def test_no_input_takes_over_a_second(report):
    slow = [f for f in report["failure_details"] if f["kind"] == "slow"]
    assert not slow, slow


def test_every_seed_decodes():
    for name, data in seed_files().items():
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
