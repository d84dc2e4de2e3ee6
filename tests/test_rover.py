"""The simulated rover: surface, ray-caster, drives and ROS 2 bags (dftpcc.experiments.rover)."""

from __future__ import annotations

import math
import sys
import time

import numpy as np
import pytest

from dftpcc.errors import InvalidInputError, MissingDependencyError
from dftpcc.experiments import rover
from dftpcc.files import dem_from_geotiff

from .conftest import data_file

#: A short-range, sparse sensor so tests stay fast: 16 beams, 1 degree steps, 40 m.
SMALL_LIDAR = rover.Lidar(16, -15.0, 15.0, 1.0, 40.0, 0.5, 0.02, 1.5)


def plane(a: float = 0.1, b: float = -0.05, size: int = 120, spacing: float = 1.0) -> rover.Surface:
    i, j = np.mgrid[0:size, 0:size]
    x, y = (j + 0.5) * spacing, (i + 0.5) * spacing
    return rover.Surface(a * x + b * y, spacing)


@pytest.fixture(scope="module")
def gale() -> rover.Surface:
    dem, _ = dem_from_geotiff(data_file("dems/mars_gale_1m.tif"))
    return rover.Surface.from_dem(dem)


def test_surface_is_bilinear_and_undefined_outside():
    s = plane()
    x = np.array([0.5, 10.25, 60.0, 119.5, 0.4, 130.0])
    y = np.array([0.5, 33.75, 60.0, 119.5, 10.0, 10.0])
    h = s.height(x, y)
    np.testing.assert_allclose(h[:4], 0.1 * x[:4] - 0.05 * y[:4], atol=1e-12)
    assert np.isnan(h[4:]).all()  # before the first node, after the last
    # The slope bound holds the plane's gradient (to round-off).
    assert s.slope == pytest.approx(math.hypot(0.1, 0.05), rel=1e-9)


def test_flat_ground_ranges_are_exact():
    """A level sensor h above a flat plane: a beam at elevation e < 0 returns at h / sin(-e)."""
    s = rover.Surface(np.zeros((200, 200)), 1.0)
    lidar = rover.Lidar(8, -20.0, 15.0, 5.0, 80.0, 0.5, 0.0, 1.5)
    pose = rover.sensor_pose(s, 100.0, 100.0, 0.3, mount_height=1.5)
    pts = rover.cast_scan(s, pose, lidar)
    r = np.linalg.norm(pts, axis=1)
    elev = np.arcsin(pts[:, 2] / r)
    np.testing.assert_allclose(r, 1.5 / np.sin(-elev), rtol=1e-6)
    # Beams at or above the horizon, and those reaching beyond 80 m, return nothing.
    downward = np.radians(np.linspace(-20.0, 15.0, 8))
    expected = sum(1 for e in downward if e < 0 and 1.5 / math.sin(-e) <= 80.0) * 72
    assert pts.shape[0] == expected


def test_first_crossing_on_real_terrain(gale):
    """Every return lies on the Gale surface and is the first crossing: a brute-force march with 4 cm steps agrees."""
    pose = rover.sensor_pose(gale, 170.0, 160.0, 1.0, mount_height=1.5)
    lidar = rover.Lidar(16, -15.0, 15.0, 6.0, 100.0, 0.5, 0.0, 1.5)
    pts = rover.cast_scan(gale, pose, lidar)
    world = pts @ pose[:3, :3].T + pose[:3, 3]
    np.testing.assert_allclose(world[:, 2], gale.height(world[:, 0], world[:, 1]), atol=1e-5)
    dirs = lidar.directions() @ pose[:3, :3].T
    t = np.arange(lidar.min_range, lidar.max_range, 0.04)
    p = pose[:3, 3] + t[None, :, None] * dirs[:, None, :]
    below = p[..., 2] <= gale.height(p[..., 0], p[..., 1])
    hit = below.any(axis=1)
    first = np.where(hit, t[np.argmax(below, axis=1)], np.nan)
    # Match returns to rays by direction.
    ours = np.full(dirs.shape[0], np.nan)
    unit = pts / np.linalg.norm(pts, axis=1)[:, None]
    ray = np.argmax(unit @ lidar.directions().T, axis=1)
    ours[ray] = np.linalg.norm(pts, axis=1)
    both = np.isfinite(first) & np.isfinite(ours)
    assert both.sum() > 0.9 * hit.sum()
    # The brute force overshoots by at most one of its steps (0.04 m); only grazing rays may differ.
    assert np.mean(np.abs(ours[both] - first[both]) <= 0.045) > 0.99


