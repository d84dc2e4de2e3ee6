"""Crash safety: a compression killed at any point leaves the previous file intact.

``container.atomic_write`` writes a hidden temporary file in the target's
folder, syncs it and renames it over the target in one step. These tests
kill real ``dftpcc compress`` processes at random moments (SIGKILL: no
clean-up possible; SIGTERM: the CLI unwinds) and check that the target
always holds either its previous bytes or the complete new file, that no
partial file is ever visible under a normal name, and that the hidden
temporary a SIGKILL can leave is removed by the next write.
"""

from __future__ import annotations

import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import dftpcc
from dftpcc import cli
from dftpcc.io.atomic import atomic_write
from dftpcc.experiments.terrain import regolith_plain

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")

#: Fixed seed: the kill moments are random but the same on every run.
KILL_SEED = 20240607
#: Kills per signal (each costs a process start, about 1.5 s).
KILLS = {signal.SIGKILL: 4, signal.SIGTERM: 3}
RESOLUTION = "0.1"

#: The child announces that imports are done, then runs the real command line.
CHILD = """
import sys
from dftpcc import cli
print("ready", flush=True)
sys.exit(cli.main(sys.argv[1:]))
"""


def _visible(folder: Path) -> set[str]:
    return {p.name for p in folder.iterdir() if not p.name.startswith(".")}


def _hidden(folder: Path) -> set[str]:
    return {p.name for p in folder.iterdir() if p.name.startswith(".")}


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A cloud file, the map it compresses to, an older map, and how long compressing takes."""
    folder = tmp_path_factory.mktemp("crash")
    src = folder / "cloud.npy"
    np.save(src, regolith_plain(150_000, size=60.0, seed=2))
    old = dftpcc.compress(regolith_plain(5_000, size=20.0, seed=9), resolution=1.0)
    ref = folder / "reference.dftpc"
    t0 = time.perf_counter()
    assert cli.main(["compress", str(src), str(ref), "-r", RESOLUTION, "-q"]) == 0
    work = time.perf_counter() - t0
    return src, old, ref.read_bytes(), work


def _start(src: Path, out: Path) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", CHILD, "compress", str(src), str(out), "-r", RESOLUTION, "-q"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    return proc


@pytest.mark.parametrize("sig", list(KILLS), ids=lambda s: signal.Signals(s).name)
def test_killed_compress_keeps_the_previous_file(tmp_path, setup, sig):
    src, old, new, work = setup
    rng = random.Random(KILL_SEED + int(sig))
    out = tmp_path / "map.dftpc"
    outcomes = []
    for _ in range(KILLS[sig]):
        out.write_bytes(old)
        before = _visible(tmp_path)
        proc = _start(src, out)
        time.sleep(rng.uniform(0.0, 1.2 * work))  # anywhere from reading to renaming
        proc.send_signal(sig)
        _stdout, stderr = proc.communicate(timeout=60)
        content = out.read_bytes()
        assert content in (old, new), "the map is neither the previous file nor the complete new one"
        assert _visible(tmp_path) == before, "a partial file appeared under a visible name"
        outcomes.append("new" if content == new else "old")
        if sig == signal.SIGTERM:
            # Unwound cleanly: no temporary left, one line, the conventional exit status.
            # (-SIGTERM: the signal fell after the command returned, while Python shut down.)
            assert _hidden(tmp_path) == set()
            assert proc.returncode in (0, cli.EXIT_SIGNAL_BASE + signal.SIGTERM, -signal.SIGTERM), stderr
            if proc.returncode == cli.EXIT_SIGNAL_BASE + signal.SIGTERM:
                assert stderr.strip() == "dftpcc: stopped by signal SIGTERM"
        else:
            assert proc.returncode in (0, -signal.SIGKILL)
    # The next complete write replaces the map and removes what killed writers left.
    assert cli.main(["compress", str(src), str(out), "-r", RESOLUTION, "-q"]) == 0
    assert out.read_bytes() == new
    assert _hidden(tmp_path) == set()
    assert "old" in outcomes  # the kills did land before the end


WRITER = """
import sys, time
from pathlib import Path
from dftpcc.io.atomic import atomic_write

def slow(tmp):
    with open(tmp, "wb") as fh:
        fh.write(b"partial" * 100_000)
        fh.flush()
        print("writing", flush=True)
        time.sleep(60)

atomic_write(sys.argv[1], slow)
"""


def test_killed_while_writing_the_file(tmp_path):
    out = tmp_path / "map.dftpc"
    out.write_bytes(b"previous map")
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(out)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "writing"
    proc.kill()
    proc.wait(timeout=60)
    assert out.read_bytes() == b"previous map"
    leftovers = _hidden(tmp_path)
    assert len(leftovers) == 1 and str(proc.pid) in leftovers.pop()  # hidden, named after the dead writer
    atomic_write(out, lambda tmp: Path(tmp).write_bytes(b"new map"))
    assert out.read_bytes() == b"new map"
    assert _hidden(tmp_path) == set()


def test_a_failing_writer_leaves_nothing(tmp_path):
    out = tmp_path / "map.dftpc"
    out.write_bytes(b"previous map")

    def failing(tmp):
        Path(tmp).write_bytes(b"half")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space left"):
        atomic_write(out, failing)
    assert out.read_bytes() == b"previous map"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.dftpc"]


def test_a_live_writers_temporary_is_left_alone(tmp_path):
    out = tmp_path / "map.dftpc"
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        live = tmp_path / f".map.dftpc.{sleeper.pid}.0a1b2c3d.tmp.dftpc"
        live.write_bytes(b"another process is writing this")
        atomic_write(out, lambda tmp: Path(tmp).write_bytes(b"mine"))
        assert live.exists() and out.read_bytes() == b"mine"
    finally:
        sleeper.kill()
        sleeper.wait()
    atomic_write(out, lambda tmp: Path(tmp).write_bytes(b"mine again"))
    assert not live.exists()


def test_decompress_output_is_written_atomically_too(tmp_path, setup):
    _src, old, _new, _work = setup
    src = tmp_path / "map.dftpc"
    src.write_bytes(old)
    out = tmp_path / "points.ply"
    out.write_bytes(b"previous points")
    assert cli.main(["decompress", str(src), str(tmp_path / "no" / "such" / "dir.ply"), "-q"]) == 3
    assert cli.main(["decompress", str(src), str(out), "-q"]) == 0
    assert dftpcc.read(out).points.shape[0] == dftpcc.open(old).header.cell_count
    assert _hidden(tmp_path) == set() and _visible(tmp_path) == {"map.dftpc", "points.ply"}
