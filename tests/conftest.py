"""Shared fixtures: the real survey data beside the checkout, and small self-made terrains."""

from __future__ import annotations

import importlib.metadata
import os
import re
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

#: ../shared/data beside the checkout (CI has it there).
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


#: The checkout: its Makefile says which extras `make test` installs, its pyproject.toml what they hold.
REPO = Path(__file__).resolve().parents[1]
#: The file the Makefile touches in the venv once it installed the extras.
MAKE_STAMP = ".installed"


def makefile_extras(makefile: Path = REPO / "Makefile") -> list[str]:
    """The extras the Makefile's ``pip install -e ".[...]"`` line installs."""
    found = re.search(r'pip install [^\n]*-e "\.\[([^\]]+)\]"', makefile.read_text())
    return found.group(1).split(",") if found else []


def extra_requirements(pyproject: Path = REPO / "pyproject.toml") -> dict[str, list[str]]:
    """Distribution names (as pip spells them) per extra of pyproject.toml."""
    extras = tomllib.loads(pyproject.read_text())["project"]["optional-dependencies"]
    return {extra: [re.split(r"[<>=!~;\[ ]", req, maxsplit=1)[0] for req in reqs] for extra, reqs in extras.items()}


def extras_required() -> bool:
    """Whether every extra the Makefile installs must be present: under CI (``CI`` non-empty), or in a
    venv the Makefile installed (its stamp), where a missing one is a broken install, not a choice."""
    return bool(os.environ.get("CI")) or (Path(sys.prefix) / MAKE_STAMP).is_file()


def missing_extras() -> list[str]:
    """``extra: distribution`` of every distribution of the Makefile's extras that is not installed."""
    missing = []
    requirements = extra_requirements()
    for extra in makefile_extras():
        for name in requirements.get(extra, []):
            try:
                importlib.metadata.distribution(name)
            except importlib.metadata.PackageNotFoundError:
                missing.append(f"{extra}: {name}")
    return missing


def _optional_modules() -> set[str]:
    """Import names of distributions only extras the Makefile does not install hold (atheris)."""
    requirements = extra_requirements()
    installed = {name for extra in makefile_extras() for name in requirements.get(extra, [])}
    return {name.lower().replace("-", "_") for names in requirements.values() for name in names} - {
        name.lower().replace("-", "_") for name in installed}


def pytest_sessionstart(session: pytest.Session) -> None:
    if extras_required():
        missing = missing_extras()
        if missing:
            raise pytest.UsageError(
                f"the extras the Makefile installs must be present (CI is set, or the Makefile installed this venv), "
                f"so that no test module is skipped for want of them; missing: {', '.join(missing)} "
                f"(make test installs them; or pip install -e '.[{','.join(makefile_extras())}]')")


def strict_skip(report: pytest.TestReport | pytest.CollectReport) -> None:
    """Turn a skip for a module that could not be imported into a failure where extras are required
    (an importorskip of a module an installed extra should give), so that no module is silently skipped."""
    if not (report.skipped and extras_required()):
        return
    reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
    found = re.search(r"could not import '([\w.]+)'", reason)
    if found and found.group(1).split(".")[0].lower() not in _optional_modules():
        report.outcome = "failed"
        report.longrepr = (f"{reason}: the Makefile installs the extra that provides it, and CI is set or the "
                           f"Makefile installed this venv, so a missing module is a failure, not a skip")


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector: pytest.Collector):
    outcome = yield
    strict_skip(outcome.get_result())


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    outcome = yield
    strict_skip(outcome.get_result())


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


#: Tests measured at over SLOW_S seconds in a full run on the shared 2-core box (``tests/slow.txt``, one
#: node id a line, written by ``python scripts/slow_tests.py DURATIONS``): marked ``slow``, so
#: ``pytest -m "not slow"`` is the inner loop's fast set. CI runs every test.
SLOW_LIST = Path(__file__).parent / "slow.txt"


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "slow: over a second or two on the shared box; left out by -m 'not slow'")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    slow = set(SLOW_LIST.read_text().split()) if SLOW_LIST.is_file() else set()
    for item in items:
        # A parametrized test is listed by its function: its cases share their cost.
        if item.nodeid in slow or item.nodeid.split("[")[0] in slow:
            item.add_marker(pytest.mark.slow)


@pytest.fixture(autouse=True)
def _kernel_state_kept():
    """Each test starts with the process's kernel state as the one before left it: a test that makes
    numba's import fail (or sets DFTPCC_JIT) must not leave later tests without the compiled backend."""
    from dftpcc import kernels

    state, jit = dict(kernels._state), os.environ.get("DFTPCC_JIT")
    yield
    kernels._state.clear()
    kernels._state.update(state)
    if jit is None:
        os.environ.pop("DFTPCC_JIT", None)
    else:
        os.environ["DFTPCC_JIT"] = jit
