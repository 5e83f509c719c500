"""``pipeline.core.frame_support`` against an independent numpy/scipy implementation of
its documented formulas (issue 11, mutation kills).

OpenCV's pieces are rebuilt from their definitions: ``GaussianBlur`` with ``ksize`` 0 is
a float kernel of radius ``round(4 sigma)`` with mirrored borders (scipy's ``gaussian_filter``,
``truncate=4``, ``mode="mirror"``), ``INTER_AREA`` by a whole factor is the block mean,
``INTER_LINEAR`` upsampling samples at ``(i + 0.5) / f - 0.5`` clamped to the grid, the
3 px Laplacian is ``[[2, 0, 2], [0, -8, 0], [2, 0, 2]]``. Frame sides are multiples of 8,
so every reduction is whole blocks.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from pipeline.core import frame_support as fs
from pipeline.core.deconvolve.common import noise_sigma_2d
from pipeline.core.frame_support import FrameSupport

# ----------------------------------------------------------------------------- mutation kills
GAMMA = 2.2  # display gamma of the contrast floor
FLOOR = 2.0 / 255.0  # 2 levels of 8 bits
BANDS = ((1.0, 7.0), (4.0, 15.0))  # (detail sigma, std window), px
BLOCK = 4  # focus measure and blend weights per 4 px block
BLEND_SIGMA = 6.0


def _blur(a, sigma):
    return ndimage.gaussian_filter(a, sigma, mode="mirror", truncate=4.0)


def _block_mean(a, f):
    r, c = a.shape
    return a.reshape(r // f, f, c // f, f).mean(axis=(1, 3))


def _upsample(a, f, shape):
    r = np.clip((np.arange(shape[0]) + 0.5) / f - 0.5, 0, a.shape[0] - 1)
    c = np.clip((np.arange(shape[1]) + 0.5) / f - 0.5, 0, a.shape[1] - 1)
    rr, cc = np.meshgrid(r, c, indexing="ij")
    return ndimage.map_coordinates(a, [rr, cc], order=1)


def _grey(a):
    return a if a.ndim == 2 else a @ np.array([0.299, 0.587, 0.114])


def _reference_focus(codes):
    lap = ndimage.correlate(codes.astype(np.float64),
                            np.array([[2.0, 0, 2], [0, -8, 0], [2, 0, 2]]), mode="mirror")
    return np.sqrt(_blur(_block_mean(lap * lap, BLOCK), 8.0 / BLOCK))


def _reference_detail(grey, sigma, window):
    step = 2 if sigma >= 2 else 1
    if step > 1:
        grey = _block_mean(grey, step)
    detail = grey - _blur(grey, sigma / step)
    return np.sqrt(np.maximum(_blur(_block_mean(detail * detail, BLOCK // step),
                                    window / BLOCK), 0.0))


def _reference_prefer(image, sharpest_codes):
    """The blend towards the sharpest frame, from the docstring of ``prefer_sharpest``."""
    frame = sharpest_codes.astype(np.float64) / fs.CODE_MAX
    frame_grey = np.maximum(_grey(frame), 0.0) ** (1 / GAMMA)
    image_grey = np.maximum(_grey(image.astype(np.float64)), 0.0) ** (1 / GAMMA)
    alpha = np.zeros((image.shape[0] // BLOCK, image.shape[1] // BLOCK))
    for sigma, window in BANDS:
        gap = _reference_detail(frame_grey, sigma, window) - _reference_detail(
            image_grey, sigma, window)
        alpha = np.maximum(alpha, np.clip(gap / FLOOR - 1.0, 0.0, 1.0))
    alpha = _upsample(_blur(alpha, BLEND_SIGMA / BLOCK), BLOCK, image.shape[:2])
    white = sharpest_codes == fs.CODE_MAX
    alpha[white if white.ndim == 2 else np.any(white, axis=2)] = 0.0
    a = alpha if image.ndim == 2 else alpha[..., None]
    return image + a * (frame - image), float(np.mean(alpha > 0.5))


def _support(frames):
    out = None
    for f in frames:
        leaf = FrameSupport.of_frame(f, np.ones(f.shape[:2], bool))
        out = leaf if out is None else out.merge(leaf)
    return out


def _two_depths(shape=(48, 64), seed=0):
    """Truth, and frames sharp on the left / on the right half; a hazy restoration with a
    dark undershoot band (negative values: the display curve floors them at 0)."""
    rng = np.random.default_rng(seed)
    truth = ndimage.gaussian_filter(rng.uniform(0.05, 0.9, shape), 0.7)
    blurred = ndimage.gaussian_filter(truth, 3.0)
    half = shape[1] // 2
    near, far = truth.copy(), truth.copy()
    near[:, half:] = blurred[:, half:]
    far[:, :half] = blurred[:, :half]
    hazy = 0.6 * blurred + 0.4 * truth
    hazy[10:14, 5:60] -= 0.6
    return near.astype(np.float32), far.astype(np.float32), hazy.astype(np.float32)


def test_focus_measure_is_the_smoothed_laplacian_energy_per_block():
    rng = np.random.default_rng(1)
    frame = ndimage.gaussian_filter(rng.uniform(0, 1, (40, 56)), 1.0)
    frame[:, 30:] = ndimage.gaussian_filter(frame[:, 30:], 2.0)  # less detail on the right
    codes = fs.to_codes(frame.astype(np.float32))
    got = fs.focus_measure(codes)
    assert got.shape == (10, 14)
    np.testing.assert_allclose(got, _reference_focus(codes), rtol=1e-5)


def test_prefer_sharpest_equals_the_reference_grey_and_colour():
    near, far, hazy = _two_depths()
    far[30:34, :] = 1.5  # beyond white in the sharpest frame there: those pixels keep hazy
    support = _support([near, far])
    got, fraction = fs.prefer_sharpest(hazy.copy(), support)
    want, want_fraction = _reference_prefer(hazy, support.sharpest)
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-6)
    assert fraction == want_fraction and 0.2 < fraction < 0.8
    blended = np.abs(got - hazy)
    assert blended.max() > 0.1 and np.all(blended[30:34, 2:-2] == 0)  # the white rows kept
    tint = np.array([1.0, 0.8, 0.6], np.float32)
    colour = [np.ascontiguousarray(f[..., None] * tint) for f in (near, far, hazy)]
    support = _support(colour[:2])
    got, fraction = fs.prefer_sharpest(colour[2].copy(), support)
    want, want_fraction = _reference_prefer(colour[2], support.sharpest)
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-5)  # the codes' grey is rounded
    assert fraction == want_fraction


def test_frame_noise_reads_the_centre_crop_of_a_large_frame():
    """A 1400 x 1100 frame: noise 0.01 on the centred 1024 px square, 0.1 around it. The
    estimate is the estimator's on exactly that square."""
    rng = np.random.default_rng(2)
    frame = (0.4 + rng.normal(0, 0.1, (1400, 1100))).astype(np.float32)
    crop = (slice(188, 1212), slice(38, 1062))
    frame[crop] = 0.4 + rng.normal(0, 0.01, (1024, 1024))
    valid = np.ones(frame.shape, bool)
    got = fs.frame_noise(frame, valid)
    assert got.shape == (1,)
    assert got[0] == noise_sigma_2d(frame[crop], valid[crop])


