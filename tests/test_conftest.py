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


def test_pytest_q_output_is_only_dots_and_the_summary():
    """A test that writes past pytest's capture (``capsys.disabled()``) breaks ``pytest -q``'s lines
    of dots: the rover's ray-casting timings printed 'vlp16: 28800 rays ...' among them."""
    import subprocess
    import sys
    from pathlib import Path

    test = Path(__file__).with_name("test_rover.py")
    result = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                             f"{test}::test_raycaster_speed_is_reported"],
                            capture_output=True, text=True, timeout=600, cwd=Path(__file__).parents[1])
    assert result.returncode in (0, 5), result.stdout + result.stderr  # 5: skipped without the data
    assert "rays" not in result.stdout, result.stdout
