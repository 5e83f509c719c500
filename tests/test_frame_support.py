"""Keeping a restored stack to what its frames support (issue 13), against brute force:
the streamed range and sharpest frame against numpy over all frames at once, the clip
against scipy's min/max filters, the fallback on a stack whose truth is known, the
noise ceiling against measured noise.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy import ndimage

from pipeline.core import frame_support as fs
from pipeline.core.deconvolve.dispatch import plan, restore
from pipeline.core.deconvolve.wiener import MAX_NOISE_GAIN, lam_for_noise_gain
from pipeline.core.frame_support import FrameSupport


def _frames(n=5, shape=(40, 56, 3), seed=0):
    rng = np.random.default_rng(seed)
    return [rng.uniform(0.0, 1.0, shape).astype(np.float32) for _ in range(n)]


def _colour(image):
    """(R, B) / (R + G + B) of each pixel, every channel raised by the documented floor,
    then (R - G + 1) / 2 and (B - G + 1) / 2 (float64, written out per channel)."""
    f = fs.CHROMA_FLOOR
    r, g, b = (image[..., c].astype(np.float64) for c in range(3))
    total = r + g + b + 3 * f
    return np.stack([(r + f) / total, (b + f) / total, (r - g + 1) / 2, (b - g + 1) / 2],
                    axis=-1)


def _streamed(frames, order, full=True):
    """Merge the frames' statistics in ``order`` as two lanes would (then lane 1 into 0)."""
    lanes = [None, None]
    for k, i in enumerate(order):
        leaf = FrameSupport.of_frame(frames[i], np.ones(frames[i].shape[:2], bool), full=full)
        lane = k % 2
        lanes[lane] = leaf if lanes[lane] is None else lanes[lane].merge(leaf)
    return lanes[0].merge(lanes[1])


@pytest.mark.parametrize("shape", [(600, 70, 3), (600, 70), (600, 70, 1), (300, 40, 4)])
def test_frames_folded_by_strips_equal_brute_force(shape):
    """add_frame (the accumulation's lanes, by strips of CLIP_STRIP_ROWS) against numpy's
    min/max of every whole frame's codes (to_codes, checked on its own in this file): more
    rows than a strip, a NaN, values beyond white and below black; the colour bounds
    exactly as merging each frame's own statistics gives them (that path is checked
    against brute force above); every frame's noise, in order."""
    frames = [f * np.float32(1.3) - np.float32(0.1) for f in _frames(4, shape, seed=7)]
    frames[1][290, 5] = np.nan
    valid = np.ones(shape[:2], bool)
    got = FrameSupport.of_frame(frames[0], valid, full=False)
    merged = FrameSupport.of_frame(frames[0], valid, full=False)
    for frame in frames[1:]:
        got = got.add_frame(frame, valid)
        merged = merged.merge(FrameSupport.of_frame(frame, valid, full=False))
    codes = np.stack([fs.to_codes(f).reshape(shape) for f in frames])
    assert got.high is not got.low
    np.testing.assert_array_equal(got.low.reshape(shape), codes.min(axis=0))
    np.testing.assert_array_equal(got.high.reshape(shape), codes.max(axis=0))
    if len(shape) == 3 and shape[2] == 3:
        assert got.colour_high is not got.colour_low
        np.testing.assert_array_equal(got.colour_low, merged.colour_low)
        np.testing.assert_array_equal(got.colour_high, merged.colour_high)
    else:
        assert got.colour_low is None
    expected = [fs.frame_noise(f, valid, fs.LIMIT_NOISE_CROP_PX) for f in frames]
    np.testing.assert_array_equal(np.array(got.noise), np.array(expected))


def test_add_frame_refuses_full_statistics():
    frames = _frames(2)
    valid = np.ones(frames[0].shape[:2], bool)
    with pytest.raises(ValueError, match="range-only"):
        FrameSupport.of_frame(frames[0], valid).add_frame(frames[1], valid)


