"""The multi-frame method (``--method multiframe``, :mod:`pipeline.core.multiframe`) against
independent computations: the per-depth estimate against the normal equations solved with
explicit circulant matrices (no FFT), the depth choice and the restoration on scenes
rendered by direct convolution with asymmetric kernels, and the main job's goal of issue 13
(+1 dB over the default on noisy synthetic stacks) on the 3-plane and depth-edge scenes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from reference.depth_edge import depth_edge
from reference.matrices import DX, DY, circulant
from scipy import ndimage
from scipy.signal import fftconvolve
from test_engine import make_stack, positions_for

from pipeline.cli import main
from pipeline.core import align, multiframe
from pipeline.core.deconvolve.common import _kernel_fft, _laplacian_spectrum
from pipeline.core.quality import psnr
from pipeline.errors import InputError
from pipeline.io.read import read_frame
from pipeline.io.write import write_image
from pipeline.jobs.options import StackOptions
from pipeline.jobs.result import restore_image
from pipeline.jobs.stack import process_stack
from pipeline.parallel.accumulate import SATURATION
from pipeline.parallel.scheduler import scheduler_context


def _spur(size: int, turn: int) -> np.ndarray:
    """An asymmetric kernel: a bar with a spur on one side, rotated by ``turn`` quarters."""
    k = np.zeros((size, size))
    c = size // 2
    k[c, 1 : size - 1] = 1.0
    k[1:c, size - 2] = 0.6
    k[c + 1, 2] = 0.3
    return np.rot90(k / k.sum(), turn)


def _texture(shape, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return ndimage.gaussian_filter(rng.uniform(0.0, 1.0, shape), 1.0)


def _render(x: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Direct convolution of ``x`` extended by reflection (a wider scene), cropped."""
    h = kernel.shape[0] // 2
    return fftconvolve(np.pad(x, h, mode="reflect"), kernel, mode="valid")


# ----------------------------------------------------------------------------- the estimate
@pytest.mark.parametrize("lam", [1e-3, 0.05])
def test_estimate_solves_the_normal_equations(lam):
    """``sum_k H_k^T H_k + lam D^T D`` with circulant H_k, D built by loops: the Fourier
    closed form must equal the dense solve, and not the one with flipped kernels."""
    shape = (6, 7)
    rng = np.random.default_rng(4)
    kernels = [_spur(5, t) for t in range(3)]
    y = [rng.uniform(0.0, 1.0, shape) for _ in kernels]
    hs = [circulant(k, shape) for k in kernels]
    dx, dy = circulant(DX, shape), circulant(DY, shape)
    lhs = sum(h.T @ h for h in hs) + lam * (dx.T @ dx + dy.T @ dy) + 1e-12 * np.eye(42)
    dense = np.linalg.solve(lhs, sum(h.T @ yk.ravel() for h, yk in zip(hs, y))).reshape(shape)
    k_fft = np.stack([_kernel_fft(k, shape, np.float64) for k in kernels])
    y_fft = np.stack([np.fft.rfft2(yk) for yk in y])
    d2 = _laplacian_spectrum(shape, np.float64)
    got = np.fft.irfft2(multiframe.wiener_estimate(y_fft, k_fft, lam, d2), s=shape)
    # the DC term is unregularised in both; the dense system's tiny ridge moves it by ~1e-10
    np.testing.assert_allclose(got, dense, atol=1e-8)
    spectra, power = multiframe.kernel_spectra(kernels, shape)
    again = multiframe.wiener_estimate(y_fft, spectra, lam, d2, power)
    np.testing.assert_allclose(np.fft.irfft2(again, s=shape), dense, atol=1e-8)
    flipped = np.stack([_kernel_fft(k[::-1, ::-1], shape, np.float64) for k in kernels])
    other = np.fft.irfft2(multiframe.wiener_estimate(y_fft, flipped, lam, d2), s=shape)
    assert np.max(np.abs(other - dense)) > 1e-2


