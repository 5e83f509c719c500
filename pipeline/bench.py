"""What accuracy costs in time: sweep each accuracy knob, measure error and wall time.

Every knob of the pipeline that trades accuracy for time is swept on scenes with a
ground truth, and each setting's error and time are measured in the same run:

* IPSF (Eqs. 5-7): angular quadrature order of the analytic pixel-area integration,
  time nodes and sub-interval of the numeric Eq. 5, analytic vs numeric, kernel size
  truncation. Error: L1 distance to a converged reference kernel (analytic at order
  :data:`REFERENCE_THETA_ORDER`), mean over depths, on the Sec. 4.1 sweep
  (12.5 mm f/1.4, p(0) = 12.5 mm, 1 mm/s, 0.36 s, 4.65 um pixels).
* Simulation: layer tolerance, occlusion, magnification. Error: RMS difference per
  unit RMS contrast (the tolerance's own meaning, :mod:`pipeline.simulate`) against a
  render at :attr:`Config.truth_tolerance`.
* Alignment (Sec. 9): none / analytic / estimated at several matching resolutions.
  Error: corner reprojection error against the true magnification ``p_i / p_ref``, and
  PSNR of the final EDOF image.
* Deconvolution (Sec. 4.2): method, iterations, regularisation, kernel variance,
  tile size and overlap, float32 vs float64, kernel truncation. Error: PSNR of the
  final EDOF image against the all-in-focus ground truth.
* Stack sampling: frames over the same depth range. Error: PSNR, and the spread
  (Eq. 8) of the per-depth kernels around the depth-independent one used.

Scenes: the shipped ``stacks/motorcycle`` sample (noisy) and a generated scene with
depth edges (near rectangle, disk, far plane, a slanted floor) rendered as focal
stacks with :func:`pipeline.simulate.render_focal_stack` at a tight tolerance, noise
free and noisy. Times are the best of :attr:`Config.repeats` runs (cheap calls are
looped until a sample takes ~50 ms).

A default is *dominated* if another setting of the same knob (same scene and metric)
is faster by more than ``time_margin`` and more accurate by a clear margin
(:data:`METRICS`); :func:`dominated_defaults` lists them. Settings that need extra
information (``requires``, e.g. absolute focus positions) are reported apart.
"""

from __future__ import annotations

import csv
import dataclasses
import inspect
import logging
import math
import tempfile
import time
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path

import dask
import numpy as np
import tifffile

from pipeline import align, engine, io, optics, profiles, psf, simulate
from pipeline import deconvolve as dc
from pipeline.engine import StackOptions
from pipeline.errors import InputError
from pipeline.motion import constant_speed
from pipeline.quality import psnr
from pipeline.scene import Camera, Exposure, Scene
from pipeline.stack import check_frames, image_distances_mm, load_stack
from pipeline.tiling import deconvolve_tiled
from pipeline.weights import constant_speed_weights

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]
MOTORCYCLE = REPO / "stacks" / "motorcycle"
REFERENCE_THETA_ORDER = 64
SEC41_LENS = "fujinon-12.5mm-f1.4-sony-1-3in"
NEAR_MM, FAR_MM = 450.0, 2000.0
NOISE = Exposure(electrons_at_unit=4000.0, read_noise_e=3.0)  # as stacks/motorcycle
COLUMNS = (
    "group",
    "knob",
    "scene",
    "setting",
    "is_default",
    "metric",
    "value",
    "time_s",
    "requires",
    "note",
)


# ----------------------------------------------------------------------------- records
def default_of(function, parameter: str):
    """The default of a keyword parameter, read from the code (so the bench marks the real one)."""
    return inspect.signature(function).parameters[parameter].default


@dataclasses.dataclass(frozen=True)
class Metric:
    """How an error metric is read: direction, unit and what counts as a clear difference.

    ``b`` is clearly more accurate than ``a`` when it is better by more than
    ``max(margin_rel * |a|, margin_abs)``.
    """

    label: str
    higher_is_better: bool
    margin_abs: float
    margin_rel: float = 0.0


METRICS = {
    "psnr_db": Metric("PSNR vs ground truth, dB (higher is better)", True, 0.2),
    "kernel_l1": Metric("kernel L1 vs reference (lower is better)", False, 1e-4, 0.25),
    "rel_rms": Metric("render RMS error / RMS contrast (lower is better)", False, 2e-4, 0.25),
    "corner_px": Metric("corner reprojection error, px (lower is better)", False, 0.05, 0.25),
    "eq8_spread": Metric("Eq. 8 spread of per-depth kernels (lower is better)", False, 1e-3, 0.25),
}


@dataclasses.dataclass(frozen=True)
class Row:
    """One measured setting of one knob: its error (``metric`` = ``value``) and time."""

    group: str
    knob: str
    scene: str
    setting: str
    is_default: bool
    metric: str
    value: float
    time_s: float
    requires: str = ""
    note: str = ""


