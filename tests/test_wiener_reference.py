"""Wiener deconvolution against an independent implementation (issue 11, mutation kills of
``core/deconvolve/wiener.py`` and ``common.py``).

The reference below builds the filter ``conj(K) / (|K|^2 + V + lam |D|^2)`` with full
complex FFTs (``np.fft.fft2``), the kernel rolled to the origin by hand and ``|D|^2``
from the FFTs of the two forward-difference stencils, on the frame's mirror-periodic
domain (``[y, flip(y)]`` in each direction). That is the module's boundary model for a
filter that reaches across the frame; for a shorter filter the module reflects the frame
only as far as the filter reaches and fades beyond, which changes the result by less
than the filter's tail (1e-5 of the data range). Kernels are one-sided, so a flip or a
missing conjugate shows.
"""

from __future__ import annotations

import importlib

import numpy as np
import pytest

from pipeline.core import deconvolve as dc
from pipeline.core.deconvolve import common
from pipeline.errors import InputError

# the module, not the package's ``wiener`` function of the same name
wiener = importlib.import_module("pipeline.core.deconvolve.wiener")


def _on_grid(kernel: np.ndarray, shape) -> np.ndarray:
    """``kernel`` on a periodic grid of ``shape``, its centre pixel at (0, 0)."""
    grid = np.zeros(shape)
    grid[: kernel.shape[0], : kernel.shape[1]] = kernel
    return np.roll(grid, (-(kernel.shape[0] // 2), -(kernel.shape[1] // 2)), axis=(0, 1))


def _difference_power(shape) -> np.ndarray:
    """``|D_x|^2 + |D_y|^2`` from the FFTs of the stencils x[i+1] - x[i]."""
    dx, dy = np.zeros(shape), np.zeros(shape)
    dx[0, 0], dx[0, -1] = -1.0, 1.0  # (D x)[j] = x[j+1] - x[j]: correlation with [-1, 1]
    dy[0, 0], dy[-1, 0] = -1.0, 1.0
    return np.abs(np.fft.fft2(dx)) ** 2 + np.abs(np.fft.fft2(dy)) ** 2


def _regulariser(prior, shape):
    """The regulariser's full-grid spectrum: forward differences, or flat without the mean."""
    if prior == "natural":
        return _difference_power(shape)
    reg = np.ones(shape)
    reg[0, 0] = 0.0
    return reg


def reference_wiener(y, kernel, lam, prior="natural", samples=None):
    rows, cols = y.shape
    mirrored = np.block([[y, y[:, ::-1]], [y[::-1, :], y[::-1, ::-1]]])
    shape = mirrored.shape
    k_fft = np.fft.fft2(_on_grid(kernel, shape))
    reg = _regulariser(prior, shape)
    variance = 0.0
    if samples is not None:
        variance = np.mean(
            [np.abs(np.fft.fft2(_on_grid(s, shape)) - k_fft) ** 2 for s in samples], axis=0
        )
    x = np.conj(k_fft) * np.fft.fft2(mirrored) / (np.abs(k_fft) ** 2 + variance + lam * reg)
    return np.fft.ifft2(x).real[:rows, :cols]


def _one_sided_kernel(rows=5, cols=7):
    k = np.zeros((rows, cols))
    k[rows // 2, cols // 2 :] = np.arange(cols - cols // 2, 0, -1)  # a comet to the right
    k[rows // 2 + 1 :, cols // 2] = 0.5  # and a short tail down
    return k / k.sum()


def _scene(shape, seed=0):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    smooth = 0.5 + 0.2 * np.sin(0.3 * xx + 0.1 * yy) * np.cos(0.17 * yy)
    return smooth + 0.05 * rng.standard_normal(shape)


@pytest.mark.parametrize("prior", ["natural", "white"])
def test_a_filter_wider_than_the_frame_is_the_mirror_periodic_wiener_filter(prior):
    y = _scene((22, 30))
    kernel = _one_sided_kernel()
    lam = 1e-3
    p = dc.plan(y, kernel, method="wiener", noise_sigma=0.01, regularization=lam, prior=prior)
    assert p.params["pad"] >= min(y.shape)  # the mirror-periodic domain, no taper
    got = dc.restore(y, p)
    assert np.allclose(got, reference_wiener(y, kernel, lam, prior), rtol=0, atol=1e-10)


@pytest.mark.parametrize("shape", [(96, 112), (101, 87)])
def test_reflect_and_fade_agrees_with_the_mirror_periodic_filter(shape):
    """(The white prior's filter reaches across any frame: its DC is not regularised.)"""
    prior = "natural"
    y = _scene(shape, seed=1)
    kernel = _one_sided_kernel()
    lam = 0.05
    p = dc.plan(y, kernel, method="wiener", noise_sigma=0.01, regularization=lam, prior=prior)
    assert p.params["pad"] < min(y.shape)  # the reflect-then-fade domain
    got = dc.wiener(y, kernel, noise_sigma=0.01, regularization=lam, prior=prior)
    expected = reference_wiener(y, kernel, lam, prior)
    assert np.abs(got - expected).max() < 2e-5  # the filter's tail beyond its reach


@pytest.mark.parametrize("transpose", [False, True])
def test_kernel_samples_add_their_spread_to_the_denominator(transpose):
    y = _scene((40, 36), seed=2)
    kernel = _one_sided_kernel().T if transpose else _one_sided_kernel()  # 7 x 5 or 5 x 7
    samples = np.stack([kernel, kernel[::-1, ::-1], np.roll(kernel, 1, axis=1)])
    mean = samples.mean(axis=0)
    got = dc.wiener(y, mean, noise_sigma=0.01, regularization=0.05, kernel_samples=samples)
    expected = reference_wiener(y, mean, 0.05, samples=samples)
    assert np.abs(got - expected).max() < 2e-5
    plain = dc.wiener(y, mean, noise_sigma=0.01, regularization=0.05)
    assert np.abs(plain - expected).max() > 1e-3  # the variance term matters here


def _gain_by_parseval(kernel, lam, prior, shape):
    """sqrt(mean |G|^2) over the full grid = sqrt(sum h^2) of the impulse response."""
    k_fft = np.fft.fft2(_on_grid(kernel, shape))
    reg = _regulariser(prior, shape)
    h = np.fft.ifft2(np.conj(k_fft) / (np.abs(k_fft) ** 2 + lam * reg)).real
    return float(np.sqrt(np.sum(h**2)))


@pytest.mark.parametrize("prior", ["natural", "white"])
@pytest.mark.parametrize("shape", [(64, 48), (50, 45), (33, 64)])
def test_white_noise_gain_is_the_impulse_responses_norm(prior, shape):
    kernel = _one_sided_kernel()
    for lam in (1e-4, 1e-2, 1.0):
        got = wiener.white_noise_gain(kernel, lam, prior, shape)
        assert got == pytest.approx(_gain_by_parseval(kernel, lam, prior, shape), rel=1e-10)


def test_white_noise_gain_by_default_grid_is_a_fine_one():
    kernel = _one_sided_kernel()
    got = wiener.white_noise_gain(kernel, 1e-3)
    assert got == pytest.approx(_gain_by_parseval(kernel, 1e-3, "natural", (256, 256)), rel=1e-3)


@pytest.mark.parametrize("prior", ["natural", "white"])
def test_lam_for_noise_gain_is_the_smallest_lam_within_the_target(prior):
    kernel = _one_sided_kernel()
    for target in (1.2, 2.5):  # 3.6 at the floor
        lam = wiener.lam_for_noise_gain(kernel, target, prior)
        assert wiener.white_noise_gain(kernel, lam, prior) <= target
        assert wiener.white_noise_gain(kernel, lam / 1.03, prior) > target  # ~1% bisection
    # a point kernel never amplifies noise: the floor is enough
    assert wiener.lam_for_noise_gain(np.ones((1, 1)), 1.0, prior) == common._LAM_MIN
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(InputError, match="noise_gain"):
            wiener.lam_for_noise_gain(kernel, bad, prior)


def test_the_automatic_lam_is_never_below_the_noise_gain_limit():
    y = _scene((64, 64), seed=3)
    kernel = np.full((9, 9), 1 / 81)  # a box: gain 116 at the floor of lam
    for gain in (2.0, 5.0):
        p = dc.plan(y, kernel, method="wiener", noise_sigma=1e-6, noise_gain=gain)
        assert wiener.white_noise_gain(kernel, float(p.params["lam"][0])) <= gain
    p = dc.plan(y, kernel, method="wiener", noise_sigma=1e-6)  # the ceiling, 10
    assert wiener.white_noise_gain(kernel, float(p.params["lam"][0])) <= wiener.MAX_NOISE_GAIN
    assert wiener.white_noise_gain(kernel, float(p.params["lam"][0]) / 1.03) > 9.9


@pytest.mark.parametrize("frame", [(96, 112), (101, 87), (500, 333), (2000, 3001)])
def test_the_fft_grid_holds_the_reach_and_the_fade_and_little_more(frame):
    """Issue 15: the grid is the frame plus the reach and the fade on each side, rounded
    up to a fast length, not much larger (a 2250x2700 grid where 1890x2400 does)."""
    kernel = _one_sided_kernel()
    for pad in (0, 7, 40):
        grid, taper = wiener._wiener_grid(frame, kernel, pad)
        assert taper == wiener.TAPER_PX
        for side, n in zip(frame, grid, strict=True):
            need = side + 2 * (pad + wiener.TAPER_PX)
            assert need <= n <= 1.15 * need and n % 2 == 0
    grid, taper = wiener._wiener_grid(frame, kernel, min(frame))
    assert grid == (2 * frame[0], 2 * frame[1]) and taper is None


@pytest.mark.parametrize("prior", ["natural", "white"])
def test_the_filter_whose_reach_is_measured_is_the_filter_applied(prior):
    kernel = _one_sided_kernel()
    shape = (40, 36)
    samples = np.stack([kernel, kernel[::-1, ::-1]])
    half = shape[1] // 2 + 1
    k_fft = np.fft.rfft2(_on_grid(kernel, shape))
    d2 = _difference_power(shape)[:, :half]
    reg = d2 if prior == "natural" else np.where(np.arange(d2.size).reshape(d2.shape) == 0,
                                                 0.0, 1.0)
    for variance, v in ((None, 0.0), (dc.kernel_variance(samples, kernel), None)):
        if v is None:
            v = np.mean([np.abs(np.fft.rfft2(_on_grid(s, shape)) - k_fft) ** 2
                         for s in samples], axis=0)
        got = wiener._wiener_transfer(0.01, prior, variance)(k_fft, d2)
        expected = np.conj(k_fft) / (np.abs(k_fft) ** 2 + v + 0.01 * reg)
        assert np.allclose(got, expected, rtol=1e-12, atol=1e-12)


def test_white_prior_fit_uses_the_kernels_energy():
    """White scene of std s0 blurred by k plus noise sigma: var(y) = s0^2 sum(k^2) +
    sigma^2, so lam = sigma^2 / s0^2 (here sum(k^2) = 0.38, sum(k) = 1)."""
    rng = np.random.default_rng(7)
    s0, sigma = 0.1, 0.01
    kernel = np.array([[0.5, 0.3, 0.2]])  # no spectral zero: the gain floor stays at 1e-6
    x = 0.5 + s0 * rng.standard_normal((256, 256))
    y = np.real(np.fft.ifft2(np.fft.fft2(x) * np.fft.fft2(_on_grid(kernel, x.shape))))
    y += sigma * rng.standard_normal(y.shape)
    p = dc.plan(y, kernel, method="wiener", noise_sigma=sigma, prior="white", auto="prior")
    assert float(p.params["lam"][0]) == pytest.approx(sigma**2 / s0**2, rel=0.03)


@pytest.mark.parametrize("frame", [(30, 41), (37, 24)])
def test_taper_pad_reflects_then_fades_to_the_mean_by_a_raised_cosine(frame):
    """The frame at offset pad + taper, its mirror image for ``pad`` px all round, then a
    fade to the mean reaching it at the periodic wrap: the fade weight (the padded value's
    deviation from the mean over the mirror image's) rises from ~0 at the wrap to 1 at
    the reflection, a raised cosine (w[i] + w[-1 - i] = 1)."""
    rng = np.random.default_rng(4)
    y = rng.uniform(0.0, 1.0, frame)
    pad, taper = 5, 8
    shape = (frame[0] + 2 * (pad + taper) + 6, frame[1] + 2 * (pad + taper) + 3)  # uneven
    out = common._taper_pad(y, pad, taper, shape)
    assert out.shape == shape
    before = pad + taper
    mirror = np.pad(y, [(before, n - s - before) for s, n in zip(frame, shape, strict=True)],
                    mode="symmetric")
    inner = (slice(taper, before + frame[0] + pad), slice(taper, before + frame[1] + pad))
    assert np.array_equal(out[inner], mirror[inner])  # the frame and its reflection
    mean = y.mean()
    for axis in (0, 1):  # rows of the frame along the columns, and columns along rows
        line = slice(before, before + frame[1 - axis])
        o = out[:, line] if axis == 0 else out[line, :].T
        m = mirror[:, line] if axis == 0 else mirror[line, :].T
        weight = np.median((o - mean) / (m - mean), axis=1)  # one weight per row
        assert np.allclose((o - mean), weight[:, None] * (m - mean), atol=1e-12)
        n = shape[axis]
        s = frame[axis]
        for fade in (weight[:taper], weight[before + s + pad :][::-1]):
            assert np.all(np.diff(fade) > 0) and 0 < fade[0] < 0.05  # ~0 at the wrap
            assert np.allclose(fade + fade[::-1], 1.0)
        assert len(weight[before + s + pad :]) == n - before - s - pad
        assert np.allclose(weight[taper : before + s + pad], 1.0)


def test_pure_noise_gets_the_largest_natural_prior_lam():
    """A flat scene: all the gradient energy is the noise's own (4 sigma^2), so the fitted
    image gradient variance is at its floor, the noise's 4 sigma^2: lam = 1/4."""
    rng = np.random.default_rng(8)
    sigma = 0.02
    y = 0.5 + sigma * rng.standard_normal((128, 128))
    p = dc.plan(y, np.ones((1, 1)), method="wiener", noise_sigma=sigma, auto="prior")
    assert float(p.params["lam"][0]) == pytest.approx(0.25, rel=1e-12)
    p = dc.plan(y, np.ones((1, 1)), method="wiener", noise_sigma=sigma, prior="white", auto="prior")
    assert float(p.params["lam"][0]) == pytest.approx(1.0, rel=1e-12)  # floor sigma^2


def test_channels_run_on_channel_threads_only_inside_the_block():
    import threading

    def name(_c):
        return threading.current_thread().name

    caller = threading.current_thread().name
    assert common.map_channels(name, 3) == [caller] * 3  # serial by default
    with common.channel_threads(2):
        names = common.map_channels(name, 3)
        assert common.map_channels(name, 1) == [caller]  # one channel: no pool
    assert all(n.startswith("flexdof-channel") for n in names)
    with common.channel_threads(0):  # at least one thread: serial
        assert common.map_channels(name, 2) == [caller] * 2
    assert common.map_channels(lambda c: c * c, 4) == [0, 1, 4, 9]
    with common.channel_threads(3):
        assert common.map_channels(lambda c: c * c, 4) == [0, 1, 4, 9]  # in order


def test_the_overlap_depth_is_capped_at_the_frames_longer_side():
    """A 9 px box's natural-prior filter at lam 0.01 reaches ~240 px: on a 40 x 300 frame
    the plan's depth is that reach (more than the 40 rows, less than the 300 columns), on
    a 40 x 60 frame it is 60."""
    kernel = np.full((9, 9), 1 / 81)
    reach = dc.filter_depth(kernel, wiener._wiener_transfer(0.01, "natural"), limit=600)
    assert 40 < reach < 300
    for shape, depth in (((40, 300), reach), ((300, 40), reach), ((40, 60), 60)):
        y = _scene(shape, seed=5)
        p = dc.plan(y, kernel, method="wiener", noise_sigma=0.01, regularization=0.01)
        assert p.depth == depth


def test_kernel_samples_of_the_wrong_shape_are_named():
    with pytest.raises(InputError, match=r"shape \(n, 5, 7\), got \(2, 7, 5\)"):
        dc.kernel_variance(np.ones((2, 7, 5)), _one_sided_kernel())


@pytest.mark.parametrize("corner", [(0, 0), (0, 1), (1, 0), (1, 1)])
def test_noise_blocks_with_a_clipped_pixel_anywhere_are_left_out(corner):
    """One clipped pixel in every other 2 x 2 block, at each of the four places: those
    blocks' Haar details are the clipping, not noise, and must not enter the median."""
    rng = np.random.default_rng(6)
    y = rng.normal(0.5, 0.01, (128, 128))
    y[corner[0] :: 4, corner[1] :: 2] = 1.0  # every other block row, every block in it
    assert dc.estimate_noise_sigma(y, saturation=1.0) == pytest.approx(0.01, rel=0.15)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int32, np.float32])
def test_integer_and_float32_frames_are_deconvolved_like_float64(dtype):
    y = np.random.default_rng(9).integers(10, 200, (32, 40))
    kernel = _one_sided_kernel()
    expected = dc.wiener(y.astype(np.float64), kernel, noise_sigma=1.0, regularization=0.01)
    got = dc.wiener(y.astype(dtype), kernel, noise_sigma=1.0, regularization=0.01)
    assert got.dtype == (np.float32 if dtype == np.float32 else np.float64)
    assert np.allclose(got, expected, rtol=1e-5, atol=1e-3)
    for bad in (y > 100, y.astype(np.complex128), y.astype(str)):
        with pytest.raises(InputError, match="real numeric"):
            dc.wiener(bad, kernel, noise_sigma=1.0)


def test_a_frame_without_a_2x2_block_has_no_noise_estimate():
    for shape in ((1, 50), (50, 1), (1, 1)):
        assert dc.estimate_noise_sigma(np.random.default_rng(0).random(shape)) == 0.0


def _response(offsets: list[tuple[int, int]]):
    """A transfer whose impulse response is 1/len at each (row, col) offset, any grid."""

    def transfer(k_fft, d2):
        n0, n1 = k_fft.shape[0], 2 * (k_fft.shape[1] - 1)
        h = np.zeros((n0, n1))
        for dy, dx in offsets:
            h[dy % n0, dx % n1] += 1.0 / len(offsets)
        return np.fft.rfft2(h)

    return transfer


@pytest.mark.parametrize(
    ("offsets", "depth"),
    [
        ([(0, 0)], 0),
        ([(0, 0), (3, 1)], 3),  # below-right of the centre
        ([(0, 0), (-3, 1)], 3),  # above: wraps to the grid's last rows
        ([(0, 0), (1, -5)], 5),  # left: the last columns
        ([(-2, -2), (2, 2), (0, 0)], 2),
    ],
)
def test_filter_depth_is_the_chebyshev_radius_of_the_impulse_response(offsets, depth):
    assert dc.filter_depth(np.ones((3, 3)) / 9, _response(offsets)) == depth


def test_the_noise_gain_grid_holds_a_tall_kernel():
    tall = np.ones((301, 1)) / 301
    gain = wiener.white_noise_gain(tall, 1e-2)
    assert gain == pytest.approx(_gain_by_parseval(tall, 1e-2, "natural", (2048, 256)), rel=0.05)
    assert wiener.white_noise_gain(tall.T, 1e-2) == pytest.approx(gain, rel=1e-12)
    assert 1e-3 < wiener.lam_for_noise_gain(tall, 2.0) < 1e-2  # gain 1.92 at 1e-2


def test_gradient_energy_of_ramps_and_of_a_single_row():
    """mean |grad y|^2 with forward differences: a ramp a j + b i gives a^2 + b^2; a single
    row has only the horizontal one and is taken as isotropic: 2 a^2."""
    i, j = np.mgrid[0:6, 0:9].astype(float)
    valid = np.ones((6, 9), dtype=bool)
    assert common._gradient_energy_2d(0.3 * j + 0.2 * i, valid) == pytest.approx(0.13)
    row = 0.3 * np.arange(9.0)[None, :]
    assert common._gradient_energy_2d(row, valid[:1]) == pytest.approx(2 * 0.09)
    assert common._gradient_energy_2d(row.T, valid[:1].T) == pytest.approx(2 * 0.09)
    assert common._gradient_energy_2d(np.ones((1, 1)), valid[:1, :1]) == 0.0
    # a clipped spike: every difference touching it is left out, the ramp's stay
    spiked = 0.3 * j + 0.2 * i
    spiked[3, 4] = 9.0
    masked = valid.copy()
    masked[3, 4] = False
    assert common._gradient_energy_2d(spiked, masked) == pytest.approx(0.13)
    masked[0, :] = False  # and a clipped first row
    assert common._gradient_energy_2d(spiked, masked) == pytest.approx(0.13)


def test_natural_prior_fit_on_a_clean_scene_is_the_documented_relation():
    """No noise in the image, sigma given: mean|grad y|^2 (numpy's forward differences)
    = s2 sum(k^2) + 4 sigma^2 gives s2, and lam = sigma^2 / s2 exactly."""
    i, j = np.mgrid[0:64, 0:80].astype(float)
    y = 0.5 + 0.2 * np.sin(0.37 * j + 0.11 * i) * np.cos(0.23 * i)
    g = float(np.mean(np.diff(y, axis=0) ** 2) + np.mean(np.diff(y, axis=1) ** 2))
    kernel = np.array([[0.5, 0.3, 0.2]])  # sum k^2 = 0.38
    sigma = float(np.sqrt(g / 12.0))  # 4 sigma^2 = g / 3
    p = dc.plan(y, kernel, method="wiener", noise_sigma=sigma)
    s2 = (g - 4 * sigma**2) / 0.38
    assert float(p.params["lam"][0]) == pytest.approx(sigma**2 / s2, rel=1e-9)


def test_image_and_censored_mask_shapes_are_checked():
    one = dc.wiener(np.full((1, 1), 0.5), np.ones((1, 1)), noise_sigma=0.0)
    assert one.shape == (1, 1) and one[0, 0] == pytest.approx(0.5)
    for bad in (np.zeros((0, 5)), np.zeros(5), np.zeros((2, 2, 2, 2))):
        with pytest.raises(InputError, match="non-empty"):
            dc.wiener(bad, np.ones((1, 1)), noise_sigma=0.0)
    with pytest.raises(InputError, match=r"censored must have shape \(30, 41\), got \(30, 40\)"):
        dc.deconvolve(np.zeros((30, 41)), np.ones((1, 1)), censored=np.zeros((30, 40), bool),
                      noise_sigma=0.0)


def test_the_spectral_noise_bound_reads_only_the_high_band():
    """A checkerboard (which the Haar band reads as noise) on a strong texture below 0.25
    cycles/px: only the band above 0.3 cycles/px is noise alone (with all frequencies
    the texture's 28% of the bins lift the median: 0.024 for 0.02)."""
    rng = np.random.default_rng(12)
    n = 256
    radius = np.hypot(np.fft.fftfreq(n)[:, None], np.fft.fftfreq(n)[None, :])
    texture = np.real(np.fft.ifft2(np.fft.fft2(rng.standard_normal((n, n))) * (radius < 0.25)))
    texture *= 0.3 / texture.std()
    i, j = np.mgrid[0:n, 0:n]
    y = 0.5 + texture + 0.4 * ((i + j) % 2 * 2 - 1) + 0.02 * rng.standard_normal((n, n))
    assert dc.estimate_noise_sigma(y) == pytest.approx(0.02, rel=0.08)


def test_fast_lengths_are_even_and_hold_n():
    for n in range(1, 700):
        m = common._fast_len(n)
        assert m >= n and m % 2 == 0 and m <= max(16, 1.25 * n)


def test_per_channel_regularization_applies_to_its_own_channel():
    y = np.stack([_scene((24, 20), seed=s) for s in (1, 2, 3)], axis=-1)
    kernel = _one_sided_kernel()
    lams = [0.001, 0.05, 1.0]
    got = dc.wiener(y, kernel, noise_sigma=0.01, regularization=lams)
    for c, lam in enumerate(lams):
        alone = dc.wiener(y[..., c], kernel, noise_sigma=0.01, regularization=lam)
        # one reach for all channels (the smallest lam's): equal to the filter's tail
        assert np.abs(got[..., c] - alone).max() < 2e-5


def test_kernels_need_odd_sides_both_ways():
    for shape in ((3, 4), (4, 3), (2, 2)):
        with pytest.raises(InputError, match="odd sides"):
            dc.check_kernel(np.ones(shape) / np.prod(shape))
    assert dc.check_kernel(np.ones((3, 5)) / 15).shape == (3, 5)
