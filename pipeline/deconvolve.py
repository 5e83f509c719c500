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

from dataclasses import dataclass, field

import numpy as np
from scipy import fft as sfft
from scipy import signal

from pipeline.errors import InputError

METHODS = ("wiener", "rl", "sparse")
PRIORS = ("natural", "white")
_MAD_TO_SIGMA = 0.6744897501960817  # median(|N(0, 1)|)
_KERNEL_SUM_TOL = 1e-3
_LAM_MIN = 1e-6  # floor of the Wiener noise-to-signal weight (float32 round-off level)
_DEPTH_TOL = 1e-5  # tail of the restoration filter beyond the overlap depth
_WORKERS = -1


# ----------------------------------------------------------------------------- validation
def _check_image(image) -> np.ndarray:
    """Return ``image`` as float32/float64 (rows, cols, channels), or raise InputError."""
    arr = np.asarray(image)
    if arr.ndim not in (2, 3) or arr.size == 0:
        raise InputError(
            f"image must be a non-empty (rows, cols) or (rows, cols, channels) array, got shape "
            f"{arr.shape}; pass one linear-light frame"
        )
    if not np.issubdtype(arr.dtype, np.floating) and not np.issubdtype(arr.dtype, np.integer):
        raise InputError(f"image must be a real numeric array, got dtype {arr.dtype}")
    dtype = np.float32 if arr.dtype == np.float32 else np.float64
    arr = arr.astype(dtype, copy=False)
    if not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        raise InputError(
            f"image contains {bad} NaN/Inf pixel(s); replace or mask them before deconvolving"
        )
    return arr if arr.ndim == 3 else arr[..., np.newaxis]


def check_kernel(kernel) -> np.ndarray:
    """Validate a PSF and return it as float64 normalised to sum exactly 1.

    Raises
    ------
    InputError
        If ``kernel`` is not 2-D, has an even side, has negative or non-finite
        entries, or does not sum to 1 within 1e-3.
    """
    k = np.asarray(kernel, dtype=np.float64)
    if k.ndim != 2 or k.shape[0] % 2 == 0 or k.shape[1] % 2 == 0:
        raise InputError(
            f"kernel must be a 2-D array with odd sides (centred PSF), got shape {k.shape}"
        )
    if not np.all(np.isfinite(k)) or np.any(k < 0):
        raise InputError("kernel must be finite and non-negative; got NaN/Inf or negative entries")
    total = float(k.sum())
    if abs(total - 1.0) > _KERNEL_SUM_TOL:
        raise InputError(f"kernel must sum to 1 (a PSF), got sum {total:.6g}; normalise it first")
    return k / total


def _check_saturation(saturation) -> float | None:
    if saturation is None:
        return None
    value = float(saturation)
    if not np.isfinite(value):
        raise InputError(f"saturation must be a finite level or None, got {saturation!r}")
    return value


def _check_positive(name: str, value, *, allow_zero: bool = False) -> float:
    v = float(value)
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise InputError(f"{name} must be finite and {bound}, got {value!r}")
    return v


def _per_channel(name: str, value, channels: int) -> np.ndarray | None:
    """``None`` or a scalar/sequence broadcast to one non-negative float per channel."""
    if value is None:
        return None
    arr = np.broadcast_to(np.asarray(value, dtype=np.float64), (channels,)).copy()
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise InputError(f"{name} must be finite and >= 0 (one value or one per channel)")
    return arr


# ----------------------------------------------------------------------------- statistics
def _valid_mask(y: np.ndarray, saturation: float | None, censored=None) -> np.ndarray:
    """Pixels that obey the linear model: not clipped at ``saturation`` nor ``censored``.

    ``censored`` (rows, cols) marks pixels whose true value is only known to be at
    least the observed one (e.g. a focal-stack average where a frame clipped).
    """
    valid = np.ones(y.shape, dtype=bool) if saturation is None else y < saturation
    if censored is not None:
        censored = np.asarray(censored, dtype=bool)
        if censored.shape != y.shape[:2]:
            raise InputError(f"censored must have shape {y.shape[:2]}, got {censored.shape}")
        valid &= ~censored[..., np.newaxis]
    return valid


