"""Write the corrupt-file corpus: small damaged or crafted ``.dftpc`` files and what reading each must do.

    python tests/corpus/make_corpus.py          # rewrites tests/corpus/*.dftpc and expected.json

Each file is a small valid map (tests/fuzz/seeds.py) truncated, bit-flipped
or given a lying header (a field changed and every checksum made to match,
as a crafted file would). ``expected.json`` maps each file to the exception
``dftpcc.open(file).read_points()`` must raise (the exact class) and, for the
checks the container makes, a regular expression its message must match.
tests/test_corrupt.py replays them. Regenerate after a format change; the
cases themselves are the list below.
"""

from __future__ import annotations

import json
import struct
import sys
import zlib
from pathlib import Path

import numpy as np
import zstandard

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))  # the checkout, for tests.fuzz

from dftpcc import coding  # noqa: E402
from tests.fuzz import craft  # noqa: E402
from tests.fuzz.seeds import seed_files  # noqa: E402

#: Every corpus file stays under this size (bytes).
MAX_FILE_BYTES = 20_000


def _flip(data: bytes, pos: int, bit: int = 0) -> bytes:
    buf = bytearray(data)
    buf[pos] ^= 1 << bit
    return bytes(buf)


def _section_start(data: bytes, tag: bytes) -> int:
    return next(off for t, _tile, off, _len, _crc in craft.table(data) if t == tag)


def _json_section(data: bytes, tag: bytes, **changes) -> bytes:
    obj = craft.json_of(data, tag)
    obj.update(changes)
    return craft.with_json(data, tag, obj)


def _raw_section(data: bytes, tag: bytes, text: str | bytes) -> bytes:
    return craft.replace_section(data, tag, text.encode() if isinstance(text, str) else text)


