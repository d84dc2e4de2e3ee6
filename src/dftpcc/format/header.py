"""A map's header (docs/format.md, *Sections*): GEOM, PARM, CRS and STAT, written by
:func:`header_sections` and read back by :func:`parse_header`, the one place both layouts parse it.
"""

from __future__ import annotations

import base64
import dataclasses
import json
import math
import struct
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from ..dem import Grid
from ..errors import CorruptFileError, InvalidInputError
from ..params import Params
from .sections import F32, VERSION, TooWide, f32_up, json_text, leb128, legacy_order, pack_json, read_json, read_leb128_at
from .validate import (MAX_CELLS, as_writer, check_coef_count, check_crs, check_geometry, check_params,
                       check_points, check_row_spacing, check_grid_fields)

if TYPE_CHECKING:
    from .index import TileIndex

#: Geometry section: origin x, y, projection-plane z, resolution, rows, cols,
#: angle, original point count, occupied cells, plane a, b, c; then the row
#: spacing (0 for square cells).
GEOM = struct.Struct("<ddddIIdQQddd")
GEOM_Y = struct.Struct("<d")


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
        Coefficients stored (of a tiled map: its base layer's).
    tiles : TileIndex, optional
        The tile index of a tiled (version 1.1) map.
    notes : dict
        PARM fields :class:`Params` does not hold, kept as read and written back: a newer writer's,
        or what a tool on top of the codec records (the relocalization experiment's
        ``target_reloc``, metres).
    minor : int
        The file's minor version (what the writer writes for a new header): it says which
        coefficient order the file follows (:attr:`legacy_order`).
    """

    grid: Grid
    params: Params
    point_count: int
    cell_count: int
    plane: tuple[float, float, float] = (0.0, 0.0, 0.0)
    crs: dict[str, Any] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)
    coef_count: int = 0
    tiles: "TileIndex | None" = None
    notes: dict[str, Any] = field(default_factory=dict)
    minor: int = VERSION[1]

    @property
    def legacy_order(self) -> bool:
        """Whether the coefficients follow the legacy ``hypot`` order (a 1.0 or 1.1 file)."""
        return legacy_order(self.minor)

    @property
    def growing(self) -> bool:
        """Whether this is a growing map's header (docs/growing-maps.md): :meth:`why_not_growing` is None."""
        return self.why_not_growing() is None

    def why_not_growing(self) -> str | None:
        """Why this is no growing map's header, or None when it is one: a growing map is tiled, with no
        base layer, a zero plane and the tiles' own masks (no map mask: a tile's sections are all a scan
        may rewrite)."""
        if self.tiles is None:
            return "it is not tiled"
        if self.tiles.base_cycles:
            return f"its base layer reaches {self.tiles.base_cycles} cycle(s) per tile"
        if any(self.plane):
            return "it has a detrending plane"
        if self.tiles.map_mask:
            return "its mask is the whole map's"
        return None


#: Parameter values a version-1 file leaves out. Frozen here, apart from the
#: library's defaults, so that changing a default later cannot change what
#: an existing file means.
V1_PARAM_DEFAULTS: dict[str, Any] = {
    "cutoff": 0.8, "profile": "compact", "aggregate": "mean", "frame": "axis", "transform": "dct",
    "detrend": "plane", "fill": "consistent", "storage": "quantized", "step": 0.0, "deadzone": 0.1,
    "coder": "ans", "mask": "exact", "target_rmse": 0.0, "target_max_error": 0.0, "target_bpp": 0.0,
    "tile_size": 0,
}
#: Statistics the reader derives from the section table instead of storing them.
DERIVED_STATS = {"mask_bytes": b"MASK", "coef_bytes": b"COEF", "residual_bytes": b"RESD"}
#: Statistics left out when zero.
_OPTIONAL_STATS = ("cells_interpolated",)


def params_for_file(params: Params) -> dict[str, Any]:
    full = json.loads(params.to_json())
    if full.get("tile_size") == "auto":  # a file states what it is: 'auto' that did not tile is 0
        full["tile_size"] = 0
    # The resolution is GEOM's cell width; a reader takes it from there.
    return {k: v for k, v in full.items()
            if k != "resolution" and (k not in V1_PARAM_DEFAULTS or V1_PARAM_DEFAULTS[k] != v)}


def params_from_file(text: str, resolution: float) -> tuple[Params, dict[str, Any]]:
    """The parameters a PARM section states, and its fields :class:`Params` does not hold (notes)."""
    stored = json.loads(text)
    if not isinstance(stored, dict):
        raise InvalidInputError("parameters must be a JSON object")
    held = {f.name for f in dataclasses.fields(Params)}
    notes = {k: v for k, v in stored.items() if k not in held}
    return Params.from_json(json.dumps(V1_PARAM_DEFAULTS | {"resolution": resolution} | stored)), notes


#: Binary STAT: a marker byte, then records of a u8 field id and its value:
#: ids below 128 hold a float32 (errors rounded up to the next float32, so a
#: stated error stays an upper bound), ids from 128 an unsigned LEB128 integer.
#: A reader skips ids it does not know. The first byte is the coding: binary
#: is the only one (a reader refuses another).
STAT_BINARY = 0x01
STAT_FIELDS: dict[int, str] = {
    0: "dem_rmse_m", 1: "dem_max_error_m", 2: "gridding_rmse_m", 3: "vertical_rmse_m",
    4: "unrepresented_fraction", 5: "unrepresented_rmse_m", 6: "reloc_success_fraction",
    7: "target_rmse_m", 8: "source_nodata", 128: "coef_count", 129: "cells_interpolated", 130: "source_dtype",
}
_STAT_IDS = {name: i for i, name in STAT_FIELDS.items()}


def pack_stats(stats: dict[str, Any]) -> bytes:
    out = bytearray([STAT_BINARY])
    for name, value in sorted(stats.items(), key=lambda kv: _STAT_IDS.get(kv[0], 256)):
        i = _STAT_IDS.get(name)
        if i is None:
            raise ValueError(f"statistic {name!r} has no STAT field id")
        out.append(i)
        if i >= 128:
            out += leb128(int(value))
            continue
        packed = f32_up(float(value))
        if not math.isfinite(F32.unpack(packed)[0]):  # the reader refuses NaN and infinities
            raise InvalidInputError(f"cannot write this map: statistic {name} = {value!r} is not a finite float32")
        out += packed
    return bytes(out)


def unpack_stats(payload: memoryview) -> dict[str, Any]:
    raw = bytes(payload)
    if not raw:
        raise CorruptFileError("section STAT is empty")
    if raw[0] != STAT_BINARY:
        raise CorruptFileError(f"section STAT has unknown coding {raw[0]:#04x} (binary STAT starts with "
                               f"{STAT_BINARY:#04x})")
    stats: dict[str, Any] = {}
    pos = 1
    while pos < len(raw):
        i = raw[pos]
        pos += 1
        if i < 128:
            if pos + F32.size > len(raw):
                raise CorruptFileError("section STAT is truncated")
            (value,) = F32.unpack_from(raw, pos)
            pos += F32.size
            if not math.isfinite(value):
                raise CorruptFileError(f"section STAT: field {i} is not finite")
        else:
            try:
                value, pos = read_leb128_at(memoryview(raw), pos)
            except TooWide:
                raise CorruptFileError("section STAT holds an integer wider than 64 bits") from None
            if value is None:
                raise CorruptFileError("section STAT is truncated")
        if i in STAT_FIELDS:
            stats[STAT_FIELDS[i]] = value
    return stats


def crs_for_file(crs: dict[str, Any]) -> dict[str, Any]:
    """The CRS as stored: LAS records that are text travel as text, so the WKT
    (often present twice, as ``wkt`` and as its LAS record) compresses to once."""
    out = dict(crs)
    vlrs = []
    for vlr in crs.get("las_vlrs", []):
        data = base64.b64decode(vlr["data"])
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError:
            vlrs.append(vlr)
            continue
        if text.encode("utf-8") == data:
            vlrs.append({k: v for k, v in vlr.items() if k != "data"} | {"text": text})
        else:
            vlrs.append(vlr)
    if vlrs:
        out["las_vlrs"] = vlrs
    return out


def crs_from_file(crs: Any) -> Any:
    """Inverse of :func:`crs_for_file`: every LAS record back to base64 ``data``."""
    if not isinstance(crs, dict) or not isinstance(crs.get("las_vlrs"), list):
        return crs
    vlrs = []
    for vlr in crs["las_vlrs"]:
        if isinstance(vlr, dict) and "data" not in vlr and isinstance(vlr.get("text"), str):
            data = base64.b64encode(vlr["text"].encode("utf-8")).decode("ascii")
            vlr = {k: v for k, v in vlr.items() if k != "text"} | {"data": data}
        vlrs.append(vlr)
    return dict(crs, las_vlrs=vlrs)


def grid_and_crs(fields: tuple, geom: memoryview, crs_payload: memoryview | None) -> tuple[Grid, dict[str, Any]]:
    """The grid of checked GEOM ``fields`` (and its optional row spacing), and the checked CRS."""
    crs = crs_from_file(read_json(crs_payload, "CRS")) if crs_payload is not None else {}
    check_crs(crs)
    (x0, y0, z0, res, rows, cols, angle, *_rest) = fields
    res_y = GEOM_Y.unpack_from(geom, GEOM.size)[0] if len(geom) >= GEOM.size + GEOM_Y.size else 0.0
    check_row_spacing(res_y, rows)
    return Grid(x0=x0, y0=y0, z0=z0, resolution=res, rows=rows, cols=cols, angle=angle,
                resolution_y=res_y or None), crs


def parse_params(payload: memoryview, res: float) -> tuple[Params, dict[str, Any]]:
    """The PARM section, checked (a file states its cutoff, resolution and step), and its notes."""
    try:
        params, notes = params_from_file(json_text(payload, "PARM"), res)
    except CorruptFileError as exc:
        raise CorruptFileError(f"parameter section is invalid: {exc}") from None
    except (InvalidInputError, TypeError, UnicodeDecodeError, ValueError, OverflowError) as exc:
        raise CorruptFileError(f"parameter section is invalid: {exc}") from None
    except RecursionError:
        raise CorruptFileError("parameter section nests JSON too deeply") from None
    check_params(params, res)
    return params, notes


def header_sections(header: Header) -> list[tuple[bytes, bytes]]:
    """GEOM, PARM, CRS and STAT: what every file holds at tile 0."""
    g = header.grid
    geom = GEOM.pack(g.x0, g.y0, g.z0, g.resolution, g.rows, g.cols, g.angle,
                      header.point_count, header.cell_count, *header.plane)
    if g.resolution_y:  # square cells leave the row spacing out
        geom += GEOM_Y.pack(g.resolution_y)
    info = dict(header.stats, coef_count=header.coef_count)
    return [
        (b"GEOM", geom),
        (b"PARM", pack_json(header.notes | params_for_file(header.params), "PARM")),
    ] + ([(b"CRS ", pack_json(crs_for_file(header.crs), "CRS"))] if header.crs else []) + [
        (b"STAT", pack_stats({k: v for k, v in info.items()
                               if k not in DERIVED_STATS and not (k in _OPTIONAL_STATS and v == 0)})),
    ]


def parse_header(payloads: dict[bytes, memoryview], *, budget: int, file_size: int, limit: int = MAX_CELLS,
                 tiled: bool = False) -> Header:
    """The header of a file from its checked tile-0 payloads (GEOM, PARM, STAT, CRS), checked in the
    reader's order; ``budget`` and ``limit``: the most cells its grid may have (format-validation.md).

    A tiled map's caller adds its tile index; an untiled (1.0) map may leave STAT out.
    """
    geom = payloads[b"GEOM"]
    if len(geom) < GEOM.size:
        raise CorruptFileError("geometry section is too short")
    fields = GEOM.unpack_from(geom, 0)
    check_geometry(fields, budget, file_size, limit=limit)
    (_x0, _y0, _z0, res, rows, cols, _angle, npoints, ncells, pa, pb, pc) = fields
    params, notes = parse_params(payloads[b"PARM"], res)
    if params.tile_size and not tiled:
        raise CorruptFileError(f"parameters state tiles of {params.tile_size} cells in an untiled (1.0) map")
    check_points(params, npoints, ncells)
    stats = unpack_stats(payloads[b"STAT"]) if b"STAT" in payloads else {}
    coef_count = stats.get("coef_count")
    check_coef_count(coef_count, rows * cols)
    grid, crs = grid_and_crs(fields, geom, payloads.get(b"CRS "))
    return Header(grid=grid, params=params, point_count=npoints, cell_count=ncells, plane=(pa, pb, pc),
                  crs=crs, stats=stats, coef_count=coef_count, notes=notes)


def check_header(header: Header) -> None:
    """Refuse a header :func:`unpack` would refuse, so no file is written that dftpcc cannot read.

    The reader's checks on geometry, parameters, coefficient count and CRS;
    :func:`pack` runs them first, and also refuses statistics or JSON sections
    the reader could not take.

    Raises
    ------
    InvalidInputError
        "cannot write this map: <what the reader would say>".
    """
    g = header.grid
    with as_writer():
        if header.tiles is None and header.params.tile_size not in (0, "auto"):
            raise CorruptFileError(f"an untiled map states tiles of {header.params.tile_size} cells")
        check_grid_fields(g, header.point_count, header.cell_count, header.params, header.plane, header.tiles is not None)
        check_params(header.params, g.resolution)
        check_coef_count(header.coef_count, g.size)
        check_crs(header.crs)
