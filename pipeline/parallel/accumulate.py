"""The streaming weighted sum of a focal stack (Sec. 9) as a dask graph: per-frame
leaves (read, warp, weight) merged in a binary tree, so at most a few frames are in
memory whatever the stack's length.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import dask
import numpy as np

from pipeline.core import align, guard
from pipeline.io.read import read_frame

SATURATION = 0.999  # normalised level at and above which a pixel is treated as clipped


# ----------------------------------------------------------------------------- frame leaves
def _warped_leaf(path: str, homography, weight, shape, frame_range: bool = False):
    """Read one frame, warp it onto the reference, weight it; its clipped pixels; decode time.

    ``weight`` is a number, or one weight per row (per-row DOFs, Secs. 6-7). With
    ``frame_range`` (one number as ``weight``) also the weight and the frame's focus
    weight: :func:`_merge` recovers the unweighted frame as ``sum / weight`` for the
    running per-pixel minimum, maximum and focus-weighted sum of the frames (see
    :mod:`pipeline.core.guard`), so a leaf holds no extra copy of its frame.
    """
    t0 = time.perf_counter()
    frame = read_frame(path)
    read_s = time.perf_counter() - t0
    if homography is not None:
        frame = align.warp(frame, homography, shape)
    clipped = clipped_pixels(frame)
    extra = ()
    if frame_range:
        if np.ndim(weight) != 0 or not weight > 0:
            raise ValueError("frame ranges need one positive weight per frame")
        extra = (float(weight), None, None, guard.focus_weight(frame))
    if np.ndim(weight) == 0:
        frame *= np.float32(weight)
    else:
        frame *= np.asarray(weight, np.float32).reshape((-1,) + (1,) * (frame.ndim - 1))
    return (frame, clipped, read_s, *extra)


def _frames_of(node):
    """``(min, max, sum q frame)`` of a node: from a leaf's own frame (``sum / weight``) or
    merged; ``q`` is the frame's focus weight (:func:`pipeline.core.guard.focus_weight`)."""
    if node[4] is None:
        frame = node[0] / np.float32(node[3])
        q = node[6][..., np.newaxis] if frame.ndim == 3 else node[6]
        return frame, frame, frame * q
    return node[3], node[4], node[5]


def _merge(a, b):
    """Sum two partial weighted sums (in place), OR their clipped masks, add decode times;
    with frame ranges, the running minimum, maximum and focus-weighted sum too."""
    ranges = ()
    if len(a) > 3:  # before the in-place sum: a leaf's frame is its sum / weight
        (lo_a, hi_a, s_a), (lo_b, hi_b, s_b) = _frames_of(a), _frames_of(b)
        hi = np.maximum(hi_a, hi_b, out=hi_a if a[4] is not None else None)
        lo = np.minimum(lo_a, lo_b, out=lo_a)  # lo_a is a's own array (or a fresh frame)
        ranges = (lo, hi, np.add(s_a, s_b, out=s_a), np.add(a[6], b[6], out=a[6]))
    np.add(a[0], b[0], out=a[0])  # each partial sum feeds exactly one merge: safe in place
    np.logical_or(a[1], b[1], out=a[1])
    return (a[0], a[1], a[2] + b[2], *ranges)


def frame_range_of(node):
    """``(min, max, focus-weighted frame, sum of focus weights)`` of a computed graph's result."""
    lo, hi, weighted = _frames_of(node)
    q = node[6][..., np.newaxis] if weighted.ndim == 3 else node[6]
    return lo, hi, weighted / q, node[6]


def weighted_sum_graph(
    files: Sequence[Path], homographies, weights, shape, *, frame_range: bool = False
):
    """A dask graph for ``sum_i w_i warp(frame_i)`` as a binary tree of merges.

    ``weights[i]`` is frame i's weight, a number or one per row. Frames whose
    weights are all zero are not read. Returns a Delayed yielding
    ``(sum, clipped_any_frame, decode_seconds)``, and with ``frame_range`` also the
    per-pixel minimum, maximum, sharpest frame and its focus measure over the frames read.
    """
    level = [
        dask.delayed(_warped_leaf, pure=True)(
            str(path),
            h,
            float(w) if np.ndim(w) == 0 else np.asarray(w),
            tuple(shape),
            frame_range,
        )
        for path, h, w in zip(files, homographies, weights)
        if np.max(w) > 0
    ]
    while len(level) > 1:
        merged = [dask.delayed(_merge)(level[i], level[i + 1]) for i in range(0, len(level) - 1, 2)]
        if len(level) % 2:
            merged.append(level[-1])
        level = merged
    return level[0]


def clipped_pixels(image: np.ndarray) -> np.ndarray:
    """Pixels at the clipping level in any channel."""
    return np.any(image >= SATURATION, axis=-1) if image.ndim == 3 else image >= SATURATION