def test_any_gain_in_focus_takes_the_other_frame():
    """A flat frame and one a single code brighter at one pixel: the second has a (tiny)
    focus measure there, so it is the sharpest nearby; ties keep the first frame."""
    flat = np.full((32, 32), 16384 / fs.CODE_MAX, np.float32)
    bump = flat.copy()
    bump[16, 16] = 16385 / fs.CODE_MAX
    assert 0 < fs.focus_measure(fs.to_codes(bump)).max() < 1  # below one code of measure
    support = _support([flat, bump])
    np.testing.assert_array_equal(support.sharpest, fs.to_codes(bump))
    brighter = np.full((32, 32), 30000 / fs.CODE_MAX, np.float32)  # also no detail: a tie
    np.testing.assert_array_equal(_support([flat, brighter]).sharpest, fs.to_codes(flat))
    np.testing.assert_array_equal(_support([brighter, flat]).sharpest, fs.to_codes(brighter))


def test_a_small_frames_noise_is_read_on_the_whole_frame():
    rng = np.random.default_rng(3)
    frame = (0.4 + rng.normal(0, 0.02, (40, 56, 3))).astype(np.float32)
    frame[0, :, :] += 0.5  # a bright first row and column: a crop without them reads less
    frame[:, 0, :] += 0.5
    valid = np.ones(frame.shape[:2], bool)
    want = [noise_sigma_2d(frame[..., c], valid) for c in range(3)]
    np.testing.assert_array_equal(fs.frame_noise(frame, valid), want)


def test_the_noise_ceiling_needs_frames_noisier_than_their_average():
    """Averaging lowers noise: a frame noisier than the average gets a ceiling; an average
    that reads noisier (texture, not noise) gets none."""
    rng = np.random.default_rng(4)
    base = np.full((64, 64, 3), 0.4, np.float32)
    frames = [base + rng.normal(0, 0.01, base.shape).astype(np.float32) for _ in range(3)]
    support = _support(frames)
    none = np.zeros((64, 64), bool)
    quiet = base + rng.normal(0, 0.003, base.shape).astype(np.float32)
    np.testing.assert_array_equal(fs.noise_ceiling(support, quiet, none),
                                  fs.frame_noise_ceiling(support))
    loud = base + rng.normal(0, 0.03, base.shape).astype(np.float32)
    assert fs.noise_ceiling(support, loud, none) is None


