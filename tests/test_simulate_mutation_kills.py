"""The simulator (``pipeline.core.simulate``: render, composite, edge) against computations
made here independently: analytic zooms of ramps, explicit loops and direct sums, areas
worked out by hand, and renders that must not depend on how the work is split (bands,
layers). Mutation kills (helper mut-sim, tests/mutation/README.md)."""

from __future__ import annotations

import dataclasses
import importlib
import itertools
import math

import numpy as np
import pytest

from pipeline.core import optics, simulate
from pipeline.core.lens import Lens
from pipeline.core.motion import constant_speed
from pipeline.core.scene import Camera, Exposure, Scene
from pipeline.core.simulate import edge
from pipeline.errors import InputError

# 5 um pixels: blurs of tens of pixels on small frames (kernels wider than the spline
# margin of the banded render)
render_mod = importlib.import_module("pipeline.core.simulate.render")

FINE = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=5.0, width_px=48, height_px=40)


def _texture(shape, seed):
    rng = np.random.default_rng(seed)
    return rng.uniform(0.0, 1.0, shape)


# ----------------------------------------------------------------------------- render.py
def test_scale_zooms_a_ramp_about_the_given_or_the_image_centre():
    """A linear ramp zoomed by ``s`` about ``c`` is ``f(c + (x - c) / s)``, worked out here
    from the ramp's formula (the cubic spline reproduces a ramp away from the borders)."""
    rows, cols = 31, 41
    r, c = np.mgrid[:rows, :cols].astype(float)
    image = np.stack([0.3 * r - 0.7 * c + 20.0, -0.2 * r + 0.1 * c + 5.0], axis=2)

    def ramp(rr, cc):
        return np.stack([0.3 * rr - 0.7 * cc + 20.0, -0.2 * rr + 0.1 * cc + 5.0], axis=2)

    inner = (slice(10, -10), slice(10, -10))
    centre = np.array([15.0, 20.0])  # (rows - 1) / 2, (cols - 1) / 2
    got = render_mod._scale(image, 1.08)
    want = ramp(centre[0] + (r - centre[0]) / 1.08, centre[1] + (c - centre[1]) / 1.08)
    np.testing.assert_allclose(got[inner], want[inner], atol=1e-3)
    off = np.array([12.0, 23.5])
    got = render_mod._scale(image, 0.95, off)
    want = ramp(off[0] + (r - off[0]) / 0.95, off[1] + (c - off[1]) / 0.95)
    np.testing.assert_allclose(got[inner], want[inner], atol=1e-3)
    # a cubic spline reproduces cubics too (a quadratic spline would not), and its
    # prefilter's mirrored border fades by 0.27 per px (_SPLINE_MARGIN): 1e-6 ten px in
    # (a quartic spline's fades by 0.36: 2e-5)
    def cubic(rr, cc):
        u, v = rr / 10.0, cc / 10.0
        return (u**3 - 2.0 * u * v**2 + 0.5 * v**3 + u * v)[:, :, None]

    got = render_mod._scale(cubic(r, c), 1.08)
    want = cubic(centre[0] + (r - centre[0]) / 1.08, centre[1] + (c - centre[1]) / 1.08)
    np.testing.assert_allclose(got[inner], want[inner], rtol=0, atol=3e-6)


def _sweep_scene():
    """Two depths, 200 and 215 mm, in stripes (kernels up to 105 px at 5 um), a
    two-channel texture whose channels differ, swept so that the image scale changes by
    a few percent."""
    rows, cols = 200, 24
    rad = np.stack([_texture((rows, cols), 1), _texture((rows, cols), 2)], axis=2)
    depth = np.where(np.mgrid[:rows, :cols][1] % 6 < 3, 200.0, 215.0)
    scene = Scene.from_depth(rad, depth)
    v_near, v_far = optics.image_distance(12.5, 300.0), optics.image_distance(12.5, 2000.0)
    cam = Camera(FINE, constant_speed(v_far, (v_near - v_far) / 0.1, 0.1))
    return scene, cam


