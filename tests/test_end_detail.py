"""The end frame's own detail where the stack's restoration leaves its content softer than
the frame (issue 13; :func:`pipeline.jobs.ends.keep_end_detail`): measured against the
frame's own band energy, on textures blurred by known Gaussians, on grain alone, on colour,
and on the real beetle stack, whose shell lies beyond its last frame; and the result kept
to the end frame's own range there (:func:`pipeline.jobs.ends.keep_to_end_frames`), on bars and
on pcb7's far barcode."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy import ndimage

from pipeline.core import align
from pipeline.core.colour import STRIP_ROWS, linear_to_srgb, mean_grey, move_grey, scale_channels
from pipeline.io.read import read_frame
from pipeline.jobs.ends import EndRange, keep_end_detail, keep_to_end_frames, restore_ends
from pipeline.jobs.stack import process_stack


def _texture(seed: int, shape=(160, 200)) -> np.ndarray:
    """A 1/f-like texture (linear light around 0.4), different along x and y."""
    rng = np.random.default_rng(seed)
    out = np.zeros(shape, np.float32)
    for sigma, amp in ((1.0, 0.08), (2.5, 0.12), (6.0, 0.15)):
        layer = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigma)
        out += amp * layer / layer.std()
    out[:, ::7] += 0.05  # an asymmetric pattern: columns, not rows
    return np.clip(0.4 + out, 0.01, None)


def _band_std(image: np.ndarray, box=np.s_[16:-16, 16:-16]) -> float:
    """Std of the 1-4 px band (independent of the code's own bands: a difference of
    box filters)."""
    g = image.mean(axis=2) if image.ndim == 3 else image
    return float(np.std((cv2.blur(g, (3, 3)) - cv2.blur(g, (9, 9)))[box]))


def test_a_weight_above_one_takes_no_more_than_the_frames_band():
    """The end correction may be scaled up past 1 where the end frame shows more of it
    (``ends._frame_agreement``); the frame's own detail is still taken at most whole:
    ``restore_ends`` passes that weight on, and 1.5 does what 1 does."""
    truth = _texture(9)
    frame = cv2.GaussianBlur(truth, (0, 0), 0.7)
    result = cv2.GaussianBlur(truth, (0, 0), 2.5)
    outs = []
    for w in (1.0, 1.5):
        out = result.copy()
        keep_end_detail(out, frame, np.full(truth.shape, w, np.float32), noise=0.0)
        outs.append(out)
    np.testing.assert_array_equal(outs[0], outs[1])
    assert _band_std(outs[1]) < 1.05 * _band_std(frame)


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 10_000), extra=st.floats(1.5, 3.0))
@example(seed=7, extra=2.5)
def test_a_result_softer_than_the_frame_gets_the_frames_detail(seed, extra):
    truth = _texture(seed)
    frame = cv2.GaussianBlur(truth, (0, 0), 0.7)  # the end frame: nearly in focus
    result = cv2.GaussianBlur(truth, (0, 0), extra)  # the stack's result: softer
    before = float(np.abs(result - frame)[16:-16, 16:-16].mean())
    out = result.copy()
    keep_end_detail(out, frame, np.ones(truth.shape, np.float32), noise=0.0)
    after = float(np.abs(out - frame)[16:-16, 16:-16].mean())
    assert after < 0.5 * before  # towards the frame, not elsewhere
    assert _band_std(result) < 0.8 * _band_std(frame)  # the case: clearly softer
    assert _band_std(out) > 0.85 * _band_std(frame)


def test_a_result_sharper_than_the_frame_stays():
    truth = _texture(3)
    frame = cv2.GaussianBlur(truth, (0, 0), 2.0)  # the frame is the softer one here
    out = truth.copy()
    keep_end_detail(out, frame, np.ones(truth.shape, np.float32), noise=0.0)
    assert np.abs(out - truth).max() < 0.05 * np.ptp(truth)
    assert _band_std(out) > 0.97 * _band_std(truth)


def test_the_weight_confines_it_and_none_leaves_the_result_as_it_is():
    truth = _texture(5)
    frame = truth.copy()
    result = cv2.GaussianBlur(truth, (0, 0), 2.5)
    weight = np.zeros(truth.shape, np.float32)
    weight[:, 100:] = 1.0  # the right half only
    out = result.copy()
    keep_end_detail(out, frame, weight, noise=0.0)
    np.testing.assert_array_equal(out[:, :90], result[:, :90])  # beyond the filters' reach
    assert _band_std(out, np.s_[16:-16, 116:-16]) > 0.85 * _band_std(frame, np.s_[16:-16, 116:-16])
    out = result.copy()
    keep_end_detail(out, frame, np.zeros(truth.shape, np.float32), noise=0.0)
    np.testing.assert_array_equal(out, result)


@pytest.mark.parametrize(("sigma", "level"), [(0.005, 0.3), (0.02, 0.3), (0.01, 0.0)])
def test_a_frames_grain_is_no_detail(sigma, level):
    """Also where the result is exactly flat (0: no band energy at all)."""
    rng = np.random.default_rng(11)
    flat = np.full((128, 128), level, np.float32)
    frame = 0.3 + sigma * rng.standard_normal(flat.shape).astype(np.float32)
    out = flat.copy()
    keep_end_detail(out, frame, np.ones(flat.shape, np.float32), noise=sigma)
    assert float(np.std(out - flat)) < 0.1 * sigma  # without the noise term: ~0.5 sigma
    grainy = flat.copy()
    keep_end_detail(grainy, frame, np.ones(flat.shape, np.float32), noise=0.0)
    assert float(np.std(grainy - flat)) > 0.3 * sigma  # the test can fail


def test_colour_keeps_its_hue():
    grey = _texture(9)
    colour = np.array([0.9, 0.35, 0.1], np.float32)  # an orange, far from grey
    frame = grey[..., None] * colour
    result = cv2.GaussianBlur(grey, (0, 0), 2.5)[..., None] * colour
    out = result.copy()
    keep_end_detail(out, frame, np.ones(grey.shape, np.float32), noise=0.0)
    inner = out[16:-16, 16:-16].reshape(-1, 3)
    ratios = inner / inner.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(ratios, np.broadcast_to(colour / colour.sum(), ratios.shape),
                               atol=1e-4)
    assert _band_std(out) > 0.85 * _band_std(frame)


def test_restore_ends_leaves_clipped_pixels_and_reports_the_share():
    truth = _texture(13, (96, 96))
    frame = np.repeat(truth[..., None], 3, axis=2)
    soft = np.repeat(cv2.GaussianBlur(truth, (0, 0), 2.5)[..., None], 3, axis=2)
    delta_kernel = np.zeros((7, 7), np.float32)
    delta_kernel[3, 3] = 1.0
    wider = cv2.getGaussianKernel(7, 1.5) @ cv2.getGaussianKernel(7, 1.5).T

    class End:  # an end at the end frame's own depth, whose kernel is wider than the stack's
        frame, beyond, kernel, frame_kernel = 0, 0.0, wider.astype(np.float32), delta_kernel
        weight = coarse_weight = np.ones((24, 24), np.float32)
        frame_image = cv2.resize(truth, (96, 96), interpolation=cv2.INTER_AREA)

    def read(i, box):
        return frame[box], np.ones(frame[box].shape[:2], bool)

    clipped = np.zeros(truth.shape, bool)
    clipped[:, :48] = True
    corrected = soft.copy()
    restore_ends(corrected, soft, [End], delta_kernel)  # the correction alone
    out = soft.copy()
    (entry,), ranges = restore_ends(out, soft, [End], delta_kernel, read_frame=read,
                                    clipped=clipped)
    np.testing.assert_allclose(out[:, :36], corrected[:, :36], atol=1e-6)  # clipped: no detail
    right = np.s_[16:-16, 64:-16]
    assert _band_std(corrected, right) < 0.8 * _band_std(frame, right)  # the case
    assert _band_std(out, right) > 0.85 * _band_std(frame, right)
    assert 0.3 < entry["detail_kept"] <= 1.0
    (kept,) = ranges  # the end frame's grey range over 5x5, where its detail is kept
    assert kept.box == (slice(0, 96), slice(0, 96))
    np.testing.assert_allclose(kept.low, ndimage.minimum_filter(truth, 5, mode="nearest"))
    np.testing.assert_allclose(kept.high, ndimage.maximum_filter(truth, 5, mode="nearest"))
    assert np.all(kept.weight[:, :48] == 0) and kept.weight[:, 60:].min() > 0.5
    # a frame read at 1.25 times the stack's exposure (as shot): its range as the result sees it
    _, (dim,) = restore_ends(soft.copy(), soft, [End], delta_kernel, read_frame=read,
                             clipped=clipped, exposures=[1.25])
    np.testing.assert_allclose(dim.low, kept.low / 1.25, rtol=1e-6)
    np.testing.assert_allclose(dim.high, kept.high / 1.25, rtol=1e-6)


def _stacked_and_last_frame(files, folder):
    """The main job's result of ``files``, its sidecar, and the last frame warped onto the
    result by the sidecar's own homography."""
    out = folder / "result.tif"
    process_stack(files, out)
    result = read_frame(out)
    side = json.loads(out.with_name(out.name + ".json").read_text())
    last = align.warp(read_frame(files[-1]), np.array(side["frames"][-1]["homography"]),
                      result.shape)
    return result, side, last


