"""Sums whose bits reach a file: numpy's own pairwise summation, never BLAS.

``np.dot`` and ``@`` on long vectors go to BLAS, whose result depends on how
many threads it runs (OpenBLAS splits the sum among them): the same map then
gave other bytes under ``OPENBLAS_NUM_THREADS=1``, on a dask worker (which
runs one thread) or on a machine with another core count. ``np.sum`` of the
products adds in the same order everywhere.
"""

from __future__ import annotations

import numpy as np

from . import kernels

__all__ = ["dot", "weighted_sq_sum"]


def dot(a: np.ndarray, b: np.ndarray) -> float:
    """``sum(a * b)`` of two 1-D arrays, the same bits whatever BLAS and its threads."""
    return float(np.sum(np.multiply(a, b)))


@kernels.kernel("weighted_sq_sum")
def weighted_sq_sum(counts: np.ndarray, mask: np.ndarray, errors: np.ndarray) -> float:
    """``sum(counts[mask] * errors * errors)``: ``counts`` per cell (rows, cols), ``errors`` one per set
    cell of ``mask``, row-major (metres: the sum is in m² times the counts' unit)."""
    return float(np.sum(counts[mask] * errors * errors))
