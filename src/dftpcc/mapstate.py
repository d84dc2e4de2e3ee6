"""The state file of a growing map (``MAP.state``): written and read back, checked as a map is.

:mod:`dftpcc.mapbuilder` keeps its cells' sums here between updates. The
layout is docs/growing-maps.md, *The state file*: a ZIP of ``.npy`` members
(as ``numpy.savez`` writes it) with a SHA-256 of its own. Reading checks
everything a damaged or crafted state could get wrong before any of it is
used, and fails with one :class:`~dftpcc.errors.CorruptFileError` naming the
file; whether the state belongs to the map is :mod:`dftpcc.mapbuilder`'s part.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import re
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from .format.validate import MAX_TILES
from .errors import CorruptFileError
from .params import MAX_COORDINATE_M, TILE_SIZES

__all__ = ["STATE_VERSION", "FIGURES", "write_state", "read_state"]

#: Layout of the state file written; version 1 (no checksum, no update record) is read too.
STATE_VERSION = 2
#: Figures kept per coded tile: cells, squared error (m²), largest error (m), point-weighted squared error (m²).
FIGURES = 4
#: The arrays of a state, in the order the checksum takes them (after ``settings``), with their dtypes.
ARRAYS = {"tiles": "<i8", "sum": "<i8", "sumsq": "<f8", "count": "<i4", "figures": "<f8", "gridding": "<f8"}
_CHECKSUM = "checksum"
_SETTINGS = "settings"
#: The settings' keys by version, with what each must be.
_KEYS_V1 = ("state_version", "resolution", "tile_size", "cutoff", "step", "origin", "crs", "point_count",
            "map_sha256", "previous_sha256")
_KEYS = {1: _KEYS_V1, 2: (*_KEYS_V1, "update_sha256")}
_HEX64 = re.compile(r"[0-9a-f]{64}")
#: Micrometres per metre: the unit of the sums (grid.HEIGHT_QUANTUM_M).
_MICRO = 1e6


def write_state(path: str | os.PathLike[str], settings: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
    """Write a state file (version :data:`STATE_VERSION`) to ``path``: the settings, the arrays and their checksum.

    ``settings`` are written as given (with ``state_version``); ``arrays`` are
    the :data:`ARRAYS`, converted to their dtypes.
    """
    members = {_SETTINGS: np.array(json.dumps({"state_version": STATE_VERSION, **settings}, allow_nan=False))}
    members.update({name: np.ascontiguousarray(arrays[name], dtype=dtype) for name, dtype in ARRAYS.items()})
    digest = hashlib.sha256()
    for value in members.values():
        digest.update(_npy(value))
    members[_CHECKSUM] = np.frombuffer(digest.digest(), dtype=np.uint8)
    with open(path, "wb") as fh:  # a file object: np.savez would add .npz to a name
        np.savez(fh, **members)  # type: ignore[arg-type]


def _npy(value: np.ndarray) -> bytes:
    """The ``.npy`` file np.savez stores for ``value``."""
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.asanyarray(value), allow_pickle=False)
    return buf.getvalue()


def read_state(path: str | os.PathLike[str]) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The arrays and settings of a state file, every byte checked (docs/growing-maps.md, *Checks on reading*).

    Raises
    ------
    CorruptFileError
        A damaged, cut, crafted or unreadable state, or one of another
        version: one line naming ``path``.
    """
    path = Path(path)
    members = _members(path)
    version = 2 if _CHECKSUM in members else 1
    if version == 2:
        stated = _array(path, _CHECKSUM, members[_CHECKSUM], "|u1")
        if stated.shape != (32,):
            raise CorruptFileError(f"{path}: the map state's checksum is not 32 bytes")
        digest = hashlib.sha256()
        for name in (_SETTINGS, *ARRAYS):
            digest.update(members[name])
        if digest.digest() != stated.tobytes():
            raise CorruptFileError(f"{path}: the map state fails its checksum (damaged or edited)")
    settings = _settings(path, _array(path, _SETTINGS, members[_SETTINGS], None), version)
    arrays = {name: _array(path, name, members[name], dtype) for name, dtype in ARRAYS.items()}
    _check_arrays(path, arrays, settings)
    return arrays, settings


