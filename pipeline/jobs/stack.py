"""The main job: a focal stack (or a sweep capture) to an extended-DOF image (Sec. 9).

Data flow (docs/architecture.md)::

    frames -> Stack -> align (homography per frame) -> weights (Sec. 9)
      -> streaming weighted sum (dask, one chain per worker) -> sweep image
      -> deconvolve with its IPSF (Eqs. 5-6, computed beside the sum) -> output + sidecar

The weighted sum runs one chain per worker, each adding its frames (read, warp,
weight) into one running sum, so at most a few frames are in memory at once
whatever the stack's length. The same graph runs on the local threaded scheduler or
on a ``dask.distributed`` cluster (``scheduler="tcp://..."``).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import dask
import numpy as np

from pipeline.core import align, defocus, multiframe
from pipeline.core.exposure import exposure_gains
from pipeline.core.focus_order import focus_order
from pipeline.core.frame_support import (
    FrameSupport,
    clip_to_frames,
    keep_to_frames,
    noise_ceiling,
    quiet_flat_areas,
    visible_noise_limit,
)
from pipeline.core.lens import Lens
from pipeline.core.stack_kernel import frame_kernels, positions_from_scales, stack_kernel
from pipeline.core.weights import constant_speed_weights
from pipeline.errors import InputError
from pipeline.io.profiles import load_lens
from pipeline.io.read import read_preview
from pipeline.io.stackfile import Stack, check_frames, image_distances_mm, load_stack
from pipeline.jobs.ends import (
    correction_factor,
    end_kernels,
    keep_to_end_frames,
    reduced_size,
    restore_ends,
)
from pipeline.jobs.frame_detail import away_from_other_depths, detail_maps, keep_inner_detail
from pipeline.jobs.multiframe import restore_multiframe
from pipeline.jobs.options import (
    Progress,
    StackOptions,
    StackResult,
    _no_progress,
    megapixels,
)
from pipeline.jobs.result import (
    RESCALE_ABOVE,
    check_not_input,
    check_output,
    restore_image,
    write_result,
)
from pipeline.jobs.sweep import process_sweep_stack
from pipeline.parallel.accumulate import weighted_sum_graph
from pipeline.parallel.scheduler import _TaskProgress, local_workers

log = logging.getLogger(__name__)

PREVIEW_SIDE_PX = 320  # resolution of the defocus (blur-span) fit
OTHER_UNITS_ABOVE = 1.5  # an average this far above white (1): frames in other units
# clipped (at white) in some frame over more of the image than this: warned (the real stacks
# here: 0-4%; pcb7 with 39% of a frame white rang along the clipped area's border)
CLIPPED_WARN = 0.1
END_DOMINANT = 0.5  # an end frame the sharpest over more of the image than this: warned,
END_BEYOND = 0.02  # ... if its content lies at least this share of the range beyond it
# the mean Eq. 8 dissimilarity of the per-depth kernels to the stack's IPSF above which the
# stack is warned of as too sparse for one kernel (check_sparse_stack): the real stacks
# 0.02-0.82, their three- and four-frame sub-stacks 1.66-2.69, two frames 3.48-4.75
SPARSE_SPREAD = 3.0
# The estimated alignment is kept only if the blur model explains the aligned frames clearly
# better than unaligned ones (issue 13: ECC, biased by the frames' depth-dependent blur,
# invents a breathing of up to 1.9% on stacks without any); judged at this resolution
CHOICE_SIDE_PX = 128
CHOICE_MARGIN = 0.1  # the estimate must leave under (1 - this) of the identity's unexplained
# ... with the lens's exact model; with the fitted pillbox, which explains real frames only
# roughly (beetle, amber: 10-22% of the detail unexplained either way), the identity must
# explain at least as well: there a real breathing of 1-2% moved the share by only 4-7%
CHOICE_MARGIN_FITTED = 0.0
# The blur-span fit matches a pillbox core to the frames; real lenses' defocus also has
# a wide soft tail, which a kernel of the fitted span leaves as haze (issue 13: pcb7's
# far barcode kept 45 of its frame's 68 contrast). Twice the fit restored it on pcb7,
# pcb10, beetle and amber (tests/benchmarks/results/real_regions/NOTE.md); what
# overshoots is clipped to the frames' range (pipeline.core.frame_support).
FITTED_SPAN_SCALE = 2.0
MIN_FRAME_SIDE_PX = 8  # smaller frames hold no usable detail (and no room for a kernel)
# frames' exposures (as shot) further apart than this are warned of (beetle's flash: 0.49)
EXPOSURE_WARNING = 0.05
# A frame whose contrast (1st to 99th percentile of its reduced grey copy) is below this share
# of the stack's median is blank (a misfire, the lens cap, a black or white frame) and left
# out: kept, one black frame in four of beetle's made the blur-span fit read 400 px and the
# result rang over the whole image. A frame defocused far beyond the subject keeps most of
# its contrast: the real stacks' frames read 0.73-1.21 of their median (beetle; pcb7
# 0.98-1.01, pcb10 0.99-1.02, amber 0.92-1.04), a beetle frame blurred by a 40 px Gaussian 0.43.
BLANK_CONTRAST = 0.02
COVERED = 0.999  # a warped frame's pixels with this much coverage are its own (not edge fill)


# ----------------------------------------------------------------------------- limits
def check_frame_size(stack: Stack, shape: tuple[int, ...], options: StackOptions) -> None:
    """Refuse frames too small to process or larger than ``options.max_pixels`` (header only)."""
    rows, cols = shape[:2]
    first = stack.files[0]
    if min(rows, cols) < MIN_FRAME_SIDE_PX:
        raise InputError(
            f"{first}: the frames are {cols}x{rows} px; flexdof needs at least "
            f"{MIN_FRAME_SIDE_PX}x{MIN_FRAME_SIDE_PX} px"
        )
    if rows * cols > options.max_pixels:
        raise InputError(
            f"{first}: the frames are {cols}x{rows} px ({megapixels(rows * cols)} Mpx), more than "
            f"the limit of {megapixels(options.max_pixels)} Mpx; raise it with --max-pixels if "
            "this is a real image (memory grows about 40 bytes per pixel)"
        )


def check_white(stack: Stack, average: np.ndarray) -> None:
    """Warn when the frames' average goes far above white (1): float TIFF frames in other
    units whose white level was not given. Clipping (``>= 0.999``) and the frames' range
    (16-bit codes of [0, 1]) assume white at 1, so such a stack comes out about 1 dB worse
    with the range off (frames scaled by 1000: 29.61 against 30.60 dB on the three planes;
    with ``--white 1000`` as in [0, 1])."""
    peak = float(np.max(average)) if average.size else 0.0
    if peak <= OTHER_UNITS_ABOVE:
        return
    if stack.white is not None:  # given, but too low
        log.warning(
            "%s: the frames' average reaches %.4g times the white level %g given: pixels at "
            "or above it count as clipped and the frames' range is not applied there; check "
            "--white (or white in stack.toml)",
            _describe_frames(stack),
            peak,
            stack.white,
        )
        return
    log.warning(
        "%s: the frames' average reaches %.4g where white is 1 (float TIFFs are linear "
        "light with white at 1): pixels at or above 1 count as clipped and the frames' "
        "range is not applied there; give the frames' white level with --white LEVEL "
        "(or white = LEVEL in stack.toml)",
        _describe_frames(stack),
        peak,
    )


def check_clipped(stack: Stack, clipped: np.ndarray) -> None:
    """Warn when over ``CLIPPED_WARN`` of the image is clipped (at white) in some frame.

    A clipped pixel tells only that the scene is at least that bright, so the deconvolution
    censors it (Sec. 4.2) and fills it from its surroundings. That suits specular
    highlights (pcb10: 4% of its pixels in some frame). Over a large area the result comes
    out soft there and rings along the area's border (pcb7 with the top 39% of its last
    frame overwritten with white: blobs along the border, soft above it)."""
    share = float(np.mean(clipped)) if clipped.size else 0.0
    if share <= CLIPPED_WARN:
        return
    log.warning(
        "%s: %.0f%% of the image is clipped (at white) in at least one frame; there the "
        "result is restored as a lower bound, comes out soft and may ring along the "
        "clipped area's border: lower the exposure, or leave the overexposed frames out",
        _describe_frames(stack),
        100 * share,
    )


def check_end_dominance(stack: Stack, ends: list[dict]) -> None:
    """Warn when an end frame is the sharpest over most of the image (``END_DOMINANT``) and
    its content lies beyond it (``END_BEYOND``): the scene lies mostly beyond that end of the
    focus range, where the stack's kernel and the ends' correction restore least (Sec. 4.1).
    pcb10's frames 4-9, whose content is sharpest in pcb10's frames 2-3, leave 87% to frame
    4 (0.047 of the range beyond it), and the result is softer than that frame in 8 of 9
    regions; ``--frame-guard`` takes it there from 0/9 to 4/9 regions as good as focus-stack
    (``tests/benchmarks/results/real_regions/NOTE.md``, stop 28). Content at the end frame's
    own depth (a scene two thirds at it: 61%, 0.0 beyond) is restored by its own kernel."""
    for end in ends:  # content at the end frame itself is restored by its own kernel
        if end["fraction"] > END_DOMINANT and end["beyond_range"] >= END_BEYOND:
            log.warning(
                "%s: %s is the sharpest frame over %.0f%% of the image: most of the scene lies "
                "beyond its focus, the end of the stack's focus range, where the result is "
                "restored least; add frames focused beyond it, or try --frame-guard",
                _describe_frames(stack),
                end["frame"],
                100 * end["fraction"],
            )


def check_sparse_stack(stack: Stack, summary: dict) -> None:
    """Warn when the frames lie too far apart, for their blur, for one kernel to fit every
    depth: the mean Eq. 8 dissimilarity of the per-depth kernels to the stack's IPSF (the
    kernel summary's ``depth_invariance_eq8``) above ``SPARSE_SPREAD``.

    Sec. 9's average emulates a sweep only as far as its frames sample the focus range: two
    frames 28-106 px of blur apart see content at their own depths sharp once and blurred
    once, and content between them blurred twice, so the IPSF is no longer one kernel (mean
    spread 3.5-4.8, against 0.02-0.8 on the real stacks). On nine two-frame sub-stacks of
    pcb7, pcb10 and amber the result's edges were wider than the sharpest frame's in 53 of
    the 73 regions with edges to measure, and 10 of 81 regions were as good as
    focus-stack's. ``--frame-guard`` took that to 38 of 81, every stack gaining, and 0.30 dB
    against a truth on two rendered planes at the frames' depths. It is not chosen
    automatically: its mosaic of the sharpest frame per 4 px block pastes hard-edged patches
    where the frames' tones differ (amber's translucent layers), which the region measures
    do not count (``tests/benchmarks/results/real_regions/sparse/``). On three and four
    frames (spread 1.7-2.7) the default held 4-7 of 9 and ``--frame-guard`` did not do
    better overall: no warning there."""
    spread = summary["depth_invariance_eq8"]["mean"]
    if spread <= SPARSE_SPREAD:
        return
    log.warning(
        "%s: the frames lie too far apart for one kernel to fit every depth (%.0f px of blur "
        "across them; Eq. 8 spread %.1f, above %.1f): the result may be softer than the "
        "sharpest frame; add frames between them, or try --frame-guard (sharper there, but "
        "its patches of the sharpest frame can show where the frames' tones differ)",
        _describe_frames(stack),
        summary["blur_span_px"],
        spread,
        SPARSE_SPREAD,
    )


def check_lens_size(stack: Stack, lens: Lens | None, shape: tuple[int, ...]) -> None:
    """Warn when the frames' size is not the lens profile's sensor size (blur in px is off)."""
    if lens is None or not lens.width_px or not lens.height_px:
        return
    rows, cols = shape[:2]
    if (cols, rows) in ((lens.width_px, lens.height_px), (lens.height_px, lens.width_px)):
        return
    log.warning(
        "%s: the frames are %dx%d px but lens profile %s describes a %dx%d px sensor; its "
        "pixel pitch (so the blur in px, and the kernel) does not fit these frames: use a "
        "profile for this resolution",
        stack.files[0],
        cols,
        rows,
        lens.source or lens.name,
        lens.width_px,
        lens.height_px,
    )


def check_blur_span(stack: Stack, span: float, shape: tuple[int, ...], source: str) -> None:
    """A blur span larger than the frame's diagonal cannot be deconvolved (and would need a
    kernel larger than the frame): refuse it, naming where it came from."""
    diagonal = float(np.hypot(*shape[:2]))
    if not np.isfinite(span) or span > diagonal:
        raise InputError(
            f"{stack.base_dir}: {source} gives a blur span of {span:.4g} px, more than the "
            f"frames' diagonal ({diagonal:.0f} px); check it"
        )


def blank_frames(previews: Sequence[np.ndarray]) -> list[int]:
    """Indices of the frames whose contrast is below ``BLANK_CONTRAST`` of the stack's median.

    The contrast is the spread between the 1st and 99th percentiles of a frame's reduced
    grey copy: defocus takes a frame's fine detail far more than that spread (a 40 px blur
    keeps 0.43 of it), so only a frame that shows (next to) nothing reads far below the
    others. Empty when the stack's median is 0 (every frame flat: nothing to compare with).
    """
    spread = [
        float(np.subtract(*np.percentile(p[::2, ::2], [99, 1]))) if p.size else 0.0
        for p in previews
    ]
    typical = float(np.median(spread)) if spread else 0.0
    if typical <= 0:
        return []
    return [i for i, s in enumerate(spread) if s < BLANK_CONTRAST * typical]


def leave_out_blank(stack: Stack, previews: list[np.ndarray], positions: np.ndarray | None):
    """``stack``, ``previews`` and ``positions`` without the blank frames
    (:func:`blank_frames`), and the names of those left out (each warned about); an error
    when fewer than two frames are left."""
    blank = blank_frames(previews)
    if not blank:
        return stack, previews, positions, ()
    names = tuple(stack.files[i].name for i in blank)
    keep = [i for i in range(len(stack)) if i not in blank]
    if len(keep) < 2:
        raise InputError(
            f"{_describe_frames(stack)}: {', '.join(names)} "
            f"{'shows' if len(names) == 1 else 'show'} no image (blank: black, white or flat), "
            "which leaves fewer than two frames; reshoot or replace the blank frames"
        )
    log.warning(
        "%s: %s left out of the stack: blank (no image content beside the other frames: a "
        "misfire, the lens cap, a black or white frame)",
        _describe_frames(stack),
        ", ".join(names),
    )
    stack = dataclasses.replace(stack, frames=tuple(stack.frames[i] for i in keep))
    return (
        stack,
        [previews[i] for i in keep],
        None if positions is None else positions[keep],
        names,
    )


# ----------------------------------------------------------------------------- positions
def _resolve_lens(stack: Stack, options: StackOptions) -> Lens | None:
    if options.lens is not None:
        return load_lens(options.lens)  # a path given by the user: relative to the cwd
    return stack.lens_profile


def _sidecar_positions(stack: Stack, lens: Lens | None) -> tuple[np.ndarray | None, bool]:
    """(positions, absolute) from stack.toml/EXIF; uncalibrated focus steps stay in steps."""
    kinds = {frame.position_kind for frame in stack.frames}
    if kinds == {"focus_step"} and (lens is None or lens.step_image_distance_um is None):
        return np.array([f.focus_step for f in stack.frames], dtype=np.float64), False
    found = image_distances_mm(stack, lens)
    if found is None:
        return None, False
    return found.image_distances_mm, not found.relative


# ----------------------------------------------------------------------------- previews
def read_previews(
    files: Sequence[Path],
    max_side_px: int,
    progress: Progress = _no_progress,
    *,
    white: float | None = None,
) -> list[np.ndarray]:
    """Reduced grey copies of every frame, decoded in parallel (one cheap decode each).

    ``white``: the frames' white level (:func:`pipeline.io.read.read_frame`). Float frames
    far brighter than white (above ``RESCALE_ABOVE``) are divided by their common peak, so
    alignment statistics cannot overflow float32.
    """
    with _TaskProgress("read_preview", lambda done: progress("preview", done, len(files))):
        previews = list(
            dask.compute(
                *[dask.delayed(read_preview)(f, max_side_px, white=white) for f in files]
            )
        )
    peak = max((float(np.max(np.abs(p))) for p in previews if p.size), default=0.0)
    if peak > RESCALE_ABOVE:
        previews = [(p.astype(np.float64) / peak).astype(np.float32) for p in previews]
    return previews


def _fit_factor(full_shape) -> float:
    """Full-resolution size / the defocus fit's (never upscale a small frame)."""
    return max(1.0, max(full_shape[:2]) / PREVIEW_SIDE_PX)


