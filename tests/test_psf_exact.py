"""PSF values worked out by hand (issue 11, mutation kills of ``core/psf.py``).

Each expected value is computed here from the lens PSFs' definitions (Eq. 3: a disk of
diameter ``b`` with density ``4 / (pi b^2)``; Eq. 4: ``2 / (pi c^2) exp(-2 r^2 / c^2)``,
``c = g b``), never by the module's code path: stationary pieces (pauses), ``g != 1``,
mixed still and moving pieces, and the size and threshold edges.
"""

import math

import numpy as np
import pytest
from scipy import integrate

from pipeline.core import psf
from pipeline.core.lens import Lens
from pipeline.core.motion import Profile, constant_speed
from pipeline.errors import InputError

STILL = [(0.1, 4.0, 4.0)]  # a pause at a blur of 4 px


def test_a_still_pillbox_is_eq3():
    assert psf.ipsf_radial(1.0, STILL) == pytest.approx(1 / (4 * math.pi), rel=1e-12)
    assert psf.ipsf_radial(2.5, STILL) == 0.0  # outside the 2 px radius
    assert psf.encircled_energy(1.0, STILL) == pytest.approx(0.25, rel=1e-12)  # (1/2)^2
    assert psf.encircled_energy(1.5, STILL) == pytest.approx(0.5625, rel=1e-12)  # (3/4)^2
    assert psf.encircled_energy(3.0, STILL) == pytest.approx(1.0, rel=1e-12)


def test_a_still_gaussian_is_eq4_with_its_g():
    # g = 0.5: c = 2 px, density 2/(4 pi) exp(-2/4) at r = 1
    value = psf.ipsf_radial(1.0, STILL, model="gaussian", gaussian_g=0.5)
    assert value == pytest.approx(math.exp(-0.5) / (2 * math.pi), rel=1e-12)
    value = psf.ipsf_radial(1.5, STILL, model="gaussian", gaussian_g=0.5)
    assert value == pytest.approx(math.exp(-1.125) / (2 * math.pi), rel=1e-12)
    energy = psf.encircled_energy(1.0, STILL, model="gaussian", gaussian_g=0.5)
    assert energy == pytest.approx(1 - math.exp(-0.5), rel=1e-12)


def test_a_pause_and_a_moving_piece_average_by_time():
    # pillbox, rho = 1: the pause holds (1/2)^2 = 1/4 of its energy; the piece from b = 2
    # to 6 px holds (1/4) int_2^6 4/b^2 db = 1/3; weighted 0.2 : 0.1
    pieces = [(0.2, 4.0, 4.0), (0.1, 2.0, 6.0)]
    expected = (0.2 * 0.25 + 0.1 / 3) / 0.3
    assert psf.encircled_energy(1.0, pieces) == pytest.approx(expected, rel=1e-12)
    # density at r = 1: pause 1/(4 pi); moving (1/4) int_2^6 4/(pi b^2) db = 1/(3 pi)
    expected = (0.2 / (4 * math.pi) + 0.1 / (3 * math.pi)) / 0.3
    assert psf.ipsf_radial(1.0, pieces) == pytest.approx(expected, rel=1e-12)


def test_a_one_pixel_kernel_is_allowed():
    lens = Lens(12.5, 1.4, 4.65, 640, 480)
    profile = Profile([0.0, 0.1], [12.6, 12.7])
    for model in ("pillbox", "gaussian"):
        kernel = psf.integrated_psf(lens, 1000.0, profile, model=model, size=1)
        assert kernel.shape == (1, 1) and kernel[0, 0] == 1.0
        assert psf.lens_psf(lens, 1000.0, 12.7, model=model, size=1).tolist() == [[1.0]]
    for bad in (0, -1, 2, 1.0, True):
        with pytest.raises(InputError, match="positive odd integer"):
            psf.integrated_psf(lens, 1000.0, profile, size=bad)
    np.testing.assert_equal(psf.kernel_size(0.0), 3)


@pytest.mark.parametrize("model", ["pillbox", "gaussian"])
def test_small_blur_changes_match_a_fine_quadrature(model):
    """Below SMALL_CHANGE_PX a piece is the 6-node Gauss-Legendre mean of exact rasters;
    against a 0.01 px, 12-node quadrature of Eq. 5: ~1e-14 at b = 2-2.45 px and 2e-5
    (L1) at 1-1.49 px, where a 5-node rule is at 3e-12 and 1.1e-4."""
    for (b0, b1), tol in (((2.0, 2.45), 1e-13), ((1.0, 1.49), 5e-5)):
        kernel = psf._analytic_ipsf([(1.0, b0, b1)], 12, model, 1.0)
        fine = psf._numeric_ipsf([(1.0, b0, b1)], 12, model, 1.0, order=12, step_px=0.01)
        assert np.abs(kernel - fine).sum() < tol


