"""``pipeline.parallel.tiling``'s tile geometry (issue 11): the tiles handed to ``restore``
against the ones worked out by hand from the tile size, the overlap and the frame edges
(``boundary="none"``: no overlap beyond the frame), and when a frame is restored whole."""

from __future__ import annotations

import logging
import threading

import numpy as np
import pytest

from pipeline.core import deconvolve as dc
from pipeline.core.deconvolve.wiener import TAPER_PX
from pipeline.errors import InputError
from pipeline.parallel import tiling
from pipeline.parallel.tiling import deconvolve_tiled

KERNEL = np.zeros((5, 5))
KERNEL[1:4, 2] = [0.2, 0.5, 0.3]


def _extents(length, tile, depth):
    """Tile extents along one axis: chunks of ``tile`` (the last shorter), each grown by
    ``depth`` on the sides that have a neighbour."""
    starts = list(range(0, length, tile))
    sizes = [min(tile, length - s) for s in starts]
    return [n + depth * ((i > 0) + (i < len(sizes) - 1)) for i, n in enumerate(sizes)]


def _tiles(rows, cols, tile, depth):
    return sorted((r, c) for r in _extents(rows, tile, depth) for c in _extents(cols, tile, depth))


@pytest.fixture
def calls(monkeypatch):
    """The (shape, main thread?) of every ``restore`` call."""
    seen = []
    real = dc.restore

    def spy(y, p, censored=None):
        seen.append((np.shape(y), threading.current_thread() is threading.main_thread()))
        return real(y, p, censored)

    monkeypatch.setattr(tiling.dc, "restore", spy)
    return seen


def _image(shape, seed=0):
    return np.random.default_rng(seed).uniform(0.2, 0.8, shape)


def test_small_tiles_are_raised_to_the_minimum_and_grown_by_the_overlap(calls, caplog):
    y = _image((150, 140, 2))
    with caplog.at_level(logging.INFO, logger="pipeline.parallel.tiling"):
        out = deconvolve_tiled(y, KERNEL, tile_px=10, overlap_px=5, noise_sigma=0.01)
    assert "tile_px 10 raised to 64 px" in caplog.text
    assert out.shape == y.shape and out.dtype == np.float64
    assert sorted((s[0], s[1]) for s, _ in calls) == _tiles(150, 140, 64, 5)
    assert {s[2] for s, _ in calls} == {2}  # channels are never split
    caplog.clear()
    calls.clear()
    with caplog.at_level(logging.INFO, logger="pipeline.parallel.tiling"):
        deconvolve_tiled(y[..., 0], KERNEL, tile_px=64, overlap_px=0, noise_sigma=0.01)
    assert "raised" not in caplog.text
    assert sorted(s for s, _ in calls) == _tiles(150, 140, 64, 0)


def test_an_overlap_as_wide_as_an_axis_makes_one_tile_along_it(calls):
    y = _image((64, 100))
    deconvolve_tiled(y, KERNEL, tile_px=64, overlap_px=100, noise_sigma=0.01)
    assert [s for s, _ in calls] == [(64, 100)]
    calls.clear()
    deconvolve_tiled(y, KERNEL, tile_px=64, overlap_px=36, noise_sigma=0.01)
    assert sorted(s for s, _ in calls) == [(64, 72), (64, 100)]  # 64 + 36, 36 + 36


def test_frames_up_to_the_whole_frame_limit_are_restored_whole(calls, monkeypatch):
    y = _image((300, 480), seed=1)
    p = dc.plan(y, KERNEL, noise_sigma=0.1, auto="prior")  # the geometry below is for its lam
    tile = tiling.TILE_OVER_REACH * (2 * p.depth + TAPER_PX)  # times (reach + taper)
    assert 0 < p.depth and tile < 300 and 480 % tile >= p.depth and 300 - tile >= p.depth
    monkeypatch.setattr(tiling, "WHOLE_FRAME_PX", 300 * 480)
    whole = deconvolve_tiled(y, KERNEL, tile_px=64, noise_sigma=0.1, auto="prior")
    assert calls == [((300, 480), True)]  # in this thread, no dask
    calls.clear()
    monkeypatch.setattr(tiling, "WHOLE_FRAME_PX", 300 * 480 - 1)
    tiled = deconvolve_tiled(y, KERNEL, tile_px=64, noise_sigma=0.1, auto="prior")
    assert sorted(s for s, _ in calls) == _tiles(300, 480, tile, p.depth)
    np.testing.assert_allclose(tiled, whole, atol=1e-4)


