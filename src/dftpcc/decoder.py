"""Decode stage: a parsed ``.dftpc`` becomes a DEM again.

The decoder derives the coefficient order, count and interleaving from the
grid's shape and the cutoff alone (:mod:`dftpcc.spectrum`, shared with the
encoder), decodes the mask and the coefficients, inverts the transform, adds
the plane back and, for a complete file, the residual layer.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from . import coding, kernels, occupancy, quantizer, spectrum, tiles
from .cluster import serial
from .format import Header
from .dem import DEM
from .errors import CorruptFileError, InvalidInputError
from .fill import add_plane
from .params import check_cutoff
from .residual import decode_residual, residual_step

__all__ = ["decode_dem", "decode_tiled", "decode_window", "Whole"]

#: An untiled map's window is rebuilt from its basis vectors (cost about ``h * kc * (kr + w)``
#: multiply-adds) rather than by the whole grid's inverse transform (about ``n * m * log2(n * m)``
#: times this factor) when that is less work.
WINDOW_TRANSFORM_FACTOR = 4.0


def decode_dem(header: Header, blobs: dict[bytes, Any], *, cutoff: float | None = None,
               allow_partial: bool = False) -> DEM:
    """Rebuild the DEM of a parsed file.

    Parameters
    ----------
    header : Header
    blobs : dict
        Coded sections from :func:`dftpcc.format.unpack`.
    cutoff : float, optional
        Decode with a larger cutoff than the file was made with (fewer
        coefficients, coarser map). Must be at least the file's cutoff.
    allow_partial : bool
        Accept a truncated coefficient section and decode its whole chunks.
    """
    params, grid = header.params, header.grid
    if header.tiles is not None:
        raise InvalidInputError("a tiled map decodes tile by tile: use decode_tiled (dftpcc.open does)")
    if cutoff is not None:
        check_cutoff(cutoff)
        if cutoff < params.cutoff:
            raise InvalidInputError(
                f"cannot decode at cutoff {cutoff}: the file keeps only frequencies up to cutoff {params.cutoff}")
    # The mask, then any residual layer, decode beside the spectrum (on a second core, with the
    # compiled kernels); a damaged file still fails as a serial decoder fails: on its mask first,
    # then its spectrum, then its residual layer.
    layer = blobs.get(b"RESD") if cutoff is None else None
    side = kernels.Side(_mask_and_layer, blobs[b"MASK"], header, layer, cells=grid.size)
    try:
        with spectrum.fft_workers(side.cores_left):
            heights, complete = _spectrum_heights(header, blobs, cutoff, allow_partial)
    except Exception:
        _checked_mask(side.result()[0], header)
        raise
    mask, q = side.result()
    mask = _checked_mask(mask, header)
    if layer is not None and complete:
        # The residual layer only applies to the full-resolution map it was computed for.
        if isinstance(q, Exception):
            raise q
        _add_residual(heights, mask, q, residual_step(params.target_max_error))
    if not np.isfinite(heights).all() and not np.isfinite(heights[mask]).all():
        raise CorruptFileError("coefficients decode to non-finite heights (damaged or crafted file)")
    return DEM(grid=grid, heights=heights, mask=mask)


def _mask_and_layer(blob: Any, header: Header, layer: Any) -> tuple[np.ndarray, np.ndarray | Exception | None]:
    """An untiled map's mask and, given a residual layer, its integers decoded with that mask (or
    the error decoding them raised, for the caller to raise after the spectrum's own errors; None
    where the mask is wrong: the caller refuses it first)."""
    mask = occupancy.decode_mask(blob, header.grid.shape)
    if layer is None or int(mask.sum()) != header.cell_count:
        return mask, None
    try:
        return mask, decode_residual(layer, mask)
    except Exception as exc:  # noqa: BLE001 - raised by the caller, in a serial decoder's order
        return mask, exc


@kernels.kernel("add_residual")
def _add_residual(heights: np.ndarray, mask: np.ndarray, q: np.ndarray, step: float) -> None:
    """``heights[mask] += q * step`` in place: ``q`` one integer per set cell of ``mask``, row-major;
    ``step`` in metres."""
    heights[mask] += q * step


def _checked_mask(mask: np.ndarray, header: Header) -> np.ndarray:
    if int(mask.sum()) != header.cell_count:
        raise CorruptFileError("occupancy mask disagrees with the header's cell count")
    return mask


def _spectrum_heights(header: Header, blobs: dict[bytes, Any], cutoff: float | None,
                      allow_partial: bool) -> tuple[np.ndarray, bool]:
    """The heights of an untiled file's coefficients and plane (relative to z0, before any residual
    layer), and whether every coefficient was decoded at the file's own cutoff."""
    params, grid = header.params, header.grid
    lay = spectrum.layout(params.transform, params.storage, grid.shape, legacy=header.legacy_order)
    order, radii, angles = spectrum.kept_order(lay, params.cutoff)
    n = spectrum.kept_count(lay, params.cutoff, radii)  # all of them (a search, not a pass over the grid)
    if n != header.coef_count:
        raise CorruptFileError("coefficient count disagrees with the grid and cutoff")
    per_coef = spectrum.values_per_coefficient(lay, params.storage)
    radius, angle = (radii[:n], angles[:n]) if per_coef == 1 else \
        (np.repeat(radii[:n], per_coef), np.repeat(angles[:n], per_coef))
    stream = coding.decode_coefficients(blobs[b"COEF"], n * per_coef, radius=radius, angle=angle,
                                        allow_partial=allow_partial)
    if stream.size == 0:  # a prefix too short for one whole chunk: the map is its trend
        values = np.zeros(0, dtype=np.complex128 if lay.kind != "dct" else np.float64)
    elif params.storage == "quantized":
        if stream.dtype.kind != "i":
            raise CorruptFileError("quantized file holds float coefficients")
        values = stream[: stream.size - stream.size % per_coef]  # a DCT's: dequantized where they go
        if per_coef == 2:
            values = quantizer.dequantize(values, params.step).view(np.complex128)
    else:
        if stream.dtype.kind != "c":
            raise CorruptFileError("complex64 file holds integer coefficients")
        values = stream
    if cutoff is not None:
        values = values[: spectrum.kept_count(lay, cutoff, radii)]
    if lay.kind == "dct":  # only the low-frequency corner: the inverse pads it with zeros
        shape, where = spectrum.kept_corner(lay, params.cutoff) if values.size == order.size else \
            spectrum.corner(lay, order[: values.size])
    else:
        shape, where = lay.coef_shape, order[: values.size]
    if values.dtype.kind == "i":
        coefs = quantizer.dequantize_into(shape, where, values, params.step)
    else:
        coefs = np.zeros(shape, dtype=values.dtype)
        coefs.ravel()[where] = values
    heights = spectrum.inverse(coefs, lay, overwrite=True)
    if params.detrend == "plane":
        add_plane(heights, header.plane)
    return heights, values.size == n and cutoff is None


