"""The tile index of a tiled (1.1) map (docs/format.md, ``TIDX``): where each tile's sections lie,
its cells and its errors.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

import numpy as np
import zstandard

from ..dem import Grid, TileGrid
from ..errors import CorruptFileError
from ..params import Params
from .sections import f32_coarse_up
from .validate import TILES_PER_FILE_BYTE, check_tiled_params

#: The tile index's coding byte: 1, its errors one after another (read only); 2, in byte planes.
TIDX_CODING = 2
TIDX_CODINGS = (1, 2)
#: The low mantissa bits the writer rounds the tile index's errors up to 0 (format.md, TIDX).
TIDX_ERROR_LOW_BITS = 8
_TIDX_HEAD = struct.Struct("<BIHB")


@dataclass
class TileIndex:
    """What a tiled file says of its tiles (docs/format.md, ``TIDX``).

    Attributes
    ----------
    tiling : TileGrid
    overlap : int
        Cells of its neighbours a tile's transform also spans on each side.
    base_cycles : int
        Reach of the base layer, cycles per tile (0: none).
    cells : ndarray of int64, shape (n,)
        Rebuilt cells per tile (0: the tile has no sections).
    rmse, max_error : ndarray of float, shape (n,)
        DEM error per tile measured at compression, metres (NaN for empty tiles).
    sections : dict
        Tile (0-based) -> tag -> (offset, length, CRC-32) of its payloads in the file.
    map_mask : bool
        Whether tile 0 holds the map mask (format.md, *Tile sections*): then no tile holds a MASK,
        and a tile's mask is the map mask's cells of it.
    map_resid : bool
        Whether tile 0 holds the map residual (only beside the map mask): then no tile holds a
        RESD, and a tile's residual integers are the map residual's at its cells.
    """

    tiling: TileGrid
    overlap: int
    base_cycles: int
    cells: np.ndarray
    rmse: np.ndarray
    max_error: np.ndarray
    sections: dict[int, dict[bytes, tuple[int, int, int]]] = field(default_factory=dict)
    map_mask: bool = False
    map_resid: bool = False

    def tile_bytes(self, k: int) -> int:
        """Bytes of tile ``k``'s payloads."""
        return sum(length for _, length, _ in self.sections.get(k, {}).values())


def pack_index(index: TileIndex) -> bytes:
    cells = index.cells.astype("<u4")
    occupied = index.cells > 0
    rmse, max_error = (f32_coarse_up(values[occupied], TIDX_ERROR_LOW_BITS) for values in (index.rmse, index.max_error))
    if max_error.size:  # no tile states more than the map's maximum error (their maximum, in STAT)
        max_error = np.minimum(max_error, f32_coarse_up(index.max_error[occupied].max(keepdims=True), 0))
    errors = np.concatenate([rmse, max_error]).astype("<f4")
    body = b"".join(a.view(np.uint8).reshape(-1, 4).T.tobytes() for a in (cells, errors))
    frame = zstandard.ZstdCompressor(level=19, write_content_size=True).compress(body)
    return _TIDX_HEAD.pack(TIDX_CODING, index.tiling.size, index.overlap, index.base_cycles) + frame


