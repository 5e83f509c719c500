"""Generalized cross-validation for Wiener's ``lam`` against explicit matrices: on a small
periodic image the influence matrix ``A = H (H^T H + lam D^T D)^-1 H^T`` is built from
circulant convolution and forward-difference matrices, and ``GCV = N |(I - A) y|^2 /
tr(I - A)^2`` computed by linear algebra, with no FFT.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from reference.matrices import gcv_and_noise, influence, one_sided_scene
from scipy import ndimage

from pipeline.core.deconvolve import gcv
from pipeline.core.deconvolve.dispatch import plan, restore


def _brute_gcv(y_periodic: np.ndarray, kernel: np.ndarray, lams) -> list[float]:
    return [gcv_and_noise(y_periodic, influence(kernel, y_periodic.shape, lam))[0] for lam in lams]


def _grid(y, kernel):
    return gcv.kernel_grid(gcv.crop_shape(y.shape, kernel.shape), kernel)


def _asymmetric_kernel() -> np.ndarray:
    k = np.array([[0.0, 0.1, 0.0], [0.05, 0.5, 0.25], [0.0, 0.0, 0.1]])
    return k / k.sum()


@pytest.mark.parametrize("lam", [1e-4, 1e-2, 0.3])
def test_gcv_score_equals_the_matrix_gcv(lam):
    rng = np.random.default_rng(1)
    y = rng.uniform(0.0, 1.0, (6, 7))
    kernel = _asymmetric_kernel()
    spectra = gcv._spectra(y, _grid(y, kernel))
    mirrored = np.pad(y, [(0, 6), (0, 7)], mode="symmetric")  # the periodic domain used
    (brute,) = _brute_gcv(mirrored, kernel, [lam])
    assert gcv.gcv_score(lam, spectra) == pytest.approx(brute, rel=1e-9)


def test_gcv_regularization_finds_the_matrix_gcv_minimum():
    rng = np.random.default_rng(2)
    x = ndimage.gaussian_filter(rng.uniform(0, 1, (5, 6)), 0.8)
    kernel = _asymmetric_kernel()
    y = ndimage.convolve(x, kernel, mode="wrap") + rng.normal(0, 0.02, x.shape)
    mirrored = np.pad(y, [(0, 5), (0, 6)], mode="symmetric")
    grid = np.logspace(-7, 1, 81)
    brute = grid[int(np.argmin(_brute_gcv(mirrored, kernel, grid)))]
    lam, _ = gcv.gcv_regularization(y, _grid(y, kernel))
    assert np.log10(lam) == pytest.approx(np.log10(brute), abs=0.1)


def test_gcv_lam_is_near_the_best_lam_on_a_noisy_blurred_texture():
    rng = np.random.default_rng(3)
    x = ndimage.gaussian_filter(rng.uniform(0, 1, (160, 160)), 1.2)
    kernel = np.zeros((15, 15))
    kernel[7, 2:13] = 1.0
    kernel[3:7, 9] = 0.5  # asymmetric
    kernel /= kernel.sum()
    y = ndimage.convolve(x, kernel, mode="reflect") + rng.normal(0, 0.02, x.shape)
    inner = (slice(20, -20), slice(20, -20))

    def error(**options):
        p = plan(y, kernel, method="wiener", noise_sigma=0.02, **options)
        return float(np.sqrt(np.mean((restore(y, p) - x)[inner] ** 2))), p

    best = min(error(regularization=lam)[0] for lam in np.logspace(-5, 0, 26))
    chosen, p = error()
    lam_gcv, noise = gcv.gcv_regularization(y, _grid(y, kernel))
    assert 0.02 / gcv.GCV_TRUST <= noise <= 0.02 * gcv.GCV_TRUST  # trusted here
    assert float(p.params["lam"][0]) == pytest.approx(lam_gcv)
    assert chosen <= 1.05 * best
    prior, _ = error(auto="prior")
    assert chosen < prior  # the prior fit is further off here


def test_the_crop_holds_the_kernel_or_gcv_stands_aside():
    assert gcv.crop_shape((1536, 2048), (31, 31)) == (512, 512)
    assert gcv.crop_shape((1536, 2048), (637, 637)) == (638, 638)  # pcb10 with a doubled span
    assert gcv.crop_shape((100, 300), (31, 31)) == (200, 512)
    assert gcv.crop_shape((100, 100), (301, 301)) is None
    rng = np.random.default_rng(4)
    y = rng.uniform(0, 1, (100, 100))
    kernel = np.ones((151, 151)) / 151**2
    p = plan(y, kernel, method="wiener", noise_sigma=0.01)  # the prior fit decides
    q = plan(y, kernel, method="wiener", noise_sigma=0.01, auto="prior")
    assert p.params["lam"] == pytest.approx(q.params["lam"])


def test_gcv_with_a_kernel_variance_wider_than_the_crop():
    rng = np.random.default_rng(5)
    y = rng.uniform(0, 1, (700, 700))
    kernel = np.ones((301, 301)) / 301**2  # its variance's autocorrelation: 601 px
    samples = np.stack([kernel, np.roll(kernel, 3, axis=1), np.roll(kernel, -2, axis=0)])
    p = plan(y, kernel, method="wiener", noise_sigma=0.01, kernel_samples=samples)
    assert np.all(np.isfinite(p.params["lam"]))


@pytest.mark.parametrize("lam", [1e-3, 0.05])
def test_gcv_noise_is_wahbas_estimate_from_the_matrices(lam):
    """``sigma^2 = |(I - A) y|^2 / tr(I - A)`` with the explicit influence matrix."""
    rng = np.random.default_rng(6)
    y = rng.uniform(0.0, 1.0, (5, 6))
    kernel = _asymmetric_kernel()
    mirrored = np.pad(y, [(0, 5), (0, 6)], mode="symmetric")
    want = gcv_and_noise(mirrored, influence(kernel, mirrored.shape, lam))[1]
    grid = _grid(y, kernel)
    got = gcv.gcv_noise(lam, gcv._spectra(y, grid), mirrored.size)
    assert got == pytest.approx(want, rel=1e-9)


def test_the_refined_lam_is_the_fine_grid_minimum():
    y, kernel = one_sided_scene("wrap")
    grid = _grid(y, kernel)
    lam, noise = gcv.gcv_regularization(y, grid)
    spectra = gcv._spectra(y, grid)
    fine = np.logspace(-7, 1, 1601)  # 0.005 decade
    scores = [gcv.gcv_score(t, spectra) for t in fine]
    assert np.log10(lam) == pytest.approx(np.log10(fine[int(np.argmin(scores))]), abs=0.01)
    size = 4 * y.shape[0] * y.shape[1]
    assert noise == pytest.approx(gcv.gcv_noise(lam, spectra, size), rel=1e-12)


@pytest.mark.parametrize("lam", [1e-3, 0.05])
def test_gcv_with_a_kernel_variance_equals_the_matrix_gcv(lam):
    """With per-depth kernels ``H_u`` around the one used, ``H``, the estimate minimising the
    expected error is ``(H^T H + C + lam D^T D)^-1 H^T y``, ``C = mean_u (H_u - H)^T (H_u - H)``
    (Sec. 4.2); its influence ``A = H (H^T H + C + lam D^T D)^-1 H^T``. GCV and Wahba's
    noise from these matrices equal :func:`gcv.gcv_score` and :func:`gcv.gcv_noise` on a
    grid with :func:`wiener.kernel_variance` (which would pass with ``V = 0`` only if ``C``
    were ignored: the samples differ by one-sided shifts)."""
    from pipeline.core.deconvolve.wiener import kernel_variance

    rng = np.random.default_rng(8)
    y = rng.uniform(0.0, 1.0, (6, 7))
    kernel = _asymmetric_kernel()
    samples = np.stack([kernel, np.roll(kernel, 1, axis=1), np.roll(kernel, -1, axis=0)])
    samples[2, 0, 0] += 0.05
    mirrored = np.pad(y, [(0, 6), (0, 7)], mode="symmetric")
    a = influence(kernel, mirrored.shape, lam, samples=samples)
    want_score, want_noise, _ = gcv_and_noise(mirrored, a)

    shape = gcv.crop_shape(y.shape, tuple(2 * n - 1 for n in kernel.shape))
    grid = gcv.kernel_grid(shape, kernel, variance=kernel_variance(samples, kernel))
    spectra = gcv._spectra(y, grid)
    assert gcv.gcv_score(lam, spectra) == pytest.approx(want_score, rel=1e-9)
    assert gcv.gcv_noise(lam, spectra, mirrored.size) == pytest.approx(want_noise, rel=1e-9)
    without = gcv._spectra(y, gcv.kernel_grid(shape, kernel))
    assert gcv.gcv_score(lam, without) != pytest.approx(want_score, rel=1e-3)


def _clean_textured_scene():
    """A 1/f texture (fine detail everywhere, as the ray-traced depth edge of issue 13)
    blurred by an asymmetric IPSF-like kernel (equal-weight discs of radius 0-5 px, whose
    sharp core keeps the spectrum away from zero, plus a tail to the right), no noise: the
    data's own noise estimate reads the texture."""
    from reference.cases import texture

    x = texture((160, 160), 5)
    yy, xx = np.mgrid[-5:6, -5:6]
    kernel = sum((yy**2 + xx**2 <= r * r) / np.count_nonzero(yy**2 + xx**2 <= r * r)
                 for r in range(6))
    kernel[5, 6:10] += [0.3, 0.2, 0.12, 0.05]
    kernel /= kernel.sum()
    return x, ndimage.convolve(x, kernel, mode="reflect"), kernel


