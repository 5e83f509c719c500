"""Non-blind deconvolution of a sweep or focal-stack image with its IPSF (Sec. 4.2, 4.3).

Forward model: ``y = k * x + n`` on linear-light data, with ``k`` the integrated PSF
(Eq. 5; odd-sized, centred, non-negative, sums to 1) and ``n`` white Gaussian noise
of standard deviation ``sigma`` (Sec. 4.3). Three estimators of ``x``:

* :func:`wiener`: Wiener deconvolution [24] with a natural-image prior, the
  estimator the paper uses for its SNR analysis (Sec. 4.3);
* :func:`richardson_lucy`: Richardson-Lucy [24] with masked data, a known
  background (handles zero and negative pixels) and optional damping;
* :func:`sparse`: MAP with a hyper-Laplacian gradient prior (Krishnan & Fergus
  2009) solved by ADMM with an unknown-boundary data split (Almeida & Figueiredo
  2013); the quality option.

Global statistics (noise level, gradient energy, background) are resolved once on
the whole image by :func:`plan`; :func:`restore` then applies the plan to an array
treated as a complete frame. :func:`deconvolve` is ``restore(image, plan(image))``;
``pipeline.tiling`` applies the same plan to overlapping tiles.

Boundaries. Wiener pads each frame by reflection over ``plan.depth`` pixels (the
support of its restoration filter, see :func:`filter_depth`) plus a cosine taper to
the frame mean, so the FFT's wrap-around and the taper's ringing do not reach the
frame. The iterative methods estimate ``x`` on a domain extended by the kernel radius
beyond the frame and fit only observed, unsaturated pixels (a mask in the data term),
so nothing outside the frame is assumed.
"""

from __future__ import annotations

import numpy as np

from pipeline.core.deconvolve.common import (
    METHODS,
    Plan,
    _check_image,
    _check_saturation,
    _per_channel,
    _valid_mask,
    check_kernel,
    map_channels,
    noise_sigma_2d,
)
from pipeline.core.deconvolve.rl import _plan_rl, _rl_channel
from pipeline.core.deconvolve.sparse import _plan_sparse, _sparse_channel
from pipeline.core.deconvolve.wiener import (
    _plan_wiener,
    _wiener_channel,
    _wiener_grid,
    _wiener_spectra,
)
from pipeline.errors import InputError


# ----------------------------------------------------------------------------- plan / restore
def plan(
    image,
    kernel,
    *,
    method: str = "wiener",
    saturation=None,
    noise_sigma=None,
    censored=None,
    **options,
) -> Plan:
    """Resolve the global quantities of a deconvolution once, on the whole image.

    Parameters
    ----------
    image : array (rows, cols[, channels])
        Linear-light data (numpy; ``pipeline.tiling`` materialises dask input).
    kernel : array
        The PSF/IPSF (odd sides, centred, non-negative, sums to 1).
    method : {"wiener", "rl", "sparse"}
    saturation : float, optional
        Pixels ``>= saturation`` are clipped and excluded from the data term.
    noise_sigma : float or sequence, optional
        Noise standard deviation per channel; estimated by
        :func:`estimate_noise_sigma` when omitted (Wiener then treats it as an upper
        bound: fine texture raises it, see ``_plan_wiener``).
    censored : bool array (rows, cols), optional
        Pixels treated like clipped ones: excluded from the data term, their true
        value at least the observed one (pass the same mask to :func:`restore`).
    **options
        The method's options, see :func:`wiener`, :func:`richardson_lucy`,
        :func:`sparse`.
    """
    if method not in METHODS:
        raise InputError(f"method must be one of {METHODS}, got {method!r}")
    y = _check_image(image)
    k = check_kernel(kernel)
    sat = _check_saturation(saturation)
    valid = _valid_mask(y, sat, censored)
    sigma = _per_channel("noise_sigma", noise_sigma, y.shape[2])
    if sigma is None:
        sigma = np.array(
            map_channels(lambda c: noise_sigma_2d(y[..., c], valid[..., c]), y.shape[2])
        )
        if method == "wiener":  # an upper bound, not a known level (see _plan_wiener)
            options = {**options, "sigma_is_estimate": True}
    builder = {"wiener": _plan_wiener, "rl": _plan_rl, "sparse": _plan_sparse}[method]
    params, depth = builder(y, valid, k, sigma, **options)
    return Plan(method, k, sat, sigma, params, depth)


