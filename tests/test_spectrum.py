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


@pytest.mark.parametrize("shape", [(741, 702), (2125, 414), (414, 2125), (7, 3), (1, 9), (9, 1), (1, 1), (64, 64)])
def test_a_dct_corner_has_the_bits_of_the_whole_transform(shape):
    """A file at a fixed cutoff transforms only the corner its circle needs (the second pass on
    the corner's lines alone): the same bits as the whole transform's corner, whatever corner,
    and the orthonormal DCT-II of scipy's dctn to round-off."""
    from scipy import fft as sfft

    rng = np.random.default_rng(shape[0] * 7 + shape[1])
    x = rng.normal(0, 100, shape)
    lay = spectrum.layout("dct", "quantized", shape)
    whole = spectrum.forward(x.copy(), lay)
    np.testing.assert_allclose(whole, sfft.dctn(x, type=2, norm="ortho"), rtol=0, atol=1e-12 * np.abs(x).sum())
    for kr, kc in ((1, 1), (max(1, shape[0] // 4), max(1, shape[1] // 3)), (shape[0], 1), shape):
        part = spectrum.forward(x.copy(), lay, overwrite=True, corner=(kr, kc))
        assert part.shape == (kr, kc) and part.tobytes() == whole[:kr, :kc].tobytes()
    # Cut at 0.8, the analysis keeps those corner's coefficients, bit for bit.
    order, _, _ = spectrum.kept_order(lay, 0.8)
    corner_shape, where = spectrum.corner(lay, order)
    assert spectrum.forward(x.copy(), lay, corner=corner_shape).ravel()[where].tobytes() == whole.ravel()[order].tobytes()


def test_fft_workers_hold_for_this_thread_and_leave_the_bits_alone():
    import threading

    rng = np.random.default_rng(3)
    heights = rng.standard_normal((300, 170))
    lay = spectrum.layout("dct", "quantized", heights.shape)
    before = spectrum.forward(heights, lay), spectrum.inverse(spectrum.forward(heights, lay)[:40, :30], lay)
    seen = {}
    with spectrum.fft_workers(1):
        seen["here"] = spectrum._fft_workers()
        other = threading.Thread(target=lambda: seen.update(there=spectrum._fft_workers()))
        other.start()
        other.join()
        inside = spectrum.forward(heights, lay), spectrum.inverse(spectrum.forward(heights, lay)[:40, :30], lay)
        with spectrum.fft_workers(None):
            seen["none"] = spectrum._fft_workers()
        asked = iter([1, None])
        with spectrum.fft_workers(lambda: next(asked)):  # asked before each transform
            seen["asked"] = spectrum._fft_workers(), spectrum._fft_workers()
    assert seen == {"here": 1, "there": spectrum.FFT_WORKERS, "none": spectrum.FFT_WORKERS,
                    "asked": (1, spectrum.FFT_WORKERS)}
    assert spectrum._fft_workers() == spectrum.FFT_WORKERS
    for a, b in zip(before, inside):
        assert a.tobytes() == b.tobytes()
