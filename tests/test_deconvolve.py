"""Deconvolution (Sec. 4.2-4.3): hard cases, invariants and quality against ground truth."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage, signal
from skimage import data

from pipeline.core import deconvolve as dc
from pipeline.errors import InputError

METHODS = ["wiener", "rl", "sparse"]
FAST = {"wiener": {}, "rl": {"iterations": 15}, "sparse": {"iterations": 15}}


def disk_kernel(radius: float, supersample: int = 8) -> np.ndarray:
    """Pillbox rasterised by supersampling (independent of pipeline.psf)."""
    half = int(np.ceil(radius))
    side = 2 * half + 1
    c = (np.arange(side * supersample) + 0.5) / supersample - side / 2
    inside = (c[:, None] ** 2 + c[None, :] ** 2 <= radius**2).astype(float)
    k = inside.reshape(side, supersample, side, supersample).mean(axis=(1, 3))
    return k / k.sum()


def blur(x: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Direct linear convolution of the scene extended by reflection (a wider scene)."""
    r0, r1 = k.shape[0] // 2, k.shape[1] // 2
    return signal.fftconvolve(np.pad(x, ((r0, r0), (r1, r1)), mode="symmetric"), k, "valid")


def psnr(estimate: np.ndarray, truth: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((estimate.astype(np.float64) - truth) ** 2)))


@pytest.fixture(scope="module")
def camera() -> np.ndarray:
    """skimage camera, 256x256, sRGB -> linear [0, 1] float64 (the ground truth)."""
    u = data.camera()[::2, ::2] / 255.0
    return np.where(u <= 0.04045, u / 12.92, ((u + 0.055) / 1.055) ** 2.4)


@pytest.fixture(scope="module")
def noisy(camera):
    k = disk_kernel(7.5)
    y = blur(camera, k) + np.random.default_rng(7).normal(0.0, 0.01, camera.shape)
    return y.astype(np.float32), k


# ----------------------------------------------------------------------------- validation
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_image_rejected(bad):
    y = np.full((16, 16), 0.5, np.float32)
    y[3, 4] = bad
    with pytest.raises(InputError, match="image"):
        dc.deconvolve(y, np.ones((3, 3)) / 9)


@pytest.mark.parametrize(
    "kernel",
    [np.ones((2, 3)) / 6, np.ones((3, 3)), -np.eye(3) / 3 + 2 * np.ones((3, 3)) / 9,
     np.ones(3) / 3, np.full((3, 3), np.nan)],
    ids=["even", "sum9", "negative", "1d", "nan"],
)
def test_bad_kernel_rejected(kernel):
    with pytest.raises(InputError, match="kernel"):
        dc.deconvolve(np.zeros((8, 8)), kernel)


def test_bad_method_and_options_rejected():
    y, k = np.zeros((8, 8)), np.ones((1, 1))
    with pytest.raises(InputError, match="method"):
        dc.deconvolve(y, k, method="blind")
    with pytest.raises(InputError, match="prior"):
        dc.wiener(y, k, prior="cauchy")
    with pytest.raises(InputError, match="alpha"):
        dc.sparse(y, k, alpha=1.5)


# ----------------------------------------------------------------------------- noise estimate
@pytest.mark.parametrize("sigma", [0.003, 0.02])
def test_noise_sigma_estimate(sigma):
    rows, cols = np.mgrid[0:256, 0:256] / 256.0
    smooth = 0.3 + 0.4 * np.sin(3 * rows) * np.cos(2 * cols)
    y = smooth + np.random.default_rng(1).normal(0, sigma, smooth.shape)
    assert dc.estimate_noise_sigma(y) == pytest.approx(sigma, rel=0.06)
    stacked = np.stack([y, 2 * y], axis=-1)
    np.testing.assert_allclose(dc.estimate_noise_sigma(stacked), [sigma, 2 * sigma], rtol=0.06)


def test_noise_sigma_ignores_saturated_blocks():
    y = np.random.default_rng(2).normal(0.5, 0.01, (128, 128))
    y[:, :100] = 1.0  # clipped: zero detail there would bias the median down
    assert dc.estimate_noise_sigma(y, saturation=1.0) == pytest.approx(0.01, rel=0.15)