def test_clean_texture_gets_gcvs_floor_not_the_prior_fit_fed_texture_as_noise():
    """The estimated sigma is only an upper bound: on clean data GCV's minimum sits in its
    grid's first decade with a noise far below it, and that ``lam`` is kept (within 0.3 dB
    of the ``lam`` chosen with the truth by a brute-force scan). Passing the same sigma as
    a known level keeps the two-sided rule, whose prior fit over-smooths by > 1 dB."""
    import importlib

    from pipeline.core.deconvolve.common import _LAM_MIN, estimate_noise_sigma
    from pipeline.core.quality import psnr

    wiener_module = importlib.import_module("pipeline.core.deconvolve.wiener")

    x, y, kernel = _clean_textured_scene()
    inner = (slice(16, -16), slice(16, -16))

    def db(p):
        return psnr(restore(y, p)[inner], x[inner])

    sigma = estimate_noise_sigma(y)
    assert sigma > 1e-3  # the texture, read as noise (the data are clean)
    best = max(db(plan(y, kernel, regularization=lam)) for lam in np.logspace(-7, -1, 25))
    auto = plan(y, kernel)
    lam_gcv, noise = gcv.gcv_regularization(y, _grid(y, kernel))
    assert gcv.interpolates(lam_gcv, noise, sigma)
    known = plan(y, kernel, noise_sigma=sigma)  # the same sigma, given: the prior fit
    assert gcv.floor_predicts_better(y, _grid(y, kernel), lam_gcv, known.params["lam"][0])
    floor = wiener_module.lam_for_noise_gain(kernel, wiener_module.MAX_NOISE_GAIN)
    assert float(auto.params["lam"][0]) == pytest.approx(max(lam_gcv, floor, _LAM_MIN))
    assert db(auto) >= best - 0.3
    assert db(auto) > psnr(y[inner], x[inner]) + 10  # it restores (a flipped kernel fails)
    assert db(known) < db(auto) - 1.0
    # GCV's lam, once kept, is exempt from a noise ceiling (as where GCV's noise agrees)
    capped = plan(y, kernel, max_noise=1e-4)
    assert float(capped.params["lam"][0]) == float(auto.params["lam"][0])


