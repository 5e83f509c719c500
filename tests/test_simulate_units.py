"""The simulator's edge and compositing units (``pipeline.core.simulate.edge`` and
``composite``) against independent computations: areas worked out by hand, numeric
integration (``scipy.integrate``, midpoint grids), explicit loops, Eq. 2 from the thin
lens, and the two-plane reference trace of ``tests/reference/raytrace.py`` with an 'over'
model made here from ``scipy.ndimage``. Mutation kills (helper simmut,
tests/mutation/README.md); each test well under a second."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from reference.disk import pixel_disk_kernels
from reference.raytrace import edge_grid_image
from scipy import integrate, ndimage

from pipeline.core import optics, simulate
from pipeline.core.lens import Lens
from pipeline.core.motion import Profile
from pipeline.core.scene import Camera, Scene
from pipeline.core.simulate import composite, edge


def _disk_area_grid(x0, x1, y0, y1, r=1.0, n=1600):
    """Area of the disk of radius ``r`` inside ``[x0, x1] x [y0, y1]`` by a midpoint grid
    over the rectangle clipped to the disk's box (error ~ perimeter * cell^2)."""
    x0, x1, y0, y1 = max(x0, -r), min(x1, r), max(y0, -r), min(y1, r)
    if x1 <= x0 or y1 <= y0:
        return 0.0
    hx, hy = (x1 - x0) / n, (y1 - y0) / n
    x = x0 + (np.arange(n) + 0.5) * hx
    y = y0 + (np.arange(n) + 0.5) * hy
    return float(np.count_nonzero(x[None, :] ** 2 + y[:, None] ** 2 < r * r)) * hx * hy


# ------------------------------------------------------------------------------- edge.py
def test_unit_disk_fraction_worked_by_hand():
    """Quarter disk 1/4; half disk 1/2; the whole disk (bounds beyond the rim) 1; the strip
    ``[-1, 1] x [0, 1/2]``: ``2 int_0^{1/2} sqrt(1 - y^2) dy = [y sqrt(1-y^2) + asin y]_0^{1/2}
    = 0.4330127 + 0.5235988 = 0.9566115``, over pi 0.3044988; the same strip's left half
    ``[-1, 0] x [0, 1/2]`` half of it; an empty rectangle (x1 < x0) 0."""
    f = edge.unit_disk_fraction
    assert f(0.0, 1.0, 0.0, 1.0) == pytest.approx(0.25, abs=1e-12)
    assert f(-1.0, 0.0, -1.0, 0.0) == pytest.approx(0.25, abs=1e-12)
    assert f(-1.0, 1.0, 0.0, 2.0) == pytest.approx(0.5, abs=1e-12)
    assert f(-7.0, 9.0, -3.0, 5.0) == pytest.approx(1.0, abs=1e-12)
    assert f(-1.0, 1.0, 0.0, 0.5) == pytest.approx(0.9566115 / math.pi, abs=1e-7)
    assert f(-1.0, 0.0, 0.0, 0.5) == pytest.approx(0.5 * 0.9566115 / math.pi, abs=1e-7)
    assert f(-1.0, 1.0, -0.5, 0.0) == pytest.approx(0.9566115 / math.pi, abs=1e-7)
    assert f(0.4, 0.1, -0.5, 0.5) == 0.0
    assert f(-0.5, 0.5, 0.6, 0.2) == 0.0
    assert f(1.2, 3.0, -1.0, 1.0) == 0.0  # right of the disk


@pytest.mark.parametrize(
    "rect",
    [(-0.83, 0.27, -0.41, 0.66), (0.12, 0.95, 0.31, 0.88), (-0.9, -0.2, -0.95, -0.15),
     (-0.3, 0.6, -0.9, 0.2), (0.35, 1.7, -1.4, -0.25), (-2.6, -0.55, 0.05, 3.1)],
)
def test_unit_disk_fraction_against_a_midpoint_grid(rect):
    """Asymmetric rectangles in every quadrant, across the axes and beyond the rim."""
    want = _disk_area_grid(*rect) / math.pi
    assert edge.unit_disk_fraction(*rect) == pytest.approx(want, abs=3e-5)


