"""The format (dftpcc.format): what ``dftpcc.open`` accepts and refuses, and what ``pack`` will write.

The corrupt-file corpus (tests/test_corrupt.py) covers the reader's checks one file each;
these tests pin the rules that involve both sides: the arguments of ``open``, the integers of
the section table, the bytes after the last section, and the writer applying the reader's checks.
"""

from __future__ import annotations

import io
import json
import re
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
import zstandard

import dftpcc
from dftpcc import format as fmt
from dftpcc.dem import Grid
from dftpcc.errors import CorruptFileError, InvalidInputError, ResourceLimitError

from . import spec_decoder
from .fuzz import craft
from .fuzz.seeds import seed_files


@pytest.fixture(scope="module")
def seeds() -> dict[str, bytes]:
    return seed_files()


@pytest.fixture(scope="module")
def good(seeds) -> bytes:
    return seeds["with_crs"]


# --- the arguments of open ---------------------------------------------------------------------------

class _Unread(io.BytesIO):
    """A stream that fails the test if anything reads it."""

    def read(self, *args):  # type: ignore[override]
        raise AssertionError("the file was read before the arguments were checked")


@pytest.mark.parametrize("bad", [0, -1, 1.5, "100", True])
def test_max_bytes_is_checked_before_the_file_is_read(tmp_path, good, bad):
    with pytest.raises(InvalidInputError, match="max_bytes"):
        dftpcc.open(_Unread(good), max_bytes=bad)
    # A path is not even looked at: the argument is wrong whatever the file.
    with pytest.raises(InvalidInputError, match="max_bytes"):
        dftpcc.open(tmp_path / "missing.dftpc", max_bytes=bad)
    with pytest.raises(InvalidInputError, match="max_bytes"):
        dftpcc.decompress(good, max_bytes=bad)


@pytest.mark.parametrize("bad", [0, -1, 1.5, "10", True])
def test_max_cells_is_checked_before_the_file_is_read(tmp_path, good, bad):
    with pytest.raises(InvalidInputError, match="max_cells"):
        dftpcc.open(_Unread(good), max_cells=bad)
    with pytest.raises(InvalidInputError, match="max_cells"):
        dftpcc.open(tmp_path / "missing.dftpc", max_cells=bad)


def test_a_negative_max_bytes_does_not_read_the_whole_file(tmp_path, good):
    path = tmp_path / "m.dftpc"
    path.write_bytes(good)
    with pytest.raises(InvalidInputError, match="max_bytes must be a positive"):
        dftpcc.open(path, max_bytes=-1)


# --- LEB128 integers of the section table and STAT: at most 64 bits -----------------------------------

def _entry_index(data: bytes, tag: bytes) -> int:
    return [t for t, *_ in craft.table(data)].index(tag)


@pytest.mark.parametrize("field,value", [("tile", 1 << 64), ("tile", (1 << 70) + 5), ("length", (1 << 64) + 3)])
def test_a_table_integer_wider_than_64_bits_is_refused(good, field, value):
    # A tile of 2**64 used to be read as a tile other than 0: the CRS section was
    # skipped and the map lost its CRS without a word.
    crafted = craft.with_table_entry(good, _entry_index(good, b"CRS "), **{field: value})
    with pytest.raises(CorruptFileError, match="wider than 64 bits"):
        dftpcc.open(crafted)
    with pytest.raises(ValueError, match="wider than 64 bits"):
        spec_decoder.decode(crafted)


def test_an_endless_leb128_is_refused_as_too_wide(good):
    at = craft.PREAMBLE.size + 4  # the first entry's tile
    crafted = craft.fix_table_crc(good[:at] + b"\x80" * 10 + b"\x00" + good[at + 1:])
    with pytest.raises(CorruptFileError, match="wider than 64 bits"):
        dftpcc.open(crafted)
    with pytest.raises(ValueError, match="wider than 64 bits"):
        spec_decoder.decode(crafted)