def unpack_index(payload: memoryview, grid: Grid, params: Params, ncells: int, file_size: int) -> TileIndex:
    raw = bytes(payload)
    if len(raw) < _TIDX_HEAD.size:
        raise CorruptFileError("tile index is too short")
    coding, size, overlap, base_cycles = _TIDX_HEAD.unpack_from(raw, 0)
    if coding not in TIDX_CODINGS:
        raise CorruptFileError(f"tile index has unknown coding {coding}")
    check_tiled_params(params, grid, size)
    if overlap > size // 2:
        raise CorruptFileError(f"tile overlap {overlap} is more than half the tile size {size}")
    tiling = TileGrid(grid.rows, grid.cols, size)
    n = tiling.count
    if n > TILES_PER_FILE_BYTE * file_size:
        raise CorruptFileError(f"{n:,} tiles in a {file_size:,}-byte file: more than {TILES_PER_FILE_BYTE} "
                               f"a byte (crafted?)")
    frame = raw[_TIDX_HEAD.size:]
    try:
        declared = zstandard.frame_content_size(frame)
    except zstandard.ZstdError as exc:
        raise CorruptFileError(f"tile index does not decompress: {exc}") from None
    if declared < 0:  # zstandard's CONTENTSIZE_UNKNOWN: format.md requires the size be stated
        raise CorruptFileError("tile index's zstd frame does not state its content size")
    if declared < 4 * n or declared > 12 * n:
        raise CorruptFileError(f"tile index declares {declared} bytes, not 4 per tile and 8 per occupied tile "
                               f"of {n} tiles")
    try:
        body = zstandard.ZstdDecompressor().decompress(frame, max_output_size=declared)
    except zstandard.ZstdError as exc:
        raise CorruptFileError(f"tile index does not decompress: {exc}") from None
    if len(body) != declared:
        raise CorruptFileError("tile index is shorter than it declares")
    cells = np.frombuffer(body[: 4 * n], dtype=np.uint8).reshape(4, n).T.copy().view("<u4").ravel().astype(np.int64)
    occupied = np.flatnonzero(cells)
    if declared != 4 * n + 8 * occupied.size:
        raise CorruptFileError(f"tile index holds {declared} bytes where {n} tiles, {occupied.size} occupied, "
                               f"need {4 * n + 8 * occupied.size}")
    for k in occupied:
        h, w = tiling.shape(int(k))
        if cells[k] > h * w:
            raise CorruptFileError(f"tile {k + 1} claims {cells[k]} cells in a {h} x {w} tile")
    if int(cells.sum()) != ncells:
        raise CorruptFileError(f"the tiles' cells add up to {int(cells.sum())}, the map states {ncells}")
    errors = np.frombuffer(body[4 * n:], dtype=np.uint8)
    if coding == 2:  # byte planes
        errors = errors.reshape(4, -1).T.copy()
    errors = errors.view("<f4").ravel().astype(np.float64)
    if not (np.isfinite(errors).all() and (errors >= 0).all()):
        raise CorruptFileError("tile index holds a negative or non-finite error")
    rmse, max_error = np.full(n, np.nan), np.full(n, np.nan)
    rmse[occupied], max_error[occupied] = errors[: occupied.size], errors[occupied.size:]
    return TileIndex(tiling=tiling, overlap=overlap, base_cycles=base_cycles, cells=cells, rmse=rmse,
                     max_error=max_error)


def tile_needs(index: TileIndex, params: Params, k: int, have: set[bytes]) -> set[bytes]:
    """The sections tile ``k`` (0-based) must hold, given those it has (format.md, TIDX): MASK and
    COEF, and RESD with a maximum-error target, when it has cells; a full tile may leave its MASK
    out (every cell), any tile its COEF (every coefficient 0); no tile has a MASK with a map mask,
    nor a RESD with a map residual."""
    if not index.cells[k]:
        return set()
    need = {b"MASK", b"COEF"} | ({b"RESD"} if params.target_max_error > 0 and not index.map_resid else set())
    if index.map_mask or (index.cells[k] == math.prod(index.tiling.shape(k)) and b"MASK" not in have):
        need.discard(b"MASK")
    if b"COEF" not in have:
        need.discard(b"COEF")
    return need


def check_map_resid(index: TileIndex, params: Params) -> None:
    """A RESD at tile 0 is the map residual: it needs the map mask (its cells) and a bound."""
    if index.map_resid and not index.map_mask:
        raise CorruptFileError("a map residual (RESD at tile 0) needs the map mask (MASK at tile 0)")
    if index.map_resid and not params.target_max_error > 0:
        raise CorruptFileError("a map residual (RESD at tile 0) in a file without a maximum-error target")
