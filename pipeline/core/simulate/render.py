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
to the layered render (:func:`pipeline.core.simulate.composite.edge_correction`). A static
detector is then exact at an edge between two surfaces; during a sweep the error falls with
the time cells. The layers are composited in :mod:`pipeline.core.simulate.composite`.

Magnification: the image scales by ``p(t) / p_ref`` about the centre (Sec. 3, footnote 1);
when it matters the exposure is cut into sub-steps, each rendered with its own IPSF and
scaled (cubic spline). Noise: Poisson shot noise plus Gaussian read noise in electrons.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np
from scipy import ndimage

from pipeline.core.lens import Lens
from pipeline.core.scene import Camera, Exposure, Scene, Surface
from pipeline.core.simulate import composite
from pipeline.core.simulate.planner import Plan, _KernelCache, plan
from pipeline.errors import InputError

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
            sub = composite.layered(
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