@pytest.mark.parametrize("model", ["pillbox", "gaussian"])
def test_a_blur_change_of_1e_12_px_is_a_pause(model):
    """The closed forms divide by the blur change: a change at round-off level is taken
    as a pause (Eq. 3 / Eq. 4 at the mean blur), not as 0/0 of two near-equal terms."""
    tiny = [(0.1, 4.0, 4.0 + 1e-12)]
    for r in (0.5, 1.0, 1.9):
        still = psf.ipsf_radial(r, STILL, model=model, gaussian_g=0.5)
        assert psf.ipsf_radial(r, tiny, model=model, gaussian_g=0.5) == pytest.approx(
            still, rel=1e-9
        )
        still = psf.encircled_energy(r, STILL, model=model, gaussian_g=0.5)
        assert psf.encircled_energy(r, tiny, model=model, gaussian_g=0.5) == pytest.approx(
            still, rel=1e-9
        )


def test_kernel_sizes_hold_the_disk_or_four_sigma():
    # pillbox: radius b/2 plus the pixel it touches; Gaussian: radius 2 g b (4 sigma)
    assert psf.kernel_size(10.0) == 13  # 2 ceil(5 + 0.5) + 1
    assert psf.kernel_size(10.0, model="gaussian") == 43  # 2 ceil(20 + 0.5) + 1
    assert psf.kernel_size(10.0, model="gaussian", gaussian_g=0.5) == 23
    assert psf.kernel_size(0.0, model="gaussian") == 3


def test_kernel_size_refuses_negative_and_non_finite_blurs():
    for bad in (-0.5, -1e-9, float("nan"), float("inf")):
        with pytest.raises(InputError, match="max_blur_px"):
            psf.kernel_size(bad)


def test_the_default_polar_rule_resolves_a_gaussian_ipsf_to_round_off():
    """8 Gauss-Legendre nodes per angular piece (the default) against 24: 2e-12 (L1) on
    the Sec. 4.1 sweep's Gaussian IPSF; 7 nodes are at 5e-11."""
    lens = Lens(12.5, 1.4, 4.65, 1024, 768, psf_model="gaussian")
    sweep = constant_speed(12.5, 1.0, 0.36)
    reference = psf.integrated_psf(lens, 1000.0, sweep, theta_order=24)
    assert np.abs(psf.integrated_psf(lens, 1000.0, sweep) - reference).sum() < 1e-11


@pytest.mark.parametrize("model", ["pillbox", "gaussian"])
def test_on_small_changes_both_methods_compute_the_same_sum(model):
    """A piece whose blur changes by less than SMALL_CHANGE_PX = the numeric method's
    0.5 px step is one Gauss-Legendre interval in both methods: the same kernel."""
    for b0, b1 in ((6.8, 7.25), (19.8, 20.25), (3.0, 2.6)):
        analytic = psf._analytic_ipsf([(1.0, b0, b1)], 12, model, 1.0)
        numeric = psf._numeric_ipsf([(1.0, b0, b1)], 12, model, 1.0)
        assert np.abs(analytic - numeric).max() < 1e-15


def test_sub_pixel_and_in_focus_pauses():
    # b = 0.5 px: (rho / 0.25)^2 of the energy within rho < 0.25
    assert psf.encircled_energy(0.1, [(1.0, 0.5, 0.5)]) == pytest.approx(0.16, rel=1e-12)
    # b = 0 (in focus): a point, all its energy within any radius
    assert psf.encircled_energy(0.01, [(1.0, 0.0, 0.0)]) == 1.0


@pytest.mark.parametrize("model", ["pillbox", "gaussian"])
def test_a_truncated_kernel_keeps_its_outer_ring(model):
    """size=7 for a blur of 46-53 px: the kernel is flat out to its edge, which both
    methods must integrate alike (the analytic one mirrors an octant out to the edge)."""
    lens = Lens(12.5, 1.4, 4.65, 1024, 768)
    profile = Profile([0.0, 0.1], [12.5, 12.55])
    analytic = psf.integrated_psf(lens, 450.0, profile, model=model, size=7)
    numeric = psf.integrated_psf(lens, 450.0, profile, model=model, size=7, method="numeric")
    assert analytic[0, 3] > analytic[3, 3] * 0.5  # the ring holds real energy
    assert np.abs(analytic - numeric).sum() < 1e-3


