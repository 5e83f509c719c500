"""Depth layers blurred by their kernels and composited: the image-formation model of
:mod:`pipeline.core.simulate.render` (its module notes): hat-function blending without
occlusion, "over" compositing with coverage renormalisation at depth edges, and
sub-aperture compositing near occluding edges (:func:`edge_correction`).

Used by the renderer and by the planner, which renders the edge box with 1, 2, 4, ...
time cells to estimate the error of sub-aperture compositing.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import signal

from pipeline.core.simulate import edge as edge_model

_CELL_CHUNK = 1 << 22  # values per batch of aperture cells (32 MiB of float64)


def layered(
    scene, layers, profile, cache, occlusion, edge, scale=1.0, time_cells=0
) -> np.ndarray:
    """Blur each depth layer by its kernel and composite (module notes).

    ``scale``: the step is scaled by it afterwards, so its kernels are in grid pixels
    (Eq. 2's detector blur divided by ``scale``). ``time_cells`` > 0: near the
    occluding layers' edges, add the sub-aperture correction (:func:`edge_correction`)
    with that many time cells.
    """
    dtype = scene.dtype
    kernels = [cache.kernel(layer.inv_rep, profile, scale).astype(dtype) for layer in layers]
    pad = max(k.shape[0] // 2 for k in kernels)
    ends = np.array([layer.inv_hi for layer in layers])
    ordered = sorted(scene.surfaces, key=lambda s: -float(np.median(s.depth_mm)))  # far first
    padded = []
    for s in ordered:
        inv = 1.0 / s.depth_mm
        idx = np.searchsorted(ends, inv, side="left").clip(0, len(layers) - 1)
        widths = ((pad, pad), (pad, pad))
        hat = None if occlusion else _hat(inv, layers, idx)
        padded.append(
            (
                np.pad(s.radiance * s.alpha[:, :, None], (*widths, (0, 0)), mode="reflect"),
                np.pad(s.alpha, widths, mode="reflect"),
                np.pad(idx, widths, mode="reflect"),
                None if hat is None else tuple(np.pad(h, widths, mode="reflect") for h in hat),
            )
        )
    shape = padded[0][1].shape
    channels = padded[0][0].shape[2]
    out = np.zeros((*shape, channels), dtype=dtype)
    if occlusion:
        transmit = np.ones(shape, dtype=dtype)
        covered = np.zeros(shape, dtype=dtype)
        coverage = np.zeros(shape, dtype=dtype)
        pending: list = []
        blocks: list = []  # (layer, rows, cols, unblurred colour + alpha) for the edge cells
    for i in range(len(layers) - 1, -1, -1):  # near to far
        if occlusion:
            weights = [((idx == i) & (a > 0)).astype(dtype) for _, a, idx, _ in padded]
        else:  # hat functions: each pixel split between its two nearest representatives
            weights = [
                np.where(a > 0, np.where(lo == i, 1 - th, 0) + np.where(lo + 1 == i, th, 0), 0)
                for _, a, _, (lo, th) in padded
            ]
        masks = [w > 0 for w in weights]
        union = np.logical_or.reduce(masks)
        if not union.any():
            continue
        h = kernels[i].shape[0] // 2
        rr, cc = np.nonzero(union.any(axis=1))[0], np.nonzero(union.any(axis=0))[0]
        r0, r1 = max(rr[0] - h, 0), min(rr[-1] + h + 1, shape[0])
        c0, c1 = max(cc[0] - h, 0), min(cc[-1] + h + 1, shape[1])
        color = np.zeros((r1 - r0, c1 - c0, channels), dtype=dtype)
        alpha = np.zeros((r1 - r0, c1 - c0), dtype=dtype)
        for (c, a, _, _), w in zip(padded, weights):  # far to near within the layer: "over"
            w = w[r0:r1, c0:c1].astype(dtype)
            a_here = w * a[r0:r1, c0:c1]
            color = w[:, :, None] * c[r0:r1, c0:c1] + (1 - a_here)[:, :, None] * color
            alpha = a_here + (1 - a_here) * alpha
        block = np.concatenate([color, alpha[:, :, None]], axis=2) if occlusion else color
        if occlusion and time_cells:
            blocks.append((i, (r0, r1, c0, c1), block))
        blurred = signal.oaconvolve(block, kernels[i][:, :, None], mode="same", axes=(0, 1))
        if not occlusion:
            out[r0:r1, c0:c1] += blurred
            continue
        inv = layers[i].inv_rep
        while pending and pending[0][0] > inv + edge:  # nearer by more than an edge: occludes
            _, (q0, q1, s0, s1), a_near = pending.pop(0)
            transmit[q0:q1, s0:s1] *= 1 - a_near
        t = transmit[r0:r1, c0:c1]
        a_blur = blurred[:, :, -1]
        out[r0:r1, c0:c1] += blurred[:, :, :-1] * t[:, :, None]
        covered[r0:r1, c0:c1] += a_blur * t
        coverage[r0:r1, c0:c1] += a_blur
        pending.append((inv, (r0, r1, c0, c1), a_blur))
    if occlusion:
        with np.errstate(divide="ignore", invalid="ignore"):
            lost = np.minimum(coverage, 1) / covered  # coverage lost to self-occlusion
            factor = np.where(covered > 1e-6, np.maximum(lost, 1), 0).astype(dtype)
        out *= factor[:, :, None]
        if time_cells:  # after the renormalisation, which is 1 at edges between surfaces
            lens = cache.lens
            edge_correction(out, blocks, layers, profile, lens, edge, scale, time_cells, pad)
    return out[pad : shape[0] - pad, pad : shape[1] - pad]


def edge_correction(out, blocks, layers, profile, lens, edge, scale, time_cells, pad) -> None:
    """Add sub-aperture compositing minus 'over' compositing near occluding edges to ``out``.

    The window ``profile`` is cut into ``time_cells`` equal cells; in each, at its
    mid-time detector position ``p``, every layer is a pillbox (Eq. 3) of signed radius
    ``rho_i(p)`` (Eq. 2, :func:`edge.signed_radius`), the aperture is split into the cells
    bounded by the occluders' pixel lines (:func:`edge.aperture_cells`), and each cell's
    view is composited with its own partial kernels and visibilities
    (:mod:`pipeline.core.simulate.edge`). Subtracting the over model made from the same
    pillboxes leaves only the partial-occlusion correction, which is 0 where no
    occluder's alpha changes within its blur: the work is confined to the box around the
    occluders' edges. The time average of the pillboxes tends to the IPSF of Eqs. 5-6 as
    the time cells shrink.

    Parameters
    ----------
    out : ndarray
        The layered render on the padded grid (rows, cols, channels); changed in place.
    blocks : list of (int, (r0, r1, c0, c1), ndarray)
        Each layer's index, extent on the padded grid and unblurred premultiplied colour
        with its alpha as the last channel, near to far.
    layers : sequence of Layer
    profile : Profile
        The sub-step's motion window.
    lens : Lens
    edge : float
        Layer ``k`` occludes layer ``i`` when ``D_k > D_i + edge`` (as in the over model).
    scale : float
        The sub-step's image scale (its kernels are in grid px).
    time_cells : int
        Time cells of a moving window (a static one needs one).
    pad : int
        The padding of ``out``, at least every layer's kernel half size.
    """
    inv = {i: layers[i].inv_rep for i, _, _ in blocks}
    occluders = {k: [j for j in inv if inv[j] > inv[k] + edge] for k in inv}
    front = sorted({j for near in occluders.values() for j in near})
    box = _edge_box(blocks, front, out.shape[:2], pad)
    if box is None:
        return
    b0, b1, c0, c1 = box
    rows, cols = b1 - b0, c1 - c0
    sources = {}
    for i, (r0, r1, s0, s1), block in blocks:  # each layer's block on the box + its halo
        src = np.zeros((rows + 2 * pad, cols + 2 * pad, block.shape[2]))
        q0, q1, t0, t1 = max(r0, b0 - pad), min(r1, b1 + pad), max(s0, c0 - pad), min(s1, c1 + pad)
        if q0 < q1 and t0 < t1:
            src[q0 - b0 + pad : q1 - b0 + pad, t0 - c0 + pad : t1 - c0 + pad] = block[
                q0 - r0 : q1 - r0, t0 - s0 : t1 - s0
            ]
        sources[i] = src
    t_a, t_b = float(profile.times_s[0]), float(profile.times_s[-1])
    n = time_cells if np.ptp(profile.image_distances_mm) > 0 else 1
    mids = t_a + (np.arange(n) + 0.5) * (t_b - t_a) / n
    cells_img = 0.0
    chunk = max(1, _CELL_CHUNK // next(iter(sources.values())).size)
    mean_k = {i: np.zeros((2 * pad + 1, 2 * pad + 1)) for i in sources}
    for p in profile.position(mids):
        rho = {i: edge_model.signed_radius(lens, inv[i], float(p), scale) for i in sources}
        cells, shares = edge_model.aperture_cells([rho[k] for k in front])
        for j0 in range(0, len(cells), chunk):
            sel = slice(j0, j0 + chunk)
            views = {}
            for i, src in sources.items():
                h = min(pad, math.ceil(abs(rho[i]) + 0.5))  # the pillbox's support
                k = edge_model.cell_kernels(cells[sel], rho[i], h)
                mean_k[i][pad - h : pad + h + 1, pad - h : pad + h + 1] += k.sum(axis=0) / n
                views[i] = _correlate(src[pad - h : rows + pad + h, pad - h : cols + pad + h], k)
            share = shares[sel, None, None, None]
            for i, view in views.items():
                seen = view[..., :-1] * _transmit(views, occluders[i], share)
                cells_img = cells_img + np.sum(seen, axis=0) / n
    views = {i: _correlate(src, mean_k[i][None])[0] for i, src in sources.items()}
    over = sum(view[..., :-1] * _transmit(views, occluders[i], 1.0) for i, view in views.items())
    out[b0:b1, c0:c1] += (cells_img - over).astype(out.dtype)


def _transmit(views, occluders, share):
    """``prod_k (1 - A_k / share)``: the part of a cell (aperture ``share``) that passes
    the occluders, whose views (alpha last) are in ``views``."""
    t = 1.0
    for k in occluders:
        t = t * (1 - views[k][..., -1:] / share)
    return t


def _edge_box(blocks, front, shape, pad):
    """Rows and columns (padded grid, inside the image) within ``pad`` px of a pixel where
    an occluding layer's alpha changes; ``None`` if there is none."""
    hit = np.zeros(shape, bool)
    for i, (r0, r1, c0, c1), block in blocks:
        if i not in front:
            continue
        a = np.pad(block[:, :, -1], 1, mode="edge")
        core = a[1:-1, 1:-1]
        change = (core > 0) & (core < 1)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                change |= a[1 + dy : a.shape[0] - 1 + dy, 1 + dx : a.shape[1] - 1 + dx] != core
        hit[r0:r1, c0:c1] |= change
    hit[:pad], hit[shape[0] - pad :], hit[:, :pad], hit[:, shape[1] - pad :] = (False,) * 4
    rr, cc = np.nonzero(hit.any(axis=1))[0], np.nonzero(hit.any(axis=0))[0]
    if not rr.size:
        return None
    return (
        max(rr[0] - pad, pad),
        min(rr[-1] + pad + 1, shape[0] - pad),
        max(cc[0] - pad, pad),
        min(cc[-1] + pad + 1, shape[1] - pad),
    )


def _correlate(src: np.ndarray, kernels: np.ndarray) -> np.ndarray:
    """``out[j, y, x] = sum_d kernels[j, h + d] src[h + y + d]``: each kernel's correlation
    over the valid part of ``src`` (rows, cols, channels)."""
    flipped = kernels[:, ::-1, ::-1, None]
    return signal.fftconvolve(src[None], flipped, mode="valid", axes=(1, 2))


def _hat(inv: np.ndarray, layers, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hat-function split: ``(lo, theta)``, weight ``1 - theta`` to layer ``lo`` and
    ``theta`` to ``lo + 1``, linear in inverse depth between their representatives.

    The kernel is then piecewise linear in D and continuous across layer boundaries (box
    layers leave seams proportional to the mean radiance). Only within a group (layers of
    different surfaces' depth ranges never mix); elsewhere the pixel keeps its box layer.
    """
    n = len(layers)
    if n == 1:
        return np.zeros(inv.shape, int), np.zeros(inv.shape)
    reps = np.array([layer.inv_rep for layer in layers])
    group = np.array([layer.group for layer in layers])
    lo = (np.searchsorted(reps, inv, side="right") - 1).clip(0, n - 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        theta = np.clip((inv - reps[lo]) / (reps[lo + 1] - reps[lo]), 0.0, 1.0)
    same = group[lo] == group[lo + 1]
    box_theta = (idx == lo + 1).astype(float)
    theta = np.where(same, np.nan_to_num(theta), box_theta)
    return lo, theta
