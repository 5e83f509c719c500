"""One function per group of knobs of the accuracy benchmark: IPSFs, simulation,
alignment, deconvolution and frame sampling, each measured against ground truth.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from pathlib import Path

import numpy as np

from pipeline.core import align, psf, simulate, stack_kernel
from pipeline.core import deconvolve as dc
from pipeline.core.motion import constant_speed
from pipeline.core.quality import psnr
from pipeline.core.scene import Camera, Scene
from pipeline.io import profiles
from pipeline.io.stackfile import check_frames, load_stack
from pipeline.jobs.options import ALIGN_MODELS, StackOptions
from pipeline.jobs.stack import process_stack
from pipeline.paper.bench.pareto import Config, Row, default_of
from pipeline.paper.bench.scenes import (
    REFERENCE_THETA_ORDER,
    SEC41_LENS,
    Prepared,
    _estimated,
    scene_lens,
    stack_positions,
    write_stack,
)
from pipeline.paper.bench.timing import PendingRun, time_runs
from pipeline.parallel.tiling import deconvolve_tiled


def knob_settings(measure, knob, function, parameter, values, label, **fixed) -> list:
    """One pending measurement per value of a function's parameter; the function's own
    default (read from its signature) is marked as the default setting."""
    default = default_of(function, parameter)
    return [measure(knob, label.format(v), v == default, **fixed, **{parameter: v}) for v in values]


# ----------------------------------------------------------------------------- IPSF
def ipsf_rows(config: Config) -> list[Row]:
    """Quadrature orders, numeric Eq. 5 steps and truncation on the Sec. 4.1 sweep."""
    lens = profiles.load_lens(SEC41_LENS)
    sweep = constant_speed(12.5, 1.0, 0.36)  # Sec. 4.1: p(0) = 12.5 mm, s = 1 mm/s, T = 0.36 s
    depths = config.ipsf_depths_mm
    refs = [psf.integrated_psf(lens, d, sweep, theta_order=REFERENCE_THETA_ORDER) for d in depths]
    scene = f"sec4.1 sweep, {len(depths)} depths"

    def measure(knob, setting, default, **kwargs) -> PendingRun:
        def build():
            return [psf.integrated_psf(lens, d, sweep, **kwargs) for d in depths]

        def finish(seconds, kernels) -> Row:
            l1 = np.mean([np.abs(_pad_to(k, r.shape) - r).sum() for k, r in zip(kernels, refs)])
            return Row("ipsf", knob, scene, setting, default, "kernel_l1", float(l1), seconds)

        return PendingRun(build, finish)

    ipsf = psf.integrated_psf
    rows = knob_settings(
        measure,
        "pixel-integration order (analytic)",
        ipsf,
        "theta_order",
        config.theta_orders,
        "{} nodes",
    )
    rows += knob_settings(
        measure,
        "time nodes (numeric Eq. 5)",
        ipsf,
        "time_order",
        config.time_orders,
        "{} nodes",
        method="numeric",
    )
    rows += knob_settings(
        measure,
        "time sub-interval (numeric Eq. 5)",
        ipsf,
        "time_step_px",
        config.time_steps_px,
        "{:g} px",
        method="numeric",
    )
    rows += [measure("IPSF method", m, m == "analytic", method=m) for m in ("analytic", "numeric")]
    full = refs[0].shape[0]
    for frac in config.size_fractions:
        size = max(3, 2 * round(frac * full / 2) + 1) if frac < 1 else full
        rows.append(measure("kernel size (IPSF)", f"{frac:g} x ({size} px)", frac >= 1, size=size))
    return time_runs(rows, config.repeats)


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

    def measure(knob, setting, default, **plan_options) -> PendingRun:
        def run():
            p = simulate.plan(scene, camera, **plan_options)
            return simulate.render(scene, camera, plan_=p)

        def finish(seconds, image) -> Row:
            err = float(np.sqrt(np.mean((image - truth) ** 2)) / contrast)
            return Row("simulation", knob, name, setting, default, "rel_rms", err, seconds)

        return PendingRun(run, finish)

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
    return time_runs(rows, config.repeats)


# ----------------------------------------------------------------------------- alignment
def alignment_rows(config: Config, prepared: Sequence[Prepared], work: Path) -> list[Row]:
    """None / analytic / estimated alignment (at each matching size, and under each motion
    model at the default size): corner error and final PSNR."""
    return [row for prep in prepared for row in _alignment_rows(config, prep, work)]


def _homographies(
    mode: str, side: int, files, positions, shape, model: str = StackOptions.align_model
) -> list[np.ndarray]:
    if mode == "none":
        return [np.eye(3)] * len(files)
    if mode == "analytic":
        return [a.homography for a in align.analytic_alignment(positions, shape)]
    return _estimated(files, shape, side, model)


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
    default_model, default_side = StackOptions.align_model, StackOptions.align_max_side_px
    settings = [
        ("none", "none", 0, default_model, False),
        ("analytic", "analytic", 0, default_model, False),
    ]
    settings += [
        (f"estimate @{s} px", "estimate", s, default_model, s == default_side)
        for s in config.align_sides_px
    ]
    settings += [
        (f"estimate @{default_side} px, --align-model {m}", "estimate", default_side, m, False)
        for m in ALIGN_MODELS
        if m != default_model
    ]
    pending = []
    for label, mode, side, model, default in settings:
        requires = "absolute focus positions" if mode == "analytic" else ""
        corner = partial(
            Row, "alignment", "alignment (corner error)", prep.name, label, default, "corner_px"
        )
        pending.append(
            PendingRun(
                partial(_homographies, mode, side, stack.files, prep.positions, shape, model),
                lambda seconds, hs, corner=corner, requires=requires: corner(
                    _corner_error(hs, truth, shape), seconds, requires
                ),
            )
        )
        final = partial(
            Row, "alignment", "alignment (final PSNR)", prep.name, label, default, "psnr_db"
        )
        options = StackOptions(
            align=mode, align_model=model, align_max_side_px=side or 768, encoding="float32"
        )
        out = work / f"align-{prep.name}-{mode}-{side}-{model}.tif"
        pending.append(
            PendingRun(
                partial(process_stack, prep.directory, out, options),
                lambda seconds, result, final=final, requires=requires: final(
                    psnr(result.image, prep.truth), seconds, requires, "whole flexdof stack run"
                ),
            )
        )
    return time_runs(pending, config.repeats)


def frame_support_rows(config: Config, prepared: Sequence[Prepared], work: Path) -> list[Row]:
    """The main job as it is (``--no-frame-range``), kept to the frames' range (the default:
    flat areas' fine band from the average, then the clip) and with ``--frame-guard``:
    final PSNR and the whole run's time (issue 13)."""
    settings = (
        ("none (--no-frame-range)", {"frame_range": False}, False),
        ("frame range", {}, True),
        ("--frame-guard", {"frame_guard": True}, False),
    )
    pending = []
    for prep in prepared:
        for label, extra, default in settings:
            final = partial(
                Row, "frames", "keeping to the frames (final PSNR)", prep.name, label, default,
                "psnr_db",
            )  # fmt: skip
            options = StackOptions(encoding="float32", **extra)
            out = work / f"frames-{prep.name}-{len(pending)}.tif"
            pending.append(
                PendingRun(
                    partial(process_stack, prep.directory, out, options),
                    lambda seconds, result, final=final, prep=prep: final(
                        psnr(result.image, prep.truth), seconds, "", "whole flexdof stack run"
                    ),
                )
            )
    return time_runs(pending, config.repeats)