def _fit_preview(preview, alignment, full_shape) -> np.ndarray:
    """A preview at the defocus-fit resolution, aligned by its full-resolution homography."""
    factor = _fit_factor(full_shape)
    size = (max(1, round(full_shape[1] / factor)), max(1, round(full_shape[0] / factor)))
    return _aligned_at(preview, alignment, full_shape, size)


def _aligned_at(preview, alignment, full_shape, size) -> np.ndarray:
    """``preview`` aligned by its full-resolution homography, then reduced to ``size``
    (cols, rows).

    The warp runs at the preview's own resolution, before the reduction. Bilinear
    interpolation blurs a frame by up to half a pixel, by an amount that varies with the
    frame's offset, and the defocus fits (:func:`pipeline.core.defocus.estimate_blur_span`,
    :func:`~pipeline.core.defocus.end_depths`) compare the frames' blur at the reduced
    size, where two frames a few steps apart may differ by a pixel or less. Warped after
    the reduction, rendered stacks of a tilted board read blur spans 25-71% above the
    truth (7.4 px on 768 px frames read as 12.7 px; issue 13,
    ``tests/benchmarks/regions_vs_truth.py``), and a stack rendered by brute force and
    magnified 0.3% per frame 55% above (``tests/test_defocus.py``). Warped first, the
    boards read 11.3 px as 10.5 and 7.4 as 7.6 (with the fit's pairs four frames apart,
    :func:`pipeline.core.defocus._pairs`), the brute-force stack 13% above.
    """
    h = align.rescale_homography(alignment.homography, full_shape[:2], preview.shape[:2])
    return cv2.resize(align.warp(preview, h, preview.shape), size, interpolation=cv2.INTER_AREA)


