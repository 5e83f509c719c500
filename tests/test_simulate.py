"""Forward model: layered rendering vs brute force, effect planning, hard cases."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy import ndimage

from pipeline.cli import main as cli_main
from pipeline.core import optics, psf, simulate
from pipeline.core.lens import Lens
from pipeline.core.motion import Profile, constant_speed
from pipeline.core.scene import Camera, Exposure, Scene
from pipeline.errors import InputError

# 12.5 mm f/1.4 with coarse 20 um pixels: blurs of a few pixels keep brute force cheap.
LENS = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=20.0, width_px=64, height_px=48)


def texture(shape, seed=0, sigma=1.0):
    """A smooth-ish random texture in [0, 1] with sharp stripes (edges at every scale)."""
    rng = np.random.default_rng(seed)
    t = ndimage.gaussian_filter(rng.random(shape), sigma)
    t = (t - t.min()) / (t.max() - t.min())
    t[:, ::7] = 1.0
    return t


def rel_rms(a, b, ref):
    """RMS difference per unit RMS contrast of the scene (the tolerance's meaning)."""
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.std(ref))


def brute_force(radiance, depth, alpha, lens, p_mm, edge, pad, occlusion=True):
    """Per-pixel reference: every scene pixel spreads its own exact pixel-integrated PSF.

    Visibility rule: light from scene pixel y reaching output pixel x is multiplied by
    ``V = 1 - min(1, sum_{z: D_z > D_y + edge} alpha_z k_z(x - z))`` (D = 1/depth), and
    the result by ``max(1, min(1, sum_z alpha_z k_z(x - z)) / sum_y alpha_y k_y(x - y) V)``.
    The scene continues mirrored beyond its borders (``pad`` px).
    """
    rad = np.pad(radiance, pad, mode="reflect")
    dep = np.pad(depth, pad, mode="reflect")
    alp = np.pad(alpha, pad, mode="reflect")
    inv = 1.0 / dep
    kernels = {}
    for d in np.unique(dep):
        kernels[d] = psf.lens_psf(lens, float(d), p_mm)
    margin = max(k.shape[0] for k in kernels.values())
    shape = (rad.shape[0] + 2 * margin, rad.shape[1] + 2 * margin)
    field = np.zeros(shape)
    color, covered, coverage = np.zeros(shape), np.zeros(shape), np.zeros(shape)
    coords = [(r, c) for r in range(rad.shape[0]) for c in range(rad.shape[1])]
    occluders = sorted(coords, key=lambda rc: -inv[rc])
    sources = sorted(coords, key=lambda rc: -inv[rc])
    ptr = 0

    def window(rc, k):
        h = k.shape[0] // 2
        r, c = rc[0] + margin, rc[1] + margin
        return slice(r - h, r + h + 1), slice(c - h, c + h + 1)

    for y in sources:
        while occlusion and ptr < len(occluders) and inv[occluders[ptr]] > inv[y] + edge:
            z = occluders[ptr]
            k = kernels[dep[z]]
            field[window(z, k)] += alp[z] * k
            ptr += 1
        k = kernels[dep[y]]
        w = window(y, k)
        vis = 1 - np.minimum(field[w], 1)
        color[w] += rad[y] * alp[y] * k * vis
        covered[w] += alp[y] * k * vis
        coverage[w] += alp[y] * k
    if occlusion:
        with np.errstate(divide="ignore", invalid="ignore"):
            color *= np.where(covered > 1e-6, np.maximum(np.minimum(coverage, 1) / covered, 1), 0)
    cut = margin + pad
    return color[cut : shape[0] - cut, cut : shape[1] - cut]


def edge_scene(rows=30, cols=36):
    """A gently tilted background (700-1400 mm) and a near square (400 mm)."""
    xx = np.mgrid[:rows, :cols][1]
    depth = 700.0 + 700.0 * xx / (cols - 1)
    depth[8:20, 10:22] = 400.0
    return texture((rows, cols)), depth


