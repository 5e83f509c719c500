"""The quality method (``pipeline.core.deconvolve.sparse``) against independent facts: the
hyper-Laplacian prox's non-zero branch is the larger root of its stationarity equation
(found here by bracketing with ``scipy.optimize.brentq``, no Newton table), and ADMM treats
the two gradient directions alike, so transposing the image and the (one-sided) kernel
transposes the result."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage, optimize

from pipeline.core import deconvolve as dc


def _larger_root(v: float, t: float, a: float) -> float:
    """The larger root of ``w - v + t a w^(a-1) = 0`` on ``(w*, v]``, ``w*`` the minimum of
    the left side (where its derivative ``1 + t a (a-1) w^(a-2)`` vanishes)."""
    w_star = (t * a * (1.0 - a)) ** (1.0 / (2.0 - a))
    return optimize.brentq(lambda w: w - v + t * a * w ** (a - 1.0), w_star, v, xtol=1e-14)


@pytest.mark.parametrize(("t", "alpha"), [(0.5, 0.5), (2.0, 0.8), (0.05, 0.3)])
def test_the_prox_above_its_threshold_is_the_stationary_points_larger_root(t, alpha):
    c = 2.0 * t * (1.0 - alpha)
    tau = (2.0 - alpha) / (2.0 * (1.0 - alpha)) * c ** (1.0 / (2.0 - alpha))
    v = np.concatenate([np.linspace(1.0005 * tau, 1.6 * tau, 40), -np.linspace(1.1, 1.5, 5) * tau])
    got = dc.hyper_laplacian_prox(v, t, alpha)
    want = np.sign(v) * np.array([_larger_root(abs(x), t, alpha) for x in v])
    np.testing.assert_allclose(got, want, rtol=0, atol=5e-8 * tau)  # the table: 2e-8
    assert np.all(dc.hyper_laplacian_prox(0.999 * tau * np.array([1.0, -1.0]), t, alpha) == 0)


def test_transposing_image_and_kernel_transposes_the_result():
    rng = np.random.default_rng(3)
    x = ndimage.gaussian_filter(rng.uniform(0, 1, (48, 56)), 1.0)
    kernel = np.zeros((7, 7))
    kernel[3, 2:7] = [0.1, 0.4, 0.2, 0.15, 0.05]  # one-sided on both axes
    kernel[0:3, 5] = [0.03, 0.03, 0.04]
    kernel /= kernel.sum()
    y = ndimage.convolve(x, kernel, mode="reflect") + rng.normal(0, 0.01, x.shape)
    options = dict(method="sparse", iterations=12, noise_sigma=0.01)
    out = dc.deconvolve(y, kernel, **options)
    flipped = dc.deconvolve(np.ascontiguousarray(y.T), np.ascontiguousarray(kernel.T), **options)
    np.testing.assert_allclose(flipped.T, out, rtol=0, atol=1e-9)
    assert np.abs(out - y).max() > 1e-3  # it did deconvolve
