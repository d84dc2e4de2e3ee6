"""A map grown scan by scan (dftpcc.mapbuilder) and ``dftpcc update``."""

from __future__ import annotations

import hashlib
import math
import warnings

import numpy as np
import pytest

import dftpcc
from dftpcc.cli import main
from dftpcc.format.source import Source
from dftpcc.format.reader import read_tile
from dftpcc.format.reader import unpack_source
from dftpcc.errors import InvalidInputError
from dftpcc.mapbuilder import HEIGHT_QUANTUM_M, MapBuilder, StateRecoveredWarning, is_growing, state_path
from dftpcc.tiles import TILE_OVERLAP

#: Small settings so a test codes a map in a fraction of a second.
RES, TILE, STEP = 0.25, 32, 0.005


def terrain_z(xy: np.ndarray) -> np.ndarray:
    """Rolling ground with a slope, metres."""
    return 1.5 * np.sin(xy[:, 0] / 6.0) + np.cos(xy[:, 1] / 4.0) + 0.02 * xy[:, 0] + 100.0


def yaw_pose(yaw: float, t) -> tuple[np.ndarray, np.ndarray]:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.asarray(t, dtype=float)


def drive(n_scans: int, *, start=(0.0, 0.0), heading=0.3, speed=2.0, points=3000, reach=6.0, seed=0):
    """Scans of a rover driving straight: (points in the sensor frame, pose) each, the sensor 1.5 m up."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n_scans):
        t = np.array([start[0] + k * speed * math.cos(heading), start[1] + k * speed * math.sin(heading), 0.0])
        a, d = rng.random(points) * 2 * math.pi, reach * np.sqrt(rng.random(points))
        xy = t[:2] + np.c_[d * np.cos(a), d * np.sin(a)]
        world = np.c_[xy, terrain_z(xy) + 0.003 * rng.standard_normal(points)]
        t[2] = terrain_z(t[None, :2])[0] + 1.5
        rotation, translation = yaw_pose(heading + 0.1 * k, t)
        out.append(((world - translation) @ rotation, (rotation, translation)))  # p_sensor = R^T (p - t)
    return out


def in_map_frame(scans):
    return np.concatenate([p @ r.T + t for p, (r, t) in scans])


def new_builder(**kw):
    return MapBuilder(RES, tile_size=TILE, step=STEP, **kw)


def tile_payloads(data: bytes) -> dict[tuple[float, float], tuple[bytes, ...]]:
    """MASK, COEF, RESD payloads of each occupied tile, by the world position of its corner."""
    source = Source(data)
    header, _ = unpack_source(source)
    g, tiling = header.grid, header.tiles.tiling
    out = {}
    for k in np.flatnonzero(header.tiles.cells):
        i, j = divmod(int(k), tiling.tile_cols)
        blobs = read_tile(source, header, int(k))
        corner = (round(g.x0 + j * tiling.size * g.resolution, 6), round(g.y0 + i * tiling.size * g.resolution, 6))
        out[corner] = tuple(bytes(blobs.get(tag, b"")) for tag in (b"MASK", b"COEF", b"RESD"))
    return out


@pytest.fixture(scope="module")
def scans():
    # Driving west-south-west from the first scan, so the map grows towards negative tiles too.
    return drive(6, heading=3.5, speed=2.5) + drive(3, start=(4.0, 9.0), heading=0.8, seed=1)


def test_a_grown_map_equals_all_its_points_added_at_once(scans):
    grown = new_builder()
    for points, pose in scans[:4]:
        grown.add(points, pose)
    grown.encode()
    for points, pose in scans[4:]:
        grown.add(points, pose)
    data = grown.encode()
    once = new_builder(origin=grown.origin).add(in_map_frame(scans)).encode()
    # Exact integer sums: the same cell means whatever the order, so the same bytes.
    assert data == once
    assert grown.origin[2] % 1.0 == 0 and min(i for i, _ in grown.tiles) < 0


def test_the_decoded_map_is_the_cells_means_within_the_stated_error(scans):
    pts = in_map_frame(scans)
    data = new_builder().add(pts).encode()
    with dftpcc.open(data) as cmap:
        assert cmap.tiled and cmap.header.tiles.base_cycles == 0 and is_growing(cmap.header)
        stats = cmap.info()["stats"]
        dem = cmap.read_dem()
    g = dem.grid
    rows, cols = g.cell_of(pts[:, :2])
    flat = rows * g.cols + cols
    count = np.bincount(flat, minlength=g.size)
    mean = np.bincount(flat, weights=pts[:, 2] - g.z0, minlength=g.size)[count > 0] / count[count > 0]
    assert np.array_equal(dem.mask.ravel(), count > 0)
    err = np.abs(dem.heights.ravel()[count > 0] - mean)
    assert err.max() <= stats["dem_max_error_m"] + HEIGHT_QUANTUM_M
    assert 0 < stats["dem_rmse_m"] < 0.05
    spread = pts[:, 2] - g.z0 - (np.bincount(flat, weights=pts[:, 2] - g.z0, minlength=g.size) / np.maximum(count, 1))[flat]
    assert stats["gridding_rmse_m"] == pytest.approx(math.sqrt(np.mean(spread ** 2)), rel=1e-6)


def test_only_tiles_a_scan_changes_are_coded_again_and_the_others_keep_their_bytes(scans):
    builder = new_builder()
    for points, pose in scans[:6]:
        builder.add(points, pose)
    before = builder.encode()
    held = set(builder.tiles)
    points, pose = scans[7]
    builder.add(points, pose)
    changed = set(builder.changed_tiles())
    after = builder.encode()
    assert changed and set(builder.tiles) - held <= changed and len(changed) < len(builder.tiles)
    old, new = tile_payloads(before), tile_payloads(after)
    size = TILE * RES
    ox, oy, _ = builder.origin
    kept = {(round(ox + j * size, 6), round(oy + i * size, 6)) for i, j in held - changed}
    assert kept and all(new[c] == old[c] for c in kept)
    assert all(new[(round(ox + j * size, 6), round(oy + i * size, 6))] != old.get(
        (round(ox + j * size, 6), round(oy + i * size, 6))) for i, j in changed & held)


def test_a_change_within_the_overlap_marks_the_neighbour_and_only_then():
    res = 1.0
    builder = MapBuilder(res, tile_size=TILE, step=STEP, origin=(0.0, 0.0, 0.0))
    # Fill tiles (0, 0) and (0, 1) and code them.
    xy = np.stack(np.meshgrid(np.arange(2 * TILE) + 0.5, np.arange(TILE) + 0.5), -1).reshape(-1, 2)
    builder.add(np.c_[xy, np.zeros(len(xy))])
    builder.encode()
    assert builder.changed_tiles() == []
    builder.add(np.array([[TILE / 2 + 0.5, TILE / 2, 1.0]]))  # the middle of tile (0, 0)
    assert builder.changed_tiles() == [(0, 0)]
    builder.encode()
    builder.add(np.array([[TILE - TILE_OVERLAP + 0.5, 3.5, 1.0]]))  # 8 cells from the edge: in (0, 1)'s window
    assert builder.changed_tiles() == [(0, 0), (0, 1)]
    builder.encode()
    builder.add(np.array([[TILE - TILE_OVERLAP - 0.5, 3.5, 1.0]]))  # 9 cells from it: not
    assert builder.changed_tiles() == [(0, 0)]


def test_a_cell_seen_again_at_its_mean_codes_no_tile_and_new_cells_recode_the_mask():
    builder = MapBuilder(1.0, tile_size=TILE, step=STEP, origin=(0.0, 0.0, 0.0))
    xy = np.stack(np.meshgrid(np.arange(2 * TILE) + 0.5, np.arange(TILE // 2) + 0.5), -1).reshape(-1, 2)
    first = np.c_[xy, 0.1 * np.sin(xy[:, 0] / 3.0)]
    builder.add(first)
    before = builder.encode()
    # A point at the exact mean of a cell within the overlap: no mean moves, so no tile is coded again,
    # but the map's point-weighted error still counts it.
    again = first[[TILE - 2]]
    builder.add(again)
    assert builder.changed_tiles() == []
    after = builder.encode()
    once = MapBuilder(1.0, tile_size=TILE, step=STEP, origin=(0.0, 0.0, 0.0)).add(np.r_[first, again]).encode()
    assert after == once and after != before
    assert tile_payloads(after) == tile_payloads(before)
    # A new cell in the tile's upper half (empty so far): the tile's mask is coded again, its neighbour's is not.
    builder.add(np.array([[3.5, TILE - 1.5, 0.0]]))
    assert builder.changed_tiles() == [(0, 0)]
    grown = builder.encode()
    old, new = tile_payloads(after), tile_payloads(grown)
    assert new[(0.0, 0.0)][0] != old[(0.0, 0.0)][0] and new[(float(TILE), 0.0)] == old[(float(TILE), 0.0)]
    assert grown == MapBuilder(1.0, tile_size=TILE, step=STEP, origin=(0.0, 0.0, 0.0)).add(
        np.r_[first, again, [[3.5, TILE - 1.5, 0.0]]]).encode()


def test_a_pose_is_applied_as_rotation_then_translation(scans):
    points, (rotation, translation) = scans[0]
    posed = new_builder().add(points, (rotation, translation)).encode()
    placed = new_builder().add(points @ rotation.T + translation).encode()
    assert posed == placed


def test_a_pose_places_points_by_rounded_products_and_sums_not_blas():
    # Points whose place is on a cell's edge: a product rounded as BLAS's kernel does (FMA on this
    # machine, not on another) moves some of them to the next cell.
    rng = np.random.default_rng(5)
    rotation, translation = yaw_pose(0.7, (3.0, -2.0, 1.0))
    placed = np.c_[rng.integers(-200, 200, (4000, 2)) * RES, rng.random(4000)]
    points = (placed - translation) @ rotation
    x, y, z = points[:, 0:1], points[:, 1:2], points[:, 2:3]
    # Each coordinate as IEEE double arithmetic gives it, one rounding a product or sum, left to right.
    by_hand = x * rotation[:, 0] + y * rotation[:, 1] + z * rotation[:, 2] + translation
    origin = (0.0, 0.0, 0.0)
    posed = new_builder(origin=origin).add(points, (rotation, translation))
    assert posed.encode() == new_builder(origin=origin).add(by_hand).encode()


def test_a_map_within_one_tile_is_still_a_tiled_file():
    pts = np.c_[np.random.default_rng(2).random((500, 2)) * 3, np.zeros(500)]
    data = new_builder().add(pts).encode()
    with dftpcc.open(data) as cmap:
        assert cmap.tiled and cmap.header.tiles.tiling.count == 9 and int(np.count_nonzero(cmap.header.tiles.cells)) == 1
        assert cmap.read_points().shape[0] == cmap.header.cell_count


def test_the_state_resumes_the_map_exactly(tmp_path, scans):
    builder = new_builder()
    for points, pose in scans[:5]:
        builder.add(points, pose)
    builder.save(tmp_path / "m.dftpc")
    resumed = MapBuilder.from_file(tmp_path / "m.dftpc")
    assert resumed.changed_tiles() == []
    for b in (builder, resumed):
        for points, pose in scans[5:]:
            b.add(points, pose)
    assert resumed.changed_tiles() == builder.changed_tiles()
    assert resumed.encode() == builder.encode()


def test_a_state_ahead_of_its_map_is_recovered_and_another_maps_state_refused(tmp_path, scans):
    builder = new_builder()
    for points, pose in scans[:3]:
        builder.add(points, pose)
    old = builder.save(tmp_path / "m.dftpc")
    for points, pose in scans[3:5]:
        builder.add(points, pose)
    new = builder.encode()
    builder.save(tmp_path / "m.dftpc", data=new)
    (tmp_path / "m.dftpc").write_bytes(old)  # as if stopped between the state's write and the map's
    with pytest.warns(StateRecoveredWarning):
        assert MapBuilder.from_file(tmp_path / "m.dftpc").encode() == new
    other = new_builder().add(*scans[6])
    other.save(tmp_path / "o.dftpc")
    with pytest.raises(InvalidInputError, match="belongs to another map"):
        MapBuilder.from_file(tmp_path / "m.dftpc", state_path(tmp_path / "o.dftpc"))


# -- dftpcc update ------------------------------------------------------------------------------


def write_scans(tmp_path, scans, name, crs=None):
    path = tmp_path / name
    dftpcc.write(path, in_map_frame(scans), crs=crs)
    return path


def run(capsys, *argv):
    code = main([*map(str, argv), "-q"])
    return code, capsys.readouterr().err


def digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_update_starts_grows_in_place_and_equals_one_compression(tmp_path, scans, capsys):
    first, second = write_scans(tmp_path, scans[:5], "a.laz"), write_scans(tmp_path, scans[5:], "b.ply")
    m = tmp_path / "m.dftpc"
    assert run(capsys, "update", m, first, "-r", RES, "--tile-size", TILE, "--step", STEP) == (0, "")
    assert state_path(m).is_file()
    assert run(capsys, "update", m, second) == (0, "")
    builder = MapBuilder.from_file(m)
    once = new_builder(origin=builder.origin).add(
        np.concatenate([dftpcc.read(first).points, dftpcc.read(second).points])).encode()
    assert m.read_bytes() == once


def test_update_refusals_write_nothing(tmp_path, scans, capsys):
    from rasterio.crs import CRS

    utm33, utm34 = ({"wkt": CRS.from_epsg(code).to_wkt()} for code in (32633, 32634))
    m = tmp_path / "m.dftpc"
    assert run(capsys, "update", m, write_scans(tmp_path, scans[:3], "a.laz", utm33), "-r", RES,
               "--tile-size", TILE)[0] == 0
    before = {p.name: digest(p) for p in tmp_path.iterdir() if p.is_file()}
    other = write_scans(tmp_path, scans[3:], "b.laz", utm34)
    cases = [
        (("update", m, other), "CRS"),
        (("update", m, write_scans(tmp_path, scans[3:], "c.laz", utm33), "-r", 2 * RES), "resolution"),
    ]
    compressed = tmp_path / "c.dftpc"
    dftpcc.compress_file(write_scans(tmp_path, scans, "all.laz"), compressed, resolution=RES, tile_size=TILE)
    cases.append((("update", compressed, other), "not a growing map"))  # base reach 1, no state
    grown = tmp_path / "g.dftpc"
    new_builder().add(in_map_frame(scans[:2])).save(grown)
    state_path(grown).unlink()
    cases.append((("update", grown, other), "state file"))
    before = {p.name: digest(p) for p in tmp_path.iterdir() if p.is_file()}
    for argv, words in cases:
        code, err = run(capsys, *argv, "-o", tmp_path / "new.dftpc")
        assert code == 3 and err.count("\n") == 1 and words in err, (argv, err)
        code, err = run(capsys, *argv)  # in place
        assert code == 3 and words in err
    assert {p.name: digest(p) for p in tmp_path.iterdir() if p.is_file()} == before


def test_a_map_compressed_growable_is_updated_like_any_growing_map(tmp_path, scans, capsys):
    first, second = write_scans(tmp_path, scans[:5], "a.laz"), write_scans(tmp_path, scans[5:], "b.ply")
    m = tmp_path / "m.dftpc"
    assert run(capsys, "compress", first, m, "--growable", "-r", RES, "--tile-size", TILE, "--step", STEP) == (0, "")
    assert state_path(m).is_file() and is_growing(dftpcc.open(m).header)
    assert run(capsys, "update", m, second) == (0, "")
    builder = MapBuilder.from_file(m)
    once = new_builder(origin=builder.origin).add(
        np.concatenate([dftpcc.read(first).points, dftpcc.read(second).points])).encode()
    assert m.read_bytes() == once
    # What a growing map cannot honour is refused before anything is read or written.
    for extra, words in ((("--target-rmse", "0.01"), "--target-rmse"), ((), "--resolution")):
        argv = ("compress", first, tmp_path / "x.dftpc", "--growable", *extra) + (("-r", RES) if extra else ())
        code, err = run(capsys, *argv)
        assert code == 3 and err.count("\n") == 1 and words in err, err
    assert not (tmp_path / "x.dftpc").exists()
    # Compressed again over it: a new map of its input alone, not an update of the old one.
    grown = m.read_bytes()
    assert run(capsys, "compress", first, m, "--growable", "-f", "-r", RES, "--tile-size", TILE, "--step", STEP) == (0, "")
    assert m.read_bytes() != grown
    assert m.read_bytes() == new_builder(origin=MapBuilder.from_file(m).origin).add(dftpcc.read(first).points).encode()


def test_open_by_mode_reads_appends_and_writes(tmp_path, scans):
    m = tmp_path / "g.dftpc"
    with dftpcc.open(m, "w", resolution=RES, tile_size=TILE, step=STEP) as grown:
        for points, pose in scans[:4]:
            grown.add(points, pose)
    with dftpcc.open(m, "a") as grown:
        for points, pose in scans[4:]:
            grown.add(points, pose)
    once = new_builder(origin=MapBuilder.from_file(m).origin)
    for points, pose in scans:
        once.add(points, pose)
    assert m.read_bytes() == once.encode() and state_path(m).is_file()
    with dftpcc.open(m) as cmap:  # "r", the default
        assert cmap.tiled and cmap.header.point_count == sum(p.shape[0] for p, _ in scans)
    before = m.read_bytes()
    with pytest.raises(RuntimeError), dftpcc.open(m, "a") as grown:  # an error inside writes nothing
        grown.add(*scans[0])
        raise RuntimeError("stop")
    assert m.read_bytes() == before
    for args, kw, words in (((m, "x"), {}, "mode"), ((tmp_path / "none.dftpc", "a"), {}, "no such file"),
                            ((tmp_path / "n.dftpc", "w"), {}, "resolution"), ((m, "a"), {"step": 1.0}, "settings"),
                            ((m, "r"), {"resolution": 1.0}, "settings")):
        with pytest.raises(InvalidInputError, match=words):
            dftpcc.open(*args, **kw)


def _largest_error(data: bytes, pts: np.ndarray) -> float:
    """Largest distance (metres) of the decoded map from the cells' mean heights of ``pts``."""
    with dftpcc.open(data) as cmap:
        dem = cmap.read_dem()
    g = dem.grid
    rows, cols = g.cell_of(pts[:, :2])
    flat = rows * g.cols + cols
    count = np.bincount(flat, minlength=g.size)
    mean = np.bincount(flat, weights=pts[:, 2] - g.z0, minlength=g.size)[count > 0] / count[count > 0]
    return float(np.abs(dem.heights.ravel()[count > 0] - mean).max())


