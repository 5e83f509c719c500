"""The end of every job: deconvolve the average (tiled, clipped pixels censored) and
write the image, the optional kernel and the ``OUT.json`` sidecar.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from pipeline.core.common_area import common_area
from pipeline.core.stack_kernel import wiener_options
from pipeline.errors import InputError
from pipeline.io.exif import fits_jpeg, read_exif
from pipeline.io.icc import read_icc
from pipeline.io.orientation import stack_orientation, upright, upright_exif
from pipeline.io.write import (
    check_writable,
    commit,
    discard,
    encode_image,
    encode_json,
    stage_bytes,
)
from pipeline.jobs.options import StackOptions, StackResult
from pipeline.parallel.accumulate import clipped_pixels
from pipeline.parallel.tiling import deconvolve_tiled

log = logging.getLogger(__name__)


def check_output(output: Path, save_kernel: Path | None = None) -> None:
    """Refuse, before any work, an output (and ``--save-kernel`` file) that cannot be
    written: unknown format, missing or read-only folder, a folder, a name too long."""
    if output.suffix.lower() not in (".tif", ".tiff", ".png", ".jpg", ".jpeg"):
        raise InputError(f"output {output}: use a .tif, .png or .jpg file name")
    check_writable(output, "output")
    if save_kernel is not None:
        save_kernel = Path(save_kernel)
        if save_kernel.suffix.lower() not in (".tif", ".tiff"):
            raise InputError(f"--save-kernel {save_kernel}: use a .tif file name")
        check_writable(save_kernel, "--save-kernel")


def check_not_input(output: Path, inputs, save_kernel: Path | None = None) -> None:
    """Refuse an output path that is one of the stack's input files (it would overwrite it)."""
    resolved = {Path(f).resolve(): Path(f) for f in inputs}
    for flag, path in (("-o", output), ("--save-kernel", save_kernel)):
        if path is not None and Path(path).resolve() in resolved:
            raise InputError(
                f"{flag} {path} is one of the input frames; writing it would overwrite the "
                "frame: choose another output name"
            )


RESCALE_ABOVE = 1e4  # linear light has white at 1: far larger values are rescaled first


def restore_image(
    image,
    kernel,
    options: StackOptions,
    *,
    clipped=None,
    kernel_samples=None,
    source=None,
    max_noise=None,
    noise_limit=None,
    on_plan=None,
) -> np.ndarray:
    """Deconvolve (tiled) with clipped pixels censored out of the data term (Sec. 4.2).

    ``kernel_samples`` (the blur at several depths) can make Wiener robust to the
    residual depth dependence of the IPSF (see :func:`wiener_options`); ``max_noise``
    caps the Wiener result's noise std (per channel) where GCV's ``lam`` is not used,
    ``noise_limit`` where the gain ceiling set it (see
    :func:`pipeline.core.deconvolve.wiener._plan_wiener`); ``on_plan`` is called with the
    deconvolution's plan (:func:`pipeline.parallel.tiling.deconvolve_tiled`). Images whose
    values exceed ``RESCALE_ABOVE`` (float frames in other units) are deconvolved
    divided by their peak and scaled back, so float32 sums cannot overflow.
    ``source`` (the frames, for messages) names the input in errors.
    """
    if options.method == "multiframe":
        raise InputError(
            f"{source or 'the image'}: --method multiframe restores a focal stack from its "
            "frames; a single image (a sweep capture or a video frame) has none: use "
            "--method wiener or rl"
        )
    clipped = clipped_pixels(image) if clipped is None else clipped
    # max(-min, max) is max |x| without an |x| temporary (11 ms -> 2 ms on 3 Mpx RGB)
    peak = max(-float(np.min(image)), float(np.max(image))) if np.size(image) else 0.0
    scale = peak if peak > RESCALE_ABOVE else 1.0
    extra = {}
    if options.method == "wiener":
        extra = wiener_options(kernel, kernel_samples)
        if max_noise is not None:
            extra["max_noise"] = max_noise / scale
        if noise_limit is not None:
            extra["noise_limit"] = noise_limit / scale
    finite = np.isfinite(image)
    if not np.all(finite):
        raise InputError(
            f"{source or 'the image'}: the average of the frames holds "
            f"{int(np.count_nonzero(~finite))} non-finite values; check the frames' values"
        )
    data = image if scale == 1.0 else (np.asarray(image, np.float64) / scale).astype(image.dtype)
    result = deconvolve_tiled(  # clipped in any frame: at least the observed value
        data,
        kernel,
        method=options.method,
        tile_px=options.tile_px,
        censored=clipped,
        on_plan=on_plan,
        **extra,
    )
    if scale != 1.0:
        with np.errstate(over="ignore"):
            result = (np.asarray(result, np.float64) * scale).astype(result.dtype)
    if not np.all(np.isfinite(result)):
        where = source or "the image"
        if scale != 1.0:
            raise InputError(
                f"{where}: the frames' values reach {peak:.3g} and the restored image "
                f"overflows {result.dtype}; scale the frames (linear light has white at 1)"
            )
        raise InputError(
            f"{where}: deconvolution ({options.method}) produced non-finite values; "
            "check the frames and --blur-span-px"
        )
    return result


