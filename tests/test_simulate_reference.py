"""pipeline.simulate against independent references (issue 14).

The references (``tests/reference``) share no code with ``pipeline.simulate`` or
``pipeline.psf``: a brute-force time integration for smooth scenes and an exact thin-lens
ray trace of two planes with an edge. The first tests check the references themselves;
the rest are the issue's acceptance checks (measured <= the plan's estimate <= 3x
measured).
``tests/benchmarks/simulate_vs_reference.py`` prints the full table.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import tracemalloc

import numpy as np
import pytest
from reference import cases as refcases
from reference import disk, raytrace, smooth
from reference import optics as ref_optics

from pipeline.core import optics, simulate
from pipeline.core.lens import Lens
from pipeline.core.motion import Profile
from pipeline.core.scene import Camera, Scene

CASES = refcases.build_cases()


@functools.cache
def reference(name: str) -> np.ndarray:
    return CASES[name].reference()


def measured_and_estimate(name: str, tol: float) -> tuple[float, float]:
    case = CASES[name]
    pl = simulate.plan(case.scene, case.camera, tolerance=tol)
    out = simulate.render(case.scene, case.camera, plan_=pl)
    return refcases.rel_rms(out, reference(name), case.contrast), pl.estimated_error


def assert_estimate_holds(measured: float, estimate: float) -> None:
    if measured < 1e-9 and estimate < 1e-9:
        return  # exact, and says so
    assert measured <= estimate <= 3 * measured, f"measured {measured:.3g}, estimate {estimate:.3g}"


# ----------------------------------------------------------------------------- the references
def test_reference_geometry_matches_eq2():
    """2 |rho| * m is Eq. 2's blur in detector pixels; the lens law matches pipeline.optics."""
    f, n, pitch, p_ref = 12.5, 1.4, 0.02, 12.7
    for u, p in [(500.0, 12.6), (1500.0, 12.9), (math.inf, 12.8), (700.0, 12.5)]:
        rho = float(ref_optics.grid_radius(f, n, pitch, p_ref, 0.0 if math.isinf(u) else 1 / u, p))
        b = optics.blur_diameter_mm(f / n, optics.image_distance(f, u), p) / pitch
        assert 2 * abs(rho) * p / p_ref == pytest.approx(b, rel=1e-12)
        assert ref_optics.image_distance(f, u) == pytest.approx(optics.image_distance(f, u))


def test_disk_rect_area_exact():
    rng = np.random.default_rng(0)
    assert disk.disk_rect_area(-5, 5, -5, 5, 1.3) == pytest.approx(math.pi * 1.3**2)
    pts = rng.uniform(-1, 1, (400_000, 2))
    inside = np.hypot(*pts.T) < 1
    for _ in range(4):
        x0, x1 = np.sort(rng.uniform(-1.2, 1.2, 2))
        y0, y1 = np.sort(rng.uniform(-1.2, 1.2, 2))
        box = (pts[:, 0] > x0) & (pts[:, 0] < x1) & (pts[:, 1] > y0) & (pts[:, 1] < y1)
        mc = np.mean(inside & box) * 4
        assert disk.disk_rect_area(x0, x1, y0, y1, 1.0) == pytest.approx(mc, abs=0.01)
    k = disk.pixel_disk_kernels([3.3], 5)[0]
    assert k.sum() == pytest.approx(1) and np.allclose(k, k.T) and np.allclose(k, k[::-1])


@pytest.mark.parametrize("label", ["near", "far", "between"])
def test_exact_ray_trace_matches_monte_carlo(label):
    """The closed-form two-plane trace equals a literal first-hit ray tracer."""
    case = CASES[f"edge focus {label}"]
    near = case.scene.surfaces[1].radiance[:, :, 0]
    far = case.scene.surfaces[0].radiance[:, :, 0]
    lens, p = case.camera.lens, case.camera.motion.start_mm
    pixels = [(10, c) for c in (26, 30, 31, 32, 33, 38)]
    mc = raytrace.trace_pixels_monte_carlo(
        near, far, refcases.EDGE_COL, refcases.NEAR_MM, refcases.FAR_MM,
        f_mm=lens.focal_length_mm, f_number=lens.f_number, pitch_mm=lens.pixel_pitch_mm,
        p_mm=p, p_ref_mm=case.camera.reference_mm, pixels=pixels, samples=200_000,
    )
    ref = reference(case.name)
    for (r, c), (mean, err) in zip(pixels, mc):
        assert abs(ref[r, c] - mean) <= 5 * err + 1e-9, (r, c, ref[r, c], mean, err)