@pytest.mark.parametrize("focus_mm", [1000.0, 400.0], ids=["background-sharp", "front-sharp"])
def test_layered_matches_brute_force_with_occlusion(focus_mm):
    radiance, depth = edge_scene()
    scene = Scene.from_depth(radiance, depth)
    p = optics.image_distance(LENS.focal_length_mm, focus_mm)
    cam = Camera.static(LENS, p, 0.1)
    pl = simulate.plan(scene, cam, tolerance=1e-3)
    assert pl.occlusion and pl.layer_count > 2
    rendered = simulate.render(scene, cam, plan_=pl)
    pad = 12
    ref = brute_force(radiance, depth, np.ones_like(depth), LENS, p, pl.edge_inv_depth, pad)
    mae = float(np.mean(np.abs(rendered - ref)))
    assert mae < 1e-3, mae
    # The same scene without occlusion is far from the occlusion-aware reference.
    flat = simulate.render(scene, cam, plan_=simulate.plan(scene, cam, occlusion=False))
    assert float(np.mean(np.abs(flat - ref))) > 5 * max(mae, 1e-3)
    # ... but matches the brute force without visibility (plain superposition).
    ref_add = brute_force(radiance, depth, np.ones_like(depth), LENS, p, 0, pad, occlusion=False)
    assert float(np.mean(np.abs(flat - ref_add))) < 1e-3


def test_kernel_error_is_rms_change_of_natural_image():
    n = 256
    rng = np.random.default_rng(1)
    fy, fx = np.fft.fftfreq(n)[:, None], np.fft.fftfreq(n)[None, :]
    amp = 1 / np.maximum(np.hypot(fx, fy), 1 / n)
    img = np.real(np.fft.ifft2(np.fft.fft2(rng.standard_normal((n, n))) * amp))
    img /= img.std()
    k1, k2 = psf.raster_pillbox(3.0, 5), psf.raster_pillbox(4.0, 5)

    def circ(k):
        pad = np.zeros((n, n))
        pad[:11, :11] = k
        return np.real(np.fft.ifft2(np.fft.fft2(img) * np.fft.fft2(np.roll(pad, (-5, -5), (0, 1)))))

    measured = float(np.sqrt(np.mean((circ(k1) - circ(k2)) ** 2)))
    assert 0.5 < measured / simulate.kernel_error(k1, k2) < 2
    assert simulate.kernel_error(k1, k1) == 0


def test_flat_scene_is_one_convolution_and_matches_direct():
    img = texture((40, 50)).astype(np.float32)
    scene = Scene.from_depth(img, np.full(img.shape, 700.0))
    cam = Camera.static(LENS, 12.8, 0.05)
    pl = simulate.plan(scene, cam)
    assert pl.convolutions == 1 and not pl.occlusion
    out = simulate.render(scene, cam, plan_=pl)
    assert out.dtype == np.float32
    k = psf.lens_psf(LENS, 700.0, 12.8)
    np.testing.assert_allclose(
        out, ndimage.convolve(img.astype(float), k, mode="mirror"), atol=1e-5
    )
    assert "depth layers" in pl.explain() and "skip" in pl.explain()


def test_layers_skip_measured_below_tolerance():
    """Depth varying by less than one layer: one layer; finer layering changes < tol."""
    img = texture((40, 40), seed=3)
    xx = np.mgrid[:40, :40][1]
    depth = 800.0 + 0.005 * xx  # a nearly flat plane (0.2 mm of depth)
    scene = Scene.from_depth(img, depth)
    cam = Camera.static(LENS, 12.75, 0.1)
    tol = 1e-3
    pl = simulate.plan(scene, cam, tolerance=tol)
    assert pl.layer_count == 1
    fine = simulate.render(scene, cam, plan_=simulate.plan(scene, cam, tolerance=tol / 100))
    assert rel_rms(simulate.render(scene, cam, plan_=pl), fine, img) < tol
    # A steeper plane needs several layers, and they meet the tolerance against a finer split.
    steep = Scene.from_depth(img, 600.0 + 20.0 * xx)
    pl = simulate.plan(steep, cam, tolerance=tol)
    assert pl.layer_count > 3
    fine = simulate.render(steep, cam, plan_=simulate.plan(steep, cam, tolerance=tol / 20))
    assert rel_rms(simulate.render(steep, cam, plan_=pl), fine, img) < tol


def test_occlusion_skip_measured_below_tolerance():
    img = texture((40, 40), seed=4)
    xx = np.mgrid[:40, :40][1]
    scene = Scene.from_depth(img, 900.0 + 2.0 * xx)  # continuous, gentle: no depth edges
    cam = Camera.static(LENS, 12.7, 0.1)
    pl = simulate.plan(scene, cam)
    assert not pl.occlusion
    forced = simulate.plan(scene, cam, occlusion=True)
    diff = rel_rms(
        simulate.render(scene, cam, plan_=pl), simulate.render(scene, cam, plan_=forced), img
    )
    assert diff < pl.tolerance