class Whole:
    """An untiled (1.0) map read as the one-tile, no-base case: its mask, its kept DCT corner (or, for
    another transform, its decoded heights) and its residual, decoded once; a window's heights are
    then the inverse transform evaluated on that window only (:meth:`heights`)."""

    def __init__(self, header: Header, blobs: dict[bytes, Any]):
        params, grid = header.params, header.grid
        self.header = header
        self.mask = _checked_mask(occupancy.decode_mask(blobs[b"MASK"], grid.shape), header)
        self.lay = spectrum.layout(params.transform, params.storage, grid.shape, legacy=header.legacy_order)
        self.corner: np.ndarray | None = None
        self.dem: np.ndarray | None = None
        if self.lay.kind == "dct" and params.storage == "quantized":
            self.corner = _dct_corner(header, blobs[b"COEF"])
        else:  # the paper's DFT layouts: decoded whole, then cut
            self.dem, _ = _spectrum_heights(header, blobs, None, False)
        self.resid = None
        if b"RESD" in blobs:
            self.resid = np.zeros(grid.shape)
            self.resid[self.mask] = decode_residual(blobs[b"RESD"], self.mask) * residual_step(params.target_max_error)

    def heights(self, rows: tuple[int, int], cols: tuple[int, int]) -> np.ndarray:
        """Heights (relative to z0) of the cells ``rows`` x ``cols``."""
        (r0, r1), (c0, c1) = rows, cols
        if self.dem is not None:
            out = self.dem[r0:r1, c0:c1].copy()
        else:
            assert self.corner is not None
            n, m = self.lay.shape
            kr, kc = self.corner.shape
            h, w = r1 - r0, c1 - c0
            # The inverse on the window alone (orthonormal DCT-II basis at its samples) when that is
            # less work than the whole grid's transform; else the whole transform, cut.
            if h * kc * (kr + w) < n * m * (math.log2(n) + math.log2(m) + 1) * WINDOW_TRANSFORM_FACTOR:
                out = tiles.base_basis(n, kr, r0, r1) @ self.corner @ tiles.base_basis(m, kc, c0, c1).T
            else:
                out = spectrum.inverse(self.corner, self.lay)[r0:r1, c0:c1]
            if self.header.params.detrend == "plane":
                a, b, c = self.header.plane
                out += a + b * np.arange(c0, c1, dtype=float)[None, :] + c * np.arange(r0, r1, dtype=float)[:, None]
        if self.resid is not None:
            out += self.resid[r0:r1, c0:c1]
        mask = self.mask[r0:r1, c0:c1]
        if not np.isfinite(out[mask]).all():
            raise CorruptFileError("coefficients decode to non-finite heights (damaged or crafted file)")
        return out