@pytest.mark.parametrize("name", ["flat in focus", "flat", "edge focus near", "edge focus far"])
def test_reference_and_simulator_agree_where_both_are_exact(name):
    """Same units, centre, borders and normalisation: exact agreement (1e-12)."""
    measured, estimate = measured_and_estimate(name, 1e-3)
    assert measured < 1e-12 and estimate < 1e-12


def test_reference_converged():
    """Doubling the time cells changes the sweep references far below the tested tolerances."""
    for name in ("ramp sweep", "edge sweep"):
        case = CASES[name]
        coarse = case.reference(n_time=128)
        assert refcases.rel_rms(coarse, reference(name), case.contrast) < 2e-5
    # Many-depth scenes (not used by the cases above, which have <= 64 distinct depths and
    # get one exact layer each): white-noise depth over 110 mm-3 m, linear split between
    # depth nodes; the change falls about 3x per doubling (1.9e-4, 6.3e-5, 1.8e-5 for
    # 257/513/1025 nodes on 24x32 px with 64 time cells; 8e-5 for 513 vs 1025 with 8 cells).
    case = CASES["wide-angle"]
    rng = np.random.default_rng(3)
    depth = 1 / (1 / 3000 + (1 / 110 - 1 / 3000) * rng.random((12, 16)))
    tex = refcases.texture((12, 16), 4)
    kw = dict(f_mm=4.0, f_number=2.8, pitch_mm=0.005, times_s=[0.0, 0.1],
              positions_mm=case.camera.motion.image_distances_mm, p_ref_mm=4.08, n_time=8)
    a = smooth.render_smooth(tex, depth, **kw, n_layers=513)
    b = smooth.render_smooth(tex, depth, **kw, n_layers=1025)
    assert refcases.rel_rms(a, b, float(np.std(tex))) < 1e-4


# ----------------------------------------------------------------------------- acceptance


@pytest.mark.parametrize(
    ("name", "tol"),
    [
        ("ramp static narrow", 1e-2),
        ("ramp static narrow", 1e-3),
        ("ramp static narrow", 1e-4),
        ("stack frame", 1e-3),
        ("ramp sweep", 1e-2),
        ("ramp sweep", 1e-3),
        ("edge focus between", 1e-2),
        ("edge focus between", 1e-3),
        ("edge focus between", 1e-4),
        ("edge jump between", 1e-2),
        ("edge jump between", 1e-3),
        ("edge jump between", 1e-4),
        ("edge sweep", 1e-2),
        ("edge sweep", 1e-3),
        ("edge sweep", 1e-4),
        ("wide-angle", 1e-2),
        ("wide-angle", 1e-3),
    ],
)
def test_measured_error_within_estimate(name, tol):
    assert_estimate_holds(*measured_and_estimate(name, tol))


@pytest.mark.parametrize("name", ["edge focus between", "edge jump between"])
def test_sub_aperture_cells_make_a_static_edge_exact(name):
    """Both sides out of focus (opposite signs): 'over' compositing was off by 0.0256 (0.0356
    for the larger jump) at every tolerance; aperture cells along the near plane's pixel
    lines trace it exactly, and only near the edge (elsewhere the render is unchanged)."""
    case = CASES[name]
    pl = simulate.plan(case.scene, case.camera, tolerance=1e-2)
    assert pl.edge_time_cells == 1 and pl.estimated_error == 0
    out = simulate.render(case.scene, case.camera, plan_=pl)
    over_plan = dataclasses.replace(pl, edge_time_cells=0)
    over = simulate.render(case.scene, case.camera, plan_=over_plan)
    assert refcases.rel_rms(out, reference(name), case.contrast) < 1e-12
    assert refcases.rel_rms(over, reference(name), case.contrast) > 0.02
    far_from_edge = np.abs(np.arange(refcases.COLS) - refcases.EDGE_COL) > 12
    assert np.array_equal(out[:, far_from_edge], over[:, far_from_edge])


def test_edge_sweep_time_cells_follow_the_tolerance():
    """The occlusion estimate (doubling the time cells) falls with the tolerance and bounds
    the measured partial-occlusion error: render vs the same plan with 8x the cells."""
    case = CASES["edge sweep"]
    for tol in (1e-2, 1e-3):
        pl = simulate.plan(case.scene, case.camera, tolerance=tol)
        occl = next(e for e in pl.effects if e.name == "occlusion").estimated_error
        assert 0 < occl <= tol
        out = simulate.render(case.scene, case.camera, plan_=pl)
        fine = dataclasses.replace(pl, edge_time_cells=8 * pl.edge_time_cells)
        assert_estimate_holds(
            refcases.rel_rms(out, simulate.render(case.scene, case.camera, plan_=fine),
                             case.contrast),
            occl,
        )


