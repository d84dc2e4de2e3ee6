"""The bytes of a file do not depend on how many threads BLAS runs (dftpcc.sums): a dask worker
runs one, a laptop eight, and both must write the same map."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np

import dftpcc
from dftpcc.sums import dot

from .conftest import data_file


def test_dot_is_numpys_pairwise_sum():
    rng = np.random.default_rng(5)
    a, b = rng.standard_normal(100_001), rng.standard_normal(100_001)
    assert dot(a, b) == float(np.sum(a * b))


def test_one_blas_thread_writes_the_same_bytes(tmp_path):
    src = data_file("pointclouds/field_gentle_ign.laz")
    here, there = tmp_path / "here.dftpc", tmp_path / "there.dftpc"
    dftpcc.compress_file(src, here, resolution=0.5, classes=[2])
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    subprocess.run([sys.executable, "-m", "dftpcc", "compress", str(src), str(there), "-r", "0.5", "--classes", "2",
                    "-q", "--no-warnings"], env=env, check=True)
    assert there.read_bytes() == here.read_bytes()
