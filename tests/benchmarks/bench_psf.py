"""IPSF construction time (issue 2): a 101x101 analytic kernel and a numeric 3-segment one.

    python tests/benchmarks/bench_psf.py [--repeat 5]

Times, best of ``--repeat``: the analytic Eq. 6 and Eq. 7 kernels (pixel-area
integrated) of the Sec. 4.1 sweep at 750 mm on a 101x101 grid; the numeric Eq. 5
kernel of a 3-segment motion (sweep, pause, reversal) on the same grid; and a
single lens PSF for scale. Also prints the analytic/numeric L1 difference.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from pipeline.core import psf
from pipeline.core.motion import Profile, constant_speed
from pipeline.io.profiles import load_lens


def best_time(fn, repeat: int) -> tuple[float, np.ndarray]:
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    lens = load_lens("fujinon-12.5mm-f1.4-sony-1-3in")
    sweep = constant_speed(12.5, 1.0, 0.36)
    three = Profile([0.0, 0.15, 0.25, 0.4], [12.5, 12.8, 12.8, 12.6])
    rows = []
    for label, fn in [
        ("analytic Eq. 6, 101x101", lambda: psf.integrated_psf(lens, 750.0, sweep, size=101)),
        (
            "analytic Eq. 7, 101x101",
            lambda: psf.integrated_psf(lens, 750.0, sweep, size=101, model="gaussian"),
        ),
        (
            "numeric Eq. 5, 3 segments, 101x101",
            lambda: psf.integrated_psf(lens, 750.0, three, size=101, method="numeric"),
        ),
        ("analytic, 3 segments, 101x101", lambda: psf.integrated_psf(lens, 750.0, three, size=101)),
        ("lens PSF (Eq. 3), 101x101", lambda: psf.lens_psf(lens, 750.0, 12.6, size=101)),
    ]:
        seconds, kernel = best_time(fn, args.repeat)
        rows.append((label, seconds, kernel))
        print(f"{label:<38} {seconds * 1e3:8.1f} ms")
    l1 = np.abs(rows[2][2] - rows[3][2]).sum()
    print(f"3-segment analytic vs numeric L1 difference: {l1:.2e}")


if __name__ == "__main__":
    main()
