"""Estimate a focal stack's defocus scale from its frames (for stacks without a lens profile).

In a focal stack, a point in focus in frame ``i`` appears in frame ``j`` blurred
by a disk of diameter ``b = a |p_i - p_j| / (v pitch)`` (Eq. 2): linear in the
frames' focus positions, with one unknown slope. With positions normalised to
``x in [0, 1]`` the slope is the *blur span* ``D`` (px): the blur, in frame
``j``, of a point focused in frame ``i``, is ``D |x_i - x_j|``.

``D`` is fitted by predicting frame ``j`` from frame ``i`` on the pixels where
``i`` is the sharpest frame: ``g_j ~ g_i * P(D |x_i - x_j|)`` (Eq. 3 pillbox),
minimising the squared residual over a log-spaced grid of ``D``, refined by a
parabola through the best three. The fit runs on reduced-resolution, aligned,
grey, mean-normalised frames.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from pipeline.core.psf import kernel_size, raster_pillbox
from pipeline.errors import InputError

log = logging.getLogger(__name__)

def _focus_measure(grey: np.ndarray) -> np.ndarray:
    """Local energy of the Laplacian (a standard focus measure), smoothed over ~9 px."""
    lap = cv2.Laplacian(grey, cv2.CV_32F, ksize=3)
    return cv2.GaussianBlur(lap * lap, (0, 0), 3.0)


def _pairs(n: int) -> list[tuple[int, int]]:
    """Frame pairs 2+ frames apart (neighbours only for tiny stacks).

    A pixel's sharpest frame is itself blurred by up to ``D dx / 2`` (the point
    focuses between frames); blur adds roughly in quadrature, so predicting a frame
    ``k`` steps away underestimates ``D`` by about ``1 / (8 k^2)``: 12% for
    neighbours, 3% for k = 2.
    """
    steps = {1, 2} if n < 4 else {2, 3, max(2, n // 3)}
    return [(i, i + s * d) for i in range(n) for s in steps for d in (-1, 1) if 0 <= i + s * d < n]


def estimate_blur_span(
    frames: list[np.ndarray],
    positions,
    *,
    downscale: float = 1.0,
    max_span_px: float = 400.0,
) -> float:
    """Blur span ``D`` (px at full resolution) of an aligned focal stack.

    Parameters
    ----------
    frames : list of 2-D float arrays
        Aligned grey frames, all one shape (reduced resolution is fine).
    positions : array_like, shape (n,)
        The frames' focus positions in any coordinate linear in image distance.
    downscale : float
        Full-resolution size / the frames' size; the result is in full-res px.
    max_span_px : float
        Upper end of the search.

    Returns
    -------
    float
        ``D``; a point focused at one end of the stack has a blur of ``D`` px at the
        other end.
    """
    x = np.asarray(positions, dtype=np.float64)
    n = len(frames)
    if n < 2 or x.size != n:
        raise InputError(f"need >= 2 frames with one position each, got {n} and {x.size}")
    span = np.ptp(x)
    if span <= 0:
        raise InputError("all frames have the same focus position: no defocus to measure")
    x = (x - x.min()) / span
    grey = [np.asarray(f, np.float32) / max(float(np.mean(f)), 1e-12) for f in frames]
    focus = np.stack([_focus_measure(g) for g in grey])
    sharpest = np.argmax(focus, axis=0)
    best = focus.max(axis=0)
    textured = best > np.percentile(best, 70)
    border = max(4, int(0.05 * min(grey[0].shape)))
    interior = np.zeros_like(textured)
    interior[border:-border, border:-border] = True
    masks = [(sharpest == i) & textured & interior for i in range(n)]
    pairs = [(i, j) for i, j in _pairs(n) if masks[i].sum() > 50]
    if not pairs:
        raise InputError("no textured, in-focus regions to measure the defocus from")

    def cost(span_px: float) -> float:
        total, count = 0.0, 0
        for i, j in pairs:
            diameter = span_px * abs(x[i] - x[j]) / downscale
            pillbox = raster_pillbox(diameter, kernel_size(diameter) // 2).astype(np.float32)
            predicted = cv2.filter2D(grey[i], -1, pillbox, borderType=cv2.BORDER_REFLECT_101)
            residual = (predicted - grey[j])[masks[i]]
            total += float(np.dot(residual, residual))
            count += residual.size
        return total / count

    grid = np.geomspace(2.0, max_span_px, 14)
    costs = np.array([cost(d) for d in grid])
    k = int(np.argmin(costs))
    if 0 < k < grid.size - 1:  # parabola through the best three in log(D)
        lx = np.log(grid[k - 1 : k + 2])
        a, b, _ = np.polyfit(lx, costs[k - 1 : k + 2], 2)
        estimate = float(np.exp(-b / (2 * a))) if a > 0 else float(grid[k])
        estimate = float(np.clip(estimate, grid[k - 1], grid[k + 1]))
    else:
        estimate = float(grid[k])
        log.warning("blur span at the edge of the search (%.1f px); check the stack", estimate)
    return estimate