@pytest.mark.parametrize(
    ("lam", "noise", "expected"),
    [
        (9e-7, 0.39, True),
        (1.1e-6, 0.39, False),
        (9e-7, 0.41, False),
        (1e-7, 0.0, True),
        (1e-6, 0.39, False),  # the decade's end and the bound's share are excluded
        (9e-7, 0.4, False),
    ],
)
def test_gcv_interpolates_only_in_its_first_decade_below_the_bound_over_trust(
    lam, noise, expected
):
    """The first decade ends at ``GCV_LAMS[1] = 1e-6``; the noise must stay below
    ``1 / GCV_TRUST = 0.4`` of the bound (1 here)."""
    assert gcv.interpolates(lam, noise, 1.0) is expected


def test_the_floor_is_preferred_from_the_margin_on(monkeypatch):
    """``floor_predicts_better`` compares GCV's two scores with ``GCV_FLOOR_MARGIN``: just
    above their ratio it says no, just below it says yes (and never for equal ``lam``)."""
    _, y, kernel = _clean_textured_scene()
    grid = _grid(y, kernel)
    spectra = gcv._spectra(y, grid)
    ratio = gcv.gcv_score(1e-2, spectra) / gcv.gcv_score(1e-7, spectra)
    assert ratio > 1.5
    monkeypatch.setattr(gcv, "GCV_FLOOR_MARGIN", ratio * 1.001)
    assert not gcv.floor_predicts_better(y, grid, 1e-7, 1e-2)
    monkeypatch.setattr(gcv, "GCV_FLOOR_MARGIN", ratio * 0.999)
    assert gcv.floor_predicts_better(y, grid, 1e-7, 1e-2)
    assert not gcv.floor_predicts_better(y, grid, 1e-2, 1e-2)
    monkeypatch.setattr(gcv, "GCV_FLOOR_MARGIN", 1.0)
    assert gcv.floor_predicts_better(y, grid, 1e-2, 1e-2)  # "at least": an equal score


