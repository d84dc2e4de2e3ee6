"""Every check a reader makes of a header (docs/format-validation.md lists them), shared by the
writer, which runs them on what it is about to state so that nothing is written dftpcc cannot read.
"""

from __future__ import annotations

import base64
import binascii
import math
from typing import Any

from ..dem import Grid
from ..errors import CorruptFileError, InvalidInputError, ResourceLimitError
from ..limits import DECODE_BYTES_PER_CELL, MAX_CELLS, cell_budget
from ..params import MAX_COORDINATE_M, MIN_RESOLUTION_M, Params
from .sections import U64_LIMIT

#: Tiles of a 1.1 file, at most, and at most this many per byte of the file.
MAX_TILES = 1 << 20
TILES_PER_FILE_BYTE = 64
#: rows x cols of a tiled map, at most (MAX_CELLS applies to each tile).
MAX_TILED_CELLS = 1 << 36

#: MAX_COORDINATE_M (from params, which checks steps and targets against it):
#: the largest coordinate, height, grid extent or quantizer step a header may state.
#: Largest plane term ``|a| + |b|*cols + |c|*rows`` a header may state, metres.
MAX_PLANE_M = 1e18
#: LAS variable-length records: 16-bit record id and length, 32-byte description.
VLR_MAX_ID = 0xFFFF
VLR_MAX_BYTES = 0xFFFF
VLR_DESCRIPTION = 32


