"""Tiles coded and decoded on dask.distributed: byte-identical to the serial run, and a cluster that
fails ends in one clear error in bounded time with nothing written (issue 12, point 6)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

import dftpcc
from dftpcc.cluster import CONNECT_TIMEOUT_S, executor
from dftpcc.errors import ClusterError, InvalidInputError

from .conftest import data_file

pytest.importorskip("distributed")

#: Seconds after which a command that should have ended is taken for hung (a guard, not a measure).
HANG_GUARD_S = 600


@pytest.fixture(scope="module")
def gale_tiled(tmp_path_factory):
    out = tmp_path_factory.mktemp("cluster") / "serial.dftpc"
    dftpcc.compress_file(data_file("dems/mars_gale_1m.tif"), out, tile_size=128, target_rmse=0.05)
    return out


def test_two_workers_write_the_serial_bytes(gale_tiled, tmp_path):
    parallel = tmp_path / "parallel.dftpc"
    dftpcc.compress_file(data_file("dems/mars_gale_1m.tif"), parallel, tile_size=128, target_rmse=0.05, workers=2)
    assert parallel.read_bytes() == gale_tiled.read_bytes()
    serial_tif, parallel_tif = tmp_path / "s.tif", tmp_path / "p.tif"
    dftpcc.decompress_file(gale_tiled, serial_tif)
    dftpcc.decompress_file(gale_tiled, parallel_tif, workers=2)
    assert parallel_tif.read_bytes() == serial_tif.read_bytes()


def test_an_unreachable_scheduler_is_one_error_in_bounded_time(tmp_path, monkeypatch):
    """Bounded by the connect timeout dftpcc gives dask, not by a clock on a shared machine: the client is
    asked for CONNECT_TIMEOUT_S (and dask's connect timeout set to it), and the command says so in one line."""
    import distributed

    asked = []
    real = distributed.Client

    def client(*args, **kwargs):
        import dask

        asked.append((kwargs.get("timeout"), dask.config.get("distributed.comm.timeouts.connect")))
        return real(*args, **kwargs)

    monkeypatch.setattr(distributed, "Client", client)
    with pytest.raises(ClusterError, match=f"cannot reach scheduler tcp://127.0.0.1:9 within {CONNECT_TIMEOUT_S} s"):
        with executor(scheduler="tcp://127.0.0.1:9"):
            pass
    assert asked == [(CONNECT_TIMEOUT_S, f"{CONNECT_TIMEOUT_S}s")]
    out = tmp_path / "never.dftpc"
    result = subprocess.run([sys.executable, "-m", "dftpcc", "compress", str(data_file("dems/mars_gale_1m.tif")),
                             str(out), "--tile-size", "128", "--scheduler", "tcp://127.0.0.1:9"],
                            capture_output=True, text=True, timeout=HANG_GUARD_S)
    assert result.returncode == 10
    assert result.stderr.count("\n") == 1 and "cannot reach scheduler tcp://127.0.0.1:9" in result.stderr
    assert not out.exists() and not list(tmp_path.iterdir())


def test_a_map_of_one_tile_reaches_no_cluster():
    """An untiled map is one tile: nothing to share out, so no cluster is started or reached."""
    with executor(scheduler="tcp://127.0.0.1:9", tiles=1) as run:
        assert run(abs, [-1, 2]) == [1, 2]


def test_a_local_cluster_says_nothing_when_another_holds_dasks_port():
    """Another dask cluster on the machine (its HTTP port, 8787, taken) is no concern of the user's
    run: dask warned of it in three lines on the command's stderr."""
    import socket
    import warnings

    holder = socket.socket()
    try:
        holder.bind(("", 8787))
        holder.listen()
    except OSError:
        pass  # held already: the case itself
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            with executor(workers=1, tiles=2) as run:
                assert run(abs, [-1, 2]) == [1, 2]
        assert not [w for w in caught if "already in use" in str(w.message)]
    finally:
        holder.close()


class _Unpicklable(Exception):
    """As GDAL's errors (rasterio's CPLE_*): pickled, but ``args`` cannot be set back."""

    @property
    def args(self):
        return ("gdal",)


def _refuse_after_a_library_error(x):
    try:
        raise _Unpicklable()
    except _Unpicklable:
        raise InvalidInputError(f"input {x} changed while it was read") from None


def test_the_librarys_error_on_a_worker_reaches_the_client_as_itself():
    """An error of ours raised while another library's was handled: dask pickled the chain, the
    other's did not unpickle, and the client got a bare Exception (the CLI a traceback)."""
    with pytest.raises(InvalidInputError, match="input 1 changed"):
        with executor(workers=1, tiles=2) as run:
            run(_refuse_after_a_library_error, [1])


def test_a_worker_that_dies_ends_in_a_cluster_error():
    with executor(workers=1) as run:
        with pytest.raises(ClusterError, match="worker died"):
            run(os._exit, [3])  # the worker process exits mid-task


def test_workers_and_scheduler_are_checked_first(tmp_path):
    with pytest.raises(InvalidInputError, match="not both"):
        dftpcc.compress_file(data_file("dems/mars_gale_1m.tif"), tmp_path / "x.dftpc", workers=2,
                             scheduler="tcp://127.0.0.1:9")
    assert not (tmp_path / "x.dftpc").exists()


def test_a_map_streamed_in_blocks_is_the_serial_bytes_on_two_workers(tmp_path, monkeypatch):
    """Blocks read by the workers themselves, many calls in a row (one a window), byte-identical to serial."""
    from dftpcc import stream

    monkeypatch.setattr(stream, "STREAM_CELLS", 50_000)
    monkeypatch.setattr(stream, "BLOCK_TILES", 1)
    src = data_file("dems/mars_gale_1m.tif")
    serial, parallel = tmp_path / "s.dftpc", tmp_path / "p.dftpc"
    dftpcc.compress_file(src, serial, tile_size=64, target_rmse=0.05)
    dftpcc.compress_file(src, parallel, tile_size=64, target_rmse=0.05, workers=2)
    assert parallel.read_bytes() == serial.read_bytes()
    dftpcc.files.decompress_bands(serial, tmp_path / "s.tif")
    dftpcc.files.decompress_bands(serial, tmp_path / "p.tif", workers=2)
    assert (tmp_path / "p.tif").read_bytes() == (tmp_path / "s.tif").read_bytes()


def test_local_workers_keep_glibcs_adaptive_mmap_threshold():
    """dask's MALLOC_TRIM_THRESHOLD_ made every large temporary a fresh mapping on the workers."""
    with executor(workers=1) as run:
        assert run(os.environ.get, ["MALLOC_TRIM_THRESHOLD_"]) == [os.environ.get("MALLOC_TRIM_THRESHOLD_")]
        assert run(os.environ.get, ["OPENBLAS_NUM_THREADS"]) == ["1"]  # dask's other settings stay


def _backend_here(_item):
    from dftpcc import kernels

    return kernels.current().value


def test_workers_run_the_clients_backend():
    """A worker is a process of its own: it ran numpy's kernels where the client had chosen the
    compiled ones (a 20,000² GeoTIFF at a maximum error took 2.8x the serial CPU time on 2 workers)."""
    from dftpcc import kernels

    pytest.importorskip("numba")
    for backend in ("compiled", "numpy"):
        with kernels.use(backend), executor(workers=1, tiles=2) as run:
            assert run(_backend_here, [0, 1]) == [backend, backend]


def test_more_workers_than_a_local_cluster_should_have_are_refused(tmp_path, capsys):
    """Issue 41, item 6: --workers 1000000 started a million processes (1.46 GB, then a traceback)."""
    from dftpcc.cli import main
    from dftpcc.cluster import MAX_WORKERS_PER_CORE
    from dftpcc.kernels import available_cores

    most = MAX_WORKERS_PER_CORE * available_cores()
    out = tmp_path / "x.dftpc"
    for workers in (most + 1, 1_000_000):
        with pytest.raises(InvalidInputError, match=f"more than {MAX_WORKERS_PER_CORE} per core.*--scheduler"):
            dftpcc.compress_file(data_file("dems/mars_gale_1m.tif"), out, tile_size=128, workers=workers)
        assert main(["compress", str(data_file("dems/mars_gale_1m.tif")), str(out), "--tile-size", "128",
                     "--workers", str(workers)]) == 3
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"at most {most}" in err
    assert not out.exists()


def _descendants(pid: int) -> set[int]:
    """Processes below ``pid`` (children, grandchildren...), from /proc."""
    parents = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    parents[int(entry)] = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                pass
    found, frontier = set(), {pid}
    while frontier:
        frontier = {p for p, parent in parents.items() if parent in frontier} - found
        found |= frontier
    return found


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


#: Seconds a stopped local cluster may take to be gone, its workers included. Issue 41 asks 10 s (one
#: run took 43 s); the graceful close took 10.0-10.7 s here, and a stop now takes 0.8-1.6 s at a load
#: of 26 on 2 cores, so half the promise tells the two apart with room for a busy machine.
STOP_WITHIN_S = 5


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
# The run ends 13.7 s after its workers start on this machine, quiet (18-19 s before the cheaper choosing of
# 2026-12-07 late, longer before the compiled passes): signalled 15 s after its workers started, it had
# finished on a fresh CI machine, so the signal came at its end. (Run it in the foreground, or under job
# control: a background job of a shell without it starts with SIGINT ignored, and Python keeps that.)
@pytest.mark.parametrize(("sig", "after_s"), [("SIGTERM", 2.0), ("SIGINT", 7.0)],
                         ids=["SIGTERM-starting", "SIGINT-at-work"])
def test_a_stop_signal_ends_a_local_cluster_and_its_workers(tmp_path, sig, after_s):
    """Issue 41, item 6: a real `dftpcc compress --workers 2`, stopped once its workers run: the command and
    every worker process are gone within STOP_WITHIN_S (10 s asked) of the signal, with one line and nothing written."""
    import signal

    out = tmp_path / "stopped.dftpc"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(dftpcc.__file__).parents[1]),
                                                       os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.Popen([sys.executable, "-m", "dftpcc", "compress", str(data_file("dems/earth_heidelberg_25m.tif")),
                             str(out), "--tile-size", "64", "--target-max-error", "0.05", "--workers", "2"],
                            stderr=subprocess.PIPE, text=True, env=env)
    try:
        # Both workers' processes (their nannies run in the command's own process).
        deadline = time.monotonic() + HANG_GUARD_S
        while len(_descendants(proc.pid)) < 2 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert proc.poll() is None, "the run ended before its cluster was up"
        time.sleep(after_s)  # the cluster still starting, or its workers at their tiles
        assert proc.poll() is None, "the run ended before the signal: give it more work"
        workers = _descendants(proc.pid)
        proc.send_signal(getattr(signal, sig))
        sent = time.monotonic()
        code = proc.wait(timeout=60)
        ended = time.monotonic() - sent
        while any(_alive(p) for p in workers) and time.monotonic() - sent < 60:
            time.sleep(0.1)
        gone = time.monotonic() - sent
        err = proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert code == 128 + getattr(signal, sig), err
    assert err.strip().count("\n") == 0 and ("stopped by signal" in err or "interrupted" in err), err
    assert ended <= STOP_WITHIN_S and gone <= STOP_WITHIN_S, (ended, gone)
    assert not out.exists() and not list(tmp_path.iterdir())


