"""Shared fixtures: the real survey data beside the checkout, and small self-made terrains."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

#: ../shared/data beside the checkout (CI has it there).
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def data_file(name: str) -> Path:
    """Path of a file in ../shared/data.

    When it is absent the test is skipped on a developer's machine, but fails
    under CI (the ``CI`` environment variable set to anything non-empty): CI
    has the data, so a missing file there is a broken checkout or a renamed
    file, and silently skipping would hide every real-data test.
    """
    path = DATA / name
    if not path.is_file():
        if os.environ.get("CI"):
            pytest.fail(f"real data {name} not found at {path} (CI is set, so real data is required)",
                        pytrace=False)
        pytest.skip(f"real data {name} not found at {path}")
    return path


@pytest.fixture(scope="session")
def field_ground() -> np.ndarray:
    """Ground points (class 2) of the gentle IGN field: flat terrain, quarter-disc footprint."""
    import dftpcc

    return dftpcc.read(data_file("pointclouds/field_gentle_ign.laz"), classes=[2]).points


@pytest.fixture(scope="session")
def redrocks() -> np.ndarray:
    """The rough Red Rocks cloud (local metres)."""
    import dftpcc

    return dftpcc.read(data_file("pointclouds/redrocks_rough.ply")).points


@pytest.fixture(scope="session")
def small_terrain() -> np.ndarray:
    """A small deterministic built-in terrain (about 14 000 points, 40 m square)."""
    from dftpcc.experiments.terrain import regolith_plain

    return regolith_plain(20_000, size=40.0, craters=4, rocks=30, seed=3)


@pytest.fixture
def tile_masks(monkeypatch):
    """The writer codes each tile's mask and residual layer, as for a map over
    ``tiles.MAP_MASK_CELLS`` cells, rather than the map mask and map residual at tile 0 it writes
    for a small map (docs/format.md, *Tile sections*)."""
    from dftpcc import encoder

    monkeypatch.setattr(encoder, "MAP_MASK_CELLS", 0)
