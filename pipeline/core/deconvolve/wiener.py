"""Wiener deconvolution with a natural-image prior and, for depth-dependent IPSFs,
the kernel variance in its denominator (Sec. 4.2).
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft

from pipeline.core.deconvolve import gcv
from pipeline.core.deconvolve.common import (
    _LAM_MIN,
    _WORKERS,
    PRIORS,
    _fast_shape,
    _frame_depth,
    _gradient_energy_2d,
    _kernel_fft,
    _laplacian_spectrum,
    _per_channel,
    _taper_pad,
    map_channels,
    prior_spectrum,
    spectral_grid,
)
from pipeline.errors import InputError


def _natural_prior_scale(y, valid, sigma, kernel, channels=None) -> np.ndarray:
    """Gradient variance ``s2`` of the sharp image under the 1/|w|^2 prior, per channel
    (of ``channels``, default all; ``sigma`` is given for those).

    With ``E|X(w)|^2 = N s2 / |D(w)|^2`` (``D`` the forward-difference pair), Parseval
    gives ``mean|grad y|^2 = s2 sum(k^2) + 4 sigma^2``; solve for ``s2``.
    """
    channels = range(y.shape[2]) if channels is None else channels
    energy = np.array(
        map_channels(
            lambda i: _gradient_energy_2d(y[..., channels[i]], valid[..., channels[i]]),
            len(channels),
        )
    )
    s2 = (energy - 4.0 * sigma**2) / float(np.sum(kernel**2))
    return np.maximum(s2, 4.0 * sigma**2)


def _prior_scale(y, valid, sigma, kernel, prior, channels) -> np.ndarray:
    """The sharp image's spectrum scale under ``prior`` (the prior fit), one value for
    each of ``channels`` (``sigma`` is given for those)."""
    if prior == "natural":
        return _natural_prior_scale(y, valid, sigma, kernel, channels)
    # white spectrum: E|X|^2 = N s0^2, var(y) = s0^2 sum(k^2) + sigma^2
    var = np.array(
        [
            float(np.var(y[..., c][valid[..., c]])) if valid[..., c].any() else 0.0
            for c in channels
        ]
    )
    return np.maximum((var - sigma**2) / float(np.sum(kernel**2)), sigma**2)


AUTO_RULES = ("gcv", "prior")  # how lam is chosen when not given
MAX_NOISE_GAIN = 10.0  # ceiling of the automatic Wiener filter's white-noise gain
# Width of the fade to the mean beyond the reflected ``pad``: the fade starts ``pad`` (the
# filter's reach, mass beyond it < 1e-5) from the frame, so its width does not reach the
# frame; it only smooths the periodic wrap. It was the kernel's size (161 px on pcb10:
# a 2250x2700 grid where 1890x2400 does; issue 15).
TAPER_PX = 32


def _gain_grid(kernel: np.ndarray, prior: str, shape=None):
    """``|K|^2``, the regulariser's spectrum and the rfft weights on one grid."""
    if shape is None:
        shape = _fast_shape((max(256, 2 * kernel.shape[0]), max(256, 2 * kernel.shape[1])))
    k2, reg, weight = spectral_grid(kernel, shape, prior)
    return k2, reg, weight / weight.sum()


def _gain_on(grid, lam: float) -> float:
    k2, reg, weight = grid
    return float(np.sqrt(np.sum(weight * k2 / (k2 + lam * reg) ** 2)))


def white_noise_gain(kernel, lam: float, prior: str = "natural", shape=None) -> float:
    """``sqrt(mean |G|^2)`` of the Wiener filter: how much it scales white noise's std."""
    return _gain_on(_gain_grid(np.asarray(kernel, dtype=np.float64), prior, shape), lam)


def lam_for_noise_gain(kernel, target: float, prior: str = "natural") -> float:
    """The smallest ``lam`` whose white-noise gain (:func:`white_noise_gain`) is ``<= target``.

    A noise target instead of the prior fit: for wide IPSFs ``sum(k^2)`` is tiny, so the
    natural-prior scale grows and ``lam`` collapses (gains of 30+ on real stacks: grain
    and ringing). Bisection in ``log lam`` (the gain falls monotonically with ``lam``) on
    one kernel spectrum.
    """
    if not np.isfinite(target) or target <= 0:
        raise InputError(f"noise_gain must be a positive number, got {target!r}")
    grid = _gain_grid(np.asarray(kernel, dtype=np.float64), prior)
    if _gain_on(grid, _LAM_MIN) <= target:
        return _LAM_MIN
    lo, hi = np.log(_LAM_MIN), np.log(100.0)
    for _ in range(24):  # 16 decades to ~1% in lam
        mid = 0.5 * (lo + hi)
        if _gain_on(grid, float(np.exp(mid))) > target:
            lo = mid
        else:
            hi = mid
    return float(np.exp(hi))