def test_edge_cells_beyond_the_work_budget_keep_over_compositing(monkeypatch):
    """Too much work for sub-aperture compositing: 'over' with the straight-edge estimate."""
    monkeypatch.setattr(simulate.planner, "EDGE_WORK_BUDGET", 1.0)
    case = CASES["edge focus between"]
    pl = simulate.plan(case.scene, case.camera, tolerance=1e-3)
    assert pl.edge_time_cells == 0
    assert_estimate_holds(*measured_and_estimate("edge focus between", 1e-3))
    assert pl.estimated_error == pytest.approx(0.0256, abs=5e-4)


def small_rolling(rows: int, cols: int = 32):
    """A rolling-shutter sweep: 1 ms/row, 10 ms rows, constant speed; slanted plane."""
    lens = Lens(12.5, 1.4, 20.0, cols, rows, shutter="rolling", line_time_us=1000.0)
    line, exposure = 1e-3, 0.01
    v = refcases.v
    speed = (v(500.0) - v(1500.0)) / (47 * line + exposure)
    duration = (rows - 1) * line + exposure
    motion = Profile([0.0, duration], [v(1500.0), v(1500.0) + speed * duration])
    camera = Camera(lens, motion, row_exposure_s=exposure)
    xx = np.ones((rows, 1)) * np.arange(cols, dtype=float)[None, :]
    radiance = refcases.texture((rows, cols), 1)
    return radiance, 600.0 + 600.0 * xx / (cols - 1), camera


def rolling_render_and_reference(rows: int):
    """:func:`small_rolling`'s scene planned at 1e-2 and rendered, beside the brute-force
    reference (256 time steps, per-row windows): (radiance, plan, render, reference)."""
    radiance, depth, camera = small_rolling(rows)
    scene = Scene.from_depth(radiance, depth)
    pl = simulate.plan(scene, camera, tolerance=1e-2)
    out = simulate.render(scene, camera, plan_=pl)
    lens = camera.lens
    ref = smooth.render_smooth(
        radiance, depth, f_mm=lens.focal_length_mm, f_number=lens.f_number,
        pitch_mm=lens.pixel_pitch_mm, times_s=camera.motion.times_s,
        positions_mm=camera.motion.image_distances_mm, p_ref_mm=camera.reference_mm,
        row_windows=camera.row_windows(rows), n_time=256,
    )
    return radiance, pl, out, ref


def test_rolling_shutter_within_estimate():
    """6 rows at 1e-2 (the 48-row case of the benchmark is in tests/benchmarks/results)."""
    rows = 6
    radiance, pl, out, ref = rolling_render_and_reference(rows)
    assert_estimate_holds(refcases.rel_rms(out, ref, float(np.std(radiance))), pl.estimated_error)


def test_twelve_row_rolling_capture_does_not_crash():
    """The last row's window ends 8.7e-19 s past the motion (0.005 s): a rounding unit."""
    lens = Lens(12.5, 1.4, 20.0, 16, 12, shutter="rolling", line_time_us=30.0)
    camera = Camera(lens, Profile([0.0, 0.005], [12.6, 12.9]))
    scene = Scene.from_depth(np.ones((12, 16)), np.full((12, 16), 800.0))
    out = simulate.render(scene, camera, plan_=simulate.plan(scene, camera))
    assert np.all(np.isfinite(out))


def plan_peak_bytes(rows: int) -> int:
    radiance, depth, camera = small_rolling(rows, cols=16)
    scene = Scene.from_depth(radiance, depth)
    tracemalloc.start()
    try:
        simulate.plan(scene, camera, tolerance=1e-2)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_rolling_shutter_memory_linear_in_the_image():
    """A 2x16 / 4x16 px capture: at most 100 MB, and at most 5 MB per added row (before
    issue 14's fix 190 MB and +27 MB per row, i.e. 52 GB for the paper's 1944 rows)."""
    small, large = plan_peak_bytes(2), plan_peak_bytes(4)
    assert small < 100e6, small
    assert (large - small) / 2 < 5e6, (small, large)


