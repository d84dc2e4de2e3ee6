"""The rover-ground link (dftpcc.link, docs/format.md *Link frames*) over a simulated bad link (dftpcc.linksim)."""

from __future__ import annotations

import hashlib
import logging

import numpy as np
import pytest

import dftpcc
from dftpcc.errors import InvalidInputError
from dftpcc.link import (DATA_OVERHEAD, PREVIEW_ITEM, Ack, Budget, DataFrame, FrameError, Receiver, Sender, make_change,
                         pack_ack, pack_data, read_frame)
from dftpcc.linksim import Channel, Ends, run_link
from dftpcc.mapbuilder import MapBuilder

from . import spec_decoder
from .fuzz.fuzz_link import run as fuzz_run
from .test_mapbuilder import RES, STEP, TILE, drive

#: Mutated frames per CI run (a few seconds).
FUZZ_INPUTS = 3_000
FRAME = 400  # bytes: small frames, so that tiles span several


@pytest.fixture(scope="module")
def drive_scans():
    # Out and back along a bend: new ground at first, then scans over tiles seen before.
    return drive(14, heading=0.2, speed=2.0) + drive(6, start=(20.0, 12.0), heading=2.2, seed=3)


@pytest.fixture(scope="module")
def versions(drive_scans):
    """The map after each scan."""
    builder = MapBuilder(RES, tile_size=TILE, step=STEP)
    out = []
    for points, pose in drive_scans:
        out.append(builder.add(points, pose).encode())
    return out


def frames_of(sender: Sender, now: float = 0.0) -> list[bytes]:
    return sender.poll(now)


class Growing:
    """A map growing on the rover's side, one scan at each event, and every version it took."""

    def __init__(self, ends: Ends, scans, *, every: float = 1.0, start: float = 0.0):
        self.ends, self.scans = ends, scans
        self.builder = MapBuilder(RES, tile_size=TILE, step=STEP)
        self.by_version: dict[int, bytes] = {}
        self.events = [(start + n * every, self._add(n)) for n in range(len(scans))]

    def _add(self, n):
        def add():
            data = self.builder.add(*self.scans[n]).encode()
            self.by_version[self.ends.sender.update(data)] = data
        return add


def run_drive(scans, *, downlink: Channel, uplink: Channel | None = None, rate: float = 2000.0, every: float = 1.0,
              sender=None, receiver=None, extra=(), until=900.0):
    ends = Ends(sender or Sender(max_frame_bytes=FRAME), receiver or Receiver(max_frame_bytes=FRAME))
    grow = Growing(ends, scans, every=every)
    result = run_link(ends, downlink=downlink, uplink=uplink or Channel(seed=99), budget=Budget(rate),
                      events=grow.events + list(extra), until=until)
    return ends, grow, result


def assert_same_at_every_version(ends, grow, result):
    assert result.converged, (result, ends.sender.counts, ends.receiver.refused)
    assert ends.receiver.data == grow.builder.encode()
    for version, _t, sha in result.applied:  # every version the ground took is byte for byte the rover's
        assert hashlib.sha256(grow.by_version[version]).digest() == sha
    assert [v for v, *_ in result.applied] == sorted({v for v, *_ in result.applied})


# -- frames -----------------------------------------------------------------------------------------------------