def test_beetles_shell_beyond_its_last_frame_is_as_detailed_as_that_frame(tmp_path, shared_data):
    """The shell at the top of beetle lies beyond the last frame (0.09 of the range by the
    end fit, more at the top): before, the result's 1-4 px band there held 0.79 of the
    frame's; the end frame's detail brings it to at least 0.95, without adding grain in the
    dark background."""
    files = sorted((shared_data / "chimpstackr-beetle").glob("DSC_*.jpg"))
    result, side, last = _stacked_and_last_frame(files, tmp_path)
    shell = np.s_[10:160, 260:490]

    def band(image, box):
        g = np.power(np.clip(image.mean(axis=2), 0, None), 1 / 2.2)  # display terms
        return float(np.std((g - cv2.GaussianBlur(g, (0, 0), 2.0))[box]))

    assert band(result, shell) > 0.95 * band(last, shell)
    background = np.s_[5:60, 640:745]  # dark, out of focus everywhere
    assert band(result, background) < band(last, background)
    ends = side["frame_range"]["beyond_ends"]
    assert ends[-1]["frame"] == files[-1].name and ends[-1]["detail_kept"] > 0.5


def test_dark_and_undershooting_pixels_are_not_blown_up():
    """A deconvolved result dips below 0 near dark edges: scaling its channels by the grey
    image's change would multiply them by thousands there, or (a ratio to a floor, until
    stop 44) move them the wrong way. Where the grey image is at or below 0 the frame's
    detail is added to every channel alike, and nowhere is a change larger than the
    frame's own detail."""
    grey = _texture(17)
    frame = np.repeat(grey[..., None], 3, axis=2)
    result = np.repeat(cv2.GaussianBlur(grey, (0, 0), 2.5)[..., None], 3, axis=2)
    result[40:60, 40:60] = [-0.01, -0.005, 0.0]  # an undershoot, and a black pixel
    out = result.copy()
    keep_end_detail(out, frame, np.ones(grey.shape, np.float32), noise=0.0)
    assert np.all(np.isfinite(out))
    change = out - result
    block = change[40:60, 40:60]
    np.testing.assert_allclose(block[..., 0], block[..., 2], atol=1e-6)  # alike
    np.testing.assert_allclose(block[..., 1], block[..., 2], atol=1e-6)
    assert np.abs(block).max() > 0.01  # the frame's detail did arrive
    detail = np.abs(grey - cv2.GaussianBlur(grey, (0, 0), 8.0)).max()
    assert np.abs(change).max() < 1.5 * detail and out.max() < 1.5