def _noise_sigma_2d(y: np.ndarray, valid: np.ndarray) -> float:
    rows, cols = (y.shape[0] // 2) * 2, (y.shape[1] // 2) * 2
    if rows == 0 or cols == 0:
        return 0.0
    q = y[:rows, :cols].astype(np.float64)
    # finest diagonal Haar detail, orthonormal: keeps the noise variance sigma^2
    hh = (q[0::2, 0::2] - q[0::2, 1::2] - q[1::2, 0::2] + q[1::2, 1::2]) / 2.0
    v = valid[:rows, :cols]
    ok = v[0::2, 0::2] & v[0::2, 1::2] & v[1::2, 0::2] & v[1::2, 1::2]
    if not ok.any():
        return 0.0
    return float(np.median(np.abs(hh[ok])) / _MAD_TO_SIGMA)


def estimate_noise_sigma(image, *, saturation=None):
    """Robust noise level of ``image`` per channel (Donoho & Johnstone 1994).

    ``sigma = median(|HH|) / 0.6745`` of the finest diagonal Haar wavelet band
    (2x2 blocks ``(a - b - c + d) / 2``); an orthonormal band keeps white-noise
    variance, and the median ignores the few large coefficients of edges. Blocks
    touching pixels ``>= saturation`` are excluded.

    Parameters
    ----------
    image : array, (rows, cols) or (rows, cols, channels)
    saturation : float, optional
        Clipping level; ``None`` (default) means no pixel is saturated.

    Returns
    -------
    float or ndarray
        ``float`` for a 2-D image, one value per channel for a 3-D image.
    """
    y = _check_image(image)
    sat = _check_saturation(saturation)
    sig = np.array(
        [_noise_sigma_2d(y[..., c], _valid_mask(y[..., c], sat)) for c in range(y.shape[2])]
    )
    return float(sig[0]) if np.ndim(image) == 2 else sig


def _gradient_energy_2d(y: np.ndarray, valid: np.ndarray) -> float:
    """Mean of ``|grad y|^2`` (forward differences, both directions) over valid pairs."""
    total, count = 0.0, 0
    for axis in (0, 1):
        if y.shape[axis] < 2:
            continue
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis], hi[axis] = slice(None, -1), slice(1, None)
        d = np.diff(y.astype(np.float64), axis=axis)
        ok = valid[tuple(lo)] & valid[tuple(hi)]
        total += float(np.mean(d[ok] ** 2)) if ok.any() else 0.0
        count += 1
    return total * 2.0 / count if count else 0.0


@dataclass(frozen=True)
class Plan:
    """Everything a tile needs to reproduce the whole-frame result.

    Attributes
    ----------
    method : str
    kernel : ndarray
        float64, normalised.
    saturation : float or None
    noise_sigma : ndarray
        Per channel.
    params : dict
        Per-method resolved scalars/arrays (see the methods).
    depth : int
        Overlap (pixels) beyond which the input no longer changes the output by
        more than ~1e-5 of the data range (see :func:`filter_depth`).
    """

    method: str
    kernel: np.ndarray
    saturation: float | None
    noise_sigma: np.ndarray
    params: dict = field(default_factory=dict)
    depth: int = 0


def _natural_prior_scale(y, valid, sigma, kernel) -> np.ndarray:
    """Gradient variance ``s2`` of the sharp image under the 1/|w|^2 prior, per channel.

    With ``E|X(w)|^2 = N s2 / |D(w)|^2`` (``D`` the forward-difference pair), Parseval
    gives ``mean|grad y|^2 = s2 sum(k^2) + 4 sigma^2``; solve for ``s2``.
    """
    energy = np.array([_gradient_energy_2d(y[..., c], valid[..., c]) for c in range(y.shape[2])])
    s2 = (energy - 4.0 * sigma**2) / float(np.sum(kernel**2))
    return np.maximum(s2, 4.0 * sigma**2)