def _dct_corner(header: Header, blob: Any) -> np.ndarray:
    """The dequantized low-frequency corner of an untiled DCT map's coefficients (the rest are 0)."""
    params, grid = header.params, header.grid
    lay = spectrum.layout(params.transform, params.storage, grid.shape, legacy=header.legacy_order)
    order, radii, angles = spectrum.kept_order(lay, params.cutoff)
    n = spectrum.kept_count(lay, params.cutoff, radii)
    if n != header.coef_count:
        raise CorruptFileError("coefficient count disagrees with the grid and cutoff")
    stream = coding.decode_coefficients(blob, n, radius=radii[:n], angle=angles[:n])
    if stream.dtype.kind != "i" or stream.size != n:
        raise CorruptFileError("quantized file holds float coefficients" if stream.dtype.kind != "i" else
                               "coefficient section holds fewer values than the header states")
    shape, where = spectrum.kept_corner(lay, params.cutoff)
    return quantizer.dequantize_into(shape, where, stream, params.step)


def decode_window(header: Header, shared: dict[bytes, Any], read: Callable[[int], dict[bytes, Any]], *,
                  rows: tuple[int, int] | None = None, cols: tuple[int, int] | None = None,
                  map_tiles: Callable[..., list] | None = None, whole: "Whole | None" = None) -> DEM:
    """The one reader path: the DEM of the cells ``rows`` x ``cols`` of any map (default all of it).

    A tiled map decodes only the tiles the window touches (:func:`decode_tiled`); an untiled one is
    its single tile: its mask, coefficients and residual decoded once (``whole``, which a caller
    reading several windows keeps) and the inverse transform evaluated on the window only.
    """
    if header.tiles is not None:
        return decode_tiled(header, shared, read, rows=rows, cols=cols, map_tiles=map_tiles)
    grid = header.grid
    rows = rows or (0, grid.rows)
    cols = cols or (0, grid.cols)
    whole = whole or Whole(header, shared)
    out_grid = grid if (rows, cols) == ((0, grid.rows), (0, grid.cols)) else \
        grid.window(rows[0], cols[0], rows[1] - rows[0], cols[1] - cols[0])
    return DEM(grid=out_grid, heights=whole.heights(rows, cols), mask=whole.mask[rows[0]:rows[1], cols[0]:cols[1]].copy())