@pytest.mark.parametrize(
    "values",
    [
        np.abs(np.random.default_rng(0).normal(size=262_144)),  # Haar coefficients' shape
        np.round(np.random.default_rng(1).random(100_001) * 20) / 20,  # ties, odd count
        np.sort(np.random.default_rng(2).random(50_000)),  # a regular sample of a sorted array
        np.tile(np.random.default_rng(3).random(7), 20_000),  # periodic: the sample misses
        np.r_[np.random.default_rng(4).random(30_000), np.inf, np.inf],
        np.r_[np.random.default_rng(5).random(30_000), np.nan],
        np.random.default_rng(6).random(999),  # small: np.median itself
    ],
)
def test_exact_median_is_np_median(values):
    """The noise estimates' median (a bracketed partition) is np.median's number."""
    from pipeline.core.deconvolve.common import exact_median

    want = np.median(values)
    got = exact_median(values.copy())
    assert got == want or (np.isnan(want) and np.isnan(got))


# ----------------------------------------------------------------------------- hard cases
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("size", [1, 5])
def test_delta_kernel_returns_input(method, size):
    y = np.random.default_rng(3).uniform(0.1, 1.0, (40, 52)).astype(np.float32)
    k = np.zeros((size, size))
    k[size // 2, size // 2] = 1.0
    out = dc.deconvolve(y, k, method=method, noise_sigma=0.0)
    assert out.dtype == np.float32 and out.shape == y.shape
    np.testing.assert_allclose(out, y, atol=2e-3)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("shape", [(33, 40), (30, 41, 3)])
def test_constant_image_stays_constant(method, shape):
    y = np.full(shape, 0.37)
    out = dc.deconvolve(y, disk_kernel(4.5), method=method, **FAST[method])
    assert out.dtype == np.float64 and out.shape == shape
    np.testing.assert_allclose(out, 0.37, atol=1e-6)


@pytest.mark.parametrize("method", METHODS)
def test_zero_image_and_zero_pixels(method):
    y = np.zeros((32, 32), np.float32)
    out = dc.deconvolve(y, disk_kernel(3.5), method=method, **FAST[method])
    assert np.all(np.isfinite(out)) and np.abs(out).max() < 1e-3
    y[8:20, 8:20] = 0.8  # zeros next to signal: RL's ratio must stay defined
    out = dc.deconvolve(y, disk_kernel(3.5), method=method, **FAST[method])
    assert np.all(np.isfinite(out))


@pytest.mark.parametrize("method", METHODS)
def test_zero_noise_and_spectral_zeros_improve(camera, method):
    k = disk_kernel(5.5)  # pillbox: |K| has rings of zeros
    y = blur(camera, k).astype(np.float32)
    out = dc.deconvolve(y, k, method=method)
    assert np.all(np.isfinite(out))
    assert psnr(out, camera) > psnr(y, camera) + 1.0


@pytest.mark.parametrize("method", METHODS)
def test_huge_kernel(camera, method):
    k = disk_kernel(100.0)  # 201 px on a 256 px frame
    y = (blur(camera, k) + np.random.default_rng(4).normal(0, 0.01, camera.shape))
    out = dc.deconvolve(y.astype(np.float32), k, method=method, **FAST[method])
    assert out.shape == camera.shape and out.dtype == np.float32
    assert np.all(np.isfinite(out))
    assert np.abs(out).max() < 10.0


def test_rl_negative_pixels_keep_nonnegative_output():
    y = np.random.default_rng(5).normal(0.0, 0.05, (48, 48))
    out = dc.richardson_lucy(y, disk_kernel(2.5), iterations=10)
    assert np.all(np.isfinite(out)) and out.min() >= 0.0


def _bright_blob_scene():
    rows, cols = np.mgrid[0:96, 0:96]
    x = 0.2 + 0.1 * np.sin(cols / 5.0) * np.cos(rows / 7.0)
    x[(rows - 48) ** 2 + (cols - 48) ** 2 < 10**2] = 6.0  # far above the clip level
    return x


@pytest.mark.parametrize("method", ["rl", "sparse"])
def test_saturated_pixels_excluded(method):
    x = _bright_blob_scene()
    k = disk_kernel(3.5)
    y = np.minimum(blur(x, k) + np.random.default_rng(6).normal(0, 0.002, x.shape), 1.0)
    near = (blur((x > 1.0).astype(float), np.ones((21, 21)) / 441) > 0) & (y < 1.0)
    naive = dc.deconvolve(y, k, method=method, noise_sigma=0.002)
    masked = dc.deconvolve(y, k, method=method, noise_sigma=0.002, saturation=1.0)
    assert np.all(np.isfinite(masked))
    err_naive = np.sqrt(np.mean((naive - x)[near] ** 2))
    err_masked = np.sqrt(np.mean((masked - x)[near] ** 2))
    # RL/sparse drop clipped pixels from the data term (Wiener is linear: the main job
    # keeps its clipped pixels at least at their observed value, see test_tiling)
    assert err_masked < 0.7 * err_naive


# ----------------------------------------------------------------------------- invariants
@pytest.mark.parametrize("method", METHODS)
def test_channels_are_independent(method):
    rng = np.random.default_rng(8)
    y = rng.uniform(0.0, 1.0, (24, 30, 3)).astype(np.float32)
    k = disk_kernel(2.5)
    out = dc.deconvolve(y, k, method=method, noise_sigma=[0.01, 0.02, 0.03], **FAST[method])
    for c, s in enumerate([0.01, 0.02, 0.03]):
        single = dc.deconvolve(y[..., c], k, method=method, noise_sigma=s, **FAST[method])
        np.testing.assert_allclose(out[..., c], single, atol=1e-6)


def test_wiener_is_exact_inverse_without_noise():
    """Gaussian blur (no spectral zeros) of a smooth periodic-free scene, tiny lam."""
    x = ndimage.gaussian_filter(np.random.default_rng(9).uniform(0, 1, (64, 64)), 3.0)
    g = np.exp(-np.arange(-4, 5) ** 2 / 2.0)
    k = np.outer(g, g) / np.outer(g, g).sum()
    y = blur(x, k)
    out = dc.wiener(y, k, regularization=1e-6)
    assert np.abs(out - x)[8:-8, 8:-8].max() < 5e-3


@settings(max_examples=30, deadline=None)
@given(
    v=st.floats(-3.0, 3.0),
    t=st.floats(1e-3, 0.5),
    alpha=st.sampled_from([0.5, 0.8, 1.0]),
)
def test_hyper_laplacian_prox_is_the_minimiser(v, t, alpha):
    w = float(dc.hyper_laplacian_prox(np.array([v, 3.5]), t, alpha)[0])
    grid = np.linspace(-3.5, 3.5, 70001)  # brute force
    objective = t * np.abs(grid) ** alpha + 0.5 * (grid - v) ** 2
    best = objective.min()
    assert t * abs(w) ** alpha + 0.5 * (w - v) ** 2 <= best + 1e-6


# ----------------------------------------------------------------------------- quality
def test_quality_against_ground_truth(camera, noisy):
    y, k = noisy
    scores = {m: psnr(dc.deconvolve(y, k, method=m), camera) for m in METHODS}
    blurred = psnr(y, camera)
    print(f"PSNR blurred {blurred:.2f} dB, " + ", ".join(f"{m} {s:.2f}" for m, s in scores.items()))
    assert all(s > blurred + 1.0 for s in scores.values())
    assert scores["sparse"] > scores["wiener"] + 0.3


def test_natural_prior_beats_white_prior(camera, noisy):
    y, k = noisy
    natural = psnr(dc.wiener(y, k, prior="natural"), camera)
    white = psnr(dc.wiener(y, k, prior="white"), camera)
    assert natural > white


def test_no_ringing_from_frame_edges(camera, noisy):
    """The border band is restored about as well as the interior (no edge ringing)."""
    y, k = noisy
    for method in METHODS:
        err = (dc.deconvolve(y, k, method=method) - camera) ** 2
        border = np.ones(err.shape, bool)
        border[16:-16, 16:-16] = False
        assert np.sqrt(err[border].mean()) < 1.5 * np.sqrt(err[~border].mean()), method


@pytest.mark.parametrize("shape", [(64, 48), (12, 10)])
def test_kernel_variance_equals_direct_spectral_variance(shape):
    """V from autocorrelations == mean |K_u - K|^2 of the kernels placed on the same periodic
    grid by explicit loops. On the 12 x 10 grid the kernels' lags (2k - 1 = 17) exceed it (a
    blur as wide as a small frame): V is then that of the kernels wrapped onto it."""
    rng = np.random.default_rng(3)
    samples = rng.random((5, 9, 9))
    samples[:, :, :3] *= 3.0  # asymmetric
    samples /= samples.sum(axis=(1, 2), keepdims=True)
    mean = samples.mean(axis=0)
    variance = dc.kernel_variance(samples, mean)((shape[0], shape[1] // 2 + 1))

    def wrapped_rfft(k):
        grid = np.zeros(shape)
        for i in range(9):
            for j in range(9):
                grid[(i - 4) % shape[0], (j - 4) % shape[1]] += k[i, j]
        return np.fft.rfft2(grid)

    direct = np.mean([np.abs(wrapped_rfft(k) - wrapped_rfft(mean)) ** 2 for k in samples], axis=0)
    np.testing.assert_allclose(variance, direct, atol=1e-12)


def test_kernel_samples_shape_is_checked():
    with pytest.raises(InputError, match="kernel_samples"):
        dc.kernel_variance(np.ones((3, 5, 5)), np.ones((7, 7)))


# ----------------------------------------------------------------------------- Richardson-Lucy
def _rl_case(seed=11):
    rng = np.random.default_rng(seed)
    x = ndimage.gaussian_filter(rng.uniform(0.2, 1.0, (40, 44)), 1.5)
    k = np.zeros((5, 7))
    k[2, 1:] = [0.1, 0.15, 0.2, 0.25, 0.2, 0.1]  # one-sided: the adjoint must be flipped
    y = blur(x, k) + rng.normal(0.0, 0.01, x.shape)
    return y, k / k.sum()


def test_damped_rl_limits_are_plain_rl_and_no_update():
    """White (1994): residuals far above ``damping * sigma`` update as plain RL does, residuals
    far below it not at all (the estimate stays the data)."""
    y, k = _rl_case()
    plain = dc.richardson_lucy(y, k, iterations=6, noise_sigma=0.01)
    sharp = dc.richardson_lucy(y, k, iterations=6, noise_sigma=0.01, damping=1e-9)
    np.testing.assert_allclose(sharp, plain, rtol=1e-9, atol=1e-12)
    assert np.abs(plain - y).max() > 0.05  # plain RL did change the frame
    frozen = dc.richardson_lucy(y, k, iterations=6, noise_sigma=0.01, damping=1e9)
    np.testing.assert_allclose(frozen, y, rtol=1e-12, atol=1e-12)
    for bad in (0.0, -1.0):
        with pytest.raises(InputError, match="damping"):
            dc.richardson_lucy(y, k, damping=bad)


def test_rl_transfer_is_the_iterated_landweber_step():
    """The closed form against ``n`` explicit steps ``X <- X + conj(K) (Y - K X)``, ``X0 = Y``."""
    from pipeline.core.deconvolve.rl import _rl_transfer

    rng = np.random.default_rng(12)
    k_fft = rng.uniform(0.0, 1.0, 200) * np.exp(1j * rng.uniform(-np.pi, np.pi, 200))
    k_fft[:3] = [0.0, 1e-7, 1.0]  # a spectral zero, a near zero (the series branch), no blur
    for n in (0, 1, 7, 30):
        x = np.ones_like(k_fft)
        for _ in range(n):
            x = x + np.conj(k_fft) * (1.0 - k_fft * x)
        np.testing.assert_allclose(_rl_transfer(n)(k_fft, None), x, rtol=1e-9, atol=1e-12)
