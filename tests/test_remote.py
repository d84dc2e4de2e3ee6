"""Maps and inputs read by URL (dftpcc.remote.Remote, through fsspec): a local HTTP server on
loopback that counts the bytes it serves, with and without range requests, sends an ETag (of the
file's bytes, as a server's of its length and date), and can change a file between two requests."""

from __future__ import annotations

import http.server
import re
import shutil
import threading
import zlib
from pathlib import Path

import numpy as np
import pytest

import dftpcc
from dftpcc import cli
from dftpcc.dem import DEM, Grid
from dftpcc.encoder import encode_dem
from dftpcc.params import make_params

pytest.importorskip("fsspec")
pytest.importorskip("aiohttp")


def _etag(data: bytes) -> str:
    return f'"{zlib.crc32(data):08x}-{len(data):x}"'


class _Handler(http.server.SimpleHTTPRequestHandler):
    """Serves a folder, with single-range requests when the server allows them; counts bytes sent and
    GET requests; ``server.on_get(count)``, when set, runs before the GET numbered ``count`` (from 1)."""

    def log_message(self, *args):  # quiet
        pass

    def do_GET(self):  # noqa: N802 - http.server's name
        self.server.gets += 1
        if self.server.on_get is not None:
            self.server.on_get(self.server.gets)
        path = Path(self.translate_path(self.path))
        if not path.is_file():
            self.send_error(404)
            return
        data = path.read_bytes()
        found = re.fullmatch(r"bytes=(\d+)-(\d*)", self.headers.get("Range", ""))
        if found and self.server.ranges:
            start = int(found[1])
            end = min(int(found[2]) + 1 if found[2] else len(data), len(data))
            self.send_response(206)
            self.send_header("Content-Range", f"bytes {start}-{end - 1}/{len(data)}")
            body = data[start:end]
        else:
            self.send_response(200)
            body = data
        self.send_header("Content-Length", str(len(body)))
        self.send_header("ETag", _etag(data))
        if self.server.ranges:
            self.send_header("Accept-Ranges", "bytes")
        self.end_headers()
        self.wfile.write(body)
        self.server.sent += len(body)

    def do_HEAD(self):  # noqa: N802
        path = Path(self.translate_path(self.path))
        if not path.is_file():
            self.send_error(404)
            return
        self.send_response(200)
        self.send_header("Content-Length", str(path.stat().st_size))
        self.send_header("ETag", _etag(path.read_bytes()))
        self.end_headers()


@pytest.fixture
def serve(tmp_path):
    """``serve(ranges)``: the URL of ``tmp_path`` on a new loopback server; ``serve.servers`` its servers."""
    servers = []

    def start(ranges: bool = True) -> str:
        handler = lambda *a, **k: _Handler(*a, directory=str(tmp_path), **k)  # noqa: E731
        server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        server.ranges, server.sent, server.gets, server.on_get = ranges, 0, 0, None
        threading.Thread(target=server.serve_forever, daemon=True).start()
        servers.append(server)
        return f"http://127.0.0.1:{server.server_address[1]}"

    start.servers = servers
    yield start
    for server in servers:
        server.shutdown()
        server.server_close()


def _tiled(tmp_path: Path) -> Path:
    rows, cols = 768, 768
    r, c = np.mgrid[0:rows, 0:cols].astype(float)
    h = 0.02 * c + 3 * np.sin(r / 29) * np.cos(c / 37) + 0.05 * np.random.default_rng(1).standard_normal((rows, cols))
    dem = DEM(grid=Grid(x0=0.0, y0=0.0, z0=0.0, resolution=1.0, rows=rows, cols=cols), heights=h,
              mask=np.ones((rows, cols), dtype=bool))
    path = tmp_path / "tiled.dftpc"
    path.write_bytes(encode_dem(dem, make_params(tile_size=128, cutoff=0.8, step=0.01)))
    return path


def test_a_bbox_read_by_url_fetches_what_a_local_read_reads(tmp_path, serve):
    path = _tiled(tmp_path)
    base = serve(ranges=True)
    box = (10.0, 10.0, 100.0, 100.0)  # one tile
    with dftpcc.open(path) as local:
        want = local.read_points(bbox=box)
        local_bytes = local.bytes_read
    with dftpcc.open(f"{base}/tiled.dftpc") as remote:
        got = remote.read_points(bbox=box)
        remote_bytes = remote.bytes_read
    assert np.array_equal(got, want)
    assert remote_bytes == local_bytes < path.stat().st_size / 4
    served = serve.servers[0].sent
    assert local_bytes <= served < path.stat().st_size / 4  # what was asked, not the file


