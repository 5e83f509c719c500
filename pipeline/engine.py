"""The main job as dask graphs: a focal stack or a sweep capture to an extended-DOF image.

Data flow (DESIGN.md)::

    frames -> Stack -> align (homography per frame) -> weights (Sec. 9)
      -> streaming weighted sum (dask tree reduction) -> sweep image + its IPSF
      -> deconvolve (tiled) -> output + JSON sidecar

The weighted sum is a binary tree of merges over per-frame leaves (read, warp,
weight), so at most a few frames are in memory at once whatever the stack's
length. The same graph runs on the local threaded scheduler or on a
``dask.distributed`` cluster (``scheduler="tcp://..."``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import dask
import numpy as np
from dask.callbacks import Callback

from pipeline import align, defocus, optics, psf
from pipeline.errors import InputError
from pipeline.io import read_exif, read_frame, read_preview, write_image, write_json
from pipeline.motion import constant_speed
from pipeline.profiles import Lens, load_lens
from pipeline.stack import Stack, check_frames, image_distances_mm, load_stack
from pipeline.tiling import deconvolve_tiled
from pipeline.weights import constant_speed_weights

log = logging.getLogger(__name__)

METHODS = ("wiener", "rl", "sparse")
ALIGN_MODES = ("estimate", "analytic", "none")
SATURATION = 0.999  # normalised level at and above which a pixel is treated as clipped
PREVIEW_SIDE_PX = 320  # resolution of the defocus (blur-span) fit
KERNEL_VARIANCE_SPREAD = 0.1  # Eq. 8 spread of per-depth kernels above which Wiener uses it
WIENER_EM_PASSES = 0  # Wiener's EM re-solves for clipped pixels (see wiener_options)


@dataclasses.dataclass(frozen=True)
class StackOptions:
    """Options of the main job (the ``flexdof stack`` flags)."""

    lens: str | None = None
    method: str = "wiener"
    align: str = "estimate"
    encoding: str | None = None
    blur_span_px: float | None = None
    tile_px: int = 1024
    align_max_side_px: int = 768
    save_kernel: Path | None = None
    sweep_ends: str = "full"

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise InputError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if self.align not in ALIGN_MODES:
            raise InputError(f"align must be one of {', '.join(ALIGN_MODES)}, got {self.align!r}")
        if self.blur_span_px is not None and not self.blur_span_px > 0:
            raise InputError(f"blur_span_px must be > 0, got {self.blur_span_px!r}")


@dataclasses.dataclass
class StackResult:
    output: Path
    sidecar: dict
    image: np.ndarray


Progress = Callable[[str, int, int], None]


def _no_progress(stage: str, done: int, total: int) -> None:
    """Default progress sink: nothing."""


# ----------------------------------------------------------------------------- frame leaves
def _warped_leaf(path: str, homography, weight: float, shape):
    """Read one frame, warp it onto the reference, weight it; its clipped pixels; decode time."""
    t0 = time.perf_counter()
    frame = read_frame(path)
    read_s = time.perf_counter() - t0
    if homography is not None:
        frame = align.warp(frame, homography, shape)
    clipped = clipped_pixels(frame)
    frame *= np.float32(weight)
    return frame, clipped, read_s


def _merge(a, b):
    """Sum two partial weighted sums (in place), OR their clipped masks, add decode times."""
    np.add(a[0], b[0], out=a[0])  # each partial sum feeds exactly one merge: safe in place
    np.logical_or(a[1], b[1], out=a[1])
    return a[0], a[1], a[2] + b[2]


def weighted_sum_graph(files: Sequence[Path], homographies, weights, shape):
    """A dask graph for ``sum_i w_i warp(frame_i)`` as a binary tree of merges.

    Returns a Delayed yielding ``(sum, clipped_any_frame, decode_seconds)``.
    """
    level = [
        dask.delayed(_warped_leaf, pure=True)(str(path), h, float(w), tuple(shape))
        for path, h, w in zip(files, homographies, weights)
        if w > 0
    ]
    while len(level) > 1:
        merged = [dask.delayed(_merge)(level[i], level[i + 1]) for i in range(0, len(level) - 1, 2)]
        if len(level) % 2:
            merged.append(level[-1])
        level = merged
    return level[0]


class _TaskProgress(Callback):
    """Counts finished tasks whose key starts with ``prefix`` (local schedulers only)."""

    def __init__(self, prefix: str, report: Callable[[int], None]) -> None:
        super().__init__()
        self.prefix, self.report, self.done = prefix, report, 0

    def _posttask(self, key, result, dsk, state, worker_id) -> None:
        name = key[0] if isinstance(key, tuple) else key
        if str(name).startswith(self.prefix):
            self.done += 1
            self.report(self.done)


# ----------------------------------------------------------------------------- scheduler
@contextlib.contextmanager
def scheduler_context(scheduler: str | None = None, threads: int | None = None):
    """Local threads (default) or a dask.distributed cluster at ``scheduler`` (tcp://...)."""
    if threads is not None and (
        isinstance(threads, bool) or not isinstance(threads, int) or threads < 1
    ):
        raise InputError(f"--threads must be a whole number >= 1, got {threads!r}")
    if scheduler:
        from distributed import Client

        try:
            client = Client(scheduler, timeout="10s", set_as_default=False)
        except OSError as err:
            raise InputError(f"--scheduler {scheduler}: cannot connect ({err})") from err
        with client, dask.config.set(scheduler=client):
            yield
    else:
        with dask.config.set(scheduler="threads", num_workers=threads):
            yield


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


def positions_from_scales(scales: np.ndarray) -> tuple[np.ndarray, str]:
    """Focus coordinate from measured magnifications (``scale = p_i / p_ref``).

    Used when they rise or fall steadily and span more than 0.5%; otherwise the
    frames are taken as evenly spaced in focus (their index), the usual capture.
    """
    s = np.asarray(scales, dtype=np.float64)
    if s.size >= 3 and np.ptp(s) > 0.005:
        steps = np.diff(s)
        if (
            np.all(steps > 0)
            or np.all(steps < 0)
            or abs(np.corrcoef(s, np.arange(s.size))[0, 1]) > 0.97
        ):
            return s, "magnification"
    return np.arange(s.size, dtype=np.float64), "frame-order"


# ----------------------------------------------------------------------------- kernels
def stack_kernel(
    positions: np.ndarray,
    weights: np.ndarray,
    *,
    lens: Lens | None,
    absolute: bool,
    blur_span_px: float | None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """The IPSF of the weighted average (Sec. 9), per-depth samples of it, and a summary.

    With a lens and absolute image distances, a point focused at ``v`` is blurred
    in frame ``i`` by ``a |v - p_i| / v`` (Eq. 2); the stack-average kernel is
    compared with the single analytic kernel of a constant-speed sweep over the
    same range (Eq. 6, corrected) and the one closer (Eq. 8) to the per-depth
    kernels is kept. Otherwise blur is ``D |x_i - x|`` with the blur span ``D``.
    """
    model = lens.psf_model if lens else "pillbox"
    g = lens.gaussian_g if lens else 1.0
    if lens is not None and absolute:
        a_px = lens.aperture_mm / lens.pixel_pitch_mm

        def blur(p, v):
            return a_px * np.abs(v - p) / v  # Eq. 2

        span = float(blur(positions.max(), positions.min()))
    else:
        if blur_span_px is None:
            raise InputError("internal: no blur span for a stack without absolute positions")
        width = max(np.ptp(positions), 1e-300)

        def blur(p, x):
            return blur_span_px * np.abs(p - x) / width

        span = float(blur_span_px)
    kernel, per_position = psf.focal_stack_psf(positions, weights, blur, model=model, gaussian_g=g)
    summary = {"size": int(kernel.shape[0]), "source": "stack-average", "blur_span_px": span}
    if lens is not None and absolute and np.ptp(positions) > 0:
        p_lo, p_hi = float(positions.min()), float(positions.max())
        middle = optics.focus_distance(lens.focal_length_mm, 0.5 * (p_lo + p_hi))
        sweep = constant_speed(p_lo, p_hi - p_lo, 1.0)
        analytic = psf.integrated_psf(lens, middle, sweep, size=kernel.shape[0])
        d_avg = np.mean([psf.dissimilarity(k, kernel) for k in per_position])
        d_eq6 = np.mean([psf.dissimilarity(k, analytic) for k in per_position])
        summary["dissimilarity"] = {"stack-average": float(d_avg), "analytic-eq6": float(d_eq6)}
        if d_eq6 < d_avg:
            kernel, summary["source"] = analytic, "analytic-eq6"
    spread = [psf.dissimilarity(k, kernel) for k in per_position]
    summary["depth_invariance_eq8"] = {"mean": float(np.mean(spread)), "max": float(np.max(spread))}
    return kernel, per_position[::4], summary


# ----------------------------------------------------------------------------- previews
def read_previews(
    files: Sequence[Path], max_side_px: int, progress: Progress = _no_progress
) -> list[np.ndarray]:
    """Reduced grey copies of every frame, decoded in parallel (one cheap decode each)."""
    with _TaskProgress("read_preview", lambda done: progress("preview", done, len(files))):
        return list(dask.compute(*[dask.delayed(read_preview)(f, max_side_px) for f in files]))


def _blur_fit_previews(previews, alignments, full_shape) -> tuple[list[np.ndarray], float]:
    """Aligned copies at the defocus-fit resolution, and their downscale factor."""
    factor = max(full_shape[:2]) / PREVIEW_SIDE_PX
    small = []
    for preview, alignment in zip(previews, alignments):
        size = (max(1, round(full_shape[1] / factor)), max(1, round(full_shape[0] / factor)))
        reduced = cv2.resize(preview, size, interpolation=cv2.INTER_AREA)
        h = align.rescale_homography(alignment.homography, full_shape[:2], reduced.shape)
        small.append(align.warp(reduced, h, reduced.shape))
    return small, factor


# ----------------------------------------------------------------------------- main job
def process_stack(
    paths: Sequence[str | Path] | str | Path,
    output: str | Path,
    options: StackOptions = StackOptions(),
    *,
    progress: Progress = _no_progress,
) -> StackResult:
    """Focal stack (or sweep capture) -> extended-DOF image at ``output`` + ``output.json``.

    Runs on the current dask scheduler (see :func:`scheduler_context`). Nothing
    is written unless the whole job succeeds; the image and its sidecar are each
    written atomically.
    """
    output = Path(output)
    check_output(output)
    timings: dict[str, float] = {}
    start = time.perf_counter()
    stack = load_stack(paths)
    lens = _resolve_lens(stack, options)
    if stack.kind == "sweep":
        from pipeline.sweep import process_sweep_stack

        return process_sweep_stack(stack, lens, output, options, progress=progress)
    info = check_frames(stack)
    shape = info.shape
    n = len(stack)
    positions, absolute = _sidecar_positions(stack, lens)

    t0 = time.perf_counter()
    needs_fit = not (lens is not None and absolute) and options.blur_span_px is None
    previews = None
    if options.align == "estimate" or needs_fit:
        previews = read_previews(stack.files, options.align_max_side_px, progress)
    progress("align", 0, 1)
    alignments = _align(stack, options, positions, absolute, previews, shape)
    progress("align", 1, 1)
    timings["align"] = time.perf_counter() - t0

    positions_source = stack.positions_source or "stack.toml"
    if positions is None:
        positions, positions_source = positions_from_scales(np.array([a.scale for a in alignments]))
        absolute = False
    weights = constant_speed_weights(positions, ends=options.sweep_ends)

    t0 = time.perf_counter()
    blur_span = options.blur_span_px
    if needs_fit:
        if n < 2:
            raise InputError(
                f"{stack.files[0]}: a focal stack needs at least two frames focused at different "
                "depths (got one); for a single sweep capture use flexdof sweep"
            )
        if np.ptp(positions) == 0:
            raise InputError(
                f"{stack.base_dir}: all {n} frames have the same focus position: nothing to sweep"
            )
        small, factor = _blur_fit_previews(previews, alignments, shape)
        blur_span = defocus.estimate_blur_span(small, positions, downscale=factor)
        log.info("estimated blur span: %.1f px across the stack", blur_span)
    kernel, kernel_samples, kernel_summary = stack_kernel(
        positions, weights, lens=lens, absolute=absolute, blur_span_px=blur_span
    )
    timings["kernel"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    graph = weighted_sum_graph(
        stack.files,
        [None if options.align == "none" else a.homography for a in alignments],
        weights,
        shape,
    )
    frames_used = int(np.count_nonzero(weights > 0))
    progress("accumulate", 0, frames_used)
    with _TaskProgress("_warped_leaf", lambda done: progress("accumulate", done, frames_used)):
        ((average, clipped, read_s),) = dask.compute(graph)
    progress("accumulate", frames_used, frames_used)
    timings["accumulate"] = time.perf_counter() - t0
    timings["read"] = read_s  # full-resolution decoding, summed over worker threads

    progress("deconvolve", 0, 1)
    t0 = time.perf_counter()
    result = restore_image(average, kernel, options, clipped=clipped, kernel_samples=kernel_samples)
    timings["deconvolve"] = time.perf_counter() - t0
    progress("deconvolve", 1, 1)
    exif = read_exif(stack.files[0])
    frames_meta = [
        {
            "file": str(frame.file.name),
            "position": float(p),
            "weight": float(w),
            "scale": float(a.scale),
            "homography": a.homography.tolist(),
            "alignment": a.method if a.ok else f"fallback: {a.message}",
        }
        for frame, p, w, a in zip(stack.frames, positions, weights, alignments)
    ]
    if absolute:
        for meta, p in zip(frames_meta, positions):
            meta["image_distance_mm"] = float(p)
    sidecar = {
        "version": 1,
        "inputs": [str(f) for f in stack.files],
        "lens": (lens.source or lens.name) if lens else None,
        "method": options.method,
        "align": options.align,
        "positions_source": positions_source,
        "frames": frames_meta,
        "kernel": kernel_summary,
        "partial_stack": stack.partial,
    }
    return write_result(output, result, kernel, sidecar, timings, start, options, exif)


def check_output(output: Path) -> None:
    """Refuse an output whose folder is missing or whose format is unknown, before any work."""
    if not output.parent.is_dir():
        raise InputError(f"output {output}: the folder {output.parent} does not exist")
    if output.suffix.lower() not in (".tif", ".tiff", ".png", ".jpg", ".jpeg"):
        raise InputError(f"output {output}: use a .tif, .png or .jpg file name")


def _align(stack, options, positions, absolute, previews, shape):
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
    estimated = align.estimate_alignment(previews, max_side_px=options.align_max_side_px)
    alignments = []
    for path, a in zip(stack.files, estimated):
        if not a.ok:
            log.warning("frame %s: alignment fell back (%s)", path.name, a.message)
        h = align.rescale_homography(a.homography, previews[0].shape, shape[:2])
        alignments.append(dataclasses.replace(a, homography=h))
    return alignments


def clipped_pixels(image: np.ndarray) -> np.ndarray:
    """Pixels at the clipping level in any channel."""
    return np.any(image >= SATURATION, axis=-1) if image.ndim == 3 else image >= SATURATION


def wiener_options(kernel, kernel_samples=None) -> dict:
    """The main job's Wiener settings (measured with ``flexdof bench accuracy``).

    * No EM passes for clipped pixels: they bought < 0.1 dB with 25% of pixels
      clipped, for +80% time (rl and sparse mask clipped pixels out of the data term).
    * The kernel variance of ``kernel_samples`` only when the IPSF's depth dependence is
      large, their mean Eq. 8 dissimilarity to ``kernel`` above ``KERNEL_VARIANCE_SPREAD``:
      +0.5-0.9 dB on 3-frame stacks (spread 0.4-1.1), but -0.14-0.22 dB and +25% time on
      dense stacks (spread <= 0.03), where it only adds estimation noise.
    """
    if kernel_samples is not None:
        spread = np.mean([psf.dissimilarity(k, kernel) for k in kernel_samples])
        kernel_samples = kernel_samples if spread > KERNEL_VARIANCE_SPREAD else None
    return {"saturation_passes": WIENER_EM_PASSES, "kernel_samples": kernel_samples}


def restore_image(
    image, kernel, options: StackOptions, *, clipped=None, kernel_samples=None
) -> np.ndarray:
    """Deconvolve (tiled) with clipped pixels censored out of the data term (Sec. 4.2).

    ``kernel_samples`` (the blur at several depths) can make Wiener robust to the
    residual depth dependence of the IPSF (see :func:`wiener_options`).
    """
    clipped = clipped_pixels(image) if clipped is None else clipped
    extra = wiener_options(kernel, kernel_samples) if options.method == "wiener" else {}
    result = deconvolve_tiled(  # clipped in any frame: at least the observed value
        image, kernel, method=options.method, tile_px=options.tile_px, censored=clipped, **extra
    )
    if not np.all(np.isfinite(result)):
        raise InputError("deconvolution produced non-finite values; try --method rl")
    return result


def write_result(output, result, kernel, sidecar, timings, start, options, exif) -> StackResult:
    """Write the image, the optional kernel and ``OUTPUT.json`` (each atomically)."""
    t0 = time.perf_counter()
    write_image(output, result, encoding=options.encoding, exif=exif)
    if options.save_kernel is not None:
        write_image(options.save_kernel, kernel.astype(np.float32), encoding="float32")
        sidecar["kernel"]["file"] = str(options.save_kernel)
    timings["write"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - start
    sidecar["timings_s"] = timings
    write_json(output.with_name(output.name + ".json"), sidecar)
    return StackResult(output, sidecar, result)
