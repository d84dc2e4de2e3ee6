"""The ``.dftpc`` format (docs/format.md), by job: the bytes of sections and the section table
(:mod:`.sections`), the header's GEOM, PARM, CRS and STAT (:mod:`.header`), a tiled map's index
(:mod:`.index`), every check a reader makes (:mod:`.validate`), where the bytes come from
(:mod:`.source`), and the one :mod:`.reader` and one :mod:`.writer` every map goes through.
"""

from .header import STAT_FIELDS, Header, check_header
from .index import TileIndex
from .reader import read_tile, tile_sections, unpack, unpack_source
from .sections import MAGIC, VERSION, VERSION_TILED, entry_bytes, leb128, read_leb128
from .source import RemoteSource, Source, is_url
from .validate import cells_allowed, check_grid, check_max_bytes, check_max_cells
from .writer import MapWriter, pack, pack_tiled, restate, tiled_head, tiled_parts

__all__ = [
    "MAGIC", "VERSION", "VERSION_TILED", "STAT_FIELDS", "Header", "TileIndex", "Source", "RemoteSource", "is_url",
    "MapWriter", "restate", "pack", "pack_tiled", "tiled_head", "tiled_parts", "unpack", "unpack_source", "read_tile",
    "tile_sections", "leb128", "read_leb128", "entry_bytes", "cells_allowed", "check_grid", "check_header",
    "check_max_bytes", "check_max_cells",
]