@pytest.mark.parametrize("steps", [3, 0])
def test_bands_render_the_same_image_as_one_band(steps):
    """Rendering the rows in three bands (each with the rows that reach it) gives the same
    image as one band: the margins hold every kernel's reach, the scaling about the
    frame's centre moved into the band's rows, and the spline's reach; with and without
    magnification sub-steps. Progress counts every band's steps."""
    scene, cam = _sweep_scene()
    pl = simulate.plan(scene, cam, tolerance=1e-3, magnification_steps=steps, occlusion=False)
    (band,) = pl.bands
    n = len(band.steps)
    assert n == max(steps, 1) and (band.steps[0].scale != 1.0) == (steps > 0)
    cache = simulate.planner._KernelCache(FINE, pl.model, None)
    sizes = [cache.kernel(layer.inv_rep, s.profile, s.scale).shape[0]
             for layer in band.layers for s in band.steps]
    half = max(sizes) // 2
    assert half > 50  # a margin short of a sixth of the kernel shows beyond the spline's
    whole = simulate.render(scene, cam, plan_=pl)
    cuts = [0, 70, 130, 200]
    bands = [dataclasses.replace(band, row_start=a, row_stop=b)
             for a, b in itertools.pairwise(cuts)]
    banded = dataclasses.replace(pl, bands=tuple(bands))
    calls = []
    got = simulate.render(scene, cam, plan_=banded, progress=lambda d, t: calls.append((d, t)))
    assert calls == [(i, 3 * n) for i in range(1, 3 * n + 1)]
    assert got.shape == whole.shape == (200, 24, 2)
    np.testing.assert_allclose(got, whole, rtol=0, atol=1e-9)


def test_a_static_frame_off_the_reference_position_is_a_zoom_about_the_frame_centre():
    """A plane in focus at ``p = 12.9`` mm (kernel: a delta) seen with ``p_ref = 12.6``
    is the scene zoomed by ``12.9 / 12.6`` about the centre ((rows - 1) / 2, (cols - 1) /
    2) = (20, 24.5): on a ramp, ``f(c + (x - c) / s)`` worked out here."""
    lens = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=20.0, width_px=50,
                height_px=41)
    rows, cols = 41, 50
    r, c = np.mgrid[:rows, :cols].astype(float)
    ramp = 0.3 * r - 0.7 * c + 40.0
    u = 1.0 / (1.0 / 12.5 - 1.0 / 12.9)
    scene = Scene.from_depth(ramp, np.full((rows, cols), u))
    cam = Camera.static(lens, 12.9, 0.1, reference_image_distance_mm=12.6)
    pl = simulate.plan(scene, cam)
    (step,) = pl.bands[0].steps
    assert step.scale == pytest.approx(12.9 / 12.6)
    got = simulate.render(scene, cam, plan_=pl)
    s = 12.9 / 12.6
    want = 0.3 * (20.0 + (r - 20.0) / s) - 0.7 * (24.5 + (c - 24.5) / s) + 40.0
    inner = (slice(10, -10), slice(10, -10))
    assert got.shape == (rows, cols)
    np.testing.assert_allclose(got[inner], want[inner], atol=1e-4)


def test_one_electron_of_read_noise_is_added():
    """A dark frame (radiance 0: no shot noise) with 1 e- of read noise and 4 e- per unit
    radiance: the output is Gaussian with std 1/4 (40 000 pixels: std within 2%)."""
    lens = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=20.0, width_px=200,
                height_px=200)
    scene = Scene.from_depth(np.zeros((200, 200)), np.full((200, 200), 800.0))
    cam = Camera.static(lens, 12.7, 0.1, exposure=Exposure(4.0, read_noise_e=1.0))
    out = simulate.render(scene, cam, seed=3)
    assert float(np.std(out)) == pytest.approx(0.25, rel=0.02)
    assert abs(float(np.mean(out))) < 0.01


