"""The blur-span fit (``core.defocus``) on stacks rendered with a known span.

Frames are rendered by brute force: each depth strip of a random texture is convolved
with a supersampled disk (``tests/test_stack_heart.py``) of diameter ``D |x_i - z|``,
independent of ``psf.raster_pillbox`` and of the fit's own convolution.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from test_stack_heart import supersampled_pillbox

from pipeline.core.align import Alignment
from pipeline.core.defocus import estimate_blur_span
from pipeline.errors import InputError
from pipeline.jobs.stack import _blur_fit_previews


def render_stack(span_px: float, n: int = 7, seed: int = 0, size: int = 160, strips: int = 8):
    """``n`` frames at x = 0..1 of a scene whose ``strips`` column strips are in focus at
    evenly spaced positions."""
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.random((size, size)).astype(np.float32), (0, 0), 0.7)
    depth = (np.arange(size) * strips // size) / (strips - 1)  # column -> focus position
    x = np.linspace(0.0, 1.0, n)
    frames = []
    for xi in x:
        frame = np.empty_like(texture)
        for z in np.unique(depth):
            diameter = span_px * abs(xi - z)
            half = int(np.ceil(diameter / 2)) + 1
            k = supersampled_pillbox(diameter, half, n=16).astype(np.float32)
            blurred = cv2.filter2D(texture, -1, k[::-1, ::-1], borderType=cv2.BORDER_REFLECT)
            frame[:, depth == z] = blurred[:, depth == z]
        frames.append(0.2 + frame)
    return frames, x


@pytest.mark.parametrize("span", [12.0, 30.0])
def test_recovers_the_span_it_was_rendered_with(span):
    frames, x = render_stack(span)
    assert estimate_blur_span(frames, x) == pytest.approx(span, rel=0.15)


def test_span_is_in_full_resolution_pixels_and_ignores_position_units():
    frames, x = render_stack(20.0)
    assert estimate_blur_span(frames, 1000 + 37 * x, downscale=2.0) == pytest.approx(
        40.0, rel=0.15
    )


def test_all_frames_at_one_position_is_refused():
    frames, _ = render_stack(10.0, n=3)
    with pytest.raises(InputError, match="same focus position"):
        estimate_blur_span(frames, [5, 5, 5])


def test_fit_previews_of_a_breathing_stack_keep_its_blur():
    """The job's fit previews (aligned, then reduced) of a stack magnified 0.3% per frame:
    the span fitted on them stays the rendered one. Reduced before the bilinear warp, the
    warp's offset-dependent blur (up to half a pixel at the fit's 320 px) read 55% more."""
    size, span = 640, 8.0
    frames, x = render_stack(span, n=9, size=size, strips=64)
    centre = (size - 1) / 2
    magnified, alignments = [], []
    for i, frame in enumerate(frames):
        s = 1 + 0.003 * (i - 4)
        m = np.array([[s, 0, (1 - s) * centre], [0, s, (1 - s) * centre], [0, 0, 1.0]])
        magnified.append(
            cv2.warpPerspective(
                frame, m, (size, size), flags=cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REFLECT
            )
        )
        alignments.append(Alignment(np.linalg.inv(m), 1 / s, "test", True, "", 1.0))
    small, factor = _blur_fit_previews(magnified, alignments, (size, size))
    assert factor == pytest.approx(2.0)
    assert estimate_blur_span(small, x, downscale=factor) == pytest.approx(span, rel=0.2)