def test_the_document_alone_reads_the_frames_and_rebuilds_the_change(versions):
    a, b = versions[5], versions[9]
    sender = Sender(max_frame_bytes=FRAME, map_id=77)
    sender.update(a)
    sender.receive(pack_ack(Ack(0, 1, 1, 0, hashlib.sha256(b"").digest(), 0, 0)))
    whole = frames_of(sender)
    assert spec_decoder.link_rebuild(b"", whole) == a
    receiver = Receiver(max_frame_bytes=FRAME)
    for frame in whole:
        receiver.receive(frame)
    assert receiver.data == a and receiver.version == 1
    ack = receiver.poll(0.0)[0]
    sender.receive(ack)
    sender.update(b)
    change = frames_of(sender, 1.0)
    fields = [spec_decoder.link_frame(f) for f in change]
    assert {f["base_version"] for f in fields} == {1} and {f["target_version"] for f in fields} == {2}
    assert {f["base_check"] for f in fields} == {hashlib.sha256(a).digest()[:8]}
    assert spec_decoder.link_rebuild(a, change[::-1] + change[:3]) == b  # any order, repeats
    parsed = spec_decoder.link_frame(ack)
    assert parsed["kind"] == "ack" and parsed["map_id"] == 77 and parsed["version"] == 1
    assert parsed["sha256"] == hashlib.sha256(a).digest()
    with pytest.raises(ValueError, match="base check"):
        spec_decoder.link_rebuild(versions[4], change)


def test_an_ack_with_reports_reads_the_same_in_the_library_and_the_document():
    ack = Ack(5, 7, 3, 2, bytes(range(32)), 2, 4, {0: (3, frozenset({0, 1, 2})), 9: (11, frozenset({0, 3, 10}))})
    data = pack_ack(ack)
    assert read_frame(data) == ack
    doc = spec_decoder.link_frame(data)
    assert doc["reports"] == {0: (3, {0, 1, 2}), 9: (11, {0, 3, 10})}
    assert (doc["epoch"], doc["sequence"], doc["base_version"], doc["target_version"]) == (7, 3, 2, 4)


def test_no_frame_exceeds_its_size_and_tiles_span_frames(versions):
    for size in (64, 150, 1000):
        sender = Sender(max_frame_bytes=size)
        sender.update(versions[-1])
        frames = frames_of(sender)
        assert max(len(f) for f in frames) <= size
        assert any(read_frame(f).parts > 1 and read_frame(f).item for f in frames) == (size < 300)
        assert spec_decoder.link_rebuild(b"", frames) == versions[-1]
    with pytest.raises(InvalidInputError, match="at least 64"):
        Sender(max_frame_bytes=63)


def test_a_change_copies_the_tiles_the_base_has_and_is_smaller_than_the_whole_map(versions):
    a, b = versions[12], versions[13]
    plan, items = make_change(a, b)
    whole_plan, whole_items = make_change(b"", b)
    change = len(plan) + sum(map(len, items.values()))
    whole = len(whole_plan) + sum(map(len, whole_items.values()))
    assert 0 < len(items) < len(whole_items)
    assert change < 0.6 * whole, (change, whole)


def test_tiles_go_newest_first_after_the_plan():
    builder = MapBuilder(RES, tile_size=TILE, step=STEP)
    for scan in drive(3, seed=4):
        builder.add(*scan)
    first = builder.encode()
    for scan in drive(3, start=(40.0, 0.0), seed=5):  # new ground far away: the first tiles keep their bytes
        builder.add(*scan)
    second = builder.encode()
    sender = Sender(max_frame_bytes=FRAME)
    sender.update(first)
    sender.update(second)  # the ground has nothing: the whole map, the tiles of the second version first
    frames = [read_frame(f) for f in frames_of(sender)]
    assert frames[0].item == 0 and all(f.item == 0 for f in frames[:frames[0].parts])
    old = set(make_change(b"", first)[1].values())
    _plan, items = make_change(b"", second)
    order = list(dict.fromkeys(f.item for f in frames if f.item))
    assert sorted(order) == sorted(items)
    ages = [items[k] in old for k in order]  # True: a tile of the first version
    assert ages == sorted(ages) and not ages[0] and ages[-1], ages  # every new tile before every old one
    for age in (False, True):  # within one age, in tile order
        same = [k for k, a in zip(order, ages) if a == age]
        assert same == sorted(same)