def restore(image, p: Plan, censored=None) -> np.ndarray:
    """Apply a :class:`Plan` to ``image``, treated as a complete frame.

    Returns an array of the input's shape, float32 for float32 input else float64.
    """
    y = _check_image(image)
    out = np.empty_like(y)
    prm = p.params
    if p.method == "wiener":  # kernel, variance and Laplacian spectra: once per grid
        shared = _shared_wiener_spectra(p, y.shape[:2], y.dtype)

        def channel(c):
            lam = float(prm["lam"][c])
            out[..., c] = _wiener_channel(
                y[..., c], p.kernel, lam, prm["prior"], prm["pad"], prm["variance"], spectra=shared
            )

    else:  # the iterative methods use the data term's mask
        valid = _valid_mask(y, p.saturation, censored)

        def channel(c):
            yc, vc = y[..., c], valid[..., c]
            if p.method == "rl":
                thr = None if prm["threshold"] is None else float(prm["threshold"][c])
                bg = float(prm["background"][c])
                out[..., c] = _rl_channel(yc, vc, p.kernel, prm["iterations"], bg, thr)
            else:
                mu = float(prm["mu"][c])
                out[..., c] = _sparse_channel(
                    yc, vc, p.kernel, mu, prm["alpha"], prm["iterations"], prm["rho"]
                )

    map_channels(channel, y.shape[2])
    return out if np.ndim(image) == 3 else out[..., 0]


def _shared_wiener_spectra(p: Plan, frame_shape, dtype):
    """:func:`_wiener_spectra` for a frame (or tile) of ``frame_shape``, cached in the plan
    per FFT grid (tiles of one size share them; a few grids at most per plan)."""
    grid, _ = _wiener_grid(frame_shape, p.kernel, p.params["pad"])
    cache = p.params.setdefault("_spectra", {})
    key = (grid, np.dtype(dtype).str)
    found = cache.get(key)
    if found is None:
        found = _wiener_spectra(grid, p.kernel, p.params["prior"], p.params["variance"], dtype)
        cache[key] = found  # a race computes it twice, harmlessly
    return found


# ----------------------------------------------------------------------------- public API
def deconvolve(image, kernel, *, method: str = "wiener", saturation=None, censored=None, **options):
    """Deconvolve ``image`` with ``kernel`` (Sec. 4.2): dispatch to a method.

    Parameters
    ----------
    image : array (rows, cols) or (rows, cols, channels)
        Linear-light image; NaN/Inf raise :class:`~pipeline.errors.InputError`.
    kernel : array
        PSF/IPSF: odd sides, centred, non-negative, sums to 1.
    method : {"wiener", "rl", "sparse"}
    saturation : float, optional
        Clipping level (1.0 for normalised data); ``None``: nothing is saturated.
    **options
        ``noise_sigma`` and the options of :func:`wiener`, :func:`richardson_lucy` or
        :func:`sparse`.

    Returns
    -------
    ndarray
        Same shape; float32 for float32 input, else float64. Never clipped.

    Examples
    --------
    An asymmetric kernel (a one-sided motion blur): restoring with it must undo
    the blur, which a flipped kernel would not.

    >>> import numpy as np
    >>> from scipy.ndimage import convolve
    >>> sharp = np.random.default_rng(0).uniform(0.2, 0.8, (64, 64))
    >>> kernel = np.zeros((7, 7)); kernel[3, 3:] = [0.4, 0.3, 0.2, 0.1]
    >>> blurred = convolve(sharp, kernel, mode="wrap")
    >>> restored = deconvolve(blurred, kernel, noise_sigma=1e-4)
    >>> def rms(x): return float(np.sqrt(np.mean((x - sharp)[8:-8, 8:-8] ** 2)))
    >>> rms(restored) < 0.1 * rms(blurred)
    True
    >>> rms(deconvolve(blurred, kernel[::-1, ::-1], noise_sigma=1e-4)) > rms(blurred)
    True
    """
    p = plan(image, kernel, method=method, saturation=saturation, censored=censored, **options)
    return restore(image, p, censored)


