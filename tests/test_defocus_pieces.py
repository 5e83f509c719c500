"""The pieces of the blur-span and end-depth fits (:mod:`pipeline.core.defocus`), each
against an independent computation: which frame pairs the fit compares, the coarse focus
measure against scipy's Gaussians, the parabola's refinement on a cost with a known
minimum, the maps' border, the mean normalisation, and the fits' refusals (stop 55's
mutation run: the fits' tests read rendered stacks to 15%, which let these drift)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from scipy import ndimage
from test_defocus import render_stack

from pipeline.core import defocus
from pipeline.errors import InputError

# the steps between compared frames, as documented: neighbours and two apart for tiny
# stacks, 2 and 3 apart for four frames, then 2, 3, 4 and a third of the stack
STEPS = {2: {1}, 3: {1, 2}, 4: {2, 3}, 5: {2, 3, 4}, 9: {2, 3, 4}, 15: {2, 3, 4, 5},
         21: {2, 3, 4, 7}}


@pytest.mark.parametrize("n", sorted(STEPS))
def test_the_fit_compares_every_frame_with_those_its_steps_away_both_ways(n):
    expected = sorted((i, j) for i in range(n) for j in range(n) if abs(i - j) in STEPS[n])
    assert sorted(defocus._pairs(n)) == expected
    assert len(set(defocus._pairs(n))) == len(expected)  # each pair once


def test_the_coarse_measure_is_the_smoothed_energy_of_a_band_of_one_to_three_px():
    """``(G_1 g - G_3 g)^2`` smoothed by ``G_3`` (scipy's Gaussians, OpenCV's reflected
    border, 4-sigma reach); the same on a transposed frame, transposed (no axis favoured)."""
    rng = np.random.default_rng(3)
    grey = ndimage.gaussian_filter(rng.random((64, 80)), 0.7).astype(np.float32)
    grey[:, ::6] += 0.3  # columns, not rows

    def g(a, s):
        return ndimage.gaussian_filter(a, s, mode="mirror", truncate=4.0)

    g64 = grey.astype(np.float64)
    expected = g((g(g64, 1.0) - g(g64, 3.0)) ** 2, 3.0)
    got = defocus._coarse_measure(grey)
    np.testing.assert_allclose(got, expected, rtol=0, atol=2e-4 * expected.max())
    np.testing.assert_allclose(defocus._coarse_measure(np.ascontiguousarray(grey.T)), got.T,
                               rtol=0, atol=1e-6 * expected.max())


def test_the_parabola_finds_a_minimum_between_grid_points_on_either_side():
    """A cost quadratic in ``log d`` with its minimum 10% above a grid point (so the
    nearest grid point is below it) and 10% under one: the refinement returns it exactly,
    with the index of the best grid point; at the grid's ends, the end itself."""
    grid = np.geomspace(2.0, 400.0, 14)
    for k, factor in ((5, 1.1), (8, 1 / 1.1)):
        target = grid[k] * factor
        estimate, best = defocus._best_on_grid(lambda d, t=target: np.log(d / t) ** 2, grid)
        assert best == k and estimate == pytest.approx(target, rel=1e-9)
    assert defocus._best_on_grid(lambda d: d, grid) == (2.0, 0)
    assert defocus._best_on_grid(lambda d: -d, grid) == (pytest.approx(400.0), 13)


def test_a_fit_at_the_search_edge_is_warned_of_unless_asked_not_to(caplog):
    """Identical frames (no blur between them): the span lands on the grid's first point,
    2 px, and the user is told; with ``warn=False`` (a caller that fits again) not."""
    frame = render_stack(20.0, n=1)[0][0]
    frames = [frame.copy() for _ in range(4)]
    with caplog.at_level(logging.WARNING, logger="pipeline.core.defocus"):
        assert defocus.estimate_blur_span(frames, np.arange(4.0)) == pytest.approx(2.0)
    assert "edge of the search" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pipeline.core.defocus"):
        defocus.estimate_blur_span(frames, np.arange(4.0), warn=False)
    assert caplog.text == ""


