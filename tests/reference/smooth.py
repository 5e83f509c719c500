"""Brute-force time integration for occlusion-free (smooth) depth-map scenes.

Independent of ``pipeline.simulate`` / ``pipeline.psf``: its own lens law
(:mod:`.optics`), its own exact pixel-integrated disks (:mod:`.disk`), no layer
planning, no kernel-error metric. The only thing it shares with the simulator is the
*convention* of what a scene is (``pipeline.scene``):

* radiance and depth are per grid pixel at ``p_ref`` (a pixel's light leaves from its
  square with that pixel's depth); the grid continues mirrored beyond its borders
  (numpy ``reflect``, as the simulator pads);
* a scene pixel at inverse depth ``D`` reaches the grid, at detector position ``p``, as
  a disk of radius ``|rho(D, p)|`` grid px (:func:`.optics.grid_radius`: Eq. 2's blur
  ``b`` divided by the magnification ``m = p / p_ref``, the exact thin-lens value);
* the detector sees that grid image scaled by ``m`` about the grid centre, read by a
  cubic spline with mirrored borders (the simulator's interpolant; the reference uses
  ``scipy.ndimage`` for it, as the simulator does: this fixes the meaning of a sub-pixel
  position, which the scene's pixel grid alone leaves open);
* the output is the time average over each row's exposure window; no noise, no
  irradiance fall-off with ``m`` (neither is in Eq. 5 nor in the simulator).

Time: ``n_time`` equal cells (midpoint rule), each with its own exact magnification and
exact kernels, every row weighting each cell by its overlap with the row's window.
Depth: one layer per distinct inverse depth when there are at most ``max_exact`` (exact
per-pixel depth), else ``n_layers`` nodes uniform in ``D`` with each pixel's light split
linearly between its two neighbouring nodes (second-order accurate).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import fft as sfft
from scipy import ndimage

from .disk import pixel_disk_kernels
from .optics import grid_radius


def scale_about_centre(image: np.ndarray, m: float) -> np.ndarray:
    """Image seen at magnification ``m``: output ``x`` reads input ``c + (x - c) / m``."""
    if m == 1.0:
        return image
    rows, cols = image.shape
    centre = np.array([(rows - 1) / 2, (cols - 1) / 2])
    return ndimage.affine_transform(
        image, np.full(2, 1 / m), offset=centre * (1 - 1 / m), order=3, mode="mirror"
    )


def time_cells(times_s, n_time: int):
    """Equal cells over the motion: bounds and midpoints."""
    t0, t1 = float(times_s[0]), float(times_s[-1])
    bounds = np.linspace(t0, t1, n_time + 1)
    return bounds, 0.5 * (bounds[1:] + bounds[:-1])


def row_weights(bounds: np.ndarray, windows, rows: int) -> np.ndarray:
    """``(rows, cells)``: overlap of each cell with each row's window / the window's length."""
    if windows is None:
        w = np.diff(bounds) / (bounds[-1] - bounds[0])
        return np.broadcast_to(w, (rows, w.size)).copy()
    win = np.asarray(windows, dtype=np.float64)
    lo = np.maximum(bounds[None, :-1], win[:, :1])
    hi = np.minimum(bounds[None, 1:], win[:, 1:])
    return np.clip(hi - lo, 0.0, None) / (win[:, 1:] - win[:, :1])


def depth_nodes(inv: np.ndarray, n_layers: int | None, max_exact: int):
    """Layer nodes in ``D`` and each pixel's (node, weight) pairs (exact or linear split)."""
    uniq = np.unique(inv)
    if n_layers is None and uniq.size <= max_exact:
        idx = np.searchsorted(uniq, inv)
        return uniq, [(idx, np.ones_like(inv))]
    n = n_layers or 257
    lo, hi = float(uniq[0]), float(uniq[-1])
    nodes = np.linspace(lo, hi, n) if hi > lo else np.array([lo])
    if nodes.size == 1:
        return nodes, [(np.zeros(inv.shape, int), np.ones_like(inv))]
    pos = (inv - lo) / (hi - lo) * (n - 1)
    i0 = np.clip(np.floor(pos).astype(int), 0, n - 2)
    frac = pos - i0
    return nodes, [(i0, 1 - frac), (i0 + 1, frac)]


def render_smooth(
    radiance: np.ndarray,
    depth_mm: np.ndarray,
    *,
    f_mm: float,
    f_number: float,
    pitch_mm: float,
    times_s,
    positions_mm,
    p_ref_mm: float,
    row_windows=None,
    n_time: int = 256,
    n_layers: int | None = None,
    max_exact: int = 192,
    magnification: bool = True,
    blur_times_m: bool = False,
) -> np.ndarray:
    """Capture of a smooth scene: sum over time cells and thin depth layers (module notes).

    ``blur_times_m`` (diagnosis only, not physics): blur each time cell's grid image by
    Eq. 2's detector blur ``b`` instead of ``b / m`` before scaling it by ``m``, i.e. the
    simulator's model of a scaled sub-step (its output blur is ``b m``).
    """
    radiance = np.asarray(radiance, dtype=np.float64)
    rows, cols = radiance.shape
    with np.errstate(divide="ignore"):
        inv = np.where(np.isinf(depth_mm), 0.0, 1.0 / np.asarray(depth_mm, dtype=np.float64))
    nodes, splits = depth_nodes(inv, n_layers, max_exact)
    times_s = np.asarray(times_s, dtype=np.float64)
    positions_mm = np.asarray(positions_mm, dtype=np.float64)
    bounds, mids = time_cells(times_s, n_time)
    p_mid = np.interp(mids, times_s, positions_mm)
    weights = row_weights(bounds, row_windows, rows)
    optics = (f_mm, f_number, pitch_mm, p_ref_mm)
    rho_max = float(
        np.max(np.abs(grid_radius(*optics, nodes[:, None], positions_mm[None, :])))
    )
    half = math.ceil(rho_max + 0.5) + 1
    pad = half
    shape = (rows + 2 * pad, cols + 2 * pad)
    layer_spectra = np.zeros((nodes.size, shape[0], shape[1] // 2 + 1), dtype=complex)
    rad_p = np.pad(radiance, pad, mode="reflect")
    for idx, w in splits:
        idx_p = np.pad(idx, pad, mode="reflect")
        w_p = np.pad(w, pad, mode="reflect")
        for node in np.unique(idx_p):
            sel = idx_p == node
            layer = np.where(sel, rad_p * w_p, 0.0)
            layer_spectra[node] += sfft.rfft2(layer)
    out = np.zeros((rows, cols))
    size = 2 * half + 1
    for k in np.flatnonzero(weights.max(axis=0) > 0):
        rho = grid_radius(*optics, nodes, p_mid[k])
        if blur_times_m:
            rho = rho * (p_mid[k] / p_ref_mm)
        kernels = pixel_disk_kernels(rho, half)
        padded = np.zeros((nodes.size, *shape))
        padded[:, :size, :size] = kernels
        padded = np.roll(padded, (-half, -half), axis=(1, 2))
        spec = np.einsum("lij,lij->ij", layer_spectra, sfft.rfft2(padded, axes=(1, 2)))
        image = sfft.irfft2(spec, s=shape)[pad : pad + rows, pad : pad + cols]
        if magnification:
            image = scale_about_centre(image, float(p_mid[k] / p_ref_mm))
        out += weights[:, k][:, None] * image
    return out