def _blur_fit_previews(previews, alignments, full_shape) -> tuple[list[np.ndarray], float]:
    """Aligned copies at the defocus-fit resolution, and their downscale factor."""
    small = [_fit_preview(p, a, full_shape) for p, a in zip(previews, alignments)]
    return small, _fit_factor(full_shape)


def normalise_exposure(aligned: AlignedStack, weights, options: StackOptions):
    """The aligned previews at the defocus fit's resolution, ``(copies, factor)`` (``None``
    where no previews were read), and each frame's exposure relative to the stack's
    measured on them (:func:`pipeline.core.exposure.exposure_gains`; ``weights``: the
    frames' in the sum), as ``aligned.exposures``. With ``--match-exposure`` they are also
    ``aligned.gains``: the copies are returned divided by them, and every read of a frame
    past this point divides it by its own (its clipped pixels found first, as shot); as
    shot, exposures that differ by more than ``EXPOSURE_WARNING`` are named in a warning."""
    if aligned.previews is None:
        return None
    copies, factor = fit = _blur_fit_previews(aligned.previews, aligned.alignments, aligned.shape)
    gains = exposure_gains(copies, weights)
    if np.all(gains == 1):
        return fit
    aligned.exposures = gains
    names = [f.name for f in aligned.stack.files]
    low, high = int(np.argmin(gains)), int(np.argmax(gains))
    spread = (f"{gains[low]:.3f} ({names[low]}) to {gains[high]:.3f} ({names[high]}) of the "
              "stack's")  # fmt: skip
    if options.match_exposure:
        aligned.gains = gains
        log.info("exposure differs between frames: %s; each frame is divided by its own", spread)
        return [c / np.float32(g) for c, g in zip(copies, gains)], factor
    if gains[high] - gains[low] > EXPOSURE_WARNING:
        log.warning(
            "%s: the frames' exposures differ, %s (a flash, flicker or a macro lens's "
            "effective aperture); --match-exposure divides each frame by its own",
            aligned.stack.base_dir, spread,
        )  # fmt: skip
    return fit


