"""Depth-aware multi-frame deconvolution of a focal stack: the quality method (issue 13).

Sec. 9 averages the aligned frames with the weights of a constant-speed sweep and
deconvolves the average with one kernel, the IPSF, which hardly depends on depth (Eqs.
5-6): no depth has to be known. The price is the average itself. It is one fixed linear
combination of the frames: a detail in focus in frame ``k`` enters it at weight ``w_k``
(about ``1/n``), the deconvolution must amplify it about ``n``-fold, and with it the noise
of every frame.

Given the depth, all frames can be used as they are. For a scene at one depth ``d``,
frame ``k`` sees ``Y_k = K_kd X + N_k`` with ``K_kd`` the defocus of frame ``k`` at ``d``
(Eqs. 2-4), and the Wiener estimate from all frames under the natural-image prior of the
default Wiener (``E|X(w)|^2 = s2 / |D(w)|^2``, white noise of std ``sigma``) is

    X_d(w) = sum_k conj(K_kd(w)) Y_k(w) / (sum_k |K_kd(w)|^2 + lam |D(w)|^2),
    lam = sigma^2 / s2,

the normal equations of ``min sum_k |K_kd * x - y_k|^2 + lam |grad x|^2``. Where frame
``k`` is in focus ``K_kd`` is about 1, so the fine detail comes from that frame at its own
noise, not amplified.

The depth of each pixel is chosen by the same model (depth from defocus): among the
candidate depths (the frames' focus positions and a few beyond each end of the range,
Sec. 4.1), the one whose estimate, blurred again by each frame's kernel, explains the
frames best (the smallest local residual ``sum_k |K_kd * X_d - Y_k|^2``,
:func:`depth_index`). The model holds inside a region of one depth: near a depth change
the other depth's light enters the estimate with the wrong kernels. There, where a frame
clipped, where the model leaves much of the frames' detail unexplained (:func:`fit_weight`)
and where the estimate shows fine detail that no frame shows (:func:`supported_weight`:
ringing of kernels that are not the lens's, which the residual cannot see), the result
blends to the caller's fallback (the main job's Sec. 9 result, whose kernel is the same
for every depth): :func:`restore`.

On the synthetic scenes of issue 13 this gains 1.1-2.9 dB over the default on five of the
seven noisy ones (+0.56 and +0.59 on the other two), at 2.1-2.6x its time
(``tests/benchmarks/results/real_regions/synthetic_guard.md``); on the
real JPEG stacks, whose blur the per-frame pillbox model fits only roughly, it does not
beat the default (``tests/benchmarks/results/quality_method/README.md``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import cv2
import numpy as np
from scipy import fft as sfft

from pipeline.core.deconvolve.common import (
    _fast_shape,
    _gradient_energy_2d,
    _kernel_fft,
    _laplacian_spectrum,
    _taper_pad,
    noise_sigma_2d,
)
from pipeline.errors import InputError

# candidate depths beyond each end of the focus range, as shares of the range (Sec. 4.1:
# content beyond the last frame is in focus in none; pcb7's barcode lies ~0.17 beyond)
BEYOND_SHARES = (0.1, 0.2, 0.35)
RESIDUAL_SIGMA_PX = 2.0  # smoothing of the per-depth residual (depth-map px) before the choice
# the multi-frame estimate is used where the chosen depth spans at most one candidate step
# within this radius (full-resolution px); beyond, light of another depth enters it
STEADY_RADIUS_PX = 6
DEPTH_MAP_SIDE_PX = 768  # longest side of the frames the depth map is chosen on
DETAIL_SIGMA_PX = 4.0  # the frames' detail the residual is judged against: y - G_4px y
# share of that detail the model may leave unexplained: all of the multi-frame estimate
# below the first, none above the second (where the frames do not follow the model)
FIT_SHARE = (0.5, 1.0)
# fine detail of the result against the sharpest frame's there: all of the multi-frame
# estimate up to the first ratio, none from the second (detail no frame shows)
DETAIL_EXCESS = (1.5, 3.0)
_TAPER_PX = 8  # fade of the padded margin to the mean (a smooth periodic extension)

KernelsAt = Callable[[float, float], Sequence[np.ndarray]]


def candidate_depths(positions: np.ndarray, beyond: Sequence[float] = BEYOND_SHARES) -> np.ndarray:
    """The depths the depth map chooses from, in the frames' focus coordinate: every
    frame's focus position and ``beyond`` shares of the range past each end, ascending."""
    p = np.unique(np.asarray(positions, dtype=np.float64))
    if p.size < 2:
        raise InputError("a multi-frame restoration needs frames at two or more focus positions")
    width = float(p[-1] - p[0])
    b = np.asarray(sorted(beyond), dtype=np.float64) * width
    return np.concatenate([p[0] - b[::-1], p, p[-1] + b])