def _wiener_gain(k_fft, d2, lam: float, prior: str, variance=None) -> np.ndarray:
    denominator = np.abs(k_fft) ** 2 + lam * prior_spectrum(d2, prior)  # Wiener, Sec. 4.3 [24]
    if variance is not None:
        denominator = denominator + variance(k_fft.shape)
    return np.conj(k_fft) / denominator


def kernel_variance(samples, kernel):
    """``V(w) = mean_u |K_u(w) - K(w)|^2`` of per-depth kernels around the one used.

    With a depth-dependent blur ``K_u`` of mean ``K`` and variance ``V``, the linear
    estimate minimising the expected error is ``K* / (|K|^2 + V + lam |D|^2)``:
    frequencies where the IPSF is not depth-invariant (Eq. 8) are not amplified.
    ``|K_u - K|^2`` is the spectrum of the autocorrelation of ``k_u - k``, a compact
    array, so ``V`` is exact on any grid at the cost of one FFT. Returns a function
    of an rfft grid shape giving ``V`` there.
    """
    samples = np.asarray(samples, dtype=np.float64)
    kernel = np.asarray(kernel, dtype=np.float64)
    if samples.ndim != 3 or samples.shape[1:] != kernel.shape:
        raise InputError(
            f"kernel_samples must have shape (n, {kernel.shape[0]}, {kernel.shape[1]}), "
            f"got {samples.shape}"
        )
    diffs = samples - kernel
    full = (2 * kernel.shape[0] - 1, 2 * kernel.shape[1] - 1)  # every lag, no wrap-around
    power = np.mean(np.abs(sfft.rfft2(diffs, full)) ** 2, axis=0)
    autocorrelation = sfft.fftshift(sfft.irfft2(power, full))  # lag 0 at the centre

    def on_grid(rshape: tuple[int, int]) -> np.ndarray:
        shape = (rshape[0], 2 * (rshape[1] - 1))  # grids here are even (see _fast_len)
        if all(a <= g for a, g in zip(autocorrelation.shape, shape)):
            return np.abs(_kernel_fft(autocorrelation, shape, np.float64))
        # lags beyond a small frame's grid (a blur as wide as the frame): the spectrum
        # sampled on a periodic grid is that of the lags folded onto it
        rows = (np.arange(full[0]) - full[0] // 2) % shape[0]
        cols = (np.arange(full[1]) - full[1] // 2) % shape[1]
        folded = np.zeros(shape)
        np.add.at(folded, (rows[:, np.newaxis], cols[np.newaxis, :]), autocorrelation)
        return np.abs(sfft.rfft2(folded))

    return on_grid


def _wiener_spectra(shape, kernel, prior, variance, dtype):
    """What every channel on a grid of ``shape`` shares: ``conj(K)``, ``|K|^2 + V`` and the
    regulariser (``|D|^2`` or the flat spectrum), computed once (in ``dtype``)."""
    k_fft = _kernel_fft(kernel, shape, dtype)
    d2 = _laplacian_spectrum(shape, dtype)
    reg = prior_spectrum(d2, prior)
    base = np.abs(k_fft) ** 2
    if variance is not None:
        base = base + variance(k_fft.shape)
    return np.conj(k_fft), base.astype(d2.dtype, copy=False), reg


def _wiener_grid(y_shape, kernel, pad):
    """(FFT grid shape, taper width) of :func:`_wiener_channel` for a frame of ``y_shape``.

    A filter that reaches across the frame (``pad`` at least its shorter side) gets the
    frame's mirror-periodic domain, ``2 rows x 2 cols`` and no taper (width ``None``):
    reflected once, the frame tiles the plane by reflection, the boundary model of
    ``pad`` (Ng, Chan & Tang 1999, exact for symmetric kernels), where a reflect-then-fade
    pad puts the faded band inside the filter's reach (a 201 px pillbox on a 256 px
    frame: 2.4 dB worse than the input at the borders).
    """
    if pad >= min(y_shape):
        return (2 * y_shape[0], 2 * y_shape[1]), None
    shape = _fast_shape((y_shape[0] + 2 * (pad + TAPER_PX), y_shape[1] + 2 * (pad + TAPER_PX)))
    return shape, TAPER_PX


def _wiener_channel(y, kernel, lam, prior, pad, variance=None, spectra=None) -> np.ndarray:
    """One channel; ``spectra`` (from :func:`_wiener_spectra` on this grid) may be shared."""
    shape, taper = _wiener_grid(y.shape, kernel, pad)
    if spectra is None:
        spectra = _wiener_spectra(shape, kernel, prior, variance, y.dtype)
    conj_k, base, reg = spectra
    if taper is None:  # the mirror-periodic domain: [y, flip(y)] in each direction
        crop = tuple(slice(0, n) for n in y.shape)
        padded = np.pad(y, [(0, n) for n in y.shape], mode="symmetric")
    else:
        crop = tuple(slice(pad + taper, pad + taper + n) for n in y.shape)
        padded = _taper_pad(y, pad, taper, shape)
    x_fft = sfft.rfft2(padded, workers=_WORKERS)
    x_fft *= conj_k  # X = K* Y / (|K|^2 + V + lam |D|^2), Sec. 4.3 [24]
    x_fft /= base + np.asarray(lam, base.dtype) * reg
    return sfft.irfft2(x_fft, s=shape, overwrite_x=True, workers=_WORKERS)[crop]


def _wiener_transfer(lam: float, prior: str, variance=None):
    return lambda k_fft, d2: _wiener_gain(k_fft, d2, lam, prior, variance)


def _plan_wiener(
    y,
    valid,
    k,
    sigma,
    *,
    prior="natural",
    regularization=None,
    kernel_samples=None,
    noise_gain=None,
    max_noise=None,
    noise_limit=None,
    auto="gcv",
    sigma_is_estimate=False,
):
    """The Wiener filter's ``lam`` per channel and its reach (``pad``).

    ``lam`` is ``regularization`` when given, else chosen by generalized cross-validation
    (``auto="gcv"``, :func:`pipeline.core.deconvolve.gcv.gcv_regularization`) or as
    ``sigma^2 / s2`` of the prior fit (``auto="prior"``), raised until the filter's
    white-noise gain is at most ``noise_gain`` (and ``MAX_NOISE_GAIN``) and, in channels
    whose ``lam`` is not GCV's, the result's noise std ``gain * sigma`` at most
    ``max_noise`` (one value or one per channel; e.g. a single frame's noise, issue 13:
    where GCV's noise agrees with the data's its ``lam`` is near-optimal, and the ceiling
    only smoothed, 2.3 dB on a nine-frame stack at sigma 0.01).

    ``noise_limit`` (one value or one per channel) caps the result's noise std ``gain *
    sigma`` in the channels where the gain ceiling raises the automatic ``lam`` (GCV's
    included), i.e. where GCV or the prior fit asked for a white-noise gain above
    ``MAX_NOISE_GAIN`` (or ``noise_gain``); ``params["noise_limited"]`` says in which
    channels it then held ``lam``. There the data did not set ``lam``: GCV's
    residual on a real stack is mostly the single kernel's mismatch, so on noisy frames
    (pcb7 at ISO 3200, a 54 px blur span) its ``lam`` (1.3-2e-4) lay under the ceiling's
    floor (4.8e-4) whatever the noise, as on the same frames without it, and the result
    carried 10x the average's noise, 3x a frame's. Where GCV's or the prior fit's ``lam``
    is above the floor, the data chose it and it stands (issue 13: on every rendered scene
    with noise, 3 planes, a ray-traced depth edge, the motorcycle, it is; capping there
    cost up to 3.9 dB against the truth-tuned ``lam``). See
    :func:`pipeline.core.frame_support.visible_noise_limit`.

    ``sigma_is_estimate``: ``sigma`` is the data's own estimate, an upper bound that fine
    texture raises (:func:`pipeline.core.deconvolve.common.estimate_noise_sigma`), not a
    known level. Then GCV's own minimum is kept also where it lies in its grid's first
    decade with a noise below ``sigma / GCV_TRUST`` (:func:`pipeline.core.deconvolve.gcv.
    interpolates`) *and* GCV scores the prior fit's ``lam`` clearly worse
    (:func:`pipeline.core.deconvolve.gcv.floor_predicts_better`): the data show no noise
    the model leaves unexplained, and the prior fit, fed the texture as noise, smooths
    signal away (issue 13: a ray-traced depth edge of 1/f textures reads sigma 0.005 when
    clean; the prior fit's ``lam`` 3.5e-3 left 1.1-1.5 dB to the truth-tuned ``lam``, GCV's
    floor 0.06-0.08 dB). Where GCV barely separates the two (a noisy photograph under a
    delta kernel: 1.01-1.07x), its floor would skip a real denoising (0.1-0.7 dB) and the
    prior fit stays. A known sigma keeps the two-sided rule (a 40 px comet with sigma
    given: GCV's floor 0.1 dB worse than the prior fit).

    Where GCV is trusted but its noise exceeds the data's own estimate (with
    ``sigma_is_estimate``), its ``lam`` is scaled by ``(sigma / noise_gcv)^2``: GCV's
    residual also holds what the single kernel does not explain (a stack's depth-dependent
    blur), which is no noise to smooth away, and the natural-prior Wiener filter's
    ``lam`` goes as the noise variance (``sigma^2 / s2``). The estimate, an upper bound,
    can only make the scaling smaller. Issue 13, nine-frame three-plane stacks at sigma
    0.01 over six 256 px crops: GCV read 0.0037-0.0050 against the data's 0.0031-0.0040 (the
    truth 0.0033), and its ``lam`` left 0.01-0.89 dB to the truth-tuned one; scaled, 0.00-0.04
    dB. At sigma 0.02 the two agree within 17% (-0.03 to +0.07 dB); the real stacks' GCV
    is not in this case (their results are unchanged).
    """
    if prior not in PRIORS:
        raise InputError(f"prior must be one of {PRIORS}, got {prior!r}")
    if auto not in AUTO_RULES:
        raise InputError(f"auto must be one of {AUTO_RULES}, got {auto!r}")
    lam = _per_channel("regularization", regularization, y.shape[2])
    variance = None if kernel_samples is None else kernel_variance(kernel_samples, k)
    limited = np.zeros(y.shape[2], bool)  # channels whose lam noise_limit held
    if lam is None:
        lam = np.zeros_like(sigma)
        # the kernel variance is the spectrum of an autocorrelation, 2k - 1 px wide
        support = k.shape if variance is None else tuple(2 * n - 1 for n in k.shape)
        shape = gcv.crop_shape(y.shape, support)
        trusted = np.zeros(y.shape[2], bool)
        if auto == "gcv" and shape is not None:  # where its noise agrees with the data's
            grid = gcv.kernel_grid(shape, k, prior, variance)
            found = map_channels(lambda c: gcv.gcv_regularization(y[..., c], grid), y.shape[2])
            for c, (lam_gcv, noise_gcv) in enumerate(found):
                if sigma[c] / gcv.GCV_TRUST <= noise_gcv <= gcv.GCV_TRUST * sigma[c]:
                    lam[c], trusted[c] = lam_gcv, True
                    if sigma_is_estimate and noise_gcv > sigma[c]:  # mismatch, not noise
                        lam[c] *= (sigma[c] / noise_gcv) ** 2
        fit = np.flatnonzero(~trusted)  # the prior fit decides elsewhere
        if fit.size:
            scale = _prior_scale(y, valid, sigma[fit], k, prior, fit)
            lam[fit] = np.divide(
                sigma[fit] ** 2, scale, out=np.zeros_like(scale), where=scale > 0
            )
        if sigma_is_estimate and auto == "gcv" and shape is not None:
            for c in fit:  # clean data whose texture the estimate read as noise
                lam_gcv, noise_gcv = found[c]
                if gcv.interpolates(lam_gcv, noise_gcv, sigma[c]) and gcv.floor_predicts_better(
                    y[..., c], grid, lam_gcv, lam[c]
                ):
                    lam[c], trusted[c] = lam_gcv, True
        # never amplify white noise by more than noise_gain (issue 13), nor ever by more
        # than MAX_NOISE_GAIN: with a clean input (sigma ~ 0) lam falls to its floor and a
        # lens PSF's spectral zeros amplify round-off (issue 14: an 89 px pillbox, -11 dB)
        gain = np.full(y.shape[2], MAX_NOISE_GAIN)
        if noise_gain is not None:
            gain = np.minimum(gain, float(noise_gain))
        ceiling = _per_channel("max_noise", max_noise, y.shape[2])
        if ceiling is not None:  # the result's noise std at most max_noise (issue 13),
            ok = (sigma > 0) & ~trusted  # where GCV's lam, near-optimal there, is not used
            gain[ok] = np.minimum(gain[ok], np.maximum(ceiling[ok], 1e-9) / sigma[ok])
        floors = {g: lam_for_noise_gain(k, g, prior) for g in set(gain.tolist())}
        limit = _per_channel("noise_limit", noise_limit, y.shape[2])
        if limit is not None:  # where the gain ceiling raises lam, GCV's included (issue 13)
            raised = np.maximum(lam, _LAM_MIN) < [floors[g] for g in gain.tolist()]
            ok = (sigma > 0) & raised
            held = np.maximum(limit, 1e-9) / np.where(sigma > 0, sigma, 1.0)
            limited = ok & (held < gain)
            gain[limited] = held[limited]
            floors.update({g: lam_for_noise_gain(k, g, prior) for g in set(gain.tolist())})
        lam = np.maximum(lam, [floors[g] for g in gain.tolist()])
    lam = np.clip(lam, _LAM_MIN, None)
    pad = _frame_depth(y, k, _wiener_transfer(float(lam.min()), prior, variance))
    params = {"lam": lam, "prior": prior, "pad": pad, "variance": variance}
    params["noise_limited"] = limited
    return params, pad
