"""The exposure of each frame of a focal stack, from its aligned reduced copy.

Sec. 9 emulates a constant-speed sweep by a weighted sum of the frames, ``sum_k w_k y_k``,
and deconvolves it with ``sum_k w_k K_k`` (Eqs. 5-6). That holds when every frame saw the
scene with the same exposure. Real stacks do not: a flash's output varies from shot to
shot (the beetle stack, lit at 1/200 s: 0.74-1.26 of the stack's), and a macro lens's
effective aperture changes with its focus (pcb7: 0.98-1.03, pcb10: 1.08-0.95). A frame
``y_k = g_k K_k x`` then enters the sum at ``w_k g_k``: the detail in focus in a bright frame
is over-restored and that of a dark one stays soft, and the frame-based steps (the frames'
range, their detail) see each frame's own brightness.

Defocus moves light but keeps it: blurred by more than the defocus, every frame shows the
same image times its gain. :func:`exposure_gains` takes, per frame, the median ratio of its
blurred copy to the blurred weighted average, over pixels no frame clipped (nor within the
blur of one), away from the borders. Divided by ``g_k`` (normalised so that ``sum_k w_k g_k
= 1``: the sum keeps its brightness), the frames follow the model again: the main job does
so with ``--match-exposure`` (:func:`pipeline.jobs.stack.normalise_exposure`), and reports
the measured exposures either way.

Measured (``tests/test_exposure.py``, ``tests/benchmarks/exposure_drift.py``): gains a
stack was rendered with are found within 0.5% (brute-force defocus, noise, a clipped
highlight). On the rendered truth scenes with gains of 1.12 .. 0.90, a flicker of 0.85-1.10
and beetle's flash spread (0.74-1.25), ``--match-exposure`` keeps the result within 0.10 dB
of the scene shot at one exposure; as shot it loses 0.03-0.78 dB. It is not the default: on
the real beetle stack, lit by a flash (0.74-1.26), its regions as good as focus-stack go
from 9 to 6 of 9. Its three brightest frames (1.11-1.18) are the last, sharpest where its
content lies beyond the last frame; as shot their detail entered the sum above the weight
the kernel gives it, an over-restoration that the clip to the frames' range turns into
crisp edges (the mandible's: 4.50 px, 5.75 matched, the frame's own 4.12).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

# the blur (and the border left out, and the reach round clipped pixels), as a share of
# the copies' longer side: more than the defocus of every stack measured here (pcb10's
# 162 px blur span is 8% of its 2048 px; a radius of 4%)
REACH = 0.05
CLIPPED = 0.98  # a copy's level (white at 1) at and above which a pixel counts as clipped
DARK = 0.02  # ratios are taken where the blurred average exceeds this share of its mean
MIN_PIXELS = 500  # fewer usable pixels: the exposures are not measured (all 1)
# gains within this of 1 in every frame are taken as 1: the estimate's own error on stacks
# rendered at one exposure reaches 0.5% (planes at three depths, blurred past the border
# left out), and a drift of 1% changes a result by about a display level at white
DEAD_BAND = 0.01


def exposure_gains(copies: Sequence[np.ndarray], weights) -> np.ndarray:
    """Each frame's exposure relative to the stack's, from its aligned grey copy.

    Parameters
    ----------
    copies : sequence of ndarray (rows, cols), float
        The frames' grey images (linear light, white at 1), aligned and reduced alike.
    weights : array_like (frames,) or (rows, frames)
        The frames' weights in the sum (Sec. 9); per-row weights count by their mean.

    Returns
    -------
    ndarray (frames,)
        ``g_k`` with ``sum_k w_k g_k = 1``, finite and positive; all 1 where fewer than
        ``MIN_PIXELS`` pixels can be used, every gain lies within ``DEAD_BAND`` of 1, a copy
        is not finite, a frame reads black, or the weights sum to no positive number.
    """
    stack = np.stack([np.asarray(c, np.float32) for c in copies])
    n, rows, cols = stack.shape
    if not np.all(np.isfinite(stack)):
        return np.ones(n)
    w = np.asarray(weights, np.float64)
    w = w.mean(axis=0) if w.ndim == 2 else w
    if not (np.all(np.isfinite(w)) and np.all(w >= 0) and w.sum() > 0):
        return np.ones(n)  # no weighted sum to measure against
    w = w / w.sum()
    reach = max(2, round(REACH * max(rows, cols)))
    sigma = reach / 2.0
    usable = np.zeros((rows, cols), np.uint8)
    usable[reach:-reach, reach:-reach] = 1
    clipped = (stack.max(axis=0) >= CLIPPED).astype(np.uint8)
    near = cv2.dilate(clipped, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1,) * 2))
    usable &= near == 0
    blurred = np.stack([cv2.GaussianBlur(c, (0, 0), sigma) for c in stack])
    mean = np.tensordot(w, blurred, axes=1).astype(np.float32)
    usable &= (mean > DARK * float(np.mean(mean))).astype(np.uint8)
    where = usable.astype(bool)
    if np.count_nonzero(where) < MIN_PIXELS:
        return np.ones(n)
    ratios = np.array([float(np.median(b[where] / mean[where])) for b in blurred])
    if not np.all(ratios > 0):  # a frame black where the others are not: no gain to divide by
        return np.ones(n)
    gains = ratios / float(np.dot(w, ratios))
    if np.all(np.abs(gains - 1) <= DEAD_BAND):
        return np.ones(n)
    return gains