def test_censored_pixels_are_tiled_with_the_image():
    y = _image((130, 120, 3), seed=2)
    censored = np.zeros((130, 120), bool)
    censored[::7, ::5] = True
    y[censored] = 0.95
    whole = dc.deconvolve(y, KERNEL, noise_sigma=0.01, saturation=0.9, censored=censored)
    tiled = deconvolve_tiled(
        y, KERNEL, tile_px=64, overlap_px=40, noise_sigma=0.01, saturation=0.9, censored=censored
    )
    np.testing.assert_allclose(tiled, whole, atol=1e-4)
    grey = deconvolve_tiled(
        y[..., 1],
        KERNEL,
        tile_px=64,
        overlap_px=40,
        noise_sigma=0.01,
        saturation=0.9,
        censored=censored,
    )
    np.testing.assert_allclose(grey, whole[..., 1], atol=1e-4)


def test_tile_and_overlap_bounds():
    y = _image((20, 20))
    for tile_px, overlap_px in ((1, None), (64, 0)):  # both accepted
        assert (
            deconvolve_tiled(
                y, KERNEL, tile_px=tile_px, overlap_px=overlap_px, noise_sigma=0.01
            ).shape
            == y.shape
        )
    for bad in (-1, True):
        with pytest.raises(InputError, match="overlap_px"):
            deconvolve_tiled(y, KERNEL, overlap_px=bad)


def test_dask_channels_in_separate_chunks_keep_their_own_noise_levels():
    import dask.array as da

    y = _image((70, 60, 3), seed=3)
    sigmas = [0.01, 0.2, 0.05]  # one plan entry per channel: a channel alone in a chunk
    whole = dc.deconvolve(y, KERNEL, noise_sigma=sigmas)  # would be restored as channel 0
    tiled = deconvolve_tiled(da.from_array(y, chunks=(70, 60, 1)), KERNEL, noise_sigma=sigmas)
    np.testing.assert_allclose(tiled.compute(), whole, atol=1e-6)


# --- mutation kills (helper mut11) -------------------------------------------------------------


def test_the_default_tile_is_1024_px(calls):
    y = _image((1030, 16), seed=4)
    deconvolve_tiled(y, KERNEL, overlap_px=3, noise_sigma=0.01, auto="prior")
    assert sorted(s for s, _ in calls) == _tiles(1030, 16, 1024, 3) == [(9, 16), (1027, 16)]


def test_an_unknown_core_count_runs_on_one(monkeypatch):
    """``os.cpu_count()`` may return None (documented): the FFTs and channels then use one
    thread, on both paths, with the same result."""
    y = _image((80, 70, 2), seed=5)
    want = dc.deconvolve(y, KERNEL, noise_sigma=0.01)
    monkeypatch.setattr(tiling.os, "cpu_count", lambda: None)
    np.testing.assert_allclose(deconvolve_tiled(y, KERNEL, noise_sigma=0.01), want, atol=1e-12)
    tiled = deconvolve_tiled(y, KERNEL, tile_px=64, overlap_px=40, noise_sigma=0.01)
    np.testing.assert_allclose(tiled, want, atol=1e-4)


