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