def _end_frame(aligned: AlignedStack, index: int) -> np.ndarray:
    """Frame ``index``, grey and aligned, at the end correction's resolution
    (:func:`pipeline.jobs.ends.correction_factor`; a cheap reduced decode for JPEGs)."""
    size = reduced_size(aligned.shape, correction_factor(aligned.shape))
    preview = read_preview(aligned.stack.files[index], max(size), white=aligned.stack.white)
    if aligned.gains is not None:
        preview /= np.float32(aligned.gains[index])
    return _aligned_at(preview, aligned.alignments[index], aligned.shape, size)


def _aligned_frame(aligned: AlignedStack, index: int, box, kept) -> tuple[np.ndarray, np.ndarray]:
    """The ``box`` (rows, columns) of frame ``index``, grey (``mean_grey``: all that
    :func:`pipeline.jobs.ends.keep_end_detail` reads), aligned at full resolution (bicubic:
    its fine detail is used as it is), and where the frame covers it. The grey frame is the
    accumulation's copy (:func:`accumulate`'s ``keep``: an end frame always has a weight,
    so it is always read there)."""
    rows, cols = box
    shift = np.array([[1.0, 0.0, -cols.start], [0.0, 1.0, -rows.start], [0.0, 0.0, 1.0]])
    frame = kept[index]
    image, coverage = align.warp(
        frame,
        shift @ aligned.alignments[index].homography,
        (rows.stop - rows.start, cols.stop - cols.start),
        return_coverage=True,
        interpolation="cubic",
    )
    return image, coverage > COVERED


def _streamed_end_previews(aligned: AlignedStack):
    """What the correction at the ends (:mod:`pipeline.jobs.ends`) needs where the
    alignment read no previews (``--align none`` or ``analytic``): the aligned previews
    at the fit's resolution of the frames :func:`pipeline.core.defocus.end_frames` names,
    their downscale factor, and the stack's :class:`~pipeline.core.defocus.FocusMaps`.
    Frames are read one at a time (a cheap reduced decode for JPEGs), so memory stays
    flat in the number of frames; before the accumulation, which needs the maps for the
    inner frames' detail (:mod:`pipeline.jobs.frame_detail`)."""
    keep = set(defocus.end_frames(aligned.positions))
    maps, kept = defocus.FocusMaps(), {}
    for i, (path, alignment) in enumerate(zip(aligned.stack.files, aligned.alignments)):
        preview = read_preview(path, PREVIEW_SIDE_PX, white=aligned.stack.white)
        small = _fit_preview(preview, alignment, aligned.shape)
        maps.add(i, small)
        if i in keep:
            kept[i] = small
    return kept, _fit_factor(aligned.shape), maps


