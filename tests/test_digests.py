"""What the renovation must not change: the files the codec writes on the real data.

``tests/digests.json`` holds the SHA-256 of every ``.dftpc`` that
``scripts/digests.py`` writes for the files of ../shared/data with the default
options, the paper profile, each rate-control target and the footprint mask
(or the error a case ends in). This test recomputes those of the files under
2 M points; ``python scripts/digests.py`` checks all of them. A deliberate
change of the output is recorded with ``python scripts/digests.py --write``
and said in CHANGELOG.md.

SHA-256 admits no round-off, and float results may differ in their last bit on another CPU's
SIMD paths, so this runs where the digests were recorded: set ``DFTPCC_DIGESTS=1`` (or run
``make digests``). ``tests/test_sizes.py`` guards the sizes on every machine, within 0.5 %.
"""

from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path

import pytest

from .conftest import data_file

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("digests", ROOT / "scripts" / "digests.py")
digests = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(digests)
RECORDED = json.loads((ROOT / "tests" / "digests.json").read_text())
SMALL = [name for name, large in digests.FILES.items() if not large]


@pytest.mark.skipif(not os.environ.get("DFTPCC_DIGESTS"), reason="digests are exact: DFTPCC_DIGESTS=1 where recorded")
@pytest.mark.parametrize("name", SMALL)
def test_the_codec_writes_the_recorded_files(name):
    data_file(name)
    for case, options in digests.CASES.items():
        key = f"{name}|{case}"
        assert digests.digest(name, options) == RECORDED[key], f"{key} changed"


@pytest.mark.skipif(not os.environ.get("DFTPCC_DIGESTS"), reason="digests are exact: DFTPCC_DIGESTS=1 where recorded")
def test_a_growing_map_writes_the_recorded_files():
    data_file(digests.GROWING_FILE)
    for key, value in digests.growing().items():
        assert value == RECORDED[key], f"{key} changed"
