"""Exact thin-lens ray trace of two fronto-parallel textured planes with a straight edge.

The near plane (depth ``u_near``) is opaque over the grid columns ``< edge_col`` (a
vertical straight edge at grid x = ``edge_col - 0.5``), the far plane (``u_far``) is
textured everywhere. Both textures are per grid pixel at ``p_ref`` (the simulator's scene
convention, ``pipeline.scene``; :mod:`.smooth` explains the rest of it), mirrored beyond
the borders.

A grid point ``g0`` and an aperture point ``A = (a/2) xi`` (``xi`` in the unit disk) give
the ray that meets the plane at inverse depth ``D`` at grid position
``g0 - rho(D) xi`` (:mod:`.optics`, signed ``rho``). The ray is the near plane's when
``g0_x - rho_n xi_x < e``; otherwise it passes the edge and lands on the far plane. So:

* near light: ``sum_y R_near[y] |unit disk ∩ xi-rectangle of pixel y| / pi`` over the
  near pixels (whose squares lie entirely on the near side);
* far light: the same over all far pixels (also those behind the near plane, which
  rays passing the edge see), each rectangle clipped to the half-plane
  ``rho_n xi_x <= g0_x - e`` of rays that miss the near plane (partial occlusion).

Areas are exact (:func:`.disk.unit_disk_fraction`), so the trace is exact for each time;
over an exposure it is summed over ``n_time`` cells (each with its magnification, the
grid image then scaled as in :mod:`.smooth`). :func:`trace_pixels_monte_carlo` is the
literal ray tracer (random aperture samples, first hit) used to check this.
"""

from __future__ import annotations

import math

import numpy as np

from .disk import unit_disk_fraction
from .optics import grid_radius
from .smooth import row_weights, scale_about_centre, time_cells


def _safe(rho: float) -> float:
    return rho if abs(rho) > 1e-12 else 1e-12


def _rect(d: np.ndarray, rho: float):
    """xi-interval of the pixel at offset ``d`` seen through a disk of signed radius ``rho``."""
    a, b = -(d - 0.5) / rho, -(d + 0.5) / rho
    return np.minimum(a, b), np.maximum(a, b)


def edge_grid_image(near, far, edge_col, inv_near, inv_far, optics, p_mm):
    """Grid image (at p_ref geometry) of the two planes for a detector at ``p_mm``."""
    rows, cols = near.shape
    rho_n = _safe(float(grid_radius(*optics, inv_near, p_mm)))
    rho_f = _safe(float(grid_radius(*optics, inv_far, p_mm)))
    half = math.ceil(max(abs(rho_n), abs(rho_f), 1e-9) + 0.5) + 1
    pad = half
    if not (pad < edge_col < cols - pad):
        raise ValueError(f"edge column {edge_col} within {pad} px of a border")
    near_p = np.pad(near, pad, mode="reflect")
    far_p = np.pad(far, pad, mode="reflect")
    alpha_p = np.pad((np.arange(cols) < edge_col).astype(float)[None, :].repeat(rows, 0),
                     pad, mode="reflect")
    off = np.arange(-half, half + 1, dtype=np.float64)
    e = edge_col - 0.5
    gx = np.arange(cols, dtype=np.float64)
    # near: no clipping (the near plane is first)
    ny0, ny1 = _rect(off[:, None], rho_n)
    nx0, nx1 = _rect(off[None, :], rho_n)
    w_near = unit_disk_fraction(nx0, nx1, ny0, ny1)  # (dy, dx)
    # far: clip xi_x to the rays that miss the near plane: rho_n xi_x <= gx - e
    fy0, fy1 = _rect(off[:, None, None], rho_f)
    fx0, fx1 = _rect(off[None, :, None], rho_f)
    thr = (gx - e) / rho_n  # (cols,)
    if rho_n > 0:  # xi_x <= thr
        fx1 = np.minimum(fx1, thr[None, None, :])
    else:  # xi_x >= thr
        fx0 = np.maximum(fx0, thr[None, None, :])
    w_far = unit_disk_fraction(fx0, np.maximum(fx1, fx0), fy0, fy1)  # (dy, dx, cols)
    size = 2 * half + 1
    win_n = np.lib.stride_tricks.sliding_window_view(near_p * alpha_p, (size, size))
    # every far pixel, also those behind the near plane: rays that pass the edge see them
    win_f = np.lib.stride_tricks.sliding_window_view(far_p, (size, size))
    img = np.einsum("yxij,ij->yx", win_n, w_near) + np.einsum("yxij,ijx->yx", win_f, w_far)
    return img


