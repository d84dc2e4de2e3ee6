"""Damaged, truncated and crafted ``.dftpc`` files fail clearly, cheaply, and before allocating.

"Cheaply" is counted, not timed (tests/workbound.py): Python events and peak
allocation, so a slow machine never fails these tests and a decoder that
loops over a count a file chose, or allocates what it claims, always does.

The checked-in corpus (tests/corpus, written by tests/corpus/make_corpus.py)
is replayed file by file; the systematic tests below damage fresh maps made
by the current encoder, so they follow the format as it evolves.
"""

from __future__ import annotations

import base64
import json
import re
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest

import dftpcc
from dftpcc import cli, encoder, limits
from dftpcc import decoder, mapfile, rebuild  # noqa: F401 - the reader loaded before any work is measured
from dftpcc import format as fmt
from dftpcc.errors import (
    CorruptFileError,
    DftpccError,
    InvalidInputError,
    LargeGridWarning,
    ResourceLimitError,
    UnsupportedFormatError,
)

from .fuzz import craft
from .fuzz.seeds import seed_files
from .workbound import measure_work

CORPUS = Path(__file__).resolve().parent / "corpus"
EXPECTED = json.loads((CORPUS / "expected.json").read_text())
#: Reading a corrupt file must fail within this many Python events (calls and
#: lines): every corpus file is refused in at most 4,200 (coef_chunk_count_huge),
#: a sound 40 x 40 map decodes in 4,700, a loop over a crafted count takes far more ...
FAIL_FAST_EVENTS = 20_000
#: ... and allocate at most this much while doing so (bytes): far less than any
#: grid (the most a corpus file takes is 1.05 MB, parm_zstd_garbage: zstd's context).
FAIL_SMALL_BYTES = 2 << 20


@pytest.fixture(scope="module")
def seeds() -> dict[str, bytes]:
    return seed_files()


@pytest.fixture(scope="module")
def good(seeds) -> bytes:
    return seeds["with_crs"]


def _read(data: bytes, **options) -> np.ndarray:
    with dftpcc.open(data, **options) as cmap:
        return cmap.read_points()


# --- the checked-in corpus -------------------------------------------------------------------------

def test_corpus_is_small_and_complete():
    files = {p.name for p in CORPUS.glob("*.dftpc")}
    assert files == set(EXPECTED), "regenerate with python tests/corpus/make_corpus.py"
    assert len(files) >= 60
    for name in files:
        assert (CORPUS / name).stat().st_size < 20_000, name


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_corpus_file_fails_as_expected(name):
    expected = EXPECTED[name]
    data = (CORPUS / name).read_bytes()
    with measure_work(max_events=FAIL_FAST_EVENTS) as work:
        with pytest.raises(DftpccError) as info:
            _read(data)
    assert work.peak_bytes < FAIL_SMALL_BYTES, work
    assert type(info.value).__name__ == expected["error"], str(info.value)
    if expected["match"]:
        assert re.search(expected["match"], str(info.value)), str(info.value)
    # The one-shot API raises nothing but dftpcc errors either (its NaN output for
    # paper_nan_coefficient is test_decompress_rejects_nan_coefficients).
    try:
        dftpcc.decompress(data)
    except DftpccError:
        pass


# --- truncation ------------------------------------------------------------------------------------

def test_every_truncation_is_refused(seeds):
    for name in ("compact_dct", "paper_dft", "one_cell"):
        data = seeds[name]
        for n in range(len(data)):
            with pytest.raises(CorruptFileError, match="truncated|only|table"):
                dftpcc.open(data[:n])


def test_every_prefix_decodes_progressively_or_fails_clearly(seeds):
    for name in ("compact_dct", "compact_dft", "compact_oriented_zero"):
        data = seeds[name]
        full = _read(data)
        decoded = 0
        for n in range(1, len(data) + 1, 7):
            try:
                points = _read(data, max_bytes=n)
            except CorruptFileError:
                continue
            decoded += 1
            assert points.shape == full.shape and np.isfinite(points).all()
        assert decoded > 0


# --- damage ----------------------------------------------------------------------------------------

def test_every_bit_flip_in_the_header_is_caught(good):
    head_end = craft.head_size(good)
    for pos in range(head_end):
        for bit in range(8):
            buf = bytearray(good)
            buf[pos] ^= 1 << bit
            with pytest.raises((CorruptFileError, UnsupportedFormatError)):
                dftpcc.open(bytes(buf))


