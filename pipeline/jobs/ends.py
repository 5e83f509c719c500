"""Content at and beyond the ends of a focal stack's focus range (Sec. 4.1, issue 13).

The stack's IPSF (:func:`pipeline.core.stack_kernel.stack_kernel`) averages the
kernels of the depths *inside* the frames' range, so it is wider than the kernel of a
depth in the middle and narrower than that of a depth at an end, where every other
frame sees the content blurred from one side only (the end effect of Sec. 4.1). A depth
at an end frame, or beyond it in focus in no frame, deconvolved with the stack's IPSF
stays soft: pcb7's far barcode keeps a contrast of 45 where its frame has 68, and a plane
at the near end frame of a rendered stack stays 3.6-5.3 dB below the middle plane. Where an
end frame is the sharpest, with its content at ``beyond`` of the range past it
(:func:`pipeline.core.defocus.end_depths`, 0 for content at the end frame itself), the
average is deconvolved again with the kernel of that depth
(:func:`pipeline.core.stack_kernel.depth_kernel`) and the difference to the stack
kernel's result is added where that end frame is the sharpest (the map of the aligned
previews, smoothed; its coarse band also where the end frame holds the most coarse detail),
at a reduced resolution (:func:`_reduced_correction`), and where
the end frame itself shows what it adds (:func:`_frame_agreement`). Where the result there
is still softer than the end frame (content further beyond the end than the one depth fitted
for it), the frame's own 2-8 px detail is kept (:func:`keep_end_detail`).

Measured (``tests/test_end_depths.py``, ``tests/benchmarks/synthetic_guard.py``): a
three-plane stack whose far plane lies beyond the frames' range goes from 25.98 to
27.64 dB at sigma 0.01 (the far plane gains more than 4 dB); a plane at the near end
frame gains 5.3 dB at sigma 0.01 (28.07 -> 33.36 dB); where the end frames lie on the
near and far planes the whole stack goes from 26.29 (the correction beyond the ends
only) to 27.43 dB with the ends' own depths and the fit kept off depth edges, and to
29.65 dB with the end frame's check: without it, across an occlusion edge the end's
kernel restored one side and rang into the other (16 px strips along the edges: 22.40
dB, 25.4 dB with the check). On the real stacks the regions as good as focus-stack went
from 0/8/4/7 to 2/8/7/8 with the correction beyond the ends, were 2/8/7/7 with the
ends' own depths, the fit kept off depth edges and the end frame's check, were 2/8/9/7
with the end frames' own detail, and are 4/8/9/8 with the correction's fine and coarse bands
each checked against the end frame (:func:`_correction_bands`; pcb7's barcode beyond its last
frame was hollow before, dark edges round grey centres)
(``tests/benchmarks/results/real_regions/NOTE.md``, stops 27-31).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
from scipy import fft as sfft

from pipeline.core import defocus, spectra
from pipeline.core.colour import mean_grey, move_grey, scale_channels
from pipeline.core.frame_support import frame_noise
from pipeline.core.stack_kernel import depth_kernel, frame_kernels
from pipeline.errors import InputError

log = logging.getLogger(__name__)

BLEND_PREVIEW_PX = 2.0  # smoothing of the end frame's map (preview px: ~13 px at full size)
CORRECTION_LAM = 1.6e-2  # weight of the gradient prior (per full-resolution frequency)
CORRECTION_SIDE_PX = 384  # the correction runs at 1 / (shorter side // this), at most ...
MAX_REDUCTION = 4  # ... a quarter of the resolution (pcb7's 1536 px: 384 px, 0.1 s)
BLEND_FLOOR = 1e-3  # rows where the blend weight stays below this are left as they are
# the end frame's check of the correction (:func:`_frame_agreement`): the window (px at the
# correction's resolution), the gain (the whole correction where the frame shows half of it),
# the most of it taken where the frame shows more than it adds, and the prior's weight (in
# the image's mean local variance of the correction)
AGREEMENT_SIGMA_PX = 2.0
AGREEMENT_GAIN = 2.0
AGREEMENT_MAX = 1.5
AGREEMENT_PRIOR = 1.0
# the correction's two bands, each checked on its own (:func:`_correction_bands`): the coarse
# band is its Gaussian of this sigma (px at the correction's resolution: 8 px of pcb7's
# frames), checked over windows of ``COARSE_WINDOW_PX``; a window with nine times the fine
# one's samples is trusted with a larger amplitude
COARSE_SIGMA_PX = 2.0
COARSE_WINDOW_PX = 6.0
COARSE_MAX = 2.0
# an end whose content covers less of the frame than this is left to the stack's kernel (the
# correction would cost its 0.05-0.1 s for nothing; amber's 2.7% gains a region)
MIN_FRACTION = 0.01
# the end frame's own detail (:func:`keep_end_detail`): the bands ``G_s0 g - G_s1 g`` (px, full
# resolution; ``G_0`` the image itself), the energy window (in units of the band's sigma, at
# least 2 px), the gain (the frame's whole band where the result shows half its energy) and
# the frame's noise energy (in multiples of its expected variance in the band) not counted
DETAIL_SIGMAS_PX = (1.0, 2.0, 4.0)
DETAIL_WINDOW = 2.0
DETAIL_GAIN = 2.0
DETAIL_NOISE = 4.0
MAX_DETAIL_GAIN = 4.0  # the most a pixel's channels are scaled by (a dark pixel's)
# the end frame's own range (:func:`keep_to_end_frames`): its grey image's min and max over
# a (2 r + 1)^2 neighbourhood. r is the slack for registration and for the frame's own blur
# where content lies a little beyond it: at 1 px beetle's bottom-left edges, blurred in its
# first frame, came out 8.88 px wide where they were 8.25 (a loss against focus-stack's
# 8.50), and the noisy three planes lost 0.07 dB; at 2 px 8.25 and 0.04 dB, and pcb7's far
# bars 4.9 levels rms from the last frame (4.7 at 1 px, 7.0 without)
END_RANGE_RADIUS_PX = 2


@dataclasses.dataclass
class EndRange:
    """The range the end frame shows over a box of the result, and how far it holds there
    (:func:`keep_to_end_frames`)."""

    box: tuple[slice, slice]  # (rows, columns) of the result
    low: np.ndarray  # the end frame's grey minimum over the neighbourhood (float32)
    high: np.ndarray  # ... and maximum
    weight: np.ndarray  # 0..1 per pixel of the box


@dataclasses.dataclass
class EndKernel:
    """The kernel of an end frame's content (at or beyond the range), and where to use it."""

    frame: int
    beyond: float  # share of the focus range beyond the end frame (0: at it)
    kernel: np.ndarray
    weight: np.ndarray  # blend weight at the previews' resolution (float32)
    frame_image: np.ndarray  # the end frame, grey and aligned, at the correction's size
    frame_kernel: np.ndarray  # the end frame's own PSF at that depth (full resolution)
    coarse_weight: np.ndarray  # the coarse band's blend weight (:func:`end_kernels`)