@given(
    seed=st.integers(0, 2**16),
    radius=st.integers(1, 6),
    tail=st.floats(0.0, 1.0),
    level=st.sampled_from([0.0, 1e-4, 3e-3]),
)
@settings(max_examples=25, deadline=None)
@example(seed=0, radius=6, tail=0.0, level=0.0)  # a plain pillbox's spectral zeros, clean
def test_the_automatic_lam_restores_a_blurred_texture_by_at_least_1_db(seed, radius, tail, level):
    """Clean or nearly clean 1/f textures under random asymmetric kernels (a pillbox of
    ``radius`` with a tail to the right), sigma estimated from the data: whichever rule
    sets ``lam`` (GCV, its floor, the prior fit, the noise-gain ceiling), the result is
    finite and at least 1 dB closer to the truth than the blurred input (returning the
    input fails; the worst of 150 random draws gained 3.1 dB)."""
    from reference.cases import texture

    from pipeline.core.quality import psnr

    x = texture((96, 112), seed)
    yy, xx = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    kernel = (yy**2 + xx**2 <= radius * radius).astype(float)
    kernel[radius, radius + 1 :] += tail
    kernel /= kernel.sum()
    y = ndimage.convolve(x, kernel, mode="reflect")
    y = y + np.random.default_rng(seed).normal(0, level, y.shape)
    out = restore(y, plan(y, kernel))
    inner = (slice(12, -12), slice(12, -12))
    assert np.all(np.isfinite(out))
    assert psnr(out[inner], x[inner]) >= psnr(y[inner], x[inner]) + 1.0