@pytest.mark.parametrize(("shift_px", "gain"), [(0.0, 0.3), (0.5, 0.5), (1.0, 0.8)])
def test_a_slightly_misaligned_frame_still_helps(shift_px, gain):
    """The end frame's alignment error (ECC's, where a lens breathes: 0.1-0.4 px) moves its
    detail against the result's coarser bands. Against the truth as the frame shows it, the
    error stays well below the soft result's up to 1 px (measured 0.21, 0.42 and 0.73 of it
    at 0, 0.5 and 1 px); at 2 px it is 1.3 times the soft result's, which the alignment's
    sub-pixel precision keeps away."""
    truth = _texture(21)
    truth[:, 100:] += 0.3  # and a step
    seen = cv2.GaussianBlur(truth, (0, 0), 0.7)
    shift = np.float32([[1, 0, shift_px], [0, 1, 0]])
    frame = cv2.warpAffine(seen, shift, truth.shape[::-1], flags=cv2.INTER_CUBIC,
                           borderMode=cv2.BORDER_REFLECT)
    result = cv2.GaussianBlur(truth, (0, 0), 2.5)
    out = result.copy()
    keep_end_detail(out, frame, np.ones(truth.shape, np.float32), noise=0.0)
    inner = np.s_[16:-16, 16:-16]
    error = float(np.abs(out - seen)[inner].mean())
    assert error < gain * float(np.abs(result - seen)[inner].mean())