def test_the_range_is_widened_by_one_code_each_way():
    """The codes round to nearest, so a value within one code beyond the frames' range
    is kept; two codes beyond is clipped back to one code beyond."""
    lo, hi = 20000, 40000
    frames = [np.full((8, 8), c / fs.CODE_MAX, np.float32) for c in (lo, hi)]
    support = _support(frames)
    image = np.array([lo - 0.75, lo - 2.0, hi + 0.75, hi + 2.0], np.float32) / fs.CODE_MAX
    image = np.tile(image, (8, 2))
    got = fs.clip_to_frames(image.copy(), support)
    want = np.array([lo - 0.75, lo - 1, hi + 0.75, hi + 1], np.float32) / fs.CODE_MAX
    np.testing.assert_allclose(got, np.tile(want, (8, 2)), rtol=1e-6)


def test_codes_span_the_full_16_bit_range():
    """0 and 1 are codes 0 and 65535 (nearest rounding between), white and beyond (and an
    overflow to infinity) saturate at 65535, negatives (and an overflow to minus infinity)
    at 0, a NaN (nothing known) is the open end code 65535."""
    values = np.float32([[0.0, 0.25, 0.5, 1.0, 1.5, np.inf, -0.1, -1e38, np.nan]])
    np.testing.assert_array_equal(fs.to_codes(values),
                                  [[0, 16384, 32768, 65535, 65535, 65535, 0, 0, 65535]])
    np.testing.assert_array_equal(fs.from_codes(np.array([[0, 65535]], np.uint16)), [[0, 1]])


def test_every_code_reads_back_as_its_value_rounded_to_float32():
    """``from_codes`` of every 16-bit code is ``code / 65535`` taken in float64 and rounded
    to float32 (what OpenCV's scaled conversion gave), in any layout; back through
    ``to_codes`` each is the same code."""
    codes = np.arange(fs.CODE_MAX + 1, dtype=np.uint16)
    want = (codes.astype(np.float64) / fs.CODE_MAX).astype(np.float32)
    for shape in ((256, 256), (128, 128, 4), (64, 1024, 1)):
        got = fs.from_codes(codes.reshape(shape))
        assert got.dtype == np.float32 and got.shape == shape
        np.testing.assert_array_equal(got.ravel(), want)
    np.testing.assert_array_equal(fs.to_codes(want.reshape(256, 256)).ravel(), codes)


def test_codes_are_the_nearest_to_the_exact_product_within_half_a_float32_ulp():
    """Against ``x * 65535`` taken exactly (float64 holds the product of a float32 and
    65535 exactly): every code lies within 0.502 codes of it (nearest rounding of the float32
    product), on seeded uniform values and on each half code and its float32 neighbours,
    where a floor or a ceiling would be a whole code off; saturated beyond [0, 1]."""
    rng = np.random.default_rng(23)
    halves = ((np.arange(0, fs.CODE_MAX) + 0.5) / fs.CODE_MAX).astype(np.float32)
    values = np.concatenate([
        rng.uniform(0, 1, 200_000).astype(np.float32), halves,
        np.nextafter(halves, np.float32(2)), np.nextafter(halves, np.float32(-1)),
    ])  # fmt: skip
    codes = fs.to_codes(values.reshape(-1, 1)).ravel()
    assert codes.dtype == np.uint16
    exact = values.astype(np.float64) * fs.CODE_MAX
    assert np.max(np.abs(codes - exact)) <= 0.502
    uniform = slice(0, 200_000)  # there, mostly the exact rounding (0.13% within the ulp)
    assert np.mean(codes[uniform] != np.floor(exact[uniform] + 0.5)) < 0.005
    beyond = fs.to_codes(np.float32([[1.0000001, 3.0, -1e-7, -3.0]]))
    np.testing.assert_array_equal(beyond, [[65535, 65535, 0, 0]])


def test_a_wider_neighbourhood_is_a_wider_min_max_filter():
    """``radius_px=3``: the range over 7 x 7 pixels (scipy's min/max filters)."""
    rng = np.random.default_rng(5)
    frames = [rng.uniform(0.05, 0.95, (24, 32)).astype(np.float32) for _ in range(2)]
    support = _support(frames)
    image = rng.uniform(-0.5, 1.5, (24, 32)).astype(np.float32)
    got = fs.clip_to_frames(image.copy(), support, radius_px=3)
    stacked = np.stack(frames)
    code = 1.0 / fs.CODE_MAX
    low = ndimage.minimum_filter(stacked.min(axis=0), size=7, mode="nearest") - code
    high = ndimage.maximum_filter(stacked.max(axis=0), size=7, mode="nearest") + code
    np.testing.assert_allclose(got, np.clip(image, low, high), atol=0.6 * code)
