"""Time deconvolve() per method on a 2048x1536x3 float32 frame with a ~61 px kernel.

Usage: .venv/bin/python benchmarks/bench_deconvolve.py [--kernel ipsf|pillbox] [--methods ...]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy import signal

from pipeline import deconvolve as dc


def pillbox(radius: float, supersample: int = 8) -> np.ndarray:
    half = int(np.ceil(radius))
    side = 2 * half + 1
    c = (np.arange(side * supersample) + 0.5) / supersample - side / 2
    inside = (c[:, None] ** 2 + c[None, :] ** 2 <= radius**2).astype(float)
    k = inside.reshape(side, supersample, side, supersample).mean(axis=(1, 3))
    return k / k.sum()


def ipsf_like(half: int = 30) -> np.ndarray:
    """Radial profile ~ 1/r out to the largest blur (the shape of Eq. 6), 61 px."""
    r = np.hypot(*np.mgrid[-half : half + 1, -half : half + 1])
    k = np.where(r <= half, 1.0 / np.maximum(r, 0.5), 0.0)
    return k / k.sum()


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
