"""Richardson-Lucy against an independent direct-sum implementation (issue 11).

The reference below uses no FFT and none of ``pipeline.core.deconvolve``: the unknown
scene is the frame plus one kernel radius all round, the forward model is the "valid"
direct convolution (``scipy.signal.convolve2d``), its adjoint the "full" direct
correlation. Kernels are one-sided (a flipped kernel or a missing adjoint flip fails),
frames are small (each test well under a second).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from pipeline.core import deconvolve as dc
from pipeline.errors import InputError

# ----------------------------------------------------------------------------- mutation kills
N_DAMP = 10  # White (1994)'s N, as the module documents it


def _reference_channel(y, valid, k, iterations, background, threshold):
    """Masked RL with unknown boundaries, in direct sums (float64)."""
    m0, m1 = k.shape[0] // 2, k.shape[1] // 2
    mask = valid.astype(np.float64)
    data = y + background
    norm = signal.correlate2d(mask, k, mode="full")  # K^T M on the extended scene
    reached = norm > 1e-6 * norm.max()
    x = np.maximum(np.pad(y, ((m0, m0), (m1, m1)), mode="symmetric"), 1e-3 * background)
    for _ in range(iterations):
        model = np.maximum(signal.convolve2d(x, k, mode="valid"), 0.0) + background
        if threshold is None:
            ratio = data / model
        else:
            r = data - model
            u = np.minimum((r / threshold) ** 2, 1.0)
            ratio = 1.0 + u ** (N_DAMP - 1) * (N_DAMP - (N_DAMP - 1) * u) * r / model
        back = signal.correlate2d(mask * ratio, k, mode="full")
        x = np.where(reached, np.maximum(x * back / np.where(reached, norm, 1.0), 0.0), x)
    return x[m0:m0 + y.shape[0], m1:m1 + y.shape[1]]


def _background(yc, sigma):
    """``max(0, -min y) + max(sigma, 1e-3 max|y|)`` (the docstring's formula)."""
    return max(0.0, -float(yc.min())) + max(sigma, 1e-3 * float(np.abs(yc).max()))


def _one_sided_kernel():
    k = np.zeros((5, 7))
    k[2, 3:] = [0.3, 0.25, 0.15, 0.1]  # the centre and to its right only
    k[3, 3] = 0.12
    k[4, 4] = 0.08  # and below: asymmetric on both axes
    return k / k.sum()


def _scene(seed=3, shape=(14, 17)):
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.1, 1.0, shape)
    x[4:7, 5:9] = 3.0  # a bright block: large ratios, saturation
    return x


def _blurred(x, k, rng, sigma):
    m0, m1 = k.shape[0] // 2, k.shape[1] // 2
    wide = np.pad(x, ((m0, m0), (m1, m1)), mode="symmetric")
    return signal.convolve2d(wide, k, mode="valid") + rng.normal(0.0, sigma, x.shape)


@pytest.mark.parametrize("iterations", [1, 4])
def test_rl_equals_a_direct_sum_implementation_per_channel(iterations):
    """Two channels with their own noise level and background (one has negative pixels);
    saturated pixels are out of the data term."""
    k = _one_sided_kernel()
    rng = np.random.default_rng(4)
    c0 = _blurred(_scene(3), k, rng, 0.02)
    c1 = _blurred(_scene(5), k, rng, 0.05) - 0.4  # negative pixels: background > guard
    y = np.stack([c0, c1], axis=-1)
    sigma = [0.02, 0.05]
    sat = 2.0
    out = dc.richardson_lucy(y, k, iterations=iterations, noise_sigma=sigma, saturation=sat)
    assert out.shape == y.shape and out.dtype == np.float64
    for c in range(2):
        yc = y[..., c]
        ref = _reference_channel(yc, yc < sat, k, iterations, _background(yc, sigma[c]), None)
        np.testing.assert_allclose(out[..., c], ref, rtol=1e-9, atol=1e-11)
    assert np.abs(out - y).max() > 0.05  # it did something


def test_rl_with_a_mask_that_leaves_margin_pixels_unreached():
    """A whole masked column band: the extended-scene pixels that only masked data reach
    keep their first estimate; the rest is the reference."""
    k = _one_sided_kernel()
    rng = np.random.default_rng(6)
    y = _blurred(_scene(7), k, rng, 0.01)
    y[:, :6] = 5.0  # saturated band at the left edge
    out = dc.richardson_lucy(y, k, iterations=3, noise_sigma=0.01, saturation=4.0)
    ref = _reference_channel(y, y < 4.0, k, 3, _background(y, 0.01), None)
    np.testing.assert_allclose(out, ref, rtol=1e-9, atol=1e-11)
    # a frame pixel inside the band no valid datum reaches: its start value, not updated
    assert out[3, 0] == pytest.approx(5.0, rel=1e-12)