def test_magnification_margins_of_a_tall_frame_reach_as_far_as_the_image_moves():
    """A 1600-row strip swept 12.2-13.4 mm in two sub-steps (scales 1 -+ 2.3%): rows 800 px from the
    centre move ~20 px, beyond the spline's 12 rows of slack. Four bands still give the
    one-band image (the margins count the movement)."""
    lens = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=20.0, width_px=6,
                height_px=1600)
    rows, cols = 1600, 6
    rad = _texture((rows, cols), 5)
    scene = Scene.from_depth(rad, np.full((rows, cols), 700.0))
    cam = Camera(lens, constant_speed(12.2, 1.2 / 0.1, 0.1))
    pl = simulate.plan(scene, cam, tolerance=1e-2, magnification_steps=2, occlusion=False)
    (band,) = pl.bands
    scales = [s.scale for s in band.steps]
    assert max(abs(1 - 1 / s) for s in scales) * 800 > 15
    whole = simulate.render(scene, cam, plan_=pl)
    cuts = [0, 400, 800, 1200, 1600]
    bands = [dataclasses.replace(band, row_start=a, row_stop=b)
             for a, b in itertools.pairwise(cuts)]
    got = simulate.render(scene, cam, plan_=dataclasses.replace(pl, bands=tuple(bands)))
    np.testing.assert_allclose(got, whole, rtol=0, atol=1e-9)


@pytest.mark.parametrize(("cuts", "farthest"), [
    ([0, 400, 800, 1200, 1600], [799.5, 399.5, 399.5, 799.5]),  # rows 0, 400, 1199, 1599
    ([0, 800, 1600], [799.5, 799.5]),
])
def test_each_band_renders_only_its_rows_and_what_reaches_them(monkeypatch, cuts, farthest):
    """The work of a band: its rows plus a margin of the kernel's half, the movement of
    its row farthest from the centre (799.5) and 12 rows of spline slack, clipped to the
    frame; worked out here for four and two bands of a 1600-row strip (a band of the whole frame,
    or margins from other rows, would be more work)."""
    lens = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=20.0, width_px=6,
                height_px=1600)
    scene = Scene.from_depth(_texture((1600, 6), 5), np.full((1600, 6), 700.0))
    cam = Camera(lens, constant_speed(12.2, 1.2 / 0.1, 0.1))
    pl = simulate.plan(scene, cam, tolerance=1e-2, magnification_steps=2, occlusion=False)
    (band,) = pl.bands
    shrink = max(abs(1 - 1 / s.scale) for s in band.steps)
    cache = simulate.planner._KernelCache(lens, pl.model, None)
    half = max(cache.kernel(x.inv_rep, s.profile, s.scale).shape[0]
               for x in band.layers for s in band.steps) // 2
    rows = []
    layered = render_mod.composite.layered
    monkeypatch.setattr(render_mod.composite, "layered",
                        lambda part, *a: rows.append(part.shape[0]) or layered(part, *a))
    bands = [dataclasses.replace(band, row_start=a, row_stop=b)
             for a, b in itertools.pairwise(cuts)]
    simulate.render(scene, cam, plan_=dataclasses.replace(pl, bands=tuple(bands)))
    want = []
    for (a, b), far in zip(itertools.pairwise(cuts), farthest):
        m = half + math.ceil(shrink * far) + 12
        want += [min(1600, b + m) - max(0, a - m)] * 2
    assert rows == want



def test_a_plan_made_for_another_frame_size_is_refused():
    lens = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=20.0, width_px=31,
                height_px=20)
    cam = Camera.static(lens, 12.7, 0.1)
    small = Scene.from_depth(_texture((20, 30), 7), np.full((20, 30), 800.0))
    other = Scene.from_depth(_texture((20, 31), 7), np.full((20, 31), 800.0))
    pl = simulate.plan(small, cam)
    assert simulate.render(small, cam, plan_=pl).shape == (20, 30)
    with pytest.raises(InputError, match="plan is for a"):
        simulate.render(other, cam, plan_=pl)