# ----------------------------------------------------------------------------- phases
@dataclasses.dataclass
class AlignedStack:
    """A loaded stack with its focus positions and its frames' homographies.

    The common first half of every job that averages a focal stack
    (:func:`process_stack`, :func:`pipeline.jobs.dof.process_dof`).
    """

    stack: Stack
    lens: Lens | None
    shape: tuple[int, ...]
    positions: np.ndarray
    absolute: bool  # positions are image distances (mm), not steps or frame order
    positions_source: str
    alignments: list[align.Alignment]
    previews: list[np.ndarray] | None
    timings: dict[str, float]
    start: float
    left_out: tuple[str, ...] = ()  # blank frames' file names (:func:`leave_out_blank`)
    # each frame's exposure relative to the stack's, as measured (:func:`normalise_exposure`;
    # None: all within 1% of 1 or not measured), and as divided out of every read of the
    # frame (``--match-exposure``; None: as shot)
    exposures: np.ndarray | None = None
    gains: np.ndarray | None = None


def load(paths, options: StackOptions) -> tuple[Stack, Lens | None, float]:
    """The stack at ``paths``, its lens (``--lens`` first, then stack.toml), the start time.
    ``--white`` replaces stack.toml's white level."""
    start = time.perf_counter()
    stack = load_stack(paths)
    if options.white is not None:
        stack = dataclasses.replace(stack, white=options.white)
    return stack, _resolve_lens(stack, options), start


def align_stack(
    stack: Stack,
    lens: Lens | None,
    options: StackOptions,
    start: float,
    *,
    progress: Progress = _no_progress,
    fit_blur_span: bool = False,
) -> AlignedStack:
    """Check the frames, find their focus positions and align them (Sec. 9).

    Positions come from stack.toml/EXIF; without them, from the measured
    magnifications (:func:`positions_from_scales`), and frames whose names are not in
    focus order are put in it where their blur and magnification agree on it
    (:func:`pipeline.core.focus_order.focus_order`; the returned stack holds them so).
    With ``fit_blur_span`` and no absolute positions with a lens, the reduced grey copies
    are kept (the blur-span fit uses them) even with ``--align`` other than ``estimate``.
    Where the reduced copies are read, blank frames are left out (:func:`leave_out_blank`;
    ``--align none`` or ``analytic`` with a lens and absolute positions read none).
    """
    shape = check_frames(stack).shape
    check_frame_size(stack, shape, options)
    check_lens_size(stack, lens, shape)
    positions, absolute = _sidecar_positions(stack, lens)
    t0 = time.perf_counter()
    previews, left_out = None, ()
    if options.align == "estimate" or (fit_blur_span and not (lens is not None and absolute)):
        previews = read_previews(
            stack.files, options.align_max_side_px, progress, white=stack.white
        )
        stack, previews, positions, left_out = leave_out_blank(stack, previews, positions)
    progress("align", 0, 1)
    alignments = _align(stack, options, positions, absolute, previews, shape, lens)
    if positions is None and previews is not None:
        order = focus_order(previews, [a.scale for a in alignments])
        if order is not None:  # aligned again: the chain matches focus neighbours
            stack, previews = _reordered(stack, order), [previews[i] for i in order]
            alignments = _align(stack, options, positions, absolute, previews, shape, lens)
    progress("align", 1, 1)
    timings = {"align": time.perf_counter() - t0}
    positions_source = stack.positions_source or "stack.toml"
    if positions is None:
        positions, positions_source = positions_from_scales(np.array([a.scale for a in alignments]))
        absolute = False
    return AlignedStack(
        stack,
        lens,
        shape,
        positions,
        absolute,
        positions_source,
        alignments,
        previews,
        timings,
        start,
        left_out,
    )


def accumulate(
    aligned: AlignedStack,
    weights: np.ndarray,
    options: StackOptions,
    *,
    progress: Progress = _no_progress,
    support: str | None = None,
    keep=(),
    detail=None,
) -> tuple[np.ndarray, np.ndarray, FrameSupport | None, dict, tuple | None]:
    """``sum_i w_i warp(frame_i)`` streamed through dask, the pixels clipped in any frame
    and, with ``support``, the frames' per-pixel range (``"range"``), or also their
    sharpest frame and noise (``"full"``); the grey images of the frames in ``keep``, as
    read; with ``detail`` (:class:`pipeline.jobs.frame_detail.DetailMaps`: where each
    inner frame is the sharpest), those frames' grey images summed by their maps, and the
    maps' sum (:func:`pipeline.parallel.accumulate.weighted_sum_graph`).

    ``weights`` is (frames,) or, for per-row DOFs, (rows, frames).
    """
    t0 = time.perf_counter()
    per_frame = weights if weights.ndim == 1 else weights.T  # (frames,) or (frames, rows)
    graph = weighted_sum_graph(
        aligned.stack.files,
        [None if options.align == "none" else a.homography for a in aligned.alignments],
        per_frame,
        aligned.shape,
        support=support,
        white=aligned.stack.white,
        gains=aligned.gains,
        keep=keep,
        detail=detail,
    )
    used = int(np.count_nonzero(per_frame.reshape(len(per_frame), -1).max(axis=1) > 0))
    progress("accumulate", 0, used)
    with _TaskProgress("_add_frame", lambda done: progress("accumulate", done, used)):
        ((average, clipped, read_s, frames, kept, sharp),) = dask.compute(graph)
    progress("accumulate", used, used)
    aligned.timings["accumulate"] = time.perf_counter() - t0
    aligned.timings["read"] = read_s  # full-resolution decoding, summed over worker threads
    return average, clipped, frames, kept, sharp