def test_a_damaged_section_is_named(good):
    for tag, _tile, offset, length, _crc in craft.table(good):
        name = tag.decode().strip()
        for pos in (offset, offset + length // 2, offset + length - 1):
            buf = bytearray(good)
            buf[pos] ^= 0x10
            with pytest.raises(CorruptFileError, match=f"section {name} fails its checksum"):
                dftpcc.open(bytes(buf))


def test_unknown_sections_and_newer_minor_versions_are_read(good):
    sections = craft.split(good)
    newer = craft.join(sections[:2] + [(b"XTRA", b"future data")] + sections[2:], version=(1, 7))
    np.testing.assert_array_equal(_read(newer), _read(good))


# --- the decoding budget -----------------------------------------------------------------------------

def test_a_small_file_cannot_ask_for_gigabytes(good):
    bomb = craft.with_geom(good, rows=10_000, cols=10_000)
    assert len(bomb) < 2_000
    tracemalloc.start()
    try:
        with pytest.raises(ResourceLimitError, match=r"10,000 x 10,000 grid .* max_cells=100000000"):
            dftpcc.open(bomb)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < FAIL_SMALL_BYTES


def test_budget_grows_with_the_file_and_has_a_hard_cap():
    assert limits.cell_budget(0) == limits.FREE_CELLS
    assert limits.cell_budget(50_000) == 50_000 * limits.CELLS_PER_BYTE
    assert limits.cell_budget(10**12) == dftpcc.limits.MAX_CELLS


def test_a_trusted_large_map_opens_with_max_cells(monkeypatch, good):
    # Shrink the budget so a small real map plays the part of a huge one.
    monkeypatch.setattr(limits, "FREE_CELLS", 10)
    monkeypatch.setattr(limits, "CELLS_PER_BYTE", 0)
    cells = dftpcc.open(good, max_cells=10**6).grid.size
    with pytest.raises(ResourceLimitError, match=f"max_cells={cells}"):
        dftpcc.open(good)
    with pytest.raises(ResourceLimitError):
        dftpcc.decompress(good)
    assert _read(good, max_cells=cells).shape[0] > 0
    with pytest.raises(ResourceLimitError):
        dftpcc.open(good, max_cells=cells - 1)
    # The writer says so when it makes such a file.
    points = np.random.default_rng(0).uniform(0, 10, (500, 3))
    with pytest.warns(LargeGridWarning, match="max_cells="):
        dftpcc.compress(points, resolution=1.0)


@pytest.mark.parametrize("bad", [0, -1, 1.5, "10", True])
def test_max_cells_must_be_a_positive_count(good, bad):
    with pytest.raises(InvalidInputError, match="max_cells"):
        dftpcc.open(good, max_cells=bad)


def test_progressive_budget_follows_the_whole_file(tmp_path, monkeypatch, good):
    # Reading a prefix of a file on disk is judged by the file's size, not the prefix's.
    path = tmp_path / "m.dftpc"
    path.write_bytes(good)
    cells = dftpcc.open(good).grid.size
    monkeypatch.setattr(limits, "FREE_CELLS", 1)
    monkeypatch.setattr(limits, "CELLS_PER_BYTE", cells / len(good) * (1 + 1e-6))  # just enough
    cut = len(good) - 3  # inside the coefficients
    assert dftpcc.open(path, max_bytes=cut).grid.size == cells
    with pytest.raises(ResourceLimitError):
        dftpcc.open(good[:cut], max_bytes=cut)


# --- what decoding produces -------------------------------------------------------------------------

def test_non_finite_heights_are_refused(monkeypatch, good):
    # Whatever makes the inverse transform produce NaN, decoding refuses it.
    from dftpcc import spectrum

    monkeypatch.setattr(spectrum, "inverse", lambda coefs, lay, **_: np.full(lay.shape, np.nan))
    with pytest.raises(CorruptFileError, match="non-finite heights"):
        _read(good)


def test_decompress_rejects_nan_coefficients():
    data = (CORPUS / "paper_nan_coefficient.dftpc").read_bytes()
    with pytest.raises(CorruptFileError):
        points = dftpcc.decompress(data)
        assert np.isfinite(points).all()


def test_paper_file_cut_inside_its_first_chunk_decodes_progressively(seeds):
    data = seeds["paper_dft"]  # one coefficient chunk
    points = _read(data, max_bytes=len(data) - 10)
    assert points.shape == _read(data).shape


#: A mask decodes one step per line along its coded axis: a 30,000 x 2 grid
#: claiming to run along the 30,000 lines would take 30,000 steps. Refused
#: before decoding in 807 events when written.
WRONG_AXIS_EVENTS = 4_000


def test_a_tall_thin_crafted_mask_is_refused_before_decoding(seeds):
    from dftpcc import occupancy

    good = seeds["compact_dct"]
    # A sound context-coded payload, but along the 30,000 lines ("not transposed"):
    # without the axis check it decodes, one step per line.
    payload = occupancy._encode_context(np.ones((30_000, 2), np.uint8), 30_000)
    lying = occupancy._HEAD.pack(occupancy.KIND_CONTEXT, 0) + payload
    data = craft.replace_section(craft.with_geom(good, rows=30_000, cols=2), b"MASK", lying)
    # Once outside the count: a reader's first call fills its caches and looks its kernels up
    # (about 2,500 events), the same for any file; the count is of what this file makes it do.
    with pytest.raises(CorruptFileError, match="occupancy mask runs along the wrong axis"):
        _read(data)
    with measure_work(max_events=WRONG_AXIS_EVENTS) as work:
        with pytest.raises(CorruptFileError, match="occupancy mask runs along the wrong axis"):
            _read(data)
    assert work.peak_bytes < FAIL_SMALL_BYTES, work


def test_a_complex_residual_layer_is_refused(seeds):
    from dftpcc import coding

    good = seeds["compact_max_error"]
    cells = dftpcc.open(good).header.cell_count
    lying = craft.replace_section(good, b"RESD", coding.encode_coefficients(np.ones(cells, dtype=np.complex64)))
    # Its chunks pass their checksums and decode: the integer check refuses it.
    for decode in (_read, dftpcc.decompress):
        with pytest.raises(CorruptFileError, match="residual layer is not one integer per rebuilt cell"):
            decode(lying)


# --- the command line: one line and a distinct exit code per kind of failure ------------------------

@pytest.mark.parametrize("name,code", [
    ("flip_in_geom.dftpc", 5),
    ("truncated_in_coef.dftpc", 5),
    ("geom_bomb_10k_squared.dftpc", 8),
    ("newer_major_version.dftpc", 4),
])
def test_cli_exit_codes_for_bad_files(capsys, tmp_path, name, code):
    for command in (["info", str(CORPUS / name)], ["decompress", str(CORPUS / name), str(tmp_path / "out.ply")]):
        assert cli.main(command) == code
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("dftpcc: error: "), err


def test_info_prints_a_stat_section_with_unusual_fields(capsys, tmp_path, good):
    # Statistics are informative, not needed to decode: a missing field shows
    # as nan, an unusual value as itself, and info succeeds.
    stats = dict(dftpcc.open(good).header.stats)
    assert "gridding_rmse_m" in stats
    del stats["gridding_rmse_m"]
    stats["vertical_rmse_m"] = 0.01
    stored = {k: v for k, v in stats.items() if k not in ("mask_bytes", "coef_bytes", "residual_bytes")}
    path = tmp_path / "odd.dftpc"
    path.write_bytes(craft.replace_section(good, b"STAT", fmt.header.pack_stats(stored)))
    assert cli.main(["info", str(path)]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    assert "vertical RMSE 10.0 mm (gridding floor n/a)" in out, out
    assert f"DEM RMSE {dftpcc.units.length(stats['dem_rmse_m'])}" in out, out


HOSTILE_CRS = {
    "wkt_not_ascii": {"wkt": "LOCAL_CS[\"r\u00e9seau \u2603\"]"},
    "wkt_multiline": {"wkt": "LOCAL_CS[\"a\"]\nend_header\nelement vertex 1"},
    "wkt_unparsable": {"wkt": "not a WKT at all"},
    "las_geokeys_garbage": {"las_vlrs": [{"record_id": 34735, "description": "x", "data": "AAECAwQFBgcICQ=="}]},
    "las_wkt_binary": {"las_vlrs": [{"record_id": 2112, "description": "x", "data": "//4AYWJj"}]},
}


@pytest.mark.parametrize("crs", sorted(HOSTILE_CRS))
def test_a_hostile_crs_is_written_or_refused_in_one_line(capsys, tmp_path, good, crs):
    path = tmp_path / "m.dftpc"
    path.write_bytes(craft.replace_section(good, b"CRS ", json.dumps(HOSTILE_CRS[crs]).encode()))
    for ext in ("las", "ply", "pcd", "tif", "xyz"):
        code = cli.main(["decompress", str(path), str(tmp_path / f"out.{ext}"), "-q"])
        err = capsys.readouterr().err
        assert code in (0, 3), err
        assert "Traceback" not in err and len(err.strip().splitlines()) <= 1, err


def test_a_las_record_too_long_for_las_is_refused(good):
    crs = {"las_vlrs": [{"record_id": 1, "description": "", "data": base64.b64encode(bytes(70_000)).decode()}]}
    with pytest.raises(CorruptFileError, match="LAS record 0"):
        dftpcc.open(craft.replace_section(good, b"CRS ", json.dumps(crs).encode()))


def test_exit_codes_are_distinct():
    codes = [code for _kind, code in cli.EXIT_CODES]
    others = [cli.EXIT_USAGE, cli.EXIT_INTERNAL, cli.EXIT_INTERRUPTED, 0]
    assert len(set(codes + others)) == len(codes) + len(others)


@pytest.mark.parametrize("raised,code,text", [
    (MemoryError(), 9, "dftpcc: error: out of memory"),
    (ValueError("boom"), 70, "dftpcc: internal error: ValueError: boom"),
    (KeyboardInterrupt(), 130, "dftpcc: interrupted"),
    (PermissionError(13, "Permission denied"), 7, "dftpcc: error: [Errno 13] Permission denied"),
])
def test_cli_maps_other_failures(monkeypatch, capsys, good, tmp_path, raised, code, text):
    path = tmp_path / "m.dftpc"
    path.write_bytes(good)

    def failing(_args):
        raise raised

    monkeypatch.setattr(cli, "cmd_info", failing)
    assert cli.main(["info", str(path)]) == code
    err = capsys.readouterr().err
    assert err.strip().splitlines()[-1].startswith(text), err


def test_cli_shows_warnings_as_one_line(monkeypatch, capsys, tmp_path, good):
    path = tmp_path / "m.dftpc"
    path.write_bytes(good)

    def warning(_args):
        warnings.warn("something to know", dftpcc.errors.MultiHeightWarning)
        return 0

    monkeypatch.setattr(cli, "cmd_info", warning)
    assert cli.main(["info", str(path)]) == 0
    assert capsys.readouterr().err == "dftpcc: warning: something to know\n"


#: Decoding the largest grid a small file is granted: Python events (3,117
#: compact, 1,304 paper when written; none of them per cell) ...
LARGEST_GRID_EVENTS = 15_000


@pytest.mark.parametrize("profile,transform,cutoff", [("compact", "dct", 0.0), ("paper", "dft", 0.99)])
def test_the_largest_grid_a_small_file_gets_decodes_within_its_budget(profile, transform, cutoff):
    # A flat map is the most compressible input: the costliest decode a tiny file can ask for.
    from dftpcc.dem import DEM, Grid

    side = int(np.sqrt(limits.FREE_CELLS))
    grid = Grid(0.0, 0.0, 0.0, 1.0, side, side)
    dem = DEM(grid, np.zeros(grid.shape), np.ones(grid.shape, bool), gridding_rmse=0.0)
    data = encoder.encode_dem(dem, dftpcc.make_params(resolution=1.0, cutoff=cutoff, profile=profile,
                                                     transform=transform))
    assert len(data) < 10_000 and grid.size <= limits.cell_budget(len(data))
    with measure_work(max_events=LARGEST_GRID_EVENTS) as work:
        points = _read(data)
    assert points.shape == (grid.size, 3)
    # ... and memory within what the container promises per cell (65 and 73 B measured).
    assert work.peak_bytes <= limits.DECODE_BYTES_PER_CELL * grid.size, work


def test_binary_stat_round_trips_and_skips_fields_it_does_not_know(good):
    stats = dftpcc.open(good).header.stats
    raw = craft.section(good, b"STAT")
    assert raw[0] == fmt.header.STAT_BINARY
    # A later writer's fields: one float (id 99) and one integer (id 200), in front.
    later = raw[:1] + b"\x63" + b"\x00\x00\x80\x3f" + b"\xc8\x96\x01" + raw[1:]
    assert dftpcc.open(craft.replace_section(good, b"STAT", later)).header.stats == stats


def test_the_fixed_header_of_a_small_map_is_small(seeds):
    # Everything but the mask and the coefficients: preamble and table (160 B),
    # GEOM (96 B), PARM and STAT; it used to be 430 B with JSON statistics.
    for name in ("compact_dct", "compact_dct_fc0"):  # default options; others add PARM fields
        data = seeds[name]
        header = len(data) - len(craft.section(data, b"MASK")) - len(craft.section(data, b"COEF"))
        assert header <= 310, (name, header)