def _killing_coder(marker: Path | None):
    """stream._code_block that kills its worker process on the block holding tile 0: on every attempt
    (``marker`` None), or on the first only (it leaves ``marker``). Pickled by value with the task."""
    from dftpcc import stream

    code = stream._code_block

    def coder(block, job):
        if 0 in block.tiles and (marker is None or not marker.exists()):
            if marker is not None:
                marker.touch()
            os._exit(3)  # as a worker killed by the OOM killer or a kill -9
        return code(block, job)

    return coder


@pytest.mark.parametrize("always", [True, False])
def test_a_worker_killed_mid_run_fails_cleanly_or_reruns_to_the_serial_bytes(tmp_path, monkeypatch, always):
    """A band-coded map whose worker dies on a block: the scheduler reruns the block once on another
    worker (the same bytes as the serial run); a block that kills every worker it lands on ends the
    run in one ClusterError, with no output."""
    from dftpcc import stream

    monkeypatch.setattr(stream, "STREAM_CELLS", 50_000)
    monkeypatch.setattr(stream, "BLOCK_TILES", 1)
    src = data_file("dems/mars_gale_1m.tif")
    out = tmp_path / "out" / "p.dftpc"
    out.parent.mkdir()
    serial = tmp_path / "s.dftpc"
    monkeypatch.setattr(stream, "_code_block", _killing_coder(None if always else tmp_path / "killed"))
    if always:
        with pytest.raises(ClusterError, match="died"):
            dftpcc.compress_file(src, out, tile_size=64, cutoff=0.8, step=0.05, workers=2)
        assert not list(out.parent.iterdir())
        return
    dftpcc.compress_file(src, out, tile_size=64, cutoff=0.8, step=0.05, workers=2)
    assert (tmp_path / "killed").exists()  # a worker did die
    monkeypatch.undo()
    monkeypatch.setattr(stream, "STREAM_CELLS", 50_000)
    dftpcc.compress_file(src, serial, tile_size=64, cutoff=0.8, step=0.05)
    assert out.read_bytes() == serial.read_bytes()


