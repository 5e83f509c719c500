"""Time deconvolve() per method on a 2048x1536x3 float32 frame with a ~61 px kernel.

Usage: .venv/bin/python tests/benchmarks/bench_deconvolve.py [--kernel ipsf|pillbox] [--methods ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np
from scipy import signal

from pipeline.core import deconvolve as dc
from pipeline.core import psf
from pipeline.core.motion import constant_speed
from pipeline.io.profiles import load_lens


def pillbox(radius: float) -> np.ndarray:
    """Eq. 3 rasterised exactly (disk areas)."""
    return psf.raster_pillbox(2 * radius, int(np.ceil(radius)))


def ipsf_like(size: int = 61) -> np.ndarray:
    """The Sec. 4.1 EDOF IPSF (Eq. 6) at 750 mm, scaled to ``size`` px by the pixel pitch."""
    lens = load_lens("fujinon-12.5mm-f1.4-sony-1-3in")
    natural = psf.integrated_psf(lens, 750.0, constant_speed(12.5, 1.0, 0.36)).shape[0]
    lens = dataclasses.replace(lens, pixel_pitch_um=lens.pixel_pitch_um * natural / size)
    return psf.integrated_psf(lens, 750.0, constant_speed(12.5, 1.0, 0.36), size=size)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--kernel", choices=["ipsf", "pillbox"], default="ipsf")
    ap.add_argument("--methods", nargs="+", default=["wiener", "rl", "sparse"])
    args = ap.parse_args()
    k = ipsf_like() if args.kernel == "ipsf" else pillbox(30.0)
    rng = np.random.default_rng(0)
    x = signal.fftconvolve(rng.uniform(0, 1, (1552, 2064, 3)), np.ones((17, 17, 1)) / 289, "valid")
    y = np.stack([signal.fftconvolve(x[..., c], k, "same") for c in range(3)], -1)
    y = (y + rng.normal(0, 0.01, y.shape)).astype(np.float32)
    print(f"image {y.shape} {y.dtype}, kernel {k.shape} ({args.kernel})")
    for method in args.methods:
        t0 = time.perf_counter()
        p = dc.plan(y, k, method=method)
        t1 = time.perf_counter()
        out = dc.restore(y, p)
        t2 = time.perf_counter()
        assert out.dtype == np.float32 and np.all(np.isfinite(out))
        print(f"{method:7s} depth {p.depth:5d}  plan {t1 - t0:6.2f} s  restore {t2 - t1:6.2f} s")


if __name__ == "__main__":
    main()