@pytest.mark.parametrize(
    ("cores", "limit_px", "threads"),
    # 60 x 50 = 3000 px: at the limit three threads, one pixel under it two (the area,
    # not a side, its square or the sum of the sides, is compared)
    [
        (2, 10**6, 3),
        (2, 100, 2),
        (4, 10**6, 4),
        (1, 10**6, 1),
        (8, 100, 8),
        (2, 3000, 3),
        (2, 2999, 2),
    ],
)
def test_channel_threads_beyond_the_cores_only_for_small_frames(
    monkeypatch, cores, limit_px, threads
):
    """Three channels on two cores get three threads up to CHANNEL_PER_THREAD_PX (a core
    is not left idle a third of the time), one per core above it (the third channel's
    grids cost memory), one with one core; the result is the same either way."""
    y = _image((60, 50, 3), seed=7)
    want = dc.deconvolve(y, KERNEL, noise_sigma=0.01)
    seen = []
    real = tiling.channel_threads

    def recording(n):
        seen.append(n)
        return real(n)

    monkeypatch.setattr(tiling.os, "cpu_count", lambda: cores)
    monkeypatch.setattr(tiling, "CHANNEL_PER_THREAD_PX", limit_px)
    monkeypatch.setattr(tiling, "channel_threads", recording)
    np.testing.assert_allclose(deconvolve_tiled(y, KERNEL, noise_sigma=0.01), want, atol=1e-12)
    assert seen == [threads]


@pytest.mark.parametrize("dtype", [np.uint8, np.float16, np.int16])
def test_tiled_input_of_other_types_is_restored_in_float64(dtype):
    """The dtype policy on the tiled path: float32 stays float32, anything else is restored
    in float64 (as :func:`dc.deconvolve` does), not in float32 because it would fit."""
    y = (_image((70, 90), seed=8) * 100).astype(dtype)
    options = dict(tile_px=64, overlap_px=30, noise_sigma=0.5)
    tiled = deconvolve_tiled(y, KERNEL, **options)
    assert tiled.dtype == dc.deconvolve(y, KERNEL, noise_sigma=0.5).dtype == np.float64
    want = deconvolve_tiled(y.astype(np.float64), KERNEL, **options)
    np.testing.assert_allclose(tiled, want, rtol=0, atol=1e-12)


def test_a_lazy_wide_frame_is_one_tile_for_the_sparse_method():
    """The sparse method is non-linear: a dask frame wider than tall, chunked in 64 px
    tiles, is restored as one tile along both axes and equals the whole-frame result."""
    import dask.array as da

    y = _image((40, 150), seed=9).astype(np.float32)
    options = dict(method="sparse", iterations=3, noise_sigma=0.01)
    want = dc.deconvolve(y, KERNEL, **options)
    tiled = deconvolve_tiled(da.from_array(y, chunks=(64, 64)), KERNEL, tile_px=64, **options)
    np.testing.assert_allclose(np.asarray(tiled), want, atol=1e-6)


def test_censored_colour_tiles_reach_richardson_lucy():
    """Wiener does not read the mask; RL does: a colour frame's mask tiles (one channel,
    broadcast) give the untiled result, which differs from ignoring the mask."""
    y = _image((130, 120, 3), seed=6)
    censored = np.zeros((130, 120), bool)
    censored[::7, ::5] = True
    y[censored] = 0.95
    options = dict(method="rl", iterations=3, noise_sigma=0.01)
    whole = dc.deconvolve(y, KERNEL, censored=censored, **options)
    tiled = deconvolve_tiled(y, KERNEL, tile_px=64, overlap_px=40, censored=censored, **options)
    np.testing.assert_allclose(tiled, whole, atol=1e-6)
    assert np.abs(whole - dc.deconvolve(y, KERNEL, **options)).max() > 1e-3  # the mask counts


def test_richardson_lucy_is_tiled_and_only_the_sparse_method_is_restored_whole(calls, monkeypatch):
    """Over the whole-frame limit a linear method's tiles overlap by its reach; the sparse
    method (non-linear: tiles differ at any overlap) is one tile whatever its size."""
    monkeypatch.setattr(tiling, "WHOLE_FRAME_PX", 1)
    y = _image((200, 190), seed=3)
    deconvolve_tiled(y, KERNEL, method="rl", tile_px=64, noise_sigma=0.01, iterations=2)
    assert len(calls) > 1 and all(s[0] < 200 or s[1] < 190 for s, _ in calls)
    calls.clear()
    deconvolve_tiled(y, KERNEL, method="sparse", tile_px=64, noise_sigma=0.01, iterations=2)
    assert [s for s, _ in calls] == [(200, 190)]