def _grid(frame_shape: tuple[int, int], kernels: Sequence[np.ndarray]):
    """The padded FFT grid for ``frame_shape`` and the largest kernel: (shape, pad)."""
    half = max(max(k.shape) for k in kernels) // 2
    pad = half + 1
    shape = _fast_shape(tuple(s + 2 * (pad + _TAPER_PX) for s in frame_shape))
    return shape, pad


def _spectra(frames: np.ndarray, shape: tuple[int, int], pad: int) -> list[np.ndarray]:
    """rfft2 of each 2-D frame, reflected by ``pad`` and faded to its mean beyond."""
    return [sfft.rfft2(_taper_pad(f, pad, _TAPER_PX, shape), workers=-1) for f in frames]


def _crop(x: np.ndarray, frame_shape: tuple[int, int], pad: int) -> np.ndarray:
    o = pad + _TAPER_PX
    return x[o : o + frame_shape[0], o : o + frame_shape[1]]


def kernel_spectra(kernels: Sequence[np.ndarray], shape: tuple[int, int], dtype=np.float64):
    """The kernels' rfft2 spectra on ``shape`` (centred), and ``sum_k |K_k|^2``. A kernel
    symmetric under a half turn (Eqs. 3-4: every lens kernel) has a real spectrum, kept
    real: the estimate's sum then costs half the multiplications."""
    spectra, power = [], None
    for k in kernels:
        kf = _kernel_fft(k, shape, np.float64)
        if np.array_equal(k, k[::-1, ::-1]):
            kf = kf.real
        kf = kf.astype(dtype if np.isrealobj(kf) else np.result_type(dtype, np.complex64))
        p = kf * kf if np.isrealobj(kf) else kf.real**2 + kf.imag**2
        power = p if power is None else power + p
        spectra.append(kf)
    return spectra, power


def wiener_estimate(y_fft, k_fft, lam: float, d2: np.ndarray, power=None) -> np.ndarray:
    """The multi-frame Wiener estimate (module docstring) on an rfft grid: ``y_fft`` and
    ``k_fft`` hold one (rows, cols//2+1) spectrum per frame, ``d2`` is ``|D|^2``, ``power``
    ``sum_k |K_k|^2`` if known (:func:`kernel_spectra`). Summed frame by frame: a spectrum
    of temporaries whatever the frame count."""
    num = None
    for kf, yf in zip(k_fft, y_fft):
        term = yf * (np.conj(kf) if np.iscomplexobj(kf) else kf)
        num = term if num is None else np.add(num, term, out=num)
    if power is None:
        power = sum(np.abs(kf) ** 2 for kf in k_fft)
    den = power + lam * d2
    den[den <= 0] = 1.0  # only at DC with lam |D|^2 = 0 and every kernel zero there: no data
    return num / den


