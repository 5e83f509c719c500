"""Forward model: scene radiance + depth -> capture, simulating only the effects that matter.

Captures: a normal capture (static p), a focus sweep (any :class:`~pipeline.core.motion.Profile`,
Eq. 5), a rolling-shutter sweep (each row integrates its own window, Sec. 6-7) and a focal
stack (a list of static p, Sec. 9). :func:`plan` decides, before rendering, which effects
a scene needs at a tolerance; :func:`render` follows the plan.

The tolerance
-------------
Every effect is judged with one metric, :func:`kernel_error`: the RMS change of a natural
image (a 1/f amplitude spectrum, :func:`pipeline.core.spectra.natural_image_spectrum`, of unit
variance on a 256 px grid) when it is blurred by ``k2`` instead of ``k1``::

    e(k1, k2) = sqrt(sum_w |K1(w) - K2(w)|^2 |F(w)|^2)

i.e. the image error per unit RMS radiance contrast. It is a norm, so errors of steps
add up at most linearly (used to bound layer assignment). A radiance image with standard
deviation ``s`` sees errors of about ``s * e``.

The image-formation model
-------------------------
Depth is split into layers in inverse depth ``D = 1/u`` (1/mm; the blur diameter of Eq. 2
is piecewise linear in D): a layer ends where its kernel (the IPSF of Eq. 5 at its
representative depth) would differ from a member depth's kernel by more than the tolerance.
Layers never span two surfaces whose depth ranges do not overlap. Without occlusion each
pixel is split between the two nearest representatives with hat-function weights linear
in D (the kernel is continuous across layer boundaries: no seams), and the image is the
plain sum of the layers' blurred premultiplied radiance ``L alpha``.

Occlusion only happens at *depth edges*: where the blur radius changes by more than 1 px
per px (``k max|D - D'| > 1`` over the 8 neighbours, ``k = (a/2) p / pitch``), or at the
silhouette of a nearer surface over a farther one; elsewhere every ray through the
aperture meets the scene once and the plain sum is exact. With edges, box layers are
composited "over" back to front, a layer covered by every layer nearer by more than
``edge`` in D::

    out = sum_i C_i T_i,  T_i = prod_{j: D_j > D_i + edge} (1 - A_j)
    out *= max(1, min(1, sum_i A_i) / sum_i A_i T_i)    (coverage renormalisation)

The over model misses partial occlusion (a pixel's aperture split by the edge when both
sides are out of focus); the plan estimates that error with an exact straight-edge trace
(:mod:`pipeline.core.simulate.edge`). Where it exceeds the tolerance the plan asks for
sub-aperture compositing (``Plan.edge_time_cells``): in a box around the occluding
layers' edges the aperture is split into cells along the occluders' pixel lines, each
cell's view composited "over" with its own partial pillboxes (Eq. 2) and visibilities,
and the cells averaged (over ``edge_time_cells`` time cells per sub-step for a sweep,
whose IPSF is the time average of Eqs. 5-6); the difference to the over model is added
to the layered render (:func:`_edge_correction`). A static detector is then exact at an
edge between two surfaces; during a sweep the error falls with the time cells.

Magnification: the image scales by ``p(t) / p_ref`` about the centre (Sec. 3, footnote 1);
when it matters the exposure is cut into sub-steps, each rendered with its own IPSF and
scaled (cubic spline). Noise: Poisson shot noise plus Gaussian read noise in electrons.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import numpy as np
from scipy import ndimage, signal

from pipeline.core.lens import Lens
from pipeline.core.scene import Camera, Exposure, Scene, Surface
from pipeline.core.simulate import edge as edge_model
from pipeline.core.simulate.planner import Plan, _KernelCache, plan
from pipeline.errors import InputError

_CELL_CHUNK = 1 << 22  # values per batch of aperture cells (32 MiB of float64)
_SPLINE_MARGIN = 12  # rows: the cubic spline's prefilter decays 0.27x per px (1e-7 at 12)


# ----------------------------------------------------------------------------- render
def render(
    scene: Scene,
    camera: Camera,
    *,
    plan_: Plan | None = None,
    tolerance: float = 1e-3,
    seed: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """Render one capture of ``scene`` with ``camera``, following a :class:`Plan`.

    Parameters
    ----------
    scene : Scene
    camera : Camera
    plan_ : Plan, optional
        From :func:`plan`; made with ``tolerance`` when omitted.
    tolerance : float
    seed : int, optional
        Seed of the noise (only used when the camera has an exposure).
    progress : callable(done, total), optional
        Called after each rendered step of the plan (bands x time steps).

    Returns
    -------
    ndarray
        Linear radiance ``(rows, cols[, channels])``, the scene's dtype (float32 or
        float64), as the time average over the exposure (Eq. 5 normalised by T).
        Noise, when applied, is not clipped: values may be negative.

    Examples
    --------
    A textured plane at 750 mm, captured while focused there and while focused
    at 450 mm: only the second is blurred (less contrast).

    >>> import numpy as np
    >>> from pipeline.core import optics
    >>> from pipeline.core.lens import Lens
    >>> from pipeline.core.scene import Camera, Scene
    >>> lens = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=4.65,
    ...             width_px=64, height_px=48)
    >>> radiance = np.random.default_rng(1).uniform(0, 1, (48, 64))
    >>> scene = Scene.from_depth(radiance, np.full((48, 64), 750.0))
    >>> def capture(focus_mm):
    ...     v = optics.image_distance(12.5, focus_mm)
    ...     return render(scene, Camera.static(lens, v, exposure_s=0.01))
    >>> sharp, blurred = capture(750.0), capture(450.0)
    >>> bool(np.allclose(sharp, radiance, atol=1e-3)), bool(blurred.std() < 0.5 * sharp.std())
    (True, True)
    """
    p = plan_ if plan_ is not None else plan(scene, camera, tolerance=tolerance)
    if p.shape != scene.shape:
        raise InputError(f"the plan is for a {p.shape} scene, got {scene.shape}")
    rows, cols = scene.shape
    channels = scene.surfaces[0].radiance.shape[2]
    out = np.zeros((rows, cols, channels), dtype=scene.dtype)
    cache = _KernelCache(p.lens, p.model, None)  # type: ignore[arg-type]
    total, done = sum(len(band.steps) for band in p.bands), 0
    centre = np.array([(rows - 1) / 2, (cols - 1) / 2])
    for band in p.bands:
        cache.clear()
        r0, r1 = band.row_start, band.row_stop
        q0, q1, part = 0, rows, scene
        if len(p.bands) > 1:  # only the band's rows plus what reaches them
            half = max(
                cache.kernel(layer.inv_rep, step.profile, step.scale).shape[0] // 2
                for layer in band.layers
                for step in band.steps
            )
            reach = max(abs(r0 - centre[0]), abs(r1 - 1 - centre[0]))
            moved = max(abs(1 - 1 / step.scale) for step in band.steps) * reach
            margin = half + int(np.ceil(moved)) + _SPLINE_MARGIN
            q0, q1 = max(0, r0 - margin), min(rows, r1 + margin)
            part = _rows(scene, q0, q1)
        image = np.zeros((q1 - q0, cols, channels), dtype=out.dtype)
        for step in band.steps:
            sub = _layered(
                part, band.layers, step.profile, cache, p.occlusion, p.edge_inv_depth,
                step.scale, p.edge_time_cells,
            )
            if step.scale != 1.0:
                sub = _scale(sub, step.scale, centre - np.array([q0, 0]))
            image += np.asarray(step.weight, dtype=out.dtype) * sub
            done += 1
            if progress is not None:
                progress(done, total)
        out[r0:r1] = image[r0 - q0 : r1 - q0]
    if p.noise is not None:
        out = _add_noise(out, p.noise, seed)
    return out if scene.channels_axis else out[:, :, 0]


def _layered(
    scene, layers, profile, cache, occlusion, edge, scale=1.0, time_cells=0
) -> np.ndarray:
    """Blur each depth layer by its kernel and composite (module notes).

    ``scale``: the step is scaled by it afterwards, so its kernels are in grid pixels
    (Eq. 2's detector blur divided by ``scale``). ``time_cells`` > 0: near the
    occluding layers' edges, add the sub-aperture correction (:func:`_edge_correction`)
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
            _edge_correction(out, blocks, layers, profile, lens, edge, scale, time_cells, pad)
    return out[pad : shape[0] - pad, pad : shape[1] - pad]


def _edge_correction(out, blocks, layers, profile, lens, edge, scale, time_cells, pad) -> None:
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


def _rows(scene: Scene, q0: int, q1: int) -> Scene:
    """The scene's rows ``[q0, q1)``."""
    surfaces = tuple(
        Surface(s.radiance[q0:q1], s.alpha[q0:q1], s.depth_mm[q0:q1]) for s in scene.surfaces
    )
    return dataclasses.replace(scene, surfaces=surfaces)


def _scale(image: np.ndarray, scale: float, centre=None) -> np.ndarray:
    """Scale about ``centre`` (default the image centre) by ``scale`` (cubic spline,
    mirrored borders)."""
    rows, cols = image.shape[:2]
    if centre is None:
        centre = np.array([(rows - 1) / 2, (cols - 1) / 2])
    out = np.empty_like(image)
    for c in range(image.shape[2]):  # output pixel x samples the input at c + (x - c) / scale
        ndimage.affine_transform(
            image[:, :, c],
            np.full(2, 1 / scale),
            offset=centre * (1 - 1 / scale),
            output=out[:, :, c],
            order=3,
            mode="mirror",
        )
    return out


def _add_noise(image: np.ndarray, exposure: Exposure, seed: int | None) -> np.ndarray:
    """Shot noise (Poisson in electrons) + read noise (Gaussian); back in radiance units."""
    rng = np.random.default_rng(seed)
    e = exposure.electrons_at_unit
    electrons = rng.poisson(np.maximum(image.astype(np.float64), 0) * e).astype(np.float64)
    if exposure.read_noise_e > 0:
        electrons += rng.normal(0.0, exposure.read_noise_e, image.shape)
    return (electrons / e).astype(image.dtype)


# ----------------------------------------------------------------------------- focal stacks
def render_focal_stack(
    scene: Scene,
    lens: Lens,
    image_distances_mm: Sequence[float],
    *,
    exposure_s: float = 1.0,
    exposure: Exposure | None = None,
    reference_image_distance_mm: float | None = None,
    psf_model: str | None = None,
    tolerance: float = 1e-3,
    seed: int | None = None,
) -> tuple[np.ndarray, list[Plan]]:
    """A focal stack: one static capture per detector position (Sec. 9).

    Every frame is scaled by ``p_i / p_ref`` (``p_ref`` default: the mean of the
    positions) when the plan says it matters. Returns ``(frames, plans)``, frames of shape
    ``(n, rows, cols[, channels])``. Per-frame noise seeds are spawned from ``seed``.
    """
    positions = [float(v) for v in np.asarray(image_distances_mm, dtype=np.float64).ravel()]
    if not positions:
        raise InputError("image_distances_mm must hold at least one position")
    p_ref = reference_image_distance_mm or float(np.mean(positions))
    seeds = np.random.SeedSequence(seed).spawn(len(positions))
    frames, plans = [], []
    for pos, child in zip(positions, seeds):
        cam = Camera.static(
            lens,
            pos,
            exposure_s,
            exposure=exposure,
            psf_model=psf_model,
            reference_image_distance_mm=p_ref,
            shutter="global",
        )
        pl = plan(scene, cam, tolerance=tolerance)
        frames.append(render(scene, cam, plan_=pl, seed=int(child.generate_state(1)[0])))
        plans.append(pl)
    return np.stack(frames), plans
