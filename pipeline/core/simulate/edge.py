"""Depth edges: the error of 'over' compositing, and sub-aperture cells that remove it.

The layered model composites a near layer over a far one: ``C_n + (1 - A_n) C_f``. At a
silhouette where both sides are out of focus that is not what the lens does: a pixel's
aperture rays are split by the edge (partial occlusion), so the far texture behind the
near plane is seen through part of the aperture and weighted by the part of the disk
that passes the edge, not by ``1 - A_n`` as a product. :func:`edge_error` measures that
error on a straight vertical edge between the scene's own two textures: the exact
thin-lens trace against the over model with the same (time averaged) kernels. It is 0
when either side is in focus.

A ray from grid point ``g0`` through aperture point ``xi`` (unit disk) meets inverse depth
``D`` at ``g0 - rho(D) xi``, ``rho = (a/2) (p_ref / pitch) (D - D_p)`` (signed, grid px;
``2 |rho|`` is Eq. 2's blur diameter :func:`signed_radius`). Areas of the unit disk inside
pixel rectangles are exact (closed form).

Sub-aperture cells
------------------
Split the aperture into rectangles ``R_j`` bounded by the *pixel lines* of every occluding
layer, ``xi = (d + 1/2) / rho`` for integers ``d`` (:func:`aperture_cells`). Over one cell
the rays of grid point ``g0`` meet each occluding layer inside a single pixel, so its
visibility is constant on the cell and "over" compositing of the cell's view is exact::

    I(g0) = sum_j sum_i (C_i * K_i^j)(g0) prod_{k nearer than i} (1 - (A_k * K_k^j)(g0) / w_j)

with ``K_i^j`` layer ``i``'s disk kernel restricted to the cell (:func:`cell_kernels`; the
kernels of all cells add up to the pillbox of Eq. 2) and ``w_j`` the cell's share of the
aperture. For a static detector this is exact; during a sweep (the IPSF of Eqs. 5-6 is
the time average of the pillboxes) the exposure is split into time cells, each rendered
with the cells of its mid-time radii, and the error falls as the time cells get shorter.
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
    """Fraction of the unit disk inside ``[x0, x1] x [y0, y1]`` (empty when ``x1 < x0``)."""
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
    """``cols`` columns of ``tex`` centred on the edge column ``centre`` (mirrored beyond:
    numpy's reflect repeats the mirroring for pads wider than the texture)."""
    tex = np.pad(np.asarray(tex, float)[:_CANONICAL_ROWS], ((0, 0), (cols, cols)), mode="reflect")
    start = centre + cols - cols // 2
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


def signed_radius(lens, inv_depth: float, p_mm: float, scale: float = 1.0) -> float:
    """Signed blur radius (grid px) of inverse depth ``D`` for a detector at ``p``.

    ``rho = (a/2) (p / scale) (D - D_p) / pitch`` with ``D_p = 1/f - 1/p`` the inverse depth
    in focus: ``2 |rho|`` is Eq. 2's blur diameter ``b = a |v - p| / v`` in pixels, divided
    by the step's image ``scale`` (as the kernels of the simulator's scaled sub-steps).

    Parameters
    ----------
    lens : pipeline.core.lens.Lens
    inv_depth : float
        ``D = 1/u`` (1/mm).
    p_mm : float
        Detector position ``p``.
    scale : float
        The sub-step's image scale ``p_step / p_ref``.

    Returns
    -------
    float
        ``rho``; its sign says on which side of focus ``D`` lies: a ray through aperture
        point ``xi`` meets the plane at ``g0 - rho xi`` (mirrored for ``rho < 0``).
    """
    d_p = 1.0 / lens.focal_length_mm - 1.0 / p_mm
    return 0.5 * lens.aperture_mm * p_mm / (lens.pixel_pitch_mm * scale) * (inv_depth - d_p)


def aperture_cells(radii) -> tuple[np.ndarray, np.ndarray]:
    """Rectangles of the unit aperture bounded by the pixel lines of layers of radii ``radii``.

    Through a cell the rays of any grid point meet each of these layers (a pillbox of
    Eq. 3 with the radius of Eq. 2) inside one pixel.

    Parameters
    ----------
    radii : sequence of float
        Signed radii ``rho`` (grid px) of the occluding layers; lines ``xi = (d + 1/2) /
        |rho|`` (integer ``d``) of every radius, the same in x and y.

    Returns
    -------
    cells : ndarray, shape (J, 4)
        ``(x0, x1, y0, y1)`` of the rectangles that meet the unit disk.
    shares : ndarray, shape (J,)
        Each cell's fraction of the disk's area (they sum to 1).
    """
    lines = [-1.0, 1.0]
    for rho in radii:
        r = abs(float(rho))
        d = np.arange(-math.ceil(r + 0.5), math.ceil(r + 0.5) + 1) + 0.5
        lines.extend(d[np.abs(d) < r] / r)
    lines = np.unique(lines)
    x0, y0 = np.meshgrid(lines[:-1], lines[:-1], indexing="ij")
    x1, y1 = np.meshgrid(lines[1:], lines[1:], indexing="ij")
    cells = np.stack([x0.ravel(), x1.ravel(), y0.ravel(), y1.ravel()], axis=1)
    shares = unit_disk_fraction(*cells.T)
    keep = shares > 1e-15
    return cells[keep], shares[keep]


def cell_kernels(cells: np.ndarray, rho: float, half: int) -> np.ndarray:
    """The pillbox (Eq. 3) of radius ``|rho|`` (Eq. 2) restricted to each aperture cell.

    Parameters
    ----------
    cells : ndarray, shape (J, 4)
        From :func:`aperture_cells`.
    rho : float
        The layer's signed radius (:func:`signed_radius`).
    half : int
        Kernel half size; at least ``ceil(|rho| + 1/2)`` for the whole disk.

    Returns
    -------
    ndarray, shape (J, 2 half + 1, 2 half + 1)
        ``K[j, half + dy, half + dx]``: the fraction of the aperture inside cell ``j``
        whose rays meet the layer in the pixel at offset ``(dy, dx)`` from ``g0`` (a
        *correlation* kernel: for ``rho < 0`` the cell's view is mirrored). Summed over
        ``j`` it is the whole pillbox.
    """
    off = np.arange(-half, half + 1, dtype=float)
    r0, r1 = _rect(off, _safe(float(rho)))
    x0, x1, y0, y1 = (c[:, None, None] for c in cells.T)
    return unit_disk_fraction(
        np.maximum(x0, r0[None, None, :]),
        np.minimum(x1, r1[None, None, :]),
        np.maximum(y0, r0[None, :, None]),
        np.minimum(y1, r1[None, :, None]),
    )
