"""Benchmarks and probes of dftpcc, run from the repository root as modules.

    python -m benchmarks.bench_codec [--quick]

They import the installed (or ``PYTHONPATH``) ``dftpcc`` through its public
modules only, and share :mod:`benchmarks.common`.
"""
