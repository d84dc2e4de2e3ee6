"""The one optional-dependency guard: a missing extra is a MissingDependencyError naming it, exit 6."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

from dftpcc import _optional, cli
from dftpcc._optional import EXTRAS, import_optional, install_hint
from dftpcc.errors import MissingDependencyError

SRC = Path(__file__).resolve().parents[1] / "src" / "dftpcc"


def test_a_missing_module_names_its_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "small_gicp", None)  # as if the extra were not installed
    with pytest.raises(MissingDependencyError) as info:
        import_optional("small_gicp", "slam", needed_for="relocalization")
    assert str(info.value) == ("relocalization needs small_gicp, which is not installed: "
                               "pip install 'dftpcc[slam]' (the small_gicp package)")
    assert isinstance(info.value, ImportError)  # callers that catch ImportError still do


def test_a_missing_submodule_is_missing_too(monkeypatch):
    monkeypatch.setitem(sys.modules, "zarr.abc.codec", None)
    with pytest.raises(MissingDependencyError, match=r"^the Zarr codec needs zarr 3, .*dftpcc\[zarr\]"):
        import_optional("zarr.abc.codec", "zarr", needed_for="the Zarr codec", name="zarr 3")


def test_an_installed_module_is_returned():
    assert import_optional("json", "plot", needed_for="nothing") is sys.modules["json"]


def test_every_extra_it_names_is_one_of_pyproject():
    text = (SRC.parents[1] / "pyproject.toml").read_text()
    for extra in EXTRAS:
        assert f"\n{extra} = [" in text, extra
        assert install_hint(extra).startswith(f"pip install 'dftpcc[{extra}]' (")


def test_the_cluster_names_the_dask_extra(monkeypatch):
    from dftpcc.cluster import executor

    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(MissingDependencyError, match=r"parallel coding needs dask.distributed.*dftpcc\[dask\]"):
        with executor(workers=1):
            pass


def test_the_command_line_exits_6(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "distributed", None)
    dem = tmp_path / "in.xyz"
    dem.write_text("".join(f"{x} {y} {x + y}\n" for x in range(40) for y in range(40)))
    code = cli.main(["compress", str(dem), str(tmp_path / "out.dftpc"), "--tile-size", "16", "--workers", "2"])
    assert code == 6
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "dftpcc[dask]" in err
    assert not (tmp_path / "out.dftpc").exists()


def test_no_module_guards_an_import_of_its_own():
    """Every optional import goes through import_optional: no ``except ImportError`` re-raised as
    MissingDependencyError elsewhere in the package."""
    for path in SRC.rglob("*.py"):
        if path.name == "_optional.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Try) and any(
                    isinstance(h.type, ast.Name) and h.type.id in ("ImportError", "ModuleNotFoundError")
                    for h in node.handlers):
                raised = [n for h in node.handlers for n in ast.walk(h) if isinstance(n, ast.Raise)]
                assert not any("MissingDependencyError" in ast.unparse(r) for r in raised), path
    assert _optional.__all__ == ["EXTRAS", "install_hint", "import_optional"]
