"""The IPSF of a focal stack's weighted average (Sec. 9): focus positions from
measured magnifications, the stack-average kernel vs the analytic Eq. 6 kernel
(the one closer by Eq. 8 is kept), and the Wiener settings it implies.
"""

from __future__ import annotations

import numpy as np

from pipeline.core import optics, psf, spectra
from pipeline.core.lens import Lens
from pipeline.core.motion import constant_speed
from pipeline.core.psf import _normalise, _resolve_size, raster_lens_psf, raster_reach
from pipeline.errors import InputError


# ----------------------------------------------------------------------------- focal stacks
def focal_stack_psf(
    frame_positions,
    weights,
    blur_px,
    *,
    model: str = "pillbox",
    gaussian_g: float = 1.0,
    focus_samples: int = 33,
    size: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth-independent kernel of a weighted focal-stack average (Sec. 9).

    A point focused at position ``x`` (in the frames' focus coordinate) is seen
    by frame ``i`` with a blur of diameter ``blur_px(x_i, x)``; the weighted
    average shows it blurred by ``K_x = sum_i w_i P(b(x_i, x))`` (the discrete
    form of Eq. 5). ``K_x`` is averaged over ``focus_samples`` positions spread
    uniformly over the stack's range (uniform in image distance, the coordinate
    a constant-speed sweep is uniform in).

    Parameters
    ----------
    frame_positions, weights : array_like, shape (n,)
        Focus positions of the frames and their weights (sum 1).
    blur_px : callable
        ``blur_px(frame_positions, x) -> diameters`` (vectorised over frames).

    Returns
    -------
    kernel : ndarray
        The average kernel (odd, centred, sums to 1).
    per_position : ndarray, shape (focus_samples, size, size)
        ``K_x`` at each sampled position, to judge how depth-invariant it is.
    """
    x = np.asarray(frame_positions, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    samples = np.linspace(x.min(), x.max(), focus_samples) if np.ptp(x) > 0 else x[:1]
    blurs = np.array([np.asarray(blur_px(x, s), dtype=np.float64) for s in samples])
    if not np.all(np.isfinite(blurs)) or np.any(blurs < 0):
        raise InputError("blur_px returned negative or non-finite diameters")
    half = _resolve_size(size, float(blurs.max()), model, gaussian_g) // 2
    cache: dict[float, np.ndarray] = {}

    def raster(b: float) -> np.ndarray:
        """The raster of blur ``b`` over its reach only (zero beyond, :func:`raster_reach`):
        a pillbox of the stack's mean blur covers a quarter of the kernel."""
        key = round(b, 6)
        if key not in cache:
            cache[key] = raster_lens_psf(model, b, raster_reach(model, b, half), gaussian_g)
        return cache[key]

    def blurred(row: np.ndarray) -> np.ndarray:
        """``sum_i w_i P(b_i)``, each raster added in order over its reach (adding the
        zeros beyond would change no bit)."""
        total = np.zeros((2 * half + 1, 2 * half + 1))
        for wi, b in zip(w, row):
            part = raster(b)
            edge = half - part.shape[0] // 2
            total[edge : total.shape[0] - edge, edge : total.shape[1] - edge] += wi * part
        return _normalise(total)

    per_position = np.array([blurred(row) for row in blurs])
    return _normalise(per_position.mean(axis=0)), per_position
KERNEL_VARIANCE_SPREAD = 0.1  # Eq. 8 spread of per-depth kernels above which Wiener uses it


MIN_BREATHING = 0.005  # the least span of magnifications read as focus breathing


def positions_from_scales(scales: np.ndarray) -> tuple[np.ndarray, str]:
    """Focus coordinate from measured magnifications (``scale = p_i / p_ref``).

    Used when they rise or fall steadily and span more than ``MIN_BREATHING`` (0.5%);
    otherwise the frames are taken as evenly spaced in focus (their index), the usual
    capture.
    """
    s = np.asarray(scales, dtype=np.float64)
    if s.size >= 3 and np.ptp(s) > MIN_BREATHING:
        steps = np.diff(s)
        if (
            np.all(steps > 0)
            or np.all(steps < 0)
            or abs(np.corrcoef(s, np.arange(s.size))[0, 1]) > 0.97
        ):
            return s, "magnification"
    return np.arange(s.size, dtype=np.float64), "frame-order"


# ----------------------------------------------------------------------------- kernels
def _blur_model(positions: np.ndarray, *, lens: Lens | None, absolute: bool, blur_span_px):
    """``blur(frame_positions, x)``: the blur diameter (px) in each frame of a point focused
    at ``x``. With a lens and absolute image distances ``a |x - p_i| / x`` (Eq. 2), else
    ``D |x - p_i|`` over the stack's range with the blur span ``D``."""
    if lens is not None and absolute:
        def blur(p, v):
            return lens.blur_px(v, p)  # Eq. 2

        return blur
    if blur_span_px is None:
        raise InputError("internal: no blur span for a stack without absolute positions")
    width = max(np.ptp(positions), 1e-300)

    def blur(p, x):
        return blur_span_px * np.abs(p - x) / width

    return blur


def _frame_rasters(positions, x, *, lens, absolute, blur_span_px, scale=1.0):
    """Every frame's defocus raster (Eq. 3 or 4, unnormalised) for a point focused at
    ``x``, on one grid wide enough for the largest, for frames resized by ``scale``."""
    blur = _blur_model(positions, lens=lens, absolute=absolute, blur_span_px=blur_span_px)
    diameters = np.asarray(blur(positions, x), dtype=np.float64) * scale
    model = lens.psf_model if lens else "pillbox"
    g = lens.gaussian_g if lens else 1.0
    half = _resolve_size(None, float(diameters.max()), model, g) // 2
    return [raster_lens_psf(model, d, half, g) for d in diameters]


def depth_kernel(
    positions: np.ndarray,
    weights: np.ndarray,
    x: float,
    *,
    lens: Lens | None,
    absolute: bool,
    blur_span_px: float | None,
) -> np.ndarray:
    """The weighted average's PSF for a point focused at ``x`` (the discrete Eq. 5,
    ``sum_i w_i P(b(p_i, x))``), which may lie outside the frames' range: the kernel of
    one depth, where :func:`stack_kernel` averages over the range's depths."""
    rasters = _frame_rasters(
        positions, x, lens=lens, absolute=absolute, blur_span_px=blur_span_px
    )
    return _normalise(sum(w * r for w, r in zip(weights, rasters)))


def frame_kernels(
    positions: np.ndarray,
    x: float,
    *,
    lens: Lens | None,
    absolute: bool,
    blur_span_px: float | None,
    scale: float = 1.0,
) -> list[np.ndarray]:
    """Each frame's own PSF for a point focused at ``x`` (Eqs. 2-4; each sums to 1), for
    frames resized by ``scale``: the kernels of the multi-frame method
    (:mod:`pipeline.core.multiframe`)."""
    rasters = _frame_rasters(
        positions, x, lens=lens, absolute=absolute, blur_span_px=blur_span_px, scale=scale
    )
    return [_normalise(r) for r in rasters]


def stack_kernel(
    positions: np.ndarray,
    weights: np.ndarray,
    *,
    lens: Lens | None,
    absolute: bool,
    blur_span_px: float | None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """The IPSF of the weighted average (Sec. 9), per-depth samples of it, and a summary.

    With a lens and absolute image distances, a point focused at ``v`` is blurred
    in frame ``i`` by ``a |v - p_i| / v`` (Eq. 2); the stack-average kernel is
    compared with the single analytic kernel of a constant-speed sweep over the
    same range (Eq. 6, corrected) and the one closer (Eq. 8) to the per-depth
    kernels is kept. Otherwise blur is ``D |x_i - x|`` with the blur span ``D``.
    """
    model = lens.psf_model if lens else "pillbox"
    g = lens.gaussian_g if lens else 1.0
    blur = _blur_model(positions, lens=lens, absolute=absolute, blur_span_px=blur_span_px)
    span = float(blur(positions.max(), positions.min()))
    kernel, per_position = focal_stack_psf(positions, weights, blur, model=model, gaussian_g=g)
    summary = {"size": int(kernel.shape[0]), "source": "stack-average", "blur_span_px": span}
    if lens is not None and absolute and np.ptp(positions) > 0:
        p_lo, p_hi = float(positions.min()), float(positions.max())
        middle = optics.focus_distance(lens.focal_length_mm, 0.5 * (p_lo + p_hi))
        sweep = constant_speed(p_lo, p_hi - p_lo, 1.0)
        analytic = psf.integrated_psf(lens, middle, sweep, size=kernel.shape[0])
        d_avg = np.mean(spectra.dissimilarities(per_position, kernel))
        d_eq6 = np.mean(spectra.dissimilarities(per_position, analytic))
        summary["dissimilarity"] = {"stack-average": float(d_avg), "analytic-eq6": float(d_eq6)}
        if d_eq6 < d_avg:
            kernel, summary["source"] = analytic, "analytic-eq6"
    spread = spectra.dissimilarities(per_position, kernel)
    summary["depth_invariance_eq8"] = {"mean": float(np.mean(spread)), "max": float(np.max(spread))}
    return kernel, per_position[::4], summary


def wiener_options(kernel, kernel_samples=None) -> dict:
    """The main job's Wiener settings (measured with ``flexdof bench accuracy``).

    * No EM passes for clipped pixels: they bought < 0.1 dB with 25% of pixels
      clipped, for +80% time (rl and sparse mask clipped pixels out of the data term).
    * The kernel variance of ``kernel_samples`` only when the IPSF's depth dependence is
      large, their mean Eq. 8 dissimilarity to ``kernel`` above ``KERNEL_VARIANCE_SPREAD``:
      +0.5-0.9 dB on 3-frame stacks (spread 0.4-1.1), but -0.14-0.22 dB and +25% time on
      dense stacks (spread <= 0.03), where it only adds estimation noise.
    """
    if kernel_samples is not None:
        spread = np.mean(spectra.dissimilarities(kernel_samples, kernel))
        kernel_samples = kernel_samples if spread > KERNEL_VARIANCE_SPREAD else None
    return {"kernel_samples": kernel_samples}
