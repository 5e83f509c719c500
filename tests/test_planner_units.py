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
from pipeline.core.scene import Camera, Scene, Surface

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
    D's farthest depth to 7.5 (touches D: the same depth value), F 9-9.5, G 9.1-9.3
    (inside F, the last span), given out of order. By hand: groups {A}, {B}, {C, D, E},
    {F, G}; the present values split so."""
    ranges = {"A": (1e-3, 2e-3), "B": (3e-3, 4e-3), "C": (5e-3, 6e-3), "D": (5.5e-3, 7e-3),
              "E": (7e-3, 7.5e-3), "F": (9e-3, 9.5e-3), "G": (9.1e-3, 9.3e-3)}
    surfaces = {k: simulate_surface(1.0 / np.linspace(lo, hi, 6)[None, :].repeat(4, 0))
                for k, (lo, hi) in ranges.items()}
    # E's nearest value is D's: the very same float depth, so the spans touch exactly
    d_depth = surfaces["D"].depth_mm
    e_depth = surfaces["E"].depth_mm.copy()
    e_depth[:, 0] = d_depth[0, -1]
    surfaces["E"] = simulate_surface(e_depth)
    order = ["F", "C", "G", "A", "E", "B", "D"]
    scene = Scene(tuple(surfaces[k] for k in order), channels_axis=False)
    present = np.unique(np.concatenate([1.0 / s.depth_mm.ravel() for s in scene.surfaces]))
    groups = planner._groups(scene, present)

    def values(*names):
        return np.unique(np.concatenate([1.0 / surfaces[k].depth_mm.ravel() for k in names]))

    assert len(groups) == 4
    for got, names in zip(groups, (("A",), ("B",), ("C", "D", "E"), ("F", "G"))):
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
    nor is one at 0.75; that is seen with a sample at 0.8 (nearest 0.75) and becomes one.
    A spike at 0.45, nearest the middle from below (scene values 0.45, 0.6), is seen."""
    parts = [(1.0, 0.0), (2.0, 1.0)]
    present = np.array([0.0, 0.05, 0.5, 0.75, 1.0])

    def spike_at(x):
        return lambda d, a, b: 1.0 if d == x else 0.0

    split, checks = planner._hat_split(parts, np.array([0.0, 1.0]), present, spike_at(0.05),
                                       0.5)
    assert split == parts and checks == [(0.5, 0.0, 1.0)]
    split, checks = planner._hat_split(parts, np.array([0.0, 1.0]), present, spike_at(0.75),
                                       0.5)  # 0.75 is nearest the end sample 1: not seen
    assert split == parts and checks == [(0.5, 0.0, 1.0)]
    split, checks = planner._hat_split(parts, np.array([0.0, 0.8, 1.0]), present,
                                       spike_at(0.75), 0.5)
    assert [r for _, r in split] == [0.0, 0.75, 1.0]
    assert checks == [(0.5, 0.0, 0.75)]  # on (0, 0.75): the middle 0.375 is nearest 0.5
    # the scene value nearest the middle may lie below it: 0.45 (0.05 away, 0.6 is 0.1)
    present = np.array([0.0, 0.45, 0.6, 1.0])
    split, checks = planner._hat_split(parts, np.array([0.0, 1.0]), present, spike_at(0.45),
                                       0.5)
    assert [r for _, r in split] == [0.0, 0.45, 1.0]


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


# ----------------------------------------------------------------------------- _Gain
def _gain_scene(rows, cols, depths, seed):
    """A depth map drawing ``depths`` (mm) in a fixed shuffled order (every value at least
    once), a texture with a non-zero mean, alpha 0.6 on a few pixels and 0 on two."""
    rng = np.random.default_rng(seed)
    radiance = 0.4 + rng.uniform(0.0, 1.0, (rows, cols, 2))
    alpha = np.ones((rows, cols))
    alpha[rng.integers(0, rows, 6), rng.integers(0, cols, 6)] = 0.6
    alpha[0, 3] = alpha[rows - 2, cols - 1] = 0.0
    covered = alpha > 0
    n = int(covered.sum())
    depth = np.full((rows, cols), depths[-1] + 50.0)  # uncovered: a depth not present
    depth[covered] = rng.permutation(np.concatenate([depths, rng.choice(depths,
                                                                          n - depths.size)]))
    return Scene.from_depth(radiance, depth, alpha=alpha)


