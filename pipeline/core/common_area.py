"""The area of an aligned stack's result that every frame covers (Sec. 9, beyond the paper).

Frames aligned to the reference frame (focus breathing, a hand's or a rail's move) leave
strips of the result that some frame does not reach; there the warp fills it from that
frame's edge (:func:`pipeline.core.align.warp` replicates borders), which shows as streaks.
:func:`common_area` finds the largest axis-aligned rectangle inside every frame's footprint:
what a user crops to (``flexdof stack --crop``), what focus-stack crops its output to.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from pipeline.core import align

GRID_SIDE_PX = 512  # the footprints are rasterised with this longest side
# sub-pixel vertices for cv2.fillConvexPoly (fixed point with this many fractional bits)
_SHIFT_BITS = 8


def footprints(
    homographies: Sequence[np.ndarray], shape: tuple[int, int], grid: tuple[int, int]
) -> np.ndarray:
    """Cells of a ``grid`` (rows, cols) over a result of ``shape`` that every frame covers
    entirely: each frame's rectangle (``shape``: the frames' size) mapped by its homography
    (frame -> result coordinates) and filled, the frames' fills intersected and eroded by one
    cell, so a cell on a footprint's edge does not count."""
    rows, cols = shape
    gy, gx = grid
    corners = np.array([[0, 0], [cols, 0], [cols, rows], [0, rows]], np.float64) - 0.5
    to_grid = np.array([gx / cols, gy / rows])
    covered = np.ones(grid, np.uint8)
    for h in homographies:
        # pixel centres span -0.5..n-0.5 in pixel-centre coordinates; the grid's cell (i, j)
        # covers [j, j + 1) x [i, i + 1) in grid units
        mapped = (align.map_points(np.asarray(h, np.float64), corners) + 0.5) * to_grid - 0.5
        fixed = np.round(mapped * (1 << _SHIFT_BITS)).astype(np.int32)
        one = np.zeros(grid, np.uint8)
        cv2.fillConvexPoly(one, fixed, 1, lineType=cv2.LINE_8, shift=_SHIFT_BITS)
        covered &= one
    return cv2.erode(covered, np.ones((3, 3), np.uint8), borderValue=0)


def largest_rectangle(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """The largest axis-aligned rectangle ``(row, col, height, width)`` of ones in a
    ``mask`` whose ones form a convex region (the intersection of convex footprints).

    In a convex region every row's ones are one run, the runs' left ends are a convex and
    their right ends a concave function of the row, so the columns all rows ``r0..r1``
    share are those the two end rows share: every pair of rows is one candidate.
    ``None`` where the mask holds no ones."""
    filled = mask.astype(bool)
    rows_with = np.flatnonzero(filled.any(axis=1))
    if rows_with.size == 0:
        return None
    left = np.argmax(filled, axis=1)
    right = filled.shape[1] - np.argmax(filled[:, ::-1], axis=1)  # one past the run's end
    r = rows_with
    lo = np.maximum(left[r][:, None], left[r][None, :])
    hi = np.minimum(right[r][:, None], right[r][None, :])
    height = r[None, :] - r[:, None] + 1
    area = np.where(height > 0, np.maximum(hi - lo, 0) * height, 0)
    i, j = np.unravel_index(int(np.argmax(area)), area.shape)
    if area[i, j] <= 0:
        return None
    return int(r[i]), int(lo[i, j]), int(height[i, j]), int(hi[i, j] - lo[i, j])


def common_area(
    homographies: Sequence[np.ndarray], shape: tuple[int, int]
) -> tuple[int, int, int, int] | None:
    """The largest rectangle ``(row, col, height, width)`` of a result of ``shape`` (the
    frames' size and geometry) that every frame covers, in whole pixels, from
    ``homographies`` (frame -> result coordinates); ``None`` if the frames share no area.

    Rasterised on a grid of ``GRID_SIDE_PX`` (longest side), so the rectangle is inside
    every footprint by at least one grid cell (4 px on a 2048 px frame) and within two
    cells of the largest; identity homographies give the whole result."""
    rows, cols = int(shape[0]), int(shape[1])
    if all(np.allclose(h, np.eye(3)) for h in homographies):
        return 0, 0, rows, cols
    factor = max(1.0, max(rows, cols) / GRID_SIDE_PX)
    grid = (max(3, round(rows / factor)), max(3, round(cols / factor)))
    covered = footprints(homographies, (rows, cols), grid)
    found = largest_rectangle(covered)
    if found is None:
        return None
    gr, gc, gh, gw = found
    # rasterised, the region is convex only up to a cell: shrink until every cell is covered
    while gh > 0 and gw > 0 and not covered[gr : gr + gh, gc : gc + gw].all():
        gr, gc, gh, gw = gr + 1, gc + 1, gh - 2, gw - 2
    if gh <= 0 or gw <= 0:
        return None
    sy, sx = rows / grid[0], cols / grid[1]
    y0, x0 = int(np.ceil(gr * sy)), int(np.ceil(gc * sx))
    y1, x1 = int(np.floor((gr + gh) * sy)), int(np.floor((gc + gw) * sx))
    return y0, x0, y1 - y0, x1 - x0