# ----------------------------------------------------------------------------- edge.py
def test_a_sweep_through_focus_on_one_side_still_has_an_edge_error():
    """The shortcut "one side in focus: over compositing is exact" holds for one static
    cell only: a sweep whose near side is in focus during one of two time cells still
    errs, as much as when it is just out of focus then (continuity in rho)."""
    rng = np.random.default_rng(21)
    near, far = rng.uniform(0, 1, (16, 40)), rng.uniform(0, 1, (16, 40))
    assert edge.edge_error(near, far, 0.0, 4.0) == 0.0
    assert edge.edge_error(near, far, 4.0, 0.0) == 0.0
    swept = edge.edge_error(near, far, [0.0, 3.0], [4.0, 6.0])
    assert swept > 1e-5
    assert swept == pytest.approx(edge.edge_error(near, far, [1e-5, 3.0], [4.0, 6.0]), rel=1e-3)
    swept = edge.edge_error(near, far, [3.0, 4.0], [0.0, 6.0])
    assert swept > 1e-5
    assert swept == pytest.approx(edge.edge_error(near, far, [3.0, 4.0], [1e-5, 6.0]), rel=1e-3)
    # a far side blurred by less than a pixel (radius 0.6) is not in focus: the error stays
    assert edge.edge_error(near, far, 4.0, 0.6) > 1e-6


@pytest.mark.parametrize("rho", [4.6, -7.3])
def test_aperture_cells_are_bounded_by_every_pixel_line(rho):
    """Rays through aperture point ``xi`` meet the layer at ``-rho xi``; pixel ``d`` spans
    ``[d - 1/2, d + 1/2]``, so the lines sit at ``xi = (k + 1/2) / |rho|`` for every
    half-integer ``k + 1/2`` inside the disk: for 4.6, 0.5 ... 4.5 (10 lines), for 7.3,
    0.5 ... 6.5 (14), plus the aperture's rim -1, 1."""
    r = abs(rho)
    top = {4.6: 4.5, 7.3: 6.5}[r]
    lines = np.arange(-top, top + 1.0) / r
    cells, shares = edge.aperture_cells([rho])
    want = np.concatenate([[-1.0], lines, [1.0]])
    np.testing.assert_allclose(np.unique(cells[:, :2]), want, atol=1e-12)
    np.testing.assert_allclose(np.unique(cells[:, 2:]), want, atol=1e-12)
    assert shares.sum() == pytest.approx(1.0, abs=1e-12)
    kernels = edge.cell_kernels(cells, rho, 8)
    assert np.all(np.count_nonzero(kernels > 1e-14, axis=(1, 2)) == 1)  # one pixel per cell


def test_flipping_both_radii_is_the_same_aperture_and_the_same_error():
    """``rho -> -rho`` on both planes is the substitution ``xi -> -xi`` over the symmetric
    aperture: the same rays, the same exact image and over model, the same error (also
    when the planes lie on opposite sides of focus, and for a sweep)."""
    rng = np.random.default_rng(22)
    near, far = rng.uniform(0, 1, (16, 60)), rng.uniform(0, 1, (16, 60))
    for rn, rf in [(4.6, 2.2), (3.3, -5.7), ([2.0, 4.6], [1.0, -3.2])]:
        want = edge.edge_error(near, far, rn, rf)
        assert want > 1e-5
        got = edge.edge_error(near, far, -np.asarray(rn), -np.asarray(rf))
        assert got == pytest.approx(want, rel=1e-9)