def test_kernel_spectra_real_for_symmetric_kernels():
    """A kernel symmetric under a half turn has a real spectrum (kept real); an asymmetric one
    keeps its phase; the power is sum |K|^2 (against numpy's FFT of the rolled kernel)."""
    shape = (12, 10)
    disc = np.array([[0, 1, 0], [1, 2, 1], [0, 1, 0]], float) / 6
    spur = _spur(5, 1)
    spectra, power = multiframe.kernel_spectra([disc, spur], shape)
    assert np.isrealobj(spectra[0]) and np.iscomplexobj(spectra[1])
    for k, got in zip((disc, spur), spectra):
        grid = np.zeros(shape)
        grid[: k.shape[0], : k.shape[1]] = k
        want = np.fft.rfft2(np.roll(grid, (-(k.shape[0] // 2), -(k.shape[1] // 2)), (0, 1)))
        np.testing.assert_allclose(got, want, atol=1e-12)
    np.testing.assert_allclose(power, sum(np.abs(s) ** 2 for s in spectra), atol=1e-12)


# ----------------------------------------------------------------------------- depth and restore
def _two_depth_stack(noise: float, seed: int = 5):
    """Frames of a scene whose left half lies at depth 0 and right half at depth 2 of the
    candidates ``[0, 1, 2]``: frame ``k`` blurs depth ``d`` by ``_spur(2 |k - d| + 1)``
    (frame 0 sharp on the left, frame 2 on the right)."""
    x = _texture((48, 64), seed)
    rng = np.random.default_rng(seed + 1)

    def kernels_at(d: float, scale: float = 1.0):
        assert scale == 1.0
        sizes = [2 * round(abs(k - d)) + 1 for k in range(3)]
        return [_spur(s, k) if s > 1 else np.ones((1, 1)) for k, s in enumerate(sizes)]

    left, right = np.zeros_like(x), np.zeros_like(x)
    left[:, :32], right[:, 32:] = x[:, :32], x[:, 32:]
    frames = []
    for k in range(3):
        ka, kb = kernels_at(0.0)[k], kernels_at(2.0)[k]
        frame = _render(left, ka) + _render(right, kb)
        frames.append(frame + rng.normal(0.0, noise, frame.shape))
    return x, np.array(frames), kernels_at


def test_depth_index_finds_each_half():
    x, frames, kernels_at = _two_depth_stack(0.005)
    lam = multiframe.regularisation(frames, x)
    depths = np.array([0.0, 1.0, 2.0])
    index, unexplained = multiframe.depth_index(frames, kernels_at, depths, lam)
    assert np.mean(index[4:-4, 4:24] == 0) > 0.95
    assert np.mean(index[4:-4, 40:-4] == 2) > 0.95
    assert np.median(unexplained[4:-4, 4:24]) < 0.1  # the model explains the frames


def test_misregistered_frames_lean_on_the_fallback():
    """Frames 6 px out of register (the model's frames are aligned): the model leaves much
    of their detail unexplained (median 0.75 against 0.005 aligned), and the result keeps
    more of the fallback."""
    x, frames, kernels_at = _two_depth_stack(0.005)
    depths = np.array([0.0, 1.0, 2.0])
    moved = np.stack([frames[0], np.roll(frames[1], 6, 1), np.roll(frames[2], -6, 0)])
    lam = multiframe.regularisation(frames, x)
    _, unexplained = multiframe.depth_index(moved, kernels_at, depths, lam)
    assert np.median(unexplained[4:-4, 4:-4]) > 0.5
    _, aligned = multiframe.restore(frames, kernels_at, depths, np.mean(frames, axis=0))
    _, info = multiframe.restore(moved, kernels_at, depths, np.mean(moved, axis=0))
    assert info["share"] < 0.7 * aligned["share"]
    # the fit, not only a restless depth map, holds it back
    index, _ = multiframe.depth_index(moved, kernels_at, depths, lam)
    steady = multiframe.steady_weight(index, multiframe.STEADY_RADIUS_PX, None)
    assert info["share"] < 0.8 * float(np.mean(steady))


def test_supported_weight_rejects_detail_no_frame_shows():
    """A maze of fine ringing where every frame is smooth is not the scene's detail; the
    sharpest frame's own detail is."""
    rng = np.random.default_rng(8)
    sharp = ndimage.gaussian_filter(rng.uniform(0, 1, (64, 64)), 0.7).astype(np.float32)
    frames = np.stack([sharp, ndimage.gaussian_filter(sharp, 2.0)])
    assert np.min(multiframe.supported_weight(sharp, frames)[8:-8, 8:-8]) > 0.99
    smooth = np.stack([ndimage.gaussian_filter(sharp, s) for s in (2.0, 3.0)])
    maze = smooth[0] + 0.05 * np.where((np.indices(sharp.shape).sum(axis=0) // 2) % 2, 1, -1)
    w = multiframe.supported_weight(maze.astype(np.float32), smooth)
    assert np.max(w[8:-8, 8:-8]) < 0.01


def test_a_model_that_over_restores_is_held_to_the_frames_detail():
    """Kernels twice too wide (the model says the frames are blurrier than they are): the
    estimate over-sharpens into ringing; the result keeps under twice the sharpest frame's
    fine detail everywhere (1.7x; 2.7x without the check)."""
    _, frames, _ = _two_depth_stack(0.002)

    def too_wide(d, scale=1.0):
        return [_spur(4 * round(abs(k - d)) + 5, k) for k in range(3)]

    out, _ = multiframe.restore(frames, too_wide, np.array([0.0, 1.0, 2.0]), frames.mean(axis=0))
    detail = multiframe._detail(out.astype(np.float32))
    sharpest = np.max([multiframe._detail(f.astype(np.float32)) for f in frames], axis=0)
    assert np.max((detail / sharpest)[6:-6, 6:-6]) < 2.0


def test_unexplained_shares_rank_alignments():
    """The same frames aligned and 3 px out of register: the model explains the aligned
    ones far better (the measure the main job chooses an alignment by)."""
    _, frames, kernels_at = _two_depth_stack(0.005)
    moved = np.stack([frames[0], np.roll(frames[1], 3, 1), np.roll(frames[2], -3, 1)])
    aligned, shifted = multiframe.unexplained_shares(
        [frames, moved], kernels_at, np.array([0.0, 1.0, 2.0])
    )
    assert aligned < 0.2 * shifted


def test_fit_weight():
    low, high = multiframe.FIT_SHARE
    got = multiframe.fit_weight(np.array([0.0, low, (low + high) / 2, high, 10.0]))
    np.testing.assert_allclose(got, [1.0, 1.0, 0.5, 0.0, 0.0], atol=1e-6)


def test_restore_beats_every_frame_and_the_fallback():
    x, frames, kernels_at = _two_depth_stack(0.01)
    fallback = np.mean(frames, axis=0)  # a poor fallback: only the depth edge keeps it
    out, info = multiframe.restore(frames, kernels_at, np.array([0.0, 1.0, 2.0]), fallback)
    inner = (slice(6, -6), slice(6, -6))
    best = max(psnr(f[inner], x[inner]) for f in frames)
    assert psnr(out[inner], x[inner]) > best + 3.0
    assert 0.5 < info["share"] < 1.0  # the edge keeps the fallback
    assert info["depths"][1] < 0.1 * out.size  # the missing middle depth is rarely chosen


def test_restore_with_flipped_kernels_is_worse():
    """Orientation matters: the kernels of the model, flipped, restore far worse."""
    x, frames, kernels_at = _two_depth_stack(0.0)
    fallback = np.mean(frames, axis=0)
    depths = np.array([0.0, 1.0, 2.0])
    right, _ = multiframe.restore(frames, kernels_at, depths, fallback)

    def flipped(d, scale=1.0):
        return [k[::-1, ::-1] for k in kernels_at(d, scale)]

    wrong, _ = multiframe.restore(frames, flipped, depths, fallback)
    inner = (slice(6, -6), slice(6, -6))
    assert psnr(right[inner], x[inner]) > psnr(wrong[inner], x[inner]) + 3.0  # 41.9 vs 38.0


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    noise=st.sampled_from([0.0, 1e-4, 0.01, 0.05]),
    flat=st.sampled_from([None, 0.0, 1.0]),
)
@example(seed=0, noise=0.0, flat=0.0)  # a black scene: zero gradient, zero noise
@example(seed=1, noise=0.0, flat=1.0)  # a white one
def test_restore_is_finite_and_in_range(seed, noise, flat):
    """Zero noise, a flat scene (no gradient: the prior's scale is 0) or heavy noise: the
    result stays finite and within the frames' plausible range."""
    _, frames, kernels_at = _two_depth_stack(noise, seed)
    if flat is not None:
        frames = np.full_like(frames, flat)
    fallback = np.mean(frames, axis=0)
    out, _ = multiframe.restore(frames, kernels_at, np.array([0.0, 1.0, 2.0]), fallback)
    assert np.all(np.isfinite(out))
    spread = float(np.ptp(frames)) + 1e-6
    assert np.min(out) > np.min(frames) - 2 * spread and np.max(out) < np.max(frames) + 2 * spread


def test_restore_keeps_the_fallback_near_blocked_pixels():
    x, frames, kernels_at = _two_depth_stack(0.01)
    fallback = np.mean(frames, axis=0).astype(np.float32)
    blocked = np.zeros(x.shape, bool)
    blocked[10, 8:14] = True
    out, _ = multiframe.restore(
        frames, kernels_at, np.array([0.0, 1.0, 2.0]), fallback, blocked=blocked
    )
    assert np.all(out[blocked] == fallback[blocked])  # clipped: exactly the fallback
    assert np.abs(out[30, 10] - fallback[30, 10]) > 1e-3  # elsewhere the estimate


def test_restore_where_the_model_holds_nowhere_is_the_fallback():
    """Every pixel blocked: no depth is used, the fallback comes back as it is (and no
    full-size spectra are computed)."""
    _, frames, kernels_at = _two_depth_stack(0.01)
    fallback = (np.mean(frames, axis=0) + 0.1).astype(np.float32)  # not any frame's mean
    out, info = multiframe.restore(
        frames, kernels_at, np.array([0.0, 1.0, 2.0]), fallback,
        blocked=np.ones(fallback.shape, bool),
    )  # fmt: skip
    assert info["share"] == 0.0 and np.array_equal(out, fallback) and out is not fallback


def test_multiframe_refuses_frames_at_one_focus_position(tmp_path, sharp):
    make_stack(tmp_path, sharp, [800.0], [12.7, 12.7, 12.7])
    with pytest.raises(InputError, match="same focus position; fix the positions"):
        process_stack(tmp_path, tmp_path / "out.tif", StackOptions(method="multiframe"))
    assert not (tmp_path / "out.tif").exists()


def test_restore_rejects_bad_input():
    x, frames, kernels_at = _two_depth_stack(0.0)
    depths = np.array([0.0, 1.0, 2.0])
    bad = frames.copy()
    bad[1, 3, 3] = np.nan
    with pytest.raises(InputError, match="finite"):
        multiframe.restore(bad, kernels_at, depths, x)
    with pytest.raises(InputError, match="fallback has shape"):
        multiframe.restore(frames, kernels_at, depths, x[:-1])
    with pytest.raises(InputError, match="n >= 2"):
        multiframe.restore(frames[:1], kernels_at, depths, x)


def test_candidate_depths():
    got = multiframe.candidate_depths(np.array([3.0, 1.0, 2.0, 2.0]), beyond=(0.5, 0.25))
    np.testing.assert_allclose(got, [0.0, 0.5, 1.0, 2.0, 3.0, 3.5, 4.0])
    with pytest.raises(InputError, match="two or more focus positions"):
        multiframe.candidate_depths(np.array([2.0, 2.0]))


def test_steady_weight_drops_at_depth_jumps_only():
    index = np.zeros((40, 60), np.int32)
    index[:, 30:] = 1  # one step: the same region for the method
    index[:, 45:] = 3  # a jump of two steps at column 45
    w = multiframe.steady_weight(index, 4, None)
    assert w[20, 10] == pytest.approx(1.0, abs=1e-3) and w[20, 30] == pytest.approx(1.0, abs=1e-3)
    assert w[20, 45] < 0.1


# ----------------------------------------------------------------------------- resampling
def test_lanczos_keeps_fine_detail_that_bilinear_halves():
    """A 0.35 cycles/px grating shifted by half a pixel: bilinear interpolation averages
    neighbours (response cos(pi f) = 0.45), Lanczos-4 keeps it within 5%, bicubic (the end
    frames' detail) in between (0.72)."""
    cols = np.arange(200)
    grating = np.tile(0.5 + 0.4 * np.cos(2 * np.pi * 0.35 * cols), (40, 1)).astype(np.float32)
    shift = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    for interpolation, low, high in (
        ("linear", 0.40, 0.50),
        ("cubic", 0.65, 0.80),
        ("lanczos", 0.95, 1.05),
    ):
        out = align.warp(grating, shift, grating.shape, interpolation=interpolation)
        amplitude = np.ptp(out[20, 20:-20]) / 2
        assert low < amplitude / 0.4 < high, interpolation
    with pytest.raises(InputError, match="interpolation must be one of"):
        align.warp(grating, shift, grating.shape, interpolation="spline")


# ----------------------------------------------------------------------------- the main job
def _job_psnr(folder: Path, tmp: Path, truth, method: str) -> tuple[float, dict]:
    with scheduler_context(threads=2):
        result = process_stack(folder, tmp / f"{method}.tif", StackOptions(method=method))
    return psnr(result.image, truth), result.sidecar


def test_multiframe_gains_a_decibel_on_the_noisy_three_planes(tmp_path, sharp):
    """Issue 13's goal for the quality method: at least +1 dB over the default when noisy
    (measured +2.35 dB; the three-plane scene of the engine tests, sigma 0.01)."""
    folder = tmp_path / "stack"
    folder.mkdir()
    make_stack(folder, sharp, [500.0, 800.0, 1600.0], positions_for(450, 2500, 9), noise=0.01)
    default, _ = _job_psnr(folder, tmp_path, sharp, "wiener")
    quality, sidecar = _job_psnr(folder, tmp_path, sharp, "multiframe")
    assert quality > default + 1.0
    assert sidecar["method"] == "multiframe" and 0.0 < sidecar["multiframe"]["share"] <= 1.0


def test_multiframe_gains_on_the_ray_traced_depth_edge(tmp_path):
    """Occlusion and breathing (the ray-traced depth edge, sigma 0.01): +3.0 dB measured."""
    truth, _, _ = depth_edge(tmp_path, 0.01)
    default, _ = _job_psnr(tmp_path, tmp_path, truth, "wiener")
    quality, _ = _job_psnr(tmp_path, tmp_path, truth, "multiframe")
    assert quality > default + 2.0


def test_multiframe_keeps_the_frames_range_and_quiet_flat_areas(tmp_path, sharp):
    """Like the default, the result stays within the frames' 3x3 range (computed here from
    the frames as written: no alignment) and a flat area keeps the average's quiet fine band
    rather than the in-focus frame's grain."""
    scene = sharp.copy()
    scene[:, 170:] = 0.3  # a flat far third
    folder = tmp_path / "stack"
    folder.mkdir()
    make_stack(folder, scene, [500.0, 800.0, 1600.0], positions_for(450, 2500, 9), noise=0.002)
    with scheduler_context(threads=2):
        runs = {
            m: process_stack(folder, tmp_path / f"{m}.tif", StackOptions(method=m, align="none"))
            for m in ("wiener", "multiframe")
        }
    frames = np.stack([read_frame(f) for f in sorted(folder.glob("frame_*.tif"))])
    lo = ndimage.minimum_filter(frames.min(axis=0), size=(3, 3, 1))
    hi = ndimage.maximum_filter(frames.max(axis=0), size=(3, 3, 1))
    image = runs["multiframe"].image
    tol = 2.0 / 65535  # the range is kept as 16-bit codes, widened by one code
    open_top = np.any(frames >= SATURATION, axis=(0, 3))  # clipped: no upper bound there
    assert np.all(image >= lo - tol)
    assert np.all((image <= hi + tol) | open_top[..., None])

    def grain(a):
        flat = a[20:-20, 190:-20]
        return float(np.std(flat - ndimage.gaussian_filter(flat, (1, 1, 0))))

    assert grain(image) < 1.2 * grain(runs["wiener"].image)
    assert grain(image) < 0.5 * grain(frames[0])


def test_multiframe_keeps_the_default_where_a_frame_clipped(tmp_path, sharp):
    """A highlight brighter than white, clipped in the frames focused on it: the linear model
    does not hold there, so those pixels keep the default's result exactly."""
    scene = sharp.copy()
    scene[100:112, 40:52] = 3.0
    folder = tmp_path / "stack"
    folder.mkdir()
    make_stack(folder, scene, [500.0, 800.0, 1600.0], positions_for(450, 2500, 9), noise=0.005)
    frames = np.stack([np.minimum(read_frame(f), 1.0) for f in sorted(folder.glob("frame_*"))])
    for i, frame in enumerate(frames):  # as a camera writes it: clipped at white
        write_image(folder / f"frame_{i:02d}.tif", frame, encoding="float32")
    clipped = np.any(frames >= SATURATION, axis=(0, 3))
    assert 50 < clipped.sum() < 2000
    with scheduler_context(threads=2):
        runs = {
            m: process_stack(folder, tmp_path / f"{m}.tif", StackOptions(method=m, align="none"))
            for m in ("wiener", "multiframe")
        }
    default, quality = runs["wiener"].image, runs["multiframe"].image
    # float32 rounding of the blend only (2e-7); the estimate there would move them by 0.05
    np.testing.assert_allclose(quality[clipped], default[clipped], atol=1e-5)
    assert np.max(np.abs(quality - default)) > 0.1  # elsewhere the multi-frame estimate


def test_multiframe_only_for_focal_stacks(tmp_path):
    with pytest.raises(InputError, match="multiframe restores a focal stack"):
        restore_image(
            np.zeros((8, 8), np.float32), np.ones((1, 1)), StackOptions(method="multiframe")
        )
    with pytest.raises(SystemExit) as exit_info:  # argparse: not a choice of flexdof sweep
        main(["sweep", str(tmp_path / "x.tif"), "-o", str(tmp_path / "o.tif"), "--method",
              "multiframe", "--lens", "x", "--near-mm", "500"])
    assert exit_info.value.code == 2


@pytest.fixture(scope="module")
def sharp():
    from skimage import data

    from pipeline.core.colour import srgb_to_linear

    return srgb_to_linear(data.astronaut()[40:296, 130:386].astype(np.float32) / 255)
