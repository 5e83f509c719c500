"""Focus-sweep captures (Sec. 4, 8): one exposure taken while the focus moves.

A sweep image is deconvolved with the IPSF of its motion (Eq. 5; Eq. 6/7 for a
constant speed), averaged over the swept depths so that one kernel serves the
whole scene. EDOF video (Sec. 4.2) alternates the sweep direction from frame
to frame; a constant-speed IPSF does not depend on the direction, so every
frame uses the same kernel and frames are deconvolved in parallel.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from pathlib import Path

import cv2
import dask
import numpy as np

from pipeline.core import optics, psf, spectra, validate
from pipeline.core.colour import linear_to_srgb, srgb_to_linear
from pipeline.core.lens import Lens
from pipeline.core.motion import Profile, constant_speed
from pipeline.errors import InputError
from pipeline.io.probe import frame_info
from pipeline.io.read import read_frame
from pipeline.io.stackfile import Stack, sweep_profile
from pipeline.jobs.options import (
    Progress,
    StackOptions,
    StackResult,
    _no_progress,
    megapixels,
)
from pipeline.jobs.result import check_output, restore_image, write_result
from pipeline.parallel.scheduler import _TaskProgress

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".m4v")


def sweep_kernel(
    lens: Lens, profile: Profile, *, depths: int = 9
) -> tuple[np.ndarray, np.ndarray, dict]:
    """IPSF of a sweep averaged over depths spread uniformly in image distance over its range.

    Each depth's kernel is :func:`pipeline.core.psf.integrated_psf` (Eq. 5, exact for the
    piecewise-linear motion); the summary reports their spread by Eq. 8.
    """
    p_lo, p_hi = profile.range_mm
    if p_hi - p_lo <= 0:
        raise InputError("the sweep does not move the focus (start == end): nothing to deconvolve")
    v = np.linspace(p_lo, p_hi, depths + 2)[1:-1]  # inside the range, ends excluded
    u = [optics.focus_distance(lens.focal_length_mm, vi) for vi in v]
    size = max(psf.integrated_psf(lens, d, profile).shape[0] for d in (u[0], u[-1]))
    kernels = [psf.integrated_psf(lens, d, profile, size=size) for d in u]
    kernel = np.mean(kernels, axis=0)
    kernel /= kernel.sum()
    spread = [spectra.dissimilarity(k, kernel) for k in kernels]
    return (
        kernel,
        np.array(kernels),
        {
            "size": int(size),
            "source": "ipsf-depth-average",
            "depths_mm": [d if np.isfinite(d) else "inf" for d in u],
            "depth_invariance_eq8": {"mean": float(np.mean(spread)), "max": float(np.max(spread))},
        },
    )


def profile_from_range(lens: Lens, near_mm: float, far_mm: float, exposure_s: float) -> Profile:
    """Constant-speed sweep of the focal plane from ``far_mm`` to ``near_mm`` (Sec. 4.1)."""
    validate.positive("exposure_s", exposure_s)
    start = optics.image_distance(lens.focal_length_mm, far_mm)
    end = optics.image_distance(lens.focal_length_mm, near_mm)
    if not end > start:
        raise InputError(f"--near ({near_mm} mm) must be closer than --far ({far_mm} mm)")
    return constant_speed(start, (end - start) / exposure_s, exposure_s)


def check_sweep_size(path: Path, lens: Lens, profile: Profile, options: StackOptions) -> None:
    """Before any work: the capture's size (8 px to ``max_pixels``) and a swept blur no
    larger than the frame's diagonal (the kernel grows with it)."""
    info = frame_info(path)
    rows, cols = info.rows, info.cols
    if min(rows, cols) < 8:
        raise InputError(f"{path}: the image is {cols}x{rows} px; flexdof needs at least 8x8 px")
    if rows * cols > options.max_pixels:
        raise InputError(
            f"{path}: the image is {cols}x{rows} px ({megapixels(rows * cols)} Mpx), more than the "
            f"limit of {megapixels(options.max_pixels)} Mpx; raise it with --max-pixels"
        )
    p_lo, p_hi = profile.range_mm
    span = float(lens.blur_px(p_lo, p_hi))  # Eq. 2: a point focused at one end, seen at the other
    diagonal = float(np.hypot(rows, cols))
    if not np.isfinite(span) or span > diagonal:
        raise InputError(
            f"{path}: the sweep ({p_lo:.4g} to {p_hi:.4g} mm) blurs by up to {span:.4g} px, more "
            f"than the image's diagonal ({diagonal:.0f} px); check the sweep's ends and the lens"
        )


def process_sweep_stack(
    stack: Stack,
    lens: Lens | None,
    output: Path,
    options: StackOptions,
    *,
    progress: Progress = _no_progress,
) -> StackResult:
    """A stack directory whose stack.toml is of kind "sweep"."""
    if lens is None:
        raise InputError(f"{stack.base_dir}: a sweep capture needs a lens (stack.toml or --lens)")
    profile = sweep_profile(stack, lens)
    options = dataclasses.replace(options, white=stack.white)  # with --white's, by load()
    return process_sweep_image(stack.sweep.file, lens, profile, output, options, progress=progress)