def test_rl_reach_threshold_is_relative_to_the_best_reached_pixel():
    """``K^T M`` below 1e-6 of its maximum is "unreached". With half the pixels masked
    (a checkerboard: the maximum is 0.7, not 1) a 1e-6 tap still reaches the margin
    pixels only it touches, and they are updated (a threshold of ``1e-6 / max`` or
    ``1e-6 ** max`` would leave them, and the frame edge next to them, different)."""
    k = np.zeros((3, 5))
    k[1, 2:] = [0.5, 0.3, 0.2 - 1e-6]
    k[0, 0] = 1e-6  # the only tap reaching the bottom-right margin
    rng = np.random.default_rng(13)
    y = _blurred(_scene(14, (12, 15)), k, rng, 0.01)
    checker = (np.indices(y.shape).sum(axis=0) % 2).astype(bool)
    y[checker] = 9.0  # saturated: out of the data term
    out = dc.richardson_lucy(y, k, iterations=3, noise_sigma=0.01, saturation=5.0)
    ref = _reference_channel(y, ~checker, k, 3, _background(y, 0.01), None)
    np.testing.assert_allclose(out, ref, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("damping", [1.5, 4.0])
def test_damped_rl_equals_the_direct_sum_implementation(damping):
    """Between the limits the existing tests check: residuals of about the threshold,
    where White's ``u^(N-1) (N - (N-1) u)`` is neither 0 nor 1."""
    k = _one_sided_kernel()
    rng = np.random.default_rng(8)
    sigma = 0.03
    y = _blurred(_scene(9), k, rng, sigma)
    out = dc.richardson_lucy(y, k, iterations=3, noise_sigma=sigma, damping=damping)
    ref = _reference_channel(y, np.ones(y.shape, bool), k, 3, _background(y, sigma),
                             damping * sigma)
    np.testing.assert_allclose(out, ref, rtol=1e-9, atol=1e-11)
    plain = _reference_channel(y, np.ones(y.shape, bool), k, 3, _background(y, sigma), None)
    assert np.abs(out - plain).max() > 1e-3  # the damping mattered
    assert np.abs(out - y).max() > 1e-3  # and did not freeze it


def test_rl_background_guard_takes_the_larger_of_sigma_and_a_thousandth_of_the_peak():
    """The plan's background per channel: ``max(0, -min) + max(sigma, 1e-3 max|y|)``, with a
    1e-12 floor; the damping threshold is ``damping * sigma``."""
    y = np.zeros((9, 11, 3))
    y[..., 0] = np.linspace(0.5, 40.0, 99).reshape(9, 11)  # 1e-3 * 40 = 0.04 > sigma
    y[..., 1] = np.linspace(-0.7, 2.0, 99).reshape(9, 11)  # -min = 0.7; sigma wins
    y[..., 2] = 0.0  # all zero, sigma 0: the 1e-12 floor
    k = _one_sided_kernel()
    p = dc.plan(y, k, method="rl", noise_sigma=[0.01, 0.2, 0.0], iterations=2)
    np.testing.assert_allclose(p.params["background"], [0.04, 0.9, 1e-12], rtol=1e-12)
    assert p.params["threshold"] is None and p.params["iterations"] == 2
    d = dc.plan(y, k, method="rl", noise_sigma=[0.01, 0.2, 0.0], damping=3.0)
    np.testing.assert_allclose(d.params["threshold"], [0.03, 0.6, 3e-12], rtol=1e-12)
    assert d.params["iterations"] == 30  # the default


def test_rl_zero_iterations_is_the_floored_start():
    """No step: the output is the start, ``max(y, 1e-3 b)``: the data where positive."""
    k = _one_sided_kernel()
    y = np.linspace(-0.5, 1.5, 14 * 17).reshape(14, 17)
    out = dc.richardson_lucy(y, k, iterations=0, noise_sigma=0.1)
    b = _background(y, 0.1)
    np.testing.assert_allclose(out, np.maximum(y, 1e-3 * b), rtol=0, atol=0)
    for bad in (-1, 2.5):
        with pytest.raises(InputError, match="iterations"):
            dc.richardson_lucy(y, k, iterations=bad)


def test_rl_float32_follows_the_reference():
    k = _one_sided_kernel()
    rng = np.random.default_rng(10)
    y = _blurred(_scene(11), k, rng, 0.02)
    out = dc.richardson_lucy(y.astype(np.float32), k, iterations=4, noise_sigma=0.02)
    assert out.dtype == np.float32
    ref = _reference_channel(y.astype(np.float32).astype(np.float64), np.ones(y.shape, bool),
                             k, 4, _background(y, 0.02), None)
    np.testing.assert_allclose(out, ref, rtol=2e-4, atol=2e-5)


def test_rl_tile_depth_is_the_filters_support_plus_the_kernel_radius():
    """No step: the filter is the identity, the overlap the kernel's larger radius. One
    step: the linearised filter ``1 - K^T K + K^T`` reaches as far as the kernel's
    autocorrelation (here 3 px, 40 px), plus the radius; capped at the frame's larger side."""
    k = _one_sided_kernel()  # 5 x 7: radius 3; autocorrelation out to 3 px
    y = _blurred(_scene(12, (60, 64)), k, np.random.default_rng(0), 0.01)

    def depth(image, kernel, n):
        return dc.plan(image, kernel, method="rl", noise_sigma=0.01, iterations=n).depth

    assert depth(y, k, 0) == 3 and depth(y, k, 1) == 3 + 3
    wide = np.full((3, 41), 1.0 / 123)  # radius 20, autocorrelation out to 40 px
    assert depth(y, wide, 0) == 20 and depth(y, wide, 1) == 40 + 20
    assert depth(y[:10, :12], wide, 1) == 12 + 20  # the filter part capped at 12 px
