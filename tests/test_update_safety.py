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
    assert main(["update", str(m), str(first), "-r", str(RES), "--tile-size", str(TILE), "--step", str(STEP), "-q"]) == 0
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