def test_crop_centres_the_edge_column_in_the_mirrored_texture():
    """``cols`` columns around the edge column, the texture continued by reflection
    (without repeating its end columns) as far as needed: worked out by hand."""
    tex = np.arange(5.0)[None, :]
    np.testing.assert_array_equal(edge._crop(tex, 2, 8), [[2, 1, 0, 1, 2, 3, 4, 3]])
    np.testing.assert_array_equal(edge._crop(tex, 1, 8), [[3, 2, 1, 0, 1, 2, 3, 4]])
    wide = np.arange(30.0)[None, :].repeat(70, axis=0)  # at most 64 rows are read
    np.testing.assert_array_equal(edge._crop(wide, 10, 8), np.arange(6.0, 14.0)[None].repeat(64, 0))


# ----------------------------------------------------------------------------- composite.py
def test_a_plane_in_focus_is_the_scene_itself():
    """Every kernel a delta (no padding at all): each pixel, the first row and column and
    the last ones included, is its own radiance."""
    lens = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=20.0, width_px=30,
                height_px=20)
    u = 1.0 / (1.0 / 12.5 - 1.0 / 12.7)
    rad = _texture((20, 30), 8)
    scene = Scene.from_depth(rad, np.full((20, 30), u))
    out = simulate.render(scene, Camera.static(lens, 12.7, 0.1))
    np.testing.assert_allclose(out, rad, rtol=0, atol=1e-12)


def _occluded_planes(f, rows=36, cols=44):
    """A plane at 500 mm with an irregular outline (a notch, a tab: no symmetry) over a
    plane at 1500 mm, textures with no symmetry either; ``f`` applied to every array."""
    alpha = np.zeros((rows, cols))
    alpha[9:24, 12:30] = 1.0
    alpha[9:13, 12:16] = 0.0  # a notch
    alpha[24:27, 20:23] = 1.0  # a tab
    near, far = _texture((rows, cols), 9), _texture((rows, cols), 10)
    c = np.ascontiguousarray
    return Scene.from_planes([(c(f(far)), None, 1500.0), (c(f(near)), c(f(alpha)), 500.0)])


@pytest.mark.parametrize(("focus_mm", "model"),
                         [(800.0, "pillbox"), (600.0, "gaussian"), (510.0, "gaussian")])
@pytest.mark.parametrize("flip", ["rows", "cols", "transpose"])
def test_flipping_the_scene_flips_the_capture(flip, focus_mm, model):
    """The pillbox is symmetric under row and column flips and the transpose, so the
    capture of a flipped scene is the flipped capture: depth edges with 'over'
    compositing and sub-aperture cells near the occluder's outline included (any bound
    of a block or of the edge box that is off on one side breaks it). Focused at 800 mm
    both planes are blurred (sub-aperture cells). Gaussian kernels have tails in their
    outermost taps (a pillbox raster's are 0 on the axes): at 600 mm the far plane has the
    wider kernel (its block reaches the padding's first column and row); at 510 mm the
    near plane is nearly sharp (a 3 px kernel: its block reaches one pixel beyond its
    outline)."""
    lens = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=20.0, width_px=44,
                height_px=44)
    f = {"rows": lambda a: a[::-1], "cols": lambda a: a[:, ::-1],
         "transpose": lambda a: np.swapaxes(a, 0, 1)}[flip]
    cam = Camera.static(lens, optics.image_distance(12.5, focus_mm), 0.1, psf_model=model)
    scene = _occluded_planes(lambda a: a)
    pl = simulate.plan(scene, cam, tolerance=1e-2)
    assert pl.occlusion and (pl.edge_time_cells > 0 or focus_mm != 800.0)
    base = simulate.render(scene, cam, plan_=pl)
    flipped = _occluded_planes(f)
    pl_f = simulate.plan(flipped, cam, tolerance=1e-2)
    assert pl_f.edge_time_cells == pl.edge_time_cells
    np.testing.assert_allclose(simulate.render(flipped, cam, plan_=pl_f), f(base), rtol=0,
                               atol=1e-9)


