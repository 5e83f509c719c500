"""Wiener's regularisation weight by generalized cross-validation (Golub, Heath & Wahba 1979).

For the linear estimate ``X = K* Y / (|K|^2 + V + lam R)`` (Sec. 4.3; ``V`` the kernel
variance, ``R`` the regulariser's spectrum) the blurred prediction is ``a Y`` with the
influence ``a = |K|^2 / (|K|^2 + V + lam R)``, diagonal in the Fourier basis, so

    GCV(lam) = mean |(1 - a) Y|^2 / mean(1 - a)^2

needs one FFT of the data and a sum per ``lam``. Its minimiser estimates the ``lam`` of
least predictive error without knowing the noise level; but it counts as "noise"
whatever the model does not explain, and at low noise it may interpolate the data. So
it is trusted only where its noise agrees with the data's own estimate (``GCV_TRUST``),
or, when that estimate is only an upper bound (no noise level given), where its minimum is
the grid's floor and it scores the prior fit's ``lam`` clearly worse (``GCV_FLOOR_MARGIN``:
clean texture that the estimate read as noise); elsewhere the natural-prior fit decides.
Where it is trusted but reads more noise than the data's own estimate, its ``lam`` is
scaled to that estimate (:func:`pipeline.core.deconvolve.wiener._plan_wiener`): the excess
is the kernel's mismatch, no noise.
Issue 13: on nine-frame synthetic stacks with noise sigma 0.01 and 0.02 the prior fit left
0.4 and 1.8 dB to a ``lam`` tuned on the truth; GCV was within 0.1 dB of it. On a clean
ray-traced depth edge the floor rule took the default from 1.5 to 0.08 dB of it.
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft

from pipeline.core.deconvolve.common import _WORKERS, spectral_grid

GCV_CROP_PX = 256  # side of the centre crop GCV reads (mirrored to twice that: periodic)
GCV_LAMS = np.logspace(-7.0, 1.0, 9)  # the coarse grid (decades), then refined
GCV_REFINE_STEPS = 10  # golden-section steps in log lam between the best's neighbours
# GCV is trusted where its noise and the data's own estimate (the high band,
# estimate_noise_sigma) agree within this factor either way. Above, GCV counts model
# mismatch or texture as noise (a clean three-plane stack: 3.7x; a checkerboard: 4e11x);
# below, its minimum sits at the grid's floor, interpolating the data (a 40 px comet:
# 0.015x, 0.1 dB worse than the prior fit). Noisy stacks read 1.2-1.5x.
GCV_TRUST = 2.5
# Where GCV's minimum is its grid's floor, it is kept over the prior fit's lam only when GCV
# scores that lam this much worse (clean 1/f textures under a stack's IPSF: 1.23-1.32x; a
# noisy photograph under a delta kernel, where the floor skips a real denoising: 1.01-1.07x)
GCV_FLOOR_MARGIN = 1.15


def interpolates(lam: float, noise: float, sigma_bound: float) -> bool:
    """GCV's minimum lies in its grid's first decade (``lam < GCV_LAMS[1]``) with a noise
    below ``sigma_bound / GCV_TRUST``: the model explains the data down to a noise the
    bound does not see. Where the bound is the data's own estimate (texture raises it),
    that is clean data, not a failed fit (:func:`pipeline.core.deconvolve.wiener.
    _plan_wiener`)."""
    return bool(lam < GCV_LAMS[1] and noise < sigma_bound / GCV_TRUST)


def floor_predicts_better(y: np.ndarray, grid, lam_floor: float, lam_other: float) -> bool:
    """GCV scores ``lam_other`` at least ``GCV_FLOOR_MARGIN`` times its score at
    ``lam_floor`` on channel ``y``: by GCV's own estimate of the prediction error, the
    larger ``lam`` removes signal, not noise (``grid`` from :func:`kernel_grid`)."""
    spectra = _spectra(y, grid)
    return gcv_score(lam_other, spectra) >= GCV_FLOOR_MARGIN * gcv_score(lam_floor, spectra)


def crop_shape(image_shape, kernel_shape) -> tuple[int, int] | None:
    """The mirrored centre crop's shape for an image of ``image_shape`` (rows, cols): twice
    ``GCV_CROP_PX`` (or half the kernel, if larger) per side, within the image; ``None``
    when the image is too small for the kernel (then GCV does not apply)."""
    shape = []
    for n, k in zip(image_shape[:2], kernel_shape[:2]):
        side = 2 * min(int(n), max(GCV_CROP_PX, (int(k) + 1) // 2))
        if side < k:
            return None
        shape.append(side)
    return tuple(shape)


def kernel_grid(shape, kernel: np.ndarray, prior: str = "natural", variance=None):
    """What every channel shares on the mirrored crop of ``shape`` (:func:`crop_shape`):
    the rfft weights, ``|K|^2 + V``, ``V`` and ``R``."""
    k2, reg, weight = spectral_grid(np.asarray(kernel, np.float64), shape, prior)
    v = np.zeros_like(k2) if variance is None else variance(k2.shape)
    return weight, k2 + v, v, reg


def _spectra(y: np.ndarray, grid):
    """Weighted data power ``w |Y|^2`` of the mirrored centre crop of ``y``, with ``grid``."""
    weight, base, v, reg = grid
    rows, cols = reg.shape[0] // 2, (reg.shape[1] - 1)  # the crop (the grid is rfft's)
    r0, c0 = (y.shape[0] - rows) // 2, (y.shape[1] - cols) // 2
    q = np.asarray(y[r0 : r0 + rows, c0 : c0 + cols], np.float64)
    q = np.pad(q, [(0, n) for n in q.shape], mode="symmetric")  # mirror-periodic: no seams
    power = np.abs(sfft.rfft2(q - q.mean(), workers=_WORKERS)) ** 2
    return weight * power, weight, base, v, reg


def gcv_noise(lam: float, spectra, size: int) -> float:
    """GCV's noise std at ``lam``: ``sqrt(|(1 - a) Y|^2 / N / trace(1 - a))`` (Wahba)."""
    power, weight, base, v, reg = spectra
    residual = (v + lam * reg) / (base + lam * reg)
    trace = float(np.sum(weight * residual))
    return float(np.sqrt(np.sum(power * residual**2) / size / max(trace, 1e-300)))