def wiener(
    image,
    kernel,
    *,
    noise_sigma=None,
    prior="natural",
    regularization=None,
    saturation=None,
    kernel_samples=None,
):
    """Wiener deconvolution with a natural-image prior (Sec. 4.3, [24]).

    ``X = K* Y / (|K|^2 + lam |D|^2)`` per channel: the Wiener filter for white noise
    of variance ``sigma^2`` and an image power spectrum ``N s2 / |D(w)|^2`` (the
    1/|w|^2 fall-off of natural images that also weights Eq. 8), i.e. a Gaussian prior
    on the image gradients (Tikhonov on forward differences, ``|D|^2 = |D_x|^2 +
    |D_y|^2``), with ``lam = sigma^2 / s2``.

    Parameters
    ----------
    noise_sigma : float or sequence, optional
        Estimated with :func:`estimate_noise_sigma` when omitted.
    prior : {"natural", "white"}
        ``"white"``: flat image spectrum, ``|D|^2`` replaced by 1 (classic Wiener).
    regularization : float or sequence, optional
        ``lam`` directly; by default ``sigma^2 / s2``, with ``s2`` fitted to the
        observed gradient energy (``mean|grad y|^2 = s2 sum k^2 + 4 sigma^2``).
        Floored at 1e-6.
    kernel_samples : array (n, kh, kw), optional
        The blur at n depths (e.g. a focal stack's per-depth kernels); their spread
        around ``kernel`` enters the denominator (:func:`kernel_variance`).
    saturation : float, optional
        Pixels at or above it are censored data: the filter is linear and uses them as
        observed; :func:`pipeline.parallel.tiling.deconvolve_tiled` then keeps each at
        least at its observed value. (Re-solving with the censored pixels filled in, an
        EM for missing data, bought < 0.1 dB with a quarter of the pixels clipped, for
        +80% time, and was removed.)

    Notes
    -----
    The frame is reflected over the filter's support radius (:func:`filter_depth`)
    and faded to its mean beyond it before the FFT, and cropped after.
    """
    return deconvolve(
        image,
        kernel,
        method="wiener",
        saturation=saturation,
        noise_sigma=noise_sigma,
        prior=prior,
        regularization=regularization,
        kernel_samples=kernel_samples,
    )


def richardson_lucy(
    image, kernel, *, iterations=30, damping=None, noise_sigma=None, saturation=None
):
    """Richardson-Lucy deconvolution [24] with masked data and unknown boundaries.

    ``x <- x K^T(M (y + b) / (K x + b)) / K^T M`` on a domain one kernel radius larger
    than the frame (Bertero & Boccacci 2005); ``M`` is 1 on observed, unsaturated
    pixels. The known background ``b = max(0, -min y) + max(sigma, 1e-3 max|y|)``
    keeps every denominator positive, so zero and negative pixels need no clipping;
    the multiplicative update keeps ``x >= 0``.

    Parameters
    ----------
    iterations : int
    damping : float, optional
        Damped RL (White 1994): residuals below ``damping * sigma`` produce no update
        (noise is not fitted). ``None``: plain RL.
    noise_sigma : float or sequence, optional
        Used by ``damping`` and the background guard; estimated when omitted.
    saturation : float, optional
        Pixels ``>= saturation`` are left out of the data term.
    """
    return deconvolve(
        image,
        kernel,
        method="rl",
        saturation=saturation,
        noise_sigma=noise_sigma,
        iterations=iterations,
        damping=damping,
    )


def sparse(
    image,
    kernel,
    *,
    alpha=0.8,
    weight=0.2,
    iterations=50,
    rho=(3e-3, 0.3),
    noise_sigma=None,
    saturation=None,
):
    """Edge-preserving deconvolution with a hyper-Laplacian gradient prior.

    Minimises ``|M (k*x - y)|^2 / 2 + mu sum_i (|dx_i|^alpha + |dy_i|^alpha)`` (Krishnan
    & Fergus 2009) by ADMM with the splits ``z = k*x`` and ``w = grad x`` (Almeida &
    Figueiredo 2013): ``x`` lives on the frame plus a kernel-radius margin, ``M`` is 1
    on observed, unsaturated pixels, so boundaries and saturation need no padding
    guesses. ``mu = weight sigma^2 / s^alpha`` (MAP scaling; ``s`` the gradient RMS of
    the natural-image fit used by :func:`wiener`); the penalty grows geometrically
    over ``rho`` (continuation) and the ``w``-step is :func:`hyper_laplacian_prox`.

    Parameters
    ----------
    alpha : float in (0, 1]
        0.8 as in Krishnan & Fergus; 1 gives anisotropic TV.
    weight : float
        Prior strength multiplier.
    iterations : int
    rho : (float, float)
        First and last ADMM penalty.
    """
    return deconvolve(
        image,
        kernel,
        method="sparse",
        saturation=saturation,
        noise_sigma=noise_sigma,
        alpha=alpha,
        weight=weight,
        iterations=iterations,
        rho=rho,
    )
