"""Deconvolution with a hyper-Laplacian gradient prior by ADMM (the quality method).
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft

from pipeline.core import validate
from pipeline.core.deconvolve.common import _WORKERS, _check_positive, _Domain
from pipeline.core.deconvolve.wiener import (
    _laplacian_spectrum,
    _natural_prior_scale,
)
from pipeline.errors import InputError


# ----------------------------------------------------------------------------- sparse prior
def hyper_laplacian_prox(v: np.ndarray, t: float, alpha: float) -> np.ndarray:
    """``argmin_w t |w|^alpha + (w - v)^2 / 2`` element-wise (Krishnan & Fergus 2009).

    Zero below the threshold ``tau = (2 - a)/(2 (1 - a)) (2 t (1 - a))^(1/(2 - a))``;
    above it, the larger root of ``w - v + t a w^(a-1) = 0`` found by Newton on a
    table of ``|v|`` (the K&F lookup table) and interpolated. ``alpha = 1`` is soft
    thresholding.
    """
    mag = np.abs(v)
    if t <= 0:
        return v.copy()
    if alpha == 1.0:
        return np.sign(v) * np.maximum(mag - t, 0.0)
    c = 2.0 * t * (1.0 - alpha)
    tau = (2.0 - alpha) / (2.0 * (1.0 - alpha)) * c ** (1.0 / (2.0 - alpha))
    top = float(mag.max()) if mag.size else 0.0
    if top <= tau:
        return np.zeros_like(v)
    grid = np.linspace(tau, top, 4096)
    w = grid.copy()
    for _ in range(30):  # g(w) convex, decreasing from w = v onto the larger root
        g = w - grid + t * alpha * w ** (alpha - 1.0)
        dg = 1.0 + t * alpha * (alpha - 1.0) * w ** (alpha - 2.0)
        w = w - g / dg
    out = np.interp(mag, grid, w).astype(v.dtype, copy=False)
    out[mag <= tau] = 0.0
    return np.sign(v) * out


def _grad(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.roll(x, -1, axis=0) - x, np.roll(x, -1, axis=1) - x


def _grad_t(g0: np.ndarray, g1: np.ndarray) -> np.ndarray:
    return (np.roll(g0, 1, axis=0) - g0) + (np.roll(g1, 1, axis=1) - g1)


def _sparse_channel(y, valid, kernel, mu, alpha, iterations, rho) -> np.ndarray:
    """ADMM for ``1/2 |M (k*x - y)|^2 + mu sum |grad x|^alpha`` on the extended domain."""
    dom = _Domain.build(y.shape, kernel, y.dtype)
    mask = dom.embed(valid.astype(y.dtype))
    my = dom.embed(y) * mask
    d2 = _laplacian_spectrum(dom.shape, y.dtype)
    k_conj = np.conj(dom.k_fft)
    ka2 = np.abs(dom.k_fft) ** 2
    x = dom.reflect(y)
    z = dom.conv(x)
    u = np.zeros_like(z)
    g = _grad(x)
    v = [np.zeros_like(z), np.zeros_like(z)]
    w = list(g)
    rhos = np.geomspace(rho[0], rho[1], iterations)
    for i, r in enumerate(rhos):
        if i:  # scaled duals follow the penalty
            scale = rhos[i - 1] / r
            u *= scale
            v[0] *= scale
            v[1] *= scale
        # x-step: (|K|^2 + |D|^2) X = K^*(z - u) + D^T(w - v)   (rho cancels)
        rhs = k_conj * sfft.rfft2(z - u, workers=_WORKERS) + sfft.rfft2(
            _grad_t(w[0] - v[0], w[1] - v[1]), workers=_WORKERS
        )
        x_fft = rhs / (ka2 + d2)
        x = sfft.irfft2(x_fft, s=dom.shape, workers=_WORKERS)
        kx = sfft.irfft2(dom.k_fft * x_fft, s=dom.shape, workers=_WORKERS)
        g = _grad(x)
        # z-step: data only where observed (M = 1), free elsewhere
        z = (my + r * (kx + u)) / (mask + r)
        # w-step: hyper-Laplacian shrinkage
        w = [hyper_laplacian_prox(g[j] + v[j], mu / r, alpha) for j in (0, 1)]
        u += kx - z
        v[0] += g[0] - w[0]
        v[1] += g[1] - w[1]
    return x[dom.crop]


def _plan_sparse(y, valid, k, sigma, *, alpha=0.8, weight=0.2, iterations=50, rho=(3e-3, 0.3)):
    alpha = float(alpha)
    if not 0 < alpha <= 1:
        raise InputError(f"alpha must be in (0, 1], got {alpha!r}")
    weight = _check_positive("weight", weight, allow_zero=True)
    iterations = validate.whole("iterations", iterations)
    rho = tuple(_check_positive("rho", r) for r in rho)
    s2 = _natural_prior_scale(y, valid, sigma, k)
    # MAP: |M(k*x - y)|^2 / (2 sigma^2) + sum |g / s|^alpha, s the per-direction gradient RMS
    s = np.sqrt(np.maximum(s2 / 2.0, 1e-24))
    mu = weight * sigma**2 / s**alpha
    # the whole frame: the method is not linear, and tiles with any overlap tried differed
    # by ~0.05 (a tiled run needs an explicit overlap_px)
    depth = max(y.shape[:2])
    return {"mu": mu, "alpha": alpha, "iterations": iterations, "rho": rho}, depth
