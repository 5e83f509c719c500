"""A guard against leaving the frames' range (issue 13).

A true all-in-focus image is, at every pixel, one of the frames (the one in focus
there), so it never leaves ``[min, max]`` of the aligned frames by more than noise.
Deconvolution's rims, moats and ringing do. Clipping the restored image to that range,
widened to a small neighbourhood (registration slack), removes them without touching
detail that some frame shows.
"""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.errors import InputError

GUARD_RADIUS_PX = 1  # 3x3 px: the aligned frames' registration slack


def widen_range(lo: np.ndarray, hi: np.ndarray, radius_px: int = GUARD_RADIUS_PX):
    """``lo`` eroded and ``hi`` dilated over a ``(2r+1)^2`` square (per channel)."""
    if lo.shape != hi.shape:
        raise InputError(f"frame range: minimum {lo.shape} and maximum {hi.shape} differ")
    if radius_px <= 0:
        return lo, hi
    element = np.ones((2 * radius_px + 1, 2 * radius_px + 1), np.uint8)
    lo = np.asarray(lo, np.float32)
    hi = np.asarray(hi, np.float32)
    return (
        cv2.erode(lo, element, borderType=cv2.BORDER_REPLICATE).reshape(lo.shape),
        cv2.dilate(hi, element, borderType=cv2.BORDER_REPLICATE).reshape(hi.shape),
    )


def clip_to_frames(result, lo, hi, radius_px: int = GUARD_RADIUS_PX) -> np.ndarray:
    """``result`` clipped per pixel to ``[min, max]`` of the frames over ``(2r+1)^2`` px.

    ``lo``/``hi`` are the per-pixel minimum and maximum of the aligned frames, in the
    same (linear) units as ``result``. Returns a new array of ``result``'s dtype.
    """
    result = np.asarray(result)
    if result.shape != np.shape(lo):
        raise InputError(f"frame range {np.shape(lo)} does not match the image {result.shape}")
    lo, hi = widen_range(lo, hi, radius_px)
    return np.clip(result, lo.astype(result.dtype), hi.astype(result.dtype))


# ----------------------------------------------------------------------------- stack ends
FOCUS_SIGMA_PX = 8.0  # smoothing of the focus measure: coherent picks, not per-pixel noise
CONTRAST_WINDOW_PX = 15  # local contrast window of the fallback
FALLBACK_FLOOR = 1.0 / 255.0  # display levels the sharpest frame must win by
FALLBACK_SMOOTH_PX = 8.0  # smoothing of the blend weight


def _grey(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image, np.float32)
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)  # luma weights; ~10x faster than a mean
    return image.mean(axis=2) if image.ndim == 3 else image


def focus_measure(frame) -> np.ndarray:
    """Per-pixel sharpness of one frame: Laplacian energy of its grey, smoothed (rows, cols)."""
    grey = _grey(frame)
    lap = cv2.Laplacian(grey, cv2.CV_32F, ksize=3)
    side = 2 * int(FOCUS_SIGMA_PX) + 1  # a box of about the same reach: O(1) per pixel
    return cv2.blur(lap * lap, (side, side))


def focus_weight(frame) -> np.ndarray:
    """A frame's weight in the soft all-in-focus composite: ``focus_measure ** 2`` (+ a tiny
    floor). Sharp content dominates where one frame is in focus; in flat areas the weights
    are alike and the composite is a smooth mean, not a patchwork of per-pixel picks."""
    f = focus_measure(frame)
    return f * f + np.float32(1e-20)


def _display(grey: np.ndarray) -> np.ndarray:
    """A display-like (gamma 1/2) version of linear grey, so the floor is in levels."""
    return np.sqrt(np.maximum(grey, 0.0))


def local_contrast(grey: np.ndarray, sigma_px: float = 1.0, window_px: int = 15) -> np.ndarray:
    """RMS of a band-pass (Gaussian ``sigma_px`` minus Gaussian ``3 sigma_px``) over windows.

    The lower cut-off keeps pixel noise (and JPEG grain) out: flat areas of a noisy
    frame must not read as more detailed than a clean result.
    """
    g = _display(grey)
    fine = cv2.GaussianBlur(g, (0, 0), sigma_px)
    band = fine - cv2.GaussianBlur(fine, (0, 0), 2.8 * sigma_px)
    return np.sqrt(np.maximum(cv2.blur(band * band, (window_px, window_px)), 0.0))


def sharpest_fallback(result, sharpest) -> np.ndarray:
    """Blend towards the per-pixel sharpest frame where it shows clearly more fine
    contrast than ``result`` (issue 13, item 4: Sec. 4.1's end effect).

    Content in focus only near an end of the stack gets the smallest weights and the
    least restorable blur; there the sharpest frame is better than any deconvolution.
    ``alpha`` rises from 0 to 1 as the frame's local contrast exceeds the result's by
    one to two ``FALLBACK_FLOOR`` (display levels), then is smoothed so no seams show.
    """
    result = np.asarray(result)
    sharpest = np.asarray(sharpest, result.dtype)
    if result.shape != sharpest.shape:
        raise InputError(f"sharpest frame {sharpest.shape} does not match the image {result.shape}")
    a, b = _grey(sharpest), _grey(result)
    gain = np.maximum(  # fine detail, and coarser contrast (bars, lettering)
        local_contrast(a) - local_contrast(b),
        local_contrast(a, 2.0, 2 * CONTRAST_WINDOW_PX + 1)
        - local_contrast(b, 2.0, 2 * CONTRAST_WINDOW_PX + 1),
    )
    alpha = np.clip((gain - FALLBACK_FLOOR) / FALLBACK_FLOOR, 0.0, 1.0)
    alpha = cv2.GaussianBlur(alpha.astype(np.float32), (0, 0), FALLBACK_SMOOTH_PX)
    if result.ndim == 3:
        alpha = alpha[..., np.newaxis]
    return (result + alpha * (sharpest - result)).astype(result.dtype, copy=False)