def test_the_budget_holds_in_every_window_and_held_frames_wait():
    budget = Budget(1000.0, window=2.0)
    sent = []
    t = 0.0
    while t < 20.0:
        if budget.fits(t, 300):
            budget.spend(t, 300)
            sent.append(t)
        t = round(t + 0.01, 2)
    for start in sent:
        assert sum(300 for s in sent if start <= s < start + 2.0) <= 2000
    assert len(sent) * 300 >= 0.9 * 1000 * 20  # and it is used, not starved


# -- the link, simulated ----------------------------------------------------------------------------------------


def test_ten_percent_loss_duplicates_and_reordering_end_byte_identical(drive_scans):
    down = Channel(seed=1, loss=0.1, duplicate=0.1, reorder=0.2, delay=0.2, jitter=0.3)
    up = Channel(seed=2, loss=0.1, duplicate=0.1, reorder=0.2, delay=0.2, jitter=0.3)
    ends, grow, result = run_drive(drive_scans, downlink=down, uplink=up)
    assert_same_at_every_version(ends, grow, result)
    assert down.lost > 0 and ends.receiver.counts["duplicate"] > 0 and ends.sender.counts["resent"] > 0
    assert not ends.receiver.refused  # loss and repeats are no refusal: nothing bad arrived
    # Loss costs resends, not whole maps: every change after the first starts from a version the ground has.
    assert ends.sender.counts["changes"] <= len(result.applied) + 1


def test_a_part_an_acknowledgement_lacks_a_round_trip_later_is_sent_again_before_the_retry_time(drive_scans):
    # The retry time alone would resend a lost frame after 60 s; the acknowledgements show the loss within
    # a few round trips (0.4 s here), so the ground has the newest map long before that.
    sender = Sender(max_frame_bytes=FRAME, retry_after=60.0)
    ends, grow, result = run_drive(drive_scans, downlink=Channel(seed=12, loss=0.1, delay=0.2),
                                   uplink=Channel(seed=13, delay=0.2), sender=sender)
    assert_same_at_every_version(ends, grow, result)
    assert sender.counts["resent"] > 0 and result.seconds < 60.0, (result.seconds, sender.counts)


def test_the_budget_is_never_exceeded_on_the_link(drive_scans):
    rate, window = 1500.0, 10.0

    class Logged(Channel):
        def send(self, frame, now):
            log.append((now, len(frame)))
            super().send(frame, now)

    log: list[tuple[float, int]] = []
    ends, grow, result = run_drive(drive_scans, downlink=Logged(seed=3, loss=0.1), rate=rate)
    assert result.converged and ends.receiver.data == grow.builder.encode()
    assert max(n for _, n in log) <= FRAME
    for start, _ in log:
        assert sum(n for t, n in log if start <= t < start + window) <= rate * window


def test_a_sixty_second_outage_is_recovered_from_the_confirmed_version(drive_scans):
    class Logged(Channel):
        def send(self, frame, now):
            log.append((now, len(frame)))
            super().send(frame, now)

    log: list[tuple[float, int]] = []
    down = Logged(seed=4, loss=0.05, outages=[(6.0, 66.0)])
    up = Channel(seed=5, outages=[(6.0, 66.0)])
    ends, grow, result = run_drive(drive_scans, downlink=down, uplink=up)
    assert_same_at_every_version(ends, grow, result)
    assert result.seconds > 66.0 and down.lost > 0
    before = [v for v, t, _ in result.applied if t < 6.0]
    after = [v for v, t, _ in result.applied if t >= 66.0]
    assert before and after and after[-1] == ends.sender.version
    # The versions of the outage were skipped: the ground went from what it had to the newest.
    assert len(after) <= 3
    # Silent for 12 s, the sender only probes: one frame per retry time, not the budget's 2 kB/s.
    quiet = [n for t, n in log if 6.0 + 12.0 + 3.0 < t < 66.0]
    assert ends.sender.counts["probes"] > 0 and len(quiet) <= (66.0 - 21.0) / 3.0 + 1, quiet


