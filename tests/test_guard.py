"""Issue 13: the noise target for Wiener's regulariser and the frames'-range guard."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage, signal

from pipeline.core import guard
from pipeline.core.deconvolve import deconvolve
from pipeline.core.deconvolve.dispatch import plan
from pipeline.core.deconvolve.wiener import lam_for_noise_gain, white_noise_gain
from pipeline.core.weights import frame_noise_gain
from pipeline.errors import InputError
from pipeline.parallel.accumulate import _merge, _warped_leaf, frame_range_of


def _asymmetric_kernel(size: int = 41) -> np.ndarray:
    """A wide, lopsided blur (not symmetric in either axis)."""
    yy, xx = np.mgrid[: size, : size] - size // 2
    k = np.exp(-((xx - 3) ** 2 / (2 * 9.0**2) + (yy + 1) ** 2 / (2 * 5.0**2)))
    k[np.hypot(xx, yy) > size // 2] = 0
    return k / k.sum()


def test_frame_noise_gain_is_the_averages_noise_reduction():
    rng = np.random.default_rng(0)
    w = np.array([0.5, 1.0, 1.0, 2.0, 0.25])
    frames = rng.normal(0, 1, (len(w), 200_000))
    average = (w[:, None] * frames).sum(0) / w.sum()
    assert frame_noise_gain(w) == pytest.approx(1.0 / average.std(), rel=0.02)
    assert frame_noise_gain(np.ones(9)) == pytest.approx(3.0)
    with pytest.raises(InputError):
        frame_noise_gain(np.zeros(3))


def test_lam_for_noise_gain_meets_its_target_on_real_noise():
    k = _asymmetric_kernel()
    for target in (1.5, 3.0, 6.0):
        lam = lam_for_noise_gain(k, target)
        assert white_noise_gain(k, lam) == pytest.approx(target, rel=0.01)
        # measured independently: deconvolve pure noise with that lam
        noise = np.random.default_rng(1).normal(0, 0.01, (256, 256))
        out = deconvolve(noise, k, regularization=lam, noise_sigma=0.01)
        assert out[40:-40, 40:-40].std() / 0.01 == pytest.approx(target, rel=0.15)


def test_noise_gain_caps_the_collapsed_prior_on_a_wide_kernel():
    rng = np.random.default_rng(2)
    k = _asymmetric_kernel(61)
    sharp = ndimage.gaussian_filter(rng.random((256, 256)), 1.0)
    blurred = signal.fftconvolve(np.pad(sharp, 40, mode="reflect"), k, mode="same")[40:-40, 40:-40]
    noisy = blurred + rng.normal(0, 0.0003, blurred.shape)
    free = plan(noisy, k).params["lam"]
    capped = plan(noisy, k, noise_gain=3.0).params["lam"]
    target = lam_for_noise_gain(k, 3.0)
    assert white_noise_gain(k, float(free[0])) > 4.0  # the prior fit alone amplifies noise
    assert capped[0] == pytest.approx(target)
    # linear for a fixed lam: the noise in the result is the filtered noise
    diff = deconvolve(noisy, k, regularization=target)
    diff -= deconvolve(blurred, k, regularization=target)
    assert diff[40:-40, 40:-40].std() < 3.0 * 0.0003 * 1.2
    assert deconvolve(noisy, k, noise_gain=3.0).shape == noisy.shape


def test_clip_to_frames_keeps_the_frames_range_with_slack():
    lo = np.zeros((9, 9, 3), np.float32)
    hi = np.full((9, 9, 3), 0.5, np.float32)
    hi[4, 6, 1] = 0.9  # one bright pixel in one frame: allowed within 1 px of it
    result = np.full((9, 9, 3), 0.95, np.float32)
    result[0, 0, 2] = -0.3
    out = guard.clip_to_frames(result, lo, hi)
    assert out.dtype == np.float32
    assert out[0, 0, 2] == 0.0
    assert out[4, 5, 1] == pytest.approx(0.9) and out[3, 7, 1] == pytest.approx(0.9)
    assert out[4, 3, 1] == pytest.approx(0.5)  # two px away: not widened
    assert out[4, 6, 0] == pytest.approx(0.5)  # per channel
    with pytest.raises(InputError):
        guard.clip_to_frames(result, lo[:5], hi[:5])


def test_guard_removes_ringing_but_keeps_a_restored_edge():
    # a step blurred by an asymmetric kernel; the frames span both the sharp and the blurred
    x = np.zeros((64, 128))
    x[:, 64:] = 1.0
    x = 0.2 + 0.6 * x
    k = _asymmetric_kernel(21)
    blurred = ndimage.convolve(x, k, mode="nearest")
    restored = deconvolve(blurred, k, regularization=1e-5)
    ring = max(restored.max() - 0.8, 0.2 - restored.min())
    assert ring > 0.02  # unguarded Wiener rings around the step
    lo, hi = np.minimum(x, blurred), np.maximum(x, blurred)
    guarded = guard.clip_to_frames(restored[..., None], lo[..., None], hi[..., None])[..., 0]
    assert guarded.min() >= 0.2 - 1e-6 and guarded.max() <= 0.8 + 1e-6
    err_before = np.abs(blurred - x)[8:-8, 8:-8].mean()
    assert np.abs(guarded - x)[8:-8, 8:-8].mean() < 0.5 * err_before


def test_leaves_and_merge_stream_the_frames_min_and_max(tmp_path):
    import tifffile

    rng = np.random.default_rng(3)
    frames = [rng.random((12, 10, 3)).astype(np.float32) * 0.9 for _ in range(3)]
    paths = []
    for i, f in enumerate(frames):
        paths.append(tmp_path / f"f{i}.tif")
        tifffile.imwrite(paths[-1], f, photometric="rgb")
    leaves = [_warped_leaf(str(p), None, 0.5, (12, 10, 3), True) for p in paths]
    total = _merge(_merge(leaves[0], leaves[1]), leaves[2])
    assert len(total) == 7
    np.testing.assert_allclose(total[0], 0.5 * sum(frames), rtol=1e-5)
    np.testing.assert_allclose(total[3], np.min(frames, axis=0), rtol=1e-5)
    np.testing.assert_allclose(total[4], np.max(frames, axis=0), rtol=1e-5)
    lo, _, sharpest, _ = frame_range_of(_warped_leaf(str(paths[0]), None, 0.3, (12, 10, 3), True))
    np.testing.assert_allclose(lo, frames[0], rtol=1e-6)  # one frame: its own range
    np.testing.assert_allclose(sharpest, frames[0], rtol=1e-6)
    plain = _warped_leaf(str(paths[0]), None, 1.0, (12, 10, 3))
    assert len(_merge(plain, _warped_leaf(str(paths[1]), None, 1.0, (12, 10, 3)))) == 3


def test_sharpest_fallback_restores_only_where_the_frame_is_clearly_sharper():
    rng = np.random.default_rng(4)
    texture = 0.2 + 0.6 * (rng.random((96, 160)) > 0.5)  # binary texture, fine detail
    soft = ndimage.gaussian_filter(texture, 3.0)
    # left half: the result lost the texture (the stack's end); right half: it kept it
    result = np.where(np.arange(160) < 80, soft, texture)
    sharpest = texture + rng.normal(0, 0.002, texture.shape)
    out = guard.sharpest_fallback(result[..., None], sharpest[..., None])[..., 0]
    assert np.abs(out - texture)[:, 5:60].mean() < 0.2 * np.abs(soft - texture)[:, 5:60].mean()
    np.testing.assert_allclose(out[:, 100:], result[:, 100:], atol=0.01)  # no change where equal
    # a frame that is only noisier (no more detail) is not taken
    flat = np.full((64, 64), 0.4)
    noisy = flat + rng.normal(0, 0.001, flat.shape)
    np.testing.assert_allclose(guard.sharpest_fallback(flat, noisy), flat, atol=2e-4)


def test_leaves_keep_the_sharpest_frame_per_pixel(tmp_path):
    import tifffile

    rng = np.random.default_rng(5)
    detail = (0.2 + 0.6 * (rng.random((40, 60)) > 0.5)).astype(np.float32)
    soft = ndimage.gaussian_filter(detail, 2.0).astype(np.float32)
    near = np.where(np.arange(60) < 30, detail, soft)  # left in focus
    far = np.where(np.arange(60) < 30, soft, detail)  # right in focus
    paths = [tmp_path / "near.tif", tmp_path / "far.tif"]
    for p, f in zip(paths, (near, far)):
        tifffile.imwrite(p, np.repeat(f[..., None], 3, axis=2), photometric="rgb")
    a, b = (_warped_leaf(str(p), None, 0.5, (40, 60, 3), True) for p in paths)
    sharpest = frame_range_of(_merge(a, b))[2][..., 0]  # soft: focus-weighted frames
    away = np.abs(np.arange(60) - 30) > 10  # the composite follows the frame in focus
    assert np.abs(sharpest - detail)[4:-4][:, away].mean() < 0.15 * np.abs(soft - detail).mean()
    flat = np.full((40, 60, 3), 0.3, np.float32)  # alike frames: a smooth mean, no picks
    for p, f in zip(paths, (flat, flat + 0.1)):
        tifffile.imwrite(p, f, photometric="rgb")
    a, b = (_warped_leaf(str(p), None, 0.5, (40, 60, 3), True) for p in paths)
    np.testing.assert_allclose(frame_range_of(_merge(a, b))[2], 0.35, atol=1e-4)


@pytest.mark.parametrize("command", ["stack", "sweep"])
def test_the_cli_no_longer_offers_the_sparse_method(command, capsys):
    from pipeline.cli import main

    args = [command, "x.tif", "-o", "out.tif", "--method", "sparse"]
    if command == "sweep":
        args += ["--near", "500"]
    with pytest.raises(SystemExit) as stop:
        main(args)
    assert stop.value.code == 2
    assert "invalid choice: 'sparse'" in capsys.readouterr().err


def test_restoration_span_widens_the_fitted_core():
    from pipeline.core import defocus

    assert defocus.restoration_span(40.0) == pytest.approx(40.0 * defocus.RESTORATION_SPAN_FACTOR)
    assert 1.0 < defocus.RESTORATION_SPAN_FACTOR <= 2.0