def _members(path: Path) -> dict[str, bytes]:
    """The members' bytes, by name without ``.npy``: only those of a state, stored, within the file's size."""
    try:
        size = path.stat().st_size
        with zipfile.ZipFile(path) as archive:
            infos = archive.infolist()
            names = [info.filename for info in infos]
            want = {f"{name}.npy" for name in (_SETTINGS, *ARRAYS)}
            if len(set(names)) != len(names) or not want <= set(names) <= want | {f"{_CHECKSUM}.npy"}:
                raise CorruptFileError(f"{path}: not a map state (its members are {', '.join(names[:8]) or 'none'})")
            for info in infos:  # before reading: a crafted size must not make a few bytes cost gigabytes
                if info.compress_type != zipfile.ZIP_STORED or info.file_size != info.compress_size \
                        or info.file_size > size or info.flag_bits & 0x1:
                    raise CorruptFileError(f"{path}: map state member {info.filename} is compressed, encrypted "
                                           f"or larger than the file")
            if sum(info.file_size for info in infos) > size:
                raise CorruptFileError(f"{path}: the map state's members are larger than the file")
            return {info.filename[:-len(".npy")]: archive.read(info) for info in infos}
    except CorruptFileError:
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, ValueError, KeyError, NotImplementedError,
            RuntimeError, UnicodeDecodeError, OverflowError) as exc:
        raise CorruptFileError(f"{path}: not a readable map state ({' '.join(str(exc).split()) or type(exc).__name__}; "
                               f"damaged or cut short?)") from None


def _array(path: Path, name: str, data: bytes, dtype: str | None) -> np.ndarray:
    """One ``.npy`` member: its header checked against what its bytes hold before anything is allocated."""
    fh = io.BytesIO(data)
    try:
        major, _minor = np.lib.format.read_magic(fh)
        if major == 1:
            shape, fortran, kind = np.lib.format.read_array_header_1_0(fh)
        elif major == 2:
            shape, fortran, kind = np.lib.format.read_array_header_2_0(fh)
        else:
            raise ValueError(f".npy version {major}")
    except Exception as exc:  # noqa: BLE001 - numpy's header parser raises tokenize, syntax, value errors ...
        raise CorruptFileError(f"{path}: map state member {name} is no array ({type(exc).__name__}: "
                               f"{' '.join(str(exc).split())[:200]})") from None
    ok = (kind.str == dtype) if dtype is not None else (kind.kind == "U" and kind.byteorder in "<=|" and shape == ())
    if not ok or fortran or kind.hasobject:
        raise CorruptFileError(f"{path}: map state member {name} holds {kind.str}{' in Fortran order' * fortran}, "
                               f"not {dtype or 'text'}")
    count = math.prod(shape)
    if count * kind.itemsize != len(data) - fh.tell():
        raise CorruptFileError(f"{path}: map state member {name} states shape {shape} but holds "
                               f"{len(data) - fh.tell():,} bytes")
    return np.frombuffer(data, dtype=kind, count=count, offset=fh.tell()).reshape(shape)


def _refuse_constant(name: str) -> None:
    raise ValueError(f"{name} is not a number")


def _settings(path: Path, text: np.ndarray, version: int) -> dict[str, Any]:
    """The settings, every key of its type and within its range."""
    try:
        settings = json.loads(str(text), parse_constant=_refuse_constant)
    except (ValueError, RecursionError) as exc:
        raise CorruptFileError(f"{path}: the map state's settings are not JSON ({exc})") from None
    if not isinstance(settings, dict):
        raise CorruptFileError(f"{path}: the map state's settings are not a JSON object")
    found = settings.get("state_version")
    if not isinstance(found, int) or isinstance(found, bool):
        found = repr(found)[:40]
    if found == STATE_VERSION and version == 1:
        raise CorruptFileError(f"{path}: the map state (version {STATE_VERSION}) lacks its checksum")
    if found != version:
        raise CorruptFileError(f"{path}: a map state of another version ({found!r}; this dftpcc reads versions "
                               f"1 and {STATE_VERSION}, and only version 2 has a checksum)")
    keys = _KEYS[version]
    if set(settings) != set(keys):
        odd = sorted(set(settings) ^ set(keys))
        raise CorruptFileError(f"{path}: the map state's settings lack or add {', '.join(map(repr, odd[:4]))}")

    def number(value: Any) -> bool:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)

    def integer(value: Any) -> bool:
        return isinstance(value, int) and not isinstance(value, bool)

    def digest(value: Any, null: bool) -> bool:
        return (null and value is None) or (isinstance(value, str) and _HEX64.fullmatch(value) is not None)

    crs = settings["crs"]
    checks = {
        "resolution": number(settings["resolution"]) and 0 < settings["resolution"] <= MAX_COORDINATE_M,
        "tile_size": integer(settings["tile_size"]) and TILE_SIZES[0] <= settings["tile_size"] <= TILE_SIZES[1],
        "cutoff": number(settings["cutoff"]) and 0 <= settings["cutoff"] < 1,
        "step": number(settings["step"]) and 0 < settings["step"] <= MAX_COORDINATE_M,
        "origin": isinstance(settings["origin"], list) and len(settings["origin"]) == 3
        and all(number(v) and abs(v) <= MAX_COORDINATE_M for v in settings["origin"]),
        "crs": isinstance(crs, dict) and all(isinstance(k, str) for k in crs)
        and isinstance(crs.get("wkt", ""), str) and isinstance(crs.get("las_vlrs", []), list),
        "point_count": integer(settings["point_count"]) and 0 < settings["point_count"] < 2**63,
        "map_sha256": digest(settings["map_sha256"], False),
        "previous_sha256": digest(settings["previous_sha256"], True),
        "update_sha256": digest(settings.get("update_sha256"), True),
    }
    for key, ok in checks.items():
        if not ok:
            raise CorruptFileError(f"{path}: the map state's {key} is {_short(settings.get(key))}, out of its "
                                   f"type or range")
    return settings


