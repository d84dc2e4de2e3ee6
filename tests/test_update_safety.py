"""``dftpcc update`` under real processes: two at once, and killed at every rename.

Issue 41: two updates of one map at once kept one scan only; a kill between
the map's rename and the delta's lost the delta for good, and a rerun added
the scan twice. These tests run the real command line in child processes.
"""

from __future__ import annotations

import hashlib
import subprocess
import sys

import numpy as np
import pytest

import dftpcc
from dftpcc.mapbuilder import state_path

from .test_mapbuilder import RES, STEP, TILE, drive, in_map_frame, new_builder

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX locks and signals")

#: The child says it is ready (imports done), waits for a line on stdin, then runs the command line:
#: children started together run their commands at the same moment.
CHILD = """
import sys
from dftpcc import cli
print("ready", flush=True)
sys.stdin.readline()
sys.exit(cli.main(sys.argv[1:]))
"""
#: Rounds of two updates at once (each about 2 s of process start-up).
ROUNDS = 3


def digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def scan_files(tmp_path_factory):
    """Three point files of one drive: the first starts the map, the other two are added at once."""
    folder = tmp_path_factory.mktemp("scans")
    scans = drive(9, heading=0.3, speed=2.0, points=20_000)
    paths = []
    for k, part in enumerate((scans[:3], scans[3:6], scans[6:])):
        path = folder / f"scan{k}.npy"
        np.save(path, in_map_frame(part))
        paths.append(path)
    return paths


