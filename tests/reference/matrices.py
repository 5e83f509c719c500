"""Wiener deconvolution's GCV as explicit linear algebra on small periodic images (no FFT):
circulant convolution and forward-difference matrices, the influence matrix
``A = H (H^T H + C + lam D^T D)^-1 H^T`` and, from it, Craven & Wahba's GCV score
``N |(I - A) y|^2 / tr(I - A)^2`` and noise ``sqrt(|(I - A) y|^2 / tr(I - A))``. The
references of ``tests/test_gcv.py`` and ``tests/test_gcv_mutation_kills.py``.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

DX = np.array([[0.0, -1.0, 1.0]])  # forward differences, centred like a kernel
DY = DX.T


def circulant(kernel: np.ndarray, shape) -> np.ndarray:
    """Matrix of periodic convolution with ``kernel`` (centred) on images of ``shape``,
    by explicit loops."""
    rows, cols = shape
    h = np.zeros((rows * cols, rows * cols))
    kh, kw = kernel.shape
    for r in range(rows):
        for c in range(cols):
            for i in range(kh):
                for j in range(kw):
                    src = ((r - (i - kh // 2)) % rows) * cols + (c - (j - kw // 2)) % cols
                    h[r * cols + c, src] += kernel[i, j]
    return h


def influence(kernel: np.ndarray, shape, lam: float, samples=None) -> np.ndarray:
    """``A`` for ``kernel`` on a periodic ``shape``; with ``samples`` (kernels at other
    depths) ``C`` is the mean of ``(H_s - H)^T (H_s - H)`` (the kernel variance), else 0."""
    h = circulant(kernel, shape)
    c = 0.0
    if samples is not None:
        diffs = [circulant(s, shape) - h for s in samples]
        c = sum(d.T @ d for d in diffs) / len(diffs)
    dx, dy = circulant(DX, shape), circulant(DY, shape)
    return h @ np.linalg.solve(h.T @ h + c + lam * (dx.T @ dx + dy.T @ dy), h.T)


def gcv_and_noise(y_periodic: np.ndarray, a: np.ndarray) -> tuple[float, float, float]:
    """GCV score, Wahba's noise and ``tr(I - A)`` of the influence matrix ``a`` on the image
    ``y_periodic`` (its mean taken out: the regulariser leaves the mean alone)."""
    flat = y_periodic.ravel() - y_periodic.mean()
    residual = flat - a @ flat
    rr = float(residual @ residual)
    trace = float(np.trace(np.eye(flat.size) - a))
    return flat.size * rr / trace**2, float(np.sqrt(rr / trace)), trace


def one_sided_scene(mode: str, seed: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """The GCV tests' larger scene: a smooth 64 px texture blurred by a 9 x 9 kernel one-sided
    on both axes (a bar and a spur), borders ``mode`` (``"wrap"`` or ``"reflect"``), noise
    sigma 0.01. Returns ``(y, kernel)``."""
    rng = np.random.default_rng(seed)
    x = ndimage.gaussian_filter(rng.uniform(0, 1, (64, 64)), 1.0)
    kernel = np.zeros((9, 9))
    kernel[4, 1:8] = 1.0
    kernel[2:4, 6] = 0.5
    kernel /= kernel.sum()
    return ndimage.convolve(x, kernel, mode=mode) + rng.normal(0, 0.01, x.shape), kernel