@pytest.mark.parametrize("noise", [0.0, 0.01])
def test_the_main_job_on_a_ray_traced_depth_edge_is_within_0_3_db_of_the_tuned_wiener(
    tmp_path, monkeypatch, noise
):
    """Issue 13's goal on its depth-edge scene (two 1/f textures, ray traced with occlusion
    and breathing; the truth is the scene): the main job's result within 0.3 dB of a
    Wiener filter whose ``lam`` is chosen with the truth (a scan on the job's own average
    and kernel). Before GCV's floor was kept it was 1.5 and 1.1 dB short (the texture
    reads as noise of 0.005); a floor margin of 1.3 instead of 1.15 fails here (the scene
    scores 1.23-1.25)."""
    from reference.depth_edge import depth_edge

    from pipeline.core.quality import psnr
    from pipeline.core.stack_kernel import wiener_options
    from pipeline.jobs import stack as stack_job
    from pipeline.jobs.options import StackOptions
    from pipeline.parallel.tiling import deconvolve_tiled

    folder = tmp_path / "stack"
    folder.mkdir()
    truth, _, _ = depth_edge(folder, noise)
    seen = {}
    restore = stack_job.restore_image

    def spy(image, kernel, options, **kw):
        seen.update(image=image.copy(), kernel=kernel, kw=kw)
        return restore(image, kernel, options, **kw)

    monkeypatch.setattr(stack_job, "restore_image", spy)
    job = stack_job.process_stack(folder, tmp_path / "out.tif", StackOptions(encoding="float32"))
    extra = wiener_options(seen["kernel"], seen["kw"].get("kernel_samples"))
    tuned = max(
        psnr(
            deconvolve_tiled(
                seen["image"], seen["kernel"], censored=seen["kw"].get("clipped"),
                regularization=lam, **extra,
            ),
            truth,
        )
        for lam in np.logspace(-7, -1, 13)
    )  # fmt: skip
    assert psnr(job.image, truth) >= tuned - 0.3
    assert psnr(job.image, truth) > 32.0  # and it restores (the best frame: 28.2-28.5 dB)


def test_gcvs_lam_is_scaled_to_the_datas_noise_where_its_residual_holds_kernel_mismatch(
    tmp_path,
):
    """A nine-frame three-plane stack (sigma 0.01) of a crop the benchmarks do not use: GCV
    reads a noise of 0.005 where the average's is 0.0033 (the rest is the depth-dependent
    blur the single kernel misses), and its ``lam`` (3.0e-3) left 0.89 dB to the best of a
    fine ``lam`` grid (1.0e-3). Scaled to the data's own noise estimate, the job's result
    is within 0.3 dB of that best."""
    from skimage import data
    from test_engine import make_stack, positions_for

    from pipeline.core.colour import srgb_to_linear
    from pipeline.core.quality import psnr
    from pipeline.core.stack_kernel import wiener_options
    from pipeline.jobs import stack as job
    from pipeline.jobs.options import StackOptions
    from pipeline.parallel.tiling import deconvolve_tiled

    sharp = srgb_to_linear(data.astronaut()[250:506, 200:456].astype(np.float32) / 255)
    make_stack(tmp_path, sharp, [500.0, 800.0, 1600.0], positions_for(450, 2500, 9), noise=0.01)
    seen = {}
    restore = job.restore_image

    def spy(image, kernel, options, **kw):
        seen.update(image=image.copy(), kernel=kernel, **kw)
        return restore(image, kernel, options, **kw)

    job.restore_image = spy
    try:
        options = StackOptions(encoding="float32", frame_range=False)
        result = job.process_stack(tmp_path, tmp_path / "out.tif", options).image
    finally:
        job.restore_image = restore
    extra = wiener_options(seen["kernel"], seen["kernel_samples"])
    best = max(
        psnr(
            deconvolve_tiled(
                seen["image"], seen["kernel"], method="wiener", censored=seen["clipped"],
                regularization=lam, **extra,
            ),
            sharp,
        )
        for lam in np.logspace(-3.5, -2, 7)
    )
    assert psnr(result, sharp) > best - 0.3  # measured 30.69 against 30.71 (29.82 unscaled)
