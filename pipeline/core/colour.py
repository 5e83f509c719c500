"""The sRGB transfer function (IEC 61966-2-1), both ways, in float32 or float64; the grey
image of a colour one; a per-pixel scale of every channel, and a grey image moved to a
target keeping the hue.
"""

from __future__ import annotations

import cv2
import numpy as np

# --- sRGB transfer functions (IEC 61966-2-1) -------------------------------------------------


def _float_dtype(x: np.ndarray) -> np.dtype:
    return np.dtype(np.float32) if x.dtype == np.float32 else np.dtype(np.float64)


def srgb_to_linear(encoded: np.ndarray) -> np.ndarray:
    """The exact sRGB EOTF: encoded values in [0, 1] -> linear light.

    ``c / 12.92`` for ``c <= 0.04045``, else ``((c + 0.055) / 1.055) ** 2.4``.
    Values outside [0, 1] follow the same formulas (no clipping). float32 in ->
    float32 out, anything else -> float64.
    """
    c = np.asarray(encoded)
    dtype = _float_dtype(c)
    c = c.astype(dtype, copy=False)
    high = ((np.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4
    return np.where(c <= 0.04045, c / 12.92, high).astype(dtype, copy=False)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """The exact inverse sRGB EOTF: linear light -> encoded values.

    ``12.92 l`` for ``l <= 0.0031308``, else ``1.055 l ** (1/2.4) - 0.055``.
    No clipping; float32 in -> float32 out, anything else -> float64.
    """
    lin = np.asarray(linear)
    dtype = _float_dtype(lin)
    lin = lin.astype(dtype, copy=False)
    base = np.maximum(lin, dtype.type(0.0031308))
    if base.ndim >= 1 and base.size:  # cv2.pow: SIMD, same result as numpy to 1 ulp
        out = cv2.pow(np.ascontiguousarray(base.reshape(-1, base.shape[-1])), 1 / 2.4)
        out = out.reshape(base.shape)
    else:
        out = np.array(np.power(base, dtype.type(1 / 2.4)), dtype=dtype)
    out *= dtype.type(1.055)  # in place: this runs on every written image
    out -= dtype.type(0.055)
    low = lin <= 0.0031308
    out[low] = dtype.type(12.92) * lin[low]
    return out


_MEAN = np.full((1, 3), 1 / 3, np.float32)


def mean_grey(image: np.ndarray) -> np.ndarray:
    """The mean of a ``(rows, cols, channels)`` image's channels (a ``(rows, cols)`` image
    is returned as it is): the grey image whose bands the end frames' detail compares
    (:func:`pipeline.jobs.ends.keep_end_detail`), the edge measure
    (:mod:`pipeline.core.quality`) and the end correction's check. float32 or float64 in,
    the same out."""
    if image.ndim == 2:
        return image
    if image.shape[2] == 3:
        return cv2.transform(image, _MEAN)  # 1.6 ms for 2048x1536 (numpy's mean: 52 ms)
    return image.mean(axis=2).astype(image.dtype, copy=False)  # e.g. a single channel axis


STRIP_ROWS = 64  # rows per strip of :func:`scale_channels` (its weights' copy stays in cache)


def scale_channels(image: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """``image *= weight`` in every channel, in place (``weight`` ``(rows, cols)``, ``image``
    that or ``(rows, cols, channels)``); returns ``image``.

    The same products as numpy's broadcast ``image * weight[..., None]``, by strips of
    ``STRIP_ROWS`` rows with the weight's rows repeated per channel (``cv2.merge``): 4
    against 11 ms on a 3 Mpx RGB image, where the broadcast walks the channels with a
    stride of one.
    """
    if image.ndim == 2:
        return np.multiply(image, weight, out=image)
    channels = image.shape[2]
    for r0 in range(0, image.shape[0], STRIP_ROWS):
        rows = slice(r0, r0 + STRIP_ROWS)
        repeated = cv2.merge([np.ascontiguousarray(weight[rows])] * channels)
        np.multiply(image[rows], repeated.reshape(image[rows].shape), out=image[rows])
    return image


def move_grey(image: np.ndarray, grey: np.ndarray, target: np.ndarray, *, max_gain: float) -> None:
    """Change ``image`` (in place; ``(rows, cols)`` or ``(rows, cols, channels)``) so that
    its grey image ``grey`` (its :func:`mean_grey`) becomes ``target``; all three float32,
    or all float64.

    Every channel is scaled by ``target / grey``, so the hue stays, within ``[0, max_gain]``
    (a dark pixel's channels are not multiplied by thousands, nor their signs flipped); what
    the scale leaves, and all of the change where ``grey`` is at or below 0 (a deconvolved
    undershoot, whose channels a ratio would move the wrong way), is added to every channel
    alike. The grey image is then ``target`` to rounding (:func:`mean_grey` is linear).
    """
    raw = cv2.divide(target, grey)  # 0 where grey is 0
    ratio = np.clip(raw, 0.0, max_gain)
    ratio[grey <= 0] = 1.0  # no ratio of an undershoot's channels: all of it added
    # where the scale does not reach the target: few pixels (found flat, then as rows and
    # columns: 0.5 against 10 ms for ``np.nonzero`` of the 2-D mask on 3 Mpx)
    rest = np.unravel_index(np.flatnonzero(ratio != raw), ratio.shape)
    offset = target[rest] - ratio[rest] * grey[rest]
    scale_channels(image, ratio)
    if image.ndim == 3:
        image[rest] += offset[:, None]
    else:
        image[rest] += offset
