"""Regenerate the committed reference arrays (run from the repository root)::

    python tests/data/reference/make_references.py

Only when a change is meant to alter these outputs; say so in the commit. The inputs
(``comet_input.npz``) are never regenerated unless missing: the outputs are compared
on the same data forever.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import ndimage, signal

HERE = Path(__file__).resolve().parent
METHODS = {
    "wiener": {"noise_sigma": 2e-3},
    "rl": {"iterations": 40, "noise_sigma": 2e-3},
    "sparse": {"iterations": 40, "noise_sigma": 2e-3},
}


def make_input() -> None:
    path = HERE / "comet_input.npz"
    if path.exists():
        return
    rng = np.random.default_rng(11)
    x = ndimage.gaussian_filter(rng.uniform(0, 1, (40, 40)), 1.0)
    x = 0.1 + 0.8 * (x - x.min()) / np.ptp(x)
    x[12:28, 18:21] = 0.95
    k = np.zeros((7, 7))
    k[3, 3] = 0.4
    k[3, 4:7] = [0.2, 0.12, 0.08]
    k[4:7, 4:7] += np.diag([0.1, 0.06, 0.04])
    k /= k.sum()
    big = np.pad(x, 7, mode="reflect")
    y = signal.fftconvolve(big, k, mode="same")[7:-7, 7:-7] + 2e-3 * rng.standard_normal(x.shape)
    np.savez_compressed(path, sharp=x.astype(np.float32), blurred=y.astype(np.float32), kernel=k)


def main() -> None:
    from pipeline.core import deconvolve as dc
    from pipeline.core import psf
    from pipeline.core.motion import constant_speed
    from pipeline.io.profiles import load_lens

    make_input()
    data = np.load(HERE / "comet_input.npz")
    for method, options in METHODS.items():
        out = dc.deconvolve(data["blurred"], data["kernel"], method=method, **options)
        np.savez_compressed(HERE / f"comet_{method}.npz", restored=out.astype(np.float32))
    lens = load_lens("fujinon-12.5mm-f1.4-sony-1-3in")
    sweep = constant_speed(12.5, 1.0, 0.36)  # Sec. 4.1
    kernels = {f"u{int(u)}": psf.integrated_psf(lens, u, sweep, size=31) for u in (450.0, 750.0)}
    np.savez_compressed(HERE / "ipsf_sec41.npz", **kernels)


if __name__ == "__main__":
    main()
