"""Deltas of a growing map (dftpcc.delta, docs/format.md *Deltas*), ``dftpcc patch``, and a short drive end to end."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import zstandard

import dftpcc
from dftpcc.format import leb128
from dftpcc.delta import COPY, apply_delta, make_delta, read_delta
from dftpcc.errors import CorruptFileError, InvalidInputError
from dftpcc.mapbuilder import MapBuilder

from .fuzz.fuzz_delta import run as fuzz_run
from .test_mapbuilder import RES, STEP, TILE, drive, in_map_frame, run, write_scans

#: Mutated deltas per CI run (about 5 s of CPU; `make fuzz` runs 100,000).
FUZZ_INPUTS = 2_000


@pytest.fixture(scope="module")
def versions():
    """Three versions of a growing map: each a few more scans."""
    scans = drive(8, heading=0.2, speed=2.0)
    builder = MapBuilder(RES, tile_size=TILE, step=STEP)
    out = []
    for part in (scans[:4], scans[4:6], scans[6:]):
        for points, pose in part:
            builder.add(points, pose)
        out.append(builder.encode())
    return out


def test_a_delta_gives_the_new_map_byte_for_byte_and_copies_the_unchanged_tiles(versions):
    a, b, _ = versions
    delta = make_delta(a, b)
    assert apply_delta(a, delta) == b
    parsed = read_delta(delta)
    assert parsed.copied > 0 and any(kind == COPY for kind, _, _ in parsed.pieces)
    assert len(delta) < len(b) - parsed.copied + 200  # new bytes and a few per piece, no more
    assert apply_delta(b"", make_delta(b"", a)) == a  # the first version: everything is new


def test_another_map_twice_or_out_of_order_is_refused(versions):
    a, b, c = versions
    ab, bc = make_delta(a, b), make_delta(b, c)
    with pytest.raises(InvalidInputError, match="applied already"):
        apply_delta(b, ab)
    sha = {m: hashlib.sha256(m).hexdigest()[:16] for m in (a, b, c)}
    # Out of order, and the map grew meanwhile: both another version of this map, versions named.
    with pytest.raises(InvalidInputError, match=f"another version of this map: it turns version {sha[b]}... "
                                                f"into {sha[c]}..., and this file is version {sha[a]}"):
        apply_delta(a, bc)
    with pytest.raises(InvalidInputError, match=f"another version of this map: it turns version {sha[a]}.*"
                                                f"this file is version {sha[c]}.*deltas apply in order"):
        apply_delta(c, ab)
    other = MapBuilder(RES, tile_size=TILE, step=STEP).add(in_map_frame(drive(2, seed=5))).encode()
    with pytest.raises(InvalidInputError, match=f"made for another map.*it turns {sha[a]}"):
        apply_delta(other, ab)
    assert apply_delta(apply_delta(a, ab), bc) == c


def test_the_base_is_checked_before_the_pieces(versions):
    """Issue 41, item 10: a delta for a larger map used to be called corrupt ("delta copies bytes 11,081 to
    16,161 of a 15,505-byte map", exit 5): whatever its copies reach, another base is named as such."""
    a, b, c = versions
    bc = make_delta(b, c)
    junk = bytes(range(256)) * 4
    assert max(offset + n for kind, offset, n in read_delta(bc).pieces if kind == COPY) > len(junk)
    with pytest.raises(InvalidInputError, match="another map, or another version of this one"):
        apply_delta(junk, bc)  # not a map at all: nothing to compare
    coarse = MapBuilder(RES * 2, tile_size=TILE, step=STEP).add(in_map_frame(drive(8, heading=0.2))).encode()
    with pytest.raises(InvalidInputError, match="made for another map"):
        apply_delta(coarse, bc)


def _rle_frame(size: int, value: int = 0) -> bytes:
    """A zstd frame declaring ``size`` bytes of ``value`` in RLE blocks: 4 bytes per 128 KiB (a bomb)."""
    block = 1 << 17
    out = bytearray(b"\x28\xb5\x2f\xfd" + bytes([0xE0]) + size.to_bytes(8, "little"))  # single segment, 8-byte size
    left = size
    while left:
        n = min(left, block)
        left -= n
        out += ((n << 3) | (1 << 1) | int(left == 0)).to_bytes(3, "little") + bytes([value])
    return bytes(out)


def _bomb(base: bytes, result: bytes, size: int) -> bytes:
    """A crafted delta for the real ``base``: one data piece of ``size`` bytes in an RLE frame, CRC right."""
    body = bytearray(b"\x89DFTPD\r\n" + bytes([1, 0, 0, 0]) + hashlib.sha256(base).digest()
                     + hashlib.sha256(result).digest())
    body += leb128(size) + leb128(1) + bytes([1]) + leb128(size) + _rle_frame(size)
    return bytes(body + zlib.crc32(body).to_bytes(4, "little"))


def test_the_rle_bomb_is_a_valid_frame():
    assert zstandard.ZstdDecompressor().decompress(_rle_frame(300_000, 7)) == bytes([7]) * 300_000


#: Address space the patch of a bomb may take above the interpreter's own (the bomb declares 4 GiB).
BOMB_BUDGET_BYTES = 256 << 20


def test_a_delta_bomb_is_refused_before_it_allocates(versions, tmp_path):
    """Issue 41, item 7: a 131 KB delta for the real base declaring 4 GiB of new data (zstd RLE blocks)
    is refused from its sizes alone, in a process that could not allocate a tenth of that."""
    a, b, _ = versions
    bomb = _bomb(a, b, 1 << 32)
    assert len(bomb) < 140_000
    (tmp_path / "a.dftpc").write_bytes(a)
    (tmp_path / "bomb.delta").write_bytes(bomb)
    script = f"""
import resource, sys
from dftpcc.delta import patch_file
from dftpcc.errors import CorruptFileError
with open("/proc/self/statm") as f:
    used = int(f.read().split()[0]) * resource.getpagesize()
resource.setrlimit(resource.RLIMIT_AS, (used + {BOMB_BUDGET_BYTES}, resource.RLIM_INFINITY))
try:
    patch_file({str(tmp_path / "a.dftpc")!r}, {str(tmp_path / "bomb.delta")!r})
except CorruptFileError as exc:
    print("refused:", exc)
"""
    env = dict(os.environ, PYTHONPATH=str(Path(dftpcc.__file__).parents[1]), OMP_NUM_THREADS="1",
               OPENBLAS_NUM_THREADS="1")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "refused:" in done.stdout and "more than 64 times" in done.stdout, done.stdout
    assert (tmp_path / "a.dftpc").read_bytes() == a


def test_new_data_within_the_bound_is_decompressed_and_checked(versions):
    """Below the factor the sizes pass, and the result's SHA-256 refuses the zeros (no result assembled)."""
    a, b, _ = versions
    with pytest.raises(CorruptFileError, match="not the map it names"):
        apply_delta(a, _bomb(a, b, 1 << 16))


def test_a_damaged_delta_is_refused_as_corrupt(versions):
    a, b, _ = versions
    delta = bytearray(make_delta(a, b))
    delta[len(delta) // 2] ^= 0x10
    with pytest.raises(CorruptFileError, match="checksum"):
        apply_delta(a, bytes(delta))
    with pytest.raises(CorruptFileError, match="no delta magic"):
        apply_delta(a, b)


def test_mutated_deltas_give_the_right_map_or_a_dftpcc_error():
    """Structure-aware and blind mutations of deltas of real growing maps (tests/fuzz/fuzz_delta.py): a
    dftpcc error or a version the delta names, within the memory budget, bombs of up to 4 GiB included."""
    report = fuzz_run(FUZZ_INPUTS, seed=3)
    print(report)
    assert report["iterations"] == FUZZ_INPUTS
    assert {"applied", "CorruptFileError", "InvalidInputError"} <= set(report["outcomes"])


def test_a_drive_updated_twice_sent_as_a_delta_patched_and_replayed_as_a_bag(tmp_path, capsys):
    """The whole chain on a short drive: bags in, update, delta, patch, a ROS 2 bag out."""
    pytest.importorskip("rosbags")
    from .test_rosbag import _bag_messages, rover_bag

    rng = np.random.default_rng(7)
    xy = rng.random((12_000, 2)) * np.array([40.0, 12.0])
    ground = np.c_[xy, 0.3 * np.sin(xy[:, 0] / 3.0) + 0.05 * xy[:, 1]]
    first = rover_bag(tmp_path / "first", ground[:6000], scans=4)
    second = rover_bag(tmp_path / "second", ground[6000:], scans=4)
    rover, ground_copy = tmp_path / "rover.dftpc", tmp_path / "ground.dftpc"
    assert run(capsys, "update", rover, first, "--pose-topic", "/odom", "-r", RES, "--tile-size", TILE) == (0, "")
    ground_copy.write_bytes(rover.read_bytes())  # the ground station has the first version
    assert run(capsys, "update", rover, second, "-o", tmp_path / "rover2.dftpc", "--delta",
               tmp_path / "d1.delta") == (0, "")
    assert run(capsys, "patch", ground_copy, tmp_path / "d1.delta", "-o", tmp_path / "ground2.dftpc") == (0, "")
    assert (tmp_path / "ground2.dftpc").read_bytes() == (tmp_path / "rover2.dftpc").read_bytes()
    before = ground_copy.read_bytes()
    code, err = run(capsys, "patch", tmp_path / "ground2.dftpc", tmp_path / "d1.delta")  # twice
    assert code == 3 and "applied already" in err and err.count("\n") == 1
    damaged = bytearray((tmp_path / "d1.delta").read_bytes())
    damaged[-1] ^= 1
    (tmp_path / "bad.delta").write_bytes(bytes(damaged))
    code, err = run(capsys, "patch", ground_copy, tmp_path / "bad.delta")
    assert code == 5 and "checksum" in err and ground_copy.read_bytes() == before
    assert run(capsys, "decompress", tmp_path / "ground2.dftpc", f"{tmp_path / 'out_bag'}/", "--topic", "/map") == (0, "")
    with dftpcc.open(tmp_path / "ground2.dftpc") as cmap:
        cells = cmap.header.cell_count
    messages = _bag_messages(tmp_path / "out_bag")
    _, msg, _ = messages["/map"]
    assert msg.width * msg.height == cells


def test_update_delta_patch_in_place_and_a_truncated_bag(tmp_path, capsys):
    pytest.importorskip("rosbags")
    from .test_rosbag import rover_bag

    scans = drive(6, heading=0.5)
    m = tmp_path / "m.dftpc"
    assert run(capsys, "update", m, write_scans(tmp_path, scans[:3], "a.laz"), "-r", RES, "--tile-size", TILE)[0] == 0
    old = m.read_bytes()
    assert run(capsys, "update", m, write_scans(tmp_path, scans[3:], "b.laz"), "--delta", tmp_path / "d.delta")[0] == 0
    (tmp_path / "copy.dftpc").write_bytes(old)
    assert run(capsys, "patch", tmp_path / "copy.dftpc", tmp_path / "d.delta")[0] == 0  # in place
    assert (tmp_path / "copy.dftpc").read_bytes() == m.read_bytes()
    # A truncated bag: one line, exit 3, the map and its state untouched.
    rng = np.random.default_rng(1)
    bag = rover_bag(tmp_path / "run.bag", np.c_[rng.random((3000, 2)) * 10, np.zeros(3000)], kind="ros1")
    bag.write_bytes(bag.read_bytes()[: bag.stat().st_size * 2 // 3])
    state = (tmp_path / "m.dftpc.state").read_bytes()
    current = m.read_bytes()
    code, err = run(capsys, "update", m, bag, "--delta", tmp_path / "d2.delta")
    assert code == 3 and err.count("\n") == 1 and str(bag) in err
    assert m.read_bytes() == current and (tmp_path / "m.dftpc.state").read_bytes() == state
    assert not (tmp_path / "d2.delta").exists()


def test_the_crc_covers_every_byte_before_it(versions):
    a, b, _ = versions
    delta = make_delta(a, b)
    assert zlib.crc32(delta[:-4]) == int.from_bytes(delta[-4:], "little")
