"""Under CI, or in a venv the Makefile installed, an extra the Makefile installs must be present: a missing
one fails the run at its start, and an importorskip of its module fails instead of skipping (issue 41, item 14)."""

from __future__ import annotations

import importlib.metadata
import sys

import pytest
from _pytest.reports import CollectReport

from . import conftest

SKIPPED_ZARR = ("tests/test_zarr_codec.py", 27, "Skipped: could not import 'zarr': No module named 'zarr'")
SKIPPED_ATHERIS = ("tests/fuzz/x.py", 3, "Skipped: could not import 'atheris': No module named 'atheris'")


def _without(monkeypatch, *names: str) -> None:
    real = importlib.metadata.distribution

    def distribution(name):
        if name in names:
            raise importlib.metadata.PackageNotFoundError(name)
        return real(name)
    monkeypatch.setattr(importlib.metadata, "distribution", distribution)


def _outside_ci(monkeypatch, tmp_path) -> None:
    monkeypatch.delenv("CI", raising=False)
    monkeypatch.setattr(sys, "prefix", str(tmp_path))  # a venv without the Makefile's stamp


def test_the_makefile_extras_are_read_from_the_makefile_and_pyproject():
    extras = conftest.makefile_extras()
    assert {"zarr", "dask", "ros", "fast", "slam"} <= set(extras)
    requirements = conftest.extra_requirements()
    assert "numba" in requirements["fast"] and "distributed" in requirements["dask"]
    assert conftest._optional_modules() == {"atheris"}  # the fuzz extra, which the Makefile leaves out


def test_a_missing_extra_fails_the_run_under_ci(monkeypatch):
    monkeypatch.setenv("CI", "true")
    _without(monkeypatch, "zarr", "numba")
    with pytest.raises(pytest.UsageError, match="missing: zarr: zarr, fast: numba"):
        conftest.pytest_sessionstart(None)


def test_a_missing_extra_fails_where_the_makefile_installed_the_venv(monkeypatch, tmp_path):
    _outside_ci(monkeypatch, tmp_path)
    (tmp_path / conftest.MAKE_STAMP).touch()
    _without(monkeypatch, "small_gicp")
    with pytest.raises(pytest.UsageError, match="slam: small_gicp"):
        conftest.pytest_sessionstart(None)


def test_a_missing_extra_is_a_choice_elsewhere(monkeypatch, tmp_path):
    _outside_ci(monkeypatch, tmp_path)
    _without(monkeypatch, "zarr")
    conftest.pytest_sessionstart(None)  # no error: skips are allowed on a developer's own install
    report = CollectReport("tests/test_zarr_codec.py", "skipped", SKIPPED_ZARR, [])
    conftest.strict_skip(report)
    assert report.skipped


def test_an_importorskip_of_an_installed_extra_fails_under_ci(monkeypatch):
    monkeypatch.setenv("CI", "1")
    report = CollectReport("tests/test_zarr_codec.py", "skipped", SKIPPED_ZARR, [])
    conftest.strict_skip(report)
    assert report.failed and "could not import 'zarr'" in str(report.longrepr)
    optional = CollectReport("tests/fuzz/x.py", "skipped", SKIPPED_ATHERIS, [])
    conftest.strict_skip(optional)
    assert optional.skipped  # atheris: the fuzz extra, not installed by the Makefile