def test_a_map_growing_faster_than_the_budget_skips_versions_and_ends_equal(drive_scans):
    ends, grow, result = run_drive(drive_scans, downlink=Channel(seed=6, loss=0.1), rate=300.0, every=0.5)
    assert_same_at_every_version(ends, grow, result)
    assert len(result.applied) < len(drive_scans) / 2  # versions skipped, not queued


def test_a_restarted_sender_resumes_from_the_confirmed_version(tmp_path, drive_scans):
    state = tmp_path / "map.dftpc.link"
    ends = Ends(Sender(max_frame_bytes=FRAME, state=state), Receiver(max_frame_bytes=FRAME))
    grow = Growing(ends, drive_scans)
    restarted: list[Sender] = []

    def restart():
        new = Sender(max_frame_bytes=FRAME, state=state)
        assert new.map_id == ends.sender.map_id and new.ground == ends.receiver.version > 0
        new.update(grow.builder.encode())
        restarted.append(new)
        ends.sender = new

    result = run_link(ends, downlink=Channel(seed=7, loss=0.1), uplink=Channel(seed=8, loss=0.1),
                      budget=Budget(2000.0), events=grow.events + [(10.5, restart)])
    assert result.converged and ends.receiver.data == grow.builder.encode()
    assert restarted and ends.sender is restarted[0]
    # after the restart, every change starts from a version the ground holds: never the whole map again
    assert restarted[0].history and all(base > 0 for base, _ in restarted[0].history), restarted[0].history


def test_a_restarted_ground_reads_its_map_and_asks_from_it(tmp_path, drive_scans):
    path = tmp_path / "ground.dftpc"
    ends = Ends(Sender(max_frame_bytes=FRAME), Receiver(path, max_frame_bytes=FRAME))
    grow = Growing(ends, drive_scans)
    seen = {}

    def restart():
        old = ends.receiver
        new = Receiver(path, max_frame_bytes=FRAME)
        assert (new.version, new.data, new.map_id) == (old.version, old.data, old.map_id) and new.version > 0
        assert new.epoch != old.epoch
        seen["version"] = new.version
        ends.receiver = new

    result = run_link(ends, downlink=Channel(seed=9, loss=0.1), uplink=Channel(seed=10, loss=0.1),
                      budget=Budget(2000.0), events=grow.events + [(12.3, restart)])
    assert result.converged and ends.receiver.data == grow.builder.encode() == path.read_bytes()
    assert seen["version"] > 0 and ends.sender.counts["changes"] <= len(result.applied) + 2


def test_a_wrong_base_makes_the_ground_ask_and_the_sender_send_from_what_it_holds(versions):
    sender = Sender(max_frame_bytes=FRAME)
    receiver = Receiver(max_frame_bytes=FRAME)
    for v in versions[:4]:
        sender.update(v)
    for f in frames_of(sender):
        receiver.receive(f)
    sender.receive(receiver.poll(0.0)[0])
    assert receiver.data == versions[3] and sender.ground == 4
    # The ground's map is replaced behind the sender's back by one the sender never had.
    other = MapBuilder(RES, tile_size=TILE, step=STEP).add(*drive(2, seed=11)[0]).encode()
    receiver.data, receiver.sha256, receiver.version = other, hashlib.sha256(other).digest(), 4
    sender.update(versions[6])
    change = frames_of(sender, 1.0)
    assert {read_frame(f).base_version for f in change} == {4}
    for f in change:
        receiver.receive(f, 1.0)
    assert receiver.refused["wrong base"] == len(change) and receiver.data == other  # nothing applied
    sender.receive(receiver.poll(2.0)[0])  # it says what it holds: unknown to the sender
    whole = frames_of(sender, 2.0)
    assert {read_frame(f).base_version for f in whole} == {0}
    for f in whole:
        receiver.receive(f, 2.0)
    assert receiver.data == versions[6] and receiver.version == sender.version


