"""Maps read by URL (format.source.RemoteSource, through fsspec): a local HTTP server on loopback
that counts the bytes it serves, with and without range requests."""

from __future__ import annotations

import http.server
import re
import threading
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


class _Handler(http.server.SimpleHTTPRequestHandler):
    """Serves a folder, with single-range requests when the server allows them; counts bytes sent."""

    def log_message(self, *args):  # quiet
        pass

    def do_GET(self):  # noqa: N802 - http.server's name
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
        self.end_headers()


@pytest.fixture
def serve(tmp_path):
    """``serve(ranges)``: the URL of ``tmp_path`` on a new loopback server; ``serve.servers`` its servers."""
    servers = []

    def start(ranges: bool = True) -> str:
        handler = lambda *a, **k: _Handler(*a, directory=str(tmp_path), **k)  # noqa: E731
        server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        server.ranges, server.sent = ranges, 0
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
