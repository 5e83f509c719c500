"""GCV (``pipeline.core.deconvolve.gcv``) against computations made here independently:
the centre crop located by hand, Parseval's theorem on the mirrored crop, Wahba's noise
from explicit influence matrices at the ``lam`` the search returns. Mutation kills
(helper mut-sim, tests/mutation/README.md)."""

from __future__ import annotations

import numpy as np
import pytest
from reference.matrices import gcv_and_noise, influence, one_sided_scene

from pipeline.core.deconvolve import gcv


def _asymmetric_kernel() -> np.ndarray:
    k = np.array([[0.0, 0.1, 0.0], [0.05, 0.5, 0.25], [0.0, 0.0, 0.1]])
    return k / k.sum()


def test_the_data_power_is_the_centre_crops_mirrored_spectrum_without_its_mean():
    """A 600 x 530 image, a 31 px kernel: the crop is 256 x 256 (``GCV_CROP_PX``) at rows
    172..427 and columns 137..392 ((600 - 256) / 2 and (530 - 256) / 2), mirrored to
    512 x 512. Its power, taken here with a full complex FFT, equals the weighted rfft
    power; the weights make the half spectrum sum to the whole (Parseval: N sum x^2)."""
    rng = np.random.default_rng(11)
    y = rng.uniform(0.0, 1.0, (600, 530)) + np.linspace(0.0, 3.0, 530)[None, :]
    kernel = np.ones((31, 31)) / 31**2
    shape = gcv.crop_shape(y.shape, kernel.shape)
    assert shape == (512, 512)
    power, weight, _, _, _ = gcv._spectra(y, gcv.kernel_grid(shape, kernel))
    crop = y[172:428, 137:393]
    mirrored = np.concatenate([crop, crop[::-1]], axis=0)
    mirrored = np.concatenate([mirrored, mirrored[:, ::-1]], axis=1)
    centred = mirrored - mirrored.mean()
    full = np.abs(np.fft.fft2(centred)) ** 2
    assert power.shape == (512, 257)
    np.testing.assert_allclose(power, weight * full[:, :257], rtol=1e-9, atol=1e-6)
    assert power[0, 0] == pytest.approx(0.0, abs=1e-6)  # the mean is taken out
    assert power.sum() == pytest.approx(centred.size * float(np.sum(centred**2)), rel=1e-9)


def test_the_noise_returned_with_lam_is_wahbas_noise_from_the_matrices():
    """``gcv_regularization`` returns, beside ``lam``, ``sqrt(|(I - A) y|^2 / tr(I - A))``
    at that ``lam`` on the whole mirrored domain (here 10 x 12 = 120 samples)."""
    rng = np.random.default_rng(12)
    y = rng.uniform(0.0, 1.0, (5, 6))
    kernel = _asymmetric_kernel()
    grid = gcv.kernel_grid(gcv.crop_shape(y.shape, kernel.shape), kernel)
    lam, noise = gcv.gcv_regularization(y, grid)
    mirrored = np.pad(y, [(0, 5), (0, 6)], mode="symmetric")
    want = gcv_and_noise(mirrored, influence(kernel, mirrored.shape, lam))[1]
    assert noise == pytest.approx(want, rel=1e-9)


def test_gcv_at_the_grids_floor_where_the_trace_is_below_one():
    """At ``lam = 1e-7`` (the coarse grid's first point) the asymmetric kernel, which has
    no spectral zero, leaves ``tr(I - A)`` far below 1: the score still equals the
    matrix GCV and Wahba's noise (a guard on the trace must not clip it)."""
    rng = np.random.default_rng(13)
    y = rng.uniform(0.0, 1.0, (6, 7))
    kernel = _asymmetric_kernel()
    mirrored = np.pad(y, [(0, y.shape[0]), (0, y.shape[1])], mode="symmetric")
    want, noise, trace = gcv_and_noise(mirrored, influence(kernel, mirrored.shape, 1e-7))
    assert 0.0 < trace < 0.1
    spectra = gcv._spectra(y, gcv.kernel_grid(gcv.crop_shape(y.shape, kernel.shape), kernel))
    assert gcv.gcv_score(1e-7, spectra) == pytest.approx(want, rel=1e-6)
    assert gcv.gcv_noise(1e-7, spectra, 4 * y.size) == pytest.approx(noise, rel=1e-6)


