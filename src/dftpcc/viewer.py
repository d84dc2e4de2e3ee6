"""``dftpcc view``: the browser viewer of a ``.dftpc`` map, served on loopback.

The page (three.js terrain, built from web/viewer/ into ``viewer_assets``) decodes the map itself
with the JavaScript decoder in a Web Worker; this server only hands it the bytes, so what the page
shows is what a receiver without Python would decode. The standard library's server is enough: one
user, on 127.0.0.1.
"""

from __future__ import annotations

import errno
import json
import os
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any, Callable
from urllib.parse import parse_qs, urlsplit

from .errors import DftpccError, InvalidInputError

__all__ = ["ASSETS", "MapServer", "grid_original", "serve"]

#: The built page (web/viewer/build.mjs writes it; the wheel ships it as package data).
ASSETS = Path(__file__).with_name("viewer_assets")
_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
          ".css": "text/css; charset=utf-8", ".map": "application/json"}
#: A throttled map (``?rate=`` on the page's address, to watch a thin link) goes out in this many slices a second.
_SLICES_PER_S = 10


def grid_original(map_path: str | os.PathLike[str], original: str | os.PathLike[str], *,
                  max_cells: int | None = None) -> bytes:
    """The original cloud gridded on the map's grid, as the page's error view reads it.

    Parameters
    ----------
    map_path : path
        The ``.dftpc`` map whose grid (and aggregate) the original is gridded on.
    original : path
        The point cloud (or raster) the map was made from.
    max_cells : int, optional
        Largest grid a trusted map may ask for (see :func:`dftpcc.open`).

    Returns
    -------
    bytes
        ``rows * cols`` little-endian float32 heights (metres, row 0 at the smallest v), NaN
        where no point falls.
    """
    import numpy as np

    from .grid import rasterize
    from .io import read
    from .mapfile import open as open_map

    with open_map(map_path, max_cells=max_cells) as cmap:
        grid, aggregate = cmap.grid, cmap.params.aggregate
    dem = rasterize(read(original).points, grid, aggregate=aggregate)
    heights = np.where(dem.mask, dem.heights + grid.z0, np.nan).astype("<f4")  # DEM heights are about z0
    return heights.tobytes()


class MapServer(ThreadingHTTPServer):
    """The page, its scripts, the map (read afresh at each request: it may grow) and the original."""

    daemon_threads = True

    def __init__(self, port: int, map_path: Path, *, original: bytes | None = None, follow: bool = False,
                 assets: Path = ASSETS):
        self.map_path = map_path
        self.original = original
        self.follow = follow
        self.assets = assets
        try:
            super().__init__(("127.0.0.1", port), _Handler)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise InvalidInputError(f"port {port} on 127.0.0.1 is in use; choose another with --port "
                                        f"(0 picks a free one)") from None
            raise

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server_address[1]}/"

    def map_state(self) -> dict[str, Any]:
        """Name, size and ETag of the map now (the page polls this with --follow)."""
        st = self.map_path.stat()
        return {"name": self.map_path.name, "bytes": st.st_size, "etag": f"{st.st_mtime_ns:x}-{st.st_size:x}",
                "follow": self.follow, "original": self.original is not None}


class _Handler(BaseHTTPRequestHandler):
    server: MapServer
    protocol_version = "HTTP/1.1"

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - the base class's name
        pass  # the terminal keeps the URL line only

    def do_GET(self) -> None:  # noqa: N802 - http.server's name
        url = urlsplit(self.path)
        routes: dict[str, Callable[[dict[str, list[str]]], None]] = {
            "/map.dftpc": self._map, "/map.json": self._state, "/original.f32": self._original}
        if url.path in routes:
            routes[url.path](parse_qs(url.query))
        else:
            self._asset("index.html" if url.path == "/" else url.path.lstrip("/"))

    def _send(self, body: bytes, kind: str, *, status: int = HTTPStatus.OK, extra: dict[str, str] | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        for key, value in (extra or {}).items():
            self.send_header(key, value)
        self.end_headers()
        self.wfile.write(body)

    def _missing(self, what: str) -> None:
        self._send(f"{what}\n".encode(), "text/plain; charset=utf-8", status=HTTPStatus.NOT_FOUND)

    def _asset(self, name: str) -> None:
        path = (self.server.assets / name).resolve()
        if path.parent != self.server.assets.resolve() or not path.is_file():
            self._missing(f"no {name}")
            return
        self._send(path.read_bytes(), _TYPES.get(path.suffix, "application/octet-stream"))

    def _state(self, _query: dict[str, list[str]]) -> None:
        try:
            state = self.server.map_state()
        except OSError as exc:
            self._missing(f"the map is gone: {exc.strerror}")
            return
        self._send(json.dumps(state).encode(), "application/json")

    def _original(self, _query: dict[str, list[str]]) -> None:
        if self.server.original is None:
            self._missing("no --original was given")
            return
        self._send(self.server.original, "application/octet-stream")

    def _map(self, query: dict[str, list[str]]) -> None:
        try:
            data = self.server.map_path.read_bytes()
            etag = self.server.map_state()["etag"]
        except OSError as exc:
            self._missing(f"the map is gone: {exc.strerror}")
            return
        try:
            rate = float(query.get("rate", ["0"])[0])
        except ValueError:
            rate = 0.0
        if not rate > 0:
            self._send(data, "application/octet-stream", extra={"ETag": f'"{etag}"'})
            return
        # A thin link, for watching the map refine: the bytes in slices, each after its share of a second.
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "application/octet-stream")
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("ETag", f'"{etag}"')
        self.end_headers()
        step = max(1, int(rate / _SLICES_PER_S))
        try:
            for start in range(0, len(data), step):
                self.wfile.write(data[start:start + step])
                self.wfile.flush()
                time.sleep(1 / _SLICES_PER_S)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the page went away or reloaded


def serve(map_path: str | os.PathLike[str], *, port: int = 8765, original: str | os.PathLike[str] | None = None,
          follow: bool = False, max_cells: int | None = None, on_ready: Callable[[str], None] = print) -> int:
    """Serve the viewer of ``map_path`` on 127.0.0.1 until Ctrl-C.

    Parameters
    ----------
    map_path : path
        The ``.dftpc`` map (read afresh at each request, so a growing map shows its latest state).
    port : int
        TCP port on 127.0.0.1; 0 picks a free one.
    original : path, optional
        The cloud the map was made from, gridded on the map's grid for the page's error view.
    follow : bool
        The page reloads the map when its file changes (it polls the file's ETag once a second).
    max_cells : int, optional
        Largest grid a trusted map may ask for when gridding the original.
    on_ready : callable
        Told the page's URL once the server listens.

    Returns
    -------
    int
        0 once stopped by Ctrl-C (SIGINT).
    """
    path = Path(map_path)
    if not path.is_file():
        raise InvalidInputError(f"{path}: no such map file")
    gridded = None if original is None else grid_original(path, original, max_cells=max_cells)
    if not (ASSETS / "index.html").is_file():
        raise DftpccError(f"the viewer's page is missing from {ASSETS} (build it with `make viewer`)")
    server = MapServer(port, path, original=gridded, follow=follow)
    # serve_forever in a thread so the main thread sleeps where Ctrl-C lands cleanly.
    worker = threading.Thread(target=server.serve_forever, name="dftpcc-view", daemon=True)
    worker.start()
    try:
        on_ready(server.url)
        while worker.is_alive():
            worker.join(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        server.shutdown()
        server.server_close()
    return 0
