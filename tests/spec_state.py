"""An independent reader of the growing map's state file, written from docs/growing-maps.md alone.

It shares no code with dftpcc: the ZIP through :mod:`zipfile`, each ``.npy``
member's header parsed by hand from the NumPy format's own definition (magic
``\\x93NUMPY``, version, header length, a Python dict literal), the checksum,
the settings and the counting rules as the document states them. If dftpcc
and this reader disagree on a state dftpcc wrote, one of them departs from
the document.
"""

from __future__ import annotations

import ast
import hashlib
import json
import math
import re
import struct
import zipfile
from pathlib import Path

import numpy as np

#: The members in the checksum's order, with the dtype and the shape (in terms of n and T) the table gives.
MEMBERS = [("settings", None), ("tiles", "<i8"), ("sum", "<i8"), ("sumsq", "<f8"), ("count", "<i4"),
           ("figures", "<f8"), ("gridding", "<f8")]
SETTINGS_V2 = {"state_version", "resolution", "tile_size", "cutoff", "step", "origin", "crs", "point_count",
               "map_sha256", "previous_sha256", "update_sha256"}


class SpecError(Exception):
    """The file departs from the document."""


def parse_npy(raw: bytes) -> tuple[str, tuple[int, ...], bytes]:
    """(dtype descr, shape, data bytes) of one ``.npy`` file of format 1.0 or 2.0."""
    if raw[:6] != b"\x93NUMPY":
        raise SpecError("no .npy magic")
    major = raw[6]
    if major == 1:
        (length,), start = struct.unpack_from("<H", raw, 8), 10
    elif major == 2:
        (length,), start = struct.unpack_from("<I", raw, 8), 12
    else:
        raise SpecError(f".npy version {major}")
    header = ast.literal_eval(raw[start:start + length].decode("latin1"))
    if header["fortran_order"]:
        raise SpecError("Fortran order")
    return header["descr"], tuple(header["shape"]), raw[start + length:]


def read(path: str | Path) -> tuple[dict, dict[str, np.ndarray]]:
    """The settings and arrays of a version 2 state, every rule of the document checked."""
    with zipfile.ZipFile(path) as archive:
        infos = {info.filename: info for info in archive.infolist()}
        if set(infos) != {f"{name}.npy" for name, _ in MEMBERS} | {"checksum.npy"}:
            raise SpecError(f"members {sorted(infos)}")
        if any(info.compress_type != zipfile.ZIP_STORED for info in infos.values()):
            raise SpecError("a member is compressed")
        raw = {name[:-4]: archive.read(name) for name in infos}
    descr, shape, data = parse_npy(raw["checksum"])
    if descr != "|u1" or shape != (32,):
        raise SpecError("checksum member")
    if hashlib.sha256(b"".join(raw[name] for name, _ in MEMBERS)).digest() != data:
        raise SpecError("checksum")
    descr, shape, data = parse_npy(raw["settings"])
    if not re.fullmatch(r"<U\d+", descr) or shape != ():
        raise SpecError("settings member")
    text = data.decode("utf-32-le").rstrip("\0")
    settings = json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(SpecError(c)))
    if set(settings) != SETTINGS_V2 or settings["state_version"] != 2:
        raise SpecError("settings keys")
    size = settings["tile_size"]
    arrays: dict[str, np.ndarray] = {}
    for name, want in MEMBERS[1:]:
        descr, shape, data = parse_npy(raw[name])
        if descr != want:
            raise SpecError(f"{name} dtype {descr}")
        arrays[name] = np.frombuffer(data, dtype=descr).reshape(shape)
    n = arrays["tiles"].shape[0]
    expected = {"tiles": (n, 2), "sum": (n, size, size), "sumsq": (n, size, size), "count": (n, size, size),
                "figures": (n, 4), "gridding": (n,)}
    if n < 1 or any(arrays[k].shape != v for k, v in expected.items()):
        raise SpecError("shapes")
    keys = [tuple(t) for t in arrays["tiles"].tolist()]
    if keys != sorted(set(keys)):
        raise SpecError("tiles not ascending or held twice")
    count = arrays["count"]
    if (count < 0).any() or int(count.sum()) != settings["point_count"]:
        raise SpecError("counts")
    empty = count == 0
    if (arrays["sum"][empty] != 0).any() or (arrays["sumsq"][empty] != 0).any():
        raise SpecError("sums in empty cells")
    figures = arrays["figures"]
    if not all(math.isfinite(v) and v >= 0 for v in [*figures.ravel(), *arrays["gridding"], *arrays["sumsq"].ravel()]):
        raise SpecError("figures")
    if [int(c) for c in figures[:, 0]] != [int(np.count_nonzero(count[k])) for k in range(n)]:
        raise SpecError("occupied cells")
    return settings, arrays


def update_record(scans: list[tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]]) -> str:
    """The ``update_sha256`` of these scans, as *The update's record* defines it."""
    digest = hashlib.sha256()
    for points, pose in scans:
        digest.update(b"".join(struct.pack("<d", float(v)) for v in np.asarray(points, float).ravel()))
        if pose is None:
            digest.update(b"none")
        else:
            digest.update(b"".join(struct.pack("<d", float(v)) for v in [*np.ravel(pose[0]), *np.ravel(pose[1])]))
    return digest.hexdigest()