@pytest.mark.parametrize("order", [[0, 1, 2, 3, 4], [4, 2, 0, 3, 1]])
def test_streamed_range_and_sharpest_equal_brute_force(order):
    frames = _frames()
    # make each frame the sharpest somewhere: blur all but one per vertical band
    for i, frame in enumerate(frames):
        for j in range(len(frames)):
            if j != i:
                band = frame[:, j * 11 : (j + 1) * 11]
                band[:] = ndimage.uniform_filter(band, size=(5, 5, 1))
    got = _streamed(frames, order)
    stacked = np.stack(frames)
    code = 0.5 / fs.CODE_MAX  # codes round to nearest
    np.testing.assert_allclose(fs.from_codes(got.low), stacked.min(axis=0), atol=code)
    np.testing.assert_allclose(fs.from_codes(got.high), stacked.max(axis=0), atol=code)
    shares = np.stack([_colour(f) for f in frames])
    near = code + 1e-6  # float32's rounding of the colour on top of the codes'
    np.testing.assert_allclose(fs.from_codes(got.colour_low), shares.min(axis=0), atol=near)
    np.testing.assert_allclose(fs.from_codes(got.colour_high), shares.max(axis=0), atol=near)
    focus = np.stack([fs.focus_measure(fs.to_codes(f)) for f in frames])
    b = fs.FOCUS_BLOCK_PX
    assert focus.shape[1:] == (-(-40 // b), -(-56 // b))  # one value per block
    # per pixel: the frame whose block holds the best focus (the stream interpolates the
    # focus differences between block centres, so pixels near a choice's boundary may
    # take the other frame)
    blocks = np.argmax(focus, axis=0)
    best = blocks[np.arange(40)[:, None] // b, np.arange(56)[None, :] // b]
    want = np.take_along_axis(stacked, best[None, ..., None], axis=0)[0]
    agree = np.all(np.abs(fs.from_codes(got.sharpest) - want) <= code, axis=2)
    assert agree.mean() > 0.9
    inside = (ndimage.maximum_filter(best, 9) == best) & (ndimage.minimum_filter(best, 9) == best)
    assert inside.sum() > 300 and agree[inside].all()  # a block or more from a boundary: exact
    # frame j is the sharpest in band j (not the same frame everywhere)
    for j in range(len(frames)):
        assert np.mean(best[8:-8, j * 11 + 4 : (j + 1) * 11 - 4] == j) > 0.9


def test_a_single_frame_merged_is_not_changed_in_place():
    frames = _frames(2)
    first = FrameSupport.of_frame(frames[0], np.ones(frames[0].shape[:2], bool))
    kept = first.low.copy()
    first.merge(FrameSupport.of_frame(frames[1], np.ones(frames[1].shape[:2], bool)))
    # the first frame's shared array became low; high and sharpest are their own arrays
    assert first.high is not first.low and first.sharpest is not first.low
    np.testing.assert_array_equal(first.low, np.minimum(kept, fs.to_codes(frames[1])))


@pytest.mark.parametrize(
    ("shape", "full"),
    [
        ((30, 33, 3), True),
        ((2 * fs.CLIP_STRIP_ROWS + 7, 21, 3), False),  # strips, and their seams
        ((fs.CLIP_STRIP_ROWS + 1, 9), False),  # grey, one row in the last strip
    ],
)
def test_clip_to_frames_is_a_3x3_min_max_filter(shape, full):
    rng = np.random.default_rng(1)
    frames = [rng.uniform(0.01, 0.99, shape).astype(np.float32) for _ in range(3)]
    support = _streamed(frames, [0, 1, 2], full)
    assert (support.sharpest is None) == (not full)  # the range only: no frame choice
    support.colour_low = support.colour_high = None  # the channels' range alone (see below)
    image = rng.uniform(-0.5, 1.5, frames[0].shape).astype(np.float32)
    clipped = np.zeros(image.shape[:2], bool)
    clipped[5:8, 10:20] = True
    got = fs.clip_to_frames(image.copy(), support, clipped)
    stacked = np.stack(frames)
    box = (3, 3, 1)[: image.ndim]
    low = ndimage.minimum_filter(stacked.min(axis=0), size=box, mode="nearest")
    high = ndimage.maximum_filter(stacked.max(axis=0), size=box, mode="nearest")
    high[clipped] = np.inf
    # the frames' own values always pass; the bound is loose by at most 1.5 codes
    assert np.all(got >= low - 1.5 / fs.CODE_MAX) and np.all(got <= high + 1.5 / fs.CODE_MAX)
    assert np.all(got >= np.minimum(image, low)) and np.all(got <= np.maximum(image, high))
    np.testing.assert_allclose(got, np.clip(image, low, high), atol=1.5 / fs.CODE_MAX)
    assert np.all(got[clipped] >= np.minimum(image[clipped], low[clipped]))
    inside = (image >= low + 1e-3) & (image <= high - 1e-3)  # nothing inside moves
    np.testing.assert_array_equal(got[inside], image[inside])
    assert np.mean(got != image) > 0.3  # and much outside did


def test_a_colour_no_frame_shows_takes_the_frames_colour_at_its_own_brightness():
    # both frames show one colour, (3, 2, 1) in linear light, darker and brighter; a pixel
    # with their highest red and lowest green and blue passes every channel's range (a red
    # rim beside a highlight) and keeps its sum R + G + B = 0.9 in the frames' colour
    dark = np.tile(np.float32([0.3, 0.2, 0.1]), (6, 7, 1))
    bright = 2 * dark
    support = _streamed([dark, bright], [0, 1])
    image = (dark + bright) / 2
    image[3, 3] = [0.6, 0.2, 0.1]
    image[2, 5] = [0.3, 0.35, 0.12]  # green: moves; the sum stays 0.77
    got = fs.clip_to_frames(image.copy(), support)
    np.testing.assert_allclose(got[3, 3], [0.45, 0.30, 0.15], atol=2e-4)
    np.testing.assert_allclose(got[2, 5], np.float32([3, 2, 1]) * 0.77 / 6, atol=2e-4)
    keep = np.ones((6, 7), bool)
    keep[3, 3] = keep[2, 5] = False
    np.testing.assert_array_equal(got[keep], image[keep])  # the frames' colour stays


def test_a_bright_pixel_in_a_dark_frames_colour_takes_the_frames_differences():
    # beside pcb10's white pads: one frame shows cream, clipped in red (at white), the
    # other gold. A pixel as bright as the cream in the gold's chromaticity passes every
    # channel's range and both ratios, but its blue falls 0.55 below its green where the
    # frames' fall 0.20-0.28: saturated yellow. It keeps its sum 2.2 and takes the
    # frames' largest fall; a frame at white shows its colour, so it is judged there too
    cream = np.tile(np.float32([1.0, 0.95, 0.75]), (5, 6, 1))
    gold = np.tile(np.float32([0.5, 0.4, 0.12]), (5, 6, 1))
    support = _streamed([cream, gold], [0, 1])
    clipped = np.ones((5, 6), bool)  # red at white in the cream frame, everywhere
    image = cream.copy()
    image[2, 3] = [0.95, 0.9, 0.35]
    got = fs.clip_to_frames(image.copy(), support, clipped)
    g = (2.2 - 0.05 + 0.28) / 3  # from the sum, R - G = 0.05 and B - G = -0.28
    np.testing.assert_allclose(got[2, 3], [g + 0.05, g, g - 0.28], atol=2e-4)
    keep = np.ones((5, 6), bool)
    keep[2, 3] = False
    np.testing.assert_array_equal(got[keep], image[keep])


def test_beyond_white_the_displayed_colour_is_judged_and_the_value_beyond_kept():
    # one frame white (1, 1, 1), one (1, 0.8, 0.8); red is at white in both, so its range
    # is open. (1.4, 0.9, 0.9) shows (1, 0.9, 0.9), a colour between theirs: it stays,
    # 1.4 included. (1.4, 0.8, 0.9) shows blue above green, which neither frame does:
    # its displayed sum 2.7 is kept with B - G = 0, R - G = 0.2; red, rebuilt at 1.03,
    # is displayed at white, so it keeps 1.4
    white = np.ones((4, 5, 3), np.float32)
    pink = np.tile(np.float32([1.0, 0.8, 0.8]), (4, 5, 1))
    support = _streamed([white, pink], [0, 1])
    image = pink.copy()
    image[1, 1] = [1.4, 0.9, 0.9]
    image[2, 3] = [1.4, 0.8, 0.9]
    got = fs.clip_to_frames(image.copy(), support)
    np.testing.assert_array_equal(got[1, 1], image[1, 1])
    g = (2.7 - 0.2) / 3
    np.testing.assert_allclose(got[2, 3], [1.4, g, g], atol=2e-4)


@pytest.mark.parametrize("shape", [(30, 33, 3), (fs.CLIP_STRIP_ROWS + 5, 12, 3)])
def test_clip_to_frames_keeps_the_frames_colour_range_over_3x3(shape):
    rng = np.random.default_rng(7)
    colour = rng.uniform(0.2, 1.0, shape)  # each pixel's colour, seen brighter or darker
    frames = [(colour * rng.uniform(0.3, 0.95, shape[:2])[..., None]
               * rng.uniform(0.95, 1.05, shape)).astype(np.float32) for _ in range(3)]
    support = _streamed(frames, [0, 1, 2], False)
    image = rng.uniform(0.0, 1.0, shape).astype(np.float32)
    clipped = np.zeros(shape[:2], bool)
    clipped[5:8, 4:9] = True
    got = fs.clip_to_frames(image.copy(), support, clipped)
    stacked = np.stack(frames)
    low = ndimage.minimum_filter(stacked.min(axis=0), size=(3, 3, 1), mode="nearest")
    high = ndimage.maximum_filter(stacked.max(axis=0), size=(3, 3, 1), mode="nearest")
    high[clipped] = np.inf
    shares = np.stack([_colour(f) for f in frames])
    share_low = ndimage.minimum_filter(shares.min(axis=0), size=(3, 3, 1), mode="nearest")
    share_high = ndimage.maximum_filter(shares.max(axis=0), size=(3, 3, 1), mode="nearest")
    tol = 1.5 / fs.CODE_MAX
    assert np.all(got >= low - tol) and np.all(got <= high + tol)  # channels: as before
    share = _colour(got)
    outside = np.any((share < share_low - 1e-4) | (share > share_high + 1e-4), axis=2)
    at_bound = np.any((got <= low + tol) | (got >= high - tol), axis=2)
    # a colour out of the frames' range is left only where the channels' range, applied
    # after the colour, holds the pixel; clipped pixels (only their channels' upper bound
    # is open) included
    assert not np.any(outside & ~at_bound)
    before = _colour(np.clip(image, low, high))
    was_out = np.any((before < share_low) | (before > share_high), axis=2)
    assert was_out.mean() > 0.3 and outside.mean() < 0.2 * was_out.mean()
    moved = was_out & ~at_bound  # the sum is kept where the channels' range let it be
    sums = got.sum(axis=2), np.clip(image, low, high).sum(axis=2)
    np.testing.assert_allclose(sums[0][moved], sums[1][moved], atol=3 * tol)  # codes' slack
    inside = np.all((before > share_low + 1e-3) & (before < share_high - 1e-3), axis=2)
    inside &= np.all((image >= low + 1e-3) & (image <= high - 1e-3), axis=2)
    np.testing.assert_array_equal(got[inside], image[inside])  # nothing inside moves
    for frame in frames:  # each frame is its own colour: the codes' rounding moves none
        np.testing.assert_array_equal(fs.clip_to_frames(frame.copy(), support), frame)


def test_clip_to_frames_bounds_black_at_zero_and_leaves_white_open():
    dark = np.zeros((12, 12), np.float32)
    bright = np.full((12, 12), 1e38, np.float32)  # float frames far beyond white
    support = _streamed([dark, bright], [0, 1])
    image = np.linspace(-2.0, 3e38, 144, dtype=np.float32).reshape(12, 12)
    np.testing.assert_array_equal(fs.clip_to_frames(image.copy(), support), np.maximum(image, 0))


def _two_depth_scene(shape=(64, 96)):
    """Truth with texture everywhere; frame 0 sharp on the left, frame 1 on the right."""
    rng = np.random.default_rng(3)
    truth = ndimage.gaussian_filter(rng.uniform(0.05, 0.9, shape), 0.7).astype(np.float32)
    truth = np.repeat(truth[..., None], 3, axis=2)
    blurred = ndimage.gaussian_filter(truth, (3, 3, 0))
    half = shape[1] // 2
    near, far = truth.copy(), truth.copy()
    near[:, half:] = blurred[:, half:]
    far[:, :half] = blurred[:, :half]
    return truth, [near, far], blurred


def test_prefer_sharpest_takes_detail_the_image_lacks():
    truth, frames, blurred = _two_depth_scene()
    support = _streamed(frames, [0, 1])
    hazy = 0.5 * blurred + 0.5 * truth  # a restoration that lost half the detail
    out, fraction = fs.prefer_sharpest(hazy.copy(), support)
    inner = (slice(10, -10), slice(10, -10))
    before = np.sqrt(np.mean((hazy - truth)[inner] ** 2))
    after = np.sqrt(np.mean((out - truth)[inner] ** 2))
    assert after < 0.35 * before
    assert fraction > 0.5


def test_prefer_sharpest_keeps_an_image_with_the_detail():
    truth, frames, _ = _two_depth_scene()
    support = _streamed(frames, [0, 1])
    out, fraction = fs.prefer_sharpest(truth.copy(), support)
    np.testing.assert_allclose(out, truth, atol=2e-3)  # only float16 rounding can leak
    assert fraction == 0.0


def test_prefer_sharpest_ignores_noise_below_the_floor():
    rng = np.random.default_rng(5)
    flat = np.full((48, 48, 3), 0.3, np.float32)
    frames = [flat + rng.normal(0, 2e-4, flat.shape).astype(np.float32) for _ in range(3)]
    support = _streamed(frames, [0, 1, 2])
    out, fraction = fs.prefer_sharpest(flat.copy(), support)
    np.testing.assert_array_equal(out, flat)
    assert fraction == 0.0


def test_prefer_sharpest_keeps_pixels_at_white_in_the_sharpest_frame():
    truth, frames, blurred = _two_depth_scene()
    for frame in frames:
        frame[..., 0] = np.where(truth[..., 0] > 0.5, 1.5, frame[..., 0])  # red beyond white
    support = _streamed(frames, [0, 1])
    hazy = 0.5 * blurred + 0.5 * truth
    out, _ = fs.prefer_sharpest(hazy.copy(), support)
    at_white = truth[..., 0] > 0.5
    np.testing.assert_array_equal(out[at_white], hazy[at_white])  # its codes end at white
    assert np.abs(out - hazy)[~at_white].max() > 0.05  # elsewhere it still blends


def test_frame_noise_reads_the_frames_noise_and_the_ceiling_has_a_floor():
    rng = np.random.default_rng(6)
    base = np.full((300, 300, 3), 0.4, np.float32)
    frames = [base + rng.normal(0, s, base.shape).astype(np.float32) for s in (0.01, 0.02, 0.03)]
    support = _streamed(frames, [0, 1, 2])
    np.testing.assert_allclose(support.median_noise(), 0.02, rtol=0.05)
    # the range-only statistics (the noise limit's) hold every frame's noise too, in any
    # order of the merges (they once kept the first frame's alone: 0.01 here)
    for order in ([0, 1, 2], [2, 0, 1]):
        ranged = _streamed(frames, order, full=False)
        assert len(ranged.noise) == 3
        np.testing.assert_allclose(ranged.median_noise(), 0.02, rtol=0.05)
    np.testing.assert_allclose(fs.frame_noise_ceiling(support), fs.NOISE_SHARE * 0.02, rtol=0.05)
    clean = _streamed([base, base.copy()], [0, 1])
    np.testing.assert_array_equal(fs.frame_noise_ceiling(clean), fs.NOISE_FLOOR)


def test_wiener_max_noise_caps_the_results_noise():
    rng = np.random.default_rng(7)
    kernel = np.zeros((31, 31))
    kernel[15, 3:28] = 1.0  # a wide, asymmetric (off-centre mass below) kernel
    kernel[16:24, 15] = 0.5
    kernel /= kernel.sum()
    sigma = 0.01
    sharp = ndimage.gaussian_filter(rng.uniform(0, 1, (256, 256)), 1.0)
    clean = ndimage.convolve(sharp, kernel, mode="reflect").astype(np.float32)
    noisy = clean + rng.normal(0, sigma, clean.shape).astype(np.float32)
    inner = (slice(40, -40), slice(40, -40))

    def output_noise(**options):  # the same linear filter on the clean and noisy image
        p = plan(noisy, kernel, method="wiener", noise_sigma=sigma, auto="prior", **options)
        return np.std((restore(noisy, p) - restore(clean, p))[inner])

    assert output_noise() > 2.0 * sigma  # the prior fit alone amplifies the noise
    assert output_noise(max_noise=1.5 * sigma) == pytest.approx(1.5 * sigma, rel=0.1)
    # where GCV's lam is taken (its noise agrees with sigma) the ceiling does not apply
    gcv_plan = plan(noisy, kernel, method="wiener", noise_sigma=sigma)
    capped = plan(noisy, kernel, method="wiener", noise_sigma=sigma, max_noise=1.5 * sigma)
    np.testing.assert_array_equal(capped.params["lam"], gcv_plan.params["lam"])


def test_the_main_job_stays_within_the_frames_unless_told_not_to(tmp_path):
    from pipeline.io.read import read_frame
    from pipeline.jobs.options import StackOptions
    from pipeline.jobs.stack import process_stack

    sample = Path(__file__).resolve().parents[1] / "stacks" / "motorcycle"

    def run(name, **options):
        options = StackOptions(align="none", encoding="float32", **options)
        return process_stack(sample, tmp_path / name, options)

    guarded, plain, unclipped = run("g.tif", frame_guard=True), run("p.tif"), run(
        "u.tif", frame_range=False
    )
    frames = np.stack([read_frame(f) for f in sorted(sample.glob("frame_*.png"))])
    low = ndimage.minimum_filter(frames.min(axis=0), size=(3, 3, 1), mode="nearest")
    high = ndimage.maximum_filter(frames.max(axis=0), size=(3, 3, 1), mode="nearest")
    high[np.any(frames >= 0.999, axis=(0, 3))] = np.inf  # clipped somewhere: no upper bound
    high[high >= 1 - 0.5 / fs.CODE_MAX] = np.inf  # white within 3x3 (the end code): open
    # 1.5 codes (nearest codes, widened by one by the clip), plus float32 rounding, at most
    # 2**-9 code each: of the codes' product (fs.to_codes; OpenCV 5.1 multiplies in float32:
    # a frame at 25920.50096 codes read 25920, so the clip's bound, 25919, sat 1.50096 codes
    # below it), of the clip's bound (fs.from_codes) and of this test's bound; float32's
    # eps is 2**-7 code
    tol = 1.5 / fs.CODE_MAX + np.finfo(np.float32).eps

    def outside(image, tol=tol):
        return (image < low - tol) | (image > high + tol)

    assert not np.any(outside(guarded.image)) and not np.any(outside(plain.image))
    assert np.mean(outside(unclipped.image)) > 0.01  # the clip did something
    assert set(guarded.sidecar["frame_guard"]) == {"sharpest_frame_fraction", "noise_ceiling"}
    assert "frame_guard" not in plain.sidecar and "frame_guard" not in unclipped.sidecar
    assert set(plain.sidecar["frame_range"]) == {
        "flat_fraction",
        "beyond_ends",
        "inner_detail_kept",
        "end_range_moved",
    }
    assert "frame_range" not in unclipped.sidecar and "frame_range" not in guarded.sidecar


def test_wiener_noise_limit_holds_where_the_gain_ceiling_raised_gcvs_lam():
    """Unlike ``max_noise``, ``noise_limit`` also caps channels whose lam GCV chose, but
    only where the gain ceiling raised that lam (GCV asked for more than MAX_NOISE_GAIN:
    on a real stack its residual is mostly kernel mismatch, pcb7 at ISO 3200); a lam the
    data chose above the ceiling's floor stands (rendered scenes with noise)."""
    rng = np.random.default_rng(11)
    kernel = np.zeros((31, 31))
    kernel[15, 3:28] = 1.0  # wide and asymmetric
    kernel[16:24, 15] = 0.5
    kernel /= kernel.sum()
    sharp = ndimage.gaussian_filter(rng.uniform(0, 1, (256, 256)), 1.0)
    clean = ndimage.convolve(sharp, kernel, mode="reflect").astype(np.float32)
    inner = (slice(40, -40), slice(40, -40))
    floor = lam_for_noise_gain(kernel, MAX_NOISE_GAIN)

    def output_noise(noisy, p):
        return np.std((restore(noisy, p) - restore(clean, p))[inner])

    # faint noise: GCV asks for a lam under the floor, so the ceiling sets it
    faint = 5e-4
    noisy = clean + rng.normal(0, faint, clean.shape).astype(np.float32)
    ceiling = plan(noisy, kernel, method="wiener", noise_sigma=faint)
    assert ceiling.params["lam"][0] == pytest.approx(floor)
    assert output_noise(noisy, ceiling) > 8 * faint  # the ceiling's gain, 10
    limited = plan(noisy, kernel, method="wiener", noise_sigma=faint, noise_limit=3 * faint)
    assert output_noise(noisy, limited) == pytest.approx(3 * faint, rel=0.15)
    assert limited.params["lam"][0] > 3 * floor
    assert limited.params["noise_limited"].tolist() == [True]
    loose = plan(noisy, kernel, method="wiener", noise_sigma=faint, noise_limit=100 * faint)
    np.testing.assert_array_equal(loose.params["lam"], ceiling.params["lam"])
    assert loose.params["noise_limited"].tolist() == [False]  # the ceiling held it first
    # strong noise: GCV's own lam is above the floor and no limit moves it
    sigma = 0.01
    noisy = clean + rng.normal(0, sigma, clean.shape).astype(np.float32)
    gcv_plan = plan(noisy, kernel, method="wiener", noise_sigma=sigma)
    assert gcv_plan.params["lam"][0] > 2 * floor
    assert output_noise(noisy, gcv_plan) > 1.5 * sigma  # it amplifies the noise
    held = plan(noisy, kernel, method="wiener", noise_sigma=sigma, noise_limit=1.2 * sigma)
    np.testing.assert_array_equal(held.params["lam"], gcv_plan.params["lam"])
    assert held.params["noise_limited"].tolist() == [False]


def test_visible_noise_limit_is_a_frames_noise_or_the_visible_floor():
    rng = np.random.default_rng(5)
    base = ndimage.gaussian_filter(rng.uniform(0.1, 0.7, (160, 160)), 2.0).astype(np.float32)
    for sigma, expected in ((0.02, 0.02), (0.002, fs.VISIBLE_NOISE)):
        frames = [base + rng.normal(0, sigma, base.shape).astype(np.float32) for _ in range(4)]
        support = _streamed(frames, [0, 1, 2, 3], full=False)
        average = np.mean(frames, axis=0)
        clipped = np.zeros(base.shape, bool)
        limit = fs.visible_noise_limit(support, average, clipped)
        np.testing.assert_allclose(limit, expected, rtol=0.1)
    # frames no noisier than their average: their "noise" is texture, no limit is set
    same = [base, base.copy()]
    support = _streamed(same, [0, 1], full=False)
    assert fs.visible_noise_limit(support, base, np.zeros(base.shape, bool)) is None

def test_quiet_flat_areas_takes_the_averages_fine_band_where_every_frame_is_flat():
    rng = np.random.default_rng(3)
    shape = (96, 128)
    base = np.full(shape, 0.3, np.float32)  # flat left half, textured right half
    texture = ndimage.gaussian_filter(rng.uniform(0.0, 1.0, shape), 1.0)
    base[:, 64:] = 0.1 + 0.6 * texture[:, 64:]
    frames = [base + rng.normal(0, 2e-4, shape).astype(np.float32) for _ in range(4)]
    support = _streamed(frames, [0, 1, 2, 3], full=False)
    average = np.mean(frames, axis=0)
    ramp = np.linspace(0.0, 0.05, shape[1], dtype=np.float32)[None, :]  # restored lows
    restored = average + ramp + rng.normal(0, 0.02, shape).astype(np.float32)  # and noise
    out, fraction = fs.quiet_flat_areas(restored.copy(), average, support)
    assert 0.3 < fraction < 0.7
    flat, textured = (slice(8, -8), slice(8, 48)), (slice(8, -8), slice(80, -8))

    def fine(x):
        return x - ndimage.gaussian_filter(x, 3.0)

    assert np.std(fine(out)[flat]) < 0.2 * np.std(fine(restored)[flat])  # the noise went
    low = ndimage.gaussian_filter(out, 4.0)[flat]  # the restored low frequencies stayed
    np.testing.assert_allclose(low, ndimage.gaussian_filter(restored, 4.0)[flat], atol=1.5e-3)
    np.testing.assert_array_equal(out[textured], restored[textured])  # detail: untouched


@pytest.mark.parametrize("level", [1.0, 3.0])  # white, and beyond it (a float stack's units)
def test_quiet_flat_areas_leaves_what_is_at_or_beyond_white(level):
    rng = np.random.default_rng(4)
    shape = (64, 160)
    base = np.full(shape, 0.3, np.float32)
    base[:, 96:] = level  # flat too, but where the codes end
    frames = [base.copy() for _ in range(3)]
    support = _streamed(frames, [0, 1, 2], full=False)
    restored = base + rng.normal(0, 0.02, shape).astype(np.float32)
    out, _ = fs.quiet_flat_areas(restored.copy(), base, support)
    np.testing.assert_array_equal(out[:, 96:], restored[:, 96:])
    fine = out[8:-8, 8:56] - cv2.GaussianBlur(out, (0, 0), 2.0)[8:-8, 8:56]
    assert np.std(fine) < 0.1 * 0.02  # below white, far from the step: quieted
