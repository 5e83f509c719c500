"""Estimate a focal stack's defocus scale from its frames (for stacks without a lens profile).

In a focal stack, a point in focus in frame ``i`` appears in frame ``j`` blurred
by a disk of diameter ``b = a |p_i - p_j| / (v pitch)`` (Eq. 2): linear in the
frames' focus positions, with one unknown slope. With positions normalised to
``x in [0, 1]`` the slope is the *blur span* ``D`` (px): the blur, in frame
``j``, of a point focused in frame ``i``, is ``D |x_i - x_j|``.

``D`` is fitted by predicting frame ``j`` from frame ``i`` on the pixels where
``i`` is the sharpest frame: ``g_j ~ g_i * P(D |x_i - x_j|)`` (Eq. 3 pillbox),
minimising the squared residual over a log-spaced grid of ``D``, refined by a
parabola through the best three. The fit runs on reduced-resolution, aligned,
grey, mean-normalised frames.
"""

from __future__ import annotations

import dataclasses
import logging

import cv2
import numpy as np

from pipeline.core.psf import kernel_size, raster_pillbox
from pipeline.errors import InputError

log = logging.getLogger(__name__)

def _focus_measure(grey: np.ndarray) -> np.ndarray:
    """Local energy of the Laplacian (a standard focus measure), smoothed over ~9 px."""
    lap = cv2.Laplacian(grey, cv2.CV_32F, ksize=3)
    return cv2.GaussianBlur(lap * lap, (0, 0), 3.0)


# the coarse band a frame's content beyond an end shows (:func:`_coarse_measure`): the band
# ``G_1 g - G_3 g`` of the fit's previews (6-19 px of pcb7's 2048 px frames at 320 px), its
# energy smoothed over this sigma (preview px)
COARSE_BAND_PX = (1.0, 3.0)
COARSE_SMOOTH_PX = 3.0


def _coarse_measure(grey: np.ndarray) -> np.ndarray:
    """Local energy of a frame's coarse band (``COARSE_BAND_PX``): the detail a few
    times coarser than the Laplacian's, which content far out of focus still shows."""
    fine, coarse = COARSE_BAND_PX
    band = cv2.GaussianBlur(grey, (0, 0), fine) - cv2.GaussianBlur(grey, (0, 0), coarse)
    return cv2.GaussianBlur(band * band, (0, 0), COARSE_SMOOTH_PX)