def test_disk_integrals_of_another_radius_against_quadrature():
    """``_s_int(x, r) = int_{-r}^{x} sqrt(r^2 - t^2) dt`` and ``_g(x, y, r)`` = the area of
    the disk of radius ``r`` inside ``(-inf, x] x (-inf, y]`` (what the inclusion-exclusion
    of ``unit_disk_fraction`` needs), for r = 1.7 (callers pass 1; the formulas are general),
    by quadrature and by a grid."""
    r = 1.7
    for x in (-1.9, -1.2, -0.3, 0.0, 0.8, 1.5, 2.4):
        want = integrate.quad(lambda t: math.sqrt(max(r * r - t * t, 0.0)), -r,
                              min(max(x, -r), r))[0]
        assert float(edge._s_int(np.float64(x), r)) == pytest.approx(want, abs=1e-9)
    for x, y in [(0.5, 0.9), (-0.7, 1.2), (1.1, -0.6), (-1.3, -0.2), (2.0, 0.4), (0.3, -2.0),
                 (0.9, 2.5)]:
        want = _disk_area_grid(-r, x, -r, y, r)
        assert float(edge._g(np.float64(x), np.float64(y), r)) == pytest.approx(want, abs=2e-4)


def test_rect_is_the_aperture_interval_of_a_pixel_worked_by_hand():
    """A ray through ``xi`` lands at offset ``-rho xi``; pixel ``d`` spans ``[d - 1/2,
    d + 1/2]``. rho 1.6, d 2: ``xi in [-2.5/1.6, -1.5/1.6] = [-1.5625, -0.9375]``; rho -2.5,
    d 1: ``xi in [0.5/2.5, 1.5/2.5] = [0.2, 0.6]``; rho 4, d -3: ``[2.5/4, 3.5/4]``."""
    for d, rho, want in [(2.0, 1.6, (-1.5625, -0.9375)), (1.0, -2.5, (0.2, 0.6)),
                         (-3.0, 4.0, (0.625, 0.875))]:
        lo, hi = edge._rect(np.float64(d), rho)
        assert (float(lo), float(hi)) == pytest.approx(want, abs=1e-12)


def test_safe_keeps_radii_above_a_nanopixel():
    assert edge._safe(0.0) == 1e-9
    assert edge._safe(5e-10) == 1e-9
    assert edge._safe(-2e-9) == -2e-9
    assert edge._safe(3.5) == 3.5
    assert edge._safe(-0.25) == -0.25


def test_signed_radius_is_eq2_with_the_side_of_focus():
    """Eq. 2 from the thin lens: ``v = f u / (u - f)``, blur ``b = a |v - p| / v`` mm, over
    the pitch and the sub-step's scale; positive for a depth nearer than focus (``v > p``)."""
    lens = Lens(focal_length_mm=12.5, f_number=2.8, pixel_pitch_um=4.0, width_px=40,
                height_px=30)
    a, pitch, f = 12.5 / 2.8, 0.004, 12.5
    p = f * 900.0 / (900.0 - f)  # in focus at 900 mm
    for u, scale in [(420.0, 1.0), (2500.0, 1.0), (420.0, 1.07), (900.0, 0.93)]:
        v = f * u / (u - f)
        b_px = a * abs(v - p) / v / pitch / scale
        rho = edge.signed_radius(lens, 1.0 / u, p, scale)
        assert abs(rho) == pytest.approx(b_px / 2, rel=1e-9, abs=1e-9)
        if u != 900.0:
            assert (rho > 0) == (v > p)


def _aperture_samples(n=700):
    g = (np.arange(n) + 0.5) / n * 2 - 1
    xi_y, xi_x = np.meshgrid(g, g, indexing="ij")
    inside = xi_x**2 + xi_y**2 < 1
    return xi_x[inside], xi_y[inside]