def test_the_widest_64_bit_tile_is_read_and_skipped(good):
    # Ten bytes and a value below 2**64 is a valid tile number: a later tiled layout's.
    sections = craft.split(good)
    extra = b"future tile"
    entries = [craft.entry(t, 0, len(p), zlib.crc32(p)) for t, p in sections]
    entries.append(craft.entry(b"GEOM", (1 << 64) - 1, len(extra), zlib.crc32(extra)))
    head = craft.PREAMBLE.pack(fmt.sections.MAGIC, 1, 0, 0, len(entries)) + b"".join(entries)
    tiled = head + craft.CRC.pack(zlib.crc32(head)) + b"".join(p for _, p in sections) + extra
    assert len(craft.leb128((1 << 64) - 1)) == 10
    np.testing.assert_array_equal(dftpcc.decompress(tiled), dftpcc.decompress(good))
    np.testing.assert_array_equal(spec_decoder.decode(tiled), spec_decoder.decode(good))
    assert dftpcc.open(tiled).crs == dftpcc.open(good).crs


def test_a_stat_integer_wider_than_64_bits_is_refused(good):
    stat = craft.section(good, b"STAT")
    wide = stat + bytes([200]) + b"\xff" * 9 + b"\x02"  # id 200 (an integer), value 2**64 + ...
    crafted = craft.replace_section(good, b"STAT", wide)
    with pytest.raises(CorruptFileError, match="STAT holds an integer wider than 64 bits"):
        dftpcc.open(crafted)
    with pytest.raises(ValueError, match="wider than 64 bits"):
        spec_decoder.decode(crafted)


# --- a file ends where its last section ends ------------------------------------------------------------

@pytest.mark.parametrize("extra", [b"\x00", b"\n", b"x" * 100], ids=["zero", "newline", "junk"])
def test_bytes_after_the_last_section_are_refused(good, extra):
    with pytest.raises(CorruptFileError, match=rf"{len(extra)} trailing byte\(s\) after the last section, "
                                               f"which ends at byte {len(good):,}"):
        dftpcc.open(good + extra)
    with pytest.raises(ValueError, match="after the last section"):
        spec_decoder.decode(good + extra)


def test_two_files_joined_are_refused_not_read_as_the_first(seeds):
    joined = seeds["compact_dct"] + seeds["paper_dft"]
    with pytest.raises(CorruptFileError, match="two files joined"):
        dftpcc.decompress(joined)
    with pytest.raises(ValueError):
        spec_decoder.decode(joined)


def test_a_prefix_is_not_trailing_data_but_a_prefix_past_the_end_is_the_whole_file(tmp_path, seeds):
    data = seeds["compact_dct"]
    whole = dftpcc.decompress(data)
    # Progressive decoding: any prefix, up to and beyond the file's length, is judged as a prefix.
    assert dftpcc.decompress(data, max_bytes=len(data) - 1).shape == whole.shape
    np.testing.assert_array_equal(dftpcc.decompress(data, max_bytes=len(data) + 10), whole)
    path = tmp_path / "joined.dftpc"
    path.write_bytes(data + b"tail")
    assert dftpcc.open(path, max_bytes=len(data) - 1).grid == dftpcc.open(data).grid
    np.testing.assert_array_equal(dftpcc.open(path, max_bytes=len(data)).read_points(), whole)
    with pytest.raises(CorruptFileError, match="1 trailing byte"):
        dftpcc.open(path, max_bytes=len(data) + 1)
    with pytest.raises(CorruptFileError, match="4 trailing byte"):
        dftpcc.open(path)


def test_trailing_bytes_cannot_buy_a_larger_decoding_budget(good):
    # Padding a small file would raise the cells it may ask for (1024 per byte).
    bomb = craft.with_geom(good, rows=4000, cols=4000)
    with pytest.raises(ResourceLimitError):
        dftpcc.open(bomb)
    with pytest.raises(CorruptFileError, match="trailing byte"):
        dftpcc.open(bomb + bytes(20_000))


# --- drafts of format 1.0 are not read ------------------------------------------------------------------
# Pre-release builds wrote three things this reader no longer knows: 28-byte section
# entries, a JSON STAT and COEF kind 2 (tests/test_coding.py). Nobody holds such files;
# they are refused as any foreign file is, with a message that names what is wrong.