def render_edge(
    near: np.ndarray,
    far: np.ndarray,
    edge_col: int,
    u_near_mm: float,
    u_far_mm: float,
    *,
    f_mm: float,
    f_number: float,
    pitch_mm: float,
    times_s,
    positions_mm,
    p_ref_mm: float,
    row_windows=None,
    n_time: int = 1,
    magnification: bool = True,
) -> np.ndarray:
    """Time average of the exact two-plane image over the exposure (module notes)."""
    near = np.asarray(near, dtype=np.float64)
    far = np.asarray(far, dtype=np.float64)
    optics = (f_mm, f_number, pitch_mm, p_ref_mm)
    times_s = np.asarray(times_s, dtype=np.float64)
    positions_mm = np.asarray(positions_mm, dtype=np.float64)
    bounds, mids = time_cells(times_s, n_time)
    p_mid = np.interp(mids, times_s, positions_mm)
    weights = row_weights(bounds, row_windows, near.shape[0])
    out = np.zeros(near.shape)
    inv_near, inv_far = 1.0 / u_near_mm, (0.0 if math.isinf(u_far_mm) else 1.0 / u_far_mm)
    for k in np.flatnonzero(weights.max(axis=0) > 0):
        img = edge_grid_image(near, far, edge_col, inv_near, inv_far, optics, p_mid[k])
        if magnification:
            img = scale_about_centre(img, float(p_mid[k] / p_ref_mm))
        out += weights[:, k][:, None] * img
    return out


def trace_pixels_monte_carlo(
    near, far, edge_col, u_near_mm, u_far_mm, *, f_mm, f_number, pitch_mm, p_mm, p_ref_mm,
    pixels, samples=400_000, seed=0,
):
    """Literal ray tracer (static detector at ``p_ref``): random aperture points, first hit.

    For each ``(row, col)`` in ``pixels``: rays from the pixel centre through uniformly
    random aperture points; a ray whose hit on the near plane falls on a pixel of the near
    plane's alpha map (nearest pixel, mirrored borders) takes that pixel's radiance, any
    other continues to the far plane. Returns the mean radiance and its standard error.
    """
    rng = np.random.default_rng(seed)
    rows, cols = near.shape
    alpha = (np.arange(cols) < edge_col)[None, :].repeat(rows, 0)
    optics = (f_mm, f_number, pitch_mm, p_ref_mm)
    rho_n = float(grid_radius(*optics, 1.0 / u_near_mm, p_mm))
    rho_f = float(grid_radius(*optics, 1.0 / u_far_mm, p_mm))
    m = p_mm / p_ref_mm
    centre = np.array([(rows - 1) / 2, (cols - 1) / 2])

    def lookup(img, g):
        r = np.rint(g[:, 0]).astype(int)
        c = np.rint(g[:, 1]).astype(int)
        r = np.abs(r)
        r = np.where(r > rows - 1, 2 * (rows - 1) - r, r)
        c = np.abs(c)
        c = np.where(c > cols - 1, 2 * (cols - 1) - c, c)
        return img[r, c]

    results = []
    for row, col in pixels:
        radius = np.sqrt(rng.random(samples))
        theta = 2 * np.pi * rng.random(samples)
        xi = np.stack([radius * np.sin(theta), radius * np.cos(theta)], axis=1)  # (y, x)
        g0 = centre + (np.array([row, col], float) - centre) / m
        g_near = g0 - rho_n * xi
        g_far = g0 - rho_f * xi
        hit_near = lookup(alpha, g_near)
        value = np.where(hit_near, lookup(near, g_near), lookup(far, g_far))
        results.append((float(value.mean()), float(value.std() / np.sqrt(samples))))
    return results
