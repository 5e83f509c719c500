"""``pipeline.core.deconvolve.dispatch`` (issue 11): the named wrappers against
``deconvolve`` with the method's own defaults, plan/restore per channel against
single-channel runs, the given noise level against the estimate, and the Wiener
spectra computed once per FFT grid and dtype."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import convolve, gaussian_filter

from pipeline.core.deconvolve import (
    deconvolve,
    dispatch,
    plan,
    restore,
    richardson_lucy,
    sparse,
    wiener,
)

KERNEL = np.zeros((5, 5))
KERNEL[2, 1:] = [0.1, 0.4, 0.3, 0.2]  # one-sided: a flip or a transpose would show


def _scene(shape=(26, 30), channels=None, sigma=0.01, seed=0):
    rng = np.random.default_rng(seed)
    full = (*shape, channels) if channels else shape
    x = gaussian_filter(rng.uniform(0.1, 0.9, full), (1.0, 1.0, 0)[: len(full)])
    y = np.stack([convolve(x[..., c], KERNEL, mode="nearest") for c in range(channels)], -1) \
        if channels else convolve(x, KERNEL, mode="nearest")
    return y + rng.normal(0.0, sigma, full)


def test_named_wrappers_use_the_methods_own_defaults():
    y = _scene()
    np.testing.assert_array_equal(wiener(y, KERNEL), deconvolve(y, KERNEL))
    np.testing.assert_array_equal(richardson_lucy(y, KERNEL), deconvolve(y, KERNEL, method="rl"))
    np.testing.assert_array_equal(sparse(y, KERNEL), deconvolve(y, KERNEL, method="sparse"))


def test_named_wrappers_forward_their_options():
    y = _scene(seed=1)
    y[3, 4] = 0.95
    cases = [
        (wiener, "wiener", dict(noise_sigma=0.02, prior="white", regularization=0.05,
                                saturation=0.9, kernel_samples=np.stack([KERNEL, KERNEL.T]))),
        (richardson_lucy, "rl", dict(iterations=4, damping=1.5, noise_sigma=0.02,
                                     saturation=0.9)),
        (sparse, "sparse", dict(alpha=0.6, weight=0.5, iterations=7, rho=(1e-2, 0.1),
                                noise_sigma=0.02, saturation=0.9)),
    ]
    for wrapper, method, options in cases:
        got = wrapper(y, KERNEL, **options)
        np.testing.assert_array_equal(got, deconvolve(y, KERNEL, method=method, **options))
        assert np.abs(got - wrapper(y, KERNEL)).max() > 1e-3  # the options changed it


@pytest.mark.parametrize("method", ["wiener", "rl"])
def test_restore_runs_each_channel_with_its_own_noise_level(method):
    y = _scene(channels=3, seed=2)
    sigmas = [0.01, 0.03, 0.02]
    extra = {"damping": 1.0} if method == "rl" else {}
    p = plan(y, KERNEL, method=method, noise_sigma=sigmas, **extra)
    np.testing.assert_array_equal(p.noise_sigma, sigmas)
    out = restore(y, p)
    assert out.shape == y.shape and out.dtype == np.float64
    for c in range(3):
        single = deconvolve(y[..., c], KERNEL, method=method, noise_sigma=sigmas[c], **extra)
        np.testing.assert_allclose(out[..., c], single, atol=1e-6)  # pad from 3 channels


def test_plan_estimates_the_noise_level_when_it_is_not_given():
    y = _scene(shape=(64, 64), sigma=0.02, seed=3)
    sigma = plan(y, KERNEL).noise_sigma
    assert sigma.shape == (1,)
    assert 0.015 < sigma[0] < 0.025  # the noise added, not the given-level path's zero
    assert plan(y, KERNEL, noise_sigma=0.005).noise_sigma[0] == 0.005


def test_wiener_spectra_are_computed_once_per_grid_and_dtype(monkeypatch):
    calls = []
    real = dispatch._wiener_spectra
    monkeypatch.setattr(dispatch, "_wiener_spectra",
                        lambda *a: calls.append(a[-1]) or real(*a))
    y = _scene(channels=2, seed=4)
    p = plan(y, KERNEL, noise_sigma=0.01)
    first = restore(y, p)
    again = restore(y, p)
    assert len(calls) == 1  # two channels, two restores: one computation
    np.testing.assert_array_equal(first, again)
    single = restore(y.astype(np.float32), p)
    assert single.dtype == np.float32 and len(calls) == 2
    assert [np.dtype(d) for d in calls] == [np.float64, np.float32]
    np.testing.assert_allclose(single, first, atol=1e-4)
    uncached = plan(y, KERNEL, noise_sigma=0.01)  # the same plan, nothing cached yet
    np.testing.assert_array_equal(single, restore(y.astype(np.float32), uncached))
    smaller = restore(y[:20], p)  # another grid: its own spectra
    assert len(calls) == 4
    np.testing.assert_array_equal(smaller, restore(y[:20], plan(y, KERNEL, noise_sigma=0.01)))