HEAP_SCRIPT = """
import ctypes, numpy as np
from dftpcc import cluster

class MallInfo2(ctypes.Structure):  # glibc's mallinfo2
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                     "fsmblks", "uordblks", "fordblks", "keepcost")]

libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = MallInfo2

def mapped():  # bytes of an 8 MB array that glibc gave a mapping of its own
    before = libc.mallinfo2().hblkhd
    array = np.ones(1 << 20)
    return libc.mallinfo2().hblkhd - before

frozen = mapped()
cluster._task(len, "tile")  # the first task on a worker
print(frozen, mapped())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_a_worker_started_with_dasks_trim_threshold_reuses_its_heap():
    """A worker started by ``dask worker`` (its nanny sets MALLOC_TRIM_THRESHOLD_) mapped every large
    temporary afresh (and page-faulted it in); its first task gives it glibc's adaptive thresholds,
    so an array of a tile comes from the heap."""
    env = {**os.environ, "MALLOC_TRIM_THRESHOLD_": "65536"}
    out = subprocess.run([sys.executable, "-c", HEAP_SCRIPT], env=env, capture_output=True, text=True, check=True)
    frozen, adaptive = map(int, out.stdout.split())
    assert frozen >= 8 * 1024 ** 2
    assert adaptive == 0