def correction_factor(shape) -> int:
    """The correction's reduction for frames of ``shape``: 1 up to ``MAX_REDUCTION``, so
    that the shorter side stays at least ``CORRECTION_SIDE_PX``."""
    return int(np.clip(min(shape[:2]) // CORRECTION_SIDE_PX, 1, MAX_REDUCTION))


def reduced_size(shape, factor: int) -> tuple[int, int]:
    """``(cols, rows)`` of frames of ``shape`` at ``1 / factor`` of their resolution."""
    rows, cols = shape[:2]
    return max(8, cols // factor), max(8, rows // factor)


def end_kernels(fit, positions, weights, span_px, *, lens, absolute, read_end) -> list[EndKernel]:
    """The end kernels of a stack from ``fit`` (aligned grey previews, their downscale
    factor and the stack's :class:`~pipeline.core.defocus.FocusMaps` or ``None``; see
    :func:`pipeline.core.defocus.end_depths`), its focus positions, frame weights and
    blur span (px). ``read_end(i)`` gives frame ``i`` grey and aligned at the
    correction's size (:func:`correction_factor`, :func:`reduced_size`), for the check of
    :func:`_frame_agreement`; it is called for the ends kept only.

    The fine band is blended where the end frame is the sharpest (the focus maps'
    ``sharpest``), the coarse band also where it holds the most coarse detail
    (``coarse_sharpest``): content beyond an end shows its coarse detail best in the end
    frame even where another depth's fine detail lies over it. pcb7's glossy board, in
    focus in frame 5, mirrors the striped background beyond frame 6, whose coarse contrast
    rises frame by frame to the end (3.2 ... 15.4, 16.2 levels); with the fine band's
    weight alone the result kept 10.7 there, with this weight 13.7, and the centre and
    right regions' haze went from losses to ties against focus-stack (pcb7 4/9 -> 6/9;
    ``tests/benchmarks/results/real_regions/NOTE.md``, stop 34)."""
    small, factor, maps = fit
    maps = defocus.FocusMaps.of(small) if maps is None else maps
    try:
        ends, sharpest = defocus.end_depths(small, positions, span_px, downscale=factor, maps=maps)
    except InputError as err:  # too few frames or no blur: nothing to extend
        log.debug("no end depths: %s", err)
        return []
    out = []
    width = float(np.ptp(positions))
    for end in ends:
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
        own = frame_kernels(
            positions, at, lens=lens, absolute=absolute, blur_span_px=span_px
        )[end.frame].astype(np.float32)
        coarse = (maps.coarse_sharpest == end.frame).astype(np.float32)
        coarse = np.maximum(weight, cv2.GaussianBlur(coarse, (0, 0), BLEND_PREVIEW_PX))
        out.append(
            EndKernel(end.frame, end.beyond, kernel, weight, read_end(end.frame), own, coarse)
        )
    return out


def _reduced_kernel(kernel: np.ndarray, factor: int) -> np.ndarray:
    """``kernel`` at ``1 / factor`` of its resolution (area-averaged, odd, sums to 1)."""
    side = max(3, (kernel.shape[0] // factor) | 1)
    small = cv2.resize(np.asarray(kernel, np.float32), (side, side), interpolation=cv2.INTER_AREA)
    return small.astype(np.float64) / float(small.sum())


def _own_kernel(kernel: np.ndarray, factor: int) -> np.ndarray:
    """An end frame's own PSF at ``1 / factor`` of the resolution: cropped to its support
    (kernels of one stack share a size), a single pixel where it is no wider than ``factor``
    full-resolution pixels (an end frame's own depth)."""
    h = kernel.shape[0] // 2
    support = np.flatnonzero(kernel.max(axis=0) > 1e-6 * kernel.max())
    half = int(max(h - support[0], support[-1] - h)) if support.size else 0
    if 2 * half + 1 <= factor:
        return np.ones((1, 1))
    return _reduced_kernel(kernel[h - half : h + half + 1, h - half : h + half + 1], factor)


def _reduced_correction(average, end_kernel, stack_kernel, factor: int) -> np.ndarray:
    """``F^-1[(W_end - W_stack) Y]`` at ``1 / factor`` of the resolution (float32, with a
    channel axis): what deconvolving with the end depth's kernel adds to deconvolving with
    the stack's.

    ``W = conj(K) / (|K|^2 + lam |D|^2)``, ``D`` the discrete gradient, ``lam =
    CORRECTION_LAM / factor^2`` (the same prior per unit of the full image's frequency).
    At a reduced resolution this is the full correction's low band only: on a 1/f-like
    texture it correlates 0.92-0.99 with it below about ``1 / (8 factor)`` cycles per pixel
    (Gaussian of 8 px), 0.2-0.4 in the band of 2-4 px. That band is the contrast an end
    depth loses (haze; the edges' fine band stays the main deconvolution's), and averaging
    ``factor^2`` pixels lowers the noise ``factor`` times (a full-resolution correction won
    one region fewer on the real stacks, losing flat-area noise, for 2-4x the time).
    """
    small = cv2.resize(
        average, reduced_size(average.shape, factor), interpolation=cv2.INTER_AREA
    ).astype(np.float64)
    small = small if small.ndim == 3 else small[..., None]
    ke, k0 = (_reduced_kernel(k, factor) for k in (end_kernel, stack_kernel))
    pad = max(ke.shape[0], k0.shape[0])  # reflect: no wrap-around at the borders
    # ... and on to a fast FFT size (one of pcb7's ends: 414 x 542, 542 = 2 x 271, took 19 ms
    # a channel's transform pair where 432 x 576 takes 2.7)
    rows, cols = small.shape[:2]
    grid = tuple(sfft.next_fast_len(n + 2 * pad, real=True) for n in (rows, cols))
    extra = ((pad, grid[0] - rows - pad), (pad, grid[1] - cols - pad), (0, 0))
    padded = np.pad(small, extra, mode="reflect")
    fy = np.fft.fftfreq(grid[0])[:, None]
    fx = np.fft.rfftfreq(grid[1])[None, :]
    gradient = (2 - 2 * np.cos(2 * np.pi * fy)) + (2 - 2 * np.cos(2 * np.pi * fx))
    transfer = 0
    lam = CORRECTION_LAM / factor**2  # the same prior per unit of the full image's frequency
    for k, sign in ((ke, 1.0), (k0, -1.0)):
        spectrum = spectra.centred_fft(k, grid, real=True)
        transfer = transfer + sign * np.conj(spectrum) / (np.abs(spectrum) ** 2 + lam * gradient)
    return np.stack(
        [
            sfft.irfft2(sfft.rfft2(padded[..., c]) * transfer, s=grid)[
                pad : pad + rows, pad : pad + cols
            ]
            for c in range(padded.shape[2])
        ],
        axis=2,
    ).astype(np.float32)


def _frame_agreement(
    result,
    delta,
    frame_image,
    frame_kernel,
    window_px: float = AGREEMENT_SIGMA_PX,
    most: float = AGREEMENT_MAX,
) -> np.ndarray:
    """How much of the correction ``delta`` (:func:`_reduced_correction`) the end frame
    supports, per pixel (0..``most``, at ``result``'s resolution), checked at the
    correction's resolution (``delta``'s, ``frame_image``'s and ``frame_kernel``'s).

    If the correction is right, the end frame shows the corrected image blurred by its own
    PSF at that depth (``frame_kernel``: a single pixel at the end frame's own depth, a
    small disc beyond it; Eqs. 2-4): ``frame = K (result + delta)``. Locally (a Gaussian
    window of ``window_px``, the window's mean removed, so the frames' exposure
    and the stack's haze do not count) the regression slope of ``frame - K result`` on
    ``K delta`` is then about 1. It is 0 or below where the correction is not the end's
    content: across an occlusion edge, the end kernel rings into the other depth, which
    the end frame shows far more blurred; where the fitted end depth overshoots (the far
    end of the end-frames scene reads 0.12 of the range beyond it, where the truth is 0),
    the frame shows less than the correction adds. The slope is shrunk towards 1 by a
    prior of ``AGREEMENT_PRIOR`` times the image's mean local variance of the correction,
    so only clear evidence takes a correction away: without it, on real stacks the slope
    read noise and JPEG artefacts and kept 0.44-0.77 of the blend at some ends, costing 5
    regions over seven sub-stacks of the real ones (``real_stack_regions.py --stack``;
    ``tests/benchmarks/results/real_regions/NOTE.md``, stop 28). The weight is
    ``AGREEMENT_GAIN`` times the slope, clipped to [0, 1]: the whole correction wherever the
    frame supports half of it. Measured (``tests/benchmarks/synthetic_guard.py``): the
    end-frames scene 27.43 -> 29.65 dB; the far plane beyond the frames 27.64 dB, as
    without the check.

    Where the slope exceeds 1 the frame shows *more* than the correction adds: the end
    depth's kernel is too narrow, because the blur span or the depth beyond the end was
    fitted short. The frame is then the better evidence, and the weight is the slope
    itself (the frame's least-squares amplitude of the correction, shrunk towards 1 by the
    prior), up to ``most``. :func:`restore_ends` checks the correction's fine and
    coarse bands each on its own (:func:`_correction_bands`).
    """
    rows, cols = result.shape[:2]
    small = cv2.resize(result, frame_image.shape[::-1], interpolation=cv2.INTER_AREA)
    r, d = (mean_grey(x) for x in (small, delta))
    if frame_kernel.size > 1:
        k = frame_kernel.astype(np.float32)
        r, d = (cv2.filter2D(x, -1, k, borderType=cv2.BORDER_REFLECT) for x in (r, d))
    e = frame_image - r
    # one common scale: the slope does not change, and products of frames in other units
    # (1e38: tests/test_ingestion.py) cannot overflow float32
    scale = max(float(np.max(np.abs(d))), float(np.max(np.abs(e))), 1e-30)
    d, e = d / np.float32(scale), e / np.float32(scale)

    def local(x):
        return cv2.GaussianBlur(x, (0, 0), window_px)

    mean_d, mean_e = local(d), local(e)
    covariance = local(d * e) - mean_d * mean_e
    variance = local(d * d) - mean_d * mean_d
    prior = AGREEMENT_PRIOR * float(np.mean(variance))
    slope = (covariance + prior) / np.maximum(variance + prior, 1e-12)
    supported = np.clip(AGREEMENT_GAIN * slope, 0, 1)
    weight = np.where(slope > 1, np.minimum(slope, most), supported).astype(np.float32)
    return cv2.resize(weight, (cols, rows), interpolation=cv2.INTER_LINEAR)


def _correction_bands(small: np.ndarray) -> list[tuple[np.ndarray, float, float]]:
    """The correction ``small`` (:func:`_reduced_correction`) as its fine and coarse bands
    (the Gaussian of ``COARSE_SIGMA_PX`` and the rest), each with the window the end
    frame's check reads it over and the most of it taken (:func:`_frame_agreement`).

    The correction's kernel is the model's (pillbox PSFs, Eqs. 2-4, one fitted depth per
    end); a real lens's blur differs from it by scale, so the share of the correction the
    end frame shows differs between fine and coarse detail. Checked as one, pcb7's
    barcode beyond its last frame kept 0.85-0.89 of that frame's 8-32 px bands, with the
    bars' interiors grey between dark edges; each band checked on its own (the coarse one
    over a window three times wider), 0.96-0.98, and the bars are solid
    (``tests/benchmarks/results/real_regions/NOTE.md``, stop 31).
    """
    coarse = cv2.GaussianBlur(small, (0, 0), COARSE_SIGMA_PX).reshape(small.shape)
    return [
        (small - coarse, AGREEMENT_SIGMA_PX, AGREEMENT_MAX),
        (coarse, COARSE_WINDOW_PX, COARSE_MAX),
    ]


def restore_ends(
    result,
    average,
    ends: list[EndKernel],
    stack_kernel,
    *,
    read_frame=None,
    clipped=None,
    exposures=None,
) -> tuple[list[dict], list[EndRange]]:
    """Add to ``result`` (in place), where each end frame is the sharpest and supports it
    (:func:`_frame_agreement`), what deconvolving ``average`` with that end depth's
    kernel adds to deconvolving it with ``stack_kernel`` (:func:`_reduced_correction`, at a
    reduced resolution for frames of ``CORRECTION_SIDE_PX`` and more), its fine and coarse
    bands each as far as the end frame shows it (:func:`_correction_bands`), the coarse one
    also where the end frame holds the most coarse detail (:func:`end_kernels`). Then, with
    ``read_frame(i, box)`` (that ``(rows, columns)`` box of frame ``i`` aligned at full
    resolution, in colour or as its :func:`mean_grey`, and where the frame covers it),
    keep there the end frame's own detail (:func:`keep_end_detail`), except where a frame
    is ``clipped``. Returns, per end, what the sidecar records, and (with ``read_frame``)
    the range each end frame shows where its detail is kept, for
    :func:`keep_to_end_frames`, at the result's exposure: ``exposures[i]`` is frame
    ``i``'s as ``read_frame`` gives it, relative to the stack's (``None``: all 1)."""
    shape = result.shape[:2]
    factor = correction_factor(shape)
    report, blends = [], []
    for end in ends:
        weights = [
            cv2.resize(w, shape[::-1], interpolation=cv2.INTER_LINEAR)
            for w in (end.weight, end.coarse_weight)
        ]
        weight = weights[0]
        small = _reduced_correction(average, end.kernel, stack_kernel, factor)
        own = _own_kernel(end.frame_kernel, factor)
        bands = _correction_bands(small)
        kept = [
            w * _frame_agreement(result, band, end.frame_image, own, window, most)
            for (band, window, most), w in zip(bands, weights)
        ]
        rows = np.flatnonzero(np.maximum(*kept).max(axis=1) >= BLEND_FLOOR)  # rows changed
        if rows.size:
            box = slice(int(rows[0]), int(rows[-1]) + 1)
            for (band, _, _), blend in zip(bands, kept):
                delta = cv2.resize(band, shape[::-1], interpolation=cv2.INTER_CUBIC)
                delta = delta.reshape(result.shape)[box]
                # in place: no full-size temporaries (14 ms less a band on 3 Mpx RGB)
                np.add(result[box], scale_channels(delta, blend[box]), out=result[box])
        blends.append(kept[0])  # the end frame's detail: where the fine band is kept
        total = max(float(np.sum(weight)), 1e-9)
        report.append(
            {
                "frame": end.frame,
                "beyond_range": round(end.beyond, 4),
                "fraction": round(float(np.mean(weight > 0.5)), 4),
                "supported": round(float(np.sum(kept[0])) / total, 4),
                "supported_coarse": round(float(np.sum(kept[1])) / total, 4),
            }
        )
    ranges: list[EndRange | None] = [None] * len(ends)
    if read_frame is not None:  # after every end's correction, each frame's detail
        boxes = [_detail_box(blend) for blend in blends]

        def detail(i: int) -> None:
            box, blend = boxes[i], blends[i]
            frame, covered = read_frame(ends[i].frame, box)
            weight = blend[box] * covered
            if clipped is not None:
                weight *= ~clipped[box]
            grey = mean_grey(frame)
            noise = float(frame_noise(grey, covered)[0])
            share = keep_end_detail(result[box], frame, weight, noise)
            report[i]["detail_kept"] = round(share, 4)
            side = 2 * END_RANGE_RADIUS_PX + 1
            reach = cv2.getStructuringElement(cv2.MORPH_RECT, (side, side))
            low = cv2.erode(grey, reach, borderType=cv2.BORDER_REPLICATE)
            high = cv2.dilate(grey, reach, borderType=cv2.BORDER_REPLICATE)
            if exposures is not None:  # as the result sees it (beetle's flash: 0.75-1.26)
                low, high = (v / np.float32(exposures[ends[i].frame]) for v in (low, high))
            ranges[i] = EndRange(box, low, high, np.clip(weight, 0, 1).astype(np.float32))

        todo = [i for i, box in enumerate(boxes) if box is not None]
        # the two ends side by side where they change disjoint boxes (pcb7: 0.08 s less)
        apart = len(todo) == 2 and not _overlap(*(boxes[i] for i in todo))
        with ThreadPoolExecutor(2 if apart else 1, thread_name_prefix="flexdof-ends") as pool:
            list(pool.map(detail, todo))
    return report, [r for r in ranges if r is not None]


def keep_to_end_frames(result: np.ndarray, ranges: list[EndRange]) -> float:
    """Keep ``result`` (in place), where an end frame is the sharpest, within the range that
    frame shows around each pixel (:class:`EndRange`, from :func:`restore_ends`); the
    share of the weighted pixels moved is returned.

    The end correction (:func:`_reduced_correction`) deconvolves with the model's kernel of
    the end depth: a difference of two inverses of pillbox-averaged kernels, which rings at
    the pillboxes' spectral zeros where the lens's blur has none. Its bands' amplitudes are
    checked against the end frame (:func:`_frame_agreement`) over windows that hold a bar's
    edges and its inside together, so a ring inside a wide bar passes with the edges that
    support it. On pcb7's barcode beyond its last frame the rings left a light line down
    each wide bar, dark 28 levels of 8-bit sRGB in the frame, 42-46 in the result:
    :func:`pipeline.core.frame_support.clip_to_frames` let it stand, since the other frames,
    which see the bar blurred, are lighter there. The end frame itself, the sharpest there,
    spans 27-31 around those pixels: a sharp image does not leave the range its sharpest
    frame shows within a small slack (``END_RANGE_RADIUS_PX``), as :func:`clip_to_frames`
    holds it to all frames' range. The range is taken at the result's exposure
    (:func:`restore_ends`' ``exposures``): beetle's flash-lit frames differ by 0.75-1.26,
    and its frames as shot moved 14% of the image at a 1 px slack, at the stack's exposure 3%.

    The grey image's excess over ``[low, high]`` is taken off by each pixel's weight ``w``
    (the grey image becomes ``g + w (clip(g, low, high) - g)``), by scaling every channel
    so the hue stays, at most by ``MAX_DETAIL_GAIN`` as :func:`keep_end_detail`; the rest,
    and all of it where the grey image is at or below 0, is added to every channel
    (:func:`pipeline.core.colour.move_grey`). It runs after :func:`clip_to_frames`: a grey
    image scaled into the end frame's range before it kept the result's hue, which the
    clip's per-channel bounds then moved out of that range (dark edges 15 levels lighter
    than the frame's). Measured on pcb7's far bars
    (``tests/benchmarks/results/real_regions/NOTE.md``, part 22): 7.0 -> 4.9 levels rms
    from the last frame, the column profile's largest distance from the frame's 10.8 ->
    6.3 levels, the light line gone.
    """
    moved = total = 0.0
    for end in ranges:
        part = result[end.box]
        grey = np.array(mean_grey(part), np.float32)  # a copy: a grey result is ``part``
        target = cv2.min(cv2.max(grey, end.low), end.high)
        w = end.weight
        changed = cv2.compare(target, grey, cv2.CMP_NE)
        moved += cv2.mean(w, mask=changed)[0] * cv2.countNonZero(changed)
        total += float(cv2.sumElems(w)[0])
        # the weighted target: g + w (clip(g, low, high) - g)
        target = cv2.add(grey, cv2.multiply(cv2.subtract(target, grey), w))
        move_grey(part, grey, target, max_gain=MAX_DETAIL_GAIN)
    return moved / total if total else 0.0


def _overlap(a, b) -> bool:
    """Whether two (rows, columns) boxes share a pixel."""
    return all(x.start < y.stop and y.start < x.stop for x, y in zip(a, b))


def _detail_box(blend) -> tuple[slice, slice] | None:
    """The rows and columns :func:`keep_end_detail` changes (``blend`` at least
    ``BLEND_FLOOR``), with the reach of its filters around them; ``None`` if none."""
    rows = np.flatnonzero(blend.max(axis=1) >= BLEND_FLOOR)
    cols = np.flatnonzero(blend.max(axis=0) >= BLEND_FLOOR)
    if not rows.size:
        return None
    reach = int(np.ceil(4 * DETAIL_WINDOW * max(DETAIL_SIGMAS_PX)))
    return tuple(
        slice(max(0, int(i[0]) - reach), min(n, int(i[-1]) + 1 + reach))
        for i, n in ((rows, blend.shape[0]), (cols, blend.shape[1]))
    )


@functools.cache
def _band_noise_gain(fine_px: float, coarse_px: float) -> float:
    """The variance of the band ``G_fine - G_coarse`` (``cv2.GaussianBlur``'s kernels; the
    image itself for ``fine_px`` 0) of unit white noise: the sum of its squared taps."""
    side = 2 * int(np.ceil(4 * coarse_px)) + 1
    impulse = np.zeros((side, side), np.float64)
    impulse[side // 2, side // 2] = 1.0
    fine = impulse if fine_px == 0 else cv2.GaussianBlur(impulse, (0, 0), fine_px)
    return float(np.sum(np.square(fine - cv2.GaussianBlur(impulse, (0, 0), coarse_px))))


class _Smooth:
    """A Gaussian window of ``window_px`` over images of ``shape``, run at a reduced
    resolution (``window_px / 2`` times coarser): what it smooths varies over the window
    and more, so the reduction changes it little (the local energies of pcb7's last frame:
    by 1.4% at the median, 6% at the 90th percentile) for a quarter to a sixteenth of the
    work. ``down`` smooths and reduces, ``up`` smooths the reduced image and brings it
    back to ``shape``."""

    def __init__(self, window_px: float, shape):
        self.factor = max(1, int(window_px // 2))
        self.window = window_px / self.factor
        self.shape = shape[:2]
        rows, cols = self.shape
        self.small = (max(1, -(-cols // self.factor)), max(1, -(-rows // self.factor)))

    def down(self, image: np.ndarray) -> np.ndarray:
        if self.factor > 1:
            image = cv2.resize(image, self.small, interpolation=cv2.INTER_AREA)
        return cv2.GaussianBlur(image, (0, 0), self.window)

    def up(self, image: np.ndarray) -> np.ndarray:
        image = cv2.GaussianBlur(image, (0, 0), self.window)
        if self.factor > 1:
            image = cv2.resize(image, self.shape[::-1], interpolation=cv2.INTER_LINEAR)
        return image


def keep_end_detail(result, frame, weight, noise) -> float:
    """Give ``result`` (in place), band by band, the end frame's detail where the frame
    shows more of it (Sec. 4.1's end effect, left after :func:`_reduced_correction`).

    Parameters
    ----------
    result : ndarray, float32, (rows, cols) or (rows, cols, 3)
        The restored image (linear light), changed in place.
    frame : ndarray, (rows, cols) or (rows, cols, 3)
        The end frame, aligned to ``result`` (only its grey image is read).
    weight : ndarray, (rows, cols)
        0..1 per pixel (above 1 counts as 1): where the end frame is the sharpest and
        supports the correction (:func:`restore_ends`); pixels below ``BLEND_FLOOR`` are
        left as they are.
    noise : float
        The std of the frame's grey image's noise (``result``'s units).

    Returns
    -------
    float
        The share of the area weighted over half where some band took over half of the
        frame's.

    Notes
    -----
    Where an end frame's content lies beyond the focus range by more than the one depth
    fitted per end (:func:`pipeline.core.defocus.end_depths`: a median), the kernel of that
    depth under-restores it, and the result stays softer than the end frame itself
    (beetle's shell beyond its last frame: edges 8.0 px wide where the frame has 4.25). A
    larger depth for the whole end rings into the content at the end frame's own depth
    (at 0.35 of the range, beetle's blurred bumps turned into rings). The end frame's own
    pixels are what a focus stacker would keep there.

    Per band ``b = G_s0 g - G_s1 g`` of the grey images (``DETAIL_SIGMAS_PX``: detail of
    2-8 px, below the haze measure's scale), with local energies ``E`` (Gaussian windows of
    ``DETAIL_WINDOW`` times the band's sigma), the frame's band replaces the result's by
    ``a = clip(DETAIL_GAIN (1 - E_result / E_shown), 0, 1)``, smoothed over the same
    window and times ``weight``. ``E_shown`` is the frame's energy less ``DETAIL_NOISE``
    times the band's share of ``noise`` (the std of the frame's grey image), so a frame's
    grain is no detail; where the result restored the detail (``E_result >= E_shown``) it
    stays. Every channel is then scaled as the grey image (at most ``MAX_DETAIL_GAIN``
    times), so the hue stays; the rest, and all of it where the grey image is at or below
    0, is added to every channel (:func:`pipeline.core.colour.move_grey`; until stop 44 a
    ratio to ``max(g, 1e-6)`` moved an undershoot's channels the wrong way, and the rest
    was dropped). Only a real frame's bands enter: nothing rings beyond what
    the frame shows. It relies on the frame's alignment: against the truth, a texture's
    error falls to 0.21 of a soft result's with the frame in place, 0.42 and 0.73 with it
    0.5 and 1 px off, but grows to 1.3 times at 2 px (``tests/test_end_detail.py``).

    Measured (``tests/benchmarks/real_stack_regions.py``,
    ``tests/benchmarks/synthetic_guard.py``): beetle 7 -> 9 regions of 9 as good as
    focus-stack (edges 4.25 px where its last frame has 4.25, the shell's bumps as the
    frame shows them), beetle's last seven frames 6 -> 9; the end-frames scene 29.65 ->
    29.92 dB, the motorcycle 30.86 -> 30.90. With the end's map alone as ``weight`` (no
    end frame's check), the end-frames scene lost 0.46 dB: the frame's cut at the planes'
    edge, which the truth does not have.
    """
    # at most the frame's own band: a correction scaled up past 1 (:func:`_frame_agreement`)
    # lends no more than the frame shows
    w = np.clip(np.asarray(weight, np.float32), 0, 1)
    w = cv2.threshold(w, BLEND_FLOOR, 0, cv2.THRESH_TOZERO)[1]
    image, own = mean_grey(result), mean_grey(np.asarray(frame, np.float32))
    # one common scale: nothing changes, and squares of frames in other units (1e38:
    # tests/test_ingestion.py) cannot overflow float32
    scale = max(*(abs(v) for x in (image, own) for v in cv2.minMaxLoc(x)[:2]), 1e-30)
    image, own, noise = image / np.float32(scale), own / np.float32(scale), noise / scale
    added = np.zeros_like(image)
    most = np.zeros(w.shape, np.float32)
    fine_image, fine_own, fine_px = image, own, 0.0
    for sigma in DETAIL_SIGMAS_PX:
        coarse_image = cv2.GaussianBlur(image, (0, 0), sigma)
        coarse_own = cv2.GaussianBlur(own, (0, 0), sigma)
        band_image = cv2.subtract(fine_image, coarse_image)
        band_own = cv2.subtract(fine_own, coarse_own)
        window = max(2.0, DETAIL_WINDOW * sigma)
        smooth = _Smooth(window, image.shape)
        # squares by multiply: cv2.pow's bits in 0.6 of its time
        energy_image = smooth.down(cv2.multiply(band_image, band_image))
        shown = smooth.down(cv2.multiply(band_own, band_own))
        shown -= np.float32(DETAIL_NOISE * noise * noise * _band_noise_gain(fine_px, sigma))
        # DETAIL_GAIN (1 - E_result / E_shown), clipped to [0, 1]; 0 where E_shown <= 0
        take = cv2.divide(energy_image, np.maximum(shown, np.float32(1e-30)))
        np.subtract(np.float32(1.0), take, out=take)
        np.multiply(take, np.float32(DETAIL_GAIN) * (shown > 0), out=take)
        np.clip(take, 0.0, 1.0, out=take)
        take = smooth.up(take)
        take *= w
        added += cv2.multiply(take, cv2.subtract(band_own, band_image))
        np.maximum(most, take, out=most)
        fine_image, fine_own, fine_px = coarse_image, coarse_own, sigma
    # every channel scaled as the grey image (the hue stays), the rest added
    s = np.float32(scale)
    move_grey(result, image * s, cv2.add(image, added) * s, max_gain=MAX_DETAIL_GAIN)
    area = float(np.sum(w > 0.5))
    return float(np.sum((most > 0.5) & (w > 0.5)) / area) if area else 0.0
