"""Each inner frame's own detail where it is the sharpest (issue 13;
:mod:`pipeline.jobs.frame_detail`): the maps say which frame is the sharpest where, the
composite's bands reach the result only where it is softer, and on rendered stacks with a
ground truth the result comes closer to the truth."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from scipy import ndimage
from skimage import data
from test_engine import make_stack, positions_for

from pipeline.core.colour import srgb_to_linear
from pipeline.core.deconvolve.common import noise_sigma_2d
from pipeline.core.defocus import FocusMaps
from pipeline.core.quality import psnr
from pipeline.jobs.ends import keep_end_detail
from pipeline.jobs.frame_detail import away_from_other_depths, detail_maps, keep_inner_detail
from pipeline.jobs.options import StackOptions
from pipeline.jobs.stack import process_stack


def _texture(seed: int, shape=(96, 120)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), 1.2)
    t[:, ::5] += 1.0  # columns, not rows: a transposed map would be caught
    return 0.4 + 0.1 * t / t.std()


def test_maps_mark_where_each_inner_frame_is_the_sharpest():
    """Five frames of one texture, frame k sharp in the k-th column strip and blurred
    elsewhere: the inner frames' maps are high in their own strip and 0 in the others; the
    two end frames get no map (they have their own step)."""
    sharp = _texture(1)
    blurred = cv2.GaussianBlur(sharp, (0, 0), 3.0)
    width = sharp.shape[1] // 5
    frames = []
    for k in range(5):
        f = blurred.copy()
        f[:, k * width : (k + 1) * width] = sharp[:, k * width : (k + 1) * width]
        frames.append(f)
    detail = detail_maps(FocusMaps.of(frames), np.arange(5.0))
    assert detail.inner == [1, 2, 3] and detail.weight(0) is None and detail.weight(4) is None
    for k in detail.inner:
        m = detail.weight(k)
        inside = m[10:-10, k * width + 6 : (k + 1) * width - 6]
        outside = np.delete(m[10:-10], np.s_[k * width - 6 : (k + 1) * width + 6], axis=1)
        assert inside.mean() > 0.9 and outside.max() == 0


def test_inner_detail_restores_a_soft_result_and_leaves_a_sharp_one():
    """A result blurred by 1.5 px against the frames' composite of the truth: the error
    falls below half; a result already as sharp as the composite does not move; clipped
    pixels stay as they were; a composite weight above 1 (overlapping maps) counts as 1."""
    truth = _texture(2)
    composite = (2.0 * truth, np.full(truth.shape, 2.0, np.float32))  # two maps overlap
    soft = cv2.GaussianBlur(truth, (0, 0), 1.5)
    result = soft.copy()
    clipped = np.zeros(truth.shape, bool)
    clipped[:, :20] = True
    everywhere = np.ones(truth.shape, np.float32)
    keep_inner_detail(result, composite, everywhere, clipped)
    inner = np.s_[12:-12, 32:-12]
    error = lambda a: float(np.sqrt(np.mean((a[inner] - truth[inner]) ** 2)))  # noqa: E731
    assert error(result) < 0.5 * error(soft)
    np.testing.assert_array_equal(result[:, :20], soft[:, :20])
    already = truth.copy()
    keep_inner_detail(already, composite, everywhere)
    nowhere = soft.copy()
    keep_inner_detail(nowhere, composite, np.zeros((8, 10), np.float32))  # any size
    np.testing.assert_array_equal(nowhere, soft)
    np.testing.assert_allclose(already, truth, atol=1e-6)


def test_composite_stays_away_from_content_two_or_more_frames_off():
    """Seven frames, column strips sharpest in frames 1 | 2 | 5 (a depth jump of three
    frames between the second and third strip): frame 2's pixels within reach of frame 5's
    content (half its blur in frame 2, ``D |x_5 - x_2| / 2``, plus the bands' reach) are
    left out, and so are frame 5's next to frame 2's; frame 1 next to frame 2 (one frame
    apart) keeps its weight."""
    sharp = _texture(3, (60, 150))
    frames = [cv2.GaussianBlur(sharp, (0, 0), 4.0) for _ in range(7)]
    for k, cols in ((1, np.s_[:, :50]), (2, np.s_[:, 50:100]), (5, np.s_[:, 100:])):
        frames[k][cols] = sharp[cols]
    detail = detail_maps(FocusMaps.of(frames), np.arange(7.0))
    away = away_from_other_depths(detail, span_px=36.0)  # frame 2 sees 5 blurred by 18 px
    row = away[30]
    assert row[10:40].min() > 0.99  # frame 1, next to frame 2 only
    reach = 9 + 8  # half the blur, and the detail bands' reach
    assert row[100 - reach + 2 : 100].max() == 0 and row[100 : 100 + reach - 2].max() == 0
    assert row[60 : 100 - reach - 3].min() > 0.99


@pytest.fixture(scope="module")
def planes(tmp_path_factory):
    folder = tmp_path_factory.mktemp("planes")
    sharp = srgb_to_linear(data.astronaut()[40:296, 130:386].astype(np.float32) / 255)
    make_stack(folder, sharp, [500.0, 800.0, 1600.0], positions_for(450, 2500, 9), noise=0.01)
    return folder, sharp


def test_the_job_comes_closer_to_the_truth_and_keeps_occlusion_edges(planes, tmp_path):
    """Nine frames of three planes (sigma 0.01): the job with the inner frames' detail
    against the same job with the step off, both against the truth. Over the image it
    gains; in 12 px strips along the planes' edges, where a frame shows the other plane
    blurred into its own (a cut the scene does not have), it must not lose (without
    leaving those pixels out it lost 3 dB there). The sidecar records the share taken."""
    import pipeline.jobs.stack as job

    folder, sharp = planes
    options = StackOptions(encoding="float32")
    with_detail = process_stack(folder, tmp_path / "a.tif", options)
    kept = with_detail.sidecar["frame_range"]["inner_detail_kept"]
    assert 0.0 < kept <= 1.0
    real = job.keep_inner_detail
    job.keep_inner_detail = lambda *args, **kwargs: 0.0
    try:
        without = process_stack(folder, tmp_path / "b.tif", options)
    finally:
        job.keep_inner_detail = real
    cols = np.arange(sharp.shape[1])
    edges = (np.abs(cols - 85) < 12) | (np.abs(cols - 171) < 12)
    assert psnr(with_detail.image, sharp) > psnr(without.image, sharp) + 0.1
    assert psnr(with_detail.image[:, edges], sharp[:, edges]) > (
        psnr(without.image[:, edges], sharp[:, edges]) - 0.25
    )


def test_grain_is_not_detail_where_the_composite_is_empty_at_the_centre():
    """A noisy composite over the image's left and right thirds only (the centre lies where
    an end frame is the sharpest) and a flat result: the composite's grain is estimated
    where it covers, so none of it is taken (a centre-crop estimate read 0 there)."""
    rng = np.random.default_rng(4)
    shape = (200, 1400)  # wider than the 1024 px centre crop of a frame's noise estimate
    grain = (0.4 + 0.01 * rng.standard_normal(shape)).astype(np.float32)
    total = np.zeros(shape, np.float32)
    total[:, :150] = total[:, -150:] = 1.0
    result = np.full(shape, 0.4, np.float32)
    keep_inner_detail(result, (grain * total, total), np.ones(shape, np.float32))
    assert float(np.std(result[20:-20, 20:130])) < 0.2 * 0.01


def _maps(labels: np.ndarray) -> FocusMaps:
    """Focus maps whose sharpest frame per pixel is ``labels`` (no frames needed)."""
    maps = FocusMaps()
    maps.sharpest = labels.astype(np.intp)
    return maps


def test_a_frames_map_opens_specks_away_and_smooths_alike_in_both_directions():
    """Frame 1 is the sharpest in a 12 px square, a 3x3 block, and two specks of 2x3 and
    3x2 px: the map is that region opened by a 3x3 square (the block stays, the specks go),
    then smoothed by a Gaussian of 1.5 px (the documented seam; scipy's, with OpenCV's
    reflected border and 4-sigma reach), values under 0.02 dropped. The labels are
    symmetric under transposition, so the map must be too. The maps are frozen: ``inner``
    is cached from them."""
    labels = np.zeros((40, 40), np.intp)
    labels[:, -1] = 2  # the far end, so frame 1 is inner
    labels[-1, :] = 2
    labels[22:34, 22:34] = 1
    labels[10:13, 10:13] = 1
    labels[25:27, 4:7] = labels[4:7, 25:27] = 1  # 2x3 and 3x2: thinner than 3 px
    detail = detail_maps(_maps(labels), np.arange(3.0))
    weight = detail.weight(1)
    opened = np.zeros((40, 40), np.float64)
    opened[22:34, 22:34] = opened[10:13, 10:13] = 1.0
    expected = ndimage.gaussian_filter(opened, 1.5, mode="mirror", truncate=4.0)
    expected[expected < 0.02] = 0
    np.testing.assert_allclose(weight, expected, atol=2e-6)
    np.testing.assert_allclose(weight, weight.T, atol=1e-6)  # float32 rounding only
    assert weight[11, 11] > 0.4 and weight[25:27, 4:7].max() == 0
    with pytest.raises(dataclasses.FrozenInstanceError):
        detail.x = np.arange(3.0)


def test_the_composite_share_is_whole_wherever_no_other_depth_is_near():
    """Frames 0 | 1 | 2 | 3 of four sharpest in column strips, each next to a frame one
    step away (no cut; 0 and 2, 1 and 3 are 40 px apart, farther than the 21 px their blur
    and the bands reach): the share is 1 wherever the inner maps reach, their soft outer
    edges included (where the total is under 1), and 0 where neither does."""
    labels = np.zeros((40, 120), np.intp)
    labels[:, 20:60], labels[:, 60:100], labels[:, 100:] = 1, 2, 3
    detail = detail_maps(_maps(labels), np.arange(4.0))
    away = away_from_other_depths(detail, span_px=40.0)
    total = detail.weight(1) + detail.weight(2)
    assert (total[20] < 0.9).sum() > 10  # the maps' soft edges are in the row
    np.testing.assert_allclose(away[total > 0], 1.0, atol=1e-6)
    assert away[total == 0].max() == 0


@pytest.mark.parametrize("factor, first, last", [(1, 83, 116), (2, 87, 112)])
def test_the_left_out_strip_is_half_the_blur_and_the_bands_reach_at_the_maps_scale(
    factor, first, last
):
    """Frames 1 | 2 | 5 of seven sharpest in column strips split at 50 and 100 (positions
    normalised: frames 2 and 5 are 0.5 apart), a span of 36 px: each of frames 2 and 5 sees
    the other's content blurred to 18 px, so 9 px, plus the detail bands' reach
    (``DETAIL_WINDOW * max(DETAIL_SIGMAS_PX)`` = 8 full-resolution px, 4 at maps of half
    resolution) on each side of the edge is left out: columns 100 - 17 .. 99 + 17, or
    100 - 13 .. 99 + 13. Beyond that strip the share is whole."""
    labels = np.zeros((60, 150), np.intp)
    labels[:, :50], labels[:, 50:100], labels[:, 100:] = 1, 2, 5
    detail = detail_maps(_maps(labels), np.arange(7.0))
    row = away_from_other_depths(detail, span_px=36.0, factor=factor)[30]
    out = np.flatnonzero(row < 1e-6)
    assert (out.min(), out.max(), out.size) == (first, last, last - first + 1)
    np.testing.assert_allclose(row[first - 20 : first], 1.0, atol=1e-6)
    np.testing.assert_allclose(row[last + 1 : last + 21], 1.0, atol=1e-6)


def test_a_partly_weighted_composite_is_its_frame_not_a_dimmer_one():
    """One frame's composite weighted 0.6 everywhere (a map's soft edge): ``sum m g / sum m``
    is that frame (to float32 rounding), so the result is the frame's own detail handed over
    at weight 0.6 (:func:`~pipeline.jobs.ends.keep_end_detail` with the frame itself and its grain
    measured on it); a composite read as 0.6 g would lend a darker frame's weaker bands."""
    truth = _texture(5)
    soft = cv2.GaussianBlur(truth, (0, 0), 1.5)
    m = np.full(truth.shape, 0.6, np.float32)
    result, expected = soft.copy(), soft.copy()
    keep_inner_detail(result, (m * truth, m), np.ones(truth.shape, np.float32))
    keep_end_detail(expected, truth, m, noise_sigma_2d(truth, np.ones(truth.shape, bool)))
    np.testing.assert_allclose(result, expected, atol=1e-6)
    inner = np.s_[12:-12, 12:-12]
    error = lambda a: float(np.sqrt(np.mean((a[inner] - truth[inner]) ** 2)))  # noqa: E731
    assert error(result) < 0.8 * error(soft)  # it did hand detail over