def test_a_depth_between_two_layers_blends_their_kernels_linearly_in_inverse_depth():
    """Hat functions: a plane at inverse depth ``D = D1 + 0.25 (D2 - D1)`` between two
    layers' representatives is ``0.75 K1 * L + 0.25 K2 * L`` (each kernel the IPSF at its
    representative; convolved here with ``ndimage.convolve`` on the mirrored scene)."""
    from scipy import ndimage

    from pipeline.core import psf

    lens = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=20.0, width_px=30,
                height_px=24)
    d1, d2 = 1.0 / 900.0, 1.0 / 600.0
    inv = d1 + 0.25 * (d2 - d1)
    rad = _texture((24, 30), 11)
    scene = Scene.from_depth(rad, np.full((24, 30), 1.0 / inv))
    cam = Camera.static(lens, 12.75, 0.1)
    pl = simulate.plan(scene, cam, occlusion=False)
    layers = (simulate.Layer(-np.inf, 0.5 * (d1 + d2), d1),
              simulate.Layer(0.5 * (d1 + d2), np.inf, d2))
    band = dataclasses.replace(pl.bands[0], layers=layers)
    got = simulate.render(scene, cam, plan_=dataclasses.replace(pl, bands=(band,)))
    k1, k2 = (psf.lens_psf(lens, 1.0 / d, 12.75) for d in (d1, d2))
    want = 0.75 * ndimage.convolve(rad, k1, mode="mirror") + 0.25 * ndimage.convolve(
        rad, k2, mode="mirror")
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


def test_a_knot_in_the_middle_of_a_straight_sweep_changes_nothing():
    """A constant-speed sweep written with a third knot at its midpoint is the same
    motion: the same capture, sub-aperture time cells at an occluding edge included (they
    must span the whole exposure, not its first segment)."""
    from pipeline.core.motion import Profile

    lens = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=20.0, width_px=44,
                height_px=36)
    a, b = optics.image_distance(12.5, 1500.0), optics.image_distance(12.5, 500.0)
    two = Camera(lens, Profile([0.0, 0.1], [a, b]))
    three = Camera(lens, Profile([0.0, 0.05, 0.1], [a, 0.5 * (a + b), b]))
    scene = _occluded_planes(lambda x: x)
    pl = simulate.plan(scene, two, tolerance=1e-2, magnification_steps=0)
    assert pl.edge_time_cells > 1
    want = simulate.render(scene, two, plan_=pl)
    band = dataclasses.replace(pl.bands[0], profile=three.motion, steps=(
        dataclasses.replace(pl.bands[0].steps[0], profile=three.motion),))
    got = simulate.render(scene, three, plan_=dataclasses.replace(pl, bands=(band,)))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


@pytest.mark.parametrize("focus_mm", [1000.0, 650.0])
def test_two_depths_with_over_compositing_equal_the_per_pixel_brute_force(focus_mm):
    """A depth map of two depths (a square at 400 mm on 1000 mm) has one layer per depth,
    each at its exact depth: the layered 'over' render with its coverage renormalisation
    equals ``test_simulate.brute_force`` (every scene pixel spreads its own PSF, with the
    visibility and renormalisation rule written per pixel) to round-off."""
    from test_simulate import LENS, brute_force

    rad = _texture((24, 28), 12)
    depth = np.full((24, 28), 1000.0)
    depth[7:16, 8:19] = 400.0
    scene = Scene.from_depth(rad, depth)
    p = optics.image_distance(12.5, focus_mm)
    cam = Camera.static(LENS, p, 0.1)
    pl = dataclasses.replace(simulate.plan(scene, cam, tolerance=1e-3), edge_time_cells=0)
    assert pl.occlusion and [round(1 / x.inv_rep) for x in pl.bands[0].layers] == [1000, 400]
    ref = brute_force(rad, depth, np.ones_like(depth), LENS, p, pl.edge_inv_depth, 12)
    np.testing.assert_allclose(simulate.render(scene, cam, plan_=pl), ref, rtol=0, atol=1e-12)


