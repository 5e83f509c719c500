"""Optics (Eqs. 1, 2, 9; Fig. 2) against the paper's numbers and ray tracing."""

import math

import numpy as np
import pytest

from pipeline.core import optics
from pipeline.errors import InputError

# Fig. 2, third column: detector translation in um.
FIG2 = [
    (9.0, 1000.0, math.inf, 81.7),
    (9.0, 500.0, math.inf, 164.9),
    (9.0, 200.0, 500.0, 259.1),
    (12.5, 1000.0, math.inf, 158.2),
    (12.5, 500.0, math.inf, 320.5),
    (12.5, 200.0, 500.0, 512.8),
]


@pytest.mark.parametrize(("f", "near", "far", "microns"), FIG2)
def test_fig2_translation_column(f, near, far, microns):
    # The paper truncates to 0.1 um (9 mm, 0.5 m - inf is 164.97 um, printed 164.9).
    assert math.floor(optics.sweep_translation(f, near, far) * 1e4) / 10 == microns


def test_sec41_sweep_end_depth():
    # p(0) = 12.5 mm, s = 1 mm/s, T = 0.36 s sweeps the focal plane from inf to 446.53 mm.
    assert optics.focus_distance(12.5, 12.5) == math.inf
    assert optics.focus_distance(12.5, 12.5 + 1.0 * 0.36) == pytest.approx(446.53, abs=0.005)


def test_lens_law_round_trip_and_infinity():
    u = np.array([13.0, 100.0, 450.0, 1e6])
    v = optics.image_distance(12.5, u)
    assert np.allclose(1 / v + 1 / u, 1 / 12.5)  # Eq. 1 checked directly
    assert np.allclose(optics.focus_distance(12.5, v), u)
    assert optics.image_distance(12.5, math.inf) == 12.5


@pytest.mark.parametrize("u", [12.5, 10.0, 0.0, -5.0])
def test_depth_at_or_inside_focal_length_is_an_error(u):
    with pytest.raises(InputError, match="focus_distance_mm"):
        optics.image_distance(12.5, u)


def test_nan_is_an_error():
    with pytest.raises(InputError, match="NaN"):
        optics.image_distance(12.5, float("nan"))


def test_blur_diameter_matches_similar_triangles():
    # A cone from an aperture a converging to v, cut at p: diameter a |v - p| / v.
    a, v = 8.93, 12.8
    for p in (12.5, 12.8, 13.1):
        cut = a * abs(v - p) / v
        assert optics.blur_diameter_mm(a, v, p) == pytest.approx(cut)
    assert optics.blur_diameter_mm(a, v, v) == 0.0


def test_image_position_change_matches_chief_ray_trace():
    f, near, far = 12.5, 500.0, math.inf
    pitch, w, h = 4.65, 1024, 768
    corner_mm = 0.5 * math.hypot(w, h) * pitch * 1e-3
    p_far = optics.image_distance(f, far)
    p_near = optics.image_distance(f, near)
    # The chief ray to the corner at p_far keeps its angle; at p_near it lands farther out.
    angle = math.atan(corner_mm / p_far)
    shift_px = (p_near * math.tan(angle) - corner_mm) / (pitch * 1e-3)
    got = optics.image_position_change_px(
        f, near, far, width_px=w, height_px=h
    )
    assert got == pytest.approx(shift_px)


def test_depth_of_field_limits_have_blur_equal_to_coc():
    f, n, focus, coc = 12.5, 1.4, 750.0, 0.0141
    near, far = optics.depth_of_field(f, n, focus, coc)
    p = optics.image_distance(f, focus)
    for limit in (near, far):
        b = optics.blur_diameter_mm(f / n, optics.image_distance(f, limit), p)
        assert b == pytest.approx(coc, rel=1e-9)
    assert near < focus < far
    # Stopping down only widens it; a huge CoC reaches infinity.
    near8, far8 = optics.depth_of_field(f, 8.0, focus, coc)
    assert near8 < near and far8 > far
    assert optics.depth_of_field(f, 8.0, focus, 1.0)[1] == math.inf


def test_eq9_paper_example_detector_tilt():
    # 1/2.5" CMOS, 1944 rows of 2.2 um, 70 ms read-out, 2.7 mm/s: about 2.6 degrees.
    theta = optics.detector_tilt_deg(2.7, 0.070, 1944 * 2.2e-3)
    assert theta == pytest.approx(2.6, abs=0.1)


@pytest.mark.parametrize("p0", [12.6, 12.82, 13.5])
@pytest.mark.parametrize("speed", [0.5, 2.7, -1.0])
def test_eq9_matches_ray_traced_focal_plane(p0, speed):
    f, h, readout = 12.5, 4.2768, 0.070
    theta = optics.detector_tilt_deg(speed, readout, h)
    phi = optics.focal_plane_tilt_deg(f, p0, h, theta)
    # Rows from y=-H/2 (exposed first, at p0) to +H/2; trace the conjugate of both end rows.
    y = np.array([-h / 2, h / 2])
    p = p0 + speed * readout * (y + h / 2) / h
    u = f * p / (p - f)
    height = -y * u / p  # chief ray through the lens centre
    # Angle with the lens plane; positive when the first row's conjugate is the farther one.
    traced = math.degrees(math.atan2(u[0] - u[1], height[0] - height[1]))
    assert phi == pytest.approx(traced, abs=1e-9)


@pytest.mark.parametrize("phi", [-40.0, 5.0, 53.0, 70.0])
def test_eq9_round_trip(phi):
    f, p0, h, readout = 12.5, 12.82, 4.2768, 0.070
    speed = optics.speed_for_focal_plane_tilt(f, p0, h, readout, phi)
    theta = optics.detector_tilt_deg(speed, readout, h)
    assert optics.focal_plane_tilt_deg(f, p0, h, theta) == pytest.approx(phi, abs=1e-9)


def test_unreachable_tilt_is_an_error():
    with pytest.raises(InputError, match="unreachable"):
        optics.speed_for_focal_plane_tilt(12.5, 12.82, 4.2768, 0.07, 89.9)
