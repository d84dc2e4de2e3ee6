"""Resource limits: how large a grid may be built, decoded or held in memory.

The encoder refuses a grid the memory cannot hold (:func:`check_grid_size`),
the reader refuses a grid a file's size does not justify (:func:`cell_budget`),
and a cloud too large to hold is read in chunks (:func:`holds_in_memory`).
"""

from __future__ import annotations

import math

from .errors import InvalidInputError

__all__ = ["MAX_CELLS", "available_memory", "cell_limit", "check_grid_size", "cell_budget", "holds_in_memory"]

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
