"""The streaming weighted sum of a focal stack (Sec. 9) as a dask graph: a few chains
("lanes", one per worker) each add their frames (read, warp, weight) one after the
other into one running sum, and the lanes' sums are added at the end, so at most two
frames per lane are in memory whatever the stack's length.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Sequence
from pathlib import Path

import cv2
import dask
import numpy as np

from pipeline.core import align
from pipeline.core.colour import mean_grey
from pipeline.core.frame_support import FrameSupport
from pipeline.io.read import read_frame

SATURATION = 0.999  # normalised level at and above which a pixel is treated as clipped
# Chains of the weighted sum. Fixed, not the worker count: the float32 summation order,
# so the output's bits, then depend only on the frames (with one lane per worker, 2% of
# pcb7's 16-bit values moved by 1 code between --threads 1 and 2).
LANES = 2


# ----------------------------------------------------------------------------- frame leaves
def _warped_leaf(
    path: str,
    homography,
    weight,
    shape,
    support: str | None = None,
    white=None,
    key=None,
    detail=None,
    gain=1.0,
    into=None,
):
    """Read one frame (with white level ``white``, :func:`pipeline.io.read.read_frame`),
    warp it onto the reference, divide it by its exposure ``gain``
    (:func:`pipeline.core.exposure.exposure_gains`; its clipped pixels are found as shot,
    before), weight it; its clipped pixels; decode time; with
    ``support`` (``"range"`` or ``"full"``), its
    :class:`~pipeline.core.frame_support.FrameSupport` (else ``None``); with a ``key``,
    ``{key: its grey image}`` (:func:`~pipeline.core.colour.mean_grey`, as read: not
    warped; divided by ``gain``), else ``{}``; with ``detail``, a zero-argument callable
    giving the frame's map (0..1, any size: where it is the sharpest), ``(m g, m)``: its
    grey image warped bicubic (fine detail kept, see :func:`pipeline.core.align.warp`) and
    divided by ``gain``, times the map brought to ``shape``, and that map (else ``None``).

    ``weight`` is a number, or one weight per row (per-row DOFs, Secs. 6-7). ``into``:
    range-only statistics of earlier frames, into which this frame's are folded
    (:meth:`~pipeline.core.frame_support.FrameSupport.add_frame`) and returned.
    """
    t0 = time.perf_counter()
    frame = read_frame(path, white=white)
    read_s = time.perf_counter() - t0
    scale = np.float32(1.0 / gain)
    grey = mean_grey(frame) if key is not None or detail is not None else None
    kept = {} if key is None else {key: np.multiply(grey, scale, dtype=np.float32)}
    sharp = None
    if detail is not None:
        if homography is not None:
            grey = align.warp(grey, homography, shape, interpolation="cubic")
        elif grey is frame:  # a grey frame is its own mean_grey: not changed in place
            grey = grey.copy()
        where = cv2.resize(np.asarray(detail(), np.float32), (shape[1], shape[0]))
        if gain == 1.0:  # ``where * 1`` is ``where``: the same bits, without a temporary
            np.multiply(grey, where, out=grey)
        else:
            grey = np.multiply(grey, where * scale, dtype=np.float32)
        sharp = (grey, where)
    if homography is not None:
        frame = align.warp(frame, homography, shape)
    clipped = clipped_pixels(frame)
    if gain != 1.0:
        frame *= scale
    if into is not None:  # the lane's range-only statistics, this frame folded in
        stats = into.add_frame(frame, ~clipped)
    elif support:
        stats = FrameSupport.of_frame(frame, ~clipped, full=support == "full")
    else:
        stats = None
    if np.ndim(weight) == 0:
        frame *= np.float32(weight)
    else:
        frame *= np.asarray(weight, np.float32).reshape((-1,) + (1,) * (frame.ndim - 1))
    return frame, clipped, read_s, stats, kept, sharp


def _merge(a, b):
    """Sum two partial weighted sums (in place), OR their clipped masks, add decode times,
    merge their frame statistics and kept grey frames, and add their detail sums."""
    np.add(a[0], b[0], out=a[0])  # each partial sum feeds exactly one step: safe in place
    np.logical_or(a[1], b[1], out=a[1])
    if a[5] is None or b[5] is None:
        sharp = a[5] if b[5] is None else b[5]
    else:
        sharp = tuple(np.add(mine, theirs, out=mine) for mine, theirs in zip(a[5], b[5]))
    if a[3] is None or b[3] is a[3]:  # none, or b's frame already folded into a's
        stats = a[3]
    else:
        stats = a[3].merge(b[3])
    return a[0], a[1], a[2] + b[2], stats, a[4] | b[4], sharp


def _add_frame(
    partial,
    path: str,
    homography,
    weight,
    shape,
    support=None,
    white=None,
    key=None,
    detail=None,
    gain=1.0,
):
    """One step of a lane: frame ``path`` warped and weighted (:func:`_warped_leaf`),
    added to the lane's running sum ``partial`` (``None`` for the lane's first frame)."""
    # range-only statistics fold the frame into the lane's own (no per-frame code arrays)
    into = partial[3] if partial is not None and support == "range" else None
    leaf = _warped_leaf(path, homography, weight, shape, support, white, key, detail, gain, into)
    return leaf if partial is None else _merge(partial, leaf)


def weighted_sum_graph(
    files: Sequence[Path],
    homographies,
    weights,
    shape,
    *,
    lanes: int = LANES,
    support: str | None = None,
    white: float | None = None,
    gains=None,
    keep=(),
    detail=None,
):
    """A dask graph for ``sum_i w_i warp(frame_i) / g_i``: ``lanes`` chains of in-place sums.

    ``weights[i]`` is frame i's weight, a number or one per row. Frames whose
    weights are all zero are not read. Frame ``i`` goes to lane ``i mod lanes``;
    each lane is a chain of :func:`_add_frame` steps, so memory is flat in the
    number of frames (a binary tree of merges held one partial sum per level, some
    140 MiB more at 28 frames of 3 Mpx than at 7) while ``lanes`` workers decode
    side by side. The result's bits depend on ``lanes`` (the float32 summation
    order), not on the scheduler or its threads. Returns a Delayed yielding
    ``(sum, clipped_any_frame, decode_seconds, support, kept, sharp)``; ``support`` is the read
    frames' :class:`~pipeline.core.frame_support.FrameSupport` when asked for (``"range"``:
    their per-pixel range only; ``"full"``: all of it), else ``None``; ``kept`` maps each
    index in ``keep`` whose frame is read to that frame's grey image as read (not warped;
    :func:`~pipeline.core.colour.mean_grey`), so the end frames' detail needs no second
    decode. ``detail`` (e.g. :class:`pipeline.jobs.frame_detail.DetailMaps`) lists in
    ``inner`` the frames that lend their detail and gives in ``weight(i)`` frame ``i``'s map
    (0..1, any size) of where it is the sharpest, made in the frame's task; ``sharp`` is
    then ``(sum_i m_i g_i, sum_i m_i)`` over the read frames among them, ``g_i`` the grey
    frame warped bicubic and ``m_i`` its map at ``shape`` (the frames' own detail,
    :mod:`pipeline.jobs.frame_detail`, without keeping the frames: memory flat in their
    number), else ``None``. ``white``: the frames' white level
    (:func:`pipeline.io.read.read_frame`). ``gains``: each frame's exposure ``g_i``
    (:func:`pipeline.core.exposure.exposure_gains`), every image of frame ``i`` above divided
    by it; ``None``: all 1.
    """
    if int(lanes) < 1:
        raise ValueError(f"lanes must be >= 1, got {lanes!r}")
    keep = {int(i) for i in keep}
    lends = set() if detail is None else set(detail.inner)
    used = [
        (
            str(path),
            h,
            float(w) if np.ndim(w) == 0 else np.asarray(w),
            i if i in keep else None,
            functools.partial(detail.weight, i) if i in lends else None,
            1.0 if gains is None else float(gains[i]),
        )
        for i, (path, h, w) in enumerate(zip(files, homographies, weights))
        if np.max(w) > 0
    ]
    level = []
    for lane in range(min(int(lanes), len(used))):
        partial = None
        for path, h, w, key, where, gain in used[lane :: int(lanes)]:
            # pure=False: equal steps (a frame listed twice, first in two lanes) stay separate
            # tasks; a shared one would be added into, in place, by two later steps
            partial = dask.delayed(_add_frame, pure=False)(
                partial, path, h, w, tuple(shape), support, white, key, where, gain
            )
        level.append(partial)
    while len(level) > 1:
        merged = [dask.delayed(_merge)(level[i], level[i + 1]) for i in range(0, len(level) - 1, 2)]
        if len(level) % 2:
            merged.append(level[-1])
        level = merged
    return level[0]


def clipped_pixels(image: np.ndarray) -> np.ndarray:
    """Pixels at the clipping level (``>= SATURATION``) in any channel; a NaN counts as
    clipped (nothing is known of it)."""
    channels = 1 if image.ndim == 2 else image.shape[2]
    if image.dtype == np.float32 and channels <= 4:
        # one OpenCV pass, all channels at once (7 against 19 ms on 3 Mpx RGB): in range
        # means every channel at most the float32 just below SATURATION
        below = float(np.nextafter(np.float32(SATURATION), np.float32(-np.inf)))
        return cv2.inRange(image, (-np.inf,) * channels, (below,) * channels) == 0
    with np.errstate(invalid="ignore"):
        if image.ndim != 3:
            return ~(image < SATURATION)
        mask = ~(image[..., 0] < SATURATION)  # no (rows, cols, c) temporary
        for c in range(1, image.shape[2]):
            mask |= ~(image[..., c] < SATURATION)
    return mask