def test_a_target_per_update_keeps_every_cell_within_it_and_recodes_only_the_changed_tiles(scans):
    builder = new_builder()
    for points, pose in scans[:6]:
        builder.add(points, pose)
    free = builder.encode()
    bound = 0.002
    assert _largest_error(free, in_map_frame(scans[:6])) > bound  # the step alone leaves more
    held = set(builder.tiles)
    before = builder.encode(target_max_error=bound)  # a new bound: every tile coded again
    assert _largest_error(before, in_map_frame(scans[:6])) <= bound + HEIGHT_QUANTUM_M
    assert all(new != old for new, old in zip(tile_payloads(before).values(), tile_payloads(free).values()))
    points, pose = scans[7]
    builder.add(points, pose)
    changed = set(builder.changed_tiles())
    after = builder.encode(target_max_error=bound)  # the same bound: only the tiles the scan changed
    assert _largest_error(after, in_map_frame(scans[:6] + scans[7:8])) <= bound + HEIGHT_QUANTUM_M
    old, new = tile_payloads(before), tile_payloads(after)
    size = TILE * RES
    ox, oy, _ = builder.origin
    kept = {(round(ox + j * size, 6), round(oy + i * size, 6)) for i, j in held - changed}
    assert kept and all(new[c] == old[c] for c in kept)
    with dftpcc.open(builder.encode()) as cmap:  # None keeps the map's bound
        assert cmap.params.target_max_error == bound and cmap.params.step == STEP
    with dftpcc.open(builder.encode(target_max_error=0)) as cmap:  # 0: none, every tile again
        assert cmap.params.target_max_error == 0 and cmap.info()["stats"]["residual_bytes"] == 0
    with pytest.raises(InvalidInputError, match="target_max_error"):
        builder.encode(target_max_error=-1.0)


