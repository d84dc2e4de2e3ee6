"""The shared test helpers themselves: missing real data skips locally and fails under CI."""

from __future__ import annotations

import pytest

from . import conftest

MISSING = "pointclouds/no_such_survey.laz"


def test_missing_data_fails_under_ci(monkeypatch):
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception) as info:
        conftest.data_file(MISSING)
    assert str(conftest.DATA / MISSING) in str(info.value)


@pytest.mark.parametrize("value", ["1", "yes", "false"])  # any non-empty value means CI
def test_any_non_empty_ci_value_makes_missing_data_fail(monkeypatch, value):
    monkeypatch.setenv("CI", value)
    with pytest.raises(pytest.fail.Exception):
        conftest.data_file(MISSING)


@pytest.mark.parametrize("ci", [None, ""])
def test_missing_data_skips_outside_ci(monkeypatch, ci):
    if ci is None:
        monkeypatch.delenv("CI", raising=False)
    else:
        monkeypatch.setenv("CI", ci)
    with pytest.raises(pytest.skip.Exception) as info:
        conftest.data_file(MISSING)
    assert str(conftest.DATA / MISSING) in str(info.value)


def test_present_data_is_returned_whatever_ci_says(monkeypatch, tmp_path):
    monkeypatch.setattr(conftest, "DATA", tmp_path)
    (tmp_path / "dems").mkdir()
    (tmp_path / "dems" / "a.tif").write_bytes(b"x")
    for ci in ("", "1"):
        monkeypatch.setenv("CI", ci)
        assert conftest.data_file("dems/a.tif") == tmp_path / "dems" / "a.tif"
