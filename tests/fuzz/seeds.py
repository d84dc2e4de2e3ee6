"""Valid ``.dftpc`` files to start fuzzing from: small, and covering every code path.

Made with the current encoder each time (never checked in), so the seeds
follow the format as it evolves; beside them the committed maps of versions
1.0 and 1.1 (tests/legacy, :func:`legacy_files`), which no encoder writes
any more and every reader still reads. ``python tests/fuzz/seeds.py DIR`` writes
them to DIR as ``NAME.dftpc``.
"""

from __future__ import annotations

import contextlib
import sys
import warnings
from pathlib import Path
from unittest import mock

import numpy as np

import dftpcc
from dftpcc.experiments.terrain import regolith_plain

#: The committed maps of versions 1.0 and 1.1 (the legacy coefficient order).
LEGACY = Path(__file__).resolve().parents[1] / "legacy"
#: The legacy maps fuzzed: the small ones (a mutation of a large map costs a whole decode).
LEGACY_MAX_BYTES = 4000
#: ... but not these, whose unmutated decode alone takes more Python events than the fuzz test's bound
#: (tests/fuzz/test_fuzz_decoder.py, 50,000: the 60 x 60 tie map about 60,000, the growing map 52,000);
#: tests/test_legacy.py reads them, and web/test/fuzz.test.mjs mutates the tie map.
LEGACY_HEAVY = ("growing", "tie_dct", "tie_dft", "tie_tiled")

#: name -> compress() options. Small grids (at most ~40 x 40 cells) keep
#: each decode around a millisecond, so a fuzzer runs many inputs a second.
SEED_OPTIONS: dict[str, dict] = {
    "compact_dct": dict(resolution=1.0, cutoff=0.8),
    "compact_dct_fc0": dict(resolution=1.5, cutoff=0.0),
    "compact_dft": dict(resolution=1.0, cutoff=0.5, transform="dft"),
    "compact_oriented_zero": dict(resolution=1.0, cutoff=0.6, frame="oriented", fill="zero", detrend="none"),
    "compact_median_step": dict(resolution=2.0, cutoff=0.3, aggregate="median", step=0.01),
    "compact_zstd_footprint": dict(resolution=1.0, cutoff=0.7, coder="zstd", mask="footprint"),
    "compact_max_error": dict(resolution=1.0, cutoff=0.8, target_max_error=0.02),  # has a RESD section
    # A coarser bound: the residual is one sparse chunk (RESD kind 4: nonzero map, magnitudes, signs).
    "compact_max_error_sparse": dict(resolution=1.0, cutoff=0.8, target_max_error=0.1),
    "paper_dft": dict(resolution=1.5, cutoff=0.8, profile="paper"),
    "paper_dft_fc0": dict(resolution=3.0, cutoff=0.0, profile="paper"),
    # Tiled (format 1.1): 40 x 40 cells in 16-cell tiles (3 x 3, the last row and column 8 cells).
    "tiled": dict(resolution=1.0, cutoff=0.8, tile_size=16),
    "tiled_max_error_zstd": dict(resolution=1.0, cutoff=0.6, tile_size=16, target_max_error=0.05, coder="zstd"),
    "tiled_coarse": dict(resolution=1.5, cutoff=0.0, tile_size=16),  # 27 x 27 cells: 2 x 2 tiles
    # 32-cell tiles at a coarse bound: one tile's residual is sparse (kind 4), the others chunked.
    "tiled_max_error_sparse": dict(resolution=1.0, cutoff=0.6, tile_size=32, target_max_error=0.1),
    # 32-cell tiles at f_c 0.8 overlap by 16 cells (tiles.tile_overlap), half a tile: the widest a reader takes.
    "tiled_wide_overlap": dict(resolution=1.0, cutoff=0.8, tile_size=32),
}
#: The tiled seeds above hold each tile's mask and residual layer, as a map of more than
#: tiles.MAP_MASK_CELLS cells does; these hold the map mask (and the map residual) at tile 0
#: (format.md, Tile sections), as the writer codes a small map.
MAP_MASK_OPTIONS: dict[str, dict] = {
    "tiled_map_mask": dict(resolution=1.0, cutoff=0.8, tile_size=16),
    "tiled_map_residual": dict(resolution=1.0, cutoff=0.6, tile_size=16, target_max_error=0.05),
    # At a target the base layer alone is the smaller file here: no tile has a COEF.
    "tiled_base_only": dict(resolution=1.0, tile_size=16, target_rmse=0.02),
}
#: The map mask beside each tile's residual layer: what the writer keeps where the map residual is
#: not the shorter.
MAP_MASK_TILE_RESIDUALS: dict[str, dict] = {
    "tiled_map_mask_max_error": dict(resolution=1.0, cutoff=0.6, tile_size=16, target_max_error=0.05),
}