def test_a_ground_behind_gets_the_change_from_its_version_not_the_whole_map(versions):
    sender = Sender(max_frame_bytes=FRAME)
    receiver = Receiver(max_frame_bytes=FRAME)
    sender.update(versions[8])
    for f in frames_of(sender):
        receiver.receive(f)
    sender.receive(receiver.poll(0.0)[0])
    for v in versions[9:]:
        sender.update(v)
    change = frames_of(sender, 1.0)
    assert {read_frame(f).base_version for f in change} == {1}
    whole = Sender(max_frame_bytes=FRAME)
    whole.update(versions[-1])
    assert sum(map(len, change)) < sum(map(len, frames_of(whole)))  # eleven scans later, most tiles changed
    plan, items = make_change(versions[8], versions[-1])
    assert len(items) < len(make_change(b"", versions[-1])[1])
    for f in change:
        receiver.receive(f, 1.0)
    assert receiver.data == versions[-1]


def test_stale_and_other_maps_acks_do_not_move_the_sender(versions):
    sender = Sender(max_frame_bytes=FRAME, map_id=5)
    sender.update(versions[2])
    a_sha = hashlib.sha256(versions[2]).digest()
    assert sender.receive(pack_ack(Ack(5, 9, 2, 1, a_sha, 0, 0)))
    assert sender.ground == 1
    assert not sender.receive(pack_ack(Ack(5, 9, 1, 0, hashlib.sha256(b"").digest(), 0, 0)))  # late
    assert not sender.receive(pack_ack(Ack(6, 9, 3, 0, hashlib.sha256(b"").digest(), 0, 0)))  # another map
    assert sender.ground == 1 and sender.counts["stale"] == 1 and sender.counts["another map"] == 1
    assert sender.receive(pack_ack(Ack(5, 10, 1, 0, hashlib.sha256(b"").digest(), 0, 0)))  # a restarted ground
    assert sender.ground == 0


def test_bad_frames_are_counted_logged_once_and_never_reach_the_map(versions, caplog):
    sender = Sender(max_frame_bytes=FRAME, map_id=3)
    sender.update(versions[4])
    good = frames_of(sender)
    receiver = Receiver(max_frame_bytes=FRAME)
    cut = good[1][:-7]
    flipped = bytearray(good[1])
    flipped[40] ^= 0x10
    f = read_frame(good[0])
    other_map = pack_data(DataFrame(4, f.base_version, f.target_version, f.base_check, 0, 0, 1, b"x"))
    oversized = pack_data(DataFrame(3, 0, 1, f.base_check, 0, 0, 1, bytes(FRAME)))
    bad_plan = pack_data(DataFrame(3, 0, 9, f.base_check, 0, 0, 1, b"not zstd"))
    with caplog.at_level(logging.WARNING, logger="dftpcc.link"):
        for frame in [good[0], cut, cut, bytes(flipped), bytes(flipped), other_map, oversized, bad_plan,
                      pack_ack(Ack(3, 1, 1, 0, bytes(32), 0, 0)), b"", b"\x89DL"]:
            assert receiver.receive(frame) is None
    assert receiver.data == b"" and receiver.version == 0
    assert receiver.refused == {"crc": 4, "another map": 1, "oversized": 1, "plan": 1, "kind": 1, "truncated": 2}
    assert len(caplog.records) == len(receiver.refused)  # once per cause
    for frame in good:  # the genuine frames still make the map
        receiver.receive(frame)
    assert receiver.data == versions[4]


def test_a_stray_item_before_the_plan_costs_itself_not_the_change(versions):
    sender = Sender(max_frame_bytes=FRAME, map_id=3)
    sender.update(versions[4])
    good = frames_of(sender)
    f = read_frame(good[0])
    stray = pack_data(DataFrame(3, f.base_version, f.target_version, f.base_check, 4000, 0, 1, b"junk"))
    receiver = Receiver(max_frame_bytes=FRAME)
    receiver.receive(stray)
    for frame in good:
        receiver.receive(frame)
    assert receiver.refused["item"] == 1 and receiver.data == versions[4]