class _Base:
    """The decoded base layer of a tiled map: values and their frequency indices."""

    def __init__(self, header: Header, blob: Any):
        assert header.tiles is not None
        params, grid = header.params, header.grid
        self.i, self.j, radius, angle = tiles.base_order(grid.shape, header.tiles.tiling.size, params.cutoff,
                                                         header.tiles.base_cycles, legacy=header.legacy_order)
        if self.i.size != header.coef_count:
            raise CorruptFileError(f"the base layer's coefficient count {header.coef_count} disagrees with the "
                                   f"grid, tile size and cutoff ({self.i.size})")
        q = coding.decode_coefficients(blob, self.i.size, radius=radius, angle=angle, progressive=False)
        if q.dtype.kind != "i" or q.size != self.i.size:
            raise CorruptFileError("the base layer is not one integer per coefficient")
        self.values = quantizer.dequantize(q, params.step)


def decode_tiled(header: Header, shared: dict[bytes, Any], read: Callable[[int], dict[bytes, Any]], *,
                 rows: tuple[int, int] | None = None, cols: tuple[int, int] | None = None,
                 map_tiles: Callable[..., list] | None = None) -> DEM:
    """Rebuild a tiled map, or the window ``rows`` x ``cols`` (cell ranges) of it, decoding only its tiles.

    Parameters
    ----------
    header : Header
        Of a tiled map (``header.tiles`` set).
    shared : dict
        Tile 0's coded sections (:func:`dftpcc.format.unpack_source`): ``b"BASE"``, and
        ``b"MASK"`` and ``b"RESD"`` when it holds the map mask and the map residual.
    read : callable
        ``read(k)`` gives tile ``k``'s checked sections (see :func:`dftpcc.format.read_tile`).
    rows, cols : (start, stop), optional
        The cells wanted; default the whole map. The DEM returned covers
        exactly these cells (its grid is that window of the map's).
    map_tiles : callable, optional
        ``map_tiles(func, items, *args)``: where the tiles are decoded (default in this process;
        see :func:`dftpcc.cluster.executor`). The sections are read here, the decoding mapped.

    Raises
    ------
    CorruptFileError
        Naming the tile whose sections are damaged.
    """
    assert header.tiles is not None
    grid, index = header.grid, header.tiles
    rows = rows or (0, grid.rows)
    cols = cols or (0, grid.cols)
    base = _Base(header, shared[b"BASE"])
    map_mask = None
    if index.map_mask:  # decoded whole for any region (format.md, Tile sections)
        try:
            map_mask = occupancy.decode_mask(shared[b"MASK"], grid.shape)
        except CorruptFileError as exc:
            raise CorruptFileError(f"map mask: {exc}") from None
    map_resid = None
    if index.map_resid:  # decoded whole too, onto the map's cells
        assert map_mask is not None  # the container refuses a map residual without the map mask
        try:
            q = decode_residual(shared[b"RESD"], map_mask)
        except CorruptFileError as exc:
            raise CorruptFileError(f"map residual: {exc}") from None
        map_resid = np.zeros(grid.shape, dtype=np.int64)
        map_resid[map_mask] = q
    out_grid = grid if (rows, cols) == ((0, grid.rows), (0, grid.cols)) else \
        grid.window(rows[0], cols[0], rows[1] - rows[0], cols[1] - cols[0])
    heights = np.zeros(out_grid.shape)
    mask = np.zeros(out_grid.shape, dtype=bool)
    wanted = [k for k in index.tiling.touching(rows, cols) if index.cells[k]]
    jobs = [(k, {tag: bytes(blob) for tag, blob in read(k).items()},
             *(None if whole is None else _tile_of(whole, index.tiling.bounds(k)) for whole in (map_mask, map_resid)))
            for k in wanted]
    decoded = (map_tiles or serial)(_decode_job, jobs, header, base)
    for k, (h, m) in zip(wanted, decoded):
        r0, r1, c0, c1 = index.tiling.bounds(k)
        # The part of the tile inside the window.
        a, b = max(r0, rows[0]), min(r1, rows[1])
        c, d = max(c0, cols[0]), min(c1, cols[1])
        heights[a - rows[0]:b - rows[0], c - cols[0]:d - cols[0]] = h[a - r0:b - r0, c - c0:d - c0]
        mask[a - rows[0]:b - rows[0], c - cols[0]:d - cols[0]] = m[a - r0:b - r0, c - c0:d - c0]
    return DEM(grid=out_grid, heights=heights, mask=mask)


