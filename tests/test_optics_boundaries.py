"""optics at the edges of its domain (mutation survivors): every check on both sides."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.core import optics
from pipeline.errors import InputError


def test_scalars_in_floats_out_arrays_in_arrays_out():
    assert type(optics.image_distance(50.0, 1000.0)) is float
    assert type(optics.focus_distance(50.0, 60.0)) is float
    out = optics.image_distance(50.0, np.array([1000.0, 2000.0]))
    assert isinstance(out, np.ndarray) and out.shape == (2,)
    one = optics.focus_distance(50.0, np.array([60.0]))
    assert isinstance(one, np.ndarray) and one.shape == (1,)
    assert type(optics.blur_diameter_mm(25.0, 52.0, 51.0)) is float


@pytest.mark.parametrize("v", [49.999, 10.0])
def test_image_distance_inside_f_is_an_error(v):
    with pytest.raises(InputError, match="image_distance_mm"):
        optics.focus_distance(50.0, v)
    with pytest.raises(InputError, match="image_distance_mm"):
        optics.focus_distance(50.0, np.array([60.0, v]))


@pytest.mark.parametrize(("near", "far"), [(1000.0, 1000.0), (2000.0, 1000.0)])
def test_sweep_needs_near_before_far(near, far):
    with pytest.raises(InputError, match="near_mm must be < far_mm"):
        optics.sweep_translation(50.0, near, far)
    assert optics.sweep_translation(50.0, 1000.0, math.inf) == pytest.approx(
        1 / (1 / 50 - 1 / 1000) - 50.0, rel=1e-12
    )


def _tilt_denominator(f, p0, h, theta_deg):
    return 2 * p0 + h * math.tan(math.radians(theta_deg)) - 2 * f


def test_focal_plane_tilt_on_both_sides_of_a_vanishing_denominator():
    f, h = 10.0, 4.0
    # theta = -45 deg: denominator 2 p0 - 4 - 20 -> zero at p0 = 12
    with pytest.raises(InputError, match="focal length"):
        optics.focal_plane_tilt_deg(f, 12.0, h, -45.0)  # exactly 0
    with pytest.raises(InputError, match="focal length"):
        optics.focal_plane_tilt_deg(f, 11.0, h, -45.0)  # negative
    assert _tilt_denominator(f, 12.25, h, -45.0) == pytest.approx(0.5)
    phi = optics.focal_plane_tilt_deg(f, 12.25, h, -45.0)  # 0 < denominator < 1
    assert phi == pytest.approx(math.degrees(math.atan(2 * f * -1.0 / 0.5)), rel=1e-9)


@pytest.mark.parametrize("p0", [10.0, 9.0])
def test_speed_for_tilt_needs_p0_beyond_f(p0):
    with pytest.raises(InputError, match="start_image_distance_mm"):
        optics.speed_for_focal_plane_tilt(10.0, p0, 4.0, 0.03, 10.0)


@pytest.mark.parametrize("phi", [90.0, -90.0, 120.0, -91.0])
def test_speed_for_tilt_refuses_tilts_outside_the_open_interval(phi):
    with pytest.raises(InputError, match="plane_tilt_deg must be in"):
        optics.speed_for_focal_plane_tilt(10.0, 10.5, 4.0, 0.03, phi)


@pytest.mark.parametrize("phi", [-89.0, -30.0, 0.0, 30.0])
def test_speed_for_tilt_inside_the_interval(phi):
    f, p0, h, t = 10.0, 10.5, 4.0, 0.03
    speed = optics.speed_for_focal_plane_tilt(f, p0, h, t, phi)
    theta = optics.detector_tilt_deg(speed, t, h) if speed else 0.0
    assert optics.focal_plane_tilt_deg(f, p0, h, theta) == pytest.approx(phi, abs=1e-6)


def test_speed_for_tilt_near_the_unreachable_limit():
    f, p0, h, t = 10.0, 10.5, 4.0, 0.03
    # denominator 2f - H tan(phi) = 0.5: reachable (a steep but finite detector tilt)
    phi = math.degrees(math.atan((2 * f - 0.5) / h))
    speed = optics.speed_for_focal_plane_tilt(f, p0, h, t, phi)
    tan_theta = math.tan(math.radians(phi)) * (2 * p0 - 2 * f) / 0.5
    assert speed == pytest.approx(h * tan_theta / t, rel=1e-9)
    with pytest.raises(InputError, match=r"needs tan\(phi\) < 2f/H = 5\.000"):
        optics.speed_for_focal_plane_tilt(f, p0, h, t, math.degrees(math.atan(5.5)))
    # just past the limit: denominator -0.5
    with pytest.raises(InputError, match="unreachable"):
        optics.speed_for_focal_plane_tilt(f, p0, h, t, math.degrees(math.atan((2 * f + 0.5) / h)))


# ----------------------------------------------------------------------------- issue 11
def test_image_distance_equal_to_f_is_focus_at_infinity():
    assert optics.focus_distance(50.0, 50.0) == math.inf
    np.testing.assert_array_equal(optics.focus_distance(50.0, np.array([50.0, 100.0])),
                                  [math.inf, 100.0])  # 1/50 = 1/100 + 1/100
    assert optics.image_distance(50.0, math.inf) == 50.0


def _thin_lens_u(f, v):
    return 1.0 / (1.0 / f - 1.0 / v)


@pytest.mark.parametrize("ratio", [0.3, 0.6, 0.9, 0.999])
def test_dof_near_limit_on_both_sides_of_its_branch(ratio):
    """Blur ``a |v - p| / v <= c``: the near limit is at ``v = p a / (a - c)`` when c < a."""
    f, n, u = 50.0, 2.0, 3000.0
    a = f / n
    c = ratio * a
    p = 1.0 / (1.0 / f - 1.0 / u)
    near, far = optics.depth_of_field(f, n, u, c)
    v_near = p * a / (a - c)
    assert near == pytest.approx(_thin_lens_u(f, v_near), rel=1e-9)
    blur_at_near = a * abs(v_near - p) / v_near
    assert blur_at_near == pytest.approx(c, rel=1e-9)
    assert far == math.inf or far > u


@pytest.mark.parametrize("ratio", [1.0, 1.5])
def test_dof_near_limit_is_the_lens_when_the_coc_reaches_the_aperture(ratio):
    f, n = 50.0, 2.0
    near, _ = optics.depth_of_field(f, n, 3000.0, ratio * f / n)
    assert near == f
