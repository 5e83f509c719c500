"""Motion planners (Sec. 4-7): Eq. 9 round trips, the paper's example, feasibility errors."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.core import motion, optics
from pipeline.errors import InputError
from pipeline.io.profiles import load_lens

ROLLING = load_lens("fujinon-12.5mm-f1.4-micron-1-2.5in")
GLOBAL = load_lens("fujinon-12.5mm-f1.4-sony-1-3in")
F = 12.5


def _row_times(lens, exposure_s=0.0):
    return np.arange(lens.height_px) * lens.line_time_us * 1e-6 + 0.5 * exposure_s


def _traced_plane(lens, profile, exposure_s=0.0):
    """Ray-trace every row: its in-focus depth and scene height along its chief ray.

    Row r (centre ``y`` below the axis) is at ``p(t_r)``; its conjugate is
    ``u = f p / (p - f)`` (Eq. 1) and the chief ray through the lens centre gives
    the scene height ``Y = -y u / p``. Returns the fitted slope du/dY and u at Y=0.
    """
    p = profile.position(_row_times(lens, exposure_s))
    y = (np.arange(lens.height_px) - 0.5 * (lens.height_px - 1)) * lens.pixel_pitch_mm
    u = F * p / (p - F)
    height = -y * u / p
    slope, intercept = np.polyfit(height, u, 1)
    residual = np.abs(np.polyval([slope, intercept], height) - u).max()
    return slope, intercept, residual


def test_paper_example_detector_tilt():
    # Sec. 6: 70 ms read-out, 2.7 mm/s -> "a detector tilt of 2.6 deg" on the 1/2.5" CMOS
    assert ROLLING.readout_time_s == pytest.approx(0.070, rel=1e-3)
    theta = optics.detector_tilt_deg(2.7, ROLLING.readout_time_s, ROLLING.sensor_height_mm)
    assert theta == pytest.approx(2.6, abs=0.1)  # we get 2.53 deg with H = 1944 x 2.2 um


def test_paper_example_53_degrees_at_top_speed():
    # Sec. 6: the 53 deg table top was reached at 2.7 mm/s. Eq. 9 with p(0) near
    # v(390 mm) gives 53 deg for that speed; the planner must need about that speed.
    plan = motion.plan_tilted_dof(ROLLING, 53.0, 390.0)
    speed = plan.max_speed_mm_s
    assert speed == pytest.approx(2.7, abs=0.05)
    theta = optics.detector_tilt_deg(speed, plan.exposure_s, ROLLING.sensor_height_mm)
    assert theta == pytest.approx(2.5, abs=0.1)


@settings(max_examples=40, deadline=None)
@given(
    phi=st.floats(-60.0, 60.0).filter(lambda a: abs(a) > 0.5),
    through=st.floats(300.0, 5000.0),
)
def test_eq9_round_trip_angle_speed_angle(phi, through):
    lens = dataclasses.replace(ROLLING, max_speed_mm_s=math.inf, travel_mm=math.inf)
    plan = motion.plan_tilted_dof(lens, phi, through)
    speed = (plan.end_mm - plan.start_mm) / plan.exposure_s
    height = (lens.height_px - 1) * lens.pixel_pitch_mm
    theta = optics.detector_tilt_deg(speed, lens.readout_time_s, height)  # Eq. 9
    back = optics.focal_plane_tilt_deg(F, plan.start_mm, height, theta)  # Eq. 9
    assert back == pytest.approx(phi, abs=1e-9)


@pytest.mark.parametrize(("phi", "through", "exposure"), [(30.0, 600.0, 0.0), (-45.0, 400.0, 0.01)])
def test_tilted_plan_matches_ray_tracing(phi, through, exposure):
    plan = motion.plan_tilted_dof(ROLLING, phi, through, exposure_s=exposure)
    slope, u_centre, residual = _traced_plane(ROLLING, plan, exposure)
    assert math.degrees(math.atan(slope)) == pytest.approx(phi, abs=1e-6)
    assert u_centre == pytest.approx(through, rel=1e-9)
    assert residual < 1e-6 * through  # the rows' conjugates lie on one plane
    assert plan.exposure_s == pytest.approx(ROLLING.readout_time_s + exposure)


def test_tilted_too_fast_names_speed_and_largest_tilt():
    with pytest.raises(InputError, match=r"max_speed_mm_s=2\.7.*largest tilt there is \+-5[23]"):
        motion.plan_tilted_dof(ROLLING, 70.0, 390.0)


def test_tilted_beyond_eq9_limit():
    lens = dataclasses.replace(ROLLING, max_speed_mm_s=math.inf)
    # tan(phi) must stay below 2 f / H = 5.85 (phi < 80.3 deg)
    with pytest.raises(InputError, match=r"plane_tilt_deg=85.*infeasible"):
        motion.plan_tilted_dof(lens, 85.0, 1000.0)


def test_tilted_needs_rolling_shutter():
    with pytest.raises(InputError, match="rolling shutter"):
        motion.plan_tilted_dof(GLOBAL, 10.0, 500.0)


def test_tilted_row_image_distances_solve_the_chief_ray():
    # independent: bisection of u = U + Y tan(phi), Y = -y u / p(u)
    phi, through = 40.0, 800.0
    offsets = np.linspace(-2.0, 2.0, 7)
    p = motion.tilted_row_image_distances(F, phi, through, offsets)
    for y, p_row in zip(offsets, p):
        def gap(u, y=y):
            return u - (through - y * u / (F * u / (u - F)) * math.tan(math.radians(phi)))

        lo, hi = 20.0, 1e5
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if gap(lo) * gap(mid) > 0 else (lo, mid)
        u = 0.5 * (lo + hi)
        assert p_row == pytest.approx(F * u / (u - F), rel=1e-10)


def test_extended_dof_is_the_paper_sweep():
    plan = motion.plan_extended_dof(GLOBAL, 446.53, math.inf, 0.36)
    assert plan.start_mm == pytest.approx(12.5)
    assert plan.end_mm == pytest.approx(12.86, abs=1e-4)
    assert plan.max_speed_mm_s == pytest.approx(1.0, abs=3e-4)


def test_extended_dof_infeasible():
    with pytest.raises(InputError, match=r"max_speed_mm_s=2\.7.*exposure_s >= 0\.30"):
        motion.plan_extended_dof(GLOBAL, 200.0, math.inf, 0.1)
    short = dataclasses.replace(GLOBAL, travel_mm=0.1)
    with pytest.raises(InputError, match=r"travel_mm=0\.1"):
        motion.plan_extended_dof(short, 446.53, math.inf, 10.0)
    with pytest.raises(InputError, match="empty"):
        motion.plan_extended_dof(GLOBAL, 500.0, 500.0, 1.0)
    with pytest.raises(InputError, match="near <= far"):
        motion.plan_extended_dof(GLOBAL, 900.0, 500.0, 1.0)
    with pytest.raises(InputError, match="exposure_s"):
        motion.plan_extended_dof(GLOBAL, 500.0, 900.0, 0.0)


def _time_in(profile, lo, hi, n=400_001):
    t = np.linspace(profile.times_s[0], profile.times_s[-1], n)
    p = profile.position(t)
    return np.mean((p >= lo - 1e-12) & (p <= hi + 1e-12)) * profile.exposure_s


def test_discontinuous_time_shares_and_transits():
    ranges = [(2000.0, 2000.0), (450.0, 600.0)]  # a pause on the backdrop, a sweep on the toys
    plan = motion.plan_discontinuous_dof(GLOBAL, ranges, [1, 3], 0.36)
    v = [optics.image_distance(F, d) for d in (2000.0, 600.0, 450.0)]
    transit = (v[1] - v[0]) / GLOBAL.max_speed_mm_s
    dwell = 0.36 - transit
    assert plan.exposure_s == pytest.approx(0.36)
    assert plan.max_speed_mm_s == pytest.approx(GLOBAL.max_speed_mm_s)
    # independent: time the sampled motion spends on each target
    assert _time_in(plan, v[1], v[2]) == pytest.approx(0.75 * dwell, abs=2e-5)
    paused = [d for d, a, b in plan.segments() if a == b == pytest.approx(v[0])]
    assert sum(paused) == pytest.approx(0.25 * dwell)
    # the wire mesh in between gets only the transit
    mid = optics.image_distance(F, 1000.0)
    assert _time_in(plan, mid - 0.01, mid + 0.01) == pytest.approx(0.02 / 2.7, abs=2e-5)


def test_discontinuous_errors():
    with pytest.raises(InputError, match="overlap"):
        motion.plan_discontinuous_dof(GLOBAL, [(450, 700), (600, 900)], [1, 1], 0.36)
    with pytest.raises(InputError, match="one share per range"):
        motion.plan_discontinuous_dof(GLOBAL, [(450, 700)], [1, 1], 0.36)
    with pytest.raises(InputError, match="lengthen the exposure"):
        motion.plan_discontinuous_dof(GLOBAL, [(100, 100), (math.inf, math.inf)], [1, 1], 0.1)
    unlimited = dataclasses.replace(GLOBAL, max_speed_mm_s=math.inf)
    with pytest.raises(InputError, match="finite max_speed_mm_s"):
        motion.plan_discontinuous_dof(unlimited, [(450, 500), (900, 1000)], [1, 1], 0.36)
    plan = motion.plan_discontinuous_dof(unlimited, [(450, 500), (900, 1000)], [1, 1], 0.36,
                                         transit=50.0)
    assert plan.max_speed_mm_s == pytest.approx(50.0)
    with pytest.raises(InputError, match=r"needs .* mm/s"):  # the sweep itself is too fast
        motion.plan_discontinuous_dof(GLOBAL, [(100, math.inf)], [1], 0.1)


def test_nonplanar_profile_hits_the_knots():
    knots = [(0, 500.0), (972, 420.0), (1943, 500.0)]  # crayons on a semi-circle (Fig. 12)
    plan = motion.plan_nonplanar_dof(ROLLING, knots)
    lt = ROLLING.line_time_us * 1e-6
    for row, depth in knots:
        assert plan.position(row * lt) == pytest.approx(optics.image_distance(F, depth))
    # linear in the row between knots
    mid = plan.position(486 * lt)
    assert mid == pytest.approx(
        optics.image_distance(F, 500.0) + (optics.image_distance(F, 420.0)
                                          - optics.image_distance(F, 500.0)) * 486 / 972
    )


def test_nonplanar_per_row_array_and_exposure():
    depths = np.linspace(600.0, 700.0, ROLLING.height_px)
    exposure = 0.005
    plan = motion.plan_nonplanar_dof(ROLLING, depths, exposure_s=exposure)
    t0 = 1000 * ROLLING.line_time_us * 1e-6
    t = np.linspace(t0, t0 + exposure, 2001)
    assert plan.position(t).mean() == pytest.approx(optics.image_distance(F, depths[1000]))


def test_nonplanar_errors_name_rows():
    with pytest.raises(InputError, match=r"rows 972 -> 1943 need .* max_speed_mm_s"):
        motion.plan_nonplanar_dof(ROLLING, [(0, 500.0), (972, 420.0), (1943, 200.0)])
    with pytest.raises(InputError, match="integers in"):
        motion.plan_nonplanar_dof(ROLLING, [(0, 500.0), (5000, 420.0)])
    with pytest.raises(InputError, match="rows"):
        motion.plan_nonplanar_dof(ROLLING, np.full(10, 500.0))
    with pytest.raises(InputError, match="rolling shutter"):
        motion.plan_nonplanar_dof(GLOBAL, [(0, 500.0), (100, 600.0)])
    with pytest.raises(InputError, match="exceed the focal length"):
        motion.plan_nonplanar_dof(ROLLING, [(0, 5.0), (100, 600.0)])