def test_magnification_skip_and_apply():
    img = texture((32, 32), seed=5)
    scene = Scene.from_depth(img, np.full(img.shape, 900.0))
    tol = 1e-3
    small = Camera(LENS, constant_speed(12.68, 0.01, 0.1))  # 1 um of travel
    pl = simulate.plan(scene, small, tolerance=tol)
    skipped = next(e for e in pl.effects if e.name == "magnification")
    assert not skipped.applied and skipped.estimated_error < tol
    forced = simulate.plan(scene, small, tolerance=tol, magnification_steps=8)
    diff = rel_rms(
        simulate.render(scene, small, plan_=pl), simulate.render(scene, small, plan_=forced), img
    )
    assert diff < tol
    # A long sweep on a larger frame moves the corner by pixels: applied.
    big_img = texture((96, 128), seed=6)
    big = Scene.from_depth(big_img, np.full(big_img.shape, 900.0))
    sweep = Camera(LENS, constant_speed(12.6, 1.0, 0.3))
    pl = simulate.plan(big, sweep, tolerance=tol)
    applied = next(e for e in pl.effects if e.name == "magnification")
    assert applied.applied and len(pl.bands[0].steps) > 1
    # A static frame at p != p_ref is one scaled image: compare with an exact zoom.
    cam = Camera.static(LENS, 12.9, 0.1, reference_image_distance_mm=12.6)
    pl = simulate.plan(big, cam, tolerance=tol)
    assert len(pl.bands[0].steps) == 1 and pl.bands[0].steps[0].scale == pytest.approx(12.9 / 12.6)


def test_shifted_sum_is_the_sum_of_shifted_kernel_spectra():
    spectra = simulate.planner._Spectra(256)
    rng = np.random.default_rng(0)
    kernels, shifts = rng.random((5, 9, 9)), rng.normal(0.0, 2.0, (5, 2))
    direct = sum(spectra.of(k) * spectra.shift(*d) for k, d in zip(kernels, shifts))
    got = spectra.shifted_sum(kernels, shifts)
    assert np.max(np.abs(got - direct)) < 1e-12 * np.max(np.abs(direct))


