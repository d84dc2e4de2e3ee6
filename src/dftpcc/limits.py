"""Resource limits: how large a grid may be built, decoded or held in memory.

The encoder refuses a grid the memory cannot hold (:func:`check_grid_size`; a cloud's grid coded
band by band, one whose band it cannot hold, :func:`check_band_size`, or whose files the disk
cannot, :func:`check_spill_space`),
the reader refuses a grid a file's size does not justify (:func:`cell_budget`),
and a cloud too large to hold is read in chunks (:func:`holds_in_memory`).
"""

from __future__ import annotations

import math
import os

from .errors import InvalidInputError

__all__ = ["MAX_CELLS", "BAND_CELLS_PER_POINT", "available_memory", "cell_limit", "check_grid_size", "band_cell_limit",
           "check_band_size",
           "check_spill_space", "cell_budget", "holds_in_memory"]

#: Largest grid dftpcc builds in memory (cells). A float64 DEM this size is
#: 800 MB and the transform needs a few such arrays.
MAX_CELLS = 100_000_000

#: Peak memory of compressing one cell, bytes: the DEM, its mask, counts,
#: fill, transform and synthesis arrays (about 90 B measured for the
#: compact profile, 120 B for the paper's complex DFT), rounded up.
ENCODE_BYTES_PER_CELL = 128

