"""Image-quality measures for results: PSNR, and a no-reference edge-width sharpness.

Edge width (after Marziliano et al. 2002, with robust plateaus): at strong edges
of a reference image, the profile of the image under test is sampled along the
edge normal; its 10%-90% rise distance between the plateau levels (medians of
the profile far from the edge) is the edge's width. Smaller is sharper. Unlike
gradient energy or Laplacian variance, noise cannot inflate it (the plateaus
and the median over thousands of edges average noise out) and ringing cannot
either (overshoot lies beyond the 90% level and does not move the crossings;
oscillations far out barely move the medians). Every image is measured at the
same edge points and along the same normals.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage

from pipeline.core.colour import mean_grey
from pipeline.errors import InputError


def psnr(image: np.ndarray, reference: np.ndarray, *, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB (image clipped to ``[0, data_range]`` first)."""
    image = np.asarray(image, np.float64)
    reference = np.asarray(reference, np.float64)
    if image.shape != reference.shape:
        raise InputError(f"image {image.shape} and reference {reference.shape} differ in shape")
    mse = np.mean((np.clip(image, 0, data_range) - reference) ** 2)
    return float(10 * np.log10(data_range**2 / max(mse, 1e-30)))


def edge_points(reference: np.ndarray, *, max_points: int = 6000, seed: int = 0):
    """Strong edges of ``reference``: positions (row, col) and unit normals, shape (n, 2) each."""
    grey = mean_grey(np.asarray(reference, np.float32))
    smooth = cv2.GaussianBlur(grey, (0, 0), 2.0)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3)
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3)
    magnitude = np.hypot(gx, gy)
    # local maxima along the gradient (non-maximum suppression, 8 directions)
    peaks = magnitude >= ndimage.maximum_filter(magnitude, size=3)
    strong = peaks & (magnitude > np.percentile(magnitude, 97))
    border = 28
    strong[:border] = strong[-border:] = False
    strong[:, :border] = strong[:, -border:] = False
    rows, cols = np.nonzero(strong)
    if rows.size == 0:
        raise InputError("the reference has no strong edges to measure sharpness on")
    if rows.size > max_points:
        pick = np.random.default_rng(seed).choice(rows.size, max_points, replace=False)
        rows, cols = rows[pick], cols[pick]
    normals = np.stack([gy[rows, cols], gx[rows, cols]], axis=1)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return np.stack([rows, cols], axis=1).astype(np.float64), normals


def edge_widths(
    image: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    *,
    reach_px: float = 20.0,
    min_contrast: float = 0.02,
) -> np.ndarray:
    """10-90% rise width (px) of ``image`` at each edge point; NaN where too faint."""
    grey = mean_grey(np.asarray(image, np.float32))
    t = np.arange(-reach_px, reach_px + 0.25, 0.25)
    coords = points[:, :, None] + normals[:, :, None] * t[None, None, :]
    profiles = ndimage.map_coordinates(grey, coords.transpose(1, 0, 2), order=1, mode="nearest")
    outer = np.abs(t) >= reach_px / 2
    low = np.median(profiles[:, outer & (t < 0)], axis=1)
    high = np.median(profiles[:, outer & (t > 0)], axis=1)
    contrast = high - low
    q = (profiles - low[:, None]) / np.where(np.abs(contrast) > 1e-12, contrast, 1.0)[:, None]
    centre = t.size // 2
    widths = np.full(points.shape[0], np.nan)
    for i in np.flatnonzero(np.abs(contrast) > min_contrast * max(float(grey.max()), 1e-12)):
        row = q[i]  # normalised by the signed contrast: falling edges rise too
        below = np.flatnonzero(row[:centre] <= 0.1)
        above = np.flatnonzero(row[centre:] >= 0.9)
        if below.size and above.size:
            widths[i] = t[centre + above[0]] - t[below[-1]]
    return widths


def edge_width(image: np.ndarray, points: np.ndarray, normals: np.ndarray, **kwargs) -> float:
    """Median edge width (px) of ``image`` at the given edges (see :func:`edge_widths`)."""
    widths = edge_widths(image, points, normals, **kwargs)
    if not np.any(np.isfinite(widths)):
        raise InputError("no measurable edges: the image has no contrast at the edge points")
    return float(np.nanmedian(widths))


def sharpness_against_frames(result: np.ndarray, aligned_frames: list[np.ndarray]) -> dict:
    """Median edge widths of a result and of every (aligned) frame, whole and per region.

    Edges are taken from the frames' mean and split into a 3x3 grid of regions.
    Returns ``result_px``, ``frames_px`` (list), ``best`` (index of the sharpest
    frame overall), ``result_regions`` and ``best_regions`` (9 medians each, NaN
    where a region has no edges) and ``regions_sharper`` / ``regions``: in how many
    regions the result's edges are narrower than the best frame's.
    """
    points, normals = edge_points(sum(aligned_frames) / len(aligned_frames))
    rows, cols = result.shape[:2]
    region = (points[:, 0] * 3 // rows).astype(int) * 3 + (points[:, 1] * 3 // cols).astype(int)

    def widths(image):
        w = edge_widths(image, points, normals)
        medians = [
            float(np.nanmedian(w[region == r])) if np.isfinite(w[region == r]).any() else np.nan
            for r in range(9)
        ]
        return float(np.nanmedian(w)), medians

    ours, ours_regions = widths(result)
    per_frame = [widths(frame) for frame in aligned_frames]
    best = int(np.argmin([w for w, _ in per_frame]))
    pairs = [(o, b) for o, b in zip(ours_regions, per_frame[best][1]) if np.isfinite(o + b)]
    return {
        "result_px": ours,
        "frames_px": [w for w, _ in per_frame],
        "best": best,
        "result_regions": ours_regions,
        "best_regions": per_frame[best][1],
        "regions_sharper": sum(o < b for o, b in pairs),
        "regions": len(pairs),
    }