# ----------------------------------------------------------------------------- deconvolution
def deconvolution_rows(config: Config, prep: Prepared) -> list[Row]:
    """Method, iterations, regularisation, kernel variance, tiles, dtype, kernel size."""
    wiener_plan = dc.plan(
        prep.average,
        prep.kernel,
        method="wiener",
        censored=prep.clipped,
        kernel_samples=prep.samples,
    )
    lam = wiener_plan.params["lam"]

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
    ) -> PendingRun:
        image = prep.average if image is None else image
        kernel = prep.kernel if kernel is None else kernel
        if method == "wiener":  # as result.restore_image
            options = {**stack_kernel.wiener_options(kernel, samples), **options}

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

        return PendingRun(call, finish)

    rows = [
        run("method", "wiener", True),
        run("method", "rl (30 it.)", False, method="rl"),
        run("method", "sparse (50 it.)", False, method="sparse"),
    ]
    rows += knob_settings(
        run,
        "rl iterations",
        dc.richardson_lucy,
        "iterations",
        config.rl_iterations,
        "{}",
        method="rl",
    )
    rows += knob_settings(
        run,
        "sparse iterations",
        dc.sparse,
        "iterations",
        config.sparse_iterations,
        "{}",
        method="sparse",
    )
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
        run("tile size", f"{t} px", t == StackOptions.tile_px, tile_px=t) for t in config.tiles_px
    ]
    tile = min(config.tiles_px)
    depth = wiener_plan.depth
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
    return time_runs(rows, config.repeats)


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
        pending.append(PendingRun(partial(process_stack, directory, out, options), finish))
    return time_runs(pending, config.repeats)