def regularisation(frames: np.ndarray, fallback: np.ndarray) -> float:
    """``lam = sigma^2 / s2`` of 2-D frames: ``sigma`` the frames' mean noise level, ``s2``
    the gradient variance of ``fallback`` (an estimate of the sharp image)."""
    ok = np.ones(fallback.shape, dtype=bool)
    sigma = float(np.mean([noise_sigma_2d(f, np.ones(f.shape, dtype=bool)) for f in frames]))
    s2 = _gradient_energy_2d(fallback, ok)
    floor = 1e-6 * max(float(np.mean(np.abs(fallback))), 1e-12) ** 2
    return max(sigma**2, floor) / max(s2, floor)


def depth_index(
    frames: np.ndarray,
    kernels_at: KernelsAt,
    depths: np.ndarray,
    lam: float,
    *,
    scale: float = 1.0,
    cache: dict | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the index of the candidate depth that explains 2-D ``frames`` best, and
    how well: the residual there as a share of the frames' local variance.

    For each depth ``d`` the multi-frame estimate ``X_d`` is blurred again by every frame's
    kernel; the residual ``sum_k (K_kd * X_d - y_k)^2``, smoothed over
    :data:`RESIDUAL_SIGMA_PX`, is smallest at the depth whose kernels fit the frames.
    Divided by ``sum_k (y_k - G_4px y_k)^2`` (smoothed alike), it is the share of the frames'
    detail the model leaves unexplained: 0.005-0.2 (median) on the synthetic stacks of issue
    13, which follow the model, 2.7-2.8 on beetle and amber, whose frames it does not fit.
    ``kernels_at(d, scale)`` gives the frames' kernels at depth ``d`` for frames resized by
    ``scale``; ``cache`` (a dict) keeps their spectra for another call on frames of the same
    shape.
    """
    frame_shape = frames.shape[1:]
    cache = {} if cache is None else cache
    if "kernels" not in cache:
        cache["kernels"] = [kernels_at(float(d), scale) for d in depths]
    kernels = cache["kernels"]
    shape, pad = _grid(frame_shape, [k for ks in kernels for k in ks])
    y_fft = _spectra(frames, shape, pad)
    d2 = _laplacian_spectrum(shape, np.float64)
    best = np.full(frame_shape, np.inf, dtype=np.float32)
    index = np.zeros(frame_shape, dtype=np.int32)
    for j, ks in enumerate(kernels):
        if j not in cache:
            cache[j] = kernel_spectra(ks, shape)
        k_fft, power = cache[j]
        x_fft = wiener_estimate(y_fft, k_fft, lam, d2, power)
        residual = np.zeros(frame_shape, dtype=np.float64)
        for kf, yf in zip(k_fft, y_fft):
            r = _crop(sfft.irfft2(kf * x_fft - yf, s=shape, workers=-1), frame_shape, pad)
            residual += r * r
        smooth = cv2.GaussianBlur(residual.astype(np.float32), (0, 0), RESIDUAL_SIGMA_PX)
        better = smooth < best
        best[better] = smooth[better]
        index[better] = j
    detail = np.zeros(frame_shape, dtype=np.float32)
    for f in frames:
        band = f - cv2.GaussianBlur(f, (0, 0), DETAIL_SIGMA_PX)
        detail += cv2.GaussianBlur(band * band, (0, 0), RESIDUAL_SIGMA_PX)
    tiny = np.float32(1e-12 * max(float(np.max(detail)), 1e-30))
    return index, best / np.maximum(detail, tiny)


def unexplained_shares(
    alternatives: Sequence[np.ndarray], kernels_at: KernelsAt, depths: np.ndarray
) -> list[float]:
    """For each stack of aligned 2-D frames in ``alternatives`` (the same frames aligned in
    different ways), the median share of their fine detail the blur model leaves unexplained
    (:func:`depth_index`), away from a border of 1/16 of the frame: how well they are aligned,
    by a measure that, unlike a correlation, expects each depth's blur to differ between
    frames (``pipeline.jobs.stack`` chooses an alignment by it). The kernels' spectra are
    computed once for all alternatives."""
    cache: dict = {}
    shares = []
    for frames in alternatives:
        f = np.asarray(frames, dtype=np.float32)
        lam = regularisation(f, f.mean(axis=0))
        _, unexplained = depth_index(f, kernels_at, depths, lam, cache=cache)
        r, c = (max(1, n // 16) for n in unexplained.shape)
        shares.append(float(np.median(unexplained[r:-r, c:-c])))
    return shares


def fit_weight(unexplained: np.ndarray) -> np.ndarray:
    """1 where the model leaves under ``FIT_SHARE[0]`` of the frames' detail unexplained,
    0 above ``FIT_SHARE[1]``, linear between (float32)."""
    low, high = FIT_SHARE
    return np.clip((high - unexplained) / (high - low), 0.0, 1.0).astype(np.float32)


def steady_weight(index: np.ndarray, radius_px: int, blocked: np.ndarray | None) -> np.ndarray:
    """Blend weight of the multi-frame estimate: 1 where the depth index spans at most one
    step within ``radius_px`` and no pixel is ``blocked`` (clipped) there, 0 elsewhere,
    smoothed (float32, in [0, 1])."""
    box = np.ones((2 * radius_px + 1, 2 * radius_px + 1), np.uint8)
    idx = index.astype(np.uint16)
    steady = (cv2.dilate(idx, box).astype(np.int32) - cv2.erode(idx, box)) <= 1
    block = blocked is not None and np.any(blocked)
    if block:
        steady &= cv2.dilate(blocked.astype(np.uint8), box) == 0
    weight = cv2.GaussianBlur(steady.astype(np.float32), (0, 0), max(radius_px / 3.0, 1.0))
    if block:
        weight[blocked] = 0.0  # exactly the fallback there, not the blur's faint tail
    return weight


def _detail(grey: np.ndarray) -> np.ndarray:
    """Local fine detail: the band ``g - G_1px g``, its energy over ~7 px (float32)."""
    band = grey - cv2.GaussianBlur(grey, (0, 0), 1.0)
    return cv2.GaussianBlur(band * band, (0, 0), 3.0)


def supported_weight(restored: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """1 where the grey ``restored`` shows no more fine detail than the sharpest of the grey
    ``frames`` there, falling to 0 at ``DETAIL_EXCESS[1]`` times it (float32).

    An all-in-focus image is, at each pixel, the frame in focus there: detail beyond every
    frame's is not the scene's. Where the per-frame kernels are not the lens's (real
    photographs with a fitted blur model, frames a pixel out of register), the multi-frame
    estimate fits the frames with a maze of fine ringing that the kernels blur away (so the
    residual cannot see it): on pcb7 it covered the barcode's white bars.
    """
    sharpest = np.zeros(restored.shape, dtype=np.float32)
    for f in frames:
        np.maximum(sharpest, _detail(f), out=sharpest)
    low, high = DETAIL_EXCESS
    floor = np.float32(1e-12 * max(float(np.max(sharpest)), 1e-30))
    ratio = _detail(restored.astype(np.float32)) / np.maximum(sharpest, floor)
    weight = np.clip((high - ratio) / (high - low), 0.0, 1.0).astype(np.float32)
    return cv2.GaussianBlur(weight, (0, 0), 2.0)


def _reduce(frames: np.ndarray, factor: float) -> np.ndarray:
    if factor >= 1.0:
        return frames
    rows, cols = frames.shape[1:3]
    size = (max(round(cols * factor), 1), max(round(rows * factor), 1))
    return np.stack([cv2.resize(f, size, interpolation=cv2.INTER_AREA) for f in frames])


def restore(
    frames: np.ndarray,
    kernels_at: KernelsAt,
    depths: np.ndarray,
    fallback: np.ndarray,
    *,
    blocked: np.ndarray | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, dict]:
    """Multi-frame Wiener estimate per depth, chosen per pixel, blended into ``fallback``.

    Parameters
    ----------
    frames : ndarray, (n, rows, cols) or (n, rows, cols, channels)
        The aligned frames, linear light.
    kernels_at : callable ``(depth, scale) -> sequence of n 2-D kernels``
        Every frame's kernel (centred, summing to 1) for a point at ``depth``, on frames
        resized by ``scale``.
    depths : ndarray
        Candidate depths (:func:`candidate_depths`).
    fallback : ndarray, (rows, cols[, channels])
        The result to keep near depth changes and clipped pixels (the main job's).
    blocked : ndarray of bool, (rows, cols), optional
        Pixels where the linear model does not hold (clipped in a frame).
    progress : callable ``(done, total)``, optional

    Returns
    -------
    image : ndarray, float32, the shape of ``fallback``
    info : dict
        ``share``: the mean blend weight of the multi-frame estimate; ``depths``: how many
        pixels chose each candidate depth.
    """
    f = np.asarray(frames, dtype=np.float32)
    if f.ndim not in (3, 4) or f.shape[0] < 2:
        raise InputError(f"frames must be (n >= 2, rows, cols[, channels]), got {f.shape}")
    if f.shape[1:] != np.shape(fallback):
        raise InputError(f"fallback has shape {np.shape(fallback)}, frames {f.shape[1:]}")
    if not (np.all(np.isfinite(f)) and np.all(np.isfinite(fallback))):
        raise InputError("frames and fallback must be finite (no NaN or infinite values)")
    colour = f.ndim == 4
    f4 = f if colour else f[..., np.newaxis]
    fb = np.asarray(fallback, dtype=np.float32).reshape(f4.shape[1:])
    grey = f4.mean(axis=3)
    scale = min(1.0, DEPTH_MAP_SIDE_PX / max(grey.shape[1:]))
    small = _reduce(grey, scale)
    small_fb = _reduce(fb.mean(axis=2)[np.newaxis], scale)[0]
    lam_small = regularisation(small, small_fb)
    index_small, unexplained = depth_index(small, kernels_at, depths, lam_small, scale=scale)
    rows, cols = grey.shape[1:]
    index = cv2.resize(index_small, (cols, rows), interpolation=cv2.INTER_NEAREST)
    fit = cv2.resize(fit_weight(unexplained), (cols, rows), interpolation=cv2.INTER_LINEAR)
    weight = steady_weight(index, STEADY_RADIUS_PX, blocked) * fit
    counts = np.bincount(index.ravel(), minlength=len(depths))
    used = [j for j in range(len(depths)) if np.any((index == j) & (weight > 0))]
    if not used:  # the model holds nowhere: the fallback, without the full-size spectra
        info = {"share": 0.0, "depths": [int(c) for c in counts]}
        return (fb if colour else fb[..., 0]).copy(), info
    kernels = {j: kernels_at(float(depths[j]), 1.0) for j in used}
    shape, pad = _grid((rows, cols), [k for ks in kernels.values() for k in ks])
    d2 = _laplacian_spectrum(shape, np.float32)
    channels = f4.shape[3]
    lam = [regularisation(f4[..., c], fb[..., c]) for c in range(channels)]
    y_fft = [_spectra(f4[..., c], shape, pad) for c in range(channels)]
    out = fb * (1.0 - weight)[..., np.newaxis]
    for step, j in enumerate(used):
        k_fft, power = kernel_spectra(kernels[j], shape, np.float32)
        mask = weight * (index == j)
        for c in range(channels):
            x_fft = wiener_estimate(y_fft[c], k_fft, np.float32(lam[c]), d2, power)
            x = sfft.irfft2(x_fft, s=shape, workers=-1)
            out[..., c] += mask * _crop(x, (rows, cols), pad)
        if progress is not None:
            progress(step + 1, len(used))
    supported = supported_weight(out.mean(axis=2), grey)
    out = fb + supported[..., np.newaxis] * (out - fb)
    info = {"share": float(np.mean(weight * supported)), "depths": [int(c) for c in counts]}
    return (out if colour else out[..., 0]), info