def _tile_of(whole: np.ndarray, bounds: tuple[int, int, int, int]) -> np.ndarray:
    r0, r1, c0, c1 = bounds
    return whole[r0:r1, c0:c1].copy()  # its own array: a job travels to a worker


def _decode_job(job: tuple[int, dict[bytes, bytes], np.ndarray | None, np.ndarray | None], header: Header,
                base: _Base) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_decode_tile` of ``(k, sections, its cells of the map mask and of the map residual, or
    None)``, its errors naming the tile."""
    k, blobs, mask, resid = job
    try:
        return _decode_tile(header, base, k, blobs, mask, resid)
    except CorruptFileError as exc:
        assert header.tiles is not None
        i, j = divmod(k, header.tiles.tiling.tile_cols)
        raise CorruptFileError(f"tile {k + 1} (tile row {i}, column {j}): {exc}") from None


def _decode_tile(header: Header, base: _Base, k: int, blobs: dict[bytes, Any],
                 mask: np.ndarray | None = None, resid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Heights (relative to z0) and mask of tile ``k``; ``mask``, ``resid``: its cells of the map mask
    and of the map residual's integers (on the map's grid), if tile 0 holds them."""
    assert header.tiles is not None
    params, grid, index = header.params, header.grid, header.tiles
    r0, r1, c0, c1 = index.tiling.bounds(k)
    shape = (r1 - r0, c1 - c0)
    # A full tile may come without its mask (the container checked its count is h x w).
    if mask is None:
        mask = occupancy.decode_mask(blobs[b"MASK"], shape) if b"MASK" in blobs else np.ones(shape, dtype=bool)
    if int(mask.sum()) != index.cells[k]:
        raise CorruptFileError("occupancy mask disagrees with the tile index's cell count")
    w0, w1, v0, v1 = tiles.coded_window(index.tiling, k, index.overlap)
    if b"COEF" in blobs:
        lay = spectrum.layout("dct", "quantized", (w1 - w0, v1 - v0), legacy=header.legacy_order)
        order, radii, angles = spectrum.kept_order(lay, params.cutoff)
        n = order.size
        stream = coding.decode_coefficients(blobs[b"COEF"], n, radius=radii, angle=angles, progressive=False)
        if stream.dtype.kind != "i" or stream.size != n:
            raise CorruptFileError("tile coefficients are not one integer per kept coefficient")
        corner_shape, where = spectrum.kept_corner(lay, params.cutoff)
        coefs = quantizer.dequantize_into(corner_shape, where, stream, params.step)
        heights = spectrum.inverse(coefs, lay, overwrite=True)[r0 - w0:r1 - w0, c0 - v0:c1 - v0]
    else:  # every coefficient 0 (format.md, TIDX)
        heights = np.zeros(shape)
    heights += tiles.base_heights(base.values, base.i, base.j, grid.shape, (r0, r1), (c0, c1), exact=False)
    a, b, c = header.plane
    heights += a + b * np.arange(c0, c1, dtype=float)[None, :] + c * np.arange(r0, r1, dtype=float)[:, None]
    if resid is not None:
        heights[mask] += resid[mask] * residual_step(params.target_max_error)
    elif b"RESD" in blobs:
        _add_residual(heights, mask, decode_residual(blobs[b"RESD"], mask), residual_step(params.target_max_error))
    if not np.isfinite(heights[mask]).all():
        raise CorruptFileError("coefficients decode to non-finite heights (damaged or crafted file)")
    return heights, mask
