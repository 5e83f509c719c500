"""What Wiener's EM passes for clipped pixels buy, and cost (the engine runs 0 passes).

    python tests/benchmarks/bench_saturation.py

A bright image (a quarter of its pixels clipped after blurring with a 7-frame
Sec. 9 kernel, plus noise) deconvolved with 0, 1 and 3 passes: PSNR overall and
on the unclipped pixels, and the time of each on a 2048x1536 pcb7 frame.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from scipy.signal import fftconvolve
from skimage import data

from pipeline import deconvolve as dc
from pipeline.engine import clipped_pixels, stack_kernel
from pipeline.io import read_frame
from pipeline.quality import psnr
from pipeline.weights import constant_speed_weights

PCB7 = Path(__file__).resolve().parents[3] / "shared/data/focusstack-pcb/pcb7/pcb_004.jpg"


def main() -> None:
    x = np.linspace(0, 1, 7)
    kernel, samples, _ = stack_kernel(
        x, constant_speed_weights(x, ends="full"), lens=None, absolute=False, blur_span_px=30
    )
    sharp = (data.astronaut().astype(np.float32) / 255) ** 2.2 * 1.6
    h = kernel.shape[0] // 2
    blurred = np.stack(
        [
            fftconvolve(np.pad(sharp[..., c], h, mode="reflect"), kernel, mode="valid")
            for c in range(3)
        ],
        axis=-1,
    ).astype(np.float32)
    noise = np.random.default_rng(0).normal(0, 0.005, blurred.shape).astype(np.float32)
    observed = np.minimum(blurred, 1.0) + noise
    clipped = blurred.max(axis=-1) >= 1.0
    print(f"clipped fraction {clipped.mean():.2f}")
    frame = read_frame(PCB7)
    frame_clipped = clipped_pixels(frame)
    for passes in (0, 1, 3):
        options = {"censored": clipped, "saturation_passes": passes, "kernel_samples": samples}
        restored = dc.deconvolve(observed, kernel, method="wiener", **options)
        t0 = time.perf_counter()
        dc.deconvolve(
            frame,
            kernel,
            method="wiener",
            censored=frame_clipped,
            saturation_passes=passes,
            kernel_samples=samples,
        )
        seconds = time.perf_counter() - t0
        whole = psnr(np.minimum(restored, 1.6) / 1.6, sharp / 1.6)
        kept = psnr(restored[~clipped] / 1.6, sharp[~clipped] / 1.6)
        print(
            f"passes {passes}: PSNR {whole:.2f} dB (unclipped {kept:.2f} dB), "
            f"2048x1536x3 in {seconds:.2f} s"
        )


if __name__ == "__main__":
    main()