def stack_sidecar(aligned: AlignedStack, weights: np.ndarray, method: str, options) -> dict:
    """The sidecar's description of the inputs, frames, weights and alignment."""
    frames_meta = [
        {
            "file": str(frame.file.name),
            "position": float(p),
            "weight": float(np.mean(w)),
            "scale": float(a.scale),
            "homography": a.homography.tolist(),
            "alignment": a.method if a.ok else f"fallback: {a.message}",
            "exposure": 1.0 if aligned.exposures is None else round(float(aligned.exposures[i]), 4),
        }
        for i, (frame, p, w, a) in enumerate(zip(
            aligned.stack.frames,
            aligned.positions,
            weights if weights.ndim == 1 else weights.T,
            aligned.alignments,
        ))
    ]
    if aligned.absolute:
        for meta, p in zip(frames_meta, aligned.positions):
            meta["image_distance_mm"] = float(p)
    lens = aligned.lens
    return {
        "version": 1,
        "inputs": [str(f) for f in aligned.stack.files],
        "lens": (lens.source or lens.name) if lens else None,
        "method": method,
        "align": options.align,
        "align_model": aligned.alignments[0].model if options.align == "estimate" else None,
        "positions_source": aligned.positions_source,
        "frames": frames_meta,
        "partial_stack": aligned.stack.partial,
        "left_out": list(aligned.left_out),
        "exposure_matched": aligned.gains is not None,
        "white": aligned.stack.white,
    }


# ----------------------------------------------------------------------------- main job
def process_stack(
    paths: Sequence[str | Path] | str | Path,
    output: str | Path,
    options: StackOptions | None = None,
    *,
    progress: Progress = _no_progress,
) -> StackResult:
    """Focal stack (or sweep capture) -> extended-DOF image at ``output`` + ``output.json``.

    Align the frames, average them with the weights of a constant-speed sweep
    (Sec. 9), deconvolve the average with its IPSF (Eqs. 5-7) and write the image
    and its sidecar. A stack.toml of kind "sweep" goes to
    :func:`pipeline.jobs.sweep.process_sweep_stack`.

    Parameters
    ----------
    paths : path, glob or sequence of paths
        A stack directory (with an optional stack.toml), a glob, or frame files.
    output : path
        ``.tif``, ``.png`` or ``.jpg``; the sidecar is ``output`` + ``.json``.
    options : StackOptions, optional
        The ``flexdof stack`` flags; defaults if omitted.
    progress : callable(stage, done, total), optional
        Called as each stage advances.

    Returns
    -------
    StackResult
        The output path, the sidecar dict and the image (float32, linear).

    Notes
    -----
    Runs on the current dask scheduler (see
    :func:`pipeline.parallel.scheduler.scheduler_context`). Nothing is written
    unless the whole job succeeds; the image and its sidecar are each written
    atomically.

    Examples
    --------
    >>> from pathlib import Path
    >>> import tempfile
    >>> sample = Path(__file__).resolve().parents[2] / "stacks" / "motorcycle"
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     result = process_stack(sample, Path(tmp) / "edof.tif")
    ...     print(result.image.shape, result.sidecar["kernel"]["source"])
    (250, 370, 3) stack-average
    """
    options = StackOptions() if options is None else options
    output = Path(output)
    check_output(output, options.save_kernel)
    stack, lens, start = load(paths, options)
    check_not_input(output, stack.files, options.save_kernel)
    if stack.kind == "sweep":
        return process_sweep_stack(stack, lens, output, options, progress=progress)
    aligned = align_stack(
        stack,
        lens,
        options,
        start,
        progress=progress,
        fit_blur_span=options.blur_span_px is None,
    )
    stack = aligned.stack  # in focus order
    needs_fit = options.blur_span_px is None and not (lens is not None and aligned.absolute)
    positions, timings = aligned.positions, aligned.timings
    weights = constant_speed_weights(positions, ends=options.sweep_ends)

    blur_span = options.blur_span_px
    if blur_span is not None:
        check_blur_span(stack, blur_span, aligned.shape, "--blur-span-px")
    elif aligned.absolute and lens is not None:
        span = float(lens.blur_px(positions.min(), positions.max()))  # Eq. 2
        check_blur_span(stack, span, aligned.shape, f"the focus positions with lens {lens.name!r}")
    if needs_fit:
        n = len(stack)
        if n < 2:
            raise InputError(
                f"{stack.files[0]}: a focal stack needs at least two frames focused at different "
                "depths (got one); for a single sweep capture use flexdof sweep"
            )
        if np.ptp(positions) == 0:
            raise InputError(
                f"{stack.base_dir}: all {n} frames have the same focus position: nothing to sweep"
            )
    # The IPSF needs only the previews and the positions, the average only the frames:
    # the blur-span fit and the kernel run beside the accumulation (issue 15; a failed
    # fit is reported once the accumulation ends).
    # the aligned previews at the fit's resolution (the full ones are dropped)
    small = normalise_exposure(aligned, weights, options)
    want_ends = options.frame_range and not options.frame_guard
    aligned.previews = None  # not needed past the alignment: memory flat in the frame count
    ends_read = None  # what the ends' correction reads (pipeline.jobs.ends)
    inner = None  # where each inner frame is the sharpest, for its own detail
    if want_ends:
        if small is not None:
            ends_read = (*small, defocus.FocusMaps.of(small[0]))
        else:  # no previews (--align none, analytic): read one at a time, before the sum
            ends_read = _streamed_end_previews(aligned)
        inner = detail_maps(ends_read[2], aligned.positions)
    with ThreadPoolExecutor(1, thread_name_prefix="flexdof-kernel") as pool:
        kernel_job = pool.submit(
            _stack_ipsf,
            aligned,
            weights,
            blur_span,
            small if needs_fit else None,
            options.frame_guard,
            ends=ends_read,
        )
        average, clipped, frames, kept, sharp = accumulate(
            aligned,
            weights,
            options,
            progress=progress,
            support=_support(options),
            keep=defocus.end_pair(aligned.positions) if want_ends else (),
            detail=inner,
        )
        kernel, kernel_samples, kernel_summary, beyond = kernel_job.result()
    check_white(stack, average)
    check_clipped(stack, clipped)
    if not options.frame_guard:  # the warning's advice
        check_sparse_stack(stack, kernel_summary)

    progress("deconvolve", 0, 1)
    t0 = time.perf_counter()
    multi = options.method == "multiframe"  # the Sec. 9 result first: its fallback
    ceiling = limit = None
    if options.frame_guard:
        ceiling = noise_ceiling(frames, average, clipped)
    elif frames is not None and (multi or options.method == "wiener"):  # Wiener's limit
        limit = visible_noise_limit(frames, average, clipped)
    source = _describe_frames(stack)
    plans = []
    result = restore_image(
        average,
        kernel,
        dataclasses.replace(options, method="wiener") if multi else options,
        clipped=clipped,
        kernel_samples=kernel_samples,
        source=source,
        max_noise=ceiling,
        noise_limit=limit,
        on_plan=plans.append,
    )
    timings["deconvolve"] = time.perf_counter() - t0
    sidecar = stack_sidecar(aligned, weights, options.method, options)
    sidecar["kernel"] = kernel_summary
    if limit is not None:  # what the limit was, and in which channels it held lam
        held = plans[0].params.get("noise_limited") if plans else None
        held = np.zeros(len(limit), bool) if held is None else held
        sidecar["noise_limit"] = {"std": [float(v) for v in limit], "held": held.tolist()}
    t0 = time.perf_counter()
    if options.frame_guard:
        result, blended = keep_to_frames(result, frames, clipped)
        timings["frame_guard"] = time.perf_counter() - t0
        sidecar["frame_guard"] = {
            "sharpest_frame_fraction": round(blended, 4),
            "noise_ceiling": None if ceiling is None else [float(v) for v in ceiling],
        }
    elif frames is not None:
        ends, end_ranges = restore_ends(
            result,
            average,
            beyond,
            kernel,
            read_frame=lambda i, box: _aligned_frame(aligned, i, box, kept),
            clipped=clipped,
            exposures=None if aligned.gains is not None else aligned.exposures,  # as shot
        )
        for end in ends:
            end["frame"] = stack.files[end["frame"]].name
        check_end_dominance(stack, ends)
        inner_kept = None
        if sharp is not None:  # each inner frame's own detail, away from depth changes
            span, factor = kernel_summary["blur_span_px"], ends_read[1]
            away = away_from_other_depths(inner, span / factor, factor)
            inner_kept = keep_inner_detail(result, sharp, away, clipped)
        result, flat = quiet_flat_areas(result, average, frames)
        result = clip_to_frames(result, frames, clipped)  # nothing leaves the range
        end_kept = keep_to_end_frames(result, end_ranges)  # nor the end frame's, at an end
        timings["frame_range"] = time.perf_counter() - t0
        sidecar["frame_range"] = {
            "flat_fraction": round(flat, 4),
            "beyond_ends": ends,
            "end_range_moved": round(end_kept, 4),
        }
        if inner_kept is not None:
            sidecar["frame_range"]["inner_detail_kept"] = round(inner_kept, 4)
    progress("deconvolve", 1, 1)
    if multi:
        t0 = time.perf_counter()
        span = kernel_summary.get("blur_span_px")
        result, sidecar["multiframe"] = restore_multiframe(
            aligned, span, result, clipped, average=average, support=frames, progress=progress
        )
        timings["multiframe"] = time.perf_counter() - t0
    return write_result(output, result, kernel, sidecar, timings, start, options, stack.files)


