"""The state file of a growing map (dftpcc.mapstate, docs/growing-maps.md): damaged or crafted states are refused.

Issue 41, item 5: a cut or flipped state ended in BadZipFile, inf/NaN figures
in OverflowError, a wrong type in the settings in TypeError, a tile index of
2**31-1 in a misleading "out of memory", and an edited state that passed the
ZIP CRC gave another map without a word.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile

import numpy as np
import pytest

from dftpcc.cli import main
from dftpcc.errors import CorruptFileError, InvalidInputError
from dftpcc.mapbuilder import MapBuilder, state_path
from dftpcc.mapstate import ARRAYS, STATE_VERSION, read_state

from .fuzz.fuzz_state import run as fuzz_run
from .test_mapbuilder import drive, in_map_frame, new_builder

#: Mutated states per CI run (the campaign, `make fuzz`, runs 100,000).
FUZZ_INPUTS = 800


@pytest.fixture(scope="module")
def grown(tmp_path_factory):
    """A growing map of a few scans and its state, and a scan file to add."""
    folder = tmp_path_factory.mktemp("state")
    scans = drive(6, heading=0.4, speed=2.0)
    m = folder / "m.dftpc"
    builder = new_builder()
    for points, pose in scans[:4]:
        builder.add(points, pose)
    builder.save(m)
    scan = folder / "scan.npy"
    np.save(scan, in_map_frame(scans[4:]))
    return m, m.read_bytes(), state_path(m).read_bytes(), scan


def members(state: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(state), allow_pickle=False) as npz:
        return {name: npz[name] for name in npz.files}


def resave(values: dict[str, np.ndarray], *, checksum: bool = True) -> bytes:
    """A state of these members, its checksum made right again (a crafted state, not a damaged one)."""
    values = dict(values)
    values.pop("checksum", None)
    if checksum:
        digest = hashlib.sha256()
        for name in [n for n in ("settings", *ARRAYS) if n in values]:
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(values[name]), allow_pickle=False)
            digest.update(buf.getvalue())
        values["checksum"] = np.frombuffer(digest.digest(), np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **values)
    return buf.getvalue()


def with_settings(state: bytes, **changes) -> bytes:
    values = members(state)
    settings = json.loads(str(values["settings"]))
    settings.update(changes)
    values["settings"] = np.array(json.dumps(settings))
    return resave(values)


def with_array(state: bytes, name: str, change) -> bytes:
    values = members(state)
    values[name] = change(values[name].copy())
    return resave(values)


def flipped(state: bytes, at: int) -> bytes:
    buf = bytearray(state)
    buf[at] ^= 0x10
    return bytes(buf)


def refused(tmp_path, grown, capsys, state: bytes, code: int = 5) -> str:
    """``dftpcc update`` with this state: one line naming the state file, the exit code, nothing written."""
    m, data, _, scan = grown
    target = tmp_path / "m.dftpc"
    target.write_bytes(data)
    state_path(target).write_bytes(state)
    got = main(["update", str(target), str(scan), "-q"])
    err = capsys.readouterr().err
    assert got == code and err.count("\n") == 1 and "state" in err and "Traceback" not in err, (got, err)
    assert target.read_bytes() == data and state_path(target).read_bytes() == state
    return err


def test_a_sound_state_reads_and_is_version_2(grown):
    m, _, state, _ = grown
    arrays, settings = read_state(state_path(m))
    assert settings["state_version"] == STATE_VERSION == 2 and "checksum" in members(state)
    assert int(arrays["count"].sum()) == settings["point_count"]


def test_a_cut_state_is_one_line_naming_the_file(tmp_path, grown, capsys):
    _, _, state, _ = grown
    for size in (0, 10, len(state) // 3, len(state) - 22, len(state) - 1):
        err = refused(tmp_path, grown, capsys, state[:size])
        assert str(state_path(tmp_path / "m.dftpc")) in err


def test_a_flipped_byte_anywhere_is_refused(tmp_path, grown, capsys):
    _, _, state, _ = grown
    rng = np.random.default_rng(3)
    for at in [*rng.integers(0, len(state), 12), 40, len(state) - 30]:
        refused(tmp_path, grown, capsys, flipped(state, int(at)))


def test_an_edited_state_that_passes_the_zip_crc_fails_its_checksum(tmp_path, grown, capsys):
    _, _, state, _ = grown
    edited = resave({**members(state), "sum": members(state)["sum"] + 7}, checksum=False)
    values = members(edited)
    values["checksum"] = members(state)["checksum"]
    err = refused(tmp_path, grown, capsys, resave(values, checksum=False))
    assert "checksum" in err


@pytest.mark.parametrize("name, value", [
    ("origin", "0,0,0"), ("origin", [0, 0]), ("origin", [1e300, 0, 0]), ("origin", [True, 0, 0]),
    ("crs", "EPSG:4326"), ("crs", {"wkt": 4326}), ("crs", []),
    ("point_count", "12"), ("point_count", 1.5), ("point_count", True), ("point_count", 2**70),
    ("resolution", 0), ("resolution", "0.25"), ("tile_size", 2**31 - 1), ("tile_size", 32.0), ("step", -1),
    ("cutoff", 1.0), ("map_sha256", "00"), ("previous_sha256", 5), ("update_sha256", "g" * 64),
    ("state_version", 3), ("state_version", True),
])
def test_wrong_types_and_ranges_in_the_settings(tmp_path, grown, capsys, name, value):
    _, _, state, _ = grown
    err = refused(tmp_path, grown, capsys, with_settings(state, **{name: value}))
    assert name in err or "version" in err


def test_nonfinite_figures_and_a_point_count_of_another_map(tmp_path, grown, capsys):
    _, _, state, _ = grown
    for bad in (np.inf, np.nan, -1.0):
        refused(tmp_path, grown, capsys, with_array(state, "figures", lambda f: (f.__setitem__((0, 1), bad), f)[1]))
        refused(tmp_path, grown, capsys, with_array(state, "gridding", lambda g: (g.__setitem__(0, bad), g)[1]))
        refused(tmp_path, grown, capsys, with_array(state, "sumsq", lambda g: (g.__setitem__((0, 5, 5), bad), g)[1]))
    settings = json.loads(str(members(state)["settings"]))
    refused(tmp_path, grown, capsys, with_settings(state, point_count=settings["point_count"] + 1))
    text = json.dumps(settings).replace(f'"step": {settings["step"]}', '"step": NaN')
    refused(tmp_path, grown, capsys, resave({**members(state), "settings": np.array(text)}))


def test_absurd_tile_indices_are_refused_as_such_not_as_out_of_memory(tmp_path, grown, capsys):
    _, _, state, _ = grown
    for far in (2**31 - 1, -(2**63), 2**40):
        far_tile = with_array(state, "tiles", lambda t: (t.__setitem__((-1, 0), far), t)[1])
        err = refused(tmp_path, grown, capsys, far_tile)
        assert "memory" not in err and ("tile" in err)
    # Within reach but spread over more tiles than a map holds.
    err = refused(tmp_path, grown, capsys, with_array(state, "tiles", lambda t: (t.__setitem__((-1, 0), 2**20), t)[1]))
    assert "tiles" in err and "memory" not in err


def test_wrong_dtypes_shapes_and_members(tmp_path, grown, capsys):
    _, _, state, _ = grown
    values = members(state)
    cases = [
        {**values, "count": values["count"].astype(np.int64)},
        {**values, "sum": values["sum"].astype(np.float64)},
        {**values, "tiles": values["tiles"][:, :1].copy()},
        {**values, "tiles": values["tiles"][::-1].copy()},  # out of order
        {**values, "settings": np.array(b"{}")},
        {k: v for k, v in values.items() if k != "gridding"},
        {**values, "extra": np.zeros(3)},
    ]
    for case in cases:
        refused(tmp_path, grown, capsys, resave(case))
    # A member compressed: its declared size must not be trusted (a ZIP bomb).
    buf = io.BytesIO()
    source = zipfile.ZipFile(io.BytesIO(state))
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as archive:
        for name in source.namelist():
            archive.writestr(name, source.read(name))
    refused(tmp_path, grown, capsys, buf.getvalue())


def test_an_edited_state_with_its_checksum_made_right_cannot_give_another_map(tmp_path, grown, capsys):
    _, _, state, _ = grown
    values = members(state)
    # Figures (the map's statistics), a tile's occupied cells, the CRS: each changes the map the state gives.
    bigger_error = with_array(state, "figures", lambda f: (f.__setitem__((0, 2), f[0, 2] * 2 + 1), f)[1])
    assert "does not give this map" in refused(tmp_path, grown, capsys, bigger_error, code=3)
    # A point more in an empty cell, with the point count and the tile's figure to match.
    count, sums = values["count"].copy(), values["sum"].copy()
    empty = tuple(np.argwhere(count[0] == 0)[0])
    count[0][empty], sums[0][empty] = 1, 1234
    figures = values["figures"].copy()
    figures[0, 0] += 1
    settings = json.loads(str(values["settings"]))
    settings["point_count"] += 1
    grown_cell = resave({**values, "count": count, "sum": sums, "figures": figures,
                         "settings": np.array(json.dumps(settings))})
    refused(tmp_path, grown, capsys, grown_cell, code=3)
    assert "does not give this map" in refused(
        tmp_path, grown, capsys, with_settings(state, crs={"wkt": "LOCAL_CS[\"x\"]"}), code=3)


def test_a_version_1_state_is_still_read_and_rewritten_as_2(tmp_path, grown):
    m, data, state, scan = grown
    values = members(state)
    settings = json.loads(str(values.pop("settings")))
    settings["state_version"] = 1
    del settings["update_sha256"]
    old = resave({"settings": np.array(json.dumps(settings)), **{k: values[k] for k in ARRAYS}}, checksum=False)
    target = tmp_path / "m.dftpc"
    target.write_bytes(data)
    state_path(target).write_bytes(old)
    assert MapBuilder.from_file(target).encode() == data
    assert main(["update", str(target), str(scan), "-q"]) == 0
    assert read_state(state_path(target))[1]["state_version"] == 2
    with pytest.raises(CorruptFileError, match="lacks its checksum"):
        state_path(target).write_bytes(resave({**members(old), "settings": np.array(json.dumps(
            {**settings, "state_version": 2, "update_sha256": None}))}, checksum=False))
        read_state(state_path(target))


def test_a_state_of_another_map_is_refused(tmp_path, grown):
    m, data, state, _ = grown
    other = new_builder().add(in_map_frame(drive(2, seed=9)))
    other.save(tmp_path / "o.dftpc")
    with pytest.raises(InvalidInputError, match="belongs to another map"):
        MapBuilder.from_file(m, state_path(tmp_path / "o.dftpc"))


def test_mutated_states_are_refused_or_give_the_map_within_the_memory_budget():
    report = fuzz_run(FUZZ_INPUTS, seed=7)
    assert report["failures"] == [], report["failures"][:3]
    assert report["outcomes"].get("accepted", 0) > 0 and report["outcomes"].get("CorruptFileError", 0) > 0
    assert report["peak_over_budget_max"] <= 1.0


def test_the_independent_reader_of_the_document_reads_what_dftpcc_writes(tmp_path):
    from . import spec_state

    scans = drive(3, heading=0.4, speed=2.0, points=500)
    m = tmp_path / "m.dftpc"
    for points, pose in scans:
        path = tmp_path / f"scan{len(list(tmp_path.glob('scan*')))}.npy"
        np.save(path, points @ pose[0].T + pose[1])
        first = ["-r", "0.25", "--tile-size", "32", "--step", "0.005"] if not m.exists() else []
        assert main(["update", str(m), str(path), *first, "-q"]) == 0
    settings, arrays = spec_state.read(state_path(m))
    mine_arrays, mine_settings = read_state(state_path(m))
    assert settings == mine_settings
    for name in ARRAYS:
        assert np.array_equal(arrays[name], mine_arrays[name]), name
    assert settings["map_sha256"] == hashlib.sha256(m.read_bytes()).hexdigest()
    assert settings["update_sha256"] == spec_state.update_record([(np.load(path), None)])
    damaged = bytearray(state_path(m).read_bytes())
    damaged[len(damaged) // 2] ^= 1
    (tmp_path / "bad.state").write_bytes(bytes(damaged))
    with pytest.raises((spec_state.SpecError, zipfile.BadZipFile)):
        spec_state.read(tmp_path / "bad.state")