def available_memory() -> int | None:
    """Bytes of memory the system can still give this process (Linux), else ``None``."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def cell_limit() -> int:
    """Largest grid (cells) compression will build here: :data:`MAX_CELLS`, or less
    when the available memory cannot hold :data:`ENCODE_BYTES_PER_CELL` per cell."""
    memory = available_memory()
    return MAX_CELLS if memory is None else max(1, min(MAX_CELLS, memory // ENCODE_BYTES_PER_CELL))


def _size(nbytes: float) -> str:
    for unit, scale in (("PB", 1e15), ("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if nbytes >= scale:
            return f"{nbytes / scale:,.1f} {unit}"
    return f"{nbytes / 1e3:,.1f} kB"


def _count(n: float) -> str:
    return f"{n:,.0f}" if n < 1e15 else f"{n:.3g}"


#: Headroom on a suggested resolution for the extra row and column a grid takes.
ROUNDING_MARGIN = 0.01


def _round_up(value: float, digits: int = 2) -> float:
    """``value`` rounded up to ``digits`` significant digits (a resolution to suggest)."""
    scale = 10.0 ** (math.floor(math.log10(value)) - digits + 1)
    return float(f"{math.ceil(value / scale) * scale:.{digits}g}")


def check_grid_size(rows: float, cols: float, resolution: float) -> None:
    """Refuse a grid of ``rows`` x ``cols`` cells of ``resolution`` metres that compression cannot build here."""
    cells = rows * cols
    limit = cell_limit()
    if math.isfinite(cells) and cells <= limit:
        return
    if not math.isfinite(cells):
        raise InvalidInputError(
            f"the points span about {_count((cols - 1) * resolution)} x {_count((rows - 1) * resolution)} m: "
            f"at {resolution:g} m that is more cells than can be counted; use a coarser resolution")
    why = (f"the {MAX_CELLS:,}-cell limit" if limit == MAX_CELLS else
           f"the {limit:,} cells that the available memory ({_size(available_memory() or 0)}) holds")
    # Cells scale with 1/resolution**2: the coarsest step that fits, rounded up.
    need = resolution * math.sqrt(cells / limit) * (1 + ROUNDING_MARGIN)
    hint = f"use a resolution of at least {_round_up(need):g} m"
    raise InvalidInputError(
        f"a {_count(rows)} x {_count(cols)} grid ({_count(cells)} cells) at {resolution:g} m would need "
        f"about {_size(cells * ENCODE_BYTES_PER_CELL)} of memory and exceeds {why}; {hint}")



# A cloud's grid coded band by band (dftpcc.grid.rasterize_bands, then dftpcc.stream): memory holds
# one band of tile rows at a time, so the limit is on a band's cells, not the map's; the map's cells
# and points go to files on disk instead.
#: Peak memory of gridding one cell of a band, bytes: its points and height sums (int64, float64),
#: a chunk's sums of them before they are added (2 x 8 B), its heights, occupancy and far-point flags
#: (8 + 1 + 1 B): 42 B, rounded up. Coding a band holds less: a block of tiles at a time.
BAND_BYTES_PER_CELL = 48
#: Disk a band-by-band cloud's files take, bytes per point: its cell (int32) and height (float64), its
#: band (at most 4 B; one for up to 256 bands), and its squared distance to the cell's height (float64).
SPILL_BYTES_PER_POINT = 24
#: ... and bytes per cell of the map: heights (float64), occupancy (bool), points (int64).
SPILL_BYTES_PER_CELL = 17


def band_cell_limit() -> int:
    """Largest band (cells) a cloud gridded band by band may have here: :data:`MAX_CELLS` (the largest
    grid built in memory), or less when the available memory cannot hold :data:`BAND_BYTES_PER_CELL`
    per cell. The map itself may be any number of bands."""
    memory = available_memory()
    return MAX_CELLS if memory is None else max(1, min(MAX_CELLS, memory // BAND_BYTES_PER_CELL))


#: A cloud gridded band by band may pass the limit of a grid held whole (:func:`cell_limit`), but not
#: with more than this many cells a point: such a grid is mostly empty (a stray point kilometres away,
#: heights in another CRS than the positions, a resolution far finer than the points), and would take
#: minutes and gigabytes of temporary files to say so (two points 10,000 km apart at 180 m: 589 s and
#: 53 GB). The shared surveys grid at 1-3 cells a point at their own spacing.
BAND_CELLS_PER_POINT = 64


def check_band_size(band_rows: int, rows: float, cols: float, resolution: float, points: int) -> None:
    """Refuse a grid of ``rows`` x ``cols`` cells of ``resolution`` metres for ``points`` points, coded band
    by band in bands of ``band_rows`` rows (a tile's side), whose band holds more than
    :func:`band_cell_limit` cells, or which passes :func:`cell_limit` with more than
    :data:`BAND_CELLS_PER_POINT` cells a point."""
    cells = rows * cols
    if not math.isfinite(cells):
        check_grid_size(rows, cols, resolution)  # its refusal of a grid too large to count
    if cells > max(cell_limit(), BAND_CELLS_PER_POINT * points):
        # Cells scale with 1/resolution**2: the coarsest step at which the points fill enough of them.
        need = resolution * math.sqrt(cells / (BAND_CELLS_PER_POINT * points)) * (1 + ROUNDING_MARGIN)
        raise InvalidInputError(
            f"the {_count(points)} points span a {_count(rows)} x {_count(cols)} grid ({_count(cells)} cells) at "
            f"{resolution:g} m, past the {cell_limit():,}-cell limit of a grid held whole with more than "
            f"{BAND_CELLS_PER_POINT} cells a point, nearly all empty; check the points' extent for stray points or "
            f"a wrong coordinate system, or use a resolution of at least {_round_up(need):g} m")
    band = min(band_rows, rows) * cols
    limit = band_cell_limit()
    if band <= limit:
        return
    why = (f"the {MAX_CELLS:,}-cell limit" if limit == MAX_CELLS else
           f"the {limit:,} cells that the available memory ({_size(available_memory() or 0)}) holds")
    # A band's rows are a tile's side: its cells scale with the columns, 1/resolution.
    need = resolution * band / limit * (1 + ROUNDING_MARGIN)
    raise InvalidInputError(
        f"a {_count(rows)} x {_count(cols)} grid at {resolution:g} m is coded in bands of {band_rows:,} rows, and "
        f"one band ({_count(band)} cells) would need about {_size(band * BAND_BYTES_PER_CELL)} of memory and "
        f"exceeds {why}; use a resolution of at least {_round_up(need):g} m or a smaller tile size")


def check_spill_space(points: int, rows: float, cols: float, resolution: float, folder: str | os.PathLike[str]) -> None:
    """Refuse a cloud of ``points`` gridded band by band into ``rows`` x ``cols`` cells of ``resolution``
    metres whose files (:data:`SPILL_BYTES_PER_POINT` a point, :data:`SPILL_BYTES_PER_CELL` a cell) the
    disk holding ``folder`` has no room for; the hint is the coarsest resolution whose cells fit."""
    import shutil

    cells = rows * cols
    need = points * SPILL_BYTES_PER_POINT + cells * SPILL_BYTES_PER_CELL
    free = shutil.disk_usage(folder).free
    if need <= free:
        return
    room = max(1.0, (free - points * SPILL_BYTES_PER_POINT) / SPILL_BYTES_PER_CELL)  # cells that would fit
    coarsest = _round_up(resolution * math.sqrt(cells / room) * (1 + ROUNDING_MARGIN))
    hint = (f"use a resolution of at least {coarsest:g} m"
            if points * SPILL_BYTES_PER_POINT < free else "the points' files alone would not fit")
    raise InvalidInputError(
        f"gridding {_count(points)} points into a {_count(rows)} x {_count(cols)} grid ({_count(cells)} cells) at "
        f"{resolution:g} m band by band needs about {_size(need)} of temporary files beside the output, and "
        f"{folder} has {_size(free)} free; {hint}, free some space, or write the output elsewhere")


# Decoding budget. Decoding costs memory and time in proportion to the grid
# (rows x cols), whatever the file's size, so a header's grid is checked
# against what the file's size justifies before anything is allocated.
#: Any file may ask for a grid this large (cells): the costliest such grid
#: decodes in under half a second and 200 MB.
FREE_CELLS = 1 << 21
#: Beyond FREE_CELLS a file must hold at least one byte per this many cells.
#: Maps of real terrain hold 5 to 100 cells per byte (measured on the
#: project's survey data, cutoffs 0.8 to 0.99); only a near-constant surface
#: compresses harder, and it can be opened with ``max_cells``.
CELLS_PER_BYTE = 1024
#: Peak memory to decode one cell, bytes (54 to 81 B measured), for messages.
DECODE_BYTES_PER_CELL = 96


def cell_budget(file_size: int) -> int:
    """Largest grid (cells) a ``.dftpc`` file of ``file_size`` bytes may ask for by default.

    ``max(FREE_CELLS, CELLS_PER_BYTE * file_size)``, capped at
    :data:`MAX_CELLS` (the largest grid the encoder builds).
    """
    return int(min(MAX_CELLS, max(FREE_CELLS, CELLS_PER_BYTE * file_size)))


#: Peak memory of compressing a cloud held in memory, bytes per point read
#: (the reader's records, x y z in float64, cell indices and distances),
#: 76-79 B measured by benchmarks/bench_memory.py on LAZ files of 2.8-22.7 M points, with headroom.
IN_MEMORY_BYTES_PER_POINT = 100
#: A cloud is read in chunks when holding it would take more than this
#: share of the memory available.
MEMORY_SHARE = 0.5


def holds_in_memory(points: int) -> bool:
    """Whether a cloud of ``points`` points can be compressed in one piece here.

    False when holding it would take more than :data:`MEMORY_SHARE` of the
    available memory (:data:`IN_MEMORY_BYTES_PER_POINT` per point).
    """
    memory = available_memory()
    return not (memory and points * IN_MEMORY_BYTES_PER_POINT > MEMORY_SHARE * memory)