def _support(options: StackOptions) -> str | None:
    """What the accumulation streams of the frames beside their sum: everything the frame
    guard uses, or the range the clip needs, or nothing."""
    if options.frame_guard:
        return "full"
    return "range" if options.frame_range else None


def _stack_ipsf(
    aligned: AlignedStack,
    weights: np.ndarray,
    blur_span: float | None,
    fit,
    frame_guard: bool = False,
    *,
    ends=None,
):
    """The stack's IPSF (:func:`stack_kernel`, Eqs. 5-6), after measuring the blur span
    (:func:`pipeline.core.defocus.estimate_blur_span`) on ``fit``, the aligned previews
    at the fit's resolution and their downscale factor, when given. With the frame
    guard, the fitted span is scaled by ``FITTED_SPAN_SCALE``. With ``ends``, the ends'
    aligned previews, their downscale factor and the stack's focus maps (made before the
    accumulation, which also needs the maps: :mod:`pipeline.jobs.frame_detail`), also the
    kernels of the content at and beyond the range's ends
    (:func:`pipeline.jobs.ends.end_kernels`; else none). Returns the kernel, its per-depth
    samples, its summary and the end kernels."""
    t0 = time.perf_counter()
    if fit is not None:
        small, factor = fit
        max_span = min(400.0, float(np.hypot(*aligned.shape[:2])))  # bounded by the frame
        try:
            blur_span = defocus.estimate_blur_span(
                small, aligned.positions, downscale=factor, max_span_px=max_span
            )
        except InputError as err:
            raise InputError(
                f"{aligned.stack.base_dir}: cannot measure the blur across the stack ({err}); "
                "give it with --blur-span-px or give the focus positions and a lens in stack.toml"
            ) from err
        log.info("estimated blur span: %.1f px across the stack", blur_span)
        if frame_guard:
            blur_span = min(FITTED_SPAN_SCALE * blur_span, max_span)
    kernel, samples, summary = stack_kernel(
        aligned.positions,
        weights,
        lens=aligned.lens,
        absolute=aligned.absolute,
        blur_span_px=blur_span,
    )
    beyond = []
    if ends is not None:
        beyond = end_kernels(
            ends,
            aligned.positions,
            weights,
            summary["blur_span_px"],
            lens=aligned.lens,
            absolute=aligned.absolute,
            read_end=lambda i: _end_frame(aligned, i),
        )
    aligned.timings["kernel"] = time.perf_counter() - t0
    return kernel, samples, summary, beyond


