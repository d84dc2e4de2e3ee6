"""``dftpcc view``: the server on loopback, its refusals, its stop on Ctrl-C, and the wheel's assets.

The page itself is tested in a headless browser by web/test/viewer.test.mjs (make test-web).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import urllib.error
import urllib.request
import zipfile
from pathlib import Path

import numpy as np
import pytest

import dftpcc
from dftpcc.viewer import ASSETS, grid_original

ROOT = Path(__file__).resolve().parents[1]
GALE = ROOT / ".." / "shared" / "data" / "dems" / "mars_gale_1m.tif"
ENV = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "PYTHONWARNINGS": "ignore"}


@pytest.fixture(scope="module")
def gale(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("view") / "gale.dftpc"
    dftpcc.compress_file(GALE, out)
    return out


def _start(*args: str) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-m", "dftpcc", "view", *args], env=ENV, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    if "http://" not in line:
        proc.kill()
        raise AssertionError(f"no URL: {line!r} {proc.stderr.read()!r}")
    return proc, line.split()[2]


def _get(url: str) -> tuple[bytes, dict[str, str]]:
    with urllib.request.urlopen(url, timeout=10) as res:
        return res.read(), dict(res.headers)


def test_view_serves_page_and_map_and_stops_on_sigint(gale: Path) -> None:
    proc, url = _start(str(gale), "--port", "0")
    try:
        assert url.startswith("http://127.0.0.1:")
        page, head = _get(url)
        assert head["Content-Type"].startswith("text/html") and b'src="viewer.js"' in page
        for name in ("viewer.js", "worker.js"):
            body, head = _get(url + name)
            assert head["Content-Type"].startswith("text/javascript") and len(body) > 10_000
        body, head = _get(url + "map.dftpc")
        assert body == gale.read_bytes() and head["ETag"]
        state = json.loads(_get(url + "map.json")[0])
        assert state["bytes"] == gale.stat().st_size and state["follow"] is False and state["original"] is False
        # A thin link: the same bytes, in slices.
        assert _get(url + "map.dftpc?rate=40000")[0] == gale.read_bytes()
        with pytest.raises(urllib.error.HTTPError) as err:
            _get(url + "original.f32")
        assert err.value.code == 404
        with pytest.raises(urllib.error.HTTPError) as err:
            _get(url + "../pyproject.toml")
        assert err.value.code == 404
    finally:
        proc.send_signal(signal.SIGINT)
        out, errs = proc.communicate(timeout=10)
    assert proc.returncode == 0, errs
    assert "Traceback" not in errs


def test_view_follows_a_replaced_map(gale: Path, tmp_path: Path) -> None:
    path = tmp_path / "growing.dftpc"
    path.write_bytes(gale.read_bytes())
    proc, url = _start(str(path), "--port", "0", "--follow")
    try:
        first = json.loads(_get(url + "map.json")[0])
        assert first["follow"] is True
        (tmp_path / "next").write_bytes(gale.read_bytes() + b"")
        os.utime(tmp_path / "next", ns=(1, 1))
        os.replace(tmp_path / "next", path)
        assert json.loads(_get(url + "map.json")[0])["etag"] != first["etag"]
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=10)


def test_view_original_is_the_map_grid(gale: Path) -> None:
    proc, url = _start(str(gale), "--port", "0", "--original", str(GALE))
    try:
        body = _get(url + "original.f32")[0]
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=10)
    assert body == grid_original(gale, GALE)
    with dftpcc.open(gale) as cmap:
        dem = cmap.read_dem()
        z0 = cmap.grid.z0
        stated = cmap.info()["stats"]["dem_max_error_m"]
    original = np.frombuffer(body, "<f4").reshape(dem.mask.shape)
    assert np.array_equal(np.isfinite(original), dem.mask)
    # The map was made from this raster: decoded minus original within the stated error (float32 heights).
    worst = np.nanmax(np.abs(dem.heights + z0 - original))
    assert 0 < worst <= stated + 2 * np.spacing(np.float32(np.nanmax(np.abs(original))))


def test_view_missing_map_is_one_line(tmp_path: Path) -> None:
    run = subprocess.run([sys.executable, "-m", "dftpcc", "view", str(tmp_path / "nope.dftpc"), "--port", "0"],
                         env=ENV, capture_output=True, text=True, timeout=60)
    assert run.returncode != 0
    assert run.stderr.count("\n") == 1 and "no such map file" in run.stderr, run.stderr


def test_view_busy_port_is_one_line(gale: Path) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        run = subprocess.run([sys.executable, "-m", "dftpcc", "view", str(gale), "--port", str(port)],
                             env=ENV, capture_output=True, text=True, timeout=60)
    assert run.returncode != 0
    assert run.stderr.count("\n") == 1 and f"port {port}" in run.stderr and "in use" in run.stderr, run.stderr


def test_assets_are_in_the_package() -> None:
    names = sorted(p.name for p in ASSETS.iterdir())
    assert names == ["index.html", "viewer.js", "worker.js"]
    # Small enough to commit (pip users need no Node): see web/viewer/build.mjs.
    assert sum(p.stat().st_size for p in ASSETS.iterdir()) < 1_000_000


def test_wheel_ships_the_viewer(tmp_path: Path) -> None:
    # From a copy of the sources: an in-tree build/ of an earlier run would carry files the package data misses.
    tree = tmp_path / "tree"
    shutil.copytree(ROOT / "src", tree / "src", ignore=shutil.ignore_patterns("*.egg-info", "__pycache__", "*.so"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, tree / name)
    run = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path), str(tree)],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    (wheel,) = tmp_path.glob("dftpcc-*.whl")
    with zipfile.ZipFile(wheel) as z:
        shipped = {n: z.read(n) for n in z.namelist() if n.startswith("dftpcc/viewer_assets/")}
    assert sorted(shipped) == [f"dftpcc/viewer_assets/{n}" for n in ("index.html", "viewer.js", "worker.js")]
    for name, body in shipped.items():
        assert body == (ASSETS / Path(name).name).read_bytes()
