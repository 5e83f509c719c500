"""The render planner's internals (``pipeline.core.simulate.planner``) against computations
made here independently: small cases worked out by hand, full-plane FFTs of the kernel
metric (the planner uses half-plane real FFTs and separable sums), direct sums over the
frequency grid, and a brute-force per-pixel gather of the mean-radiance (gain) error.

The renders the unit suite checks stay within tolerance when the plan's estimates are
off; these tests pin the estimates themselves (helper mut-planner, issue 11,
tests/mutation/README.md).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from pipeline.core import psf, simulate
from pipeline.core.lens import Lens
from pipeline.core.motion import Profile
from pipeline.core.scene import Scene, Surface

planner = simulate.planner

# 12.5 mm f/1.4 with coarse 20 um pixels: blurs of a few pixels (small kernels, fast)
LENS = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=20.0, width_px=40, height_px=24)
F = 12.5


def _static(p_mm: float, t: float = 0.01) -> Profile:
    return Profile([0.0, t], [p_mm, p_mm])


def _full_plane_error(spectrum: np.ndarray) -> float:
    """``sqrt(sum |X|^2 S / sum S)`` over the whole ``n x n`` plane, ``S = 1/|w|^2`` (w in
    cycles/px) with the DC term given ``1/n^2`` (the metric of ``kernel_error``, written
    out here on the full plane instead of the planner's half-plane)."""
    n = spectrum.shape[0]
    fy = np.fft.fftfreq(n)[:, None]
    fx = np.fft.fftfreq(n)[None, :]
    w2 = fy**2 + fx**2
    w2[0, 0] = 1.0 / n**2
    s = 1.0 / w2
    return float(np.sqrt(np.sum(np.abs(spectrum) ** 2 * s) / np.sum(s)))


def _fft(kernel: np.ndarray, n: int) -> np.ndarray:
    """Full-plane FFT of an odd ``kernel`` rolled so that its centre pixel is at (0, 0) of
    the ``n x n`` grid (the transfer function of convolving with it)."""
    size = kernel.shape[0]
    grid = np.zeros((n, n))
    grid[:size, :size] = kernel
    return np.fft.fft2(np.roll(grid, (-(size // 2), -(size // 2)), axis=(0, 1)))


def _phase(n: int, dx: float, dy: float) -> np.ndarray:
    fy = np.fft.fftfreq(n)[:, None]
    fx = np.fft.fftfreq(n)[None, :]
    return np.exp(-2j * np.pi * (fx * dx + fy * dy))


# ----------------------------------------------------------------------------- the grid
def test_grid_is_the_smallest_power_of_two_holding_a_kernel_difference():
    """``_grid(s)`` (the metric's grid for kernels of ``s`` px) is a power of two, at
    least 256 and at least ``2 s - 1`` (a difference of two ``s``-px kernels does not wrap
    around), and half of it is not: checked for every odd size to 1025 (by hand: 129 px
    -> 512, the first size beyond 256; 257 px -> 1024)."""
    assert planner._grid(1) == 256
    assert planner._grid(127) == 256 and planner._grid(129) == 512
    assert planner._grid(255) == 512 and planner._grid(257) == 1024
    for s in range(1, 1027, 2):
        n = planner._grid(s)
        need = max(256, 2 * s - 1)
        assert n & (n - 1) == 0 and n >= need and n // 2 < need, s


def test_kernel_error_of_a_wide_kernel_is_measured_on_the_larger_grid():
    """``kernel_error`` of two 129 px kernels equals the full-plane metric on a 512 grid
    (on 256 their difference would wrap around)."""
    a = psf.raster_pillbox(120.0, 64)
    b = psf.raster_pillbox(90.0, 64)
    want = _full_plane_error(_fft(a, 512) - _fft(b, 512))
    assert planner.kernel_error(a, b) == pytest.approx(want, rel=1e-9)


# ----------------------------------------------------------------------------- finite scenes
def _mean_inverse_power(rows: int, cols: int) -> float:
    """Mean of ``1/|w|^2`` over the non-zero frequencies, by a plain loop over the rows of
    the frequency grid (the planner sums in blocks of 256 rows)."""
    fy = np.fft.fftfreq(rows)
    fx = np.fft.fftfreq(cols)
    total = 0.0
    for i, y in enumerate(fy):
        w2 = y**2 + fx**2
        if i == 0:
            w2 = w2[1:]  # drop the DC term
        total += float(np.sum(1.0 / w2))
    return total / (rows * cols - 1)


@pytest.mark.parametrize(("shape", "documented"), [((16, 32), 1.31), ((48, 64), 1.18),
                                                   ((256, 256), 1.0), ((300, 21), None)])
def test_finite_scene_factor_is_the_ratio_of_mean_inverse_powers(shape, documented):
    """``_finite_scene_factor(shape, 256)`` is ``sqrt(mean_256(1/|w|^2) /
    mean_shape(1/|w|^2))`` with the means summed here row by row (300 rows: two of the
    planner's 256-row blocks), and the values its docstring states (1.31 for 16x32 px,
    1.18 for 48x64, 1 for 256x256)."""
    want = math.sqrt(_mean_inverse_power(256, 256) / _mean_inverse_power(*shape))
    got = planner._finite_scene_factor(shape, 256)
    assert got == pytest.approx(want, rel=1e-12)
    if documented is not None:
        assert got == pytest.approx(documented, abs=0.005)


# ----------------------------------------------------------------------------- partitions
def test_partition_of_a_line_worked_out_by_hand():
    """``_partition`` with ``dist = |a - b|`` on ``[0, 1]``, scene values 0, 0.1, 0.35,
    0.4, 1 and ``tol = 0.3`` (refine while a half exceeds 0.1, grow parts to 0.2).

    Bisection (an interval is split while a scene value lies strictly inside and
    ``max(dist(a, b), dist(a, m)) > 0.1``) adds 0.5, 0.25, 0.375, 0.4375, 0.3125, 0.125,
    0.0625; it stops at (0.375, 0.4375), (0.3125, 0.375), (0.0625, 0.125) with 0.0625 (the
    gap). Greedy parts: from 0, the representative is the last sample within 0.2 (0.125),
    the end the last within 0.2 of it (0.3125, worst 0.1875); the next part starts at the
    last sample below the next scene value 0.35 or past the end (0.375): representative
    and end 0.5; then 1. Error 0.1875 + 0.0625.
    """
    present = np.array([0.0, 0.1, 0.35, 0.4, 1.0])
    parts, err, xs = planner._partition(present, 0.0, 1.0, lambda a, b: abs(a - b), 0.3,
                                        integer=False)
    assert parts == [(0.3125, 0.125), (0.5, 0.5), (1.0, 1.0)]
    assert err == pytest.approx(0.25, abs=1e-15)
    np.testing.assert_array_equal(
        xs, [0.0, 0.0625, 0.125, 0.25, 0.3125, 0.375, 0.4375, 0.5, 1.0])


def simulate_surface(depth):
    """A surface at ``depth`` (alpha 1; its radiance is not read)."""
    return Surface(np.zeros((*depth.shape, 1)), np.ones(depth.shape), depth)


def test_groups_merge_overlapping_and_touching_depth_ranges_only():
    """Surfaces in inverse depth (1/m): A 1-2, B 3-4, C 5-6, D 5.5-7 (overlaps C), E from
    D's farthest depth to 7.5 (touches D: the same depth value), F 9-9.5, given out of
    order. By hand: groups {A}, {B}, {C, D, E}, {F}; the present values split so."""
    ranges = {"A": (1e-3, 2e-3), "B": (3e-3, 4e-3), "C": (5e-3, 6e-3), "D": (5.5e-3, 7e-3),
              "E": (7e-3, 7.5e-3), "F": (9e-3, 9.5e-3)}
    surfaces = {k: simulate_surface(1.0 / np.linspace(lo, hi, 6)[None, :].repeat(4, 0))
                for k, (lo, hi) in ranges.items()}
    # E's nearest value is D's: the very same float depth, so the spans touch exactly
    d_depth = surfaces["D"].depth_mm
    e_depth = surfaces["E"].depth_mm.copy()
    e_depth[:, 0] = d_depth[0, -1]
    surfaces["E"] = simulate_surface(e_depth)
    order = ["F", "C", "A", "E", "B", "D"]
    scene = Scene(tuple(surfaces[k] for k in order), channels_axis=False)
    present = np.unique(np.concatenate([1.0 / s.depth_mm.ravel() for s in scene.surfaces]))
    groups = planner._groups(scene, present)

    def values(*names):
        return np.unique(np.concatenate([1.0 / surfaces[k].depth_mm.ravel() for k in names]))

    assert len(groups) == 4
    for got, names in zip(groups, (("A",), ("B",), ("C", "D", "E"), ("F",))):
        np.testing.assert_array_equal(got, values(*names))


def test_groups_ignore_the_depths_of_uncovered_pixels():
    """A surface's pixels with alpha 0 do not widen its range: B (3-4/m) has an uncovered
    column at 5.5/m, inside C's 5-6: still two groups."""
    a = simulate_surface(1.0 / np.linspace(3e-3, 4e-3, 6)[None, :].repeat(4, 0))
    depth = a.depth_mm.copy()
    depth[:, -1] = 1.0 / 5.5e-3
    alpha = np.ones(depth.shape)
    alpha[:, -1] = 0.0
    b = Surface(a.radiance, alpha, depth)
    c = simulate_surface(1.0 / np.linspace(5e-3, 6e-3, 6)[None, :].repeat(4, 0))
    scene = Scene((b, c), channels_axis=False)
    present = planner._present_inverse_depths(scene, LENS)
    groups = planner._groups(scene, present)
    assert [g.size for g in groups] == [5, 6]


def _bump(d, a, b):
    """A blend error worked out by hand: ``4 (d - a)(b - d) / (b - a)`` (0 at the
    representatives, ``b - a`` in the middle)."""
    return 4.0 * (d - a) * (b - d) / (b - a)


def test_hat_split_adds_representatives_until_every_blend_is_within_tol():
    """``_hat_split`` on representatives 0 and 1 (parts ending at 0.5 and 1), scene values
    0, 0.1, 0.3, 0.6, 1, samples 0, 0.5, 1, tol 0.5 and the blend error ``_bump``.

    By hand: on (0, 1) the targets are the middle and sample 0.5; the scene value nearest
    them is 0.6, error 0.96 > 0.5: added. (0.6, 1) holds no scene value. On (0, 0.6) the
    targets 0.3 and 0.5 are nearest 0.3, error 0.6: added. (0.3, 0.6) is empty; on (0,
    0.3) the middle 0.15 is nearest 0.1, error 4 (0.1)(0.2)/0.3 = 0.267: the check. The
    parts split halfway between the representatives: 0 up to 0.15, 0.3 up to 0.5 (the
    old end), 0.6 up to 0.8, 1 up to 1."""
    parts = [(0.5, 0.0), (1.0, 1.0)]
    present = np.array([0.0, 0.1, 0.3, 0.6, 1.0])
    samples = np.array([0.0, 0.5, 1.0])
    split, checks = planner._hat_split(parts, samples, present, _bump, 0.5)
    assert [r for _, r in split] == [0.0, 0.3, 0.6, 1.0]
    np.testing.assert_allclose([e for e, _ in split], [0.15, 0.5, 0.8, 1.0], rtol=1e-15)
    assert checks == [(0.1, 0.0, 0.3)]


def test_hat_split_checks_the_middle_and_the_samples_inside_each_interval_only():
    """The check depths of an interval are the scene values nearest its middle and its
    samples strictly inside it, not those nearest the samples at or beyond its ends: a
    blend error only at 0.05 (scene values 0.05, 0.5, 0.75 between representatives 0 and
    1) is not seen with samples 0, 1 (the check is 0.5), and is not a representative;
    a spike at 0.75 is seen with a sample at 0.8 (nearest 0.75) and becomes one."""
    parts = [(1.0, 0.0), (2.0, 1.0)]
    present = np.array([0.0, 0.05, 0.5, 0.75, 1.0])

    def spike_at(x):
        return lambda d, a, b: 1.0 if d == x else 0.0

    split, checks = planner._hat_split(parts, np.array([0.0, 1.0]), present, spike_at(0.05),
                                       0.5)
    assert split == parts and checks == [(0.5, 0.0, 1.0)]
    split, checks = planner._hat_split(parts, np.array([0.0, 0.8, 1.0]), present,
                                       spike_at(0.75), 0.5)
    assert [r for _, r in split] == [0.0, 0.75, 1.0]
    assert checks == [(0.5, 0.0, 0.75)]  # on (0, 0.75): the middle 0.375 is nearest 0.5


def test_forced_depths_at_a_groups_nearest_or_farthest_value_become_representatives():
    """``_layers`` adds the depth the gain error names as a representative (``forced``)
    even when it is the group's end value: two planes (1/500 and 1/480 per mm) within one
    layer at a loose tolerance (representative 1/480), a gain that names 1/500 until it
    is a representative. By hand: layers 1/500 up to halfway, 1/480 after; gain error 0."""
    lo, hi = 1.0 / 500.0, 1.0 / 480.0
    present = np.array([lo, hi])
    cache = planner._KernelCache(LENS, "pillbox", planner._Spectra(256))
    calls = []

    def gain(layers):
        reps = [layer.inv_rep for layer in layers]
        calls.append(reps)
        return (0.0, None) if lo in reps else (1.0, lo)

    layers, _, _, g_err = planner._layers([present], present, _static(12.8), cache, 0.5,
                                          hat=True, gain=gain)
    assert calls[0] == [hi]  # one layer without the gain
    assert [layer.inv_rep for layer in layers] == [lo, hi] and g_err == 0.0
    assert layers[0].inv_lo == -math.inf
    assert layers[0].inv_hi == pytest.approx(0.5 * (lo + hi), rel=1e-15)
    assert layers[1].inv_hi == hi


# ----------------------------------------------------------------------------- _hat_error
def _rms_radius(size: float) -> float:
    """RMS distance from the centre along an axis of ``size`` px (uniform), by quadrature."""
    from scipy import integrate

    return math.sqrt(integrate.quad(lambda x: x * x, -size / 2, size / 2)[0] / size)


def test_hat_error_is_the_interpolated_kernels_error_over_the_shifted_sub_steps():
    """``_hat_error`` against the full-plane metric of ``sum_s w_s (K_s(D) - sum_r c_r
    K_s(r)) exp(-2 pi i w . delta_s)``, with each sub-step's kernel computed here at pitch
    x scale and ``delta_s = (scale_s - 1) r``, ``r`` the RMS radius by quadrature.

    Two groups on a 20x40 px image, two sub-steps (scales ``1 -+ sqrt(12) / 20``: shifts
    of (-2, -1) and (2, 1) px, whole pixels, so that the phase at the Nyquist row and
    column, a convention for sub-pixel shifts, is +-1 in any convention; weights 0.3 and
    0.7, the detector at 12.85 and 12.95 mm). Group 0: scene depths 600, 560, 520, 500,
    470, 450 mm with representatives 520 and 470 (the farthest beyond, 600, keeps the
    520 kernel; 450 keeps 470); group 1: 300 and 280 mm, representative 300. One check:
    500 mm between 520 and 470 (hat weights by inverse depth). The estimate is the
    largest of the four; without the check, the largest of the three ends; with only the
    depths inside the representatives near the band's rows, the check's."""
    shape = (20, 40)
    g0 = np.sort(1.0 / np.array([600.0, 560.0, 520.0, 500.0, 470.0, 450.0]))
    g1 = np.sort(1.0 / np.array([300.0, 280.0]))
    layers = (simulate.Layer(-math.inf, 1 / 500.0, 1 / 520.0, 0),
              simulate.Layer(1 / 500.0, g0[-1], 1 / 470.0, 0),
              simulate.Layer(g0[-1], g1[-1], 1 / 300.0, 1))
    check = (1 / 500.0, 1 / 520.0, 1 / 470.0)
    k = math.sqrt(12) / 20
    steps = (planner.Step(_static(12.85), 1 - k, 0.3), planner.Step(_static(12.95), 1 + k, 0.7))
    cache = planner._KernelCache(LENS, "pillbox", planner._Spectra(256))
    near = np.concatenate([g0, g1])

    radius = np.array([_rms_radius(shape[1]), _rms_radius(shape[0])])  # (x, y)
    np.testing.assert_allclose((steps[1].scale - 1) * radius, [2.0, 1.0], rtol=1e-12)
    n = 256

    def kernel(inv, step):
        lens = dataclasses.replace(LENS, pixel_pitch_um=20.0 * step.scale)
        return psf.integrated_psf(lens, 1.0 / inv, step.profile, model="pillbox")

    def err(d, terms):
        total = np.zeros((n, n), complex)
        for s in steps:
            diff = _fft(kernel(d, s), n) - sum(c * _fft(kernel(r, s), n) for c, r in terms)
            total += s.weight * diff * _phase(n, *((s.scale - 1) * radius))
        return _full_plane_error(total)

    t = (check[0] - check[1]) / (check[2] - check[1])
    ends = [err(1 / 600.0, [(1.0, 1 / 520.0)]), err(1 / 450.0, [(1.0, 1 / 470.0)]),
            err(1 / 280.0, [(1.0, 1 / 300.0)])]
    middle = err(check[0], [(1 - t, check[1]), (t, check[2])])
    assert min(ends) > 0 and middle > 0
    got = planner._hat_error([g0, g1], near, layers, [check], steps, cache, shape)
    assert got == pytest.approx(max(*ends, middle), rel=1e-9)
    got = planner._hat_error([g0, g1], near, layers, [], steps, cache, shape)
    assert got == pytest.approx(max(ends), rel=1e-9)
    inner = near[(near >= 1 / 520.0) & (near <= 1 / 470.0)]
    got = planner._hat_error([g0, g1], inner, layers, [check], steps, cache, shape)
    assert got == pytest.approx(middle, rel=1e-9)