def _short(value: Any) -> str:
    text = json.dumps(value) if not isinstance(value, float) else repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _check_arrays(path: Path, arrays: dict[str, np.ndarray], settings: dict[str, Any]) -> None:
    """Shapes, then values: tiles on the map, counts adding up, sums of empty cells 0, figures finite."""
    size = settings["tile_size"]
    tiles = arrays["tiles"]
    n = tiles.shape[0] if tiles.ndim == 2 else -1
    shapes = {"tiles": (n, 2), "sum": (n, size, size), "sumsq": (n, size, size), "count": (n, size, size),
              "figures": (n, FIGURES), "gridding": (n,)}
    for name, shape in shapes.items():
        if arrays[name].shape != shape:
            raise CorruptFileError(f"{path}: map state array {name} has shape {arrays[name].shape}, expected {shape}")
    if n < 1:
        raise CorruptFileError(f"{path}: the map state holds no tile")
    # Tiles within the coordinates a map holds, and a map of them (one empty tile around) within its tile count.
    span = settings["tile_size"] * settings["resolution"]
    reach = 2 * MAX_COORDINATE_M / span + 1  # float: a subnormal resolution gives inf, which no index exceeds
    far = max(-int(tiles.min()), int(tiles.max()))  # Python integers: no overflow at -2**63
    if far > reach:
        raise CorruptFileError(f"{path}: the map state holds a tile at lattice index {far:,}, beyond "
                               f"±{MAX_COORDINATE_M:g} m at {span:g} m per tile")
    extent = [int(tiles[:, a].max()) - int(tiles[:, a].min()) + 3 for a in (0, 1)]
    if extent[0] * extent[1] > MAX_TILES:
        raise CorruptFileError(f"{path}: the map state's tiles span {extent[0]:,} x {extent[1]:,} tiles, more than "
                               f"the {MAX_TILES:,} a map holds")
    order = np.lexsort((tiles[:, 1], tiles[:, 0]))
    keys = tiles[order]
    if (order != np.arange(n)).any() or (np.diff(keys, axis=0) == 0).all(axis=1).any():
        raise CorruptFileError(f"{path}: the map state's tiles are out of order or held twice")
    count, sums, sumsq = arrays["count"], arrays["sum"], arrays["sumsq"]
    total = int(count.sum(dtype=np.int64))
    if total != settings["point_count"]:
        raise CorruptFileError(f"{path}: the map state's cells hold {total:,} points, its point_count says "
                               f"{settings['point_count']:,}")
    figures, gridding = arrays["figures"], arrays["gridding"]
    if not (_finite_and_not_negative(figures) and _finite_and_not_negative(gridding)):
        raise CorruptFileError(f"{path}: the map state has figures that are not finite or negative")
    # Tile by tile: the temporaries of a whole state's checks would cost as much again as the state.
    for k in range(n):
        cells, cell_sums, cell_squares = count[k], sums[k], sumsq[k]
        if int(cells.min()) < 0:
            raise CorruptFileError(f"{path}: the map state holds negative counts")
        empty = cells == 0
        if cell_sums[empty].any() or cell_squares[empty].any():
            raise CorruptFileError(f"{path}: the map state has sums in empty cells")
        if not _finite_and_not_negative(cell_squares):
            raise CorruptFileError(f"{path}: the map state has sums of squares that are not finite or negative")
        # A cell's mean height above z0, like every height of a map, within ±MAX_COORDINATE_M of it.
        if (np.abs(cell_sums.astype(np.float64)) > cells * (2 * MAX_COORDINATE_M * _MICRO)).any():
            raise CorruptFileError(f"{path}: the map state has cell heights beyond ±{MAX_COORDINATE_M:g} m")
        occupied = cells.size - int(np.count_nonzero(empty))
        if occupied == 0 or figures[k, 0] != occupied:
            raise CorruptFileError(f"{path}: the map state's tile figures do not count the tiles' occupied cells "
                                   f"(or a tile is empty)")


def _finite_and_not_negative(values: np.ndarray) -> bool:
    # Reductions, no temporaries: a NaN makes min() NaN, which is not >= 0.
    return values.size == 0 or (float(values.min()) >= 0 and math.isfinite(float(values.max())))