# below this share of the result covered by every frame, its edge-filled borders are warned of
COMMON_AREA_WARNING = 0.9


def _common_box(sidecar: dict, shape: tuple[int, int], code: int):
    """The rectangle every frame covers (:func:`pipeline.core.common_area.common_area`),
    ``(row, col, height, width)`` in the written (upright) result's pixels; ``None`` for a
    result of one frame (a sweep) or frames that share no area."""
    homographies = [f["homography"] for f in sidecar.get("frames", []) if "homography" in f]
    if len(homographies) < 2:
        return None
    found = common_area(homographies, shape)
    if found is None:
        return None
    y, x, h, w = found
    inside = np.zeros(shape, np.uint8)
    inside[y : y + h, x : x + w] = 1
    turned = upright(inside, code)
    rows, cols = np.nonzero(turned.any(axis=1))[0], np.nonzero(turned.any(axis=0))[0]
    return int(rows[0]), int(cols[0]), int(rows[-1] - rows[0] + 1), int(cols[-1] - cols[0] + 1)


def _report_common_area(output, result, box, sidecar, options) -> np.ndarray:
    """Record the area every frame covers in the sidecar (``common_area``), warn where it is
    small (strong breathing, frames moved between shots: the rest is filled from their
    edges; pcb10 86%, a loose hand 74%), and crop the result to it with ``options.crop``
    (``--crop``)."""
    y, x, h, w = box
    fraction = h * w / (result.shape[0] * result.shape[1])
    area = {"x": x, "y": y, "width": w, "height": h, "fraction": round(fraction, 4)}
    sidecar["common_area"] = area
    sidecar["cropped"] = options.crop
    if options.crop:
        return np.ascontiguousarray(result[y : y + h, x : x + w])
    if fraction < COMMON_AREA_WARNING:
        log.warning(
            "%s: every frame covers only %.0f%% of the result (focus breathing, or frames "
            "moved between shots); "
            "outside %dx%d+%d+%d it is filled from the frames' edges: pass --crop, or crop "
            "it there (the sidecar's common_area)", output, 100 * fraction, w, h, x, y,
        )  # fmt: skip
    return result


def write_result(output, result, kernel, sidecar, timings, start, options, inputs) -> StackResult:
    """Write the image, the optional kernel and ``OUTPUT.json`` as one result.

    The image and the kernel are turned upright as the first of the ``inputs`` (the frame
    files) was shot (:func:`~pipeline.io.orientation.stack_orientation`; the sidecar's
    ``orientation``), and that frame's EXIF is carried into JPEG and PNG outputs, saying
    upright, and its ICC profile into sRGB-coded ones (:mod:`pipeline.io.icc`). The
    returned result holds the image as written.

    Everything is encoded and written to temporaries first; nothing is renamed
    unless all of them were written. Then the old sidecar is removed, the kernel
    and the image are renamed into place and the sidecar last: a reader (or a
    workflow's ledger) never sees a new image with an old sidecar, and a kill
    in between leaves an image without a sidecar, which counts as unfinished.
    """
    t0 = time.perf_counter()
    output = Path(output)
    sidecar_path = output.with_name(output.name + ".json")
    staged: list[tuple[Path, Path]] = []
    code = stack_orientation(inputs)
    box = _common_box(sidecar, result.shape[:2], code)
    result = upright(result, code)
    kernel = None if kernel is None else upright(kernel, code)
    sidecar["orientation"] = code
    if box is not None:
        result = _report_common_area(output, result, box, sidecar, options)
    elif options.crop:
        log.warning("%s: --crop: the aligned frames share no area; written uncropped", output)
    exif, icc = upright_exif(read_exif(inputs[0])), read_icc(inputs[0])
    if exif is not None and output.suffix.lower() in (".jpg", ".jpeg") and not fits_jpeg(exif):
        log.warning(
            "%s: the first frame's EXIF (%d bytes) does not fit a JPEG's 64 kB APP1 segment; "
            "written without it (a PNG output carries it)", output, len(exif),
        )  # fmt: skip
        exif = None
    try:
        payload = encode_image(output, result, encoding=options.encoding, exif=exif, icc=icc)
        staged.append((stage_bytes(output, payload), output))
        if options.save_kernel is not None and kernel is not None:
            kernel_path = Path(options.save_kernel)
            payload = encode_image(kernel_path, kernel.astype(np.float32), encoding="float32")
            staged.insert(0, (stage_bytes(kernel_path, payload), kernel_path))
            sidecar["kernel"]["file"] = str(options.save_kernel)
        timings["write"] = time.perf_counter() - t0
        timings["total"] = time.perf_counter() - start
        sidecar["timings_s"] = timings
        staged.append((stage_bytes(sidecar_path, encode_json(sidecar_path, sidecar)), sidecar_path))
    except BaseException:
        discard(tmp for tmp, _ in staged)
        raise
    try:
        sidecar_path.unlink(missing_ok=True)
    except OSError as err:
        discard(tmp for tmp, _ in staged)
        raise InputError(f"{sidecar_path}: cannot replace it ({err.strerror or err})") from err
    commit(staged)
    return StackResult(output, sidecar, result)