def _pairs(n: int) -> list[tuple[int, int]]:
    """Frame pairs 2+ frames apart (neighbours only for tiny stacks); from five frames on
    also 4 apart.

    A pixel's sharpest frame is itself blurred by up to ``D dx / 2`` (the point
    focuses between frames); blur adds roughly in quadrature, so predicting a frame
    ``k`` steps away underestimates ``D`` by about ``1 / (8 k^2)``: 12% for
    neighbours, 3% for k = 2. On stacks rendered with occlusion, breathing, shot noise
    and 8-bit frames (tilted boards and the motorcycle, 5-9 frames,
    ``tests/benchmarks/regions_vs_truth.py``) pairs 2 and 3 apart read the span -12% to
    +18% (six of eight 5-12% low); with pairs 4 apart as well, -9% to +2% (issue 13).
    """
    steps = {1, 2} if n < 4 else {2, 3} if n < 5 else {2, 3, 4, max(2, n // 3)}
    return [(i, i + s * d) for i in range(n) for s in steps for d in (-1, 1) if 0 <= i + s * d < n]


MIN_MASK_PX = 50  # fewer pixels where a frame is the sharpest say nothing of its blur


def _normalised(frame: np.ndarray) -> np.ndarray:
    """A grey frame divided by its mean (the fits compare frames of any exposure)."""
    return np.asarray(frame, np.float32) / max(float(np.mean(frame)), 1e-12)


class FocusMaps:
    """The sharpest frame per pixel of a stack and its focus measure, built one frame at a
    time (so a stack of any length needs two maps, not all its frames), and the same by
    the coarse band (``coarse_sharpest``, ``coarse_best``; :func:`_coarse_measure`).

    Frames are added with their index; a pixel's sharpest frame is the first of the best
    (as ``np.argmax``) when they are added in index order.
    """

    def __init__(self):
        self.sharpest: np.ndarray | None = None
        self.best: np.ndarray | None = None
        self.coarse_sharpest: np.ndarray | None = None
        self.coarse_best: np.ndarray | None = None

    @classmethod
    def of(cls, frames) -> FocusMaps:
        """The maps of aligned grey ``frames`` (a sequence), added in index order."""
        maps = cls()
        for i, frame in enumerate(frames):
            maps.add(i, frame)
        return maps

    def add(self, index: int, grey: np.ndarray) -> None:
        """Add frame ``index`` (aligned, grey)."""
        grey = _normalised(grey)
        focus, coarse = _focus_measure(grey), _coarse_measure(grey)
        if self.best is None:
            self.best, self.sharpest = focus, np.full(focus.shape, index, np.intp)
            self.coarse_best, self.coarse_sharpest = coarse, self.sharpest.copy()
            return
        better = focus > self.best
        self.best = np.where(better, focus, self.best)
        self.sharpest[better] = index
        better = coarse > self.coarse_best
        self.coarse_best = np.where(better, coarse, self.coarse_best)
        self.coarse_sharpest[better] = index

    def textured(self) -> np.ndarray:
        """The pixels with detail to tell the sharpest frame by: the 30% best in focus."""
        return self.best > np.percentile(self.best, 70)

    def masks(self, indices) -> dict[int, np.ndarray]:
        """Per frame in ``indices``, the textured pixels (:meth:`textured`) 5% or more
        from the borders where it is the sharpest."""
        textured = self.textured()
        border = max(4, int(0.05 * min(self.best.shape)))
        interior = np.zeros_like(textured)
        interior[border:-border, border:-border] = True
        return {i: (self.sharpest == i) & textured & interior for i in indices}


def _sharpest_masks(frames):
    """Mean-normalised grey frames, the sharpest frame per pixel, and per frame the
    textured pixels (the 30% best in focus) 5% or more from the borders where it is
    the sharpest."""
    grey = [_normalised(f) for f in frames]
    maps = FocusMaps.of(frames)
    masks = maps.masks(range(len(grey)))
    return grey, maps.sharpest, [masks[i] for i in range(len(grey))]


def _predict(grey: np.ndarray, diameter_px: float) -> np.ndarray:
    """``grey`` blurred by a pillbox of ``diameter_px`` (Eq. 3)."""
    pillbox = raster_pillbox(diameter_px, kernel_size(diameter_px) // 2).astype(np.float32)
    return cv2.filter2D(grey, -1, pillbox, borderType=cv2.BORDER_REFLECT_101)


def _best_on_grid(cost, grid: np.ndarray) -> tuple[float, int]:
    """The minimum of ``cost`` over a log-spaced ``grid``, refined by a parabola through
    the best three in ``log``; and the index of the best grid point."""
    costs = np.array([cost(d) for d in grid])
    k = int(np.argmin(costs))
    if 0 < k < grid.size - 1:
        lx = np.log(grid[k - 1 : k + 2])
        a, b, _ = np.polyfit(lx, costs[k - 1 : k + 2], 2)
        estimate = float(np.exp(-b / (2 * a))) if a > 0 else float(grid[k])
        return float(np.clip(estimate, grid[k - 1], grid[k + 1])), k
    return float(grid[k]), k


def estimate_blur_span(
    frames: list[np.ndarray],
    positions,
    *,
    downscale: float = 1.0,
    max_span_px: float = 400.0,
    warn: bool = True,
) -> float:
    """Blur span ``D`` (px at full resolution) of an aligned focal stack.

    Parameters
    ----------
    frames : list of 2-D float arrays
        Aligned grey frames, all one shape (reduced resolution is fine).
    positions : array_like, shape (n,)
        The frames' focus positions in any coordinate linear in image distance.
    downscale : float
        Full-resolution size / the frames' size; the result is in full-res px.
    max_span_px : float
        Upper end of the search.
    warn : bool
        Log a warning when the fit lands at an end of the search (False for a fit whose
        caller fits again, e.g. the alignment's check, so that the user is told once).

    Returns
    -------
    float
        ``D``; a point focused at one end of the stack has a blur of ``D`` px at the
        other end.
    """
    x = np.asarray(positions, dtype=np.float64)
    n = len(frames)
    if n < 2 or x.size != n:
        raise InputError(f"need >= 2 frames with one position each, got {n} and {x.size}")
    span = np.ptp(x)
    if span <= 0:
        raise InputError("all frames have the same focus position: no defocus to measure")
    x = (x - x.min()) / span
    grey, _, masks = _sharpest_masks(frames)
    pairs = [(i, j) for i, j in _pairs(n) if masks[i].sum() > MIN_MASK_PX]
    if not pairs:
        raise InputError("no textured, in-focus regions to measure the defocus from")

    def cost(span_px: float) -> float:
        total, count = 0.0, 0
        for i, j in pairs:
            predicted = _predict(grey[i], span_px * abs(x[i] - x[j]) / downscale)
            residual = (predicted - grey[j])[masks[i]]
            total += float(np.dot(residual, residual))
            count += residual.size
        return total / count

    grid = np.geomspace(2.0, max_span_px, 14)
    estimate, k = _best_on_grid(cost, grid)
    if warn and k in (0, grid.size - 1):
        log.warning("blur span at the edge of the search (%.1f px); check the stack", estimate)
    return estimate


@dataclasses.dataclass(frozen=True)
class EndDepth:
    """Content in focus in an end frame that lies beyond the stack's focus range.

    Attributes
    ----------
    frame : int
        The end frame (first or last in focus position).
    beyond : float
        How far beyond that frame the content is focused, as a fraction of the stack's
        focus range (0: at the frame).
    pixels : int
        Pixels (at the fit's resolution) where the frame is the sharpest and textured,
        away from other depths (those the fit used).
    """

    frame: int
    beyond: float
    pixels: int


def near_other_depths(sharpest, textured, x, end, others, span_px: float) -> np.ndarray:
    """Pixels whose neighbourhood in the fit of ``end`` reaches content sharpest two or
    more frames away from it (``x``: normalised positions; ``span_px`` at the map's scale).
    ``end`` may be any frame; with ``others`` ``[end]`` the fit's reach is left out (the
    inner frames' own detail, :mod:`pipeline.jobs.frame_detail`).

    Content sharpest in frame ``r`` lies blurred by ``D |x_r - x_e|`` in the end frame;
    predicting frame ``j`` blurs by up to ``D sqrt(dx^2 + dx)`` more (the widest search
    of :func:`end_depths`). Within half those diameters of such content no one pillbox
    relates the two frames: an occlusion edge sharp in the end frame, next to content
    it shows blurred, reads as content far beyond the range (a stack whose end frames
    lie on two planes read 0.13-0.2 of the range beyond where the truth is 0).
    """
    rank = np.empty(x.size, np.intp)
    rank[np.argsort(x, kind="stable")] = np.arange(x.size)
    fit_radius = 0.5 * span_px * max(abs(x[j] - x[end]) for j in others)
    near = np.zeros(sharpest.shape, bool)
    speck = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    for r in np.unique(sharpest[textured]):
        if abs(rank[r] - rank[end]) < 2:
            continue
        # where that frame is the sharpest and there is detail to tell (elsewhere the
        # choice is noise), in patches, not single pixels
        region = ((sharpest == r) & textured).astype(np.uint8)
        region = cv2.morphologyEx(region, cv2.MORPH_OPEN, speck)
        reach = int(np.ceil(0.5 * span_px * abs(x[r] - x[end]) + fit_radius))
        disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1,) * 2)
        near |= cv2.dilate(region, disk) > 0
    return near


def end_pair(positions) -> tuple[int, int]:
    """The first and the last frame in focus position: the ends :func:`end_depths` fits
    (the same frame twice for a single one)."""
    order = np.argsort(np.asarray(positions, dtype=np.float64), kind="stable")
    return int(order[0]), int(order[-1])


def end_frames(positions) -> list[int]:
    """The frames :func:`end_depths` reads when given the stack's :class:`FocusMaps`: the
    first and last frame in focus position and the three next to each."""
    order = np.argsort(np.asarray(positions, dtype=np.float64), kind="stable")
    return sorted({int(i) for i in (*order[:4], *order[-4:])})


def end_depths(frames, positions, span_px: float, *, downscale: float = 1.0, maps=None):
    """How far beyond each end of an aligned focal stack its end frames' content lies,
    and the sharpest frame per pixel (at the frames' resolution).

    Where frame ``e`` at an end is the sharpest, its content is focused at ``x_e -
    beyond`` (outside the stack's range ``[0, 1]``), so frame ``e`` itself sees it
    blurred by ``D beyond`` and a frame ``j`` at ``dx = |x_j - x_e|`` by ``D (dx +
    beyond)``. Blur adds in variance under convolution (a pillbox of diameter ``d`` has
    variance ``d^2 / 16`` per axis), so predicting frame ``j`` from ``e`` needs a pillbox
    of ``d^2 = D^2 ((dx + beyond)^2 - beyond^2)``, whence ``beyond = (d^2 / D^2 - dx^2)
    / (2 dx)``. ``d`` is fitted as in :func:`estimate_blur_span`, for the three frames
    nearest the end; the median of their ``beyond`` is kept, clipped to ``[0, 0.5]``
    (content inside the range reads <= 0). Sec. 4.1: the IPSF of such a depth is wider
    than the stack's, whose kernel leaves it soft (issue 13: pcb7's far barcode).
    Pixels within reach of content sharpest two or more frames away are left out
    (:func:`near_other_depths`): at an occlusion edge the fit reads 0.06-0.2 of the
    range beyond where the truth is 0 (``tests/test_end_depths.py``).

    Parameters
    ----------
    frames : list of 2-D float arrays, or a mapping from frame index to one
        Aligned grey frames (reduced resolution is fine). With ``maps``, only the frames
        :func:`end_frames` names are read (a mapping may hold just those).
    positions : array_like, shape (n,)
        Focus positions, in any coordinate linear in image distance.
    span_px : float
        The blur span ``D`` (full-resolution px).
    downscale : float
        Full-resolution size / the frames' size.
    maps : FocusMaps, optional
        The sharpest frame per pixel over all ``n`` frames, built beforehand (a stack
        streamed one frame at a time); else built from ``frames``.

    Returns
    -------
    ends : list of EndDepth
        The two ends (one for a two-frame stack's each frame).
    sharpest : ndarray of int
        The sharpest frame per pixel (by the local energy of the Laplacian).
    """
    x = np.asarray(positions, dtype=np.float64)
    given = x.size if maps is not None else len(frames)
    if x.size < 2 or x.size != given or np.ptp(x) <= 0 or not span_px > 0:
        raise InputError("need >= 2 frames at different focus positions and a blur span > 0")
    x = (x - x.min()) / np.ptp(x)
    read = end_frames(x)
    if maps is None:
        maps = FocusMaps.of(frames)
    grey = {i: _normalised(frames[i]) for i in read}
    sharpest, masks, textured = maps.sharpest, maps.masks(read), maps.textured()
    order = np.argsort(x, kind="stable")
    ends = []
    for end, others in ((order[0], order[1:4]), (order[-1], order[-2:-5:-1])):
        away = ~near_other_depths(sharpest, textured, x, end, others, span_px / downscale)
        mask = masks[end] & away
        beyond = []
        if mask.sum() > MIN_MASK_PX:
            for j in others:
                dx = abs(x[j] - x[end])
                if dx <= 0:  # a frame at the end frame's own position says nothing
                    continue

                def cost(d, source=grey[end], target=grey[j], mask=mask):
                    residual = (_predict(source, d) - target)[mask]
                    return float(np.dot(residual, residual)) / residual.size

                # from half the blur of content at the end frame to that of content
                # half the range beyond it (d^2 = D^2 (dx^2 + dx)), at the fit's scale
                near, far = span_px * dx / downscale, span_px * np.sqrt(dx * dx + dx) / downscale
                d, _ = _best_on_grid(cost, np.geomspace(max(0.3, 0.5 * near), far, 12))
                d *= downscale
                beyond.append((d * d / (span_px * span_px) - dx * dx) / (2 * dx))
        value = float(np.clip(np.median(beyond), 0.0, 0.5)) if beyond else 0.0
        ends.append(EndDepth(int(end), value, int(mask.sum())))
    return ends, sharpest
