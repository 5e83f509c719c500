"""Exact area of a disk inside an axis-aligned rectangle (closed form, vectorised).

``G(x, y) = int_{-R}^{x} |chord(X) below y| dX`` for the disk of radius ``R`` at the
origin; the area inside ``[x0, x1] x [y0, y1]`` is ``G(x1,y1) - G(x0,y1) - G(x1,y0) +
G(x0,y0)``. With ``s(X) = sqrt(R^2 - X^2)`` the chord below ``y`` has length
``s + clip(y, -s, s)`` and ``int min(|y|, s) dX`` splits where ``s = |y|``.
"""

from __future__ import annotations

import numpy as np


def _s_int(x, r):
    """``int_{-R}^{x} sqrt(R^2 - X^2) dX`` for ``x`` in [-R, R]."""
    with np.errstate(invalid="ignore", divide="ignore"):
        q = np.where(r > 0, x / np.where(r > 0, r, 1.0), 0.0)
    q = np.clip(q, -1.0, 1.0)
    return 0.5 * r * r * (q * np.sqrt(np.maximum(1 - q * q, 0.0)) + np.arcsin(q) + np.pi / 2)


def _g(x, y, r):
    xc = np.clip(x, -r, r)
    w = np.sqrt(np.maximum(r * r - y * y, 0.0))
    ay = np.abs(y)
    part1 = _s_int(np.minimum(xc, -w), r)
    part2 = ay * np.clip(xc + w, 0.0, 2 * w)
    part3 = _s_int(np.maximum(xc, w), r) - _s_int(w, r)
    below = np.sign(y) * (part1 + part2 + part3)
    return _s_int(xc, r) + below


def disk_rect_area(x0, x1, y0, y1, r) -> np.ndarray:
    """Area of the disk of radius ``r`` (at the origin) inside ``[x0,x1] x [y0,y1]`` (x0<=x1)."""
    x0, x1, y0, y1, r = np.broadcast_arrays(
        *(np.asarray(v, dtype=np.float64) for v in (x0, x1, y0, y1, r))
    )
    area = _g(x1, y1, r) - _g(x0, y1, r) - _g(x1, y0, r) + _g(x0, y0, r)
    return np.maximum(area, 0.0)


def unit_disk_fraction(x0, x1, y0, y1) -> np.ndarray:
    """Fraction of the unit disk inside ``[x0,x1] x [y0,y1]`` (bounds may be +-huge)."""
    lo_x, hi_x = np.clip(x0, -2.0, 2.0), np.clip(x1, -2.0, 2.0)
    lo_y, hi_y = np.clip(y0, -2.0, 2.0), np.clip(y1, -2.0, 2.0)
    hi_x, hi_y = np.maximum(hi_x, lo_x), np.maximum(hi_y, lo_y)
    return disk_rect_area(lo_x, hi_x, lo_y, hi_y, 1.0) / np.pi


def pixel_disk_kernels(radii, half: int) -> np.ndarray:
    """Disks of the given radii (px) integrated over each pixel: ``(n, 2h+1, 2h+1)``, unit sum.

    Pixel ``(i, j)`` (offsets from the centre) covers ``[j-0.5, j+0.5] x [i-0.5, i+0.5]``;
    a radius below 1e-9 px gives the delta.
    """
    r = np.abs(np.asarray(radii, dtype=np.float64)).ravel()
    off = np.arange(-half, half + 1, dtype=np.float64)
    safe = np.maximum(r, 1e-9)[:, None, None]
    # in units of the radius: fraction of the unit disk inside the scaled pixel square
    yy, xx = off[None, :, None], off[None, None, :]
    k = unit_disk_fraction((xx - 0.5) / safe, (xx + 0.5) / safe, (yy - 0.5) / safe,
                           (yy + 0.5) / safe)
    return k / k.sum(axis=(1, 2), keepdims=True)