def test_a_minimum_in_the_grids_last_decade_is_refined_not_left_at_its_end():
    """Strong noise (sigma 0.3 on a smooth texture): the coarse grid's best is its last
    point, ``lam = 10``, but GCV's minimum lies inside the last decade, near 10^0.785 (a
    0.005-decade scan of the score): the search brackets it between the last two grid
    points and refines it."""
    from scipy import ndimage

    kernel = np.zeros((5, 5))
    kernel[2, 1:5] = 1.0
    kernel[0:2, 3] = 0.5
    kernel /= kernel.sum()
    x = ndimage.gaussian_filter(np.random.default_rng(0).uniform(0, 1, (32, 32)), 1.0)
    y = ndimage.convolve(x, kernel, mode="wrap")
    y = y + np.random.default_rng(1).normal(0, 0.3, x.shape)
    grid = gcv.kernel_grid(gcv.crop_shape(y.shape, kernel.shape), kernel)
    spectra = gcv._spectra(y, grid)
    coarse = [gcv.gcv_score(t, spectra) for t in gcv.GCV_LAMS]
    assert int(np.argmin(coarse)) == len(gcv.GCV_LAMS) - 1
    fine = np.logspace(0.0, 1.0, 201)
    best = fine[int(np.argmin([gcv.gcv_score(t, spectra) for t in fine]))]
    assert 0.7 < np.log10(best) < 0.9
    lam, _ = gcv.gcv_regularization(y, grid)
    assert np.log10(lam) == pytest.approx(np.log10(best), abs=0.01)


def test_a_minimum_in_the_grids_first_decade_is_refined_not_left_at_its_end():
    """Weak noise (sigma 3e-4) on data that fit the mirrored model exactly (a white
    texture mirrored, blurred periodically by a Gaussian, its first quadrant): the coarse
    grid's best is its first point, ``lam = 1e-7``, but GCV's minimum lies inside the
    first decade, near 10^-6.68 (a 0.005-decade scan): the search brackets it between
    the first two grid points and refines it."""
    from scipy import ndimage

    x = np.random.default_rng(0).uniform(0, 1, (32, 32))
    g = np.exp(-0.5 * np.arange(-8, 9) ** 2)
    kernel = np.outer(g, g) / np.outer(g, g).sum()
    mirrored = ndimage.convolve(
        np.pad(x, [(0, 32), (0, 32)], mode="symmetric"), kernel, mode="wrap"
    )
    y = mirrored[:32, :32] + np.random.default_rng(1).normal(0, 3e-4, x.shape)
    grid = gcv.kernel_grid(gcv.crop_shape(y.shape, kernel.shape), kernel)
    spectra = gcv._spectra(y, grid)
    assert int(np.argmin([gcv.gcv_score(t, spectra) for t in gcv.GCV_LAMS])) == 0
    fine = np.logspace(-7.0, -6.0, 201)
    best = fine[int(np.argmin([gcv.gcv_score(t, spectra) for t in fine]))]
    assert -6.8 < np.log10(best) < -6.5
    lam, _ = gcv.gcv_regularization(y, grid)
    assert np.log10(lam) == pytest.approx(np.log10(best), abs=0.01)


def test_the_crop_of_an_even_kernel_is_twice_its_half():
    """Sides worked out by hand: a 600 px kernel (even) on a 1000 px frame needs a
    600 px mirrored crop (twice half the kernel, over twice ``GCV_CROP_PX``); a 100 px
    kernel on a 50 px frame just fits the 100 px mirrored frame (not too small)."""
    assert gcv.crop_shape((1000, 1000), (600, 600)) == (600, 600)
    assert gcv.crop_shape((50, 60), (100, 100)) == (100, 120)
    assert gcv.crop_shape((50, 60), (101, 101)) is None


@pytest.mark.parametrize(
    ("ratio", "trusted"), [(2.0, True), (0.5, True), (3.0, False), (1 / 3.0, False)]
)
def test_gcv_is_trusted_within_a_factor_2_5_of_the_datas_noise(ratio, trusted):
    """Wiener's automatic ``lam`` is GCV's where GCV's noise and the given noise sigma
    agree within 2.5x either way (``GCV_TRUST``), else the prior fit's: GCV's noise 2x
    and 0.5x the given sigma keep GCV's ``lam``; 3x and 1/3 do not."""
    from pipeline.core.deconvolve.dispatch import plan

    y, kernel = one_sided_scene("reflect")
    lam_gcv, noise = gcv.gcv_regularization(
        y, gcv.kernel_grid(gcv.crop_shape(y.shape, kernel.shape), kernel)
    )
    p = plan(y, kernel, method="wiener", noise_sigma=noise / ratio)
    assert (float(p.params["lam"][0]) == pytest.approx(lam_gcv, rel=1e-9)) == trusted