def test_magnification_estimate_is_the_pixel_rms_of_each_depths_error():
    """A band's magnification estimate is the RMS over its pixels of the error at each
    pixel's own depth and distance from the centre (computed here with one FFT per time
    node and the shift phases directly; the planner sums them as separable DFTs): a 20 ms
    window of a sweep over four columns of depths, whose errors differ 18x; two rows at the
    top and two at the centre (which move less)."""
    planner = simulate.planner
    rows, cols, tol = 24, 32, 1e-4
    depths = np.array([600.0, 750.0, 900.0, 1200.0])
    inv_map = 1.0 / (np.repeat(depths, cols // 4)[None, :] * np.ones((rows, 1)))
    window = Profile([0.0, 0.1], [optics.image_distance(12.5, 1500.0), 12.83]).window(0.04, 0.06)
    p_ref = 12.7
    invs = np.sort(1.0 / depths)
    layers = tuple(simulate.Layer(lo, hi, hi) for lo, hi in zip([-math.inf, *invs[:-1]], invs))
    spectra = planner._Spectra(256)
    edges = np.linspace(0.04, 0.06, planner._MAG_NODES + 1)
    p = window.position(0.5 * (edges[1:] + edges[:-1]))
    radius = np.array([cols, rows]) / math.sqrt(12)

    def error_at(inv, n):
        moved = radius * (p / p_ref - 1)[:, None]
        step_of = np.arange(p.size) * n // p.size
        moved -= np.array([moved[step_of == s].mean(axis=0) for s in range(n)])[step_of]
        blur = LENS.blur_px(optics.image_distance(12.5, 1.0 / inv), p)
        half = psf.kernel_size(float(blur.max())) // 2
        diff = sum(
            spectra.of(psf.raster_pillbox(b, half)) * (spectra.shift(*d) - 1)
            for b, d in zip(blur, moved)
        )
        return spectra.error(diff / p.size)

    for r0 in (0, 11):
        band = inv_map[r0 : r0 + 2]
        steps, estimate, applied, n = planner._magnification(
            window, layers, LENS, "pillbox", spectra, p_ref, (rows, cols), band, r0, tol, hat=True
        )
        assert applied and len(steps) == n > 1
        e = {inv: error_at(inv, n) for inv in invs}
        assert max(e.values()) > 10 * min(e.values())
        yy, xx = np.indices(band.shape)
        rho2 = (yy + r0 - (rows - 1) / 2) ** 2 + (xx - (cols - 1) / 2) ** 2
        pixel_e2 = np.vectorize(e.get)(band) ** 2 * rho2 / (radius @ radius)
        assert estimate == pytest.approx(math.sqrt(pixel_e2.mean()), rel=1e-9)

def test_rolling_shutter_bands_vs_per_row():
    rolling = dataclasses.replace(LENS, shutter="rolling", line_time_us=500.0)
    img = texture((24, 20), seed=7)
    scene = Scene.from_depth(img, np.full(img.shape, 700.0))
    tol = 1e-3
    # Slow motion: every row sees nearly the same IPSF -> one band.
    slow = Camera(rolling, Profile([0.0, 0.05], [12.73, 12.7301]))
    pl = simulate.plan(scene, slow, tolerance=tol)
    assert len(pl.bands) == 1
    per_row = simulate.plan(scene, slow, tolerance=tol, per_row=True, magnification_steps=0)
    diff = rel_rms(
        simulate.render(scene, slow, plan_=pl), simulate.render(scene, slow, plan_=per_row), img
    )
    assert diff < tol
    # Fast sweep (Sec. 6: a tilted focal plane): several bands, each within the tolerance.
    fast = Camera(rolling, Profile([0.0, 0.05], [12.6, 12.9]), row_exposure_s=0.01)
    pl = simulate.plan(scene, fast, tolerance=tol, magnification_steps=0)
    assert len(pl.bands) > 1
    per_row = simulate.plan(scene, fast, tolerance=tol, per_row=True, magnification_steps=0)
    a = simulate.render(scene, fast, plan_=pl)
    b = simulate.render(scene, fast, plan_=per_row)
    assert rel_rms(a, b, img) < tol
    # Rows differ: the top row (near 12.6 mm) and the bottom row see different blur.
    assert not np.allclose(
        a[0],
        simulate.render(scene, Camera.static(rolling, 12.9, 0.01, shutter="global"))[0],
        atol=1e-3,
    )


@pytest.mark.parametrize("bad", [np.nan, -np.inf, 0.0])
def test_missing_depth_choices(bad):
    img = texture((30, 30), seed=8)
    depth = np.full(img.shape, 800.0)
    depth[10:14, 10:14] = bad
    cam = Camera.static(LENS, 12.75, 0.1)
    with pytest.raises(InputError, match="missing_depth"):
        Scene.from_depth(img, depth)
    filled = Scene.from_depth(img, depth, missing_depth="fill")
    out = simulate.render(filled, cam)
    assert np.all(np.isfinite(out)) and filled.missing_pixels == 16
    assert "16 px given the nearest" in simulate.plan(filled, cam).explain()
    excluded = Scene.from_depth(img, depth, missing_depth="exclude")
    out = simulate.render(excluded, cam)
    assert np.all(np.isfinite(out)) and out[12, 12] < 0.2 * img.mean()
    assert "excluded" in simulate.plan(excluded, cam).explain()


def test_depth_at_infinity_focused_is_identity():
    img = texture((20, 24), seed=9)
    scene = Scene.from_depth(img, np.full(img.shape, np.inf))
    cam = Camera.static(LENS, LENS.focal_length_mm, 0.1)  # focused at infinity
    np.testing.assert_allclose(simulate.render(scene, cam), img, atol=1e-12)
    out = simulate.render(scene, Camera.static(LENS, 12.9, 0.1))
    assert np.all(np.isfinite(out))


def test_zero_exposure_and_bad_inputs():
    with pytest.raises(InputError, match="exposure_s"):
        Camera.static(LENS, 12.7, 0.0)
    with pytest.raises(InputError, match="exposure_s"):
        constant_speed(12.5, 1.0, 0.0)
    with pytest.raises(InputError, match="electrons_at_unit"):
        Exposure(0.0)
    scene = Scene.from_depth(np.ones((8, 8)), np.full((8, 8), 10.0))  # closer than f
    with pytest.raises(InputError, match="focal length"):
        simulate.plan(scene, Camera.static(LENS, 12.7, 0.1))


def test_huge_blur():
    img = texture((40, 40), seed=10)
    scene = Scene.from_depth(img, np.full(img.shape, 13.0))  # 13 mm from a 12.5 mm lens
    fine = dataclasses.replace(LENS, pixel_pitch_um=0.05)
    with pytest.raises(InputError, match="blur reaches"):
        simulate.plan(scene, Camera.static(fine, 12.5, 0.1))
    # ~120 px blur on a 40 px scene: finite, mean preserved by the mirrored borders.
    near = Scene.from_depth(img, np.full(img.shape, 200.0))
    out = simulate.render(near, Camera.static(LENS, 12.5, 0.1))
    assert np.all(np.isfinite(out)) and abs(out.mean() - img.mean()) < 0.05


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_noise_statistics_and_seed(dtype):
    img = np.full((64, 64, 3), 0.5, dtype=dtype)
    scene = Scene.from_depth(img, np.full((64, 64), 800.0))
    cam = Camera.static(LENS, 12.7, 0.1, exposure=Exposure(1000.0, read_noise_e=5.0))
    a = simulate.render(scene, cam, seed=1)
    assert a.dtype == dtype and a.shape == img.shape
    np.testing.assert_array_equal(a, simulate.render(scene, cam, seed=1))
    expected_var = (0.5 * 1000 + 25) / 1000**2  # Poisson + read, in radiance units
    assert float(a.var()) == pytest.approx(expected_var, rel=0.1)
    assert float(a.mean()) == pytest.approx(0.5, abs=3e-3)


def test_planes_scene_and_focal_stack():
    rows, cols = 24, 30
    back = texture((rows, cols), seed=11)
    front = np.ones((rows, cols))
    alpha = np.zeros((rows, cols))
    alpha[6:18, 8:20] = 1
    scene = Scene.from_planes([(back, None, 1500.0), (front, alpha, 500.0)])
    positions = [optics.image_distance(12.5, u) for u in (1500.0, 500.0)]
    frames, plans = simulate.render_focal_stack(scene, LENS, positions, seed=0)
    assert frames.shape == (2, rows, cols) and all(p.occlusion for p in plans)
    # Focused on the front plane: its interior is the plane's radiance.
    assert frames[1][10:14, 12:16] == pytest.approx(1.0, abs=1e-3)  # cubic-spline scaling
    assert math.isclose(plans[0].bands[0].steps[0].scale, positions[0] / np.mean(positions))


def test_cli_explain(tmp_path, capsys):
    img = texture((20, 24), seed=12).astype(np.float32)
    from pipeline.io import read, write

    write.write_image(tmp_path / "scene.tif", img, encoding="float32")
    depth = np.full(img.shape, 800.0)
    depth[0, 0] = np.nan
    np.save(tmp_path / "depth.npy", depth)
    args = [
        "simulate",
        str(tmp_path / "scene.tif"),
        "--depth",
        str(tmp_path / "depth.npy"),
        "--lens",
        "fujinon-12.5mm-f1.4-sony-1-3in",
        "--focus-mm",
        "750",
    ]
    assert cli_main(args) == 2  # missing depth, no choice
    assert "missing_depth" in capsys.readouterr().err
    out = tmp_path / "out.tif"
    assert cli_main([*args, "--missing-depth", "fill", "--explain", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "simulation plan" in text and "[skip ] magnification" in text
    assert read.read_frame(out).shape == img.shape


@pytest.mark.parametrize("rho", [3.3, -2.1, 0.2])
def test_aperture_cells_split_the_pillbox_along_the_pixel_lines(rho):
    """The cells cover the aperture once; their partial kernels add up to Eq. 2's pillbox,
    and through each cell the rays meet the layer that made the lines in one pixel."""
    from pipeline.core.simulate import edge

    cells, shares = edge.aperture_cells([rho])
    assert shares.sum() == pytest.approx(1, abs=1e-12)
    half = math.ceil(abs(rho) + 0.5)
    kernels = edge.cell_kernels(cells, rho, half)
    assert np.allclose(kernels.sum(axis=(1, 2)), shares, atol=1e-14)
    assert np.allclose(kernels.sum(axis=0), psf.raster_pillbox(2 * abs(rho), half), atol=1e-14)
    assert np.all(np.count_nonzero(kernels > 1e-14, axis=(1, 2)) == 1)
    other = edge.cell_kernels(cells, 1.7 * rho + 0.4, half + 2)  # another layer, same cells
    assert np.allclose(other.sum(axis=0), psf.raster_pillbox(2 * abs(1.7 * rho + 0.4), half + 2))
