"""Deltas of a growing map (dftpcc.delta, docs/format.md *Deltas*), ``dftpcc patch``, and a short drive end to end."""

from __future__ import annotations

import hashlib
import zlib

import numpy as np
import pytest

import dftpcc
from dftpcc.delta import COPY, apply_delta, make_delta, read_delta
from dftpcc.errors import CorruptFileError, InvalidInputError
from dftpcc.mapbuilder import MapBuilder

from .fuzz.fuzz_delta import run as fuzz_run
from .test_mapbuilder import RES, STEP, TILE, drive, in_map_frame, run, write_scans

#: Mutated deltas per CI run (about 1 s).
FUZZ_INPUTS = 20_000


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
    with pytest.raises(InvalidInputError, match="deltas apply in order"):
        apply_delta(a, bc)  # out of order: b's delta not applied yet
    other = MapBuilder(RES, tile_size=TILE, step=STEP).add(in_map_frame(drive(2, seed=5))).encode()
    with pytest.raises(InvalidInputError, match="applies to the map whose SHA-256 is " + hashlib.sha256(a).hexdigest()[:16]):
        apply_delta(other, ab)
    assert apply_delta(apply_delta(a, ab), bc) == c


def test_a_damaged_delta_is_refused_as_corrupt(versions):
    a, b, _ = versions
    delta = bytearray(make_delta(a, b))
    delta[len(delta) // 2] ^= 0x10
    with pytest.raises(CorruptFileError, match="checksum"):
        apply_delta(a, bytes(delta))
    with pytest.raises(CorruptFileError, match="no delta magic"):
        apply_delta(a, b)


def test_mutated_deltas_give_the_right_map_or_a_dftpcc_error():
    report = fuzz_run(FUZZ_INPUTS, seed=3)
    print(report)
    assert report["iterations"] == FUZZ_INPUTS and len(report["outcomes"]) > 1


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