def test_a_frame_the_plan_does_not_name_is_refused(versions):
    sender = Sender(max_frame_bytes=FRAME, map_id=3)
    sender.update(versions[4])
    good = frames_of(sender)
    receiver = Receiver(max_frame_bytes=FRAME)
    f = read_frame(good[0])
    for frame in good[:f.parts]:
        receiver.receive(frame)
    stray = pack_data(DataFrame(3, f.base_version, f.target_version, f.base_check, 4000, 0, 1, b"junk"))
    receiver.receive(stray)
    assert receiver.refused["item"] == 1
    for frame in good:
        receiver.receive(frame)
    assert receiver.data == versions[4]


def test_frame_fuzz_never_crashes_and_never_applies_a_wrong_map():
    report = fuzz_run(FUZZ_INPUTS, seed=3)
    assert report["iterations"] == FUZZ_INPUTS
    assert report["outcomes"].get("refused", 0) > 0 and report["outcomes"].get("applied", 0) > 0, report


def test_payload_size_is_the_frame_size_minus_the_head(versions):
    sender = Sender(max_frame_bytes=200)
    sender.update(versions[1])
    frames = frames_of(sender)
    assert all(len(read_frame(f).payload) <= 200 - DATA_OVERHEAD for f in frames)
    assert any(len(f) == 200 for f in frames)
    with pytest.raises(FrameError) as refused:
        read_frame(frames[0], max_bytes=len(frames[0]) - 1)
    assert refused.value.cause == "oversized"


def test_a_plan_declaring_far_more_than_its_bytes_is_refused_unread():
    import zstandard

    from dftpcc.link import read_plan

    bomb = zstandard.ZstdCompressor(write_content_size=True).compress(bytes(50_000_000))
    assert len(bomb) < 10_000
    with pytest.raises(FrameError, match="declaring 50,000,000"):
        read_plan(bomb, base_size=0)
    with pytest.raises(ValueError, match="declares more"):
        spec_decoder.link_plan(bomb, 0)


def test_a_new_missions_map_is_refused_with_one_line_naming_the_option_or_archived(tmp_path, versions, caplog):
    path = tmp_path / "ground.dftpc"
    old, new = Sender(max_frame_bytes=FRAME), Sender(max_frame_bytes=FRAME)
    old.update(versions[3])
    ground = Receiver(path, max_frame_bytes=FRAME)
    for f in frames_of(old):
        ground.receive(f)
    assert path.read_bytes() == versions[3]
    other = MapBuilder(RES, tile_size=TILE, step=STEP).add(*drive(2, seed=11)[0]).encode()
    new.update(other)
    change = frames_of(new)
    assert len(change) > 2
    with caplog.at_level(logging.WARNING, logger="dftpcc.link"):
        for f in change:
            assert ground.receive(f) is None
    assert ground.refused["another map"] > 1 and path.read_bytes() == versions[3]
    lines = [r.getMessage() for r in caplog.records if "another map" in r.getMessage()]
    assert len(lines) == 1 and "--new-maps archive" in lines[0]
    # Restarted to take new missions: the old map stays until the new one's first version is whole.
    ground = Receiver(path, max_frame_bytes=FRAME, new_maps="archive")
    assert ground.receive(change[0]) is None and path.read_bytes() == versions[3]
    # Its acknowledgement speaks to the new map's sender, which learns the ground holds none of it.
    assert new.receive(ground.poll(2.0)[0]) and new.ground == 0
    assert [ground.receive(f) for f in change[1:]][-1] == new.version
    kept = tmp_path / f"ground.{old.map_id:016x}.dftpc"
    assert path.read_bytes() == other and kept.read_bytes() == versions[3]
    assert Receiver(path).map_id == new.map_id and Receiver(kept).map_id == old.map_id
    # The old map, put aside, is not taken again: not a change from a version of it, nor a whole one.
    old.update(versions[5])
    for f in frames_of(old, 3.0):
        assert ground.receive(f) is None
    ground = Receiver(path, max_frame_bytes=FRAME, new_maps="archive")
    again = Sender(max_frame_bytes=FRAME, map_id=old.map_id)  # the old rover, restarted: a whole version
    again.update(versions[5])
    for f in frames_of(again):
        assert ground.receive(f) is None
    assert path.read_bytes() == other and ground.refused["another map"] > 0
    with pytest.raises(InvalidInputError, match="new_maps"):
        Receiver(path, new_maps="yes")