def _brute_gain(scene, groups, profile, node_count):
    """Mean-radiance error of hat layers by a per-pixel gather, written out here: pixel
    ``p`` gathers ``sum_surfaces sum_delta alpha(s) (K_hat_{D(s)}(delta) -
    K_{D(s)}(delta))`` over sources ``s = p - delta`` (each surface mirrored beyond the
    border without repeating the edge pixel), ``K_hat`` linear in D between neighbouring
    representatives of the group ``[(lo, hi, reps), ...]`` holding ``D`` (its end ones
    beyond them), ``K`` the true kernel (over ``node_count`` depths: linear between that
    many nodes uniform in D). Returns ``mean radiance / std * RMS(g)`` (the surfaces
    cover disjoint pixels) and the depth of the worst pixel's largest share that is not
    a representative."""
    rows, cols = scene.shape
    covered = sum((s.alpha > 0).astype(int) for s in scene.surfaces)
    assert covered.max() == 1
    radiance = np.concatenate([s.radiance.mean(axis=-1)[s.alpha > 0] for s in scene.surfaces])
    ratio = radiance.mean() / radiance.std()
    depths = np.unique(np.concatenate([1.0 / s.depth_mm[s.alpha > 0] for s in scene.surfaces]))
    all_reps = [r for _, _, reps in groups for r in reps]

    def kern(d):
        return psf.integrated_psf(LENS, 1.0 / d, profile, model="pillbox")

    h = max(kern(d).shape[0] for d in (depths[0], depths[-1], *all_reps)) // 2

    def padded(d):
        k = kern(d)
        return np.pad(k, h - k.shape[0] // 2)

    nodes = depths if depths.size <= node_count else np.linspace(depths[0], depths[-1],
                                                                   node_count)
    node_k = np.array([padded(d) for d in nodes])
    u_node = np.interp(depths, nodes, np.arange(nodes.size))

    def blend(stack, u):
        lo = np.minimum(np.floor(u).astype(int), len(stack) - 1)
        hi = np.minimum(lo + 1, len(stack) - 1)
        return (1 - (u - lo))[:, None, None] * stack[lo] + (u - lo)[:, None, None] * stack[hi]

    rendered = np.zeros((depths.size, *node_k.shape[1:]))
    for lo, hi, reps in groups:
        mine = (depths >= lo) & (depths <= hi)
        u_rep = np.interp(depths[mine], reps, np.arange(len(reps)))  # clamped at the ends
        rendered[mine] = blend(np.array([padded(d) for d in reps]), u_rep)
    assert all(((depths >= lo) & (depths <= hi)).any() for lo, hi, _ in groups)
    error = rendered - blend(node_k, u_node)  # per depth, (2h+1)^2

    def mirror(i, n):
        i = np.abs(i)
        return np.where(i > n - 1, 2 * (n - 1) - i, i)

    g = np.zeros((rows, cols))
    share, worst = None, None
    for y in range(rows):
        for x in range(cols):
            total, mine = 0.0, np.zeros(nodes.size)
            for surface in scene.surfaces:
                alpha, inv = surface.alpha, 1.0 / surface.depth_mm
                for dy in range(-h, h + 1):
                    for dx in range(-h, h + 1):
                        sy, sx = mirror(y - dy, rows), mirror(x - dx, cols)
                        if alpha[sy, sx] == 0:
                            continue
                        k = int(np.searchsorted(depths, inv[sy, sx]))
                        part = alpha[sy, sx] * error[k, h + dy, h + dx]
                        total += part
                        lo = min(int(np.floor(u_node[k])), nodes.size - 1)
                        frac = u_node[k] - lo
                        mine[lo] += (1 - frac) * part
                        if frac:
                            mine[lo + 1] += frac * part
            g[y, x] = total
            if worst is None or abs(total) > abs(g[worst]):
                worst, share = (y, x), mine
    share[np.isin(nodes, all_reps)] = 0
    best = int(np.argmax(np.abs(share)))
    return ratio * math.sqrt(np.mean(g**2)), (float(nodes[best]) if share[best] else None)


@pytest.mark.parametrize(("count", "seed"), [(40, 1), (257, 2), (300, 3)])
def test_gain_error_matches_a_per_pixel_gather(count, seed):
    """``_Gain.error`` on a whole band (every pixel sampled) against ``_brute_gain``: 40
    depths (each its own true kernel), exactly 257 (still each its own: not nodes, which
    would interpolate), 300 (257 nodes uniform in D between the nearest and farthest),
    spread unevenly over 560-630 mm, a sweep window focusing across them, three
    representatives; and the ratio ``mean / std`` of the visible radiance."""
    rng = np.random.default_rng(seed)
    depths = np.sort(560.0 + 70.0 * rng.uniform(0.0, 1.0, count) ** 2)
    rows, cols = (8, 6) if count == 40 else (16, 20)
    scene = _gain_scene(rows, cols, depths, seed)
    present = planner._present_inverse_depths(scene, LENS)
    assert present.size == count
    profile = Profile([0.0, 0.01], [12.78, 12.82])
    reps = [float(present[count // 5]), float(present[count // 2]), float(present[-3])]
    ends = [0.5 * (reps[0] + reps[1]), 0.5 * (reps[1] + reps[2]), float(present[-1])]
    layers = tuple(simulate.Layer(lo, hi, r, 0)
                   for lo, hi, r in zip([-math.inf, *ends[:-1]], ends, reps))
    cache = planner._KernelCache(LENS, "pillbox", planner._Spectra(256))
    half = max(cache.kernel(float(d), profile).shape[0] for d in present) // 2
    gain = planner._Gain(scene, present, half)
    seen = scene.surfaces[0].alpha > 0
    visible = scene.surfaces[0].radiance.mean(axis=-1)[seen]
    assert gain.ratio == pytest.approx(visible.mean() / visible.std(), rel=1e-12)
    got, depth = gain.error(0, rows, layers, profile=profile, cache=cache, near=present)
    want, want_depth = _brute_gain(scene, [(present[0], present[-1], reps)], profile, 257)
    assert want > 0
    assert got == pytest.approx(want, rel=1e-9)
    assert depth == want_depth


# ----------------------------------------------------------------------------- edges
def _plane(shape, depth, box=None, value=0.5):
    """A plane at ``depth`` mm covering ``box`` (rows, cols slices; default all)."""
    alpha = np.zeros(shape)
    alpha[box if box is not None else (slice(None), slice(None))] = 1.0
    rng = np.random.default_rng(int(depth))
    return (value + 0.3 * rng.uniform(0.0, 1.0, shape), alpha, float(depth))


def test_edges_of_a_block_over_a_plane_worked_out_by_hand():
    """A 4x5 block at 400 mm over a plane at 410 mm (10x12 px): inverse depths differ by
    ``1/400 - 1/410 = 6.1e-5`` per mm. With ``k`` making that 0.4 px no pixel is an edge
    (both planes are flat: no jump within a surface); with 0.8 px the block's 14 border
    pixels are (its outline over the far plane), the largest jump 0.8. A block whose
    outline lies where the far plane has no pixel (alpha 0) has no edge."""
    shape, box = (10, 12), (slice(2, 6), slice(3, 8))
    diff = 1 / 400.0 - 1 / 410.0
    scene = Scene.from_planes([_plane(shape, 400.0, box), _plane(shape, 410.0)])
    mask, worst = planner._edges(scene, 0.4 / diff)
    assert not mask.any() and worst == 0.0
    mask, worst = planner._edges(scene, 0.8 / diff)
    ring = np.zeros(shape, bool)
    ring[box] = True
    ring[3:5, 4:7] = False
    assert ring.sum() == 14
    np.testing.assert_array_equal(mask, ring)
    assert worst == pytest.approx(0.8, rel=1e-12)
    # the far plane covers only columns 0-5; the block sits on columns 7-10
    scene = Scene.from_planes([_plane(shape, 400.0, (slice(2, 6), slice(7, 11))),
                               _plane(shape, 410.0, (slice(None), slice(0, 6)))])
    mask, worst = planner._edges(scene, 0.8 / diff)
    assert not mask.any() and worst == 0.0


def test_a_one_pixel_occluder_turns_occlusion_on():
    """One pixel at 300 mm in front of a plane at 700 mm is one depth-edge pixel (its own
    outline), so the plan composites with occlusion."""
    shape = (9, 9)
    scene = Scene.from_planes([_plane(shape, 300.0, (slice(4, 5), slice(4, 5))),
                               _plane(shape, 700.0)])
    pl = simulate.plan(scene, Camera.static(LENS, 12.78, 0.01), tolerance=1e-2)
    assert pl.occlusion
    occlusion = next(e for e in pl.effects if e.name == "occlusion")
    assert occlusion.applied and occlusion.reason.startswith("1 px on depth edges")


def _occlusion(scene, profile):
    band = planner.Band(0, scene.shape[0], profile, (), ())
    return planner._occlusion_error(scene, Camera(LENS, profile), [band],
                                    float(profile.image_distances_mm[0]))


def test_occlusion_error_is_zero_below_half_a_pixel_of_blur_difference():
    """Near 500 mm over far 501 mm: ``k (1/500 - 1/501)`` with ``k = a p / (2 pitch)`` =
    8.93 x 12.7 / 0.04 x 4.0e-6 = 0.011 px, below 0.5: no error is counted (though both
    are out of focus). Near 400 over far 600 (k x 8.3e-4 = 2.4 px) is counted."""
    shape = (12, 16)
    profile = _static(12.7)
    box = (slice(None), slice(0, 8))
    scene = Scene.from_planes([_plane(shape, 500.0, box), _plane(shape, 501.0, value=0.2)])
    assert _occlusion(scene, profile) == 0.0
    scene = Scene.from_planes([_plane(shape, 400.0, box), _plane(shape, 600.0, value=0.2)])
    assert _occlusion(scene, profile) > 0.0


def test_occlusion_error_of_a_mirrored_scene_is_the_same():
    """The estimate traces a straight edge with the near side left, mirroring the
    textures when the near surface lies right of its silhouette: a two-column strip at
    the left border (silhouette column 1; two columns of it left of column 1 inclusive,
    one from column 1 on) and the left-right mirror image of the whole scene give the
    same estimate."""
    shape = (12, 16)
    profile = _static(12.7)
    near = _plane(shape, 400.0, (slice(None), slice(0, 2)))
    far = _plane(shape, 600.0, value=0.2)
    scene = Scene.from_planes([near, far])
    mirrored = Scene.from_planes([(rad[:, ::-1], alpha[:, ::-1], depth)
                                  for rad, alpha, depth in (near, far)])
    got = _occlusion(scene, profile)
    assert got > 0
    assert _occlusion(mirrored, profile) == pytest.approx(got, rel=1e-12)


# ----------------------------------------------------------------------------- the plan's sums
def test_plan_sums_the_bands_estimates_as_row_weighted_rms(monkeypatch):
    """The plan's estimates from its bands' (patched here to known values per band): the
    rolling-shutter rows' is the partition's error times the finite-scene factor ``F``;
    the depth layers' ``sqrt(sum_b n_b ((F h_b)^2 + g_b^2) / rows)`` (``h_b`` the hat
    error, ``g_b`` the gain error, ``n_b`` the band's rows); the magnification's ``F
    sqrt(sum_b n_b m_b^2 / rows)``; ``F`` the ratio of mean inverse powers summed here.
    A rolling sweep of a 24x20 px plane gives bands of unequal rows (7, 9, 7, 1 today)."""
    rolling = dataclasses.replace(LENS, shutter="rolling", line_time_us=500.0)
    rng = np.random.default_rng(5)
    scene = Scene.from_depth(rng.uniform(0.0, 1.0, (24, 20)), np.full((24, 20), 700.0))
    cam = Camera(rolling, Profile([0.0, 0.05], [12.6, 12.65]), row_exposure_s=0.01)
    hat = iter([3e-3, 1e-3, 4e-3, 1.5e-3, 5e-3, 9e-3, 2e-3, 6e-3] * 4)
    gains = iter([2e-3, 7e-3, 1e-3, 8e-3, 2.5e-3, 3e-3, 4e-3, 1e-3] * 4)
    mags = iter([5e-4, 2e-3, 1e-3, 3e-3, 4e-4, 6e-4, 7e-4, 8e-4] * 4)
    seen = {"h": [], "g": [], "m": [], "band": []}
    layers, magnification, partition = planner._layers, planner._magnification, \
        planner._partition

    def fake_layers(*args, **kwargs):
        out = layers(*args, **kwargs)
        seen["g"].append(next(gains))
        return (*out[:3], seen["g"][-1])

    def fake_hat_error(*args):
        seen["h"].append(next(hat))
        return seen["h"][-1]

    def fake_magnification(*args, **kwargs):
        out = magnification(*args, **kwargs)
        seen["m"].append(next(mags))
        return (out[0], seen["m"][-1], *out[2:])

    def fake_partition(*args, **kwargs):
        out = partition(*args, **kwargs)
        if kwargs.get("integer"):
            seen["band"].append(out[1])
        return out

    monkeypatch.setattr(planner, "_layers", fake_layers)
    monkeypatch.setattr(planner, "_hat_error", fake_hat_error)
    monkeypatch.setattr(planner, "_magnification", fake_magnification)
    monkeypatch.setattr(planner, "_partition", fake_partition)
    near, near_rows = planner._near, []

    def spy_near(scene, q0, q1):
        near_rows.append((q0, q1))
        return near(scene, q0, q1)

    monkeypatch.setattr(planner, "_near", spy_near)
    pl = simulate.plan(scene, cam, tolerance=1e-2)
    assert not pl.occlusion
    rows = np.array([b.row_stop - b.row_start for b in pl.bands])
    assert len(set(rows)) > 1 and rows.sum() == 24 and len(seen["h"]) == len(rows)
    f = math.sqrt(_mean_inverse_power(256, 256) / _mean_inverse_power(24, 20))
    h, g, m = (np.array(seen[k]) for k in "hgm")
    effects = {e.name: e.estimated_error for e in pl.effects}
    assert effects["rolling-shutter rows"] == pytest.approx(f * seen["band"][0], rel=1e-12)
    rolling_effect = next(e for e in pl.effects if e.name == "rolling-shutter rows")
    assert rolling_effect.applied and rolling_effect.reason.startswith(f"{len(rows)} bands")
    # the rows that reach a band: the widest kernel's half-size plus the largest shift
    # 0.5 hypot(24, 20) |p / p_ref - 1| (p_ref = 12.625, p from 12.6 to 12.65), + 1
    blur = max(LENS.blur_px(F * u / (u - F), p) for u in (700.0,) for p in (12.6, 12.65))
    reach = psf.kernel_size(blur) // 2 + math.ceil(0.5 * math.hypot(24, 20) * 0.025 / 12.625) + 1
    assert near_rows == [(max(0, b.row_start - reach), b.row_stop + reach) for b in pl.bands]
    assert effects["depth layers"] == pytest.approx(
        math.sqrt(np.sum(rows * ((f * h) ** 2 + g**2)) / 24), rel=1e-12)
    assert effects["magnification"] == pytest.approx(
        f * math.sqrt(np.sum(rows * m**2) / 24), rel=1e-12)


def test_kernel_cache_scales_the_pitch_of_a_sub_step_either_way():
    """The kernel of a sub-step scaled by ``s`` is the blur of Eq. 2 over ``s`` times the
    pitch, for ``s`` below and above 1: for a plane at 500 mm and the detector at 12.9
    mm, ``b = a |v - p| / v / (0.02 s)`` px with ``a = 12.5 / 1.4`` and ``v = 12.5 x 500
    / 487.5``, rasterised here as a pillbox."""
    cache = planner._KernelCache(LENS, "pillbox", None)
    a, v = 12.5 / 1.4, 12.5 * 500.0 / 487.5
    for s in (0.9, 1.0, 1.1):
        b = a * abs(v - 12.9) / v / (0.02 * s)
        want = psf.raster_pillbox(b, psf.kernel_size(b) // 2)
        got = cache.kernel(1 / 500.0, _static(12.9), s)
        np.testing.assert_allclose(got, want / want.sum(), rtol=0, atol=1e-12)


def test_plan_reports_the_corner_displacement_and_its_bands_are_frozen():
    """A static frame at 12.9 mm seen with ``p_ref = 12.6`` on 41x50 px moves its corner
    by ``0.5 hypot(40, 49) x 0.3 / 12.6`` = 0.7533 px (worked out by hand); bands are
    immutable records."""
    lens = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=20.0, width_px=50,
                height_px=41)
    scene = Scene.from_depth(np.random.default_rng(0).uniform(size=(41, 50)),
                             np.full((41, 50), 600.0))
    pl = simulate.plan(scene, Camera.static(lens, 12.9, 0.01, reference_image_distance_mm=12.6))
    reason = next(e.reason for e in pl.effects if e.name == "magnification")
    assert "image moves up to 0.753 px at the corner" in reason
    with pytest.raises(dataclasses.FrozenInstanceError):
        pl.bands[0].row_start = 1


@pytest.mark.parametrize("depth", [10.0, 12.5])
def test_a_scene_at_or_inside_the_focal_length_is_refused_by_the_planner(depth):
    """A pixel at or nearer than f (no real image) is refused with the planner's message,
    naming the depth and f (not a later failure of the optics)."""
    depths = np.full((6, 8), 600.0)
    depths[2, 5] = depth
    scene = Scene.from_depth(np.ones((6, 8)), depths)
    with pytest.raises(planner.InputError,
                       match=rf"scene depth {depth:g} mm is not beyond the focal length 12.5"):
        simulate.plan(scene, Camera.static(LENS, 12.7, 0.01))


def test_edge_cells_need_the_budget_for_their_work(monkeypatch):
    """Sub-aperture compositing is planned only when its work fits the budget: sub-steps
    x aperture cells x layers x px of the box ``[r0 - 2h, r1 + 2h) x [c0 - 2h, c1 + 2h)``
    around the edge pixels (``h`` the widest kernel's half-size), clipped to the image,
    counted here; a moving detector starts by comparing 1 and 2 time cells, so it needs
    twice the work. A block on rows 12-19 at the left border of a 36x28 px plane (the box
    is clipped on the left only): at the budget exactly the cells are planned, 1 below
    it they are not (``None``)."""
    shape = (36, 28)
    box_rc = (slice(12, 20), slice(0, 8))
    scene = Scene.from_planes([_plane(shape, 400.0, box_rc), _plane(shape, 600.0, value=0.2)])
    for cam, factor in ((Camera.static(LENS, 12.8, 0.01), 1),
                        (Camera(LENS, Profile([0.0, 0.01], [12.75, 12.85])), 2)):
        pl = simulate.plan(scene, cam, tolerance=1e-1, occlusion=True)
        (band,) = pl.bands
        cache = planner._KernelCache(LENS, pl.model, planner._Spectra(256))
        a_p = LENS.aperture_mm * float(cam.motion.image_distances_mm.max()) / 0.02
        mask, _ = planner._edges(scene, 0.5 * a_p)
        rr, cc = np.nonzero(mask)
        assert (rr.min(), rr.max(), cc.min(), cc.max()) == (12, 19, 0, 7)
        cells, widths = [], []
        aperture_cells = planner.edge_model.aperture_cells

        def record(widest, aperture_cells=aperture_cells, cells=cells, widths=widths):
            widths.append([float(w) for w in widest])
            out = aperture_cells(widest)
            cells.append(len(out[0]))
            return out

        monkeypatch.setattr(planner.edge_model, "aperture_cells", record)
        h = max(cache.kernel(layer.inv_rep, s.profile, s.scale).shape[0] // 2
                for layer in band.layers for s in band.steps)
        assert 12 - 2 * h > 0 and 19 + 2 * h < 36 and 7 + 2 * h < 28
        box = (19 + 2 * h - (12 - 2 * h)) * (7 + 2 * h - 0)
        args = (scene, band, cache, pl.edge_inv_depth, mask, 1e-9)
        monkeypatch.setattr(planner, "EDGE_WORK_BUDGET", 0.0)
        assert planner._edge_cells(*args) is None and len(cells) == 1  # counted, refused
        # the aperture cells follow the occluders only: the near plane's widest blur
        # radius over the window (the far plane occludes nothing)
        knots = cam.motion.image_distances_mm
        assert widths[-1] == [max(abs(planner.edge_model.signed_radius(LENS, 1 / 400.0, p))
                                  for p in knots)]
        work = factor * len(band.steps) * cells[0] * len(band.layers) * box
        monkeypatch.setattr(planner, "EDGE_WORK_BUDGET", work - 1)
        assert planner._edge_cells(*args) is None
        monkeypatch.setattr(planner, "EDGE_WORK_BUDGET", work)
        n, est = planner._edge_cells(*args)
        assert n == 1 and (est > 0) == (factor == 2)
        monkeypatch.setattr(planner.edge_model, "aperture_cells", aperture_cells)
    # beyond the budget the plan keeps 'over' compositing and says so
    monkeypatch.setattr(planner, "EDGE_WORK_BUDGET", 0.0)
    pl = simulate.plan(scene, cam, tolerance=1e-3, occlusion=True)
    occlusion = next(e for e in pl.effects if e.name == "occlusion")
    assert pl.edge_time_cells == 0 and occlusion.estimated_error > 1e-3
    assert occlusion.reason.endswith(": partial occlusion at the silhouettes is not modelled")


def test_layers_measure_kernels_and_hat_blends_with_the_metric(monkeypatch):
    """The distances ``_layers`` hands to the partition and the blend errors it hands to
    the hat split, against the full-plane metric of ``K(a) - K(b)`` and of ``K(d) - (1 -
    t) K(a) - t K(b)``, ``t = (d - a) / (b - a)``, computed here (at 450, 500 and 570 mm,
    a sweep window focused between them)."""
    profile = Profile([0.0, 0.01], [12.78, 12.84])
    present = np.sort(1.0 / np.array([570.0, 540.0, 500.0, 470.0, 450.0]))
    cache = planner._KernelCache(LENS, "pillbox", planner._Spectra(256))
    got = {}
    partition, hat_split = planner._partition, planner._hat_split

    def spy_partition(present, lo, hi, dist, tol, **kw):
        got["dist"] = dist
        return partition(present, lo, hi, dist, tol, **kw)

    def spy_hat_split(parts, samples, present, blend, tol, forced=()):
        got["blend"] = blend
        return hat_split(parts, samples, present, blend, tol, forced)

    monkeypatch.setattr(planner, "_partition", spy_partition)
    monkeypatch.setattr(planner, "_hat_split", spy_hat_split)
    planner._layers([present], present, profile, cache, 1e-2, hat=True)

    def k(inv):
        return _fft(psf.integrated_psf(LENS, 1.0 / inv, profile, model="pillbox"), 256)

    d, a, b = 1 / 500.0, 1 / 570.0, 1 / 450.0
    t = (d - a) / (b - a)
    assert got["dist"](a, b) == pytest.approx(_full_plane_error(k(a) - k(b)), rel=1e-9)
    want = _full_plane_error(k(d) - (1 - t) * k(a) - t * k(b))
    assert want > 1e-3
    assert got["blend"](d, a, b) == pytest.approx(want, rel=1e-9)


def test_the_occlusion_estimate_follows_the_whole_window():
    """A sweep given with a knot in the middle of a straight segment (three collinear
    knots) is the same motion: the same occlusion estimate as with two knots."""
    shape = (12, 16)
    scene = Scene.from_planes([_plane(shape, 400.0, (slice(None), slice(0, 8))),
                               _plane(shape, 600.0, value=0.2)])
    two = Profile([0.0, 0.01], [12.70, 12.90])
    three = Profile([0.0, 0.0025, 0.01], [12.70, 12.75, 12.90])
    got = _occlusion(scene, two)
    assert got > 0
    assert _occlusion(scene, three) == pytest.approx(got, rel=1e-9)


def test_plan_records_are_frozen_and_a_plan_without_edge_cells_renders_over():
    """Layers, sub-steps, bands, effects and plans are immutable; a ``Plan`` built
    without ``edge_time_cells`` renders as one with 0 (no sub-aperture compositing)."""
    shape = (12, 16)
    scene = Scene.from_planes([_plane(shape, 400.0, (slice(None), slice(0, 8))),
                               _plane(shape, 600.0, value=0.2)])
    cam = Camera(LENS, Profile([0.0, 0.01], [12.75, 12.85]))
    pl = simulate.plan(scene, cam, tolerance=1e-1, occlusion=True, magnification_steps=2)
    band = pl.bands[0]
    for record, name in ((band.layers[0], "inv_rep"), (band.steps[0], "scale"),
                         (band, "row_start"), (pl.effects[0], "applied"), (pl, "tolerance")):
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(record, name, getattr(record, name))
    fields = {f.name: getattr(pl, f.name) for f in dataclasses.fields(pl)
              if f.name != "edge_time_cells"}
    bare = planner.Plan(**fields)
    over = dataclasses.replace(pl, edge_time_cells=0)
    np.testing.assert_array_equal(simulate.render(scene, cam, plan_=bare),
                                  simulate.render(scene, cam, plan_=over))


def test_lru_counts_bytes_from_zero_after_clear():
    """A 16-byte ``_Lru`` keeps two 8-byte arrays (16 is not over 16), before and after
    ``clear``; a third drops the least recently used (the first, unless it was read)."""
    lru = planner._Lru(16)
    for _ in range(2):
        lru["a"], lru["b"] = np.zeros(1), np.ones(1)
        assert list(lru) == ["a", "b"] and lru.nbytes == 16
        lru.clear()
        assert lru.nbytes == 0 and not lru
    lru["a"], lru["b"] = np.zeros(1), np.ones(1)
    assert "a" in lru  # read: now the most recent
    lru["c"] = np.full(1, 2.0)
    assert list(lru) == ["a", "c"] and lru.nbytes == 16


def test_gain_of_a_scene_without_contrast_is_zero():
    """A uniform radiance (RMS contrast 0, the unit of the estimate) has no gain error to
    report and names no depth, whatever its depths: also at 0.7, whose ``np.std`` is
    1.1e-16 by rounding (the ratio was 6e15)."""
    depth = np.linspace(560.0, 630.0, 48).reshape(6, 8)
    scene = Scene.from_depth(np.full((6, 8), 0.7), depth)
    present = planner._present_inverse_depths(scene, LENS)
    profile = Profile([0.0, 0.01], [12.78, 12.82])
    cache = planner._KernelCache(LENS, "pillbox", planner._Spectra(256))
    gain = planner._Gain(scene, present, 5)
    layers = (simulate.Layer(-math.inf, float(present[-1]), float(present[10]), 0),)
    assert gain.ratio == 0.0
    assert gain.error(0, 6, layers, profile=profile, cache=cache, near=present) == (0.0, None)


def test_a_uniform_scene_is_planned_as_one_without_contrast():
    """Plans of a uniform radiance do not depend on its level: at 0.7 (whose ``np.std``
    is 1.1e-16 by rounding) a depth ramp gets the layers of radiance 0.5 (whose std is
    exactly 0), not one per depth (192, the gain ratio was 6e15); a plane over a plane
    gets the occlusion estimate 0 and no edge time cells (it was 13.7, with 64 cells)."""
    depth = np.linspace(560.0, 630.0, 192).reshape(12, 16)
    alpha = np.zeros((12, 16))
    alpha[:, :8] = 1.0
    sweep = Camera(LENS, Profile([0.0, 0.01], [12.75, 12.85]))

    def plans(v):
        uniform = np.full((12, 16), v)
        ramp = simulate.plan(Scene.from_depth(uniform, depth), sweep, tolerance=1e-2)
        planes = Scene.from_planes([(uniform, alpha, 400.0), (uniform, None, 600.0)])
        return ramp, simulate.plan(planes, sweep, tolerance=1e-2)

    (ramp, planes), (ramp_half, planes_half) = plans(0.7), plans(0.5)
    assert ramp.layer_count == ramp_half.layer_count < 30
    layers_effect = next(e for e in ramp.effects if e.name == "depth layers")
    assert layers_effect.applied
    assert layers_effect.reason.startswith(f"{ramp.layer_count} layers over 560-630 mm")
    assert planes.occlusion and planes.edge_time_cells == planes_half.edge_time_cells == 0
    assert next(e for e in planes.effects if e.name == "occlusion").estimated_error == 0.0


def test_visible_is_the_nearest_covering_surface_worked_out_by_hand():
    """``_visible`` on three planes given far, near, middle (3x4 px, two channels of the
    value -+ 0.1): 900 mm on columns 0-2 (0.1), 300 mm on column 0 (0.9), 500 mm on
    columns 0-1 (0.5; alpha 0.5 on row 2, still covering): per pixel the channel mean and
    the inverse depth of the nearest surface with alpha > 0; column 3 has none (radiance
    0, NaN)."""
    def plane(value, cols, depth, alpha_rows=slice(None), alpha_value=1.0):
        alpha = np.zeros((3, 4))
        alpha[:, cols] = 1.0
        alpha[alpha_rows, cols] = alpha_value
        rad = np.stack([np.full((3, 4), value - 0.1), np.full((3, 4), value + 0.1)], axis=2)
        return rad, alpha, depth

    far = plane(0.1, slice(0, 3), 900.0)
    near = plane(0.9, slice(0, 1), 300.0)
    middle = plane(0.5, slice(0, 2), 500.0, slice(2, 3), 0.5)
    radiance, inv = planner._visible(Scene.from_planes([far, near, middle]))
    want_r = np.array([[0.9, 0.5, 0.1, 0.0]] * 3)
    want_i = np.array([[1 / 300, 1 / 500, 1 / 900, np.nan]] * 3)
    np.testing.assert_allclose(radiance, want_r, rtol=0, atol=1e-15)
    np.testing.assert_allclose(inv, want_i, rtol=1e-15)


def test_outline_of_a_hole_and_of_partial_cover_worked_out_by_hand():
    """A surface's outline: its partly covered pixels and those with an uncovered pixel
    among their 8 neighbours (outside the image counts as covered). A 5x6 plane with a
    one-pixel hole at (2, 3) and alpha 0.5 at (0, 0): the hole's 8 neighbours and (0, 0)
    (the pixel left of the hole sees it only as its right-hand neighbour)."""
    alpha = np.ones((5, 6))
    alpha[2, 3] = 0.0
    alpha[0, 0] = 0.5
    want = np.zeros((5, 6), bool)
    want[1:4, 2:5] = True
    want[2, 3] = False
    want[0, 0] = True
    np.testing.assert_array_equal(planner._outline(alpha), want)


def test_gain_error_of_two_groups_matches_a_per_pixel_gather():
    """``_Gain.error`` with two surfaces (two groups: 560-630 mm on the left columns, one
    layer; 400-430 mm on the right, two) against ``_brute_gain``: a depth is blended only
    between its own group's representatives, its group's end kernel beyond them."""
    rng = np.random.default_rng(7)
    rows, cols = 8, 10
    left = np.zeros((rows, cols))
    left[:, :5] = 1.0
    far = 560.0 + 70.0 * rng.uniform(0.0, 1.0, (rows, cols))
    near = 400.0 + 30.0 * rng.uniform(0.0, 1.0, (rows, cols))
    surfaces = tuple(Surface(0.3 + rng.uniform(0.0, 1.0, (rows, cols, 1)), a, d)
                     for a, d in ((left, far), (1.0 - left, near)))
    scene = Scene(surfaces, channels_axis=False)
    present = planner._present_inverse_depths(scene, LENS)
    groups = planner._groups(scene, present)
    assert len(groups) == 2
    g0, g1 = groups
    reps0 = [float(g0[len(g0) // 3])]
    reps1 = [float(g1[3]), float(g1[-4])]
    layers = (simulate.Layer(-math.inf, float(g0[-1]), reps0[0], 0),
              simulate.Layer(float(g0[-1]), 0.5 * (reps1[0] + reps1[1]), reps1[0], 1),
              simulate.Layer(0.5 * (reps1[0] + reps1[1]), float(g1[-1]), reps1[1], 1))
    profile = Profile([0.0, 0.01], [12.78, 12.84])
    cache = planner._KernelCache(LENS, "pillbox", planner._Spectra(256))
    half = max(cache.kernel(float(d), profile).shape[0] for d in present) // 2
    gain = planner._Gain(scene, present, half)
    got, depth = gain.error(0, rows, layers, profile=profile, cache=cache, near=present)
    want, want_depth = _brute_gain(scene, [(g0[0], g0[-1], reps0), (g1[0], g1[-1], reps1)],
                                   profile, 257)
    assert want > 0
    assert got == pytest.approx(want, rel=1e-9)
    assert depth == want_depth