def process_sweep_image(
    path: Path,
    lens: Lens,
    profile: Profile,
    output: Path,
    options: StackOptions,
    *,
    kernel_info=None,
    progress: Progress = _no_progress,
) -> StackResult:
    """Deconvolve one sweep capture; writes ``output`` and ``output.json``."""
    check_output(output, options.save_kernel)
    if kernel_info is None:
        check_sweep_size(path, lens, profile, options)
    start = time.perf_counter()
    progress("kernel", 0, 1)
    kernel, samples, summary = kernel_info or sweep_kernel(lens, profile)
    timings = {"kernel": time.perf_counter() - start}
    progress("kernel", 1, 1)
    t0 = time.perf_counter()
    image = read_frame(path, white=options.white)
    timings["read"] = time.perf_counter() - t0
    progress("deconvolve", 0, 1)
    t0 = time.perf_counter()
    result = restore_image(image, kernel, options, kernel_samples=samples, source=str(path))
    timings["deconvolve"] = time.perf_counter() - t0
    progress("deconvolve", 1, 1)
    sidecar = {
        "version": 1,
        "inputs": [str(path)],
        "lens": lens.source or lens.name,
        "method": options.method,
        "sweep": {"image_distance_mm": list(profile.range_mm), "exposure_s": profile.exposure_s},
        "kernel": summary,
        "white": options.white,
    }
    return write_result(output, result, kernel, sidecar, timings, start, options, [path])


def process_sweep_sequence(
    paths: Sequence[Path],
    lens: Lens,
    profile: Profile,
    out_dir: Path,
    options: StackOptions,
    *,
    progress: Progress = _no_progress,
) -> list[Path]:
    """Deconvolve a sequence of sweep images (EDOF video frames) in parallel into ``out_dir``."""
    if not out_dir.is_dir():
        raise InputError(f"output {out_dir}: for several inputs give an existing folder")
    kernel_info = sweep_kernel(lens, profile)
    suffix = ".tif" if options.encoding else ".png"
    tasks = [
        dask.delayed(process_sweep_image)(
            Path(p),
            lens,
            profile,
            out_dir / f"{Path(p).stem}_edof{suffix}",
            options,
            kernel_info=kernel_info,
        )
        for p in paths
    ]
    progress("deconvolve", 0, len(tasks))
    with _TaskProgress("process_sweep_image", lambda n: progress("deconvolve", n, len(tasks))):
        return [r.output for r in dask.compute(*tasks)]


def process_sweep_video(
    path: Path,
    lens: Lens,
    profile: Profile,
    output: Path,
    options: StackOptions,
    *,
    batch: int = 4,
    progress: Progress = _no_progress,
) -> int:
    """Deconvolve every frame of an EDOF video (Sec. 4.2) into a video; returns the frame count.

    Frames are read in batches of ``batch`` and deconvolved in parallel; the
    video is written to a temporary file and renamed when complete.
    """
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise InputError(f"{path}: cannot open it as a video")
    fps = capture.get(cv2.CAP_PROP_FPS) or 25.0
    total = int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) or 0
    kernel, samples, _ = sweep_kernel(lens, profile)
    tmp = output.with_name(f".{output.stem}.partial{output.suffix}")
    writer = None
    count = 0
    try:
        while True:
            frames = []
            for _ in range(batch):
                ok, frame = capture.read()
                if not ok:
                    break
                frames.append(srgb_to_linear(frame[..., ::-1].astype(np.float32) / 255.0))
            if not frames:
                break
            restored = dask.compute(
                *[
                    dask.delayed(restore_image)(f, kernel, options, kernel_samples=samples)
                    for f in frames
                ]
            )
            for image in restored:
                encoded = np.round(linear_to_srgb(np.clip(image, 0, 1)) * 255).astype(np.uint8)
                if writer is None:
                    fourcc = cv2.VideoWriter_fourcc(
                        *("mp4v" if output.suffix != ".avi" else "MJPG")
                    )
                    writer = cv2.VideoWriter(str(tmp), fourcc, fps, encoded.shape[1::-1])
                    if not writer.isOpened():
                        raise InputError(
                            f"{output}: cannot write this video format; use .mp4 or .avi"
                        )
                writer.write(np.ascontiguousarray(encoded[..., ::-1]))
                count += 1
                progress("deconvolve", count, max(total, count))
        if count == 0:
            raise InputError(f"{path}: the video has no frames")
        writer.release()
        writer = None
        tmp.replace(output)
    finally:
        capture.release()
        if writer is not None:
            writer.release()
        tmp.unlink(missing_ok=True)
    return count