def _children(*argvs):
    procs = [subprocess.Popen([sys.executable, "-c", CHILD, *map(str, argv)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for argv in argvs]
    for proc in procs:
        assert proc.stdout.readline().strip() == "ready"
    for proc in procs:  # both read the map before either writes it, unless one waits
        proc.stdin.write("go\n")
        proc.stdin.flush()
    return [(proc.wait(timeout=300), *proc.communicate()) for proc in procs]


def test_two_updates_at_once_keep_both_scans(tmp_path, scan_files):
    first, a, b = scan_files
    for _ in range(ROUNDS):
        m = tmp_path / "m.dftpc"
        for path in (m, state_path(m)):
            path.unlink(missing_ok=True)
        assert dftpcc.cli.main(["update", str(m), str(first), "-r", str(RES), "--tile-size", str(TILE),
                                "--step", str(STEP), "-q"]) == 0
        origin = dftpcc.mapbuilder.MapBuilder.from_file(m).origin
        results = _children(["update", m, a], ["update", m, b])
        assert [code for code, _, _ in results] == [0, 0], results
        everything = np.concatenate([np.load(p) for p in scan_files])
        assert m.read_bytes() == new_builder(origin=origin).add(everything).encode(), "a scan was lost"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["m.dftpc", "m.dftpc.state"]  # no lock file left


# -- an output that is an input ------------------------------------------------------------------


def _files(folder) -> dict[str, str]:
    return {p.name: digest(p) for p in folder.iterdir() if p.is_file()}


def test_an_output_that_is_an_input_the_map_or_its_state_is_refused(tmp_path, scan_files, capsys):
    import os

    first, a, _ = scan_files
    m, n = tmp_path / "m.dftpc", tmp_path / "n.dftpc"
    main = dftpcc.cli.main
    assert main(["update", str(m), str(first), "-r", str(RES), "--tile-size", str(TILE), "--step", str(STEP),
                 "-q"]) == 0
    assert main(["update", str(m), str(a), "-o", str(n), "-q"]) == 0
    (tmp_path / "link.dftpc").symlink_to(m)
    os.link(state_path(m), tmp_path / "hard.state")
    scan = tmp_path / "scan.npy"
    scan.write_bytes(a.read_bytes())
    cases = [
        ["update", m, scan, "--delta", m],  # the delta over the map just written
        ["update", m, scan, "--delta", state_path(m)],
        ["update", m, scan, "--delta", tmp_path / "link.dftpc"],  # the map through a symbolic link
        ["update", m, scan, "--delta", tmp_path / "hard.state"],  # its state through a hard link
        ["update", m, scan, "--delta", scan],
        ["update", m, scan, "--delta", tmp_path / "sub" / ".." / "m.dftpc"],
        ["update", m, scan, "-o", state_path(m)],
        ["update", m, scan, "-o", m],
        ["update", m, scan, "-o", tmp_path / "link.dftpc"],
        ["update", m, scan, "-o", scan],
        ["update", m, scan, "-o", n, "--delta", state_path(n)],
        ["update", m, scan, "-o", n, "--delta", n],
        ["update", m, scan, "--delta", tmp_path / "m.dftpc.lock"],
        ["patch", n, tmp_path / "none.dftpd", "-o", tmp_path / "none.dftpd"],
        ["patch", n, tmp_path / "none.dftpd", "-o", n],
    ]
    (tmp_path / "sub").mkdir()
    (tmp_path / "none.dftpd").write_bytes(b"a delta")
    before = _files(tmp_path)
    for argv in cases:
        code = main([*map(str, argv), "-q"])
        err = capsys.readouterr().err
        assert code == 3 and err.count("\n") == 1 and "the same file" in err, (argv, code, err)
        assert _files(tmp_path) == before, argv


# -- killed at every rename ----------------------------------------------------------------------

#: The child SIGKILLs itself just before (or just after) its N-th rename (os.replace: every file
#: dftpcc writes is renamed into place), and reports the renames of a run it did not kill.
KILLER = """
import atexit, os, signal, sys
where, at = sys.argv[1], int(sys.argv[2])
real, calls = os.replace, []

def replace(src, dst):
    calls.append(os.path.basename(dst))
    if where == "before" and len(calls) == at:
        os.kill(os.getpid(), signal.SIGKILL)
    real(src, dst)
    if where == "after" and len(calls) == at:
        os.kill(os.getpid(), signal.SIGKILL)

os.replace = replace
atexit.register(lambda: print("renamed", *calls, flush=True))
from dftpcc import cli
sys.exit(cli.main(sys.argv[3:]))
"""


def _killed(where: str, at: int, *argv) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", KILLER, where, str(at), *map(str, argv)], capture_output=True,
                          text=True, timeout=300)


@pytest.fixture(scope="module")
def started(tmp_path_factory, scan_files):
    """A map of the first scan, and the map and delta a clean update with the second writes."""
    folder = tmp_path_factory.mktemp("clean")
    first, a, _ = scan_files
    m = folder / "m.dftpc"
    assert dftpcc.cli.main(["update", str(m), str(first), "-r", str(RES), "--tile-size", str(TILE), "--step",
                            str(STEP), "-q"]) == 0
    old, old_state = m.read_bytes(), state_path(m).read_bytes()
    run = _killed("never", 0, "update", m, a, "--delta", folder / "d.dftpd", "-q")
    assert run.returncode == 0, run.stderr
    renames = run.stdout.split()[1:]
    return old, old_state, m.read_bytes(), (folder / "d.dftpd").read_bytes(), renames


def test_an_update_renames_the_delta_then_the_state_then_the_map(started):
    *_, renames = started
    assert renames == ["d.dftpd", "m.dftpc.state", "m.dftpc"]


@pytest.mark.parametrize("where, at", [("before", 1), ("before", 2), ("before", 3), ("after", 3)])
def test_an_update_killed_at_any_rename_is_finished_by_running_it_again(tmp_path, scan_files, started, where, at):
    from dftpcc.delta import apply_delta

    _, a, b = scan_files
    old, old_state, new, new_delta, _ = started
    m, d = tmp_path / "m.dftpc", tmp_path / "d.dftpd"
    m.write_bytes(old)
    state_path(m).write_bytes(old_state)
    killed = _killed(where, at, "update", m, a, "--delta", d, "-q")
    assert killed.returncode == -9, killed.stderr
    # Renamed before the state, the delta is there whenever the state moved on: the ground can follow.
    assert m.read_bytes() in (old, new) and (d.read_bytes() == new_delta if at >= 2 or where == "after" else True)
    rerun = subprocess.run([sys.executable, "-m", "dftpcc", "update", str(m), str(a), "--delta", str(d)],
                           capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    assert m.read_bytes() == new, "the scan was added twice, or not at all"
    assert d.read_bytes() == new_delta and apply_delta(old, d.read_bytes()) == new
    assert dftpcc.mapbuilder.MapBuilder.from_file(m).encode() == new
    assert ("nothing added again" in rerun.stdout) == (at >= 3 or where == "after"), rerun.stdout
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".")) == [
        "d.dftpd", "m.dftpc", "m.dftpc.state"]
    # And the map grows on from there, the next delta following this one.
    assert dftpcc.cli.main(["update", str(m), str(b), "--delta", str(tmp_path / "e.dftpd"), "-q"]) == 0
    assert apply_delta(new, (tmp_path / "e.dftpd").read_bytes()) == m.read_bytes()
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # what the kill left, the next write removed