def test_a_resumed_map_keeps_the_bound_its_tiles_were_coded_with(tmp_path, scans):
    builder = new_builder()
    for points, pose in scans[:5]:
        builder.add(points, pose)
    path = tmp_path / "grown.dftpc"
    builder.save(path, data=builder.encode(target_max_error=0.003))
    resumed = MapBuilder.from_file(path)
    points, pose = scans[5]
    data = resumed.add(points, pose).encode()
    with dftpcc.open(data) as cmap:
        assert cmap.params.target_max_error == 0.003
    assert _largest_error(data, in_map_frame(scans[:6])) <= 0.003 + HEIGHT_QUANTUM_M


def test_update_takes_a_target_max_error_and_an_update_interrupted_after_changing_it_is_finished(
        tmp_path, scans, capsys):
    first, second = write_scans(tmp_path, scans[:4], "a.laz"), write_scans(tmp_path, scans[4:], "b.laz")
    m = tmp_path / "m.dftpc"
    assert run(capsys, "update", m, first, "-r", RES, "--tile-size", TILE, "--step", STEP,
               "--target-max-error", "0.003") == (0, "")
    with dftpcc.open(m) as cmap:
        assert cmap.params.target_max_error == 0.003
    assert _largest_error(m.read_bytes(), dftpcc.read(first).points) <= 0.003 + HEIGHT_QUANTUM_M
    old = m.read_bytes()
    assert run(capsys, "update", m, second, "--target-max-error", "0.002") == (0, "")
    new = m.read_bytes()
    with dftpcc.open(new) as cmap:
        assert cmap.params.target_max_error == 0.002
    # The same update killed after its state was written, before its map: the file states the old
    # bound, the state does not record one. Run again as it was, it finishes the update.
    m.write_bytes(old)
    assert run(capsys, "update", m, second, "--target-max-error", "0.002")[0] == 0
    assert m.read_bytes() == new
    # Without the bound it says what to do, in one line.
    m.write_bytes(old)
    code, err = run(capsys, "update", m, second)
    assert code != 0 and err.count("\n") == 1 and "--target-max-error" in err
    with pytest.raises(SystemExit):  # argparse's usage error: one line, exit 2
        run(capsys, "update", m, second, "--target-max-error", "-1")


def test_one_crs_written_two_ways_is_the_same_crs():
    """Two IGN surveys in EPSG:2154, one stating it as WKT1 "RGF93 v1 / Lambert-93", the other as
    WKT2 "RGF93 / Lambert-93": an update of a map made of one with the other was refused."""
    from rasterio.crs import CRS

    from dftpcc.mapbuilder import same_crs

    from .conftest import data_file

    field = dftpcc.read(data_file("pointclouds/field_gentle_ign.laz")).crs
    coast = dftpcc.read(data_file("pointclouds/coastal_plain_ign.laz")).crs
    assert field["wkt"] != coast["wkt"]
    assert same_crs(field, coast) and same_crs(coast, {"wkt": CRS.from_epsg(2154).to_wkt()})
    assert not same_crs(field, {"wkt": CRS.from_epsg(32631).to_wkt()})  # UTM 31N: another CRS