@pytest.mark.parametrize("model", ["pillbox", "gaussian"])
def test_numeric_sub_intervals_are_the_step_wide(model):
    """A 2 px blur change with 0.5 px steps is four sub-intervals: the same kernel as the
    piece cut into its four 0.5 px quarters (three sub-intervals differ by 3e-6-7e-4)."""
    whole = psf._numeric_ipsf([(1.0, 0.2, 2.2)], 6, model, 1.0, step_px=0.5)
    quarters = [(0.25, 0.2 + 0.5 * i, 0.7 + 0.5 * i) for i in range(4)]
    cut = psf._numeric_ipsf(quarters, 6, model, 1.0, step_px=0.5)
    assert np.abs(whole - cut).max() < 1e-12  # round-off of the nodes' positions
    three = psf._numeric_ipsf([(1.0, 0.2, 2.2)], 6, model, 1.0, step_px=2 / 3)
    assert np.abs(whole - three).sum() > 1e-6


def test_rasters_of_a_zero_blur_are_unit_deltas():
    for raster in (psf.raster_pillbox(0.0, 3), psf.raster_gaussian(0.0, 3),
                   psf.raster_lens_psf("gaussian", 1e-13, 2, g=0.5)):
        expected = np.zeros(raster.shape)
        expected[raster.shape[0] // 2, raster.shape[1] // 2] = 1.0
        assert np.array_equal(raster, expected)
    # half the time in focus, half at a 4 px blur: half the energy on the centre pixel
    kernel = psf._analytic_ipsf([(0.5, 0.0, 0.0), (0.5, 4.0, 4.0)], 3, "pillbox", 1.0)
    assert kernel.sum() == pytest.approx(1.0, rel=1e-12)
    assert kernel[3, 3] == pytest.approx(0.5 + 0.5 * psf.raster_pillbox(4.0, 3)[3, 3])


def test_through_focus_and_sub_pixel_pieces_near_the_centre():
    # a piece from b = 0 to 2 px: E(rho) = (1/2) int_0^2 min(1, 4 rho^2 / b^2) db
    # = 2 rho - rho^2 for rho < 1; the density at r < 1: (1/2)(4/pi)(1/(2r) - 1/2)
    through = [(1.0, 0.0, 2.0)]
    assert psf.encircled_energy(0.25, through) == pytest.approx(0.4375, rel=1e-12)
    assert psf.ipsf_radial(0.25, through) == pytest.approx(3 / math.pi, rel=1e-12)
    # a pause at b = 1 px: 4/pi inside r < 1/2, nothing outside
    assert psf.ipsf_radial(0.25, [(1.0, 1.0, 1.0)]) == pytest.approx(4 / math.pi, rel=1e-12)
    assert psf.ipsf_radial(0.6, [(1.0, 1.0, 1.0)]) == 0.0


@pytest.mark.parametrize("model", ["pillbox", "gaussian"])
def test_a_piece_not_through_focus_is_the_mean_of_its_lens_psfs(model):
    """A piece from b = 2 to 6 px (no zero blur), g = 0.5: the IPSF and its encircled
    energy are the averages over b of Eq. 3 / Eq. 4 and of their energies (quadrature)."""
    g = 0.5

    def density(b, r):
        if model == "pillbox":
            return 4 / (math.pi * b**2) if 2 * r < b else 0.0
        c = g * b
        return 2 / (math.pi * c**2) * math.exp(-2 * r**2 / c**2)

    def energy(b, rho):
        if model == "pillbox":
            return min(1.0, 4 * rho**2 / b**2)
        return 1 - math.exp(-2 * rho**2 / (g * b) ** 2)

    piece = [(0.3, 2.0, 6.0)]
    for r in (0.5, 1.5, 2.5):
        kink = [2 * r] if 2 < 2 * r < 6 else None
        expected = integrate.quad(density, 2.0, 6.0, args=(r,), points=kink)[0] / 4
        got = psf.ipsf_radial(r, piece, model=model, gaussian_g=g)
        assert got == pytest.approx(expected, rel=1e-9)
        expected = integrate.quad(energy, 2.0, 6.0, args=(r,), points=kink)[0] / 4
        got = psf.encircled_energy(r, piece, model=model, gaussian_g=g)
        assert got == pytest.approx(expected, rel=1e-9)
