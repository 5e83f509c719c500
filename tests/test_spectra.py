"""Eq. 8's ingredients on non-square grids and its input checks (mutation survivors)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import fft as sfft

from pipeline.core import spectra
from pipeline.errors import InputError


@pytest.mark.parametrize("shape", [(32, 64), (64, 32), (24, 40)])
def test_natural_spectrum_on_non_square_grids(shape):
    power = spectra.natural_image_spectrum(shape)
    fy = sfft.fftfreq(shape[0])[:, None]
    fx = sfft.fftfreq(shape[1])[None, :]
    w2 = fy**2 + fx**2
    w2[0, 0] = 1.0 / max(shape) ** 2  # DC at the lowest non-zero frequency of the grid
    expected = (1 / w2) / (1 / w2).sum()
    np.testing.assert_allclose(power, expected, rtol=1e-12)


@pytest.mark.parametrize("shape", [(4, 5), (5, 4), (6, 6), (5,), (3, 3, 3)])
def test_dissimilarity_refuses_kernels_without_a_centre(shape):
    k = np.ones(shape) / np.prod(shape)
    odd = np.ones((3, 3)) / 9
    with pytest.raises(InputError, match="odd size"):
        spectra.dissimilarity(k, odd)
    with pytest.raises(InputError, match="odd size"):
        spectra.dissimilarity(odd, k)


@pytest.mark.parametrize("side", [1, 3, 5, 7, 9, 11, 13, 15, 17])
def test_dissimilarity_accepts_every_odd_kernel(side):
    k = np.zeros((side, side))
    k[side // 2, side // 2 :] = 1.0
    k /= k.sum()
    assert spectra.dissimilarity(k, k) == 0.0


def test_dissimilarity_refuses_non_finite_kernels():
    k = np.full((3, 3), 1 / 9)
    bad = k.copy()
    bad[0, 0] = np.nan
    with pytest.raises(InputError, match="finite"):
        spectra.dissimilarity(k, bad)


def test_dissimilarity_default_grid_is_64_for_small_kernels():
    """Kernels up to 16 px are compared on a 64 x 64 grid (the default n)."""
    k = np.zeros((9, 9))
    k[4, 4:] = [0.4, 0.3, 0.2, 0.1, 0.0]
    other = k[::-1, ::-1].copy()
    assert spectra.dissimilarity(k, other) == spectra.dissimilarity(k, other, n=64)
    assert spectra.dissimilarity(k, other) != spectra.dissimilarity(k, other, n=66)
    big = np.zeros((41, 41))
    big[20, 20:] = 1 / 21
    # 41 px: 2 * 41 - 1 = 81 -> 128
    assert spectra.dissimilarity(big, big[::-1, ::-1]) == spectra.dissimilarity(
        big, big[::-1, ::-1], n=128
    )


def test_mtf_of_a_box_is_a_sinc():
    n = 256
    box = np.ones((1, 3)) / 3
    box = np.pad(box, ((1, 1), (0, 0)))  # 3 x 3, one row of three
    freq, m = spectra.mtf(box, n=n)
    assert freq[0] == 0 and freq[-1] == 0.5 and len(freq) == n // 2 + 1
    expected = np.abs(np.sin(3 * np.pi * freq) / (3 * np.sin(np.pi * np.maximum(freq, 1e-12))))
    expected[0] = 1.0
    np.testing.assert_allclose(m, expected, atol=1e-12)


def test_dissimilarity_default_grid_for_a_23_px_kernel():
    """2 * 23 - 1 = 45 -> the next power of two is 64 (a 3 * size rule would give 128)."""
    k = np.zeros((23, 23))
    k[11, 11:] = 1 / 12
    assert spectra.dissimilarity(k, k[::-1, ::-1]) == spectra.dissimilarity(
        k, k[::-1, ::-1], n=64
    )


def test_mtf_of_a_wide_kernel():
    """A 1 x 301 box on n=256: the grid grows to the kernel's widest side (it raised)."""
    _, m = spectra.mtf(np.full((1, 301), 1 / 301), n=256)
    assert m[0] == pytest.approx(1.0)


@pytest.mark.parametrize("n", [None, 63, 64])
def test_batched_dissimilarities_equal_the_full_plane_eq8(n):
    """The batched form sums Eq. 8 on the real FFT's half-plane with mirrored columns
    counted twice (issue 15); it must give the full-plane numbers for asymmetric
    kernels on even and odd grids (a missing or doubled Nyquist column, or a dropped
    multiplicity, changes them by 1e-3 or more)."""
    rng = np.random.default_rng(8)
    kernels = rng.random((4, 9, 7)) ** 3  # asymmetric, odd sides
    kernels[:, 4, 0] += 2.0  # mass off-centre
    kernels /= kernels.sum(axis=(1, 2), keepdims=True)
    reference = rng.random((9, 7))
    reference /= reference.sum()
    batched = spectra.dissimilarities(kernels, reference, n=n)
    single = [spectra.dissimilarity(k, reference, n=n) for k in kernels]
    np.testing.assert_allclose(batched, single, rtol=1e-12)


@pytest.mark.parametrize("n", [None, 64, 66])
def test_symmetric_kernels_quarter_plane_equals_full_plane_eq8(n):
    """Kernels symmetric in both axes take the quarter-plane DCT path (a focal stack's
    per-depth kernels); it must give the full-plane numbers: a wrong multiplicity of the
    zero or Nyquist rows/columns, or a shifted quadrant, changes them by 1e-3 or more."""
    rng = np.random.default_rng(9)
    quadrants = rng.random((4, 6, 5)) ** 3
    kernels = np.concatenate([quadrants[:, :0:-1], quadrants], axis=1)  # mirror rows
    kernels = np.concatenate([kernels[:, :, :0:-1], kernels], axis=2)  # ... and columns
    kernels /= kernels.sum(axis=(1, 2), keepdims=True)
    reference = kernels.mean(axis=0)
    batched = spectra.dissimilarities(kernels, reference, n=n)
    single = [spectra.dissimilarity(k, reference, n=n) for k in kernels]
    np.testing.assert_allclose(batched, single, rtol=1e-12)


@pytest.mark.parametrize("shape", [(64, 64), (50, 70), (1024, 1024)])
def test_centred_rfft_over_the_kernels_rows_is_rfft2_bit_for_bit(shape):
    """centred_fft(real=True) transforms only the kernel's own rows (the others are 0):
    the same bits as rfft2 of the whole grid, in float64 and float32."""
    rng = np.random.default_rng(10)
    kernel = rng.random((31, 17))
    for dtype in (np.float64, np.float32):
        grid = np.zeros(shape, dtype)
        rows = (np.arange(31) - 15) % shape[0]
        cols = (np.arange(17) - 8) % shape[1]
        grid[np.ix_(rows, cols)] = kernel
        got = spectra.centred_fft(kernel, shape, real=True, dtype=dtype)
        want = sfft.rfft2(grid)
        assert got.dtype == want.dtype
        assert np.array_equal(got, want)