@dataclasses.dataclass(frozen=True)
class Config:
    """What to sweep (``Config.quick()`` for CI, ``Config.full()`` for the report)."""

    repeats: int
    shape: tuple[int, int]
    frames: int
    truth_tolerance: float
    ipsf_depths_mm: tuple[float, ...]
    theta_orders: tuple[int, ...]
    time_orders: tuple[int, ...]
    time_steps_px: tuple[float, ...]
    size_fractions: tuple[float, ...]
    tolerances: tuple[float, ...]
    align_sides_px: tuple[int, ...]
    rl_iterations: tuple[int, ...]
    sparse_iterations: tuple[int, ...]
    regularization_factors: tuple[float, ...]
    tiles_px: tuple[int, ...]
    overlap_fractions: tuple[float, ...]
    frame_counts: tuple[int, ...]
    deconvolution_scenes: tuple[str, ...]

    @classmethod
    def quick(cls) -> Config:
        return cls(
            repeats=2,
            shape=(120, 180),
            frames=8,
            truth_tolerance=2e-4,
            ipsf_depths_mm=(450.0, 750.0, 2000.0),
            theta_orders=(2, 4, 8, 16),
            time_orders=(2, 6),
            time_steps_px=(2.0, 0.5),
            size_fractions=(0.5, 0.75, 1.0),
            tolerances=(1e-2, 3e-3, 1e-3),
            align_sides_px=(192, 768),
            rl_iterations=(10, 30),
            sparse_iterations=(20, 50),
            regularization_factors=(0.3, 1.0, 3.0),
            tiles_px=(64, 1024),
            overlap_fractions=(0.5, 1.0),
            frame_counts=(4, 8),
            deconvolution_scenes=("motorcycle", "edges-noisy"),
        )

    @classmethod
    def full(cls) -> Config:
        return cls(
            repeats=3,
            shape=(192, 288),
            frames=8,
            truth_tolerance=1e-4,
            ipsf_depths_mm=(450.0, 600.0, 750.0, 1000.0, 1500.0, 2000.0),
            theta_orders=(2, 3, 4, 6, 8, 12, 16, 32),
            time_orders=(1, 2, 3, 4, 6, 8),
            time_steps_px=(4.0, 2.0, 1.0, 0.5, 0.25),
            size_fractions=(0.25, 0.5, 0.75, 0.9, 1.0),
            tolerances=(3e-2, 1e-2, 3e-3, 1e-3, 3e-4),
            align_sides_px=(192, 256, 384, 768),
            rl_iterations=(10, 30, 100),
            sparse_iterations=(20, 50, 100),
            regularization_factors=(0.1, 0.3, 1.0, 3.0, 10.0),
            tiles_px=(64, 128, 256, 1024),
            overlap_fractions=(0.25, 0.5, 1.0),
            frame_counts=(3, 4, 6, 8, 12, 16),
            deconvolution_scenes=("motorcycle", "edges-clean", "edges-noisy"),
        )


def best_times(fns: Sequence[Callable[[], object]], repeats: int) -> list[tuple[float, object]]:
    """Best wall time (s) of ``repeats`` runs of each callable, and its last result.

    The callables are run round-robin (all once, then all again, ...), so a change in
    machine load during a sweep hits every setting alike. A call under 50 ms is
    looped within each sample so clock resolution and scheduling jitter stay small
    against it.
    """
    best, results, inner = [], [], []
    for fn in fns:
        start = time.perf_counter()
        results.append(fn())
        first = time.perf_counter() - start
        inner.append(min(20, max(1, math.ceil(0.05 / max(first, 1e-6)))))
        best.append(first)
    for _ in range(max(repeats - 1, 1)):
        for i, fn in enumerate(fns):
            start = time.perf_counter()
            for _ in range(inner[i]):
                results[i] = fn()
            best[i] = min(best[i], (time.perf_counter() - start) / inner[i])
    return list(zip(best, results))


@dataclasses.dataclass(frozen=True)
class _Pending:
    """A setting to time (``run``) and how to turn its time and result into row(s)."""

    run: Callable[[], object]
    finish: Callable[[float, object], Row | list[Row]]


def _measure(pending: Sequence[_Pending], repeats: int) -> list[Row]:
    rows: list[Row] = []
    for p, (seconds, result) in zip(pending, best_times([p.run for p in pending], repeats)):
        done = p.finish(seconds, result)
        rows += done if isinstance(done, list) else [done]
    return rows


# ----------------------------------------------------------------------------- Pareto
def oriented(row: Row) -> float:
    """The row's error with lower = better (PSNR is negated)."""
    return -row.value if METRICS[row.metric].higher_is_better else row.value


def pareto_front(times: Sequence[float], errors: Sequence[float]) -> np.ndarray:
    """Mask of the points no other point beats in both time and error (lower is better).

    A point is dominated when another is at least as good in both and strictly
    better in one.
    """
    t, e = np.asarray(times, float), np.asarray(errors, float)
    front = np.ones(t.size, dtype=bool)
    for i in range(t.size):
        better_eq = (t <= t[i]) & (e <= e[i])
        strictly = (t < t[i]) | (e < e[i])
        front[i] = not np.any(better_eq & strictly)
    return front


def clearly_better(candidate: Row, default: Row) -> bool:
    """Is ``candidate`` more accurate than ``default`` by more than the metric's margin?"""
    m = METRICS[default.metric]
    gain = oriented(default) - oriented(candidate)
    return gain > max(m.margin_rel * abs(default.value), m.margin_abs)