def test_a_draft_table_of_28_byte_entries_is_refused_as_corrupt(good):
    sections = craft.split(good)
    head = craft.PREAMBLE.size + 28 * len(sections) + craft.CRC.size
    table, body = b"", b""
    for tag, payload in sections:  # tag, u32 tile, u64 offset, u64 length, u32 crc
        table += struct.pack("<4sIQQI", tag, 0, head + len(body), len(payload), zlib.crc32(payload))
        body += payload
    top = good[:craft.PREAMBLE.size] + table
    draft = top + craft.CRC.pack(zlib.crc32(top)) + body
    with pytest.raises(CorruptFileError, match="section table fails its checksum") as info:
        dftpcc.open(draft)
    assert not isinstance(info.value, ResourceLimitError)
    with pytest.raises(ValueError, match="section table fails its checksum"):
        spec_decoder.decode(draft)


@pytest.mark.parametrize("coding", ["text", "zstd"])
def test_a_json_stat_of_the_drafts_is_refused(good, coding):
    stats = {k: v for k, v in dftpcc.open(good).header.stats.items() if not k.endswith("_bytes")}
    text = json.dumps(stats).encode()
    payload = text if coding == "text" else zstandard.ZstdCompressor().compress(text)
    crafted = craft.replace_section(good, b"STAT", payload)
    with pytest.raises(CorruptFileError, match=f"section STAT has unknown coding {payload[0]:#04x}"):
        dftpcc.open(crafted)
    with pytest.raises(ValueError, match="section STAT has unknown coding"):
        spec_decoder.decode(crafted)


def test_an_empty_stat_is_refused(good):
    crafted = craft.replace_section(good, b"STAT", b"")
    with pytest.raises(CorruptFileError, match="section STAT is empty"):
        dftpcc.open(crafted)
    with pytest.raises(ValueError, match="section STAT is empty"):
        spec_decoder.decode(crafted)


@pytest.mark.parametrize("field,value,message", [("cutoff", None, "states no cutoff"),
                                                  ("resolution", "auto", "parameter resolution")])
def test_a_file_must_state_what_params_may_leave_open(seeds, field, value, message):
    # Params takes cutoff=None and resolution='auto' for the encoder to choose; a file states
    # both. Found by the fuzzer: a PARM with "cutoff": null decoded into a TypeError.
    good = seeds["compact_dft"]
    parm = craft.json_of(good, b"PARM")
    parm[field] = value
    with pytest.raises(CorruptFileError, match=message):
        dftpcc.open(craft.with_json(good, b"PARM", parm)).read_points()


def test_a_file_with_coef_kind_2_of_the_drafts_is_refused(seeds):
    good = seeds["compact_dct"]
    draft = craft.with_chunk_kind(good, b"COEF", 2)
    with pytest.raises(CorruptFileError, match="coefficient chunk 0 has unknown kind 2"):
        dftpcc.open(draft).read_points()
    with pytest.raises(ValueError, match="unknown kind 2"):
        spec_decoder.decode(draft)


# --- the writer applies the reader's checks: no file is written that dftpcc refuses -----------------

@pytest.fixture(scope="module")
def cloud_file(tmp_path_factory) -> Path:
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0, 50, (2, 4000))
    path = tmp_path_factory.mktemp("cloud") / "cloud.npy"
    np.save(path, np.c_[x, y, 100 + 0.05 * x + np.sin(y / 5) + rng.normal(0, 0.01, x.size)])
    return path


