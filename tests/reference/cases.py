"""The cases of issue 14: each a simulator scene + camera and an independent reference.

A :class:`Case` builds the ``pipeline`` scene and camera (public classes only) and knows
how to render the same capture with :mod:`.smooth` or :mod:`.raytrace`. ``contrast`` is
the scene's RMS contrast (std of the visible radiance), the plan's error unit.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from pipeline.core.lens import Lens
from pipeline.core.motion import Profile, plan_extended_dof
from pipeline.core.scene import Camera, Scene

from . import raytrace, smooth
from .optics import image_distance

ROWS, COLS = 48, 64
LENS = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=20.0, width_px=COLS,
            height_px=ROWS)
ROLLING = dataclasses.replace(LENS, shutter="rolling", line_time_us=1000.0)
WIDE = Lens(focal_length_mm=4.0, f_number=2.8, pixel_pitch_um=5.0, width_px=COLS,
            height_px=ROWS, name="wide 4 mm f/2.8")
NEAR_MM, FAR_MM, EDGE_COL = 500.0, 1500.0, COLS // 2
JUMP_NEAR_MM, JUMP_FAR_MM = 300.0, 5000.0  # a larger depth jump


def texture(shape, seed: int) -> np.ndarray:
    """A 1/f (natural-image) random texture, mean 0.4, std 0.1, non-negative."""
    rng = np.random.default_rng(seed)
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.fftfreq(shape[1])[None, :]
    amp = 1.0 / np.maximum(np.hypot(fx, fy), 1.0 / max(shape))
    t = np.real(np.fft.ifft2(np.fft.fft2(rng.standard_normal(shape)) * amp))
    t = 0.4 + 0.1 * (t - t.mean()) / t.std()
    return np.clip(t, 0.0, None)


def rel_rms(a, b, contrast: float, region=None) -> float:
    d = np.asarray(a, float) - np.asarray(b, float)
    if region is not None:
        d = d[region]
    return float(np.sqrt(np.mean(d**2)) / contrast)


@dataclasses.dataclass
class Case:
    name: str
    description: str
    scene: Scene
    camera: Camera
    contrast: float
    reference: Callable[..., np.ndarray]  # reference(**accuracy) -> image
    accuracy: dict  # default accuracy options; doubled for the convergence check
    smooth: bool  # occlusion-free: forcing occlusion off is the right model
    edge_region: np.ndarray | None = None  # columns near a depth edge


def _motion_args(camera: Camera) -> dict:
    lens = camera.lens
    return dict(
        f_mm=lens.focal_length_mm,
        f_number=lens.f_number,
        pitch_mm=lens.pixel_pitch_mm,
        times_s=camera.motion.times_s,
        positions_mm=camera.motion.image_distances_mm,
        p_ref_mm=camera.reference_mm,
        row_windows=None
        if camera.effective_shutter == "global"
        else camera.row_windows(ROWS),
    )


def smooth_case(name, description, radiance, depth, camera, *, n_time=256, n_layers=None):
    scene = Scene.from_depth(radiance, depth)
    args = _motion_args(camera)
    static = np.ptp(camera.motion.image_distances_mm) == 0

    def reference(n_time=n_time, n_layers=n_layers, blur_times_m=False):
        return smooth.render_smooth(
            radiance, depth, **args, n_time=1 if static else n_time, n_layers=n_layers,
            blur_times_m=blur_times_m,
        )

    return Case(name, description, scene, camera, float(np.std(radiance)), reference,
                {"n_time": n_time, "n_layers": n_layers}, smooth=True)


def edge_case(name, description, camera, *, n_time=256, seed=20, near_mm=NEAR_MM,
              far_mm=FAR_MM):
    near, far = texture((ROWS, COLS), seed), texture((ROWS, COLS), seed + 1)
    alpha = np.zeros((ROWS, COLS))
    alpha[:, :EDGE_COL] = 1.0
    scene = Scene.from_planes([(far, None, far_mm), (near, alpha, near_mm)])
    args = _motion_args(camera)
    static = np.ptp(camera.motion.image_distances_mm) == 0

    def reference(n_time=n_time):
        return raytrace.render_edge(near, far, EDGE_COL, near_mm, far_mm, **args,
                                    n_time=1 if static else n_time)

    visible = np.where(alpha > 0, near, far)
    region = np.zeros((ROWS, COLS), bool)
    region[:, EDGE_COL - 8 : EDGE_COL + 8] = True
    return Case(name, description, scene, camera, float(np.std(visible)), reference,
                {"n_time": n_time}, smooth=False, edge_region=region)


def v(u: float, lens: Lens = LENS) -> float:
    return image_distance(lens.focal_length_mm, u)


def build_cases() -> dict[str, Case]:
    rows = np.arange(ROWS, dtype=float)[:, None] * np.ones((1, COLS))
    cols = np.ones((ROWS, 1)) * np.arange(COLS, dtype=float)[None, :]
    tex = texture((ROWS, COLS), 1)
    cases = []
    cases.append(smooth_case(
        "flat in focus", "one plane at 700 mm, focused on it (sanity: exact)",
        tex, np.full((ROWS, COLS), 700.0), Camera.static(LENS, v(700.0), 0.1)))
    cases.append(smooth_case(
        "flat", "one plane at 700 mm, detector at 12.8 mm (4.7 px blur)",
        tex, np.full((ROWS, COLS), 700.0), Camera.static(LENS, 12.8, 0.1)))
    cases.append(smooth_case(
        "ramp static narrow", "slanted plane 800-1200 mm down the rows, focus 600 mm",
        tex, 800.0 + 400.0 * rows / (ROWS - 1), Camera.static(LENS, v(600.0), 0.1)))
    cases.append(smooth_case(
        "stack frame", "one plane at 700 mm, static at 12.9 mm with p_ref 12.6 mm (a focal-"
        "stack frame off the reference: magnification 1.024)",
        tex, np.full((ROWS, COLS), 700.0),
        Camera.static(LENS, 12.9, 0.1, reference_image_distance_mm=12.6)))
    sweep = Profile([0.0, 0.1], [v(2000.0), v(500.0)])
    cases.append(smooth_case(
        "ramp sweep", "slanted plane 500-2000 mm down the rows, swept 2000->500 mm",
        tex, 500.0 + 1500.0 * rows / (ROWS - 1), Camera(LENS, sweep)))
    for label, focus in (("near", NEAR_MM), ("far", FAR_MM), ("between", 750.0)):
        cases.append(edge_case(
            f"edge focus {label}",
            f"planes 500 | 1500 mm, vertical edge at col {EDGE_COL}, focus {focus:g} mm",
            Camera.static(LENS, v(focus), 0.1)))
    cases.append(edge_case(
        "edge jump between", f"planes {JUMP_NEAR_MM:g} | {JUMP_FAR_MM:g} mm, vertical edge at "
        f"col {EDGE_COL}, focus 560 mm (9 px blur on both sides, opposite signs)",
        Camera.static(LENS, v(560.0), 0.1), near_mm=JUMP_NEAR_MM, far_mm=JUMP_FAR_MM))
    cases.append(edge_case(
        "edge sweep", "planes 500 | 1500 mm, swept 1500->500 mm",
        Camera(LENS, Profile([0.0, 0.1], [v(FAR_MM), v(NEAR_MM)]))))
    cases.append(edge_case(
        "edge jump sweep", f"planes {JUMP_NEAR_MM:g} | {JUMP_FAR_MM:g} mm, swept "
        f"{JUMP_FAR_MM:g}->{JUMP_NEAR_MM:g} mm (up to 18 px blur)",
        Camera(LENS, Profile([0.0, 0.1], [v(JUMP_FAR_MM), v(JUMP_NEAR_MM)])),
        near_mm=JUMP_NEAR_MM, far_mm=JUMP_FAR_MM))
    line = ROLLING.line_time_us * 1e-6
    readout = (ROWS - 1) * line
    rolling = Camera(ROLLING, Profile([0.0, readout + 0.01], [v(1500.0), v(500.0)]),
                     row_exposure_s=0.01)
    cases.append(smooth_case(
        "rolling", "slanted plane 600-1200 mm across the columns, rolling shutter "
        "(1 ms/row, 10 ms rows) during a 1500->500 mm sweep",
        tex, 600.0 + 600.0 * cols / (COLS - 1), rolling))
    wide_sweep = plan_extended_dof(WIDE, 100.0, math.inf, 0.1)
    inv = 1 / 3000.0 + (1 / 110.0 - 1 / 3000.0) * rows / (ROWS - 1)
    cases.append(smooth_case(
        "wide-angle", "4 mm f/2.8, 5 um px, sweep 100 mm-inf; surface 3000->110 mm "
        "(linear in 1/depth) down the rows",
        tex, 1.0 / inv, Camera(WIDE, wide_sweep)))
    return {c.name: c for c in cases}