def dominated_defaults(
    rows: Sequence[Row], *, time_margin: float = 0.2, conditional: bool = False
) -> list[tuple[Row, Row]]:
    """``(default, better)`` pairs: a setting faster by > ``time_margin`` and clearly better.

    Compared within one (knob, scene, metric). Settings with ``requires`` (they need
    information the default does without) count only with ``conditional=True``.
    """
    found = []
    for _, group in _groups(rows, ("knob", "scene", "metric")):
        defaults = [r for r in group if r.is_default]
        if len(defaults) != 1:
            continue
        d = defaults[0]
        for r in group:
            if r is d or (r.requires and not conditional):
                continue
            if r.time_s < (1 - time_margin) * d.time_s and clearly_better(r, d):
                found.append((d, r))
    return found


def _groups(rows: Sequence[Row], keys: Sequence[str]):
    order: dict[tuple, list[Row]] = {}
    for r in rows:
        order.setdefault(tuple(getattr(r, k) for k in keys), []).append(r)
    return list(order.items())


# ----------------------------------------------------------------------------- scenes
def edges_scene(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Radiance (rows, cols, 3) float32 and depth (mm) of a scene with depth edges.

    A far plane (2000 mm), a slanted floor (1400 -> 700 mm, linear in inverse depth),
    a disk at 800 mm and a near rectangle at 450 mm, each textured with a different
    photograph bundled with scikit-image (linearised sRGB).
    """
    from skimage import data
    from skimage.transform import resize

    rows, cols = shape

    def texture(image):
        return io.srgb_to_linear(resize(image / 255.0, (rows, cols), anti_aliasing=True))

    radiance = texture(data.astronaut())
    depth = np.full(shape, FAR_MM)
    r, c = np.mgrid[0:rows, 0:cols]
    floor = r >= int(0.7 * rows)
    frac = np.clip((r - 0.7 * rows) / (0.3 * rows), 0.0, 1.0)
    depth = np.where(floor, 1.0 / (1 / 1400 + frac * (1 / 700 - 1 / 1400)), depth)
    radiance = np.where(floor[..., None], texture(data.rocket()), radiance)
    disk = (r - 0.4 * rows) ** 2 + (c - 0.72 * cols) ** 2 <= (0.22 * rows) ** 2
    depth = np.where(disk, 800.0, depth)
    radiance = np.where(disk[..., None], texture(data.chelsea()), radiance)
    rect = (r >= 0.15 * rows) & (r < 0.6 * rows) & (c >= 0.08 * cols) & (c < 0.4 * cols)
    depth = np.where(rect, NEAR_MM, depth)
    radiance = np.where(rect[..., None], texture(data.coffee()), radiance)
    return radiance.astype(np.float32), depth


def scene_lens(shape: tuple[int, int]) -> profiles.Lens:
    """The motorcycle sample's lens (12.5 mm f/1.4, 12.869 um pixels) on a ``shape`` sensor."""
    base = profiles.load_lens(MOTORCYCLE / "lens.toml")
    return dataclasses.replace(base, width_px=shape[1], height_px=shape[0], source=None)


def stack_positions(lens: profiles.Lens, frames: int) -> np.ndarray:
    """``frames`` focus positions uniform in image distance over 2000..450 mm."""
    v_far = optics.image_distance(lens.focal_length_mm, FAR_MM)
    v_near = optics.image_distance(lens.focal_length_mm, NEAR_MM)
    return np.linspace(v_far, v_near, frames)


def write_stack(
    directory: Path,
    radiance: np.ndarray,
    depth: np.ndarray,
    lens: profiles.Lens,
    frames: int,
    *,
    noisy: bool,
    tolerance: float,
    seed: int = 7,
) -> Path:
    """Render a focal stack of the scene into ``directory`` (float32 TIFFs + stack.toml).

    ``p_ref`` is the middle frame's position (the engine's reference), so the radiance
    itself is the ground truth of the aligned result.
    """
    directory.mkdir(parents=True, exist_ok=True)
    positions = stack_positions(lens, frames)
    scene = Scene.from_depth(radiance, depth)
    images, _ = simulate.render_focal_stack(
        scene,
        lens,
        positions,
        exposure_s=0.1,
        exposure=NOISE if noisy else None,
        reference_image_distance_mm=float(positions[frames // 2]),
        tolerance=tolerance,
        seed=seed,
    )
    (directory / "lens.toml").write_text(profiles.lens_to_toml(lens), encoding="utf-8")
    lines = ['lens = "lens.toml"', 'kind = "focal-stack"']
    for i, (image, pos) in enumerate(zip(images, positions)):
        name = f"frame_{i:02d}.tif"
        io.write_image(directory / name, image, encoding="float32")
        lines += ["", "[[frames]]", f'file = "{name}"', f"image_distance_mm = {pos:.9f}"]
    (directory / "stack.toml").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return directory


@dataclasses.dataclass
class Prepared:
    """A stack taken to the deconvolution step with the default options."""

    name: str
    directory: Path
    truth: np.ndarray
    positions: np.ndarray
    average: np.ndarray
    clipped: np.ndarray
    kernel: np.ndarray
    samples: np.ndarray


def prepare(name: str, directory: Path, truth: np.ndarray) -> Prepared:
    """Align (default: estimated), weight and average a stack; its Sec. 9 kernel."""
    options = StackOptions()
    stack = load_stack(directory)
    lens = stack.lens_profile
    shape = check_frames(stack).shape
    positions = image_distances_mm(stack, lens).image_distances_mm
    weights = constant_speed_weights(positions, ends=options.sweep_ends)
    homographies = _estimated(stack.files, shape, options.align_max_side_px)
    graph = engine.weighted_sum_graph(stack.files, homographies, weights, shape)
    (summed,) = dask.compute(graph)
    average, clipped = summed[0], summed[1]
    kernel, samples, _ = engine.stack_kernel(
        positions, weights, lens=lens, absolute=True, blur_span_px=None
    )
    return Prepared(name, directory, truth, positions, average, clipped, kernel, samples)


def _estimated(files, shape, max_side_px: int) -> list[np.ndarray]:
    previews = engine.read_previews(files, max_side_px)
    found = align.estimate_alignment(previews, max_side_px=max_side_px)
    return [align.rescale_homography(a.homography, previews[0].shape, shape[:2]) for a in found]


# ----------------------------------------------------------------------------- IPSF
def ipsf_rows(config: Config) -> list[Row]:
    """Quadrature orders, numeric Eq. 5 steps and truncation on the Sec. 4.1 sweep."""
    lens = profiles.load_lens(SEC41_LENS)
    sweep = constant_speed(12.5, 1.0, 0.36)  # Sec. 4.1: p(0) = 12.5 mm, s = 1 mm/s, T = 0.36 s
    depths = config.ipsf_depths_mm
    refs = [psf.integrated_psf(lens, d, sweep, theta_order=REFERENCE_THETA_ORDER) for d in depths]
    scene = f"sec4.1 sweep, {len(depths)} depths"

    def measure(knob, setting, default, **kwargs) -> _Pending:
        def build():
            return [psf.integrated_psf(lens, d, sweep, **kwargs) for d in depths]

        def finish(seconds, kernels) -> Row:
            l1 = np.mean([np.abs(_pad_to(k, r.shape) - r).sum() for k, r in zip(kernels, refs)])
            return Row("ipsf", knob, scene, setting, default, "kernel_l1", float(l1), seconds)

        return _Pending(build, finish)

    rows = [
        measure(
            "pixel-integration order (analytic)",
            f"{n} nodes",
            n == default_of(psf.integrated_psf, "theta_order"),
            theta_order=n,
        )
        for n in config.theta_orders
    ]
    rows += [
        measure(
            "time nodes (numeric Eq. 5)",
            f"{n} nodes",
            n == default_of(psf.integrated_psf, "time_order"),
            method="numeric",
            time_order=n,
        )
        for n in config.time_orders
    ]
    rows += [
        measure(
            "time sub-interval (numeric Eq. 5)",
            f"{s:g} px",
            s == default_of(psf.integrated_psf, "time_step_px"),
            method="numeric",
            time_step_px=s,
        )
        for s in config.time_steps_px
    ]
    rows += [measure("IPSF method", m, m == "analytic", method=m) for m in ("analytic", "numeric")]
    full = refs[0].shape[0]
    for frac in config.size_fractions:
        size = max(3, 2 * round(frac * full / 2) + 1) if frac < 1 else full
        rows.append(measure("kernel size (IPSF)", f"{frac:g} x ({size} px)", frac >= 1, size=size))
    return _measure(rows, config.repeats)


def _pad_to(kernel: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Zero-pad a centred kernel to ``shape`` (or crop it, if larger)."""
    out = np.zeros(shape)
    h, H = kernel.shape[0] // 2, shape[0] // 2
    m = min(h, H)
    out[H - m : H + m + 1, H - m : H + m + 1] = kernel[h - m : h + m + 1, h - m : h + m + 1]
    return out


# ----------------------------------------------------------------------------- simulation
def simulation_rows(config: Config, radiance: np.ndarray, depth: np.ndarray) -> list[Row]:
    """Layer tolerance, occlusion and magnification of one frame of the edges scene.

    The frame is focused at the far end, with ``p_ref`` the middle of the stack range,
    so magnification matters; the truth is a render at ``config.truth_tolerance``.
    """
    lens = scene_lens(radiance.shape[:2])
    positions = stack_positions(lens, 3)
    camera = Camera.static(
        lens, float(positions[0]), 0.1, reference_image_distance_mm=float(positions[1])
    )
    scene = Scene.from_depth(radiance, depth)
    truth = simulate.render(scene, camera, tolerance=config.truth_tolerance)
    contrast = float(np.std(truth))
    name = f"edges {radiance.shape[0]}x{radiance.shape[1]}, far-focused frame"

    def measure(knob, setting, default, **plan_options) -> _Pending:
        def run():
            p = simulate.plan(scene, camera, **plan_options)
            return simulate.render(scene, camera, plan_=p)

        def finish(seconds, image) -> Row:
            err = float(np.sqrt(np.mean((image - truth) ** 2)) / contrast)
            return Row("simulation", knob, name, setting, default, "rel_rms", err, seconds)

        return _Pending(run, finish)

    rows = [
        measure(
            "layer tolerance", f"{t:g}", t == default_of(simulate.plan, "tolerance"), tolerance=t
        )
        for t in config.tolerances
    ]
    rows += [
        measure("occlusion", "auto (on: depth edges)", True),
        measure("occlusion", "off", False, occlusion=False),
        measure("magnification", "auto (on)", True),
        measure("magnification", "off", False, magnification_steps=0),
    ]
    return _measure(rows, config.repeats)


# ----------------------------------------------------------------------------- alignment
def alignment_rows(config: Config, prepared: Sequence[Prepared], work: Path) -> list[Row]:
    """None / analytic / estimated alignment: corner error and final PSNR."""
    return [row for prep in prepared for row in _alignment_rows(config, prep, work)]


def _homographies(mode: str, side: int, files, positions, shape) -> list[np.ndarray]:
    if mode == "none":
        return [np.eye(3)] * len(files)
    if mode == "analytic":
        return [a.homography for a in align.analytic_alignment(positions, shape)]
    return _estimated(files, shape, side)


def _corner_error(homographies, truth, shape) -> float:
    """Mean over frames of the largest corner displacement between two maps (px)."""
    rows, cols = shape[:2]
    corners = np.array([[0, 0], [cols - 1, 0], [0, rows - 1], [cols - 1, rows - 1]], float)
    return float(
        np.mean(
            [
                np.linalg.norm(
                    align.map_points(h, corners) - align.map_points(t, corners), axis=1
                ).max()
                for h, t in zip(homographies, truth)
            ]
        )
    )


def _alignment_rows(config: Config, prep: Prepared, work: Path) -> list[Row]:
    stack = load_stack(prep.directory)
    shape = check_frames(stack).shape
    truth = _homographies("analytic", 0, stack.files, prep.positions, shape)
    settings = [("none", "none", 0, False), ("analytic", "analytic", 0, False)]
    settings += [
        (f"estimate @{s} px", "estimate", s, s == StackOptions.align_max_side_px)
        for s in config.align_sides_px
    ]
    pending = []
    for label, mode, side, default in settings:
        requires = "absolute focus positions" if mode == "analytic" else ""
        corner = partial(
            Row, "alignment", "alignment (corner error)", prep.name, label, default, "corner_px"
        )
        pending.append(
            _Pending(
                partial(_homographies, mode, side, stack.files, prep.positions, shape),
                lambda seconds, hs, corner=corner, requires=requires: corner(
                    _corner_error(hs, truth, shape), seconds, requires
                ),
            )
        )
        final = partial(
            Row, "alignment", "alignment (final PSNR)", prep.name, label, default, "psnr_db"
        )
        options = StackOptions(align=mode, align_max_side_px=side or 768, encoding="float32")
        out = work / f"align-{prep.name}-{mode}-{side}.tif"
        pending.append(
            _Pending(
                partial(engine.process_stack, prep.directory, out, options),
                lambda seconds, result, final=final, requires=requires: final(
                    psnr(result.image, prep.truth), seconds, requires, "whole flexdof stack run"
                ),
            )
        )
    return _measure(pending, config.repeats)


# ----------------------------------------------------------------------------- deconvolution
def deconvolution_rows(config: Config, prep: Prepared) -> list[Row]:
    """Method, iterations, regularisation, kernel variance, tiles, dtype, kernel size."""
    lam = dc.plan(
        prep.average,
        prep.kernel,
        method="wiener",
        censored=prep.clipped,
        kernel_samples=prep.samples,
    ).params["lam"]

    def run(
        knob,
        setting,
        default,
        *,
        method="wiener",
        image=None,
        kernel=None,
        samples=prep.samples,
        note="",
        **options,
    ) -> _Pending:
        image = prep.average if image is None else image
        kernel = prep.kernel if kernel is None else kernel
        if method == "wiener":  # as engine.restore_image
            options = {**engine.wiener_options(kernel, samples), **options}

        def call():
            return deconvolve_tiled(image, kernel, method=method, censored=prep.clipped, **options)

        def finish(seconds, result) -> Row:
            value = psnr(result, prep.truth)
            return Row(
                "deconvolution",
                knob,
                prep.name,
                setting,
                default,
                "psnr_db",
                value,
                seconds,
                "",
                note,
            )

        return _Pending(call, finish)

    rows = [
        run("method", "wiener", True),
        run("method", "rl (30 it.)", False, method="rl"),
        run("method", "sparse (50 it.)", False, method="sparse"),
    ]
    rows += [
        run(
            "rl iterations",
            f"{n}",
            n == default_of(dc.richardson_lucy, "iterations"),
            method="rl",
            iterations=n,
        )
        for n in config.rl_iterations
    ]
    rows += [
        run(
            "sparse iterations",
            f"{n}",
            n == default_of(dc.sparse, "iterations"),
            method="sparse",
            iterations=n,
        )
        for n in config.sparse_iterations
    ]
    rows += [
        run(
            "wiener regularisation",
            "auto" if f == 1 else f"{f:g} x auto",
            f == 1,
            **({} if f == 1 else {"regularization": lam * f}),
        )
        for f in config.regularization_factors
    ]
    rows += [
        run("wiener kernel variance", "on (per-depth samples)", False, kernel_samples=prep.samples),
        run("wiener kernel variance", "off", False, kernel_samples=None),
        run("wiener kernel variance", "auto (Eq. 8 spread > 0.1)", True),
    ]
    rows += [
        run(
            "wiener EM passes (clipped pixels)",
            f"{n}",
            n == engine.WIENER_EM_PASSES,
            saturation_passes=n,
        )
        for n in sorted({engine.WIENER_EM_PASSES, 3})
    ]
    rows += [
        run("tile size", f"{t} px", t == StackOptions.tile_px, tile_px=t) for t in config.tiles_px
    ]
    tile = min(config.tiles_px)
    depth = dc.plan(
        prep.average,
        prep.kernel,
        method="wiener",
        censored=prep.clipped,
        kernel_samples=prep.samples,
    ).depth
    rows += [
        run(
            f"tile overlap ({tile} px tiles)",
            "auto" if f >= 1 else f"{f:g} x auto ({int(f * depth)} px)",
            f >= 1,
            tile_px=tile,
            **({} if f >= 1 else {"overlap_px": int(f * depth)}),
        )
        for f in config.overlap_fractions
    ]
    rows += [
        run("precision", "float32", True),
        run("precision", "float64", False, image=prep.average.astype(np.float64)),
    ]
    full = prep.kernel.shape[0]
    for frac in config.size_fractions:
        size = max(3, 2 * round(frac * full / 2) + 1) if frac < 1 else full
        k = _crop(prep.kernel, size)
        s = np.array([_crop(x, size) for x in prep.samples])
        rows.append(
            run(
                "kernel size (deconvolution)",
                f"{frac:g} x ({size} px)",
                frac >= 1,
                kernel=k,
                samples=s,
            )
        )
    return _measure(rows, config.repeats)


def _crop(kernel: np.ndarray, size: int) -> np.ndarray:
    h, m = kernel.shape[0] // 2, size // 2
    k = kernel[h - m : h + m + 1, h - m : h + m + 1]
    return k / k.sum()


# ----------------------------------------------------------------------------- stack sampling
def sampling_rows(config: Config, radiance: np.ndarray, depth: np.ndarray, work: Path) -> list[Row]:
    """Frames over the same depth range: final PSNR and the Eq. 8 kernel spread."""
    lens = scene_lens(radiance.shape[:2])
    pending = []
    name = "edges-noisy"
    for n in config.frame_counts:
        directory = write_stack(
            work / f"frames-{n}",
            radiance,
            depth,
            lens,
            n,
            noisy=True,
            tolerance=config.truth_tolerance,
        )
        out = work / f"frames-{n}.tif"

        def finish(seconds, result, n=n) -> list[Row]:
            spread = result.sidecar["kernel"]["depth_invariance_eq8"]["mean"]
            note = "whole flexdof stack run; capture time grows with frames too"
            values = (("psnr_db", psnr(result.image, radiance)), ("eq8_spread", spread))
            return [
                Row(
                    "stack sampling",
                    "frames over 450-2000 mm",
                    name,
                    f"{n} frames",
                    False,
                    metric,
                    float(value),
                    seconds,
                    note=note,
                )
                for metric, value in values
            ]

        options = StackOptions(encoding="float32")
        pending.append(_Pending(partial(engine.process_stack, directory, out, options), finish))
    return _measure(pending, config.repeats)


# ----------------------------------------------------------------------------- driver
def run_accuracy(
    out: Path, *, quick: bool = False, progress: Callable[[str], None] = log.info
) -> list[Row]:
    """Run the benchmark; write accuracy.csv/.md, pareto.png and summary.md into ``out``."""
    config = Config.quick() if quick else Config.full()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    rows: list[Row] = []
    with tempfile.TemporaryDirectory(prefix="flexdof-bench-") as tmp:
        work = Path(tmp)
        radiance, depth = edges_scene(config.shape)
        lens = scene_lens(config.shape)
        progress("IPSF quadrature and truncation")
        rows += ipsf_rows(config)
        progress("simulation: tolerance, occlusion, magnification")
        rows += simulation_rows(config, radiance, depth)
        progress("rendering the edges focal stacks (truth)")
        truth_motorcycle = tifffile.imread(MOTORCYCLE / "ground_truth.tif")
        stacks = {"motorcycle": (MOTORCYCLE, truth_motorcycle)}
        for noisy in (False, True):
            name = "edges-noisy" if noisy else "edges-clean"
            if name in config.deconvolution_scenes:
                directory = write_stack(
                    work / name,
                    radiance,
                    depth,
                    lens,
                    config.frames,
                    noisy=noisy,
                    tolerance=config.truth_tolerance,
                )
                stacks[name] = (directory, radiance)
        prepared = [prepare(name, d, t) for name, (d, t) in stacks.items()]
        progress("alignment")
        rows += alignment_rows(config, [p for p in prepared if p.name != "edges-clean"], work)
        for prep in prepared:
            progress(f"deconvolution: {prep.name}")
            rows += deconvolution_rows(config, prep)
        progress("stack sampling")
        rows += sampling_rows(config, radiance, depth, work)
    elapsed = time.perf_counter() - start
    write_table(rows, out)
    write_plot(rows, out / "pareto.png")
    write_summary(rows, out / "summary.md", elapsed=elapsed, quick=quick)
    return rows


# ----------------------------------------------------------------------------- outputs
def write_table(rows: Sequence[Row], out: Path) -> None:
    """``accuracy.csv`` (all columns) and ``accuracy.md`` (a Markdown table)."""
    with open(out / "accuracy.csv", "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(COLUMNS)
        for r in rows:
            writer.writerow(
                [
                    r.group,
                    r.knob,
                    r.scene,
                    r.setting,
                    int(r.is_default),
                    r.metric,
                    f"{r.value:.6g}",
                    f"{r.time_s:.6g}",
                    r.requires,
                    r.note,
                ]
            )
    lines = [
        "| knob | scene | setting | default | metric | value | time s | requires |",
        "|---|---|---|---|---|---:|---:|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.knob} | {r.scene} | {r.setting} | {'**yes**' if r.is_default else ''} | "
            f"{r.metric} | {r.value:.4g} | {r.time_s:.3g} | {r.requires} |"
        )
    (out / "accuracy.md").write_text("\n".join(lines) + "\n", encoding="utf-8")


def read_table(path: Path) -> list[Row]:
    """Rows back from ``accuracy.csv``."""
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        if tuple(reader.fieldnames or ()) != COLUMNS:
            raise InputError(f"{path}: columns {reader.fieldnames}, expected {list(COLUMNS)}")
        return [
            Row(
                d["group"],
                d["knob"],
                d["scene"],
                d["setting"],
                bool(int(d["is_default"])),
                d["metric"],
                float(d["value"]),
                float(d["time_s"]),
                d["requires"],
                d["note"],
            )
            for d in reader
        ]


def write_plot(rows: Sequence[Row], path: Path) -> None:
    """Error vs time (log), one panel per (group, metric, scene), one curve per knob."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    panels = _groups(rows, ("group", "metric", "scene"))
    ncols = 3
    nrows = math.ceil(len(panels) / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(6 * ncols, 4.2 * nrows), squeeze=False)
    for ax, ((group, metric, scene), panel) in zip(axes.ravel(), panels):
        for (knob,), curve in _groups(panel, ("knob",)):
            curve = sorted(curve, key=lambda r: r.time_s)
            t = [r.time_s for r in curve]
            v = [r.value for r in curve]
            (line,) = ax.plot(t, v, "o-", ms=4, lw=1, label=knob)
            for r in curve:
                ax.annotate(
                    r.setting,
                    (r.time_s, r.value),
                    fontsize=6,
                    alpha=0.7,
                    xytext=(3, 3),
                    textcoords="offset points",
                )
                if r.is_default:
                    ax.plot(
                        r.time_s,
                        r.value,
                        "*",
                        ms=14,
                        color=line.get_color(),
                        markeredgecolor="black",
                    )
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        if not METRICS[metric].higher_is_better and min(r.value for r in panel) > 0:
            ax.set_yscale("log")
        ax.set_title(f"{group}: {scene}", fontsize=9)
        ax.set_xlabel("time, s (best of repeats)")
        ax.set_ylabel(METRICS[metric].label, fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6, loc="best")
    for ax in axes.ravel()[len(panels) :]:
        ax.axis("off")
    fig.suptitle("flexdof accuracy vs time (stars: defaults)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_summary(rows: Sequence[Row], path: Path, *, elapsed: float, quick: bool) -> None:
    """A few sentences a user can act on, from the measured numbers."""
    lines = [
        f"# Accuracy vs time ({'quick' if quick else 'full'} run, {elapsed:.0f} s)",
        "",
    ]
    lines += _highlights(rows)
    lines += ["", "## Defaults", ""]
    dominated = dominated_defaults(rows)
    conditional = [pair for pair in dominated_defaults(rows, conditional=True) if pair[1].requires]
    if not dominated:
        lines.append(
            "Every default is on the Pareto front: no measured setting is both >20% faster "
            "and clearly more accurate (margins in pipeline.bench.METRICS)."
        )
    for d, r in dominated:
        lines.append(
            f"- DOMINATED: {d.knob} on {d.scene}: default {d.setting} ({_fmt(d)}, "
            f"{d.time_s:.3g} s) is beaten by {r.setting} ({_fmt(r)}, {r.time_s:.3g} s)."
        )
    for d, r in conditional:
        lines.append(
            f"- Where {r.requires} are known: {r.setting} beats the default {d.setting} on "
            f"{d.scene} ({_fmt(r)} in {r.time_s:.3g} s vs {_fmt(d)} in {d.time_s:.3g} s)."
        )
    lines += ["", "## Per knob (default vs the most accurate and the fastest setting)", ""]
    for (knob, scene, _metric), group in _groups(rows, ("knob", "scene", "metric")):
        defaults = [r for r in group if r.is_default]
        base = defaults[0] if defaults else min(group, key=lambda r: r.time_s)
        best = min(group, key=oriented)
        fast = min(group, key=lambda r: r.time_s)
        parts = [
            f"- **{knob}** ({scene}): {'default' if defaults else 'cheapest'} "
            f"{base.setting} = {_fmt(base)} in {base.time_s:.3g} s"
        ]
        if best is not base:
            parts.append(
                f"most accurate {best.setting} = {_fmt(best)} at "
                f"{best.time_s / base.time_s:.2g}x the time"
            )
        if fast is not base and fast is not best:
            parts.append(
                f"fastest {fast.setting} = {_fmt(fast)} at "
                f"{fast.time_s / base.time_s:.2g}x the time"
            )
        lines.append("; ".join(parts) + ".")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def _fmt(r: Row) -> str:
    return f"{r.value:.2f} dB" if r.metric == "psnr_db" else f"{r.metric} {r.value:.3g}"


def _find(rows, knob, setting_prefix, scene=None, metric=None):
    for r in rows:
        if (
            r.knob == knob
            and r.setting.startswith(setting_prefix)
            and (scene is None or r.scene == scene)
            and (metric is None or r.metric == metric)
        ):
            return r
    return None


def _highlights(rows: Sequence[Row]) -> list[str]:
    """Headline comparisons, each only if both of its rows were measured."""
    out = []
    scenes = sorted({r.scene for r in rows if r.group == "deconvolution"})
    for scene in scenes:
        w32 = _find(rows, "precision", "float32", scene)
        w64 = _find(rows, "precision", "float64", scene)
        wie = _find(rows, "method", "wiener", scene)
        spa = _find(rows, "method", "sparse", scene)
        rl = _find(rows, "method", "rl", scene)
        if w32 and w64:
            out.append(
                f"- {scene}: float64 deconvolution changes PSNR by {w64.value - w32.value:+.3f} "
                f"dB for {w64.time_s / w32.time_s:.2g}x the time of float32."
            )
        if wie and spa:
            out.append(
                f"- {scene}: sparse-prior deconvolution buys {spa.value - wie.value:+.2f} dB "
                f"over Wiener for {spa.time_s / wie.time_s:.2g}x the time"
                + (
                    f"; Richardson-Lucy {rl.value - wie.value:+.2f} dB for "
                    f"{rl.time_s / wie.time_s:.2g}x."
                    if rl
                    else "."
                )
            )
    for scene in sorted({r.scene for r in rows if r.knob == "alignment (final PSNR)"}):
        none = _find(rows, "alignment (final PSNR)", "none", scene)
        est = _find(rows, "alignment (final PSNR)", "estimate @768", scene)
        ana = _find(rows, "alignment (final PSNR)", "analytic", scene)
        if none and est:
            out.append(
                f"- {scene}: skipping alignment costs {est.value - none.value:.2f} dB; "
                f"estimating it adds {est.time_s - none.time_s:.2g} s to the run"
                + (
                    f"; the analytic scaling gives {ana.value - est.value:+.2f} dB vs "
                    f"estimated (needs absolute focus positions)."
                    if ana
                    else "."
                )
            )
    tol = [r for r in rows if r.knob == "layer tolerance"]
    d = next((r for r in tol if r.is_default), None)
    if d:
        for r in tol:
            if r is not d:
                out.append(
                    f"- simulation tolerance {r.setting}: render error {r.value:.2g} vs "
                    f"{d.value:.2g} at the default {d.setting}, "
                    f"{r.time_s / d.time_s:.2g}x the time."
                )
    for knob, off in (("occlusion", "off"), ("magnification", "off")):
        on, no = _find(rows, knob, "auto"), _find(rows, knob, off)
        if on and no:
            out.append(
                f"- simulation without {knob}: error {no.value:.2g} (vs {on.value:.2g}) for "
                f"{no.time_s / on.time_s:.2g}x the time."
            )
    counts = sorted(
        (r for r in rows if r.knob == "frames over 450-2000 mm" and r.metric == "psnr_db"),
        key=lambda r: int(r.setting.split()[0]),
    )
    if len(counts) >= 2:
        out.append(
            "- frames over the same range: PSNR "
            + ", ".join(f"{r.value:.2f} dB at {r.setting}" for r in counts)
            + f" (processing {counts[0].time_s:.2g} -> {counts[-1].time_s:.2g} s)."
        )
    theta = sorted(
        (r for r in rows if r.knob == "pixel-integration order (analytic)"),
        key=lambda r: r.time_s,
    )
    if theta:
        out.append(
            "- IPSF pixel integration: L1 error "
            + ", ".join(f"{r.value:.1e} at {r.setting}" for r in theta)
            + "."
        )
    return out


__all__ = [
    "METRICS",
    "Config",
    "Metric",
    "Prepared",
    "Row",
    "alignment_rows",
    "best_times",
    "clearly_better",
    "deconvolution_rows",
    "dominated_defaults",
    "edges_scene",
    "ipsf_rows",
    "oriented",
    "pareto_front",
    "prepare",
    "read_table",
    "run_accuracy",
    "sampling_rows",
    "simulation_rows",
    "write_plot",
    "write_stack",
    "write_summary",
    "write_table",
]