@pytest.mark.parametrize("channels", [None, 1, 3, 4])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_mean_grey_is_the_channels_mean_for_any_channel_count(channels, dtype):
    """Against numpy's mean (the end correction's check passes a single channel axis; the
    3-channel path runs through cv2.transform)."""
    shape = (5, 7) if channels is None else (5, 7, channels)
    image = np.random.default_rng(3).uniform(-0.2, 1.3, shape).astype(dtype)
    grey = mean_grey(image)
    want = image if channels is None else image.astype(np.float64).mean(axis=2)
    assert grey.shape == (5, 7) and grey.dtype == dtype
    np.testing.assert_allclose(grey, want, rtol=1e-6, atol=1e-7)


def _bars(shape=(40, 90)) -> np.ndarray:
    """Dark bars of widths 3, 9 and 5 px on a light ground (linear light), with a dark dot
    above the wide bar: an asymmetric pattern."""
    frame = np.full(shape, 0.6, np.float32)
    for c0, width in ((10, 3), (30, 9), (60, 5)):
        frame[:, c0:c0 + width] = 0.05
    frame[4:7, 50:53] = 0.1
    return frame


def _frame_range(frame, weight) -> EndRange:
    """The range :func:`restore_ends` hands on, computed here by scipy's filters."""
    box = (slice(0, frame.shape[0]), slice(0, frame.shape[1]))
    grey = frame.mean(axis=2) if frame.ndim == 3 else frame
    return EndRange(box, ndimage.minimum_filter(grey, 3, mode="nearest"),
                    ndimage.maximum_filter(grey, 3, mode="nearest"), weight)


def test_a_ring_inside_a_bar_leaves_and_the_rest_stays():
    """pcb7's far bars (NOTE part 22): the end correction rang a light line down the middle
    of each wide bar, which the other frames' range let stand. Kept to the end frame's own
    range (here over 3x3; the job's is 5x5), the line goes; pixels in range are not
    touched; where the weight is 0 nothing changes, where it is 0.5 half the excess goes."""
    frame = _bars()
    result = frame.copy()
    result[:, 33:36] += 0.25  # the light line inside the 9 px bar (columns 30-38)
    result[:, 20:24] = 0.62  # the ground (0.6) a little too light
    result[:, 29] = 0.3  # beside the bar's edge: between the ground and the bar, in range
    weight = np.ones(frame.shape, np.float32)
    weight[20:30] = 0.5
    weight[30:] = 0.0  # the bottom rows: no end's
    out = result.copy()
    moved = keep_to_end_frames(out, [_frame_range(frame, weight)])
    np.testing.assert_allclose(out[:20, 33:36], 0.05, atol=1e-6)  # the line is gone
    np.testing.assert_allclose(out[:20, 20:24], 0.6, atol=1e-6)
    np.testing.assert_allclose(out[20:30, 33:36], 0.05 + 0.125, atol=1e-6)  # half way
    np.testing.assert_array_equal(out[30:], result[30:])  # weight 0: as it was
    untouched = np.ones(frame.shape[1], bool)
    untouched[20:24] = untouched[33:36] = False
    np.testing.assert_array_equal(out[:, untouched], result[:, untouched])  # column 29 too
    assert moved == pytest.approx(7 * (20 + 10 * 0.5) / (90 * (20 + 10 * 0.5)))


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000))
@example(seed=3)
def test_colour_keeps_its_hue_and_dark_pixels_stay_finite(seed):
    """The grey image moves into range by scaling the channels (the hue stays) at most by
    MAX_DETAIL_GAIN, the rest as an offset: dark, black and negative pixels (a deconvolved
    undershoot) land in range with no NaN, no blow-up."""
    rng = np.random.default_rng(seed)
    colour = np.array([0.9, 0.35, 0.1], np.float32)
    frame = _bars()[..., None] * colour
    result = frame * rng.uniform(0.3, 2.0, frame.shape[:2])[..., None].astype(np.float32)
    result[5:8, 40:44] = [-0.02, 0.0, 0.01]  # an undershoot whose grey is below 0
    result[9:11, 40:44] = 0.0  # black
    result[12:14, 40:44] = [1e-7, 1e-7, 0.0]  # almost black: the gain is bounded
    out = result.copy()
    ranges = [_frame_range(frame, np.ones(frame.shape[:2], np.float32))]
    keep_to_end_frames(out, ranges)
    assert np.all(np.isfinite(out)) and out.max() < 1.0
    grey = out.mean(axis=2)
    assert np.all(grey >= ranges[0].low - 1e-6) and np.all(grey <= ranges[0].high + 1e-6)
    scaled = (result.mean(axis=2) > 0.05)  # scaled, not offset: the hue of the input
    share = out[scaled] / out[scaled].sum(axis=1, keepdims=True)
    np.testing.assert_allclose(share, np.broadcast_to(colour / colour.sum(), share.shape),
                               atol=1e-4)
    assert np.abs(out - result).max() > 0.05  # it did something