def gcv_score(lam: float, spectra) -> float:
    """``GCV(lam)`` on the spectra of :func:`_spectra`."""
    power, weight, base, v, reg = spectra
    residual = (v + lam * reg) / (base + lam * reg)  # 1 - a
    trace = float(np.sum(weight * residual))
    return float(np.sum(power * residual**2)) / max(trace, 1e-300) ** 2


def gcv_regularization(y: np.ndarray, grid) -> tuple[float, float]:
    """The ``lam`` minimising :func:`gcv_score` for one channel ``y`` (2-D), and GCV's
    noise std there (:func:`gcv_noise`); ``grid`` from :func:`kernel_grid` on
    :func:`crop_shape` of ``y`` and the kernel.

    Coarse search on ``GCV_LAMS``, then golden-section search in ``log lam`` between the
    best's neighbours.
    """
    spectra = _spectra(y, grid)
    size = grid[3].shape[0] * 2 * (grid[3].shape[1] - 1)
    logs = np.log(GCV_LAMS)
    scores = [gcv_score(float(np.exp(t)), spectra) for t in logs]
    best = int(np.argmin(scores))
    lo, hi = logs[max(best - 1, 0)], logs[min(best + 1, len(logs) - 1)]
    ratio = (np.sqrt(5.0) - 1.0) / 2.0
    a, b = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
    fa, fb = gcv_score(float(np.exp(a)), spectra), gcv_score(float(np.exp(b)), spectra)
    for _ in range(GCV_REFINE_STEPS):
        if fa < fb:
            hi, b, fb = b, a, fa
            a = hi - ratio * (hi - lo)
            fa = gcv_score(float(np.exp(a)), spectra)
        else:
            lo, a, fa = a, b, fb
            b = lo + ratio * (hi - lo)
            fb = gcv_score(float(np.exp(b)), spectra)
    candidates = [(scores[best], logs[best]), (fa, a), (fb, b)]
    lam = float(np.exp(min(candidates)[1]))
    return lam, gcv_noise(lam, spectra, size)