def test_range_noise_has_the_stated_sigma():
    s = rover.Surface(np.zeros((200, 200)), 1.0)
    lidar = rover.Lidar(8, -20.0, -5.0, 1.0, 80.0, 0.5, 0.03, 1.5)
    pose = rover.sensor_pose(s, 100.0, 100.0, 0.0)
    exact = np.linalg.norm(rover.cast_scan(s, pose, lidar), axis=1)
    noisy = np.linalg.norm(rover.cast_scan(s, pose, lidar, rng=np.random.default_rng(4)), axis=1)
    assert noisy.shape == exact.shape
    assert np.std(noisy - exact) == pytest.approx(0.03, rel=0.1)


def test_raycaster_speed_is_reported(gale):
    """Prints the per-scan times of the 16- and 64-beam sensors (no timing assert; `pytest -rP` shows them)."""
    for name in ("vlp16", "hdl64"):
        lidar = rover.LIDARS[name]
        pose = rover.sensor_pose(gale, 170.0, 160.0, 0.0, mount_height=lidar.mount_height)
        t0 = time.perf_counter()
        pts = rover.cast_scan(gale, pose, lidar, rng=np.random.default_rng(0))
        # Captured like any test output: shown by `pytest -rP` or `-s`, not inside `pytest -q`'s dots.
        print(f"{name}: {lidar.directions().shape[0]} rays, {pts.shape[0]} returns, "
              f"{1000 * (time.perf_counter() - t0):.0f} ms")
        assert pts.shape[0] > 0.5 * lidar.directions().shape[0]


def test_drive_follows_the_ground_at_speed(gale):
    wp = [(150.0, 150.0), (160.0, 150.0), (160.0, 158.0)]
    d = rover.drive(gale, wp, speed=0.5, rate=10.0, lidar=SMALL_LIDAR)
    assert d.distance == pytest.approx(18.0, abs=0.05)
    assert d.times[-1] == pytest.approx(36.0, abs=0.1)
    # The sensor rides mount_height above the ground along the rover's up axis; below it, the
    # rover moves 5 cm per pose along the waypoints.
    feet = d.poses[:, :3, 3] - 1.5 * d.poses[:, :3, 2]
    steps = np.linalg.norm(np.diff(feet[:, :2], axis=0), axis=1)
    np.testing.assert_allclose(steps[steps > 0.049], 0.05, atol=1e-9)
    assert np.sum(steps <= 0.049) <= 1  # the corner
    np.testing.assert_allclose(feet[:, 2], gale.height(feet[:, 0], feet[:, 1]), atol=0.05)
    for pose in d.poses[::50]:
        np.testing.assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-12)


def test_drive_refusals(gale):
    with pytest.raises(InvalidInputError, match="leaves the map"):
        rover.drive(gale, [(150.0, 150.0), (400.0, 150.0)], lidar=SMALL_LIDAR, rate=2.0)
    clipped = rover.drive(gale, [(150.0, 150.0), (400.0, 150.0)], lidar=SMALL_LIDAR, clip=True, rate=2.0)
    assert clipped.clipped and clipped.poses[-1, 0, 3] < 347.5
    with pytest.raises(InvalidInputError, match="starts"):
        rover.drive(gale, [(-5.0, 150.0), (10.0, 150.0)], lidar=SMALL_LIDAR, clip=True)
    with pytest.raises(InvalidInputError, match="smaller than the simulated lidar's range"):
        rover.drive(plane(size=30), [(5.0, 5.0), (10.0, 5.0)], lidar=SMALL_LIDAR)
    holes = plane().heights.copy()
    holes[:, 50:60] = np.nan
    with pytest.raises(InvalidInputError, match="without data"):
        rover.drive(rover.Surface(holes, 1.0), [(20.0, 20.0), (100.0, 20.0)], lidar=SMALL_LIDAR)
    with pytest.raises(InvalidInputError, match="do not move"):
        rover.drive(gale, [(150.0, 150.0), (150.0, 150.0)], lidar=SMALL_LIDAR)
    with pytest.raises(InvalidInputError, match="no valid height"):
        rover.Surface(np.full((10, 10), np.nan), 1.0)


