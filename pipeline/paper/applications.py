"""The paper's four applications on synthetic scenes: extended (Fig. 6), discontinuous
(Fig. 10), tilted (Fig. 11) and non-planar (Fig. 12) depth of field, with measurements.

Each ``*_application`` builds a scene from real photographs (``skimage.data``,
linearised sRGB) as planar layers or depth maps, renders the paper's capture and its
normal-camera comparisons with :func:`pipeline.core.simulate.render.render`, and measures the
paper's claim. They return an :class:`Application`: linear images (the panels of the
figure), per-region rows and a summary of scalars. Writing files is the CLI's job.

Renders are small: :func:`scaled_lens` keeps a camera's sensor area (so its field of
view and blur in mm) and rolling-shutter read-out time, with coarser pixels.

Sharpness measures
------------------
* :func:`detail_transfer`: a region's band-passed image regressed on the sharp scene's
  band after sub-pixel registration: 1 as sharp as the scene, 0 no detail; unbiased
  by noise. Fig. 6 adds the noise RMS (noisy minus noise-free render) and PSNR.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import fft as sfft
from scipy import ndimage
from skimage import data as skdata
from skimage import registration, transform

from pipeline.core import deconvolve, optics, quality, simulate
from pipeline.core.colour import mean_grey, srgb_to_linear
from pipeline.core.lens import Lens
from pipeline.core.motion import (
    plan_discontinuous_dof,
    plan_extended_dof,
    plan_nonplanar_dof,
    plan_tilted_dof,
    row_offsets_mm,
)
from pipeline.core.scene import Camera, Exposure, Scene, Surface
from pipeline.errors import InputError
from pipeline.io.profiles import load_lens
from pipeline.jobs.sweep import sweep_kernel

GLOBAL_LENS = "fujinon-12.5mm-f1.4-sony-1-3in"  # EDOF and discontinuous DOF (Sec. 3)
ROLLING_LENS = "fujinon-12.5mm-f1.4-micron-1-2.5in"  # tilted and non-planar DOF (Sec. 6, 7)
APPLICATIONS = ("6", "10", "11", "12")
TOLERANCE = 3e-3  # simulate.plan's kernel error; at 1e-2 the EDOF planes share one layer
PEAK_RADIANCE = 0.8  # textures peak below the clipping level (noise must not clip)
DETAIL_SIGMAS_PX = (0.7, 2.0)  # band of detail_transfer (px)
MAX_SHIFT_PX = 4.0  # largest shift detail_transfer registers


@dataclasses.dataclass(frozen=True, eq=False)
class Application:
    """One application's render: panels (label -> linear image), rows and a summary.

    ``rows`` is a list of dicts with the same keys (one per measured region);
    ``summary`` holds the scalars the paper's claim is judged by.
    """

    figure: str
    title: str
    panels: dict[str, np.ndarray]
    rows: list[dict]
    summary: dict


# ----------------------------------------------------------------------------- helpers
def scaled_lens(lens: Lens, width_px: int) -> Lens:
    """``lens`` with ``width_px`` columns over the same sensor area and read-out time.

    The pixel pitch grows by ``lens.width_px / width_px``; the rows follow; a rolling
    shutter's line time grows so that the first-to-last-row delay is unchanged (Sec. 6).
    """
    if isinstance(width_px, bool) or not isinstance(width_px, int) or not 16 <= width_px:
        raise InputError(f"width_px must be an integer >= 16, got {width_px!r}")
    factor = lens.width_px / width_px
    height = max(2, round(lens.height_px / factor))
    line_time = lens.line_time_us
    if lens.shutter == "rolling":
        line_time = lens.readout_time_s * 1e6 / (height - 1)
    return dataclasses.replace(
        lens,
        pixel_pitch_um=lens.pixel_pitch_um * factor,
        width_px=width_px,
        height_px=height,
        line_time_us=line_time,
        name=f"{lens.name} ({width_px}x{height} px)",
    )


def texture(name: str, shape: tuple[int, int], *, tint=None, crop=None) -> np.ndarray:
    """A ``skimage.data`` photograph as linear radiance ``(rows, cols, 3)`` float32.

    ``crop`` is ``(r0, r1, c0, c1)`` in fractions of the image; the crop is resized
    (anti-aliased) to ``shape``; greyscale images are multiplied by ``tint`` (RGB).
    """
    try:
        image = getattr(skdata, name)()
    except AttributeError as err:
        raise InputError(f"texture {name!r} is not a skimage.data image") from err
    image = np.asarray(image, dtype=np.float64) / 255.0
    if crop is not None:
        r0, r1, c0, c1 = crop
        h, w = image.shape[:2]
        image = image[round(r0 * h) : round(r1 * h), round(c0 * w) : round(c1 * w)]
    image = transform.resize(image, shape, anti_aliasing=True, order=1)
    if image.ndim == 2:
        image = image[:, :, None] * np.asarray(tint if tint is not None else (1, 1, 1))[None, None]
    return srgb_to_linear(image[:, :, :3].astype(np.float32)) * np.float32(PEAK_RADIANCE)


def _grey(image: np.ndarray) -> np.ndarray:
    return mean_grey(np.asarray(image, dtype=np.float64))


def detail_transfer(
    image: np.ndarray,
    reference: np.ndarray,
    mask: np.ndarray,
    *,
    sigmas_px=DETAIL_SIGMAS_PX,
    register: bool = True,
) -> float:
    """Fine detail of ``image`` as a fraction of ``reference``'s inside ``mask`` (1 = sharp).

    Both grey images are band-passed (difference of Gaussians, ``sigmas_px``) and
    the image's band is regressed on the reference's over the mask:
    ``sum bp(x) bp(ref) / sum bp(ref)^2``. A blur with a real transfer function ``H``
    gives the ``|bp(ref)|^2``-weighted mean of ``H`` over the band (``H(f)`` for a
    sinusoid); noise independent of the scene averages out instead of adding detail.

    ``register``: first move the reference by the sub-pixel shift (up to
    :data:`MAX_SHIFT_PX`) that best matches the image inside the mask's bounding box
    (phase correlation of the bands, 1/20 px), so that a displaced but sharp image
    (a focus sweep images each depth at its own magnification, Sec. 3) is not
    counted as blurred. See :func:`detail_shift` for the shift.
    """
    bands, mask = _bands(image, reference, mask, sigmas_px)
    if register:
        shift = _shift(bands, mask)
        bands[1] = np.real(sfft.ifft2(ndimage.fourier_shift(sfft.fft2(bands[1]), shift)))
    energy = float(np.sum(bands[1][mask] ** 2))
    if energy <= 0:
        raise InputError("the reference has no detail inside the mask")
    return float(np.sum(bands[0][mask] * bands[1][mask])) / energy


def detail_shift(
    image: np.ndarray, reference: np.ndarray, mask: np.ndarray, *, sigmas_px=DETAIL_SIGMAS_PX
) -> tuple[float, float]:
    """Sub-pixel (rows, cols) shift of ``image``'s detail relative to ``reference``'s."""
    bands, mask = _bands(image, reference, mask, sigmas_px)
    return _shift(bands, mask)


def _bands(image, reference, mask, sigmas_px) -> tuple[list[np.ndarray], np.ndarray]:
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != np.shape(image)[:2] or not mask.any():
        raise InputError(
            f"mask must be a non-empty bool array of the image's (rows, cols), got {mask.shape}"
        )
    if np.shape(reference) != np.shape(image):
        raise InputError(f"reference {np.shape(reference)} and image {np.shape(image)} differ")
    fine, coarse = sigmas_px
    bands = [
        ndimage.gaussian_filter(g, fine) - ndimage.gaussian_filter(g, coarse)
        for g in (_grey(image), _grey(reference))
    ]
    return bands, mask


def _shift(bands: list[np.ndarray], mask: np.ndarray) -> tuple[float, float]:
    rows, cols = np.nonzero(mask)
    box = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
    window = mask[box].astype(np.float64)
    shift, _, _ = registration.phase_cross_correlation(
        bands[0][box] * window, bands[1][box] * window, upsample_factor=20, normalization=None
    )
    if np.max(np.abs(shift)) > MAX_SHIFT_PX:
        return (0.0, 0.0)  # no credible match (a featureless or erased region)
    return float(shift[0]), float(shift[1])


def _interior(mask: np.ndarray, margin_px: int) -> np.ndarray:
    return ndimage.binary_erosion(mask, iterations=margin_px, border_value=0)


def _render(scene: Scene, camera: Camera, plan_: simulate.Plan | None = None) -> np.ndarray:
    if plan_ is None:
        plan_ = simulate.plan(scene, camera, tolerance=TOLERANCE)
    return simulate.render(scene, camera, plan_=plan_)


def render_rolling(scene: Scene, camera: Camera, *, band_rows: int = 8) -> np.ndarray:
    """A rolling-shutter capture rendered band by band on crops of the scene (Sec. 6-7).

    Rows ``[r0, r0 + band_rows)`` integrate the motion over their middle row's window
    (:meth:`pipeline.core.scene.Camera.row_windows`); each band is rendered by
    :func:`pipeline.core.simulate.render.render` as a global-shutter capture of that window on
    the band's rows plus the largest blur radius above and below, so its cost grows
    with the band's rows, not the frame's. Magnification (``p / p_ref``, under 2 px
    here) is not simulated. :func:`pipeline.core.simulate.render.render` with a rolling shutter
    gives the same image up to that and its tolerance (tests compare them).
    """
    if isinstance(band_rows, bool) or not isinstance(band_rows, int) or band_rows < 1:
        raise InputError(f"band_rows must be a positive integer, got {band_rows!r}")
    lens = camera.lens
    rows = scene.shape[0]
    windows = camera.row_windows(rows)
    v = np.concatenate([
        np.atleast_1d(optics.image_distance(lens.focal_length_mm, s.depth_mm[s.alpha > 0]))
        for s in scene.surfaces
    ])
    p_lo, p_hi = camera.motion.range_mm
    blur_px = max(np.max(lens.blur_px(v, p_lo)), np.max(lens.blur_px(v, p_hi)))
    margin = math.ceil(blur_px / 2) + 2
    out = None
    for r0 in range(0, rows, band_rows):
        r1 = min(rows, r0 + band_rows)
        c0, c1 = max(0, r0 - margin), min(rows, r1 + margin)
        crop = Scene(
            tuple(
                Surface(s.radiance[c0:c1], s.alpha[c0:c1], s.depth_mm[c0:c1])
                for s in scene.surfaces
            ),
            scene.channels_axis,
        )
        band = Camera(
            lens,
            camera.motion.window(*windows[(r0 + r1 - 1) // 2]),
            shutter="global",
            psf_model=camera.psf_model,
        )
        p = simulate.plan(crop, band, tolerance=TOLERANCE, magnification_steps=0)
        image = simulate.render(crop, band, plan_=p)
        if out is None:
            out = np.empty((rows, *image.shape[1:]), dtype=image.dtype)
        out[r0:r1] = image[r0 - c0 : r1 - c0]
    return out


def _v(lens: Lens, depth_mm: float) -> float:
    return float(optics.image_distance(lens.focal_length_mm, depth_mm))


def _tiles(shape: tuple[int, int], grid: tuple[int, int]) -> list[tuple[slice, slice]]:
    """Row-major tiles of a ``grid = (rows, cols)`` partition of ``shape``."""
    rb = np.linspace(0, shape[0], grid[0] + 1).round().astype(int)
    cb = np.linspace(0, shape[1], grid[1] + 1).round().astype(int)
    return [
        (slice(rb[i], rb[i + 1]), slice(cb[j], cb[j + 1]))
        for i in range(grid[0])
        for j in range(grid[1])
    ]


def _tile_mask(shape, tile, margin_px: int) -> np.ndarray:
    mask = np.zeros(shape, dtype=bool)
    mask[tile] = True
    return _interior(mask, margin_px)


# ----------------------------------------------------------------------------- Fig. 6: EDOF
EDOF_DEPTHS_MM = (450.0, 550.0, 750.0, 1100.0, 2000.0)  # Fig. 3's depths
EDOF_TEXTURES = (  # (skimage.data name, tint for greyscale, crop fractions)
    ("astronaut", None, (0.05, 0.45, 0.3, 0.7)),
    ("coffee", None, None),
    ("chelsea", None, None),
    ("rocket", None, None),
    ("brick", (1.0, 0.6, 0.4), None),
)
EDOF_SWEEP_MM = (375.0, math.inf)  # from p(0) = f (Sec. 4.1) past 450 mm: planes inside 15-85 %
EDOF_EXPOSURE_S = 0.36  # Sec. 4.1
NORMAL_FOCUS_MM = 750.0  # Fig. 6(c)
SMALL_F_NUMBER = 8.0  # Fig. 6(d)


def edof_scene(lens: Lens, depths_mm=EDOF_DEPTHS_MM) -> tuple[Scene, np.ndarray, list]:
    """Fronto-parallel textured planes side by side, near to far (Fig. 6).

    Returns the scene, its sharp radiance and each plane's ``(rows, cols)`` slices.
    """
    if len(depths_mm) != len(EDOF_TEXTURES):
        raise InputError(f"depths_mm needs {len(EDOF_TEXTURES)} depths, got {len(depths_mm)}")
    shape = (lens.height_px, lens.width_px)
    radiance = np.zeros((*shape, 3), dtype=np.float32)
    depth = np.zeros(shape)
    tiles = _tiles(shape, (1, len(EDOF_TEXTURES)))
    for tile, u, (name, tint, crop) in zip(tiles, depths_mm, EDOF_TEXTURES):
        size = (tile[0].stop - tile[0].start, tile[1].stop - tile[1].start)
        radiance[tile] = texture(name, size, tint=tint, crop=crop)
        depth[tile] = u
    return Scene.from_depth(radiance, depth), radiance, tiles


def edof_application(
    *,
    width_px: int = 320,
    depths_mm=EDOF_DEPTHS_MM,
    electrons_at_unit: float = 4000.0,
    read_noise_e: float = 5.0,
    margin_px: int = 12,
    seed: int = 0,
) -> Application:
    """Fig. 6: (a) EDOF sweep capture, (b) its deconvolution, (c) f/1.4 and (d) f/8 captures.

    All four expose :data:`EDOF_EXPOSURE_S` with photon noise (``electrons_at_unit`` at
    f/1.4; f/8 collects ``(1.4/8)^2`` of it and is shown scaled up, as in the paper).
    The sweep moves the focal plane over :data:`EDOF_SWEEP_MM` at constant speed
    (:func:`pipeline.core.motion.plan_extended_dof`, about Sec. 4.1's 1 mm/s); (b) is Wiener
    deconvolution with the depth-averaged IPSF (:func:`pipeline.jobs.sweep.sweep_kernel`).
    Per plane: :func:`detail_transfer` and PSNR against the sharp texture.
    """
    lens = scaled_lens(load_lens(GLOBAL_LENS), width_px)
    scene, sharp, tiles = edof_scene(lens, depths_mm)
    motion = plan_extended_dof(lens, *EDOF_SWEEP_MM, EDOF_EXPOSURE_S)
    light = Exposure(electrons_at_unit, read_noise_e)
    small = lens.with_f_number(SMALL_F_NUMBER)
    dim = Exposure(electrons_at_unit * (lens.f_number / SMALL_F_NUMBER) ** 2, read_noise_e)
    v_focus = _v(lens, NORMAL_FOCUS_MM)
    cameras = (
        Camera(lens, motion, exposure=light),
        Camera.static(lens, v_focus, EDOF_EXPOSURE_S, exposure=light),
        Camera.static(small, v_focus, EDOF_EXPOSURE_S, exposure=dim),
    )
    seeds = np.random.SeedSequence(seed).generate_state(len(cameras))
    noisy, clean = [], []
    for camera, s in zip(cameras, seeds):
        p = simulate.plan(scene, camera, tolerance=TOLERANCE)
        noisy.append(simulate.render(scene, camera, plan_=p, seed=int(s)))
        clean.append(simulate.render(scene, camera, plan_=dataclasses.replace(p, noise=None)))
    kernel, samples, _ = sweep_kernel(lens, motion)
    wiener = deconvolve.plan(noisy[0], kernel, method="wiener", kernel_samples=samples)
    noisy.insert(1, deconvolve.restore(noisy[0], wiener))  # Sec. 4.2
    clean.insert(1, deconvolve.restore(clean[0], wiener))  # the same linear filter
    labels = (
        "(a) EDOF capture (sweep, f/1.4)",
        "(b) EDOF image (deconvolved)",
        f"(c) normal f/1.4, focus {NORMAL_FOCUS_MM:g} mm",
        f"(d) normal f/{SMALL_F_NUMBER:g}, scaled up",
    )
    panels = dict(zip(labels, noisy))
    keys = ("capture", "edof", "f1.4", f"f{SMALL_F_NUMBER:g}")
    rows = []
    for tile, u, (name, _, _) in zip(tiles, depths_mm, EDOF_TEXTURES):
        mask = _tile_mask(sharp.shape[:2], tile, margin_px)
        row = {"depth_mm": u, "texture": name}
        for key, image in zip(keys, noisy):
            row[f"detail {key}"] = detail_transfer(image, sharp, mask)
        for key, image, free in zip(keys, noisy, clean):
            row[f"noise {key}"] = float(np.sqrt(np.mean((image - free)[mask] ** 2)))
        for key, image in zip(keys, noisy):
            row[f"PSNR {key}"] = quality.psnr(image[mask], sharp[mask])
        rows.append(row)
    summary = {
        "sweep_focus_mm": EDOF_SWEEP_MM,
        "sweep_speed_mm_s": motion.max_speed_mm_s,
        "kernel_px": kernel.shape[0],
    }
    for key in keys:
        detail = [r[f"detail {key}"] for r in rows]
        summary[f"detail spread {key}"] = float(np.ptp(detail))
        summary[f"detail min {key}"] = float(np.min(detail))
        summary[f"noise mean {key}"] = float(np.mean([r[f"noise {key}"] for r in rows]))
    summary["spread ratio edof / f1.4"] = summary["detail spread edof"] / summary[
        "detail spread f1.4"
    ]
    return Application("6", "Extended DOF", panels, rows, summary)


# ------------------------------------------------------------------------ Fig. 10: discontinuous
TOYS_MM = 500.0
MESH_MM = 800.0
BACKDROP_MM = 3000.0
DISCONTINUOUS_EXPOSURE_S = 0.36
MESH_RADIANCE = 0.03


def _ellipse(shape, centre, radii) -> np.ndarray:
    rr, cc = np.mgrid[: shape[0], : shape[1]]
    return ((rr - centre[0]) / radii[0]) ** 2 + ((cc - centre[1]) / radii[1]) ** 2 <= 1


def _over(planes) -> np.ndarray:
    """Sharp composite of ``(radiance, alpha, depth)`` planes, far to near ("over")."""
    out = None
    for radiance, alpha, _ in sorted(planes, key=lambda p: -p[2]):
        a = np.ones(radiance.shape[:2], np.float32) if alpha is None else alpha
        a = a[:, :, None]
        out = radiance * a if out is None else radiance * a + (1 - a) * out
    return out


def mesh_alpha(shape, period_px: float, width_px: float) -> np.ndarray:
    """Coverage of a square wire mesh: lines ``width_px`` wide every ``period_px``.

    Exact pixel-area coverage of each line; crossings combine as ``1 - (1 - r)(1 - c)``.
    """

    def lines(n):
        x = np.arange(n, dtype=np.float64)
        # exact pixel coverage of a periodic line [k p - w/2, k p + w/2] over [x - 1/2, x + 1/2]
        cover = np.zeros(n)
        for k in range(-1, int(n / period_px) + 2):
            lo, hi = k * period_px - width_px / 2, k * period_px + width_px / 2
            cover += np.clip(np.minimum(x + 0.5, hi) - np.maximum(x - 0.5, lo), 0, None)
        return np.minimum(cover, 1.0)

    r, c = lines(shape[0]), lines(shape[1])
    return (1 - (1 - r[:, None]) * (1 - c[None, :])).astype(np.float32)


def discontinuous_scene(
    lens: Lens,
    *,
    mesh: bool = True,
    flat_backdrop: bool = False,
    period_px: float = 5.0,
    width_px: float = 1.2,
):
    """Two 'toys' at :data:`TOYS_MM` before a backdrop at :data:`BACKDROP_MM`, with a wire
    mesh between at :data:`MESH_MM` (Fig. 10). Returns scene, sharp image, near and far
    masks (where the toys and the backdrop are seen). ``flat_backdrop``: a uniform grey
    backdrop (to see the mesh alone)."""
    shape = (lens.height_px, lens.width_px)
    rows, cols = shape
    if flat_backdrop:
        backdrop = np.full((*shape, 3), 0.5 * PEAK_RADIANCE, np.float32)
    else:
        backdrop = texture("rocket", shape)
    toys = np.zeros((*shape, 3), np.float32)
    toys_alpha = np.zeros(shape, np.float32)
    for name, centre_col in (("chelsea", 0.25), ("coffee", 0.75)):
        disc = _ellipse(shape, (0.62 * rows, centre_col * cols), (0.3 * rows, 0.19 * cols))
        toys[disc] = texture(name, shape, crop=(0.1, 0.9, 0.15, 0.85))[disc]
        toys_alpha[disc] = 1.0
    planes = [(backdrop, None, BACKDROP_MM), (toys, toys_alpha, TOYS_MM)]
    if mesh:
        alpha = mesh_alpha(shape, period_px, width_px)
        planes.insert(1, (np.full((*shape, 3), MESH_RADIANCE, np.float32), alpha, MESH_MM))
    near = toys_alpha > 0
    return Scene.from_planes(planes), _over(planes), near, ~near


def discontinuous_application(
    *, width_px: int = 320, period_px: float = 5.0, width_line_px: float = 1.2,
    margin_px: int = 10
) -> Application:
    """Fig. 10: toys and backdrop focused, the mesh between "optically erased" (Sec. 5).

    Cameras (noise-free): (a) a normal f/8 camera focused between the toys and the
    backdrop (large DOF), (b) the flexible-DOF camera at f/1.4 pausing at the toys'
    and the backdrop's focus for half the exposure each
    (:func:`pipeline.core.motion.plan_discontinuous_dof`, transits at the actuator's top
    speed), (c) a normal f/1.4 camera focused on the toys. Measured: the mesh's
    contrast ``std / mean`` over the backdrop in a capture of the same scene with a
    uniform grey backdrop, and :func:`detail_transfer` of toys and backdrop (renders without the
    mesh, which only occludes).
    """
    lens = scaled_lens(load_lens(GLOBAL_LENS), width_px)
    kwargs = {"period_px": period_px, "width_px": width_line_px}
    scene, _, near, far = discontinuous_scene(lens, **kwargs)
    bare, sharp, _, _ = discontinuous_scene(lens, mesh=False, **kwargs)
    grey, _, _, _ = discontinuous_scene(lens, flat_backdrop=True, **kwargs)
    f = lens.focal_length_mm
    v_mid = 0.5 * (_v(lens, TOYS_MM) + _v(lens, BACKDROP_MM))
    t = DISCONTINUOUS_EXPOSURE_S
    flexible = plan_discontinuous_dof(
        lens, [(TOYS_MM, TOYS_MM), (BACKDROP_MM, BACKDROP_MM)], [0.5, 0.5], t
    )
    cameras = {
        f"(a) normal f/{SMALL_F_NUMBER:g}, focus "
        f"{optics.focus_distance(f, v_mid):.0f} mm": Camera.static(
            lens.with_f_number(SMALL_F_NUMBER), v_mid, t
        ),
        "(b) flexible DOF f/1.4 (toys + backdrop)": Camera(lens, flexible),
        f"(c) normal f/1.4, focus {TOYS_MM:g} mm": Camera.static(lens, _v(lens, TOYS_MM), t),
    }
    near_m, far_m = _interior(near, margin_px), _interior(far, margin_px)
    panels, rows = {}, []
    for (label, camera), key in zip(cameras.items(), ("f8", "flexible", "f1.4 near")):
        p = simulate.plan(scene, camera, tolerance=TOLERANCE)  # the same depths in all three
        image = _render(scene, camera, p)
        without = _render(bare, camera, p)
        panels[label] = image
        q = _grey(_render(grey, camera, p))[far_m]
        rows.append(
            {
                "camera": key,
                "detail toys": detail_transfer(without, sharp, near_m),
                "detail backdrop": detail_transfer(without, sharp, far_m),
                "mesh contrast": float(np.std(q) / np.mean(q)),
            }
        )
    by = {r["camera"]: r for r in rows}
    summary = {
        "motion_knots_s": flexible.times_s.tolist(),
        "motion_knots_mm": flexible.image_distances_mm.tolist(),
        "mesh contrast ratio flexible / f8": by["flexible"]["mesh contrast"]
        / by["f8"]["mesh contrast"],
        "detail toys flexible": by["flexible"]["detail toys"],
        "detail backdrop flexible": by["flexible"]["detail backdrop"],
        "detail backdrop f1.4 near": by["f1.4 near"]["detail backdrop"],
    }
    return Application("10", "Discontinuous DOF", panels, rows, summary)


# ----------------------------------------------------------------------------- Fig. 11: tilted
TABLE_TILT_DEG = 53.0  # Sec. 6
TABLE_THROUGH_MM = 450.0  # the table's depth on the optical axis
TILTED_ROW_EXPOSURE_S = 0.03  # Fig. 11
MUG_MM = 430.0
MUG_SIZE_MM = (80.0, 45.0)  # height, width


def _sensor_mm(lens: Lens) -> tuple[np.ndarray, np.ndarray]:
    """Row and column centres (mm from the optical axis; rows down, columns right)."""
    y = row_offsets_mm(lens.height_px, lens.sensor_height_mm)
    x = (np.arange(lens.width_px) - 0.5 * (lens.width_px - 1)) * lens.pixel_pitch_mm
    return y, x


def table_depths(lens: Lens, tilt_deg: float, through_mm: float) -> np.ndarray:
    """Depth (mm) along every row's chief ray to a plane ``u = U + Y tan(phi)`` (Sec. 6).

    Independent of :func:`pipeline.core.motion.tilted_row_image_distances`: the ray through
    a row ``y`` mm below the axis (detector at ``v(u)``) reaches height
    ``Y = -y (u - f) / f``; solving ``u = U + Y tan(phi)`` gives
    ``u = (U + y tan(phi)) / (1 + y tan(phi) / f)``.
    """
    f = lens.focal_length_mm
    y, _ = _sensor_mm(lens)
    k = math.tan(math.radians(tilt_deg))
    return (through_mm + y * k) / (1 + y * k / f)


def tilted_scene(lens: Lens, *, tilt_deg=TABLE_TILT_DEG, through_mm=TABLE_THROUGH_MM):
    """A newspaper on a table tilted by ``tilt_deg`` and a 'mug' standing on it (Fig. 11).

    The newspaper ('page' tiled, 0.25 mm per texel) is mapped in perspective; the mug
    is a fronto-parallel photograph ('coffee') at :data:`MUG_MM` whose bottom edge is
    the row where the table is at that depth. Returns the scene, its sharp radiance,
    the table and mug masks and the mug's top and bottom rows.
    """
    f = lens.focal_length_mm
    y, x = _sensor_mm(lens)
    u = table_depths(lens, tilt_deg, through_mm)
    if np.any(u <= f) or np.any(~np.isfinite(u)):
        raise InputError(f"the table tilted {tilt_deg} deg reaches the horizon inside the image")
    scale = (u - f) / f  # mm in the scene per mm on the sensor at depth u
    along = (y * scale / math.cos(math.radians(tilt_deg)))[:, None] * np.ones_like(x)[None, :]
    across = x[None, :] * scale[:, None]
    page = np.asarray(skdata.page(), dtype=np.float64) / 255.0
    texel = 0.25
    news = ndimage.map_coordinates(
        page, [along / texel + page.shape[0] / 2, across / texel + page.shape[1] / 2],
        order=1, mode="grid-wrap",
    )
    radiance = srgb_to_linear(np.repeat(news[:, :, None], 3, axis=2).astype(np.float32))
    radiance *= np.asarray([0.95, 0.9, 0.8], np.float32) * np.float32(PEAK_RADIANCE)
    depth = np.repeat(u[:, None], lens.width_px, axis=1)
    base = int(np.argmin(np.abs(u - MUG_MM)))
    m = f / (MUG_MM - f) / lens.pixel_pitch_mm  # px per scene mm at the mug
    top = max(0, base - round(MUG_SIZE_MM[0] * m))
    half = round(0.5 * MUG_SIZE_MM[1] * m)
    c0, c1 = lens.width_px // 2 - half, lens.width_px // 2 + half
    radiance[top:base, c0:c1] = texture("gravel", (base - top, c1 - c0), tint=(0.9, 0.5, 0.3))
    depth[top:base, c0:c1] = MUG_MM
    mug = np.zeros(depth.shape, bool)
    mug[top:base, c0:c1] = True
    return Scene.from_depth(radiance, depth), radiance, ~mug, mug, (top, base)


def tilted_application(
    *, width_px: int = 432, bands: int = 8, margin_px: int = 8, tilt_deg=TABLE_TILT_DEG
) -> Application:
    """Fig. 11: a rolling-shutter sweep tilts the DOF onto a table at ``tilt_deg`` (Sec. 6).

    Cameras (noise-free, f/1.4, rows exposed :data:`TILTED_ROW_EXPOSURE_S`): (a) a normal
    camera focused at the table's depth on the axis, (b) the flexible-DOF camera moving
    at the constant speed of Eq. 9 (:func:`pipeline.core.motion.plan_tilted_dof`). Measured:
    :func:`detail_transfer` of the table in ``bands`` horizontal bands of rows, and of
    the mug's top and bottom fifths.
    """
    lens = scaled_lens(load_lens(ROLLING_LENS), width_px)
    scene, sharp, table, mug, (top, base) = tilted_scene(lens, tilt_deg=tilt_deg)
    motion = plan_tilted_dof(lens, tilt_deg, TABLE_THROUGH_MM, exposure_s=TILTED_ROW_EXPOSURE_S)
    v_axis = _v(lens, TABLE_THROUGH_MM)
    cameras = {
        f"(a) normal f/1.4, focus {TABLE_THROUGH_MM:g} mm": Camera.static(
            lens, v_axis, TILTED_ROW_EXPOSURE_S, shutter="global"
        ),
        f"(b) flexible DOF: tilted {tilt_deg:g} deg": Camera(
            lens, motion, row_exposure_s=TILTED_ROW_EXPOSURE_S
        ),
    }
    images = {label: render_rolling(scene, camera) for label, camera in cameras.items()}
    keys = ("normal", "tilted")
    depth_rows = table_depths(lens, tilt_deg, TABLE_THROUGH_MM)
    rows = []
    table_m = _interior(table, margin_px)
    for tile in _tiles(sharp.shape[:2], (bands, 1)):
        mask = np.zeros_like(table_m)
        mask[tile] = table_m[tile]
        row = {
            "rows": f"{tile[0].start}-{tile[0].stop - 1}",
            "table depth mm": float(np.mean(depth_rows[tile[0]])),
        }
        for key, image in zip(keys, images.values()):
            row[f"detail {key}"] = detail_transfer(image, sharp, mask)
        rows.append(row)
    fifth = max(1, (base - top) // 5)
    mug_m = _interior(mug, margin_px // 2)
    summary = {"speed_mm_s": motion.max_speed_mm_s, "mug rows": (top, base)}
    for key in keys:
        detail = [r[f"detail {key}"] for r in rows]
        summary[f"table detail spread {key}"] = float(np.ptp(detail))
        summary[f"table detail min {key}"] = float(np.min(detail))
    for part, span in (("top", slice(top, top + fifth)), ("bottom", slice(base - fifth, base))):
        mask = np.zeros_like(mug_m)
        mask[span] = mug_m[span]
        for key, image in zip(keys, images.values()):
            summary[f"mug {part} detail {key}"] = detail_transfer(image, sharp, mask)
    return Application("11", "Tilted DOF", images, rows, summary)


# ----------------------------------------------------------------------------- Fig. 12: non-planar
CRAYONS = 7
CRAYON_OUTER_MM = 380.0  # the two end crayons and the price tag
CRAYON_MIDDLE_MM = 420.0  # the middle crayon (the arc bulges away from the camera)
CRAYON_HALF_SPAN_MM = 50.0  # half the arc's chord, across the rows
CRAYON_ARC_DEG = 50.0  # the crayons sit at angles -50 .. 50 deg on the (elliptical) arc
WALL_MM = 900.0
NONPLANAR_ROW_EXPOSURE_S = 0.01  # Fig. 12
CRAYON_COLOURS = (
    (0.9, 0.15, 0.1), (0.95, 0.55, 0.1), (0.9, 0.85, 0.15), (0.2, 0.7, 0.2),
    (0.15, 0.45, 0.9), (0.45, 0.2, 0.75), (0.85, 0.3, 0.6),
)


def crayon_arc(n: int = CRAYONS) -> tuple[np.ndarray, np.ndarray]:
    """Height ``Y`` (mm, up) and depth (mm) of ``n`` crayons on an elliptical arc.

    Angles ``theta`` from ``-CRAYON_ARC_DEG`` to ``+CRAYON_ARC_DEG``;
    ``Y = CRAYON_HALF_SPAN_MM sin(theta) / sin(arc)`` and the depth goes from
    :data:`CRAYON_OUTER_MM` at the ends to :data:`CRAYON_MIDDLE_MM` in the middle as
    ``cos(theta)``. (The camera is turned by 90 deg: the rolling shutter's rows run
    along the arc, so the depth to focus changes from row to row, Sec. 7.)
    """
    arc = math.radians(CRAYON_ARC_DEG)
    theta = np.linspace(-arc, arc, n)
    height = CRAYON_HALF_SPAN_MM * np.sin(theta) / math.sin(arc)
    rise = (np.cos(theta) - math.cos(arc)) / (1 - math.cos(arc))
    return height, CRAYON_OUTER_MM + (CRAYON_MIDDLE_MM - CRAYON_OUTER_MM) * rise


def nonplanar_scene(lens: Lens):
    """Crayons on an arc, a price tag at the end crayons' depth in the middle, a wall behind.

    Each crayon is a horizontal bar (the camera is turned, see :func:`crayon_arc`),
    8 mm thick, printed with 'text' in its colour; the tag ('page') stands in front of
    the middle crayons. Returns the scene, its sharp radiance, per-crayon masks, the
    tag mask and the focus knots ``(row, depth_mm)`` (each crayon's first and last row).
    """
    shape = (lens.height_px, lens.width_px)
    f = lens.focal_length_mm
    radiance = texture("gravel", shape, tint=(0.55, 0.5, 0.45))
    depth = np.full(shape, WALL_MM)
    heights, depths = crayon_arc()
    masks, knots = [], []
    c0, c1 = round(0.1 * shape[1]), round(0.9 * shape[1])
    for k, (height, u, colour) in enumerate(zip(heights, depths, CRAYON_COLOURS)):
        px = f / (u - f) / lens.pixel_pitch_mm  # px per scene mm at depth u
        centre = 0.5 * (shape[0] - 1) - height * px
        half = 4.0 * px
        r0, r1 = round(centre - half), round(centre + half) + 1
        if r0 < 0 or r1 > shape[0]:
            raise InputError(f"crayon {k} falls outside the {shape[0]} rows; narrow the arc")
        radiance[r0:r1, c0:c1] = texture("text", (r1 - r0, c1 - c0), tint=colour)
        depth[r0:r1, c0:c1] = u
        mask = np.zeros(shape, bool)
        mask[r0:r1, c0:c1] = True
        masks.append(mask)
        knots.append(((r0 + r1 - 1) // 2, u))
    px = f / (CRAYON_OUTER_MM - f) / lens.pixel_pitch_mm
    mid = shape[0] // 2
    t0, t1 = mid - round(14 * px), mid + round(14 * px)
    s0, s1 = round(0.55 * shape[1]), round(0.55 * shape[1] + 40 * px)
    radiance[t0:t1, s0:s1] = texture("page", (t1 - t0, s1 - s0), crop=(0.0, 0.6, 0.0, 0.5))
    depth[t0:t1, s0:s1] = CRAYON_OUTER_MM
    tag = np.zeros(shape, bool)
    tag[t0:t1, s0:s1] = True
    masks = [m & ~tag for m in masks]
    return Scene.from_depth(radiance, depth), radiance, masks, tag, np.array(knots, float)


def nonplanar_application(*, width_px: int = 648, margin_px: int = 4) -> Application:
    """Fig. 12: a curved DOF along crayons on an arc; the price tag between is defocused.

    Cameras (noise-free, f/1.4, rows exposed :data:`NONPLANAR_ROW_EXPOSURE_S`): (a) a
    normal camera focused at the end crayons' (and the tag's) depth, (b) the
    flexible-DOF camera whose detector follows each crayon's depth row by row
    (:func:`pipeline.core.motion.plan_nonplanar_dof`, knots at the crayons' middle rows).
    Measured: :func:`detail_transfer` of every crayon (outside the tag) and of the tag.
    """
    lens = scaled_lens(load_lens(ROLLING_LENS), width_px)
    scene, sharp, crayons, tag, knots = nonplanar_scene(lens)
    motion = plan_nonplanar_dof(lens, knots, exposure_s=NONPLANAR_ROW_EXPOSURE_S)
    cameras = {
        f"(a) normal f/1.4, focus {CRAYON_OUTER_MM:g} mm": Camera.static(
            lens, _v(lens, CRAYON_OUTER_MM), NONPLANAR_ROW_EXPOSURE_S, shutter="global"
        ),
        "(b) flexible DOF: curved along the crayons": Camera(
            lens, motion, row_exposure_s=NONPLANAR_ROW_EXPOSURE_S
        ),
    }
    images = {label: render_rolling(scene, camera) for label, camera in cameras.items()}
    keys = ("normal", "curved")
    _, depths = crayon_arc()
    rows = []
    for k, (mask, u) in enumerate(zip(crayons, depths)):
        row = {"object": f"crayon {k + 1}", "depth_mm": float(u)}
        inner = _interior(mask, margin_px)
        for key, image in zip(keys, images.values()):
            row[f"detail {key}"] = detail_transfer(image, sharp, inner)
        rows.append(row)
    row = {"object": "price tag", "depth_mm": CRAYON_OUTER_MM}
    for key, image in zip(keys, images.values()):
        row[f"detail {key}"] = detail_transfer(image, sharp, _interior(tag, margin_px))
    rows.append(row)
    summary = {"max_speed_mm_s": motion.max_speed_mm_s}
    for key in keys:
        crayon_detail = [r[f"detail {key}"] for r in rows[:-1]]
        summary[f"crayon detail min {key}"] = float(np.min(crayon_detail))
        summary[f"tag detail {key}"] = rows[-1][f"detail {key}"]
    return Application("12", "Non-planar DOF", images, rows, summary)
