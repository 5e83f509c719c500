"""Tiled deconvolution equals the whole-frame result on deliberately uneven chunks."""

from __future__ import annotations

import dask.array as da
import numpy as np
import pytest
from scipy import signal

from pipeline.core import deconvolve as dc
from pipeline.core import psf
from pipeline.errors import InputError
from pipeline.parallel.tiling import deconvolve_tiled


def gaussian_kernel(sigma: float, half: int) -> np.ndarray:
    g = np.exp(-np.arange(-half, half + 1) ** 2 / (2 * sigma**2))
    return np.outer(g, g) / np.outer(g, g).sum()


def disk_kernel(radius: float) -> np.ndarray:
    return psf.raster_pillbox(2 * radius, int(np.ceil(radius)))


@pytest.fixture(scope="module")
def scene():
    """Blurred, noisy random-smooth RGB scene in [0, 1] (float32, 200x230x3)."""
    rng = np.random.default_rng(11)
    x = signal.fftconvolve(rng.uniform(0, 1, (220, 250, 3)), np.ones((5, 5, 1)) / 25, "valid")
    return np.clip(x + 0.05 * (rng.uniform(size=x.shape) > 0.98), 0, 1)[:200, :230]


@pytest.mark.parametrize(
    ("method", "kernel"),
    [("wiener", gaussian_kernel(2.0, 7)), ("wiener", disk_kernel(2.5)),
     ("rl", gaussian_kernel(2.0, 7)), ("rl", disk_kernel(3.5))],
    ids=["wiener-gauss", "wiener-disk", "rl-gauss", "rl-disk"],
)
def test_tiled_equals_untiled_on_uneven_chunks(scene, method, kernel):
    blurred = np.stack([signal.fftconvolve(scene[..., c], kernel, "same") for c in range(3)], -1)
    y = (blurred + np.random.default_rng(12).normal(0, 0.01, scene.shape)).astype(np.float32)
    whole = dc.deconvolve(y, kernel, method=method)
    p = dc.plan(y, kernel, method=method)
    assert 0 < p.depth < 100  # the test must really cut tiles
    lazy = da.from_array(y, chunks=((70, 23, 107), (41, 120, 69), (3,)))
    tiled = deconvolve_tiled(lazy, kernel, method=method)
    assert isinstance(tiled, da.Array)
    out = tiled.compute()
    assert out.dtype == np.float32 and out.shape == y.shape
    assert np.abs(out - whole).max() < 1e-4


def test_numpy_input_returns_numpy_and_2d():
    y = np.random.default_rng(13).uniform(0, 1, (90, 70))
    k = gaussian_kernel(1.5, 4)
    out = deconvolve_tiled(y, k, method="wiener", tile_px=32)
    assert isinstance(out, np.ndarray) and out.dtype == np.float64 and out.shape == y.shape
    assert np.abs(out - dc.deconvolve(y, k, method="wiener")).max() < 1e-4


def test_operator_wider_than_frame_uses_one_tile():
    y = np.random.default_rng(14).uniform(0, 1, (64, 64)).astype(np.float32)
    k = disk_kernel(7.5)  # pillbox, no noise: the Wiener filter reaches across the frame
    out = deconvolve_tiled(y, k, method="wiener", tile_px=16, noise_sigma=0.0)
    assert np.abs(out - dc.deconvolve(y, k, method="wiener", noise_sigma=0.0)).max() < 1e-4


def test_bad_tile_size_and_nan_rejected():
    with pytest.raises(InputError, match="tile_px"):
        deconvolve_tiled(np.zeros((8, 8)), np.ones((1, 1)), tile_px=0)
    y = np.zeros((8, 8))
    y[0, 0] = np.nan
    with pytest.raises(InputError, match="image"):
        deconvolve_tiled(da.from_array(y, chunks=4), np.ones((1, 1)))


def test_sparse_is_never_tiled_so_it_equals_the_untiled_result():
    rng = np.random.default_rng(5)
    image = rng.random((96, 80)).astype(np.float32)
    k = disk_kernel(2.5)
    options = {"iterations": 8}
    tiled = deconvolve_tiled(image, k, method="sparse", tile_px=24, **options)
    whole = dc.deconvolve(image, k, method="sparse", **options)
    np.testing.assert_allclose(tiled, whole, atol=1e-6)


@pytest.mark.parametrize("tiled", [False, True], ids=["whole frame", "tiles"])
def test_on_plan_receives_the_plan_the_result_was_restored_with(scene, tiled):
    kernel = disk_kernel(2.5)
    y = scene.astype(np.float32)
    plans = []
    image = da.from_array(y, chunks=(100, 115, 3)) if tiled else y
    out = deconvolve_tiled(image, kernel, method="wiener", on_plan=plans.append)
    assert len(plans) == 1
    expected = dc.plan(y, kernel, method="wiener")
    np.testing.assert_array_equal(plans[0].params["lam"], expected.params["lam"])
    assert plans[0].depth == expected.depth
    restored = dc.restore(y, plans[0])  # the plan handed out is the one the result used
    assert np.abs(np.asarray(out) - restored).max() < 1e-4
