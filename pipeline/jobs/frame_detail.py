"""Each inner frame's own detail where it is the sharpest (Sec. 9's single IPSF under-restores
the finest detail of a stack with wide blur).

The stack's IPSF is one kernel for every depth, and Wiener's noise-gain cap
(:data:`pipeline.core.deconvolve.wiener.MAX_NOISE_GAIN`) holds back the frequencies it
attenuates most: on rendered stacks of a tilted board with 22-45 px of blur the result's
edges stay 0.8-2.1 px wider than the scene's and 0.3-1.6 px wider than the sharpest
frame's (issue 13, ``tests/benchmarks/regions_vs_truth.py``). The frame focused on a region
shows that detail as it is. :func:`detail_maps` says where each inner frame is the sharpest
(the ends have their own step, :mod:`pipeline.jobs.ends`); the accumulation sums those
frames' grey images weighted by the maps without keeping them
(:func:`pipeline.parallel.accumulate.weighted_sum_graph`'s ``detail``), and
:func:`keep_inner_detail` hands that composite's 2-8 px bands to the result where it
shows more of them (:func:`pipeline.jobs.ends.keep_end_detail`: a frame's grain is no
detail, and only a real frame's bands enter, so nothing rings), away from other depths
(:func:`away_from_other_depths`).

Measured against a ground truth (``tests/benchmarks/regions_vs_truth.py``,
``tests/benchmarks/synthetic_guard.py``): +0.16 to +1.32 dB on eight rendered stacks of a
tilted board and the motorcycle (4.1 dB summed), +0.06 to +0.25 dB on three-plane stacks,
+0.17 to +0.22 dB on a ray-traced depth edge with the strip along the edge unchanged; the
real stacks' region counts against focus-stack are unchanged. It costs pcb7's 2 s job 0.2-0.3 s
(the grey warps and maps in the accumulation, one detail pass) and two
full-resolution images per accumulation lane.
"""

from __future__ import annotations

import dataclasses
import functools

import cv2
import numpy as np

from pipeline.core.deconvolve.common import noise_sigma_2d
from pipeline.core.defocus import FocusMaps, end_pair, near_other_depths
from pipeline.jobs.ends import DETAIL_SIGMAS_PX, DETAIL_WINDOW, keep_end_detail

MAP_SMOOTH_PX = 1.5  # the sharpest-frame maps' blur (px of the maps), so frames blend at seams
MIN_WEIGHT = 0.02  # a map's value below which a frame lends nothing (scattered pixels)


@dataclasses.dataclass(frozen=True)
class DetailMaps:
    """Where each inner frame is the sharpest: the stack's
    :class:`~pipeline.core.defocus.FocusMaps` (at the fit previews' resolution) and the
    frames' positions normalised to 0..1. Each frame's map is made when asked for
    (:meth:`weight`), so memory stays flat in the number of frames."""

    focus: FocusMaps
    x: np.ndarray

    @functools.cached_property
    def inner(self) -> list[int]:
        """The frames that lend detail: all but the first and last in focus position (the
        ends have their own step) that are the sharpest somewhere."""
        ends = set(end_pair(self.x))
        present = set(np.unique(self.focus.sharpest).tolist())
        return [i for i in range(self.x.size) if i not in ends and i in present]

    def weight(self, i: int) -> np.ndarray | None:
        """Frame ``i``'s map, 0..1: where it is the sharpest, single pixels and thin specks
        opened away (3x3), smoothed by ``MAP_SMOOTH_PX``, values under ``MIN_WEIGHT``
        dropped; ``None`` for an end frame or one sharpest nowhere."""
        if i not in self.inner:
            return None
        region = (self.focus.sharpest == i).astype(np.uint8)
        region = cv2.morphologyEx(region, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
        where = cv2.GaussianBlur(region.astype(np.float32), (0, 0), MAP_SMOOTH_PX)
        return np.where(where >= MIN_WEIGHT, where, np.float32(0))


def detail_maps(focus: FocusMaps, positions) -> DetailMaps:
    """:class:`DetailMaps` from the stack's focus maps (made from the aligned fit previews,
    or streamed one frame at a time) and its focus positions."""
    x = np.asarray(positions, dtype=np.float64)
    return DetailMaps(focus, (x - x.min()) / max(float(np.ptp(x)), 1e-12))


def away_from_other_depths(detail: DetailMaps, span_px: float, factor: float = 1.0) -> np.ndarray:
    """The share (0..1, at the maps' resolution) of the inner frames' composite that lies out
    of reach of content sharpest two or more frames away (``span_px``: the blur span at the
    maps' resolution; :func:`pipeline.core.defocus.near_other_depths`).

    Next to an occlusion edge a frame shows its own depth sharp and the other depth blurred
    into it: a cut the scene does not have, whose band energy reads as detail. On nine-frame
    three-plane stacks the inner frames' detail gained 0.4-1.1 dB away from the planes'
    edges but lost 3.1-3.2 dB in 12 px strips along them (29.62 against 30.82 dB at sigma
    0.01 over the image) until those pixels were left out: now 31.07 dB, the strips within
    0.1 dB of the result without the step. Content of any texture counts (a smooth plane's
    bleed is a cut too: with textured content only, as the end fit counts it, the strips
    still lost 1.4 dB), and the detail bands' reach is added around it.
    """
    textured = np.ones(detail.focus.sharpest.shape, bool)  # any content: smooth bleeds too
    total = np.zeros(detail.focus.sharpest.shape, np.float32)
    away = np.zeros_like(total)
    # the detail's bands reach this far (full-resolution px) from what they read
    reach = int(np.ceil(DETAIL_WINDOW * max(DETAIL_SIGMAS_PX) / factor))
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1,) * 2)
    for i in detail.inner:
        where = detail.weight(i)
        near = near_other_depths(detail.focus.sharpest, textured, detail.x, i, [i], span_px)
        near = cv2.dilate(near.astype(np.uint8), disk) > 0
        total += where
        away += where * ~near
    return away / np.maximum(total, np.float32(1e-6))


def keep_inner_detail(result, sharp, away, clipped=None) -> float:
    """Give ``result`` (in place) the inner frames' detail where they show more of it.

    Parameters
    ----------
    result : ndarray, float32, (rows, cols) or (rows, cols, 3)
        The restored image (linear light), changed in place.
    sharp : tuple of two ndarrays, (rows, cols)
        ``(sum_i m_i g_i, sum_i m_i)`` from the accumulation: the inner frames' grey images
        ``g_i`` weighted by :func:`detail_maps` ``m_i`` (at full resolution).
    away : ndarray, (rows, cols) at any resolution
        :func:`away_from_other_depths`: the weight the composite may have.
    clipped : ndarray of bool, optional
        Pixels clipped in any frame, left as they are.

    Returns
    -------
    float
        :func:`~pipeline.jobs.ends.keep_end_detail`'s share: of the area weighted over
        half, where some band took over half of the frames'.
    """
    weighted, total = sharp
    own = weighted / np.maximum(total, np.float32(1e-6))
    reach = cv2.resize(np.asarray(away, np.float32), total.shape[::-1])
    weight = np.minimum(total, np.float32(1.0)) * reach
    if clipped is not None:
        weight[clipped] = 0
    # the composite's grain over all the pixels it covers: a centre crop (frame_noise) may
    # lie where an end frame is the sharpest and the composite is empty, and would read 0
    noise = noise_sigma_2d(own, total > 0.5)
    return keep_end_detail(result, own, weight, noise)