@functools.cache
def depth_down_the_rows_rolling():
    """8 mm f/2 rolling capture (0.4 ms/row, 4 ms rows) sweeping 2000 -> 400 mm over a
    surface from 1800 mm (top) to 450 mm (bottom): each row's window crosses focus."""
    rows, cols, line, exposure = 16, 32, 4e-4, 4e-3
    lens = Lens(8.0, 2.0, 20.0, cols, rows, shutter="rolling", line_time_us=line * 1e6)
    duration = (rows - 1) * line + exposure
    v = functools.partial(refcases.v, lens=lens)
    camera = Camera(lens, Profile([0.0, duration], [v(2000.0), v(400.0)]), row_exposure_s=exposure)
    t = np.indices((rows, cols))[0] / (rows - 1)
    depth = 1.0 / (1 / 1800.0 + (1 / 450.0 - 1 / 1800.0) * t)
    radiance = refcases.texture((rows, cols), 2)
    ref = smooth.render_smooth(
        radiance, depth, f_mm=lens.focal_length_mm, f_number=lens.f_number,
        pitch_mm=lens.pixel_pitch_mm, times_s=camera.motion.times_s,
        positions_mm=camera.motion.image_distances_mm, p_ref_mm=camera.reference_mm,
        row_windows=camera.row_windows(rows), n_time=256,
    )
    return Scene.from_depth(radiance, depth), camera, ref, float(np.std(radiance))


def test_a_row_whose_window_crosses_focus_is_not_one_layer():
    """Both ends of the depth range had one kernel (blurred alike on either side of focus),
    so row 6 was rendered with a single layer: 0.22 off the reference (estimate 0.013).
    Now every row is within 5x the tolerance."""
    scene, camera, ref, contrast = depth_down_the_rows_rolling()
    pl = simulate.plan(scene, camera, tolerance=1e-2)
    out = simulate.render(scene, camera, plan_=pl)
    per_row = np.sqrt(np.mean((out - ref) ** 2, axis=1)) / contrast
    assert min(len(b.layers) for b in pl.bands) > 1
    assert per_row.max() <= 5 * pl.tolerance


@pytest.mark.parametrize("tol", [1e-2, 1e-3])
def test_depth_down_the_rows_rolling_within_estimate(tol):
    """Was a ~0.007 error floor that no estimate saw (1e-3: measured 8.2e-3, estimate
    2.9e-3): the hat-layer blend was checked only at the depth nearest the middle of each
    interval, but where a row's window sweeps through focus it is worst next to an end.

    Then the estimate was low at 1e-2 (measured 0.0137, estimate 0.0079 layers + 0.0034
    magnification): rows 0 and 1 were off by a mean offset (0.029, -0.025 per unit
    contrast), row 1's light (and its mirror image above row 0) reaching row 0 through
    the kernel of row 0's lowest representative. Where the depth changes within a kernel
    the gathered error kernel need not sum to 0, so the mean radiance is rendered with a
    gain error no single-depth ``kernel_error`` sees; ``planner._Gain`` computes it and
    adds representatives where it exceeds the tolerance (1e-2: measured 0.0083,
    estimate 0.012; 1e-3: 9.4e-4, 1.2e-3)."""
    scene, camera, ref, contrast = depth_down_the_rows_rolling()
    pl = simulate.plan(scene, camera, tolerance=tol)
    out = simulate.render(scene, camera, plan_=pl)
    assert_estimate_holds(refcases.rel_rms(out, ref, contrast), pl.estimated_error)


def test_gain_error_is_the_rows_mean_error(monkeypatch):
    """Without the representatives it adds (1e-2), ``planner._Gain`` predicts each row's
    mean error (depth is constant along a row, so is the gain): 0.025 for 0.029 in row
    0, -0.023 for -0.025 in row 1; and the plan's estimate, which counts it, holds
    (0.0158 for 0.0137)."""
    seen = {}
    error = simulate.planner._Gain.error

    def record(self, r0, r1, layers, **kw):
        value, _ = error(self, r0, r1, layers, **kw)
        seen[r0] = value
        return value, None  # no added representative

    monkeypatch.setattr(simulate.planner._Gain, "error", record)
    scene, camera, ref, contrast = depth_down_the_rows_rolling()
    pl = simulate.plan(scene, camera, tolerance=1e-2)
    out = simulate.render(scene, camera, plan_=pl)
    mean = np.abs(np.mean(out - ref, axis=1)) / contrast
    big = [r for r in seen if seen[r] > 0.005]
    assert len(big) >= 4
    for r in big:
        assert 0.7 * mean[r] <= seen[r] <= 1.3 * mean[r], (r, seen[r], mean[r])
    assert_estimate_holds(refcases.rel_rms(out, ref, contrast), pl.estimated_error)

def test_rolling_estimate_combines_the_rows_as_an_rms():
    """Each band's estimate bounds its rows' RMS error, so the image's is their row-weighted
    RMS; the maximum over 12 one-row bands was 2.2x the measured error, now 1.25x."""
    rows = 12
    radiance, pl, out, ref = rolling_render_and_reference(rows)
    measured = refcases.rel_rms(out, ref, float(np.std(radiance)))
    assert measured <= pl.estimated_error <= 2 * measured