@pytest.mark.parametrize("option,message", [
    (["--step", "1e300"], r"quantizer step must be .* at most 1e\+12 m.*got 1e\+300"),
    (["--step", "2e12"], r"quantizer step must be .* at most 1e\+12 m"),
    (["--target-max-error", "1e300"], r"target_max_error must be .* at most 1e\+12 m"),
    (["--target-rmse", "1e300"], r"target_rmse must be .* at most 1e\+12 m"),
])
def test_the_cli_refuses_a_step_or_target_the_reader_would_refuse_before_any_work(
        capsys, monkeypatch, tmp_path, cloud_file, option, message):
    # It used to write the whole file, then fail to open it and exit 5 as if the input were corrupt.
    from dftpcc import cli, files

    read = []
    monkeypatch.setattr(files, "open_reader", lambda *a, **k: read.append(a) or pytest.fail("the cloud was read"))
    out = tmp_path / "out.dftpc"
    assert cli.main(["compress", str(cloud_file), str(out), "-r", "1", *option]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.search(message, err[0]), err
    assert not out.exists() and not read


@pytest.mark.parametrize("target", [{"target_rmse": 1e9}, {"target_max_error": 1e11}, {"target_max_error": 1e12}])
def test_a_huge_but_allowed_target_writes_a_file_the_reader_opens(cloud_file, target):
    # Rate control tries steps up to 1e4 times an RMSE target and 16 times a maximum
    # error: above 1e12 m they are held at the largest step a file states.
    points = np.load(cloud_file)
    data = dftpcc.compress(points, resolution=1.0, **target)
    with dftpcc.open(data) as m:
        assert 0 < m.params.step <= fmt.validate.MAX_COORDINATE_M
        assert np.isfinite(m.read_points()).all()


def test_a_grid_beyond_the_coordinate_limit_is_refused_before_any_work(monkeypatch):
    from dftpcc import analysis, encoder

    monkeypatch.setattr(analysis.Analysis, "__init__", lambda *a, **k: pytest.fail("the DEM was analysed"))
    points = np.random.default_rng(1).uniform(0, 100, (500, 3)) + [5e12, 0.0, 0.0]
    with pytest.raises(InvalidInputError, match=r"cannot write this map: .*origin beyond 1e\+12 m"):
        encoder.compress(points, resolution=10.0)


def _header(**changes) -> fmt.header.Header:
    grid = Grid(x0=0.0, y0=0.0, z0=0.0, resolution=1.0, rows=4, cols=5)
    fields = dict(grid=grid, params=dftpcc.make_params(resolution=1.0, cutoff=0.5, step=0.01),
                  point_count=20, cell_count=20, coef_count=7, stats={"dem_rmse_m": 0.1})
    fields.update(changes)
    return fmt.header.Header(**fields)


def test_pack_writes_what_unpack_reads():
    data = fmt.writer.pack(_header(), b"mask", b"coef")
    header, blobs = fmt.reader.unpack(data)
    assert (header.grid, header.coef_count, blobs[b"MASK"].tobytes()) == (_header().grid, 7, b"mask")


@pytest.mark.parametrize("changes,message", [
    (dict(grid=Grid(x0=2e12, y0=0.0, z0=0.0, resolution=1.0, rows=4, cols=5)), "origin beyond"),
    (dict(grid=Grid(x0=0.0, y0=0.0, z0=-3e12, resolution=1.0, rows=4, cols=5)), "origin beyond"),
    (dict(grid=Grid(x0=0.0, y0=0.0, z0=0.0, resolution=3e11, rows=4, cols=5)), "extends beyond"),
    (dict(grid=Grid(x0=0.0, y0=0.0, z0=0.0, resolution=1.0, rows=4, cols=5, resolution_y=1e12)),
     "rows of 1e\\+12 m extend beyond"),
    (dict(grid=Grid(x0=0.0, y0=0.0, z0=0.0, resolution=1.0, rows=20_000, cols=10_000)), "cell limit of the format"),
    (dict(plane=(0.0, 1e18, 0.0)), "detrending plane"),
    (dict(plane=(float("nan"), 0.0, 0.0)), "non-finite"),
    (dict(cell_count=21), "with 21 occupied cells"),
    (dict(cell_count=0), "with 0 occupied cells"),
    (dict(point_count=3), "3 original points for 20 occupied cells"),
    (dict(coef_count=21), "coefficient count"),
    (dict(params=dftpcc.make_params(resolution=1.0, cutoff=0.5)), "quantizer step 0.0 m"),
    (dict(params=dftpcc.make_params(resolution=2.0, cutoff=0.5, step=0.01)), "disagrees with the grid"),
    (dict(params=dftpcc.make_params(resolution=1.0, step=0.01)), "states no cutoff"),
    (dict(crs={"las_vlrs": [{"record_id": 70000, "description": "", "data": ""}]}), "LAS record 0"),
    (dict(crs={"wkt": "x" * (2 << 20)}), "more than the 1048576 bytes a reader accepts"),
    (dict(stats={"dem_rmse_m": float("inf")}), "dem_rmse_m"),
    (dict(stats={"dem_max_error_m": 1e39}), "dem_max_error_m"),
])
def test_pack_refuses_a_header_the_reader_would_refuse(changes, message):
    with pytest.raises(InvalidInputError, match=f"cannot write this map: .*{message}"):
        fmt.writer.pack(_header(**changes), b"mask", b"coef")