def _reordered(stack: Stack, order: list[int]) -> Stack:
    """``stack`` with its frames in ``order`` (indices into its files' order), saying so."""
    frames = tuple(stack.frames[i] for i in order)
    log.warning(
        "%s: the frames are not in focus order by name; their blur and magnification put them "
        "in the order %s (name them in focus order, or give their positions in stack.toml)",
        stack.base_dir,
        ", ".join(f.file.name for f in frames),
    )
    return dataclasses.replace(stack, frames=frames)


def _describe_frames(stack: Stack) -> str:
    files = stack.files
    if len(files) == 1:
        return str(files[0])
    return f"{stack.base_dir} ({len(files)} frames, {files[0].name} .. {files[-1].name})"


def _align(stack, options, positions, absolute, previews, shape, lens=None):
    """Per-frame homographies to the middle frame (Sec. 9), at full resolution."""
    n = len(stack)
    if options.align == "none":
        return align.analytic_alignment(np.ones(n), shape)  # identities
    if options.align == "analytic":
        if positions is None or not absolute:
            raise InputError(
                f"{stack.base_dir}: --align analytic needs absolute focus positions "
                "(image or focus distances in stack.toml); use --align estimate"
            )
        return align.analytic_alignment(positions, shape)
    estimated = align.estimate_alignment(  # warns of each fallback, naming the files
        previews,
        model=options.align_model,
        max_side_px=options.align_max_side_px,
        workers=local_workers(),
        names=[path.name for path in stack.files],
    )
    alignments = [
        dataclasses.replace(
            a, homography=align.rescale_homography(a.homography, previews[0].shape, shape[:2])
        )
        for a in estimated
    ]
    if n < 3:
        return alignments
    if positions is None:  # the frames' order as their focus steps (the usual capture)
        positions, absolute = np.arange(n, dtype=np.float64), False
    elif np.ptp(positions) <= 0:
        return alignments
    return _keep_if_explained(
        alignments, previews, positions, lens, shape, absolute, options.blur_span_px
    )


def _choice_span(frames, positions, factor: float, shape) -> float | None:
    """The blur span (full-resolution px) fitted on the choice's small ``frames``; ``None``
    where nothing can be fitted (no textured, in-focus regions)."""
    max_span = min(400.0, float(np.hypot(*shape[:2])))
    try:
        return defocus.estimate_blur_span(  # the kernel's fit warns, if it must
            list(frames), positions, downscale=factor, max_span_px=max_span, warn=False
        )
    except InputError:
        return None


def _aligned_small(previews, homographies, shape) -> tuple[np.ndarray, float]:
    """The previews at ``CHOICE_SIDE_PX``, aligned (Lanczos) by full-resolution
    ``homographies`` (``None``: as they are), and their downscale factor."""
    factor = max(1.0, max(shape[:2]) / CHOICE_SIDE_PX)
    size = (max(8, round(shape[1] / factor)), max(8, round(shape[0] / factor)))
    small = []
    for i, preview in enumerate(previews):
        reduced = cv2.resize(preview, size, interpolation=cv2.INTER_AREA)
        if homographies is not None:
            hr = align.rescale_homography(homographies[i], shape[:2], reduced.shape)
            reduced = align.warp(reduced, hr, reduced.shape, interpolation="lanczos")
        small.append(reduced)
    return np.stack(small), factor


def _keep_if_explained(
    alignments, previews, positions, lens, shape, absolute=True, blur_span_px=None
):
    """The estimated ``alignments``, or the identity where the blur model explains the
    unaligned frames about as well (``CHOICE_MARGIN``, ``CHOICE_MARGIN_FITTED`` without the
    lens's model): ECC's correlation peak moves with the
    blur differences between frames, the model predicts them (issue 13;
    ``tests/benchmarks/results/align/align_bias_planes.md``). A stack given no focus
    positions is judged with its frames' order as the positions (:func:`_align`): the
    three-plane stack without breathing, as a plain folder of frames, read a breathing of
    3% (scales 0.986-1.016) and lost 1.9 dB against ``--align none`` (28.96 against 30.83 at
    sigma 0.01) before it was.

    The model is the lens's where it is known with absolute focus positions; otherwise the
    pillbox of :mod:`pipeline.core.defocus` with ``blur_span_px`` (``--blur-span-px``) or,
    without it, the span fitted on the frames aligned by the estimate (on a stack without
    breathing the unaligned frames fit the same span, 47.6 against 48.0 px on the three-plane
    stack; on a breathing one they fit none well). Where no span can be fitted the estimate
    is kept."""
    moved, factor = _aligned_small(previews, [a.homography for a in alignments], shape)
    still, _ = _aligned_small(previews, None, shape)
    with_lens = lens is not None and absolute
    span = None
    if not with_lens:
        span = blur_span_px or _choice_span(moved, positions, factor, shape)
        if span is None:
            return alignments

    def kernels_at(x: float, scale: float) -> list[np.ndarray]:
        return frame_kernels(
            positions,
            x,
            lens=lens if with_lens else None,
            absolute=with_lens,
            blur_span_px=span,
            scale=scale / factor,
        )

    # the frames' own focus positions as the depths: the choice needs no depth beyond them
    estimated, identity = multiframe.unexplained_shares(
        [moved, still], kernels_at, np.unique(positions)
    )
    margin = CHOICE_MARGIN if with_lens else CHOICE_MARGIN_FITTED
    if estimated < (1.0 - margin) * identity:
        return alignments
    log.info(
        "alignment: the frames unaligned are explained as well (%.4g against %.4g): identity",
        identity,
        estimated,
    )
    return [
        align.Alignment(
            np.eye(3), 1.0, "identity (the estimate explained no more)", model=a.model
        )
        for a in alignments
    ]
