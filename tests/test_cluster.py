"""Tiles coded and decoded on dask.distributed: byte-identical to the serial run, and a cluster that
fails ends in one clear error in bounded time with nothing written (issue 12, point 6)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

import dftpcc
from dftpcc.cluster import CONNECT_TIMEOUT_S, executor
from dftpcc.errors import ClusterError, InvalidInputError

from .conftest import data_file

pytest.importorskip("distributed")

#: Seconds beyond the connect timeout an unreachable scheduler may take to be reported.
REPORT_SLACK_S = 20


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


def test_an_unreachable_scheduler_is_one_error_in_bounded_time(tmp_path):
    out = tmp_path / "never.dftpc"
    start = time.monotonic()
    result = subprocess.run([sys.executable, "-m", "dftpcc", "compress", str(data_file("dems/mars_gale_1m.tif")),
                             str(out), "--tile-size", "128", "--scheduler", "tcp://127.0.0.1:9"],
                            capture_output=True, text=True)
    assert time.monotonic() - start < CONNECT_TIMEOUT_S + REPORT_SLACK_S
    assert result.returncode == 10
    assert result.stderr.count("\n") == 1 and "cannot reach scheduler tcp://127.0.0.1:9" in result.stderr
    assert not out.exists() and not list(tmp_path.iterdir())


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