@pytest.mark.parametrize("radii", [[2.3, -1.4], [-0.8], [3.1]])
def test_aperture_cells_and_their_kernels_against_sampled_rays(radii):
    """Rays through a grid of aperture points: each cell's share is the fraction of points
    inside it, and ``cell_kernels(cells, rho, half)[j, half + dy, half + dx]`` the fraction
    of points inside cell ``j`` whose ray lands in the pixel at ``(dy, dx) = round(-rho xi)``
    (for a layer with another radius than the cells' too; the kernel a size larger than
    needed is 0 outside the disk's support)."""
    xi_x, xi_y = _aperture_samples()
    cells, shares = edge.aperture_cells(radii)
    assert shares.sum() == pytest.approx(1.0, abs=1e-12)
    j = np.full(xi_x.size, -1)
    for k, (x0, x1, y0, y1) in enumerate(cells):
        j[(xi_x >= x0) & (xi_x < x1) & (xi_y >= y0) & (xi_y < y1)] = k
    assert np.all(j >= 0)  # the cells cover the disk
    np.testing.assert_allclose(shares, np.bincount(j, minlength=len(cells)) / xi_x.size,
                               atol=4e-3)
    for rho in (radii[0], -1.7 * radii[0] + 0.4):
        half = math.ceil(abs(rho) + 0.5) + 1
        k = edge.cell_kernels(cells, rho, half)
        assert k.shape == (len(cells), 2 * half + 1, 2 * half + 1)
        dy = np.floor(-rho * xi_y + 0.5).astype(int) + half
        dx = np.floor(-rho * xi_x + 0.5).astype(int) + half
        want = np.zeros_like(k)
        np.add.at(want, (j, dy, dx), 1.0 / xi_x.size)
        np.testing.assert_allclose(k, want, atol=4e-3)
        np.testing.assert_allclose(k.sum(axis=0).sum(), 1.0, atol=1e-12)


