"""The transforms and the paper's circular low-pass."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dftpcc import spectrum


@pytest.mark.parametrize("kind", ["full", "half", "dct"])
@pytest.mark.parametrize("shape", [(16, 16), (15, 22), (1, 9)])
def test_cutoff_zero_keeps_everything_and_inverts(kind, shape):
    lay = spectrum.Layout(kind, shape)
    order = spectrum.kept_order(lay, 0.0)[0]
    assert order.size == lay.radius.size
    values = np.random.default_rng(0).normal(size=shape)
    np.testing.assert_allclose(spectrum.inverse(spectrum.forward(values, lay), lay), values, atol=1e-10)


def test_paper_dft_matches_equation_one():
    # F(u, v) = sum f(n, m) exp(-2j pi (un/N + vm/M)), centred.
    f = np.random.default_rng(1).normal(size=(6, 5))
    lay = spectrum.Layout("full", f.shape)
    F = spectrum.forward(f, lay)
    n, m = np.mgrid[0:6, 0:5]
    u, v = 1, 2
    direct = np.sum(f * np.exp(-2j * np.pi * (u * n / 6 + v * m / 5)))
    assert F[6 // 2 + u, 5 // 2 + v] == pytest.approx(direct)


def test_radius_limit_is_half_the_diagonal():
    assert spectrum.radius_limit((100, 60), 0.0) == pytest.approx(math.hypot(50, 30))
    assert spectrum.radius_limit((100, 60), 0.8) == pytest.approx(0.2 * math.hypot(50, 30))


def test_kept_set_shrinks_with_cutoff_and_is_a_prefix():
    lay = spectrum.Layout("dct", (64, 80))
    previous = None
    for fc in (0.0, 0.3, 0.5, 0.8, 0.95):
        order = spectrum.kept_order(lay, fc)[0]
        if previous is not None:
            assert order.size < previous.size
            np.testing.assert_array_equal(previous[: order.size], order)
        previous = order


def test_dct_and_dft_keep_the_same_frequencies():
    # The circle is in DFT frequency pixels for both, so both keep about pi r^2 reals.
    shape = (200, 300)
    r = spectrum.radius_limit(shape, 0.8)
    dct = spectrum.kept_order(spectrum.Layout("dct", shape), 0.8)[0].size
    full = spectrum.kept_order(spectrum.Layout("full", shape), 0.8)[0].size
    assert dct == pytest.approx(math.pi * r * r, rel=0.05)
    assert full == pytest.approx(math.pi * r * r, rel=0.05)