def is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def is_count(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def check_grid(grid: Grid, *, point_count: int, cell_count: int, params: Params,
               plane: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
    """Refuse, before any work, a map whose geometry the reader would refuse.

    The reader's checks on GEOM (origin, extent, plane, cells, points,
    row spacing; not the decoding budget, which a writer only warns about),
    run on what the writer is about to state.

    Raises
    ------
    InvalidInputError
        "cannot write this map: <what the reader would say>".
    """
    with as_writer():
        check_grid_fields(grid, point_count, cell_count, params, plane)


def check_grid_fields(grid: Grid, point_count: int, cell_count: int, params: Params,
                plane: tuple[float, float, float], tiled: bool = False) -> None:
    if not (is_count(point_count) and point_count < U64_LIMIT):
        raise CorruptFileError(f"point count {point_count!r} does not fit the header's 64 bits")
    fields = (grid.x0, grid.y0, grid.z0, grid.resolution, grid.rows, grid.cols, grid.angle,
              point_count, cell_count, *plane)
    # The budget is the reader's default, not a limit of the format: a writer warns (see pack).
    # A tiled map is read tile by tile: its limit is the reader's (unpack_tiled), not the whole-grid budget.
    limit = MAX_TILED_CELLS if tiled else MAX_CELLS
    check_geometry(fields, limit, 0, limit=limit)
    check_points(params, point_count, cell_count)
    check_row_spacing(grid.resolution_y or 0.0, grid.rows)


class as_writer:
    """Turn the reader's refusal (CorruptFileError) into the writer's (InvalidInputError)."""

    def __enter__(self) -> None:
        return None

    def __exit__(self, kind: type | None, exc: BaseException | None, _tb: Any) -> None:
        if isinstance(exc, CorruptFileError):
            raise InvalidInputError(f"cannot write this map: a reader would refuse the file: {exc}") from None


def check_geometry(geom: tuple, budget: int, file_size: int, *, limit: int = MAX_CELLS) -> None:
    """Geometry fields against sane limits and the decoding budget (see the constants above);
    ``limit``: the format's largest grid (:data:`MAX_TILED_CELLS` for a tiled map)."""
    (x0, y0, z0, res, rows, cols, angle, npoints, ncells, pa, pb, pc) = geom
    if not all(math.isfinite(v) for v in (x0, y0, z0, res, angle, pa, pb, pc)) or res <= 0:
        raise CorruptFileError("geometry section holds non-finite or non-positive values")
    if max(abs(x0), abs(y0), abs(z0)) > MAX_COORDINATE_M:
        raise CorruptFileError(f"geometry section states an origin beyond {MAX_COORDINATE_M:g} m")
    if res < MIN_RESOLUTION_M:
        raise CorruptFileError(f"geometry section states a cell size of {res!r} m, below {MIN_RESOLUTION_M:g} m")
    if rows == 0 or cols == 0:
        raise CorruptFileError(f"implausible grid {rows} x {cols}")
    if res * max(rows, cols) > MAX_COORDINATE_M:
        raise CorruptFileError(f"grid {rows} x {cols} of {res:g} m cells extends beyond {MAX_COORDINATE_M:g} m")
    if abs(pa) + abs(pb) * cols + abs(pc) * rows > MAX_PLANE_M:
        raise CorruptFileError(f"detrending plane ({pa:g}, {pb:g}, {pc:g}) leaves the map by more than {MAX_PLANE_M:g} m")
    cells = rows * cols
    if cells > budget:
        asks = (f"refusing to decode: the header asks for a {rows:,} x {cols:,} grid ({cells:,} cells, about "
                f"{cells * DECODE_BYTES_PER_CELL / 1e9:,.1f} GB to decode)")
        if cells > limit:
            raise ResourceLimitError(f"{asks}, more than the {limit:,}-cell limit of the format")
        raise ResourceLimitError(
            f"{asks}, more than the {budget:,} cells allowed for a {file_size:,}-byte file; if you trust "
            f"this file, open it with max_cells={cells} (command line: --max-cells {cells})")
    if not 1 <= ncells <= cells:
        raise CorruptFileError(f"implausible grid {rows} x {cols} with {ncells} occupied cells")


def check_params(params: Params, res: float) -> None:
    # Params may leave these open for the encoder to choose ('auto', None); a file states them.
    if params.cutoff is None:
        raise CorruptFileError("parameter section states no cutoff")
    if not is_number(params.resolution) or not math.isclose(params.resolution, res, rel_tol=1e-9):
        raise CorruptFileError(f"parameter resolution {params.resolution!r} m disagrees with the grid's {res!r} m")
    if params.storage == "quantized" and not 0.0 < params.step <= MAX_COORDINATE_M:
        raise CorruptFileError(f"quantizer step {params.step!r} m is not in (0, {MAX_COORDINATE_M:g}]")


def check_points(params: Params, npoints: int, ncells: int) -> None:
    # Every rebuilt cell of an exact mask held a point; a footprint mask also
    # rebuilds enclosed empty cells, so it may have more cells than points.
    if params.mask == "exact" and npoints < ncells:
        raise CorruptFileError(f"header states {npoints} original points for {ncells} occupied cells")


def check_coef_count(coef_count: Any, cells: int) -> None:
    if not is_count(coef_count) or coef_count > cells:
        raise CorruptFileError("coefficient count is missing or implausible")


def check_row_spacing(res_y: float, rows: int) -> None:
    """The optional GEOM row spacing (0 for square cells)."""
    if not (math.isfinite(res_y) and (res_y == 0 or res_y >= MIN_RESOLUTION_M)):
        raise CorruptFileError(f"geometry holds an invalid row spacing {res_y!r} m (a cell size of 0, square, "
                               f"or {MIN_RESOLUTION_M:g} m or more)")
    if res_y * rows > MAX_COORDINATE_M:
        raise CorruptFileError(f"grid {rows} rows of {res_y:g} m extend beyond {MAX_COORDINATE_M:g} m")


def check_crs(crs: Any) -> None:
    """The CRS is written back into LAS, PLY and GeoTIFF outputs, so its shape must be right."""
    if not isinstance(crs, dict):
        raise CorruptFileError("section CRS must be a JSON object")
    wkt = crs.get("wkt")
    if wkt is not None and not isinstance(wkt, str):
        raise CorruptFileError("section CRS: wkt must be a string")
    vlrs = crs.get("las_vlrs", [])
    if not isinstance(vlrs, list):
        raise CorruptFileError("section CRS: las_vlrs must be a list")
    for i, vlr in enumerate(vlrs):
        ok = (isinstance(vlr, dict)
              and isinstance(vlr.get("record_id"), int) and not isinstance(vlr.get("record_id"), bool)
              and 0 <= vlr["record_id"] <= VLR_MAX_ID
              and isinstance(vlr.get("description", ""), str)
              and len(vlr.get("description", "").encode("utf-8")) <= VLR_DESCRIPTION
              and isinstance(vlr.get("data"), str))
        if ok:
            try:
                ok = len(base64.b64decode(vlr["data"], validate=True)) <= VLR_MAX_BYTES
            except (binascii.Error, ValueError):
                ok = False
        if not ok:
            raise CorruptFileError(f"section CRS: LAS record {i} is malformed")


def check_tiled_params(params: Params, grid: Grid, size: Any) -> None:
    if not (isinstance(size, int) and 16 <= size <= 65536):
        raise CorruptFileError(f"tile size {size!r} is not in [16, 65536]")
    if params.tile_size != size:
        raise CorruptFileError(f"the tile index says tiles of {size} cells, the parameters {params.tile_size!r}")
    if max(grid.rows, grid.cols) <= size:
        raise CorruptFileError(f"a {grid.rows} x {grid.cols} grid fits one tile of {size} cells: it is no tiled map")
    wrong = {k: v for k, v in (("transform", params.transform), ("storage", params.storage),
                               ("detrend", params.detrend), ("mask", params.mask))
             if v != {"transform": "dct", "storage": "quantized", "detrend": "plane", "mask": "exact"}[k]}
    if wrong:
        raise CorruptFileError(f"a tiled map is coded with the DCT, quantized, a plane and an exact mask, not "
                               f"{', '.join(f'{k}={v}' for k, v in wrong.items())}")
    count = -(-grid.rows // size) * -(-grid.cols // size)
    if count > MAX_TILES:
        raise CorruptFileError(f"{count:,} tiles of {size} cells, more than the {MAX_TILES:,} a file may hold")


def cells_allowed(file_size: int, max_cells: int | None) -> int:
    """The largest grid a file of ``file_size`` bytes may ask for: ``max_cells`` if given
    (never over :data:`~dftpcc.limits.MAX_CELLS`), else :func:`~dftpcc.limits.cell_budget`."""
    check_max_cells(max_cells)
    if max_cells is None:
        return cell_budget(file_size)
    return min(max_cells, MAX_CELLS)


def check_max_cells(max_cells: Any) -> None:
    """Refuse a ``max_cells`` argument that is not None or a positive whole number."""
    if max_cells is not None and (not is_count(max_cells) or max_cells == 0):
        raise InvalidInputError(f"max_cells must be a positive whole number, got {max_cells!r}")


def check_max_bytes(max_bytes: Any) -> None:
    """Refuse a ``max_bytes`` argument that is not None or a positive whole number of bytes."""
    if max_bytes is not None and (not is_count(max_bytes) or max_bytes == 0):
        raise InvalidInputError(f"max_bytes must be a positive whole number of bytes, got {max_bytes!r}")