def test_two_frames_are_enough_for_both_fits():
    """The smallest stack: both fits run (one end per frame), and a wider span reads
    wider."""
    frames, x = render_stack(16.0, n=2)
    assert 8.0 < defocus.estimate_blur_span(frames, x) < 32.0
    ends, sharpest = defocus.end_depths(frames, x, 16.0)
    assert [e.frame for e in ends] == [0, 1] and sharpest.shape == frames[0].shape


@pytest.mark.parametrize("positions, span", [
    pytest.param([0.0, 1.0, 2.0, 3.0], 10.0, id="three frames, four positions"),
    pytest.param([1.0, 1.0, 1.0], 10.0, id="one position"),
    pytest.param([0.0, 1.0, 2.0], 0.0, id="no blur span"),
    pytest.param([0.0, 1.0, 2.0], -3.0, id="a negative blur span"),
    pytest.param([0.0], 10.0, id="one frame"),
])
def test_end_depths_refuse_what_they_cannot_fit(positions, span):
    frames, _ = render_stack(10.0, n=3)
    frames = frames[: len(positions)]  # one frame per position, or three for four
    with pytest.raises(InputError, match="need >= 2 frames"):
        defocus.end_depths(frames, positions, span)


def test_the_maps_border_is_five_percent_of_the_shorter_side():
    """On 200 x 300 frames the masks leave out 10 px at every border (at least 4 px)."""
    rng = np.random.default_rng(6)
    frames = [ndimage.gaussian_filter(rng.random((200, 300)), s).astype(np.float32) + 0.2
              for s in (0.5, 1.5)]
    maps = defocus.FocusMaps.of(frames)
    either = maps.masks([0, 1])[0] | maps.masks([0, 1])[1]
    rows, cols = np.nonzero(either)
    assert (rows.min(), cols.min(), rows.max(), cols.max()) == (10, 10, 189, 289)


def test_a_frames_exposure_does_not_change_its_normalised_image():
    frame = render_stack(10.0, n=1)[0][0]
    once, thrice = defocus._normalised(frame), defocus._normalised(3.0 * frame)
    assert float(np.mean(once)) == pytest.approx(1.0, rel=1e-5)
    np.testing.assert_allclose(thrice, once, rtol=1e-5)


@pytest.mark.parametrize("count, positions", [(3, [0.0, 1.0, 2.0, 3.0]), (1, [0.0])])
def test_the_span_fit_refuses_frames_without_one_position_each_or_a_single_frame(
    count, positions
):
    frames = render_stack(10.0, n=3)[0][:count]
    with pytest.raises(InputError, match="need >= 2 frames with one position each"):
        defocus.estimate_blur_span(frames, positions)


def test_a_blur_span_under_a_pixel_is_fitted_not_refused():
    frames, x = render_stack(10.0, n=3)
    ends, _ = defocus.end_depths(frames, x, 0.5)
    assert [e.frame for e in ends] == [0, 2]


@pytest.mark.parametrize("others, first", [([1, 2, 3], 38), ([0], 44)])
def test_other_depths_reach_half_their_blur_plus_the_fits(others, first):
    """Frame 0 (an end) sharpest left of column 50, frame 3 (three frames away, x = 1)
    right of it, a span of 12 px: frame 3's content lies blurred by 12 px in frame 0, so
    half of that, 6 px, plus half the widest blur the fit of frame 0 compares (frames 1-3:
    6 px more; itself alone: none) from column 50 is near: columns 38 on, or 44 on."""
    sharpest = np.zeros((40, 100), np.intp)
    sharpest[:, 50:] = 3
    textured = np.ones(sharpest.shape, bool)
    near = defocus.near_other_depths(sharpest, textured, np.linspace(0, 1, 4), 0, others, 12.0)
    row = near[20]
    assert not row[:first].any() and row[first:].all()
