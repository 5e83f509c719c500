"""The end of every job: deconvolve the average (tiled, clipped pixels censored) and
write the image, the optional kernel and the ``OUT.json`` sidecar.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from pipeline.core.stack_kernel import wiener_options
from pipeline.errors import InputError
from pipeline.io.write import write_image, write_json
from pipeline.jobs.options import StackOptions, StackResult
from pipeline.parallel.accumulate import clipped_pixels
from pipeline.parallel.tiling import deconvolve_tiled


def check_output(output: Path) -> None:
    """Refuse an output whose folder is missing or whose format is unknown, before any work."""
    if not output.parent.is_dir():
        raise InputError(f"output {output}: the folder {output.parent} does not exist")
    if output.suffix.lower() not in (".tif", ".tiff", ".png", ".jpg", ".jpeg"):
        raise InputError(f"output {output}: use a .tif, .png or .jpg file name")


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
    if options.save_kernel is not None and kernel is not None:
        write_image(options.save_kernel, kernel.astype(np.float32), encoding="float32")
        sidecar["kernel"]["file"] = str(options.save_kernel)
    timings["write"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - start
    sidecar["timings_s"] = timings
    write_json(output.with_name(output.name + ".json"), sidecar)
    return StackResult(output, sidecar, result)