def test_no_ranges_leave_the_result_and_report_nothing():
    result = _bars()
    out = result.copy()
    assert keep_to_end_frames(out, []) == 0.0
    np.testing.assert_array_equal(out, result)


def test_pcb7s_far_bars_are_as_dark_as_its_last_frame_shows_them(tmp_path, shared_data):
    """pcb7's striped background (rows 150-400, columns 1440-1640) lies beyond its last
    frame, which shows its bars sharp. Before :func:`keep_to_end_frames` the end correction
    left a light line down each wide bar: the result's column profile (8-bit sRGB, the
    mean over the rows) stood up to 10.8 levels from the frame's, 7.0 levels rms from the
    frame over the box; with it, measured 6.3 and 4.9."""
    files = sorted((shared_data / "focusstack-pcb" / "pcb7").glob("pcb_*.jpg"))
    result, side, last = _stacked_and_last_frame(files, tmp_path)
    box = np.s_[150:400, 1440:1640]

    def levels(image):
        return 255 * linear_to_srgb(np.clip(mean_grey(image[box]), 0, 1))

    got, seen = levels(result), levels(last)
    profile = np.abs(got.mean(axis=0) - seen.mean(axis=0))
    rms = float(np.sqrt(np.mean((got - seen) ** 2)))
    assert profile.max() < 8 and rms < 5.5, (profile.max(), rms)
    assert side["frame_range"]["end_range_moved"] > 0.05
    assert np.std(got) > 0.95 * np.std(seen)  # as contrasted as the frame (not flattened)


@pytest.mark.parametrize("channels", [None, 1, 3, 4])
def test_scale_channels_gives_numpys_broadcast_products_in_place(channels):
    """Every channel times the weight, bit for bit as numpy's broadcast, on a view that is
    neither contiguous nor a whole number of strips (the end correction's box), the
    pixels outside the view untouched; a weight in float64 too."""
    rng = np.random.default_rng(11)
    rows = 2 * STRIP_ROWS + 7
    shape = (rows, 50) if channels is None else (rows, 50, channels)
    whole = rng.uniform(-1, 2, shape).astype(np.float32)
    before = whole.copy()
    view = whole[5:, 3:41]
    for dtype in (np.float32, np.float64):
        weight = rng.uniform(0, 3, (rows + 4, 60)).astype(dtype)[9:, 7:45]  # a view too
        start = view.copy()
        expect = start * (weight if channels is None else weight[..., None])
        out = scale_channels(view, weight)
        assert out is view
        np.testing.assert_array_equal(view, expect.astype(np.float32))
        assert not np.array_equal(view, start)  # it changed something
    outside = np.ones(whole.shape[:2], bool)
    outside[5:, 3:41] = False
    np.testing.assert_array_equal(whole[outside], before[outside])


@pytest.mark.parametrize("channels", [None, 1, 3, 4])
def test_move_grey_reaches_the_target_keeping_the_hue_where_it_can(channels):
    """The grey image becomes the target in any channel layout; where the gain stays in
    [0, max_gain] every channel is scaled alike (the hue stays), elsewhere the rest is
    added alike; negative and black pixels get finite values."""
    rng = np.random.default_rng(5)
    shape = (24, 30) if channels is None else (24, 30, channels)
    image = rng.uniform(0.05, 0.9, shape).astype(np.float32)
    image[:3] = -0.02  # an undershoot
    image[3:5] = 0.0
    grey = np.array(mean_grey(image), np.float32)
    target = (grey * rng.uniform(0.2, 6.0, grey.shape) + 0.01).astype(np.float32)
    out = image.copy()
    move_grey(out, grey, target, max_gain=4.0)
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(mean_grey(out), target, atol=1e-5)
    ratio = target / np.where(grey > 0, grey, 1)
    scaled = (grey > 0) & (ratio <= 4.0)
    assert scaled.mean() > 0.3  # the case
    if channels is not None:
        expect = image * ratio[..., None]
        np.testing.assert_allclose(out[scaled], expect[scaled], rtol=1e-4, atol=1e-6)
        gain = np.where(grey > 0, np.clip(ratio, 0, 4), 1)  # none where the grey is <= 0
        rest = out[~scaled] - image[~scaled] * gain[~scaled][..., None]
        np.testing.assert_allclose(rest, np.repeat(rest[:, :1], channels, axis=1), atol=1e-5)