# ----------------------------------------------------------------------------- FFT helpers
def _kernel_fft(kernel: np.ndarray, shape: tuple[int, int], dtype) -> np.ndarray:
    """rfft2 of ``kernel`` centred at pixel (0, 0) of a periodic grid of ``shape``."""
    grid = np.zeros(shape, dtype=dtype)
    kr, kc = kernel.shape
    grid[:kr, :kc] = kernel
    grid = np.roll(grid, (-(kr // 2), -(kc // 2)), axis=(0, 1))
    return sfft.rfft2(grid, workers=_WORKERS)


def _laplacian_spectrum(shape: tuple[int, int], dtype) -> np.ndarray:
    """``|D_x(w)|^2 + |D_y(w)|^2`` of periodic forward differences on an rfft grid."""
    wy = 2.0 * np.pi * sfft.fftfreq(shape[0])[:, np.newaxis]
    wx = 2.0 * np.pi * sfft.rfftfreq(shape[1])[np.newaxis, :]
    return (4.0 - 2.0 * np.cos(wy) - 2.0 * np.cos(wx)).astype(dtype)


def _wiener_gain(k_fft, d2, lam: float, prior: str, variance=None) -> np.ndarray:
    if prior == "natural":
        reg = d2
    else:  # flat spectrum of the zero-mean part: the mean (DC) is not regularised
        reg = np.ones_like(d2)
        reg[0, 0] = 0.0
    denominator = np.abs(k_fft) ** 2 + lam * reg  # Wiener, Sec. 4.3 [24]
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
    autocorrelation = np.mean(
        [signal.fftconvolve(d, d[::-1, ::-1], mode="full") for d in diffs], axis=0
    )

    def on_grid(rshape: tuple[int, int]) -> np.ndarray:
        shape = (rshape[0], 2 * (rshape[1] - 1))  # grids here are even (see _fast_len)
        return np.abs(_kernel_fft(autocorrelation, shape, np.float64))

    return on_grid


def _tail_depth(h: np.ndarray) -> int:
    """Smallest Chebyshev radius ``d`` with ``sum |h| over max(|dx|,|dy|) > d`` < tol."""
    n0, n1 = h.shape
    i0 = np.minimum(np.arange(n0), n0 - np.arange(n0))
    i1 = np.minimum(np.arange(n1), n1 - np.arange(n1))
    cheb = np.maximum(i0[:, np.newaxis], i1[np.newaxis, :])
    mass = np.bincount(cheb.ravel(), np.abs(h).ravel())
    tail = np.concatenate([np.cumsum(mass[::-1])[::-1][1:], [0.0]])
    return int(np.argmax(tail < _DEPTH_TOL * mass.sum()))


def filter_depth(kernel: np.ndarray, transfer, *, limit: int = 4096) -> int:
    """Support radius of a linear restoration filter, from its impulse response.

    ``transfer(k_fft, d2)`` returns the filter on an rfft grid. The grid grows until
    the filter's mass beyond the returned radius is below 1e-5 of its total (or the
    grid reaches ``limit``): input farther away than that changes the output by
    less than 1e-5 of the data range.
    """
    n = _fast_len(max(8 * max(kernel.shape), 256))
    while True:
        shape = (n, n)
        h = sfft.irfft2(
            transfer(
                _kernel_fft(kernel, shape, np.float64), _laplacian_spectrum(shape, np.float64)
            ),
            s=shape,
            workers=_WORKERS,
        )
        depth = _tail_depth(h)
        if depth < n // 4 or n >= limit:
            return min(depth, n // 2)
        n = _fast_len(2 * n)


def _frame_depth(y: np.ndarray, kernel: np.ndarray, transfer) -> int:
    """:func:`filter_depth`, capped at the frame's larger side (reflecting farther adds
    nothing the frame does not already hold; a tile that deep is the whole frame)."""
    side = max(y.shape[:2])
    return min(filter_depth(kernel, transfer, limit=2 * side), side)


def _fast_len(n: int) -> int:
    """A fast, even FFT length >= n (even, so an rfft grid determines its full shape)."""
    return 2 * sfft.next_fast_len((int(n) + 1) // 2, real=True)


def _fast_shape(shape: tuple[int, int]) -> tuple[int, int]:
    return tuple(_fast_len(s) for s in shape)


# ----------------------------------------------------------------------------- Wiener
def _taper_pad(y: np.ndarray, pad: int, taper: int, shape: tuple[int, int]) -> np.ndarray:
    """Reflect ``y`` by ``pad`` px, then fade to its mean over the rest of ``shape``.

    The frame sits at offset ``(pad + taper, pad + taper)``; the fade is a raised
    cosine, so the periodic extension is continuous and FFT wrap-around is smooth.
    """
    before = pad + taper
    widths = [(before, n - s - before) for s, n in zip(y.shape, shape, strict=True)]
    out = np.pad(y, widths, mode="symmetric")
    mean = float(np.mean(y))
    weights = []
    for (b, a), s in zip(widths, y.shape, strict=True):
        w = np.ones(b + s + a)
        left = np.arange(b - pad)
        w[: b - pad] = 0.5 - 0.5 * np.cos(np.pi * (left + 0.5) / max(b - pad, 1))
        fade_after = a - pad
        right = np.arange(fade_after)
        w[b + s + pad :] = 0.5 + 0.5 * np.cos(np.pi * (right + 0.5) / max(fade_after, 1))
        weights.append(w)
    taper_w = np.outer(weights[0], weights[1]).astype(y.dtype)
    return (mean + taper_w * (out - mean)).astype(y.dtype, copy=False)


def _wiener_channel(y, valid, kernel, lam, prior, pad, passes, variance=None) -> np.ndarray:
    taper = max(max(kernel.shape), 16)
    shape = _fast_shape((y.shape[0] + 2 * (pad + taper), y.shape[1] + 2 * (pad + taper)))
    k_fft = _kernel_fft(kernel, shape, y.dtype)
    gain = _wiener_gain(k_fft, _laplacian_spectrum(shape, y.dtype), lam, prior, variance)
    gain = gain.astype(k_fft.dtype, copy=False)
    crop = tuple(slice(pad + taper, pad + taper + n) for n in y.shape)
    filled = y
    for step in range(passes + 1):
        x_fft = gain * sfft.rfft2(_taper_pad(filled, pad, taper, shape), workers=_WORKERS)
        x = sfft.irfft2(x_fft, s=shape, workers=_WORKERS)[crop]
        if step == passes:
            return x
        # saturated pixels are censored: fill them with max(k*x, y) and re-solve (EM)
        reblurred = sfft.irfft2(k_fft * x_fft, s=shape, workers=_WORKERS)[crop]
        filled = np.where(valid, y, np.maximum(reblurred, y)).astype(y.dtype, copy=False)
    raise AssertionError("unreachable")


def _wiener_transfer(lam: float, prior: str, variance=None):
    return lambda k_fft, d2: _wiener_gain(k_fft, d2, lam, prior, variance)


# ----------------------------------------------------------------------------- extended domain
@dataclass(frozen=True)
class _Domain:
    """Periodic grid holding the frame plus a margin of the kernel radius all round."""

    shape: tuple[int, int]
    crop: tuple[slice, slice]
    k_fft: np.ndarray

    @classmethod
    def build(cls, frame_shape, kernel, dtype) -> _Domain:
        margin = [s // 2 for s in kernel.shape]
        shape = _fast_shape(tuple(f + 2 * m for f, m in zip(frame_shape, margin, strict=True)))
        crop = tuple(slice(m, m + f) for f, m in zip(frame_shape, margin, strict=True))
        return cls(shape, crop, _kernel_fft(kernel, shape, dtype))

    def embed(self, a: np.ndarray, fill=0.0) -> np.ndarray:
        out = np.full(self.shape, fill, dtype=a.dtype)
        out[self.crop] = a
        return out

    def reflect(self, a: np.ndarray) -> np.ndarray:
        """``a`` on the frame, mirrored into the margin (an initial estimate)."""
        r0, r1 = self.crop[0].start, self.crop[1].start
        widths = ((r0, self.shape[0] - a.shape[0] - r0), (r1, self.shape[1] - a.shape[1] - r1))
        return np.pad(a, widths, mode="symmetric")

    def conv(self, x: np.ndarray) -> np.ndarray:
        return sfft.irfft2(
            self.k_fft * sfft.rfft2(x, workers=_WORKERS), s=self.shape, workers=_WORKERS
        )

    def corr(self, x: np.ndarray) -> np.ndarray:
        return sfft.irfft2(
            np.conj(self.k_fft) * sfft.rfft2(x, workers=_WORKERS), s=self.shape, workers=_WORKERS
        )


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
        :func:`estimate_noise_sigma` when omitted.
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
        sigma = np.array([_noise_sigma_2d(y[..., c], valid[..., c]) for c in range(y.shape[2])])
    builder = {"wiener": _plan_wiener, "rl": _plan_rl, "sparse": _plan_sparse}[method]
    params, depth = builder(y, valid, k, sigma, **options)
    return Plan(method, k, sat, sigma, params, depth)


def _plan_wiener(
    y,
    valid,
    k,
    sigma,
    *,
    prior="natural",
    regularization=None,
    saturation_passes=3,
    kernel_samples=None,
):
    if prior not in PRIORS:
        raise InputError(f"prior must be one of {PRIORS}, got {prior!r}")
    passes = int(saturation_passes)
    if passes < 0:
        raise InputError(f"saturation_passes must be >= 0, got {saturation_passes!r}")
    lam = _per_channel("regularization", regularization, y.shape[2])
    if lam is None:
        if prior == "natural":
            scale = _natural_prior_scale(y, valid, sigma, k)
        else:  # white spectrum: E|X|^2 = N s0^2, var(y) = s0^2 sum(k^2) + sigma^2
            var = np.array(
                [
                    float(np.var(y[..., c][valid[..., c]])) if valid[..., c].any() else 0.0
                    for c in range(y.shape[2])
                ]
            )
            scale = np.maximum((var - sigma**2) / float(np.sum(k**2)), sigma**2)
        lam = np.divide(sigma**2, scale, out=np.zeros_like(sigma), where=scale > 0)
    lam = np.clip(lam, _LAM_MIN, None)
    variance = None if kernel_samples is None else kernel_variance(kernel_samples, k)
    pad = _frame_depth(y, k, _wiener_transfer(float(lam.min()), prior, variance))
    # each EM pass re-reads data filled by the previous one: the support grows per pass
    depth = pad * (passes + 1) if not np.all(valid) else pad
    params = {"lam": lam, "prior": prior, "passes": passes, "pad": pad, "variance": variance}
    return params, depth


def _plan_rl(y, valid, k, sigma, *, iterations=30, damping=None):
    iterations = int(iterations)
    if iterations < 0:
        raise InputError(f"iterations must be >= 0, got {iterations!r}")
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


def _plan_sparse(y, valid, k, sigma, *, alpha=0.8, weight=0.2, iterations=50, rho=(3e-3, 0.3)):
    alpha = float(alpha)
    if not 0 < alpha <= 1:
        raise InputError(f"alpha must be in (0, 1], got {alpha!r}")
    weight = _check_positive("weight", weight, allow_zero=True)
    iterations = int(iterations)
    if iterations < 1:
        raise InputError(f"iterations must be >= 1, got {iterations!r}")
    rho = tuple(_check_positive("rho", r) for r in rho)
    s2 = _natural_prior_scale(y, valid, sigma, k)
    # MAP: |M(k*x - y)|^2 / (2 sigma^2) + sum |g / s|^alpha, s the per-direction gradient RMS
    s = np.sqrt(np.maximum(s2 / 2.0, 1e-24))
    mu = weight * sigma**2 / s**alpha
    # reach of one x-step (its filter K*/(|K|^2 + |D|^2)), spread diffusively over the
    # iterations; a heuristic (the w-step is not linear), see pipeline.tiling
    step = _frame_depth(y, k, _wiener_transfer(1.0, "natural")) + max(k.shape) // 2
    depth = min(int(np.ceil(step * np.sqrt(iterations))), max(y.shape[:2]))
    return {"mu": mu, "alpha": alpha, "iterations": iterations, "rho": rho}, depth


def restore(image, p: Plan, censored=None) -> np.ndarray:
    """Apply a :class:`Plan` to ``image``, treated as a complete frame.

    Returns an array of the input's shape, float32 for float32 input else float64.
    """
    y = _check_image(image)
    valid = _valid_mask(y, p.saturation, censored)
    out = np.empty_like(y)
    prm = p.params
    for c in range(y.shape[2]):
        yc, vc = y[..., c], valid[..., c]
        if p.method == "wiener":
            passes = prm["passes"] if not vc.all() else 0
            xc = _wiener_channel(
                yc,
                vc,
                p.kernel,
                float(prm["lam"][c]),
                prm["prior"],
                prm["pad"],
                passes,
                prm["variance"],
            )
        elif p.method == "rl":
            thr = None if prm["threshold"] is None else float(prm["threshold"][c])
            xc = _rl_channel(yc, vc, p.kernel, prm["iterations"], float(prm["background"][c]), thr)
        else:
            xc = _sparse_channel(
                yc, vc, p.kernel, float(prm["mu"][c]), prm["alpha"], prm["iterations"], prm["rho"]
            )
        out[..., c] = xc
    return out if np.ndim(image) == 3 else out[..., 0]


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
    saturation_passes=3,
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
        Saturated pixels are censored data: they are filled with
        ``max(k * x_hat, y)`` from the current estimate and the Wiener solve is
        repeated ``saturation_passes`` times (EM for missing data).

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
        saturation_passes=saturation_passes,
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
