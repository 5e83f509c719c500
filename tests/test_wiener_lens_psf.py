"""Issue 14: automatic Wiener on single lens PSFs never makes an input worse than it was."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from skimage import data

from pipeline.core.colour import srgb_to_linear
from pipeline.core.deconvolve import deconvolve
from pipeline.core.psf import kernel_size, raster_pillbox


def psnr(a, b, border=20):
    return 10 * np.log10(1.0 / np.mean((a - b)[border:-border, border:-border] ** 2))


@pytest.fixture(scope="module")
def sharp():
    return srgb_to_linear(data.camera()[:256, :256] / 255.0)


@pytest.mark.parametrize("diameter", [5, 21, 45, 89])
@pytest.mark.parametrize("noise", [0.0, 0.01])
def test_pillbox_restoration_is_never_worse_than_its_input(sharp, diameter, noise):
    k = raster_pillbox(diameter, kernel_size(diameter) // 2)
    k = k / k.sum()
    blurred = ndimage.convolve(sharp, k, mode="reflect")
    if noise:
        blurred = blurred + np.random.default_rng(diameter).normal(0, noise, blurred.shape)
    assert psnr(deconvolve(blurred, k), sharp) >= psnr(blurred, sharp)


@pytest.mark.parametrize("noise", [0.003, 0.01, 0.03])
def test_a_delta_kernel_never_makes_a_noisy_input_worse(sharp, noise):
    """With a delta the "blurred" input is the image itself plus noise: Wiener only
    denoises (+0.08, +0.8, +1.0 dB), so returning the input would fail too."""
    delta = np.zeros((3, 3))
    delta[1, 1] = 1.0
    observed = sharp + np.random.default_rng(11).normal(0, noise, sharp.shape)
    assert psnr(deconvolve(observed, delta), sharp) >= psnr(observed, sharp) + 0.05


def test_a_delta_kernel_leaves_a_photograph_within_its_own_grain(sharp):
    """The 8-bit photograph's own grain reads as noise of std 0.0017 (0.4 levels), so a
    delta smooths it by at most that much, never more than 0.4 levels of 8 bits."""
    delta = np.zeros((3, 3))
    delta[1, 1] = 1.0
    assert np.abs(deconvolve(sharp, delta) - sharp).max() < 0.4 / 255


def test_a_delta_kernel_leaves_a_checkerboard_alone():
    """The Haar noise estimate read the board as noise of std 1.2 (a 0.34 change)."""
    delta = np.zeros((3, 3))
    delta[1, 1] = 1.0
    board = 0.1 + 0.8 * (np.indices((64, 64)).sum(0) % 2)
    assert np.abs(deconvolve(board, delta) - board).max() < 0.01


@pytest.mark.parametrize("sigma", [0.0, 0.01, 0.03])
def test_noise_under_a_pixel_scale_texture_is_measured_not_the_texture(sigma):
    """Checkerboard + white noise: the estimate is the noise (the board alone reads 1.2)."""
    from pipeline.core.deconvolve import estimate_noise_sigma

    board = 0.1 + 0.8 * (np.indices((256, 256)).sum(0) % 2)
    noisy = board + np.random.default_rng(3).normal(0, sigma, board.shape)
    assert estimate_noise_sigma(noisy) == pytest.approx(sigma, rel=0.08, abs=1e-9)