def _over_and_exact(near, far, alpha, rn, rf, half, weights):
    """The 'over' model made here (pillbox kernels of the reference, ``ndimage`` correlation
    with mirrored borders) and the reference's exact two-plane trace, time averaged."""
    kn = sum(w * pixel_disk_kernels([r], half)[0] for r, w in zip(rn, weights))
    kf = sum(w * pixel_disk_kernels([r], half)[0] for r, w in zip(rf, weights))

    def corr(img, k):
        return ndimage.correlate(img, k, mode="mirror")

    a_n = corr(alpha, kn)
    over = corr(near * alpha, kn) + (1 - a_n) * corr(far, kf)
    # grid_radius(f, N, pitch, p_ref, D, p) = (f / N / 2) (p_ref / pitch) (D - 1/f + 1/p):
    # with f = N = pitch = p = p_ref = 1 it is rho = D / 2
    optics = (1.0, 1.0, 1.0, 1.0)
    exact = sum(w * edge_grid_image(near, far, near.shape[1] // 2, 2 * a, 2 * b, optics, 1.0)
                for a, b, w in zip(rn, rf, weights))
    return over, exact


@pytest.mark.parametrize(
    ("rn", "rf", "weights"),
    [([2.3], [-1.4], None), ([-1.8], [3.2], None), ([1.2, 2.9], [-0.7, 1.6], [0.3, 0.7]),
     ([2.6, -1.1], [1.5, 0.9], None), ([0.7], [-2.4], None), ([-0.6, 0.45], [1.9, 2.2], None)],
)
def test_edge_error_is_over_against_the_reference_trace(rn, rf, weights):
    """``edge_error`` = sum over the crop of (over - exact)^2 per row, the crop being the
    ``cols = 2 (2 half + 8)`` columns centred on the edge column (``half = ceil(max|rho| +
    1/2) + 1``) of the first 64 rows. Textures 70 rows high and wide enough not to be
    mirrored: the crop is a plain slice; rows 64.. are far off (unused)."""
    rng = np.random.default_rng(7)
    near_tex, far_tex = rng.uniform(0, 1, (70, 160)), rng.uniform(0, 1, (70, 160))
    near_tex[64:], far_tex[64:] = 50.0, -50.0
    centre = 61
    half = math.ceil(max(map(abs, rn + rf)) + 0.5) + 1
    cols = 2 * (2 * half + 8)
    s = slice(centre - cols // 2, centre - cols // 2 + cols)
    near, far = near_tex[:64, s], far_tex[:64, s]
    alpha = np.zeros((64, cols))
    alpha[:, : cols // 2] = 1.0
    w = [1.0 / len(rn)] * len(rn) if weights is None else weights
    over, exact = _over_and_exact(near, far, alpha, rn, rf, half, w)
    want = np.sum((over - exact) ** 2) / 64
    got = edge.edge_error(near_tex, far_tex, rn, rf, weights, centre)
    assert want > 1e-5
    assert got == pytest.approx(want, rel=1e-9)
    if weights is None and len(rn) > 1:
        assert edge.edge_error(near_tex, far_tex, rn, rf, [0.5, 0.5], centre) == pytest.approx(
            got, rel=1e-12)


def test_edge_error_of_uniform_sides_is_zero():
    """Uniform textures: the far light seen past the edge is ``c_f`` times the part of the
    aperture whose rays miss the near plane, which is ``1 - a_n`` exactly (both count the
    rays landing on near pixels): no error, for any radii."""
    near, far = np.full((8, 50), 0.8), np.full((8, 50), 0.3)
    for rn, rf in [(2.3, -1.4), (-3.1, 0.7), ([1.5, 2.5], [-2.0, 0.5])]:
        assert edge.edge_error(near, far, rn, rf) == pytest.approx(0.0, abs=1e-20)


# -------------------------------------------------------------------------- composite.py
def test_correlate_against_explicit_loops():
    """``out[j, y, x, c] = sum_{dy, dx} k[j, h + dy, h + dx] src[h + y + dy, h + x + dx, c]``
    over the valid part, with asymmetric kernels (a convolution would flip them)."""
    rng = np.random.default_rng(3)
    src = rng.uniform(0, 1, (9, 11, 2))
    k = rng.uniform(0, 1, (2, 3, 3))
    k[0, 0, 2] = 5.0
    got = composite._correlate(src, k)
    assert got.shape == (2, 7, 9, 2)
    want = np.zeros_like(got)
    for j in range(2):
        for y in range(7):
            for x in range(9):
                for dy in (-1, 0, 1):
                    for dx in (-1, 0, 1):
                        want[j, y, x] += k[j, 1 + dy, 1 + dx] * src[1 + y + dy, 1 + x + dx]
    np.testing.assert_allclose(got, want, atol=1e-12)


def test_transmit_is_the_product_over_the_occluders():
    """``prod_k (1 - A_k / share)`` over the listed occluders only, alpha the last channel:
    alphas 0.1 and 0.3 of a cell of share 0.5: (1 - 0.2)(1 - 0.6) = 0.32."""
    views = {0: np.array([[[7.0, 0.1]]]), 1: np.array([[[9.0, 0.3]]]),
             2: np.array([[[1.0, 0.45]]])}
    assert composite._transmit(views, [0, 1], 0.5)[0, 0, 0] == pytest.approx(0.32)
    assert composite._transmit(views, [2], 1.0)[0, 0, 0] == pytest.approx(0.55)
    assert composite._transmit(views, [], 0.5) == 1.0


def test_edge_box_worked_by_hand():
    """Padded grid 30 x 40, pad 3. A front block at rows 5..19, cols 6..24 with alpha 1 on
    its rows 4..7, cols 3..9 (grid rows 9..12, cols 9..15): the changes (both sides of the
    step, 8-neighbours) are rows 8..13, cols 8..16: box ``(8 - 3, 13 + 3 + 1, 8 - 3,
    16 + 3 + 1) = (5, 17, 5, 20)``. A partial alpha 0.5 at grid (25, 30) marks its 3 x 3
    neighbourhood: rows to 26 (box end 30, clipped to 30 - 3 = 27), cols to 31 (end 35).
    A block not in front, and changes within ``pad`` of the border, do not count."""
    shape, pad = (30, 40), 3
    a1 = np.zeros((15, 19, 2))
    a1[4:8, 3:10, -1] = 1.0
    blocks = [(2, (5, 20, 6, 25), a1)]
    assert composite._edge_box(blocks, [2], shape, pad) == (5, 17, 5, 20)
    assert composite._edge_box(blocks, [1], shape, pad) is None
    a2 = np.zeros((30, 40, 2))
    a2[25, 30, -1] = 0.5
    a2[1, 20, -1] = 1.0  # within pad of the top: dropped
    blocks.append((1, (0, 30, 0, 40), a2))
    assert composite._edge_box(blocks, [1, 2], shape, pad) == (5, 27, 5, 35)
    # flipped: the 0.5 at (4, 9) marks rows 3..5, cols 8..10; the 1.0 at (28, 19) marks
    # rows 27..29, all within pad of the bottom: box (max(0, 3), 5 + 4, 8 - 3, 10 + 4)
    assert composite._edge_box([(4, (0, 30, 0, 40), a2[::-1, ::-1])], [4], shape, pad) == (
        3, 9, 5, 14)


def test_hat_split_worked_by_hand():
    """Representatives 0.1, 0.2, 0.4, 0.5 (groups 0, 0, 1, 1): 0.15 is half way between
    layers 0 and 1; 0.05 below the first is all layer 0; 0.475 is 3/4 of the way from
    layer 2 to 3; 0.3 lies between groups: its box layer (``idx``) decides, all or nothing;
    0.6 beyond the last is all layer 3."""
    layers = [SimpleNamespace(inv_rep=r, group=g) for r, g in
              [(0.1, 0), (0.2, 0), (0.4, 1), (0.5, 1)]]
    inv = np.array([[0.15, 0.05, 0.475], [0.3, 0.3, 0.6]])
    idx = np.array([[1, 0, 3], [1, 2, 3]])
    lo, theta = composite._hat(inv, layers, idx)
    np.testing.assert_array_equal(lo, [[0, 0, 2], [1, 1, 2]])
    np.testing.assert_allclose(theta, [[0.5, 0.0, 0.75], [0.0, 1.0, 1.0]], atol=1e-12)
    lo, theta = composite._hat(inv, layers[:1], idx)
    assert not lo.any() and not theta.any() and lo.shape == inv.shape


def test_edge_error_crops_about_column_0_by_default():
    """Without ``centre`` the edge sits at column 0: the crop is the texture mirrored about
    it, column ``k - cols/2`` taking column ``|k - cols/2|`` (``rho`` 1.3 and -2.1: half
    ``ceil(2.6) + 1 = 4``, cols ``2 (8 + 8) = 32``). (Centre 1 gives the same error: its
    crop is this one mirrored about the edge line, which leaves the error unchanged.)"""
    rng = np.random.default_rng(8)
    near_tex, far_tex = rng.uniform(0, 1, (10, 90)), rng.uniform(0, 1, (10, 90))
    half, cols = 4, 32
    s = np.abs(np.arange(cols) - cols // 2)
    near, far = near_tex[:, s], far_tex[:, s]
    alpha = np.zeros((10, cols))
    alpha[:, : cols // 2] = 1.0
    over, exact = _over_and_exact(near, far, alpha, [1.3], [-2.1], half, [1.0])
    want = np.sum((over - exact) ** 2) / 10
    assert edge.edge_error(near_tex, far_tex, 1.3, -2.1) == pytest.approx(want, rel=1e-9)


def test_colour_channels_are_rendered_independently_with_occlusion():
    """Two occluding planes (an edge and a corner) in RGB, 'over' compositing with
    sub-aperture cells: each channel of the colour render is the render of that channel
    alone (grey) with the same plan. The alpha is the blocks' last channel: reading any
    other channel as coverage mixes colours (and is invisible in grey, where colour and
    alpha are the only two)."""
    rows = cols = 24
    lens = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=20.0, width_px=cols,
                height_px=rows)
    rng = np.random.default_rng(5)
    far, mid = rng.uniform(0, 1, (rows, cols, 3)), rng.uniform(0, 1, (rows, cols, 3))
    far[..., 1] *= 0.2
    mid[..., 2] += 1.5
    a_mid = np.zeros((rows, cols))
    a_mid[:15, :13] = 1.0
    p = optics.image_distance(12.5, 1000.0)
    cam = Camera.static(lens, p, 0.1)

    def scene(f, m):
        return Scene.from_planes([(f, None, 1500.0), (m, a_mid, 600.0)])

    pl = simulate.plan(scene(far, mid), cam, tolerance=1e-2)
    assert pl.occlusion and pl.edge_time_cells >= 1
    out = simulate.render(scene(far, mid), cam, plan_=pl)
    for c in range(3):
        grey = simulate.render(scene(far[..., c], mid[..., c]), cam, plan_=pl)
        np.testing.assert_allclose(out[..., c], grey.reshape(rows, cols), rtol=0, atol=1e-9)


def test_one_edge_time_cell_of_a_sweep_is_the_static_correction_at_its_mid_time():
    """One time cell renders the sub-aperture correction at the cell's mid time: for a
    sweep with an uneven speed (knots at 0, 40 and 100 ms) the correction equals that of
    a detector standing at the position of t = 50 ms, and not that of the start."""
    pad, shape = 6, (32, 38)
    lens = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=20.0, width_px=26,
                height_px=20)
    rng = np.random.default_rng(9)
    a_near = np.zeros(shape)
    a_near[:19, :17] = 1.0
    near = np.dstack([rng.uniform(0, 1, shape) * a_near, a_near])
    far = np.dstack([rng.uniform(0, 1, shape), np.ones(shape)])
    blocks = [(1, (0, shape[0], 0, shape[1]), near), (0, (0, shape[0], 0, shape[1]), far)]
    layers = [SimpleNamespace(inv_rep=1 / 1500.0), SimpleNamespace(inv_rep=1 / 600.0)]
    p0, p1, p2 = (optics.image_distance(12.5, u) for u in (2000.0, 1200.0, 700.0))
    sweep = Profile([0.0, 0.04, 0.1], [p0, p1, p2])
    p_mid = p1 + (p2 - p1) * (0.05 - 0.04) / 0.06

    def correction(profile):
        out = np.zeros((*shape, 1))
        composite.edge_correction(out, blocks, layers, profile, lens, 0.0, 1.0, 1, pad)
        return out

    got = correction(sweep)
    assert np.max(np.abs(got)) > 1e-3
    np.testing.assert_allclose(got, correction(Profile([0.0, 0.1], [p_mid, p_mid])),
                               rtol=0, atol=1e-12)
    assert np.max(np.abs(got - correction(Profile([0.0, 0.1], [p0, p0])))) > 1e-3


def test_a_depth_nearer_than_the_last_layer_is_rendered_with_it():
    """A surface nearer than the last layer's end (a plan made for a farther scene) is
    rendered with the last layer, not dropped: one layer, occlusion on, full coverage,
    is the radiance convolved with its kernel (``ndimage.convolve``, mirrored borders;
    an asymmetric kernel, so a correlation would differ)."""
    rng = np.random.default_rng(11)
    rad = rng.uniform(0, 1, (14, 17))
    scene = Scene.from_depth(rad, np.full((14, 17), 300.0))
    k = np.array([[0.0, 0.1, 0.05], [0.1, 0.4, 0.2], [0.0, 0.1, 0.05]])
    cache = SimpleNamespace(kernel=lambda inv, profile, scale: k, lens=None)
    layer = SimpleNamespace(inv_lo=1 / 2000.0, inv_hi=1 / 1000.0, inv_rep=1 / 1500.0, group=0)
    got = composite.layered(scene, [layer], None, cache, True, 0.0)
    want = ndimage.convolve(rad, k, mode="mirror")
    np.testing.assert_allclose(got[..., 0], want, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    ("width", "centre", "cols"), [(2, 1, 9), (5, 0, 40), (7, 3, 4), (3, 2, 61)]
)
def test_crop_mirrors_the_texture_about_its_end_columns_however_wide(width, centre, cols):
    """Column ``j`` of the crop is texture column ``m(centre - cols // 2 + j)``, ``m`` the
    mirror about the end columns with period ``2 (width - 1)``, written out here; crops up to
    30 times the texture's width (where a single reflection would not reach)."""
    tex = np.arange(3 * width, dtype=float).reshape(3, width) ** 1.5  # uneven columns
    period = 2 * (width - 1)

    def mirrored(i):
        i %= period
        return i if i < width else period - i

    expected = tex[:, [mirrored(centre - cols // 2 + j) for j in range(cols)]]
    np.testing.assert_array_equal(edge._crop(tex, centre, cols), expected)