def cases() -> dict[str, tuple[bytes, str, str | None]]:
    """name -> (bytes, exception class name, message regex or None)."""
    seeds = seed_files()
    good = seeds["compact_dct"]
    paper = seeds["paper_dft"]
    head_end = craft.head_size(good)
    mask_at, coef_at = _section_start(good, b"MASK"), _section_start(good, b"COEF")
    sections = craft.split(good)
    C, R, U = "CorruptFileError", "ResourceLimitError", "UnsupportedFormatError"
    out: dict[str, tuple[bytes, str, str | None]] = {
        # Not a .dftpc at all.
        "empty": (b"", C, "only 0 bytes"),
        "ten_bytes": (good[:10], C, "only 10 bytes"),
        "png_signature": (b"\x89PNG\r\n\x1a\n" + bytes(200), C, "bad magic"),
        "text_file": (b"x y z\n0 0 0\n" * 30, C, "bad magic"),
        # Truncations.
        "truncated_in_table": (good[:40], C, "truncated inside its section table"),
        "truncated_before_table_crc": (good[:head_end - 2], C, "truncated inside its section table"),
        "truncated_after_header": (good[:head_end], C, "truncated: section GEOM"),
        "truncated_in_mask": (good[:mask_at + 3], C, "truncated: section MASK"),
        "truncated_in_coef": (good[:coef_at + (len(good) - coef_at) // 2], C, "truncated: section COEF"),
        "truncated_last_byte": (good[:-1], C, "truncated: section COEF"),
        # Damage: one flipped bit, caught by a checksum that names the section.
        "flip_in_magic": (_flip(good, 1), C, "bad magic"),
        "flip_in_table": (_flip(good, craft.PREAMBLE.size + 5), C, "section table fails its checksum"),
        "flip_in_table_crc": (_flip(good, head_end - 1, 7), C, "section table fails its checksum"),
        "flip_in_section_count": (_flip(good, 12), C, "truncated inside its section table|table fails"),
    }
    with_crs = seeds["with_crs"]  # its CRS section has bytes to damage
    for tag in (b"GEOM", b"PARM", b"CRS ", b"STAT", b"MASK", b"COEF"):
        start = _section_start(with_crs, tag)
        name = tag.decode().strip()
        out[f"flip_in_{name.lower()}"] = (_flip(with_crs, start + 2, 3), C, f"section {name} fails its checksum")
    out["flip_in_paper_coef"] = (_flip(paper, len(paper) - 5), C, "section COEF fails its checksum")
    out["newer_major_version"] = (craft.join(sections, version=(2, 0)), U, "version 2.0 is not supported")
    out["newer_minor_version_is_read"] = None  # placeholder, removed below (valid files are not corpus)
    # Lying section tables (checksums fixed).
    coef = [entry[0] for entry in craft.table(good)].index(b"COEF")
    out.update({
        "count_too_large": (craft.join(sections, count=5000), C, "claims 5000 sections"),
        "count_beyond_file": (craft.join(sections, count=500), C, "truncated inside its section table"),
        "count_zero": (craft.join(sections, count=0), C, "section table fails its checksum"),
        "section_missing_mask": (craft.replace_section(good, b"MASK", None), C, "section MASK is missing"),
        "section_missing_geom": (craft.replace_section(good, b"GEOM", None), C, "section GEOM is missing"),
        "geom_length_beyond_file": (craft.with_table_entry(good, 0, length=1 << 40), C, "truncated: section GEOM"),
        # Every checksum made to match the shifted sections: the lie must be caught behind them.
        # (The last section grows by as much, so the file still ends where the table says.)
        "geom_length_shifts_the_rest": (craft.fix_crcs(craft.with_table_entry(craft.with_table_entry(
            good, 0, length=craft.table(good)[0][3] - 4), coef, length=craft.table(good)[coef][3] + 4)),
                                        C, "geometry section is too short"),
        # Bytes after the last section: the file ends where the table says.
        "trailing_zeros": (good + bytes(8), C, r"8 trailing byte\(s\) after the last section"),
        "two_files_joined": (good + seeds["paper_dft"], C, "two files joined"),
        "length_over_64_bits": (craft.fix_table_crc(good[:craft.PREAMBLE.size + 5] + b"\xff" * 10
                                                    + good[craft.PREAMBLE.size + 6:]), C,
                                "entry 0 holds an integer wider than 64 bits"),
        # A tile of 2**64 once read as "another tile": the CRS section was skipped, the CRS lost.
        "tile_over_64_bits": (craft.with_table_entry(seeds["with_crs"], [e[0] for e in craft.table(
            seeds["with_crs"])].index(b"CRS "), tile=1 << 64), C, "wider than 64 bits"),
        "length_huge": (craft.with_table_entry(good, coef, length=(1 << 63) + 12), C, "truncated: section COEF"),
        "coef_length_claims_1gb": (craft.with_table_entry(good, coef, length=1 << 30), C, "truncated: section COEF"),
    })
    del out["newer_minor_version_is_read"]
    # Lying geometry.
    g = craft.geom(good)
    out.update({
        "geom_short": (craft.replace_section(good, b"GEOM", craft.section(good, b"GEOM")[:40]), C, "too short"),
        "geom_rows_zero": (craft.with_geom(good, rows=0), C, "implausible grid 0 x"),
        "geom_bomb_10k_squared": (craft.with_geom(good, rows=10_000, cols=10_000), R, "refusing to decode.*max_cells"),
        "geom_bomb_max_u32": (craft.with_geom(good, rows=0xFFFFFFFF, cols=0xFFFFFFFF), R, "100,000,000-cell limit of the format"),
        "geom_cells_more_than_grid": (craft.with_geom(good, cell_count=g["rows"] * g["cols"] + 1), C, "occupied cells"),
        "geom_cells_zero": (craft.with_geom(good, cell_count=0), C, "with 0 occupied cells"),
        "geom_points_fewer_than_cells": (craft.with_geom(good, point_count=1), C, "original points"),
        "geom_nan_origin": (craft.with_geom(good, x0=float("nan")), C, "non-finite"),
        "geom_inf_plane": (craft.with_geom(good, plane_b=float("inf")), C, "non-finite"),
        "geom_negative_resolution": (craft.with_geom(good, resolution=-1.0), C, "non-positive"),
        "geom_huge_resolution": (craft.with_geom(good, resolution=1e300), C, "extends beyond"),
        "geom_huge_origin": (craft.with_geom(good, x0=1e200), C, "origin beyond"),
        "geom_huge_plane": (craft.with_geom(good, plane_c=1e300), C, "detrending plane"),
        "geom_wrong_shape": (craft.with_geom(good, rows=g["rows"] + 1), C, None),
        "geom_row_spacing_nan": (craft.replace_section(good, b"GEOM", craft.section(good, b"GEOM")[:craft.GEOM.size]
                                                       + struct.pack("<d", float("nan"))), C, "row spacing"),
        "geom_row_spacing_huge": (craft.replace_section(good, b"GEOM", craft.section(good, b"GEOM")[:craft.GEOM.size]
                                                        + struct.pack("<d", 1e300)), C, "extend beyond"),
    })
    # Lying parameters.
    out.update({
        "parm_not_json": (_raw_section(good, b"PARM", "resolution=1"), C, "parameter section is invalid"),
        "parm_not_utf8": (_raw_section(good, b"PARM", b"\xff\xfe{}"), C, "parameter section is invalid"),
        "parm_list": (_raw_section(good, b"PARM", "[1, 2]"), C, "must be a JSON object"),
        "parm_deep_nesting": (_raw_section(good, b"PARM", "[" * 15_000), C, "too deeply"),
        "parm_huge_int_resolution": (_json_section(good, b"PARM", resolution=10**400), C, "parameter section is invalid"),
        "parm_nan_cutoff": (_raw_section(good, b"PARM", '{"resolution": 1.0, "cutoff": NaN}'), C, "cutoff"),
        "parm_cutoff_one": (_json_section(good, b"PARM", cutoff=1.0), C, "cutoff"),
        "parm_unknown_transform": (_json_section(good, b"PARM", transform="wavelet"), C, "transform"),
        "parm_step_zero": (_json_section(good, b"PARM", step=0.0), C, "quantizer step"),
        "parm_step_huge": (_json_section(good, b"PARM", step=1e300), C, "quantizer step"),
        "parm_resolution_mismatch": (_json_section(good, b"PARM", resolution=g["resolution"] * 2), C,
                                     "disagrees with the grid"),
        "parm_storage_swapped": (_json_section(good, b"PARM", storage="complex64"), C, None),
        "parm_cutoff_changed": (_json_section(good, b"PARM", cutoff=0.5), C, None),
    })
    # Lying statistics (binary records, the only STAT coding) and CRS.
    stat = craft.section(good, b"STAT")
    out.update({
        "stat_empty": (_raw_section(good, b"STAT", b""), C, "STAT is empty"),
        "stat_json_of_a_draft": (_raw_section(good, b"STAT", json.dumps(craft.stat_of(good))), C,
                                 "STAT has unknown coding 0x7b"),
        "stat_zstd_json_of_a_draft": (_raw_section(good, b"STAT", zstandard.ZstdCompressor(level=19).compress(
            json.dumps(craft.stat_of(good)).encode())), C, "STAT has unknown coding 0x28"),
        "parm_zstd_garbage": (_raw_section(good, b"PARM", b"\x28\xb5\x2f\xfd" + bytes(40)), C,
                              "parameter section is invalid"),
        "parm_zstd_bomb": (_raw_section(good, b"PARM", zstandard.ZstdCompressor(level=19).compress(
            b"[" + b" " * 2_000_000 + b"]")), C, "declares more than"),
        "crs_deep_nesting": (_raw_section(seeds["with_crs"], b"CRS ", "[" * 15_000), C, "too deeply"),
        "stat_coef_count_huge": (craft.with_stat(good, coef_count=2**62), C, "coefficient count"),
        "stat_coef_count_largest": (craft.with_stat(good, coef_count=2**64 - 1), C, "coefficient count"),
        "stat_coef_count_off_by_one": (craft.with_stat(good, coef_count=craft.stat_of(good)["coef_count"] + 1),
                                       C, None),
        # A record cut short, a NaN error, an endless integer, a record without its value.
        "stat_binary_cut_float": (_raw_section(good, b"STAT", b"\x01\x00\x00\x00"), C, "STAT is truncated"),
        "stat_binary_nan": (_raw_section(good, b"STAT", b"\x01\x00" + struct.pack("<f", float("nan"))), C,
                            "not finite"),
        "stat_binary_endless_int": (_raw_section(good, b"STAT", b"\x01\x80" + b"\xff" * 12), C,
                                    "STAT holds an integer wider than 64 bits"),
        "stat_binary_cut_int": (_raw_section(good, b"STAT", b"\x01\x80\xff"), C, "STAT is truncated"),
        "stat_binary_id_without_value": (_raw_section(good, b"STAT", stat + b"\x81"), C, "STAT is truncated"),
        "stat_binary_no_coef_count": (_raw_section(good, b"STAT", b"\x01\x07" + struct.pack("<f", 1.0)), C,
                                      "coefficient count is missing"),
        "crs_not_object": (_raw_section(seeds["with_crs"], b"CRS ", "\"EPSG:4326\""), C, "CRS must be a JSON object"),
        "crs_wkt_number": (_raw_section(seeds["with_crs"], b"CRS ", '{"wkt": 5}'), C, "wkt must be a string"),
        "crs_vlr_bad_base64": (_raw_section(seeds["with_crs"], b"CRS ", json.dumps(
            {"las_vlrs": [{"record_id": 34735, "description": "", "data": "!!!"}]})), C, "LAS record 0"),
        "crs_vlr_id_too_large": (_raw_section(seeds["with_crs"], b"CRS ", json.dumps(
            {"las_vlrs": [{"record_id": 70000, "description": "", "data": ""}]})), C, "LAS record 0"),
    })
    # Lying coded sections (their messages belong to the codec, so only the class is fixed).
    zbomb = zstandard.ZstdCompressor(level=19).compress(b"\xff" * 50_000_000)
    out.update({
        "mask_zstd_bomb": (craft.replace_section(good, b"MASK", zbomb), C, None),
        "mask_random": (craft.replace_section(good, b"MASK", bytes(range(256)) * 2), C, None),
        "mask_empty": (craft.replace_section(good, b"MASK", b""), C, None),
        "mask_of_another_map": (craft.replace_section(good, b"MASK", craft.section(seeds["paper_dft_fc0"], b"MASK")), C,
                                None),
        "coef_empty": (craft.replace_section(good, b"COEF", b""), C, None),
        "coef_zstd_bomb": (craft.replace_section(good, b"COEF", struct.pack("<I", 1) + zbomb), C, None),
        "coef_random": (craft.replace_section(good, b"COEF", bytes(range(256)) * 4), C, None),
        "coef_chunk_count_huge": (craft.replace_section(good, b"COEF", b"\xff\xff\xff\xff" +
                                                        craft.section(good, b"COEF")[4:]), C, None),
        # COEF kind 2 (ANS with Laplace models) existed only in pre-release drafts.
        "coef_kind_2_of_a_draft": (craft.with_chunk_kind(good, b"COEF", 2), C, None),
        "coef_of_paper_file": (craft.replace_section(good, b"COEF", craft.section(paper, b"COEF")), C, None),
        "coef_swapped_with_mask": (craft.replace_section(craft.replace_section(good, b"COEF", craft.section(
            good, b"MASK")), b"MASK", craft.section(good, b"COEF")), C, None),
    })
    # A paper (complex float32) file whose coefficients are NaN: caught after decoding.
    coef = bytearray(craft.section(paper, b"COEF"))
    struct.pack_into("<f", coef, 4 + 16, float("nan"))  # first value of the first chunk
    struct.pack_into("<I", coef, 4 + 8, zlib.crc32(bytes(coef[4 + 16:4 + 16 + struct.unpack_from("<I", coef, 8)[0]])))
    out["paper_nan_coefficient"] = (craft.replace_section(paper, b"COEF", bytes(coef)), C, "non-finite heights")
    out.update(_sparse_residual_cases(seeds["compact_max_error_sparse"], C))
    out.update(tiled_cases(seeds["tiled"]))
    out.update(first_seed_cases(seeds["tiled_first_seed"]))
    out.update(full_tile_cases(seeds["tiled_coarse"]))
    out.update(map_residual_cases(seeds["tiled_map_residual"]))
    return out


def _sparse_residual_cases(data: bytes, corrupt: str) -> dict[str, tuple[bytes, str, str]]:
    """A sparse residual layer (RESD's one kind-4 chunk) that lies, its checksums made to match."""
    resd = bytes(craft.section(data, b"RESD"))
    count, _nbytes, _crc, kind = struct.unpack_from("<IIII", resd, 4)
    assert kind == coding.KIND_SPARSE_RESIDUAL, "the seed's residual is no longer sparse: pick a coarser bound"
    payload = resd[20:]

    def with_payload(p: bytes, n: int = count) -> bytes:
        return craft.replace_section(data, b"RESD", coding.one_chunk(n, p, coding.KIND_SPARSE_RESIDUAL))

    return {
        "resd_sparse_stray_sign": (with_payload(payload[:-1] + bytes([payload[-1] | 1])), corrupt, "stray sign bit"),
        "resd_sparse_map_past_chunk": (with_payload(struct.pack("<I", 1 << 30) + payload[4:]), corrupt,
                                       "runs past the chunk"),
        "resd_sparse_fewer_values": (with_payload(payload, count - 1), corrupt, "must be the stream's only chunk"),
        "resd_sparse_beside_a_chunk": (craft.replace_section(data, b"RESD", struct.pack("<I", 2) + resd[4:] + resd[4:]),
                                       corrupt, "chunk"),
        "coef_of_sparse_kind": (craft.with_chunk_kind(data, b"COEF", coding.KIND_SPARSE_RESIDUAL), corrupt,
                                "unknown kind 4"),
    }


def _flip_in_tile(data: bytes, tag: bytes, tile: int) -> bytes:
    start = next(off for t, k, off, _len, _crc in craft.table(data) if t == tag and k == tile)
    return _flip(data, start + 3, 2)


def map_residual_cases(data: bytes) -> dict[str, tuple[bytes, str, str | None]]:
    """A RESD at tile 0 is the map residual: only beside the map mask and with a bound, and then no
    tile holds one (the seed: 40 x 40 cells in 16-cell tiles, the map mask and residual at tile 0)."""
    from dftpcc import occupancy
    from dftpcc.residual import decode_residual, encode_residual

    C = "CorruptFileError"
    sections = craft.split_tiled(data)
    mask = occupancy.decode_mask(craft.section(data, b"MASK"), (40, 40))
    q = decode_residual(craft.section(data, b"RESD"), mask)
    fewer = mask.copy()
    fewer[np.argwhere(mask)[-1][0], np.argwhere(mask)[-1][1]] = False
    return {
        "tiled_map_residual_without_map_mask": (craft.join_tiled([s for s in sections if s[:2] != (b"MASK", 0)]), C,
                                                "needs the map mask"),
        "tiled_map_residual_beside_a_tile_residual": (craft.join_tiled(
            sections + [(b"RESD", 1, craft.section(data, b"RESD"))]), C, "tile 1 has sections"),
        "tiled_map_residual_without_bound": (_json_section(data, b"PARM", target_max_error=0.0), C,
                                             "without a maximum-error target"),
        "tiled_map_residual_one_value_short": (craft.replace_section(data, b"RESD", encode_residual(
            q[:-1], "ans", fewer)), C, "map residual: "),
    }


def tiled_cases(tiled: bytes) -> dict[str, tuple[bytes, str, str | None]]:
    """Lying tiled (1.1) maps: the seed has 40 x 40 cells in 16-cell tiles (3 x 3, tile 9 empty)."""
    C, R = "CorruptFileError", "ResourceLimitError"
    index = craft.tile_index(tiled)
    cells, n = index["cells"], index["cells"].size
    sections = craft.split_tiled(tiled)
    more = cells.copy()
    more[0] += 1
    over = cells.copy()  # tile 1 claims more cells than it has, the sum kept
    over[0], over[1] = 16 * 16 + 1, cells[1] - (16 * 16 + 1 - cells[0])
    raw_tidx = craft.section(tiled, b"TIDX")
    head = raw_tidx[:craft.TIDX_HEAD.size]
    body = zstandard.ZstdDecompressor().decompress(raw_tidx[craft.TIDX_HEAD.size:])
    gigabyte = b"\x28\xb5\x2f\xfd" + bytes([0xC0, 0x58]) + struct.pack("<Q", 1 << 30) + bytes(16)
    tile_3 = [(t, k, p) for t, k, p in sections if k == 3]
    return {
        "tiled_cells_sum_lies": (craft.with_tile_index(tiled, cells=more), C, "cells add up to"),
        "tiled_cells_over_tile_size": (craft.with_tile_index(tiled, cells=over), C,
                                       "tile 1 claims 257 cells in a 16 x 16 tile"),
        "tiled_index_claims_1gb": (craft.replace_section(tiled, b"TIDX", head + gigabyte), C,
                                   "tile index declares 1073741824 bytes"),
        "tiled_index_zstd_bomb": (craft.replace_section(tiled, b"TIDX", head + zstandard.ZstdCompressor(
            level=19).compress(bytes(50_000_000))), C, "tile index declares 50000000 bytes"),
        "tiled_index_size_unstated": (craft.replace_section(tiled, b"TIDX", head + zstandard.ZstdCompressor(
            write_content_size=False).compress(body)), C, "does not state its content size"),
        "tiled_index_counts_for_more_tiles": (craft.with_tile_index(tiled, cells=list(cells) + [1]), C,
                                              "tile index declares 112 bytes"),
        "tiled_overlap_over_half_a_tile": (craft.with_tile_index(tiled, overlap=9), C, "tile overlap 9"),
        "tiled_tile_size_disagrees": (craft.with_tile_index(tiled, size=32), C, "tiles of 32 cells"),
        "tiled_tile_beyond_count": (craft.join_tiled(sections + [(b"MASK", n + 1, tile_3[0][2])]), C,
                                    f"names tile {n + 1}, but the map has {n} tiles"),
        "tiled_tile_2_64_minus_1": (craft.join_tiled(sections + [(b"COEF", (1 << 64) - 1, b"")]), C,
                                    "names tile 18446744073709551615"),
        "tiled_unknown_tag_beyond_count": (craft.join_tiled(sections + [(b"XTRA", n + 1, b"later")]), C,
                                           f"names tile {n + 1}, but the map has {n} tiles"),
        "tiled_missing_mask": (craft.join_tiled([s for s in sections if s[:2] != (b"MASK", 3)]), C,
                               "tile 3 has sections COEF where its index entry needs COEF, MASK"),
        "tiled_empty_tile_has_sections": (craft.join_tiled(sections + [(t, 9, p) for t, _k, p in tile_3]), C,
                                          "tile 9 has sections COEF, MASK where its index entry needs none"),
        # A MASK at tile 0 is the map mask: then no tile holds one, and it is the whole grid's.
        "tiled_map_mask_beside_tile_masks": (craft.join_tiled(sections[:1] + [(b"MASK", 0, tile_3[0][2])]
                                                              + sections[1:]), C, "where its index entry needs"),
        "tiled_map_mask_of_one_tile": (craft.join_tiled([s for s in sections[:1] + [(b"MASK", 0, tile_3[0][2])]
                                                         + sections[1:] if not (s[0] == b"MASK" and s[1])]), C,
                                       "map mask: "),
        "tiled_base_missing": (craft.join_tiled([s for s in sections if s[0] != b"BASE"]), C,
                               "section BASE is missing"),
        "tiled_base_count_lies": (craft.with_stat(tiled, coef_count=craft.stat_of(tiled)["coef_count"] + 1), C,
                                  "base layer's coefficient count"),
        "tiled_as_version_1_0": (craft.join_tiled(sections, version=(1, 0)), C, "version 1.0 file holds a tile index"),
        "tiled_transform_dft": (_json_section(tiled, b"PARM", transform="dft"), C, "not transform=dft"),
        # The reader reads on into the payloads, which do not parse as entries.
        "tiled_section_count_2_24": (craft.join_tiled(sections, count=1 << 24), C, "section table"),
        "tiled_section_count_over_2_24": (craft.join_tiled(sections, count=(1 << 24) + 1), C,
                                          "claims 16777217 sections, more than the 16777216 allowed"),
        "tiled_flip_in_tile_5_coef": (_flip_in_tile(tiled, b"COEF", 5), C,
                                      r"tile 5 \(tile row 1, column 1\): section COEF fails its checksum"),
        "tiled_flip_in_tile_2_mask": (_flip_in_tile(tiled, b"MASK", 2), C,
                                      r"tile 2 \(tile row 0, column 1\): section MASK fails its checksum"),
        "tiled_truncated_in_last_tile": (tiled[:-3], C, "tile 8 .*truncated"),
        # 8.4 million base coefficients (a 4095-tile strip of 2048-cell tiles, at cutoff 0) in 1.5 KB.
        "tiled_base_bomb": (craft.tiled_file(2048, 2047 * 2048 + 16, 2048, {2048: 100}, cutoff=0.0), R,
                            "refusing to decode"),
        # A base layer of 8 cycles per tile at cutoff 0 (already the whole 1200 x 1200 grid): 1.4 million
        # base coefficients beside 1.4 million cells of tiles, each half within the budget of a small file.
        "tiled_base_reach_bomb": (craft.tiled_file(1200, 1200, 16, {1: 100}, cutoff=0.0, reach=8), R,
                                  "refusing to decode 2,880,000 cells"),
        # A tile's chunks hold one value fewer than its stream: 1.1 chunks have free lengths that add up.
        "tiled_coef_chunks_fall_short": (_short_chunks(craft.tiled_file(64, 64, 32, {1: 100}, cutoff=0.0)), C,
                                         r"tile 1 \(tile row 0, column 0\): coefficient chunks hold 1599 values, "
                                         "expected 1600"),
    }


def first_seed_cases(tiled: bytes) -> dict[str, tuple[bytes, str, str | None]]:
    """A tile's MASK of kind 3 (its first line a seed too) given the other kind's byte, and back:
    the seed frame then holds one line more, or one fewer, than the kind says."""
    C = "CorruptFileError"
    k, mask = next((k, p) for t, k, p in craft.split_tiled(tiled) if t == b"MASK" and p[0] == 3)
    other = next((j, p) for t, j, p in craft.split_tiled(tiled) if t == b"MASK" and p[0] == 2)
    return {
        "tiled_mask_kind_3_read_as_2": (craft.replace_section(tiled, b"MASK", b"\x02" + mask[1:], tile=k), C,
                                        f"tile {k} .*occupancy mask has seed lines it does not need"),
        "tiled_mask_kind_2_read_as_3": (craft.replace_section(tiled, b"MASK", b"\x03" + other[1][1:], tile=other[0]),
                                        C, f"tile {other[0]} .*occupancy mask"),
    }


def full_tile_cases(tiled: bytes) -> dict[str, tuple[bytes, str, str | None]]:
    """A full tile (tile 1 of the 2 x 2 seed; no MASK, its count implies it) given a mask with a hole."""
    from dftpcc import occupancy

    sections = craft.split_tiled(tiled)
    assert not any(tag == b"MASK" and k == 1 for tag, k, _ in sections)
    holed = np.ones((16, 16), dtype=bool)
    holed[5, 7] = False
    return {"tiled_full_tile_mask_with_a_hole": (craft.join_tiled([(b"MASK", 1, occupancy.encode_mask(holed))] + sections),
                                                 "CorruptFileError", r"tile 1 \(tile row 0, column 0\): .*cell count")}


def _short_chunks(tiled: bytes) -> bytes:
    """Tile 1's COEF (its values all 0) re-coded as two chunks that hold one value too few."""
    sections = []
    for tag, k, payload in craft.split_tiled(tiled):
        if tag == b"COEF" and k == 1:
            count = struct.unpack_from("<I", payload, 4)[0]  # the one chunk's value count
            cctx = zstandard.ZstdCompressor()
            payload = coding._chunks([(n, coding._code_chunk(np.zeros(n, dtype=np.int64), None, None, "zstd",
                                                             False, cctx)) for n in (count // 2, count - count // 2 - 1)])
        sections.append((tag, k, payload))
    return craft.join_tiled(sections)


def main() -> int:
    for old in HERE.glob("*.dftpc"):
        old.unlink()
    expected = {}
    for name, (data, error, match) in sorted(cases().items()):
        if len(data) > MAX_FILE_BYTES:
            raise SystemExit(f"{name}: {len(data)} bytes, over the {MAX_FILE_BYTES}-byte corpus limit")
        (HERE / f"{name}.dftpc").write_bytes(data)
        expected[f"{name}.dftpc"] = {"error": error, "match": match}
    (HERE / "expected.json").write_text(json.dumps(expected, indent=1, sort_keys=True) + "\n")
    print(f"{len(expected)} corrupt files written to {HERE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
