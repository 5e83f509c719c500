"""What every deconvolution method shares: input checks, the clipped-pixel mask, the
noise estimate, the :class:`Plan`, the padded FFT domain and the filter's reach.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from scipy import fft as sfft

from pipeline.core import spectra, validate
from pipeline.errors import InputError

METHODS = ("wiener", "rl", "sparse")
PRIORS = ("natural", "white")
_MAD_TO_SIGMA = 0.6744897501960817  # median(|N(0, 1)|)
_KERNEL_SUM_TOL = 1e-3
_LAM_MIN = 1e-6  # floor of the Wiener noise-to-signal weight (float32 round-off level)
_DEPTH_TOL = 1e-5  # tail of the restoration filter beyond the overlap depth
# FFT threads: None means scipy.fft's per-thread default (1 unless a caller sets
# ``scipy.fft.set_workers``), so there is one level of parallelism: the whole-frame path of
# pipeline.parallel.tiling sets it to the cores, tiles in dask threads run single-threaded.
_WORKERS = None
# Colour channels restored side by side: set by the whole-frame path of
# pipeline.parallel.tiling (:func:`channel_threads`); 1 elsewhere, and in the channel
# threads themselves (a context variable does not pass into new threads), so tiles in dask
# threads and nested calls stay serial.
_CHANNEL_THREADS: ContextVar[int] = ContextVar("channel_threads", default=1)


@contextmanager
def channel_threads(n: int):
    """Within the block, :func:`map_channels` runs up to ``n`` channels at once.

    Each channel thread's FFTs are single-threaded (``scipy.fft``'s worker count is
    per thread), so the cores are used by one level of parallelism, not two.
    """
    token = _CHANNEL_THREADS.set(max(1, int(n)))
    try:
        yield
    finally:
        _CHANNEL_THREADS.reset(token)


def map_channels(fn: Callable[[int], object], channels: int) -> list:
    """``[fn(c) for c in range(channels)]``, on :func:`channel_threads` threads."""
    threads = min(_CHANNEL_THREADS.get(), channels)
    if threads <= 1:
        return [fn(c) for c in range(channels)]
    with ThreadPoolExecutor(threads, thread_name_prefix="flexdof-channel") as pool:
        return list(pool.map(fn, range(channels)))


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
    if allow_zero:
        return validate.non_negative(name, value)
    return validate.positive(name, value)


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
        valid[censored] = False  # every channel; a (rows, cols, 1) operand broadcast
        # over 3 channels runs numpy's inner loop 3 elements at a time (3x slower)
    return valid


SPECTRAL_CROP_PX = 1024  # side of the centre crop the spectral noise bound looks at
SPECTRAL_BAND = 0.3  # cycles/px: the bound reads the spectrum's high band only


def noise_sigma_2d(y: np.ndarray, valid: np.ndarray) -> float:
    """The lower of two upper bounds on the white-noise level (see
    :func:`estimate_noise_sigma`)."""
    haar = haar_noise_sigma(y, valid)
    return min(haar, _spectral_noise_bound(y, valid)) if haar > 0 else 0.0


def haar_noise_sigma(y: np.ndarray, valid: np.ndarray) -> float:
    """``median(|HH|) / 0.6745`` of the finest diagonal Haar band of a 2-D ``y`` over 2x2
    blocks of ``valid`` pixels (Donoho & Johnstone 1994); 0 when none is valid."""
    rows, cols = (y.shape[0] // 2) * 2, (y.shape[1] // 2) * 2
    if rows == 0 or cols == 0:
        return 0.0
    q = y[:rows, :cols]
    # finest diagonal Haar detail (a - b - c + d) / 2, orthonormal: keeps the noise
    # variance sigma^2. In float64, cast as it is read (no float64 copy of the image);
    # the halving, exact, is applied to the median (the frame guard reads a 1024 px crop
    # of every frame: 20% faster than the plain expression, the same bits)
    hh = np.subtract(q[0::2, 0::2], q[0::2, 1::2], dtype=np.float64)
    hh -= q[1::2, 0::2]
    hh += q[1::2, 1::2]
    v = valid[:rows, :cols]
    ok = v[0::2, 0::2] & v[0::2, 1::2] & v[1::2, 0::2] & v[1::2, 1::2]
    if not ok.any():
        return 0.0
    detail = np.abs(hh, out=hh)[ok]  # a copy: the median may reorder it
    return float(exact_median(detail) / 2.0 / _MAD_TO_SIGMA)


def _spectral_noise_bound(y: np.ndarray, valid: np.ndarray) -> float:
    """``sqrt(median |Y(w)|^2 / N / ln 2)`` over the high band of a fully valid centre crop.

    White noise of std ``sigma`` has, at every frequency, ``|Y(w)|^2 / N`` exponentially
    distributed with mean ``sigma^2`` (median ``sigma^2 ln 2``); any image content adds
    to it. Returns ``inf`` (no bound) when the crop holds clipped/censored pixels (flat
    clipped areas would lower the band's power) or is too small to have a band.
    """
    r0 = max(0, (y.shape[0] - SPECTRAL_CROP_PX) // 2)
    c0 = max(0, (y.shape[1] - SPECTRAL_CROP_PX) // 2)
    crop = (slice(r0, r0 + SPECTRAL_CROP_PX), slice(c0, c0 + SPECTRAL_CROP_PX))
    if min(y[crop].shape) < 8 or not valid[crop].all():
        return float("inf")
    q = y[crop].astype(np.float64)
    power = np.abs(sfft.rfft2(q - q.mean(), workers=_WORKERS)) ** 2 / q.size
    return float(np.sqrt(exact_median(power[_high_band(q.shape)]) / np.log(2)))


@lru_cache(maxsize=8)
def _high_band(shape: tuple[int, int]) -> np.ndarray:
    """The rfft2 bins of ``shape`` beyond ``SPECTRAL_BAND`` cycles/px (read-only; cached:
    every frame of a stack has the same crop, and building the mask took a quarter of
    the bound's time)."""
    radius = np.hypot(sfft.fftfreq(shape[0])[:, None], sfft.rfftfreq(shape[1])[None, :])
    band = radius > SPECTRAL_BAND
    band.flags.writeable = False
    return band


MEDIAN_SAMPLE = 1024  # values :func:`exact_median` brackets the median with


def exact_median(values: np.ndarray) -> float:
    """``np.median`` of a 1-D float array (the same number), 2.6x faster for 10^5 values
    and more, in the order it may leave ``values`` in.

    The median of a regular sample of ``MEDIAN_SAMPLE`` values, plus or minus three
    standard errors of its rank, brackets the median's rank; only the values inside the
    bracket are partitioned (a tenth of them), after counting those below it. Where
    the bracket misses (a regular sample of a sorted or periodic array) and for NaNs or
    small arrays, ``np.median`` itself. The noise estimates take a median of 260 000
    values per channel of every frame with the frame guard.
    """
    n = values.size
    if n < 4 * MEDIAN_SAMPLE or np.isnan(np.max(values)):
        return float(np.median(values))
    sample = np.sort(values[:: n // MEDIAN_SAMPLE])
    middle, spread = sample.size // 2, int(1.5 * np.sqrt(sample.size)) + 1
    low, high = sample[max(0, middle - spread)], sample[min(sample.size - 1, middle + spread)]
    below = int(np.count_nonzero(values < low))
    inside = values[(values >= low) & (values <= high)]
    first, last = (n - 1) // 2 - below, n // 2 - below  # the middle ranks among ``inside``
    if first < 0 or last >= inside.size:
        return float(np.median(values))
    inside.partition((first, last))
    return float(np.mean(inside[first : last + 1]))  # np.median's mean of the middle pair


def estimate_noise_sigma(image, *, saturation=None):
    """Robust noise level of ``image`` per channel (Donoho & Johnstone 1994).

    ``sigma = median(|HH|) / 0.6745`` of the finest diagonal Haar wavelet band
    (2x2 blocks ``(a - b - c + d) / 2``); an orthonormal band keeps white-noise
    variance, and the median ignores the few large coefficients of edges. Blocks
    touching pixels ``>= saturation`` are excluded.

    Pixel-scale texture also lives in that band (a checkerboard's HH coefficients are
    all large: read as noise of std 1.2 on a 0.1/0.9 board), so the result is the
    lower of it and a second bound, from the high band of the power spectrum:
    white noise spreads evenly over all frequencies, a texture concentrates in a few,
    and both bounds are only raised by image content, never lowered.

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
        map_channels(lambda c: noise_sigma_2d(y[..., c], _valid_mask(y[..., c], sat)), y.shape[2])
    )
    return float(sig[0]) if np.ndim(image) == 2 else sig


def _gradient_energy_2d(y: np.ndarray, valid: np.ndarray) -> float:
    """Mean of ``|grad y|^2`` (forward differences, both directions) over valid pairs."""
    total, count = 0.0, 0
    y64 = y.astype(np.float64)
    for axis in (0, 1):
        if y.shape[axis] < 2:
            continue
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis], hi[axis] = slice(None, -1), slice(1, None)
        d = np.diff(y64, axis=axis)
        d *= d
        ok = valid[tuple(lo)] & valid[tuple(hi)]
        pairs = int(np.count_nonzero(ok))
        total += float(np.sum(d, where=ok)) / pairs if pairs else 0.0
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


# ----------------------------------------------------------------------------- FFT helpers
def _kernel_fft(kernel: np.ndarray, shape: tuple[int, int], dtype) -> np.ndarray:
    """rfft2 of ``kernel`` centred at pixel (0, 0) of a periodic grid of ``shape``."""
    return spectra.centred_fft(kernel, shape, real=True, dtype=dtype, workers=_WORKERS)


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
    cosine, so the periodic extension is continuous and FFT wrap-around is smooth. The
    fade weight is the outer product of one profile per axis, 1 except in the bands
    beyond the reflection, so only those bands are touched (twice at the corners).
    """
    before = pad + taper
    widths = [(before, n - s - before) for s, n in zip(y.shape, shape, strict=True)]
    out = np.pad(y, widths, mode="symmetric")
    mean = y.dtype.type(np.mean(y))
    for axis, ((b, a), s) in enumerate(zip(widths, y.shape, strict=True)):
        w = np.ones(b + s + a)
        left = np.arange(b - pad)
        w[: b - pad] = 0.5 - 0.5 * np.cos(np.pi * (left + 0.5) / max(b - pad, 1))
        fade_after = a - pad
        right = np.arange(fade_after)
        w[b + s + pad :] = 0.5 + 0.5 * np.cos(np.pi * (right + 0.5) / max(fade_after, 1))
        w = w.astype(y.dtype)
        for band in (slice(0, b - pad), slice(b + s + pad, None)):
            view = out[band] if axis == 0 else out[:, band]
            profile = w[band][:, np.newaxis] if axis == 0 else w[band][np.newaxis, :]
            view -= mean
            view *= profile
            view += mean
    return out


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



def prior_spectrum(d2: np.ndarray, prior: str) -> np.ndarray:
    """The regulariser's spectrum on an rfft grid: ``d2 = |D|^2`` (the Laplacian's, for
    the natural prior), else flat on the zero-mean part (the mean, DC, is not
    regularised)."""
    if prior == "natural":
        return d2
    reg = np.ones_like(d2)
    reg[0, 0] = 0.0
    return reg


def spectral_grid(kernel: np.ndarray, shape: tuple[int, int], prior: str):
    """``|K|^2``, the regulariser's spectrum (``|D|^2`` for the natural prior, else flat
    with the mean unregularised) and the rfft weights (interior columns stand for two) on
    an rfft grid of ``shape``, in float64."""
    k2 = np.abs(_kernel_fft(kernel, shape, np.float64)) ** 2
    reg = prior_spectrum(_laplacian_spectrum(shape, np.float64), prior)
    weight = np.full(k2.shape, 2.0)
    weight[:, 0] = 1.0
    if shape[1] % 2 == 0:
        weight[:, -1] = 1.0
    return k2, reg, weight


def _laplacian_spectrum(shape: tuple[int, int], dtype) -> np.ndarray:
    """``|D_x(w)|^2 + |D_y(w)|^2`` of periodic forward differences on an rfft grid."""
    wy = 2.0 * np.pi * sfft.fftfreq(shape[0])[:, np.newaxis]
    wx = 2.0 * np.pi * sfft.rfftfreq(shape[1])[np.newaxis, :]
    return (4.0 - 2.0 * np.cos(wy) - 2.0 * np.cos(wx)).astype(dtype)