def test_another_update_after_a_kill_keeps_both_scans_and_its_delta_starts_from_the_map_on_disk(
        tmp_path, scan_files, started):
    from dftpcc.delta import apply_delta

    first, a, b = scan_files
    old, old_state, _, _, _ = started
    m, d = tmp_path / "m.dftpc", tmp_path / "d.dftpd"
    m.write_bytes(old)
    state_path(m).write_bytes(old_state)
    assert _killed("before", 3, "update", m, a, "--delta", d, "-q").returncode == -9  # state renamed, map not
    # The next update, with other scans, is killed at the same point: the map on disk is still the
    # oldest, two updates behind the state; running it again must still finish both.
    assert _killed("before", 3, "update", m, b, "--delta", tmp_path / "e.dftpd", "-q").returncode == -9
    assert m.read_bytes() == old
    code = dftpcc.cli.main(["update", str(m), str(b), "--delta", str(tmp_path / "e.dftpd"), "-q"])
    assert code == 0
    origin = dftpcc.mapbuilder.MapBuilder.from_file(m).origin
    everything = np.concatenate([np.load(p) for p in (first, a, b)])
    assert m.read_bytes() == new_builder(origin=origin).add(everything).encode()
    assert apply_delta(old, (tmp_path / "e.dftpd").read_bytes()) == m.read_bytes()


def test_a_completed_update_run_again_adds_nothing_and_keeps_its_delta(tmp_path, scan_files, started, capsys):
    _, a, _ = scan_files
    old, old_state, new, new_delta, _ = started
    m, d = tmp_path / "m.dftpc", tmp_path / "d.dftpd"
    m.write_bytes(new)
    state_path(m).write_bytes(started_state := _state_after(tmp_path, started, a))
    d.write_bytes(new_delta)
    assert dftpcc.cli.main(["update", str(m), str(a), "--delta", str(d)]) == 0
    assert "nothing added again" in capsys.readouterr().out
    assert m.read_bytes() == new and d.read_bytes() == new_delta and state_path(m).read_bytes() == started_state
    # Another delta name: the map it would start from is gone; said on one line, nothing written.
    assert dftpcc.cli.main(["update", str(m), str(a), "--delta", str(tmp_path / "other.dftpd"), "-q"]) == 3
    assert "delta can no longer be made" in capsys.readouterr().err
    assert not (tmp_path / "other.dftpd").exists()


def _state_after(tmp_path, started, scan) -> bytes:
    """The state a clean update with ``scan`` writes (in a folder of its own)."""
    old, old_state, *_ = started
    folder = tmp_path / "clean"
    folder.mkdir()
    m = folder / "m.dftpc"
    m.write_bytes(old)
    state_path(m).write_bytes(old_state)
    assert dftpcc.cli.main(["update", str(m), str(scan), "-q"]) == 0
    data = state_path(m).read_bytes()
    for path in folder.iterdir():
        path.unlink()
    folder.rmdir()
    return data


def test_an_update_waits_for_the_lock_says_so_once_and_then_adds_its_scans(tmp_path, scan_files):
    from dftpcc.io.lock import lock_path, locked

    first, a, _ = scan_files
    m = tmp_path / "m.dftpc"
    assert dftpcc.cli.main(["update", str(m), str(first), "-r", str(RES), "--tile-size", str(TILE), "--step",
                            str(STEP), "-q"]) == 0
    before = m.read_bytes()
    with locked([m]):  # another update holds the map
        proc = subprocess.Popen([sys.executable, "-m", "dftpcc", "update", str(m), str(a)], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        line = proc.stdout.readline()
        assert line.strip() == f"{m}: another update holds {lock_path(m)}; waiting for it"
        with pytest.raises(subprocess.TimeoutExpired):
            proc.wait(timeout=2)
        assert m.read_bytes() == before  # nothing written while it waits
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0 and err == "" and "updated with 1 scan" in out
    assert m.read_bytes() != before and not lock_path(m).exists()


def test_a_map_in_a_folder_that_takes_no_file_is_still_read_without_its_lock(tmp_path, scan_files, monkeypatch):
    import errno
    import os

    first, a, _ = scan_files
    m, n = tmp_path / "m.dftpc", tmp_path / "n.dftpc"
    assert dftpcc.cli.main(["update", str(m), str(first), "-r", str(RES), "--tile-size", str(TILE), "--step",
                            str(STEP), "-q"]) == 0
    real = os.open

    def read_only(path, flags, *args):  # the map's folder is read-only (a root test cannot chmod it so)
        if str(path) == f"{m}.lock":
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real(path, flags, *args)

    monkeypatch.setattr(os, "open", read_only)
    assert dftpcc.cli.main(["update", str(m), str(a), "-o", str(n), "-q"]) == 0
    assert n.exists() and not (tmp_path / "n.dftpc.lock").exists()
