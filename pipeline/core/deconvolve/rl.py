"""Richardson-Lucy deconvolution with masked data and unknown boundaries.
"""

from __future__ import annotations

import numpy as np

from pipeline.core import validate
from pipeline.core.deconvolve.common import _check_positive, _Domain, _frame_depth

# ----------------------------------------------------------------------------- Richardson-Lucy
_DAMPING_POWER = 10  # White (1994)'s N: sharpness of the damping transition


def _rl_channel(y, valid, kernel, iterations, background, threshold) -> np.ndarray:
    dom = _Domain.build(y.shape, kernel, y.dtype)
    mask = dom.embed(valid.astype(y.dtype))
    data = dom.embed(y) + background
    norm = dom.corr(mask)  # K^T M: how much observed data each unknown pixel reaches
    reached = norm > 1e-6 * float(norm.max())
    inv_norm = np.where(reached, 1.0 / np.where(reached, norm, 1.0), 0.0).astype(y.dtype)
    x = np.maximum(dom.reflect(y), 1e-3 * background)  # > 0, else the update is stuck at 0
    for _ in range(iterations):
        model = np.maximum(dom.conv(x), 0.0) + background  # > 0: background > 0
        residual = data - model
        if threshold is None:
            ratio = data / model
        else:  # damped RL (White 1994), Gaussian deviance: no update inside the noise
            u = np.minimum((residual / threshold) ** 2, 1.0)
            n = _DAMPING_POWER
            ratio = 1.0 + u ** (n - 1) * (n - (n - 1) * u) * residual / model
        update = dom.corr(mask * ratio) * inv_norm
        x = np.where(reached, np.maximum(x * update, 0.0), x)  # multiplicative: x >= 0
    return x[dom.crop]


def _rl_transfer(iterations: int):
    """Linearised RL (Landweber, step 1) after ``iterations`` from ``x0 = y``.

    Around a flat image RL reads ``x <- x + K^T (y - K x)``; after n steps the output
    depends on the data through ``(1 - a)^n + K* (1 - (1 - a)^n) / a`` (``a = |K|^2``).
    """

    def transfer(k_fft, d2):
        a = np.clip(np.abs(k_fft) ** 2, 0.0, 1.0)
        decay = (1.0 - a) ** iterations
        small = a < 1e-12
        series = np.where(small, float(iterations), (1.0 - decay) / np.where(small, 1.0, a))
        return decay + np.conj(k_fft) * series

    return transfer


def _plan_rl(y, valid, k, sigma, *, iterations=30, damping=None):
    iterations = validate.whole("iterations", iterations, minimum=0)
    threshold = None
    if damping is not None:
        threshold = _check_positive("damping", damping) * np.maximum(sigma, 1e-12)
    lo = np.array([float(y[..., c].min()) for c in range(y.shape[2])])
    top = np.array([float(np.abs(y[..., c]).max()) for c in range(y.shape[2])])
    # known background b: RL fits y + b with k*x + b; keeps y + b > 0 without clipping
    guard = np.maximum(np.maximum(sigma, 1e-3 * top), 1e-12)
    background = np.maximum(-lo, 0.0) + guard
    depth = _frame_depth(y, k, _rl_transfer(iterations)) + max(k.shape) // 2
    return {"iterations": iterations, "background": background, "threshold": threshold}, depth
