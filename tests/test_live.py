"""The rover's and ground's cores (dftpcc.live): scans placed by odometry, bad input counted and kept out of the map."""

from __future__ import annotations

import numpy as np
import pytest

from dftpcc.errors import InvalidInputError
from dftpcc.link import Budget, Sender
from dftpcc.linksim import Channel
from dftpcc.live import NS, GroundCore, RoverCore
from dftpcc.mapbuilder import MapBuilder

from .test_mapbuilder import RES, STEP, TILE, drive

FRAME = 500


def quaternion(rotation: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(rotation).as_quat()


def new_rover(tmp_path, name="map.dftpc", **kw) -> RoverCore:
    return RoverCore(tmp_path / name, resolution=RES, rate=2000.0, max_frame_bytes=FRAME, step=STEP, tile_size=TILE,
                     log=kw.pop("log", lambda cause, message: None), **kw)


def feed(rover: RoverCore, scans, *, t0: float = 1.0, every: float = 0.1) -> None:
    """Each scan with a pose just before and just after its stamp (the same pose): placed exactly."""
    for k, (points, (rotation, translation)) in enumerate(scans):
        stamp = int((t0 + k * every) * NS)
        q = quaternion(rotation)
        rover.add_pose(stamp - NS // 100, translation, q)
        rover.add_pose(stamp + NS // 100, translation, q)
        assert rover.add_scan(stamp, points, "lidar")


def test_scans_placed_by_odometry_give_the_map_of_their_poses(tmp_path):
    scans = drive(5)
    rover = new_rover(tmp_path)
    feed(rover, scans)
    expected = MapBuilder(RES, tile_size=TILE, step=STEP)
    for points, pose in scans:
        expected.add(points, pose)
    assert (tmp_path / "map.dftpc").read_bytes() == expected.encode()
    assert rover.scans == 5 and not rover.refused.counts


def test_bad_input_is_counted_logged_once_and_kept_out_of_the_map(tmp_path):
    logged = []
    scans = drive(4)
    rover = new_rover(tmp_path, log=lambda cause, message: logged.append(cause))
    feed(rover, scans[:2])
    before = (tmp_path / "map.dftpc").read_bytes()
    points, (rotation, translation) = scans[2]
    q = quaternion(rotation)
    last = int((1.0 + 0.1) * NS)
    assert not rover.add_scan(last - 1, points, "lidar")  # stamp back
    assert not rover.add_scan(last - 2, points, "lidar")
    assert not rover.add_scan(last + NS, np.full((10, 3), np.nan), "lidar")  # only NaN points
    rover.add_pose(last - NS, translation, q)  # a pose stamp back
    rover.add_pose(last + 2 * NS, translation, q * 2)  # not a unit quaternion
    rover.add_pose(last + 2 * NS, translation, q)
    rover.add_pose(last + 4 * NS, translation, q)  # two seconds without a pose before it
    assert not rover.add_scan(last + 3 * NS, points, "lidar")  # in the gap
    assert (tmp_path / "map.dftpc").read_bytes() == before  # nothing of it reached the map
    with_nan = np.vstack([points, np.full((7, 3), np.nan)])
    rover.add_pose(last + 4 * NS + NS // 100, translation, q)
    assert rover.add_scan(last + 4 * NS + NS // 200, with_nan, "lidar")  # the finite points only
    expected = MapBuilder(RES, tile_size=TILE, step=STEP)
    for p, pose in scans[:3]:
        expected.add(p, pose)
    assert (tmp_path / "map.dftpc").read_bytes() == expected.encode()
    assert rover.refused.counts == {"scan stamp back": 2, "empty scan": 1, "nan points": 17, "pose stamp back": 1,
                                    "bad pose": 1, "pose gap": 1}
    assert sorted(logged) == sorted(rover.refused.counts)  # each cause once


def test_a_scan_waits_for_the_pose_after_it_then_gives_up(tmp_path):
    scans = drive(3)
    rover = new_rover(tmp_path)
    points, (rotation, translation) = scans[0]
    q = quaternion(rotation)
    rover.add_pose(NS, translation, q)
    assert not rover.add_scan(NS + NS // 20, points, "lidar")  # no pose after it yet: waits
    rover.add_pose(NS + NS // 10, translation, q)
    assert rover.scans == 1  # placed when the pose came
    assert not rover.add_scan(3 * NS, points, "lidar")
    assert rover.add_scan(5 * NS, points, "map")  # placed already; the waiting one is given up
    rover.add_pose(6 * NS, translation, q)
    assert rover.refused.counts["pose gap"] == 1 and rover.scans == 2


def test_the_cores_over_a_bad_link_end_byte_identical_and_resume(tmp_path):
    scans = drive(10, heading=0.3)
    rover = new_rover(tmp_path, "rover.dftpc")
    ground = GroundCore(tmp_path / "ground.dftpc", max_frame_bytes=FRAME)
    down, up = Channel(seed=1, loss=0.1), Channel(seed=2, loss=0.1)
    now = 0.0
    for k in range(400):
        now = k * 0.1
        if k < len(scans):
            feed(rover, [scans[k]], t0=now + 1.0)
        if k == 12:  # the rover restarts from its files
            rover = new_rover(tmp_path, "rover.dftpc")
        for f in up.deliver(now):
            rover.acknowledge(f)
        for f in rover.frames(now):
            down.send(f, now)
        for f in down.deliver(now):
            ground.frame(f, now)
        for f in ground.acks(now):
            up.send(f, now)
    assert (tmp_path / "ground.dftpc").read_bytes() == (tmp_path / "rover.dftpc").read_bytes()
    cloud = ground.points()
    assert cloud.dtype == np.float32 and cloud.shape[0] > 1000 and np.isfinite(cloud).all()


def test_a_frame_larger_than_the_budget_window_is_refused(tmp_path):
    with pytest.raises(InvalidInputError, match="does not fit a budget"):
        RoverCore(tmp_path / "m.dftpc", resolution=RES, rate=10.0, max_frame_bytes=500, window=10.0)
    assert Budget(10.0).limit == 100


def test_versions_come_at_their_cadence_and_flush_makes_the_last(tmp_path):
    scans = drive(9)
    rover = new_rover(tmp_path, version_every=0.35)
    feed(rover, scans)  # stamps 0.1 s apart: versions at scans 0, 4 and 8
    assert rover.scans == 9 and rover.sender.version == 3 and len(rover.version_seconds) == 3
    assert not rover.flush()  # nothing added since scan 8
    feed(rover, drive(2, start=(30.0, 0.0), seed=3), t0=5.0)  # scan at 5.0 s makes a version, 5.1 s waits
    assert rover.sender.version == 4
    assert rover.flush() and rover.sender.version == 5
    expected = MapBuilder(RES, tile_size=TILE, step=STEP)
    for p, pose in scans + drive(2, start=(30.0, 0.0), seed=3):
        expected.add(p, pose)
    assert (tmp_path / "map.dftpc").read_bytes() == expected.encode()
    with pytest.raises(InvalidInputError, match="version_every"):
        new_rover(tmp_path, "other.dftpc", version_every=-1.0)


def test_the_map_is_written_at_its_cadence_and_a_crash_resumes_from_the_last_write(tmp_path):
    scans = drive(8)
    rover = new_rover(tmp_path, save_every=0.35)  # versions after every scan, writes every 0.35 s of stamps
    feed(rover, scans[:6])  # stamps 1.0 ... 1.5 s: written at scans 0 and 4
    assert rover.sender.version == 6 and rover.saves == 2
    written = (tmp_path / "map.dftpc").read_bytes()
    on_disk = MapBuilder(RES, tile_size=TILE, step=STEP)
    for p, pose in scans[:5]:
        on_disk.add(p, pose)
    assert written == on_disk.encode()  # the fifth scan's version, not the sixth
    # A crash now: the restarted rover resumes the map written, with its link state.
    again = new_rover(tmp_path)
    assert again.sender.map_id == rover.sender.map_id and again.sender.version == 7
    assert again.builder.encode() == written
    feed(again, scans[6:], t0=2.0)
    assert again.save() is False  # written at every version (save_every 0)
    for p, pose in scans[6:]:
        on_disk.add(p, pose)
    assert (tmp_path / "map.dftpc").read_bytes() == on_disk.encode()
    with pytest.raises(InvalidInputError, match="save_every"):
        new_rover(tmp_path, "other.dftpc", save_every=float("nan"))


def test_a_rover_restarted_behind_the_ground_sends_a_change_from_the_grounds_map(tmp_path):
    # The rover writes its map rarely (save_every), so after a crash it resumes a map older than the
    # version the ground holds: the link must send from the ground's map (kept as MAP.link.base), not
    # the whole map.
    scans = drive(12, heading=0.3)
    rover = new_rover(tmp_path, "rover.dftpc", save_every=0.35)  # written at scans 0 and 4
    ground = GroundCore(tmp_path / "ground.dftpc", max_frame_bytes=FRAME)
    budget_free = Budget(1e9)

    def exchange(rover, now):
        for f in rover.sender.poll(now, budget_free):
            ground.frame(f, now)
        for f in ground.acks(now):
            rover.acknowledge(f)

    feed(rover, scans[:6])
    for k in range(20):
        exchange(rover, 0.1 * k)
    assert ground.receiver.version == rover.sender.version == 6
    assert (tmp_path / "rover.dftpc").read_bytes() != ground.receiver.data  # the ground has scan 5, the disk not
    again = new_rover(tmp_path, "rover.dftpc", save_every=0.35)  # the crash: resumed from scan 4's version
    feed(again, scans[6:], t0=3.0)
    sent = again.sender.counts
    for k in range(40):
        exchange(again, 5.0 + 0.1 * k)
    assert ground.receiver.data == again.sender._versions[again.sender.version]
    assert again.sender.history and all(base == 6 for base, _target in again.sender.history)
    whole = Sender(max_frame_bytes=FRAME)  # the same map to a ground that holds nothing
    whole.update(ground.receiver.data)
    # Scan 5's tiles, and those of the scans after the crash, travel again; the tiles of scans 0-4
    # only are copies.
    assert sent["bytes"] < sum(len(f) for f in whole.poll(0.0))


def test_a_rover_with_a_bound_sends_versions_within_it(tmp_path):
    """``target_max_error`` reaches every version: the map the rover keeps (and sends) is the one
    MapBuilder codes at that bound, the file states the bound, and a bad bound is refused before
    anything is made."""
    import dftpcc

    bound = 0.002  # below what the cutoff alone keeps on this rolling ground: residual layers
    scans = drive(5)
    rover = new_rover(tmp_path, target_max_error=bound, version_every=0.0)
    feed(rover, scans)
    expected = MapBuilder(RES, tile_size=TILE, step=STEP)
    for points, pose in scans:
        expected.add(points, pose)
    data = (tmp_path / "map.dftpc").read_bytes()
    assert data == expected.encode(target_max_error=bound)
    with dftpcc.open(data) as cmap:
        info = cmap.info()
        assert cmap.params.target_max_error == bound and info["stats"]["residual_bytes"] > 0
        assert info["stats"]["dem_max_error_m"] <= bound
    resumed = new_rover(tmp_path)  # no bound given: the map's own is kept
    assert resumed.builder.params.target_max_error == bound
    with pytest.raises(InvalidInputError, match="target_max_error"):
        new_rover(tmp_path, name="other.dftpc", target_max_error=-0.1)
    assert not (tmp_path / "other.dftpc").exists()