def test_a_sender_restarted_before_hearing_the_ground_applied_a_change_sends_from_that_change(tmp_path, versions):
    # The ground applied the change, but its acknowledgement never reached the rover before it
    # crashed: the restarted sender holds the change's target (STATE.target) and sends from it.
    state = tmp_path / "map.dftpc.link"
    sender, ground = Sender(max_frame_bytes=FRAME, state=state), Receiver(max_frame_bytes=FRAME)
    sender.update(versions[3])
    for f in frames_of(sender):
        ground.receive(f)
    assert sender.receive(ground.poll(0.0)[0]) and sender.ground == 1
    sender.update(versions[6])
    for f in frames_of(sender, 1.0):
        ground.receive(f)
    assert ground.data == versions[6]  # its acknowledgement is lost
    again = Sender(max_frame_bytes=FRAME, state=state)
    again.update(versions[8])
    assert again.receive(ground.poll(5.0)[0]) and again.ground == 2
    change = frames_of(again, 6.0)
    assert {read_frame(f).base_version for f in change} == {2}
    for f in change:
        ground.receive(f)
    assert ground.data == versions[8]
    whole = Sender(max_frame_bytes=FRAME)
    whole.update(versions[8])
    assert sum(map(len, change)) < sum(map(len, frames_of(whole)))


def test_a_large_change_carries_a_preview_after_its_plan_which_never_reaches_the_map(drive_scans):
    builder = MapBuilder(RES, tile_size=TILE, step=STEP)
    for points, pose in drive_scans[:12]:
        builder.add(points, pose)
    data = builder.encode()
    preview = builder.preview()
    assert 0 < len(preview) < 0.25 * len(data)
    sender = Sender(max_frame_bytes=FRAME, preview_over=1000)
    sender.update(data, preview=builder.preview)
    frames = frames_of(sender)
    items = [read_frame(f).item for f in frames]
    k, n = items.index(PREVIEW_ITEM), items.count(PREVIEW_ITEM)
    assert set(items[:k]) == {0} and set(items[k:k + n]) == {PREVIEW_ITEM} and PREVIEW_ITEM not in items[k + n:]
    # The document alone: the change rebuilt without the preview, and the preview joined.
    assert spec_decoder.link_rebuild(b"", frames) == data
    assert spec_decoder.link_preview(frames[::-1]) == preview
    receiver = Receiver(max_frame_bytes=FRAME)
    for f in frames[:k + n]:  # the plan and the preview only
        assert receiver.receive(f) is None
    assert receiver.preview == (1, preview, sender.map_id) and receiver.data == b""
    coarse = dftpcc.decompress(receiver.preview[1])
    assert coarse.shape[0] > 0 and np.isfinite(coarse).all()
    for f in frames:
        receiver.receive(f)
    assert receiver.data == data
    # A small change, or none asked for: no preview.
    for over in (None, 10 * len(data)):
        quiet = Sender(max_frame_bytes=FRAME, preview_over=over)
        quiet.update(data, preview=builder.preview)
        assert PREVIEW_ITEM not in {read_frame(f).item for f in frames_of(quiet)}
