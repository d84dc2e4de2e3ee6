"""Container stage: the ``.dftpc`` byte layout (see docs/format.md).

A file is a fixed preamble, a table of sections (tag, tile, offset, length,
CRC-32) protected by its own CRC, then the section payloads. Every section is
checked against its CRC before use, and every size is checked against the
file length before anything is allocated. Tile 0 is the whole map; the tile
field lets a later tiled layout add independently coded tiles behind an
index without changing this structure.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, BinaryIO

import numpy as np

from .errors import CorruptFileError, InvalidInputError
from .grid import MAX_CELLS, Grid
from .params import Params

__all__ = [
    "MAGIC",
    "VERSION",
    "Header",
    "pack",
    "unpack",
    "CompressedMap",
    "open",
    "atomic_write",
]

MAGIC = b"\x89DFTPC\r\n"
#: (major, minor). A reader refuses another major; a newer minor may add
#: sections and JSON fields, which an older reader skips.
VERSION = (1, 0)
_PREAMBLE = struct.Struct("<8sBBHI")  # magic, major, minor, flags, section count
_ENTRY = struct.Struct("<4sIQQI")  # tag, tile, offset, length, crc32
_CRC = struct.Struct("<I")
MAX_SECTIONS = 1024
#: Geometry section: origin x, y, projection-plane z, resolution, rows, cols,
#: angle, original point count, occupied cells, plane a, b, c.
_GEOM = struct.Struct("<ddddIIdQQddd")
#: Sections the reader needs; unknown tags are skipped.
REQUIRED = (b"GEOM", b"PARM", b"MASK", b"COEF")


@dataclass
class Header:
    """Everything about a compressed map except its coefficients and mask.

    Attributes
    ----------
    grid : Grid
    params : Params
        With ``step`` set to the quantizer step actually used (metres).
    point_count : int
        Points in the original cloud.
    cell_count : int
        Occupied cells (= points rebuilt).
    plane : tuple of float
        Detrending plane ``a + b*col + c*row`` in metres (zeros if none).
    crs : dict
        ``{"wkt": str | None, "las_vlrs": [...]}`` as read from the input.
    stats : dict
        Figures measured at compression time (metres, bytes).
    coef_count : int
        Coefficients stored.
    """

    grid: Grid
    params: Params
    point_count: int
    cell_count: int
    plane: tuple[float, float, float] = (0.0, 0.0, 0.0)
    crs: dict[str, Any] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)
    coef_count: int = 0


def pack(header: Header, mask_blob: bytes, coef_blob: bytes, resid_blob: bytes = b"") -> bytes:
    """Serialise a map into ``.dftpc`` bytes.

    ``resid_blob`` is the optional residual layer (max-error guarantee); it
    follows the coefficients, so a prefix of the file still decodes.
    """
    g = header.grid
    geom = _GEOM.pack(g.x0, g.y0, g.z0, g.resolution, g.rows, g.cols, g.angle,
                      header.point_count, header.cell_count, *header.plane)
    info = dict(header.stats, coef_count=header.coef_count)
    sections = [
        (b"GEOM", geom),
        (b"PARM", header.params.to_json().encode()),
        (b"CRS ", json.dumps(header.crs, sort_keys=True).encode()),
        (b"STAT", json.dumps(info, sort_keys=True).encode()),
        (b"MASK", mask_blob),
        (b"COEF", coef_blob),  # late, so a prefix of the file carries the low frequencies
    ] + ([(b"RESD", resid_blob)] if resid_blob else [])
    offset = _PREAMBLE.size + len(sections) * _ENTRY.size + _CRC.size
    table = []
    for tag, payload in sections:
        table.append(_ENTRY.pack(tag, 0, offset, len(payload), zlib.crc32(payload)))
        offset += len(payload)
    head = _PREAMBLE.pack(MAGIC, *VERSION, 0, len(sections)) + b"".join(table)
    return head + _CRC.pack(zlib.crc32(head)) + b"".join(p for _, p in sections)


def _sections(data: memoryview, *, allow_truncated_coef: bool) -> dict[bytes, memoryview]:
    if len(data) < _PREAMBLE.size + _CRC.size:
        raise CorruptFileError(f"not a .dftpc file: only {len(data)} bytes")
    magic, major, minor, _flags, count = _PREAMBLE.unpack_from(data, 0)
    if magic != MAGIC:
        raise CorruptFileError("not a .dftpc file (bad magic bytes)")
    if major != VERSION[0]:
        raise CorruptFileError(f"format version {major}.{minor} is not supported (this reader: {VERSION[0]}.x)")
    if count > MAX_SECTIONS:
        raise CorruptFileError(f"section table claims {count} sections")
    table_end = _PREAMBLE.size + count * _ENTRY.size
    if len(data) < table_end + _CRC.size:
        raise CorruptFileError("file is truncated inside its section table")
    (crc,) = _CRC.unpack_from(data, table_end)
    if zlib.crc32(data[:table_end]) != crc:
        raise CorruptFileError("section table fails its checksum")
    found: dict[bytes, memoryview] = {}
    for i in range(count):
        tag, tile, offset, length, crc = _ENTRY.unpack_from(data, _PREAMBLE.size + i * _ENTRY.size)
        name = tag.decode("latin-1").strip()
        if tile != 0 or tag in found:
            continue  # tiles beyond 0 belong to a later layout; duplicates keep the first
        if offset < table_end + _CRC.size:
            raise CorruptFileError(f"section {name} overlaps the header")
        end = offset + length
        if end > len(data):
            if tag == b"COEF" and allow_truncated_coef:
                found[tag] = data[offset:] if offset <= len(data) else data[0:0]
                continue
            if tag == b"RESD" and allow_truncated_coef:
                continue
            raise CorruptFileError(f"file is truncated: section {name} needs bytes up to {end}, file has {len(data)}")
        payload = data[offset:end]
        if zlib.crc32(payload) != crc:
            raise CorruptFileError(f"section {name} fails its checksum (damaged file)")
        found[tag] = payload
    for tag in REQUIRED:
        if tag not in found:
            raise CorruptFileError(f"section {tag.decode().strip()} is missing")
    return found


def _json(payload: memoryview, name: str) -> Any:
    try:
        return json.loads(bytes(payload).decode("utf-8")) if len(payload) else {}
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CorruptFileError(f"section {name} is not valid JSON: {exc}") from None


def unpack(data: bytes | memoryview, *, allow_truncated_coef: bool = False) -> tuple[Header, dict[bytes, memoryview]]:
    """Parse and check ``.dftpc`` bytes.

    Returns
    -------
    header : Header
    blobs : dict
        Payloads of the coded sections by tag (``b"MASK"``, ``b"COEF"``,
        ``b"RESD"`` when present), not yet decoded. With
        ``allow_truncated_coef`` a cut-short COEF is returned as far as it
        goes and a missing or cut RESD is left out.

    Raises
    ------
    CorruptFileError
        Bad magic, unsupported major version, a failed checksum, a size that
        does not fit the file, or an implausible geometry.
    """
    data = memoryview(data)
    found = _sections(data, allow_truncated_coef=allow_truncated_coef)
    geom = found[b"GEOM"]
    if len(geom) < _GEOM.size:
        raise CorruptFileError("geometry section is too short")
    (x0, y0, z0, res, rows, cols, angle, npoints, ncells, pa, pb, pc) = _GEOM.unpack_from(geom, 0)
    if not all(np.isfinite([x0, y0, z0, res, angle, pa, pb, pc])) or res <= 0:
        raise CorruptFileError("geometry section holds non-finite or non-positive values")
    if rows == 0 or cols == 0 or rows * cols > MAX_CELLS or ncells > rows * cols:
        raise CorruptFileError(f"implausible grid {rows} x {cols} with {ncells} occupied cells")
    try:
        params = Params.from_json(bytes(found[b"PARM"]).decode("utf-8"))
    except (InvalidInputError, TypeError, UnicodeDecodeError, ValueError) as exc:
        raise CorruptFileError(f"parameter section is invalid: {exc}") from None
    stats = _json(found[b"STAT"], "STAT") if b"STAT" in found else {}
    crs = _json(found[b"CRS "], "CRS") if b"CRS " in found else {}
    if not isinstance(stats, dict) or not isinstance(crs, dict):
        raise CorruptFileError("STAT and CRS sections must be JSON objects")
    coef_count = stats.get("coef_count")
    if not isinstance(coef_count, int) or not 0 <= coef_count <= rows * cols:
        raise CorruptFileError("coefficient count is missing or implausible")
    grid = Grid(x0=x0, y0=y0, z0=z0, resolution=res, rows=rows, cols=cols, angle=angle)
    header = Header(grid=grid, params=params, point_count=npoints, cell_count=ncells,
                    plane=(pa, pb, pc), crs=crs, stats=stats, coef_count=coef_count)
    return header, {tag: found[tag] for tag in (b"MASK", b"COEF", b"RESD") if tag in found}


class CompressedMap:
    """A ``.dftpc`` map opened for reading; use :func:`open`.

    The header is parsed and checked on opening; the mask and coefficients
    are decoded only when :meth:`read_points` or :meth:`read_dem` asks.
    """

    def __init__(self, data: bytes, name: str = "<bytes>", *, max_bytes: int | None = None):
        self.name = name
        self.size = len(data)
        if max_bytes is not None:
            if max_bytes <= 0:
                raise InvalidInputError(f"max_bytes must be positive, got {max_bytes}")
            data = data[:max_bytes]
        self._data = data
        self._partial = max_bytes is not None
        self.header, self._blobs = unpack(data, allow_truncated_coef=self._partial)

    # Context-manager protocol, like rasterio.open: nothing to release but
    # the buffer, yet `with dftpcc.open(...) as m:` reads naturally.
    def __enter__(self) -> "CompressedMap":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._data = b""

    @property
    def params(self) -> Params:
        return self.header.params

    @property
    def grid(self) -> Grid:
        return self.header.grid

    @property
    def crs(self) -> dict[str, Any]:
        return self.header.crs

    def read_dem(self, *, cutoff: float | None = None):
        """The rebuilt DEM (see :func:`dftpcc.codec.decode_dem`)."""
        from .codec import decode_dem

        return decode_dem(self.header, self._blobs, cutoff=cutoff, allow_partial=self._partial)

    def read_points(self, *, cutoff: float | None = None) -> np.ndarray:
        """The rebuilt cloud, shape (cells, 3), float64, original frame (metres)."""
        from .rebuild import dem_to_points

        return dem_to_points(self.read_dem(cutoff=cutoff))

    def info(self) -> dict[str, Any]:
        """Header, parameters and sizes as plain JSON-ready data."""
        h = self.header
        g = h.grid
        return {
            "file": self.name,
            "bytes": self.size,
            "format_version": f"{VERSION[0]}.{VERSION[1]}",
            "points_original": h.point_count,
            "points_rebuilt": h.cell_count,
            "bits_per_point": 8.0 * self.size / h.point_count if h.point_count else None,
            "grid": {"rows": g.rows, "cols": g.cols, "resolution_m": g.resolution,
                     "origin": [g.x0, g.y0], "z0_m": g.z0, "angle_rad": g.angle},
            "params": json.loads(h.params.to_json()),
            "plane": list(h.plane),
            "crs": (h.crs.get("wkt") or ("LAS GeoKeys" if h.crs.get("las_vlrs") else None)),
            "stats": h.stats,
        }


def open(source: str | os.PathLike[str] | BinaryIO | bytes, *, max_bytes: int | None = None) -> CompressedMap:  # noqa: A001
    """Open a compressed map from a path, a binary file object or bytes.

    Parameters
    ----------
    source : path, file-like or bytes
    max_bytes : int, optional
        Read only the first ``max_bytes`` bytes, as if the rest had not been
        received yet; the map decodes from the low frequencies it holds.

    Raises
    ------
    InvalidInputError
        The path does not exist or is not a file.
    CorruptFileError
        The content is not a valid ``.dftpc`` stream.
    """
    if isinstance(source, (bytes, bytearray, memoryview)):
        return CompressedMap(bytes(source), max_bytes=max_bytes)
    if hasattr(source, "read"):
        return CompressedMap(source.read(), getattr(source, "name", "<stream>"), max_bytes=max_bytes)
    path = Path(source)
    if not path.is_file():
        raise InvalidInputError(f"{path}: no such file")
    with path.open("rb") as fh:
        data = fh.read() if max_bytes is None else fh.read(max_bytes)
    return CompressedMap(data, str(path), max_bytes=max_bytes)


def atomic_write(path: str | os.PathLike[str], write: Any) -> None:
    """Create ``path`` through a temporary file in the same folder, renamed into place.

    ``write(fh_or_path)`` receives the temporary path. If it raises, or the
    process dies, the temporary file is removed (or left under a hidden name)
    and ``path`` keeps whatever it held before: never a partial file.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise InvalidInputError(f"{path}: folder {folder} does not exist")
    tmp = folder / f".{path.name}.{os.getpid()}.tmp{path.suffix}"
    try:
        write(tmp)
        with tmp.open("rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
