"""The small pieces of the ends' step (:mod:`pipeline.jobs.ends`), each against an
independent computation: an end frame's own kernel at the correction's resolution, the
boxes the two ends change, the reduced-resolution Gaussian window of the detail step, and
the detail step's indifference to the frames' units (issue 13, stop 55's mutation run: the
covering tests are whole-stack runs that let these pieces drift)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import ndimage

from pipeline.jobs import ends


def _offset_kernel(size: int, left: int, right: int) -> np.ndarray:
    """A ``size`` x ``size`` kernel (centre ``h = size // 2``) non-zero over columns
    ``h - left .. h + right`` and rows ``h - 1 .. h + 1``, ramped so no two columns are
    alike: asymmetric on purpose (a flipped or centred kernel differs)."""
    h = size // 2
    k = np.zeros((size, size), np.float32)
    k[h - 1 : h + 2, h - left : h + right + 1] = np.arange(1, left + right + 2, dtype=np.float32)
    return k / k.sum()


@pytest.mark.parametrize("left, right", [(7, 3), (3, 7)])
def test_an_end_frames_kernel_is_cropped_to_its_widest_side_about_the_centre(left, right):
    """Support from ``h - left`` to ``h + right``: the crop keeps ``max(left, right)`` on
    both sides of the centre (the kernel's centre stays the crop's), then reduces it by
    area to an odd side that sums to 1, with nothing at the far column of its short side."""
    kernel = _offset_kernel(31, left, right)
    own = ends._own_kernel(kernel, 2)
    half = max(left, right)  # 15 px crop -> 15 // 2 | 1 = 7 px
    crop = kernel[15 - half : 16 + half, 15 - half : 16 + half]
    expected = cv2.resize(crop, (7, 7), interpolation=cv2.INTER_AREA).astype(np.float64)
    np.testing.assert_allclose(own, expected / expected.sum(), rtol=1e-6)
    assert own.shape == (7, 7) and abs(own.sum() - 1) < 1e-6
    wide, short = (0, -1) if left > right else (-1, 0)  # the support's wide and short sides
    assert own[:, wide].sum() > 0 and own[:, short].sum() == 0


@pytest.mark.parametrize("half, factor, single", [(1, 3, True), (1, 4, True), (3, 8, True),
                                                  (3, 6, False), (4, 4, False)])
def test_an_end_frames_kernel_no_wider_than_the_reduction_is_one_pixel(half, factor, single):
    """A kernel ``2 half + 1`` px wide reduced ``factor`` times is a single pixel when it
    fits in one reduced pixel (``2 half + 1 <= factor``: the end frame's own depth), else a
    reduced kernel of at least 3 px."""
    kernel = _offset_kernel(41, half, half)
    own = ends._own_kernel(kernel, factor)
    if single:
        np.testing.assert_array_equal(own, np.ones((1, 1)))
    else:
        assert own.shape[0] >= 3 and own.shape[0] % 2 == 1 and abs(own.sum() - 1) < 1e-6


def test_a_kernel_that_fills_its_array_is_kept_whole():
    """A pillbox reaching the array's edge: the support is every column, nothing is cut."""
    size = 21
    yy, xx = np.mgrid[:size, :size] - size // 2
    kernel = (np.hypot(yy, xx) <= 10.5).astype(np.float32)
    own = ends._own_kernel(kernel / kernel.sum(), 2)
    expected = cv2.resize(kernel, (11, 11), interpolation=cv2.INTER_AREA).astype(np.float64)
    np.testing.assert_allclose(own, expected / expected.sum(), rtol=1e-6)


def test_boxes_that_only_touch_do_not_overlap():
    """Half-open slices: rows 0-9 and 10-19 share no pixel, rows 0-10 and 10-19 share row
    10; both axes must overlap."""
    cols = slice(0, 10)
    assert not ends._overlap((slice(0, 10), cols), (slice(10, 20), cols))
    assert not ends._overlap((slice(10, 20), cols), (slice(0, 10), cols))
    assert ends._overlap((slice(0, 11), cols), (slice(10, 20), cols))
    assert not ends._overlap((slice(0, 11), slice(0, 5)), (slice(10, 20), slice(5, 9)))


@pytest.mark.parametrize("window, shape", [(2.0, (37, 53)), (8.0, (90, 130)), (12.0, (121, 163))])
def test_the_reduced_window_smooths_as_a_gaussian_of_its_width(window, shape):
    """``up(down(x))`` smooths twice by the window: a Gaussian of ``window * sqrt(2)``
    (scipy's, reflected border) to 5% of a wide blob's peak (1.2% at 8 px, 4% at 12 px:
    the reduction's price), at the full shape,
    with the reduced image ``ceil(shape / (window // 2))`` in size; a 2 px window is not
    reduced and is exactly OpenCV's blur. Frames need not divide by the reduction."""
    yy, xx = np.mgrid[: shape[0], : shape[1]].astype(np.float32)
    blob = np.exp(-((yy - 0.45 * shape[0]) ** 2 + (xx - 0.6 * shape[1]) ** 2) / 200.0)
    blob = blob.astype(np.float32)
    smooth = ends._Smooth(window, shape)
    factor = max(1, int(window // 2))
    down = smooth.down(blob)
    assert down.shape == (-(-shape[0] // factor), -(-shape[1] // factor))
    out = smooth.up(down)
    assert out.shape == shape
    expected = ndimage.gaussian_filter(blob.astype(np.float64), window * np.sqrt(2), mode="mirror")
    assert float(np.max(np.abs(out - expected))) < 0.05 * float(expected.max())
    if factor == 1:
        once = cv2.GaussianBlur(blob, (0, 0), window)
        np.testing.assert_array_equal(down, once)


def test_the_detail_step_does_not_depend_on_the_frames_units():
    """Frames in units of 1e30 with a black pixel (squares of such values overflow float32
    unless scaled by the largest magnitude): the result is the unit result times 1e30,
    finite everywhere."""
    rng = np.random.default_rng(4)
    truth = cv2.GaussianBlur(rng.standard_normal((64, 80)).astype(np.float32), (0, 0), 1.0)
    truth = np.clip(0.4 + 0.1 * truth / truth.std(), 0, None)
    frame = cv2.GaussianBlur(truth, (0, 0), 0.6)
    soft = cv2.GaussianBlur(truth, (0, 0), 2.0)
    frame[5, 7] = soft[5, 7] = 0.0  # the smallest magnitude 0: only the largest can scale
    weight = np.ones(truth.shape, np.float32)
    unit, big = soft.copy(), soft * np.float32(1e30)
    ends.keep_end_detail(unit, frame, weight, noise=0.002)
    ends.keep_end_detail(big, frame * np.float32(1e30), weight, noise=0.002 * 1e30)
    assert np.isfinite(big).all()
    np.testing.assert_allclose(big / np.float32(1e30), unit, rtol=1e-4, atol=1e-6)
    assert float(np.abs(unit - soft).max()) > 0.01  # detail was handed over


def _three_depth_previews(patch: int) -> list[np.ndarray]:
    """Five grey previews of one texture: a ``patch`` px square at frame 0's depth, the
    right 60 columns at frame 4's, the rest at frame 2's; frame ``i`` sees depth ``d``
    blurred by a Gaussian of ``1.5 |d - i|`` px."""
    rng = np.random.default_rng(1)
    texture = cv2.GaussianBlur(rng.standard_normal((120, 160)).astype(np.float32), (0, 0), 0.8)
    texture = 0.4 + 0.1 * texture
    depth = np.full(texture.shape, 2.0)
    depth[:, 100:] = 4.0
    depth[10 : 10 + patch, 10 : 10 + patch] = 0.0
    frames = []
    for i in range(5):
        out = np.zeros_like(texture)
        for d in (0.0, 2.0, 4.0):
            sigma = 1.5 * abs(d - i)
            seen = cv2.GaussianBlur(texture, (0, 0), sigma) if sigma else texture
            out = np.where(depth == d, seen, out)
        frames.append(out)
    return frames


@pytest.mark.parametrize("patch, kept", [(10, [4]), (30, [0, 4])])
def test_an_end_that_covers_too_little_is_skipped_and_the_other_still_counts(patch, kept):
    """Frame 0 is the sharpest in a 10 px square (0.3% of the previews, under
    ``MIN_FRACTION``): it gets no kernel, and frame 4, which ``end_depths`` lists after it,
    still gets its own; a 30 px square (4.7%) keeps both."""
    frames = _three_depth_previews(patch)
    got = ends.end_kernels(
        (frames, 1.0, None), np.arange(5.0), np.full(5, 0.2), 12.0,
        lens=None, absolute=False, read_end=lambda i: frames[i],
    )
    assert [k.frame for k in got] == kept


def test_the_detail_box_holds_the_weighted_rows_and_columns_and_the_filters_reach():
    """Weight at rows 40 and 70 and columns 50-59 of a 200 x 300 blend: the box runs from
    the first to the last of them, widened by the filters' reach (4 x ``DETAIL_WINDOW`` x
    the widest band sigma = 32 px) and cut at the image's edges; no weight, no box."""
    blend = np.zeros((200, 300), np.float32)
    blend[40, 50:60] = blend[70, 55] = 0.5
    blend[100, 10] = 0.5 * ends.BLEND_FLOOR  # under the floor: not a weighted pixel
    assert ends._detail_box(blend) == (slice(8, 103), slice(18, 92))
    blend[195, 290] = 1.0
    assert ends._detail_box(blend) == (slice(8, 200), slice(18, 300))
    assert ends._detail_box(np.zeros((20, 30), np.float32)) is None


@pytest.mark.parametrize("fine, coarse", [(0.0, 1.0), (1.0, 2.0), (2.0, 4.0)])
def test_the_band_noise_gain_is_the_variance_of_filtered_white_noise(fine, coarse):
    """Unit white noise through OpenCV's ``G_fine - G_coarse`` (the image itself for
    ``fine`` 0), measured on a 1024 px field (sampling error about 1%): its variance is the
    gain, within 4%."""
    noise = np.random.default_rng(2).standard_normal((1024, 1024)).astype(np.float32)
    finer = noise if fine == 0 else cv2.GaussianBlur(noise, (0, 0), fine)
    band = (finer - cv2.GaussianBlur(noise, (0, 0), coarse))[40:-40, 40:-40]
    assert ends._band_noise_gain(fine, coarse) == pytest.approx(float(band.var()), rel=0.04)


def test_black_frames_leave_a_black_result_and_no_share():
    """A black end frame over a black result (a lens cap, a dark frame in the stack): no
    scale to take, nothing changes, nothing is NaN, no band took over."""
    result = np.zeros((40, 50, 3), np.float32)
    share = ends.keep_end_detail(result, np.zeros((40, 50), np.float32),
                                 np.ones((40, 50), np.float32), noise=0.0)
    np.testing.assert_array_equal(result, 0.0)
    assert share == 0.0


def test_the_share_counts_where_a_band_took_over():
    """The returned share: about all of the weighted area where the result is much softer
    than the frame, none where the result is the frame itself (no band has more to give)."""
    rng = np.random.default_rng(8)
    truth = cv2.GaussianBlur(rng.standard_normal((80, 96)).astype(np.float32), (0, 0), 0.8)
    truth = 0.4 + 0.1 * truth / truth.std()
    weight = np.ones(truth.shape, np.float32)
    soft = cv2.GaussianBlur(truth, (0, 0), 3.0)
    assert ends.keep_end_detail(soft, truth, weight, noise=0.0) > 0.9
    same = truth.copy()
    assert ends.keep_end_detail(same, truth, weight, noise=0.0) == 0.0
