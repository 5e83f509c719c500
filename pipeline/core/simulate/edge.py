"""Error of 'over' compositing at a depth edge, from an exact trace of a straight edge.

The layered model composites a near layer over a far one: ``C_n + (1 - A_n) C_f``. At a
silhouette where both sides are out of focus that is not what the lens does: a pixel's
aperture rays are split by the edge (partial occlusion), so the far texture behind the
near plane is seen through part of the aperture and weighted by the part of the disk
that passes the edge, not by ``1 - A_n`` as a product. :func:`edge_error` measures that
error on a straight vertical edge between the scene's own two textures: the exact
thin-lens trace against the over model with the same (time averaged) kernels. It is 0
when either side is in focus.

A ray from grid point ``g0`` through aperture point ``xi`` (unit disk) meets inverse depth
``D`` at ``g0 - rho(D) xi``, ``rho = (a/2) (p_ref / pitch) (D - D_p)`` (signed, grid px).
Areas of the unit disk inside pixel rectangles are exact (closed form).
"""

from __future__ import annotations

import math

import numpy as np

_CANONICAL_ROWS = 64


def _s_int(x, r):
    q = np.clip(x / r, -1.0, 1.0)
    return 0.5 * r * r * (q * np.sqrt(np.maximum(1 - q * q, 0.0)) + np.arcsin(q) + np.pi / 2)


def _g(x, y, r):
    xc = np.clip(x, -r, r)
    w = np.sqrt(np.maximum(r * r - y * y, 0.0))
    part1 = _s_int(np.minimum(xc, -w), r)
    part2 = np.abs(y) * np.clip(xc + w, 0.0, 2 * w)
    part3 = _s_int(np.maximum(xc, w), r) - _s_int(w, r)
    return _s_int(xc, r) + np.sign(y) * (part1 + part2 + part3)


def unit_disk_fraction(x0, x1, y0, y1) -> np.ndarray:
    """Fraction of the unit disk inside ``[x0, x1] x [y0, y1]``."""
    x0, x1 = np.clip(x0, -2.0, 2.0), np.clip(x1, -2.0, 2.0)
    y0, y1 = np.clip(y0, -2.0, 2.0), np.clip(y1, -2.0, 2.0)
    x1, y1 = np.maximum(x1, x0), np.maximum(y1, y0)
    area = _g(x1, y1, 1.0) - _g(x0, y1, 1.0) - _g(x1, y0, 1.0) + _g(x0, y0, 1.0)
    return np.maximum(area, 0.0) / np.pi


def _safe(rho: float) -> float:
    return rho if abs(rho) > 1e-9 else 1e-9


def _rect(d, rho):
    a, b = -(d - 0.5) / rho, -(d + 0.5) / rho
    return np.minimum(a, b), np.maximum(a, b)


def _crop(tex: np.ndarray, centre: int, cols: int) -> np.ndarray:
    """``cols`` columns of ``tex`` centred on the edge column ``centre`` (mirrored beyond)."""
    tex = np.asarray(tex, float)[:_CANONICAL_ROWS]
    while tex.shape[1] < 3 * cols:
        tex = np.pad(tex, ((0, 0), (tex.shape[1] - 1, tex.shape[1] - 1)), mode="reflect")
        centre += (tex.shape[1] - 1) // 3
    pad = cols
    tex = np.pad(tex, ((0, 0), (pad, pad)), mode="reflect")
    start = centre + pad - cols // 2
    return tex[:, start : start + cols]


def edge_error(near_tex, far_tex, rho_near, rho_far, weights=None, centre: int = 0) -> float:
    """Sum of squared errors per px of edge length, in the textures' units squared.

    ``near_tex``, ``far_tex``: the two sides' textures (the scene's own, cropped; mirrored
    to the needed size). ``rho_near``, ``rho_far``: signed grid radii of the near and far
    planes at each time cell, ``weights`` the cells' time weights (default equal). The
    whole-image error of a scene with ``L`` px of such edges over ``N`` px is
    ``sqrt(edge_error * L / N)``.
    """
    rn = np.atleast_1d(np.asarray(rho_near, float))
    rf = np.atleast_1d(np.asarray(rho_far, float))
    w = np.full(rn.size, 1.0 / rn.size) if weights is None else np.asarray(weights, float)
    if (np.min(np.abs(rn)) < 1e-6 and rn.size == 1) or (np.min(np.abs(rf)) < 1e-6 and rf.size == 1):
        return 0.0  # one side in focus: over compositing is exact
    half = math.ceil(max(np.max(np.abs(rn)), np.max(np.abs(rf))) + 0.5) + 1
    cols = 2 * (2 * half + 8)
    near, far = _crop(near_tex, centre, cols), _crop(far_tex, centre, cols)
    rows = near.shape[0]
    e = cols // 2 - 0.5
    alpha = (np.arange(cols) < cols // 2).astype(float)[None, :].repeat(rows, 0)
    near_p = np.pad(near * alpha, half, mode="reflect")
    alpha_p = np.pad(alpha, half, mode="reflect")
    far_p = np.pad(far, half, mode="reflect")
    size = 2 * half + 1
    win_n = np.lib.stride_tricks.sliding_window_view(near_p, (size, size))
    win_a = np.lib.stride_tricks.sliding_window_view(alpha_p, (size, size))
    win_f = np.lib.stride_tricks.sliding_window_view(far_p, (size, size))
    off = np.arange(-half, half + 1, dtype=float)
    gx = np.arange(cols, dtype=float)
    exact = np.zeros((rows, cols))
    k_n = np.zeros((size, size))
    k_f = np.zeros((size, size))
    for r_n, r_f, wt in zip(rn, rf, w):
        r_n, r_f = _safe(float(r_n)), _safe(float(r_f))
        ny0, ny1 = _rect(off[:, None], r_n)
        nx0, nx1 = _rect(off[None, :], r_n)
        kn = unit_disk_fraction(nx0, nx1, ny0, ny1)
        kf = unit_disk_fraction(*_rect(off[None, :], r_f), *_rect(off[:, None], r_f))
        fy0, fy1 = _rect(off[:, None, None], r_f)
        fx0, fx1 = _rect(off[None, :, None], r_f)
        thr = (gx - e) / r_n
        if r_n > 0:
            fx1 = np.minimum(fx1, thr[None, None, :])
        else:
            fx0 = np.maximum(fx0, thr[None, None, :])
        w_far = unit_disk_fraction(fx0, np.maximum(fx1, fx0), fy0, fy1)
        exact += wt * (
            np.einsum("yxij,ij->yx", win_n, kn) + np.einsum("yxij,ijx->yx", win_f, w_far)
        )
        k_n += wt * kn
        k_f += wt * kf
    c_n = np.einsum("yxij,ij->yx", win_n, k_n)
    a_n = np.einsum("yxij,ij->yx", win_a, k_n)
    c_f = np.einsum("yxij,ij->yx", win_f, k_f)
    over = c_n + (1 - a_n) * c_f
    return float(np.sum((over - exact) ** 2) / rows)
