"""Probes: what a design not taken would have gained, measured once and kept to be rerun.

Each prints a bound or a comparison behind a decision recorded in docs/benchmarks.md (tiles
with their own planes, richer context models, rate-distortion optimised rounding, wavelets,
residual layouts, tile overlap, tile reads). They are not part of ``make bench``; run one
with ``.venv/bin/python -m benchmarks.probes.NAME``.
"""
