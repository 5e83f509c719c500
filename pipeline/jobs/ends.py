"""Content beyond the ends of a focal stack's focus range (Sec. 4.1, issue 13).

The stack's IPSF (:func:`pipeline.core.stack_kernel.stack_kernel`) averages the
kernels of the depths *inside* the frames' range. A depth outside it, in focus in no
frame, is seen by every frame blurred, and more than the IPSF says: deconvolved with
it, it stays soft (pcb7's far barcode: contrast 45 where its frame has 68). Where an
end frame is the sharpest and its content lies beyond it
(:func:`pipeline.core.defocus.end_depths`), the average is deconvolved again with the
kernel of that depth (:func:`pipeline.core.stack_kernel.depth_kernel`) and blended in
where that end frame is the sharpest (the map of the aligned previews, smoothed).

On a three-plane stack whose far plane lies beyond the frames' range the far plane
gains 5-7 dB; on stacks whose content is inside the range nothing changes (no offset is
found); on the real stacks the regions as good as focus-stack went from 0/8/4/7 to
1/8/7/7 (amber's end is skipped, ``MIN_FRACTION``; with it 8;
``tests/benchmarks/results/real_regions/NOTE.md``).
"""

from __future__ import annotations

import dataclasses
import logging

import cv2
import numpy as np

from pipeline.core import defocus
from pipeline.core.stack_kernel import depth_kernel
from pipeline.errors import InputError

log = logging.getLogger(__name__)

MIN_BEYOND = 0.02  # offsets below this share of the range: the stack's kernel does
BLEND_PREVIEW_PX = 2.0  # smoothing of the end frame's map (preview px: ~13 px at full size)
BLEND_FLOOR = 0.1  # outside the box where the blend weight reaches this: not deconvolved again
# an end whose content covers less of the frame than this is left to the stack's kernel: a
# second deconvolution of most of the frame for a few scattered pixels (amber: 2.7%, +45%
# time) is not worth it
MIN_FRACTION = 0.05


@dataclasses.dataclass
class EndKernel:
    """The kernel of an end frame's content beyond the range, and where to use it."""

    frame: int
    beyond: float  # share of the focus range beyond the end frame
    kernel: np.ndarray
    weight: np.ndarray  # blend weight at the previews' resolution (float32)


def end_kernels(fit, positions, weights, span_px, *, lens, absolute) -> list[EndKernel]:
    """The end kernels of a stack from ``fit`` (aligned grey previews and their
    downscale factor), its focus positions, frame weights and blur span (px)."""
    small, factor = fit
    try:
        ends, sharpest = defocus.end_depths(small, positions, span_px, downscale=factor)
    except InputError as err:  # too few frames or no blur: nothing to extend
        log.debug("no end depths: %s", err)
        return []
    out = []
    width = float(np.ptp(positions))
    for end in ends:
        if end.beyond < MIN_BEYOND:
            continue
        mask = (sharpest == end.frame).astype(np.float32)
        weight = cv2.GaussianBlur(mask, (0, 0), BLEND_PREVIEW_PX)
        if np.mean(weight > 0.5) < MIN_FRACTION:
            log.debug("frame %d: content beyond the range covers too little", end.frame)
            continue
        low_end = positions[end.frame] <= np.min(positions)
        at = positions[end.frame] + (-1.0 if low_end else 1.0) * end.beyond * width
        kernel = depth_kernel(
            positions, weights, at, lens=lens, absolute=absolute, blur_span_px=span_px
        ).astype(np.float32)
        out.append(EndKernel(end.frame, end.beyond, kernel, weight))
    return out


def restore_ends(result, average, ends: list[EndKernel], deconvolve) -> list[dict]:
    """Blend into ``result`` (in place) each end's deconvolution of ``average``.

    ``deconvolve(image_part, kernel, rows, cols)`` deconvolves a part (slices ``rows``,
    ``cols``) of the average; only the box where an end's blend weight reaches
    ``BLEND_FLOOR``, and a kernel's reach around it, is deconvolved again. Returns, per
    end, what the sidecar records.
    """
    shape = result.shape[:2]
    report = []
    for end in ends:
        weight = cv2.resize(end.weight, shape[::-1], interpolation=cv2.INTER_LINEAR)
        used = weight >= BLEND_FLOOR
        if not used.any():
            continue
        reach = 2 * end.kernel.shape[0]  # the deconvolution's reach, with the tiler's margin
        box, part = [], []
        for axis in (0, 1):
            found = np.flatnonzero(used.any(axis=1 - axis))
            lo, hi = int(found[0]), int(found[-1]) + 1
            outer = max(0, lo - reach), min(shape[axis], hi + reach)
            box.append(slice(lo, hi))
            part.append((slice(*outer), slice(lo - outer[0], hi - outer[0])))
        (rows, inner_rows), (cols, inner_cols) = part
        restored = deconvolve(average[rows, cols], end.kernel, rows, cols)[inner_rows, inner_cols]
        w = weight[box[0], box[1]]
        w = w[..., None] if result.ndim == 3 else w
        result[box[0], box[1]] += w * (restored - result[box[0], box[1]])
        report.append(
            {
                "frame": end.frame,
                "beyond_range": round(end.beyond, 4),
                "fraction": round(float(np.mean(weight > 0.5)), 4),
            }
        )
    return report