def test_flipping_a_tilted_plane_near_focus_flips_the_capture():
    """A plane tilted through focus (470-550 mm, focus 510 mm, Gaussian PSF): hat-blended
    layers in bands of rows with 3-7 px kernels, one of them inside the frame; flipped
    top to bottom, the capture flips (a layer's block one row short at its bottom, or
    its top, breaks it)."""
    lens = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=20.0, width_px=16,
                height_px=40)
    rad = _texture((40, 16), 13)
    depth = 470.0 + 80.0 * np.mgrid[:40, :16][0] / 39
    cam = Camera.static(lens, optics.image_distance(12.5, 510.0), 0.1, psf_model="gaussian")
    outs = []
    for f in (lambda a: a, lambda a: a[::-1]):
        scene = Scene.from_depth(np.ascontiguousarray(f(rad)), np.ascontiguousarray(f(depth)))
        pl = simulate.plan(scene, cam, tolerance=1e-3)
        assert not pl.occlusion and pl.layer_count > 10
        outs.append(simulate.render(scene, cam, plan_=pl))
    np.testing.assert_allclose(outs[1], outs[0][::-1], rtol=0, atol=1e-9)


def test_two_occluding_planes_with_aperture_cells_match_a_ray_trace():
    """Three planes (far 1500 mm full; 800 mm with a vertical edge; 500 mm with a corner),
    focus 1000 mm (radii -0.94, 0.71, 2.83 px, both sides of focus): sub-aperture
    compositing against a ray trace written here (a 90 x 90 grid of aperture points in
    the unit disk; each ray meets plane ``i`` at ``g0 - rho_i xi`` and shows the first
    opaque plane it meets): within the trace's sampling error (0.003; 'over' is 0.09 off)."""
    rows = cols = 24
    lens = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=20.0, width_px=cols,
                height_px=rows)
    rng = np.random.default_rng(0)
    tex = [rng.uniform(0, 1, (rows, cols)) for _ in range(3)]
    a_mid = np.zeros((rows, cols))
    a_mid[:, :12] = 1.0
    a_near = np.zeros((rows, cols))
    a_near[:11, :17] = 1.0
    depths = [1500.0, 800.0, 500.0]
    scene = Scene.from_planes([(tex[0], None, depths[0]), (tex[1], a_mid, depths[1]),
                               (tex[2], a_near, depths[2])])
    p = optics.image_distance(12.5, 1000.0)
    cam = Camera.static(lens, p, 0.1)
    pl = simulate.plan(scene, cam, tolerance=1e-2)
    assert pl.occlusion and pl.edge_time_cells == 1
    out = simulate.render(scene, cam, plan_=pl)
    # the trace: rho = (a/2) (p / pitch) (1/u - 1/f + 1/p), the radius of Eq. 2 with a sign
    a = 12.5 / 1.4
    rho = [0.5 * a * p / 0.02 * (1.0 / u - 1.0 / 12.5 + 1.0 / p) for u in depths]
    g = (np.arange(90) + 0.5) / 90 * 2 - 1
    xi_y, xi_x = np.meshgrid(g, g, indexing="ij")
    inside = xi_x**2 + xi_y**2 < 1
    xi_y, xi_x = xi_y[inside], xi_x[inside]
    m = 4  # rays of the inner pixels stay on the planes (max |rho| < 3)
    yy, xx = np.mgrid[m : rows - m, m : cols - m]

    def hit(arr, r):
        y = np.floor(yy[..., None] - r * xi_y + 0.5).astype(int)
        x = np.floor(xx[..., None] - r * xi_x + 0.5).astype(int)
        return arr[y, x]

    seen = np.where(hit(a_near, rho[2]) > 0, hit(tex[2], rho[2]),
                    np.where(hit(a_mid, rho[1]) > 0, hit(tex[1], rho[1]), hit(tex[0], rho[0])))
    traced = seen.mean(axis=-1)
    assert np.max(np.abs(out[m:-m, m:-m] - traced)) < 0.01