def test_info_and_decompress_by_url_on_the_command_line(tmp_path, serve, capsys):
    path = _tiled(tmp_path)
    base = serve(ranges=True)
    assert cli.main(["info", f"{base}/tiled.dftpc", "--json"]) == 0
    assert '"format_version": "1.2"' in capsys.readouterr().out
    out = tmp_path / "part.xyz"
    assert cli.main(["decompress", f"{base}/tiled.dftpc", str(out), "--bbox", "10,10,100,100", "-q"]) == 0
    with dftpcc.open(path) as local:
        want = local.read_points(bbox=(10.0, 10.0, 100.0, 100.0))
    assert np.allclose(np.loadtxt(out), want, atol=1e-3)


def test_a_server_without_ranges_is_read_whole_and_a_missing_url_is_one_error(tmp_path, serve, capsys):
    path = _tiled(tmp_path)
    base = serve(ranges=False)
    with dftpcc.open(f"{base}/tiled.dftpc") as remote:
        pts = remote.read_points(bbox=(10.0, 10.0, 100.0, 100.0))
        assert remote._source.whole  # the fallback, said
    with dftpcc.open(path) as local:
        assert np.array_equal(pts, local.read_points(bbox=(10.0, 10.0, 100.0, 100.0)))
    code = cli.main(["info", f"{base}/missing.dftpc"])
    err = capsys.readouterr().err
    assert code == 3 and err.count("\n") == 1 and "no such file" in err
    code = cli.main(["info", "http://127.0.0.1:9/none.dftpc"])  # nothing listens on the discard port
    err = capsys.readouterr().err
    assert code == 3 and err.count("\n") == 1 and "cannot reach" in err


# -- inputs by URL -----------------------------------------------------------------------------------

from dftpcc.errors import RemoteWarning  # noqa: E402

from .conftest import data_file  # noqa: E402

DEM_NAME = "mars_gale_1m.tif"
LAZ_NAME = "urban_autzen.laz"


def _served(tmp_path: Path, name: str, folder: str) -> Path:
    path = tmp_path / name
    shutil.copyfile(data_file(f"{folder}/{name}"), path)
    return path


def test_a_geotiff_and_a_laz_by_url_compress_to_the_bytes_of_the_local_files(tmp_path, serve, capsys):
    dem, laz = _served(tmp_path, DEM_NAME, "dems"), _served(tmp_path, LAZ_NAME, "pointclouds")
    base = serve(ranges=True)
    for path, extra in ((dem, []), (laz, ["--chunk-points", "200000"])):  # the LAZ read in chunks, pass after pass
        local, remote = tmp_path / f"{path.stem}.local.dftpc", tmp_path / f"{path.stem}.url.dftpc"
        assert cli.main(["compress", str(path), str(local), "-q", "--cutoff", "0.8", "--step", "0.05", *extra]) == 0
        assert cli.main(["compress", f"{base}/{path.name}", str(remote), "-q", "--cutoff", "0.8",
                         "--step", "0.05", *extra]) == 0
        assert remote.read_bytes() == local.read_bytes()
    assert capsys.readouterr().err == ""


def test_a_band_coded_geotiff_by_url_on_two_workers_is_the_serial_bytes(tmp_path, serve, monkeypatch):
    """Each dask worker opens its own window of the URL (range requests of its own), checked against
    the client's stamp; the file is the serial run's on the local file."""
    pytest.importorskip("distributed")
    from dftpcc import stream

    monkeypatch.setattr(stream, "STREAM_CELLS", 50_000)
    dem = _served(tmp_path, DEM_NAME, "dems")
    base = serve(ranges=True)
    serial, parallel = tmp_path / "s.dftpc", tmp_path / "p.dftpc"
    dftpcc.compress_file(dem, serial, tile_size=64, cutoff=0.8, step=0.05)
    dftpcc.compress_file(f"{base}/{DEM_NAME}", parallel, tile_size=64, cutoff=0.8, step=0.05, workers=2)
    assert parallel.read_bytes() == serial.read_bytes()