def test_bag_round_trip(gale, tmp_path):
    """A short drive: every topic, frame and rate as agreed; scans agree with the ground-truth odometry."""
    pytest.importorskip("rosbags")
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    d = rover.drive(gale, [(150.0, 150.0), (152.0, 150.0)], speed=0.5, lidar=SMALL_LIDAR)  # 4 s at 50 Hz
    info = rover.write_bag(tmp_path / "bag", gale, d, SMALL_LIDAR, scan_rate=1.0, seed=3)
    assert info["scans"] == 5
    ts = get_typestore(Stores.ROS2_HUMBLE)
    msgs: dict[str, list] = {}
    with Reader(tmp_path / "bag") as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        for conn, stamp, raw in reader.messages():
            msgs.setdefault(conn.topic, []).append((stamp, ts.deserialize_cdr(raw, conn.msgtype)))
    assert types == {"/points": "sensor_msgs/msg/PointCloud2", "/odom": "nav_msgs/msg/Odometry",
                     "/odom_noisy": "nav_msgs/msg/Odometry", "/tf": "tf2_msgs/msg/TFMessage"}
    assert len(msgs["/odom"]) == len(msgs["/odom_noisy"]) == len(msgs["/tf"]) == d.times.size == 201
    assert np.diff([s for s, _ in msgs["/odom"]]).tolist() == [20_000_000] * 200  # 50 Hz
    odom = {s: m for s, m in msgs["/odom"]}
    from scipy.spatial.transform import Rotation

    for stamp, cloud in msgs["/points"]:
        assert cloud.header.frame_id == "lidar" and cloud.is_dense
        pts = np.frombuffer(cloud.data, np.float32).reshape(-1, 3).astype(np.float64)
        o = odom[stamp]
        assert o.header.frame_id == "map" and o.child_frame_id == "lidar"
        q = o.pose.pose.orientation
        R = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
        t = np.array([o.pose.pose.position.x, o.pose.pose.position.y, o.pose.pose.position.z])
        world = pts @ R.T + t
        # Range noise 2 cm: points within 5 sigma of the ground (float32 adds ~1e-5 m).
        assert np.abs(world[:, 2] - gale.height(world[:, 0], world[:, 1])).max() < 0.1
    tf = msgs["/tf"][-1][1].transforms[0]
    assert tf.header.frame_id == "map" and tf.child_frame_id == "lidar"
    assert tf.transform.translation.x == pytest.approx(msgs["/odom"][-1][1].pose.pose.position.x)
    # Dead reckoning drifts but stays near the truth over 2 m.
    end_noisy = msgs["/odom_noisy"][-1][1].pose.pose.position
    end_true = msgs["/odom"][-1][1].pose.pose.position
    drift = math.hypot(end_noisy.x - end_true.x, end_noisy.y - end_true.y)
    assert 0 < drift < 0.5
    with pytest.raises(InvalidInputError, match="exists"):
        rover.write_bag(tmp_path / "bag", gale, d, SMALL_LIDAR)


def test_bag_without_rosbags(gale, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "rosbags.rosbag2", None)
    d = rover.drive(gale, [(150.0, 150.0), (151.0, 150.0)], lidar=SMALL_LIDAR)
    with pytest.raises(MissingDependencyError, match=r"dftpcc\[ros\]"):
        rover.write_bag(tmp_path / "bag", gale, d, SMALL_LIDAR)
    assert not (tmp_path / "bag").exists()


def test_script(tmp_path, capsys):
    """python -m dftpcc.experiments.rover: a bag from a DEM, and a drive off the map refused (exit 3) with no bag."""
    pytest.importorskip("rosbags")
    tif = str(data_file("dems/mars_gale_1m.tif"))
    assert rover.main([tif, str(tmp_path / "bag"), "--duration", "1", "--scan-rate", "2", "--radius", "20"]) == 0
    assert "3 scans" in capsys.readouterr().out
    assert (tmp_path / "bag" / "metadata.yaml").is_file()
    assert rover.main([tif, str(tmp_path / "off"), "--waypoints", "150,150;500,150"]) == 3
    assert "--clip" in capsys.readouterr().err
    assert not (tmp_path / "off").exists()


def test_bag_reads_back_as_a_map_with_its_poses(gale, tmp_path):
    """dftpcc's bag reader places the scans by /odom (the agreed conventions): the map lies on the terrain."""
    pytest.importorskip("rosbags")
    import dftpcc

    d = rover.drive(gale, [(150.0, 150.0), (151.0, 150.0)], speed=0.5, lidar=SMALL_LIDAR)
    rover.write_bag(tmp_path / "bag", gale, d, SMALL_LIDAR, scan_rate=1.0, seed=5)
    for poses in ("/odom", "/tf"):
        cloud = dftpcc.read(tmp_path / "bag", topic="/points", pose_topic=poses).points
        assert cloud.shape[0] > 1000
        # float32 points, 2 cm range noise: within 5 sigma of the ground everywhere.
        assert np.abs(cloud[:, 2] - gale.height(cloud[:, 0], cloud[:, 1])).max() < 0.1