@contextlib.contextmanager
def tile_masks():
    """Within it, the writer codes each tile's mask, whatever the map's size."""
    from dftpcc import encoder

    with mock.patch.object(encoder, "MAP_MASK_CELLS", 0):
        yield


@contextlib.contextmanager
def tile_residuals():
    """Within it, the writer keeps each tile's residual layer, never the map residual."""
    from dftpcc import encoder

    with mock.patch.object(encoder, "map_residual", lambda an, masks, codes, coder: (masks, b"")):
        yield


def _rough() -> np.ndarray:
    """Rough terrain (integrated noise, a point per 1 m cell, 24 x 30 cells): at a fine bound its
    residual layer is predicted (RESD kind 5)."""
    rng = np.random.default_rng(12)
    z = np.cumsum(np.cumsum(rng.normal(0, 0.05, (24, 30)), 0), 1) + rng.normal(0, 0.003, (24, 30))
    yy, xx = np.mgrid[:24, :30] + 0.5
    keep = np.hypot(yy - 8, xx - 15) > 4  # a hole
    return np.column_stack([xx[keep], yy[keep], z[keep] + 50.0])


def _terrain() -> np.ndarray:
    # Irregular footprint (a disc sector) so masks have holes and edges.
    return regolith_plain(4000, size=40.0, craters=3, rocks=10, seed=11)


def seed_files() -> dict[str, bytes]:
    """name -> bytes of each seed map (plus a one-cell map and one with a CRS)."""
    points = _terrain()
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with tile_masks():
            for name, options in SEED_OPTIONS.items():
                out[name] = dftpcc.compress(points, **options)
            # Denser points in 32-cell tiles: a tile whose first line cuts through the map sends it as a
            # seed (MASK kind 3).
            out["tiled_first_seed"] = dftpcc.compress(regolith_plain(6000, size=40.0, craters=3, rocks=10, seed=11),
                                                      resolution=1.0, cutoff=0.8, tile_size=32)
        for name, options in MAP_MASK_OPTIONS.items():
            out[name] = dftpcc.compress(points, **options)
        with tile_residuals():
            for name, options in MAP_MASK_TILE_RESIDUALS.items():
                out[name] = dftpcc.compress(points, **options)
        # RESD kind 5, in a one-tile file and in 16-cell tiles (each tile's own residual layer).
        out["compact_max_error_predicted"] = dftpcc.compress(_rough(), resolution=1.0, target_max_error=0.005)
        with tile_masks(), tile_residuals():
            out["tiled_max_error_predicted"] = dftpcc.compress(_rough(), resolution=1.0, tile_size=16,
                                                               target_max_error=0.005)
        out["one_cell"] = dftpcc.compress(np.array([[5.0, 7.0, 1.25]]), resolution=1.0)
        out["with_crs"] = dftpcc.compress(
            points[::4], resolution=2.0, crs={"wkt": 'LOCAL_CS["rover frame"]', "las_vlrs": [
                {"record_id": 34735, "description": "GeoKeyDirectoryTag", "data": "AQABAAAAAQA="}]})
        # An int16 raster's own grid: STAT records its sample type and nodata value.
        from dataclasses import replace

        from dftpcc.dem import RasterSource
        from dftpcc.encoder import encode_dem, grid_points
        from dftpcc.params import make_params

        params = make_params(resolution=2.0, cutoff=0.8)
        dem = replace(grid_points(points[::4], params), source=RasterSource("int16", -32768.0))
        out["int16_raster"] = encode_dem(dem, params)
    return out


def legacy_files() -> dict[str, bytes]:
    """name -> bytes of the committed 1.0 and 1.1 maps of at most :data:`LEGACY_MAX_BYTES`, but the
    :data:`LEGACY_HEAVY` ones."""
    return {f"legacy_{p.stem}": p.read_bytes() for p in sorted(LEGACY.glob("*.dftpc"))
            if p.stat().st_size <= LEGACY_MAX_BYTES and p.stem not in LEGACY_HEAVY}


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: python tests/fuzz/seeds.py DIR", file=sys.stderr)
        return 2
    folder = Path(argv[0])
    folder.mkdir(parents=True, exist_ok=True)
    for name, data in seed_files().items():
        (folder / f"{name}.dftpc").write_bytes(data)
        print(f"{folder / name}.dftpc: {len(data)} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