def _change_at(path: Path, request: int):
    def on_get(count: int) -> None:
        if count == request:  # another file of the same length: only its ETag tells
            data = bytearray(path.read_bytes())
            data[-1] ^= 0xFF
            path.write_bytes(bytes(data))
    return on_get


@pytest.mark.parametrize("name, folder, extra", [(DEM_NAME, "dems", []),
                                                 (LAZ_NAME, "pointclouds", ["--chunk-points", "50000"])])
def test_an_input_that_changes_between_requests_is_refused_and_nothing_is_written(tmp_path, serve, capsys,
                                                                                 name, folder, extra):
    path = _served(tmp_path, name, folder)
    base = serve(ranges=True)
    serve.servers[0].on_get = _change_at(path, 3)
    out = tmp_path / "out.dftpc"
    code = cli.main(["compress", f"{base}/{name}", str(out), "-q", "--cutoff", "0.8", "--step", "0.05", *extra])
    err = capsys.readouterr().err
    assert code == 3 and err.count("\n") == 1 and "changed while it was read" in err and "ETag" in err, err
    assert not out.exists() and list(tmp_path.glob("out*")) == []


def test_a_band_coded_geotiff_that_changes_under_the_workers_is_refused(tmp_path, serve, monkeypatch):
    pytest.importorskip("distributed")
    from dftpcc import stream
    from dftpcc.errors import InvalidInputError

    monkeypatch.setattr(stream, "STREAM_CELLS", 50_000)
    dem = _served(tmp_path, DEM_NAME, "dems")
    base = serve(ranges=True)
    serve.servers[0].on_get = _change_at(dem, 6)  # after the survey's first reads, before the workers'
    out = tmp_path / "p.dftpc"
    with pytest.raises(InvalidInputError, match="changed while it was read"):
        dftpcc.compress_file(f"{base}/{DEM_NAME}", out, tile_size=64, cutoff=0.8, step=0.05, workers=2)
    assert not out.exists()


def test_a_map_that_changes_between_requests_is_refused(tmp_path, serve, capsys):
    path = _tiled(tmp_path)
    base = serve(ranges=True)
    serve.servers[0].on_get = _change_at(path, 2)  # after the header
    out = tmp_path / "part.xyz"
    code = cli.main(["decompress", f"{base}/tiled.dftpc", str(out), "--bbox", "10,10,300,300", "-q"])
    err = capsys.readouterr().err
    assert code != 0 and err.count("\n") == 1 and "changed while it was read" in err, err
    assert not out.exists()


def test_an_input_on_a_server_without_ranges_is_downloaded_first_and_said(tmp_path, serve):
    dem = _served(tmp_path, DEM_NAME, "dems")
    base = serve(ranges=False)
    local, remote = tmp_path / "l.dftpc", tmp_path / "r.dftpc"
    dftpcc.compress_file(dem, local, cutoff=0.8, step=0.05)
    with pytest.warns(RemoteWarning, match="does not serve byte ranges"):
        dftpcc.compress_file(f"{base}/{DEM_NAME}", remote, cutoff=0.8, step=0.05)
    assert remote.read_bytes() == local.read_bytes()


def test_a_format_not_read_by_ranges_is_downloaded_and_an_unreachable_input_is_one_line(tmp_path, serve, capsys):
    pts = np.random.default_rng(3).uniform(0, 50, (4000, 3))
    np.savetxt(tmp_path / "cloud.xyz", pts)
    base = serve(ranges=True)
    local, remote = tmp_path / "l.dftpc", tmp_path / "r.dftpc"
    assert cli.main(["compress", str(tmp_path / "cloud.xyz"), str(local), "-q", "--resolution", "2"]) == 0
    assert cli.main(["compress", f"{base}/cloud.xyz", str(remote), "-q", "--resolution", "2"]) == 0
    assert remote.read_bytes() == local.read_bytes()
    for url, words in (("http://127.0.0.1:9/dem.tif", "cannot reach"), (f"{base}/missing.tif", "no such file")):
        code = cli.main(["compress", url, str(tmp_path / "x.dftpc"), "-q"])
        err = capsys.readouterr().err
        assert code == 3 and err.count("\n") == 1 and words in err, err
    assert not (tmp_path / "x.dftpc").exists()
