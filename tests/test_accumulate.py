"""``pipeline.parallel.accumulate`` details against independent computations (issue 11):
warped leaves against a shifted numpy array, per-row colour weights against a numpy
broadcast, the decode-time sum against a counting clock, the clipping mask on one
channel and at the level itself."""

from __future__ import annotations

from types import SimpleNamespace

import dask
import numpy as np
import pytest

from pipeline.io.read import read_frame
from pipeline.io.write import write_image
from pipeline.parallel import accumulate
from pipeline.parallel.accumulate import SATURATION, clipped_pixels, weighted_sum_graph


def _write(tmp_path, arrays):
    paths, decoded = [], []
    for i, a in enumerate(arrays):
        path = tmp_path / f"g{i}.tif"
        write_image(path, a.astype(np.float32), encoding="float32")
        paths.append(path)
        decoded.append(read_frame(path).astype(np.float64))
    return paths, decoded


def test_a_translation_warps_each_frame_before_weighting(tmp_path):
    rng = np.random.default_rng(7)
    shape = (12, 15)
    paths, frames = _write(tmp_path, [rng.uniform(0.0, 0.9, shape) for _ in range(3)])
    shifts = [(0, 0), (2, 1), (1, 3)]  # (rows, cols) moved down/right on the reference
    homographies = [np.array([[1.0, 0, dc], [0, 1.0, dr], [0, 0, 1]]) for dr, dc in shifts]
    weights = [0.5, 0.2, 0.3]
    total, _, _, _, _, _ = dask.compute(
        weighted_sum_graph(paths, homographies, weights, shape), scheduler="sync"
    )[0]
    ref = np.zeros(shape)
    for (dr, dc), w, f in zip(shifts, weights, frames):
        ref[dr:, dc:] += w * f[: shape[0] - dr, : shape[1] - dc]  # out(y) = frame(y - d)
    np.testing.assert_allclose(total[3:, 3:], ref[3:, 3:], rtol=1e-5, atol=1e-6)


def test_per_row_weights_on_colour_frames(tmp_path):
    rng = np.random.default_rng(8)
    shape = (7, 4)
    paths, frames = _write(tmp_path, [rng.uniform(0.0, 0.9, (*shape, 3)) for _ in range(3)])
    rows = rng.uniform(0.0, 1.0, (3, shape[0]))
    total, _, _, _, _, _ = dask.compute(
        weighted_sum_graph(paths, [None] * 3, list(rows), shape), scheduler="sync"
    )[0]
    ref = np.zeros((*shape, 3))
    for r, f in zip(rows, frames):
        for i in range(shape[0]):
            ref[i] += r[i] * f[i]
    np.testing.assert_allclose(total, ref, rtol=1e-5, atol=1e-6)


def test_decode_seconds_are_summed_over_the_frames_read(tmp_path, monkeypatch):
    ticks = iter(range(1000))  # a clock of this module only, one tick per reading
    monkeypatch.setattr(accumulate, "time", SimpleNamespace(perf_counter=lambda: next(ticks)))
    rng = np.random.default_rng(9)
    paths, _ = _write(tmp_path, [rng.uniform(0.0, 0.9, (5, 6)) for _ in range(6)])
    weights = [0.1, 0.0, 0.2, 0.3, 0.1, 0.3]  # frame 1 is never read
    _, _, read_s, _, _, _ = dask.compute(
        weighted_sum_graph(paths, [None] * 6, weights, (5, 6)), scheduler="sync"
    )[0]
    assert read_s == 5.0  # one tick per read, five frames read


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_clipping_in_one_channel_and_at_the_level_itself(dtype):
    """float32 frames take OpenCV's one-pass path, other types numpy's: the same mask."""
    level = dtype(SATURATION)
    image = np.full((3, 4, 3), 0.5, dtype)
    image[0, 1, 1] = 1.0  # only the middle channel
    image[2, 3, 2] = 1.0  # only the last one
    image[1, 2, 0] = level  # exactly at the level: clipped
    image[0, 3, 2] = level  # and in the last channel
    image[2, 0, 0] = 1.0  # above the level in the first channel
    image[1, 0, 1] = np.nextafter(level, 0.0)  # just below: not
    expected = np.zeros((3, 4), bool)
    expected[0, 1] = expected[2, 3] = expected[1, 2] = expected[0, 3] = expected[2, 0] = True
    np.testing.assert_array_equal(clipped_pixels(image), expected)
    assert clipped_pixels(image).view(np.uint8).max() == 1  # numpy's bools: bytes 0 and 1
    np.testing.assert_array_equal(clipped_pixels(image[..., 1]), expected & [[0, 1, 0, 0]] * 3)
    grey = np.array([[level, np.nextafter(level, dtype(0.0)), 1.0]], dtype)
    np.testing.assert_array_equal(clipped_pixels(grey), [[True, False, True]])
    four = np.concatenate([image, np.full((3, 4, 1), 0.5, dtype)], axis=2)
    four[1, 1, 3] = 1.0  # clipped in a fourth channel only
    expected[1, 1] = True
    np.testing.assert_array_equal(clipped_pixels(four), expected)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_a_nan_counts_as_clipped(dtype):
    image = np.full((2, 3, 3), 0.5, dtype)
    image[1, 2, 1] = np.nan
    image[0, 0, 2] = -np.inf  # far below the level: not clipped
    expected = np.array([[False, False, False], [False, False, True]])
    np.testing.assert_array_equal(clipped_pixels(image), expected)
    np.testing.assert_array_equal(clipped_pixels(image[..., 1]), expected)


@pytest.mark.parametrize("level, clipped", [(1.0, True), (0.99, False), (0.5, False)])
def test_saturation_level_lies_between_0_99_and_1(level, clipped):
    assert clipped_pixels(np.array([[level]]))[0, 0] == clipped


def test_a_frame_listed_twice_counts_twice(tmp_path):
    """Equal leaves (same file, warp, weight) must not be one shared task: every partial sum
    is added into in place, so a shared leaf would be added into by two merges."""
    rng = np.random.default_rng(10)
    paths, (p, q) = _write(tmp_path, [rng.uniform(0.0, 0.9, (4, 5)) for _ in range(2)])
    for scheduler in ("sync", "threads"):
        total, _, _, _, _, _ = dask.compute(
            weighted_sum_graph([paths[0], paths[1]] * 2, [None] * 4, [0.5, 0.25] * 2, (4, 5)),
            scheduler=scheduler,
        )[0]
        np.testing.assert_allclose(total, p + 0.5 * q, rtol=1e-6)


@pytest.mark.parametrize("scheduler", ["sync", "threads"])
@pytest.mark.parametrize("warped", [True, False])
@pytest.mark.parametrize("channels", [3, 1])
def test_kept_frames_are_the_grey_frames_as_read(tmp_path, scheduler, warped, channels):
    """The end frames' detail reads the accumulation's copies instead of decoding again:
    each kept frame is the mean of its channels as read (not warped, not weighted: without a
    warp the frame is weighted in place), for the indices asked for only, and none for a
    frame of weight 0 (never read)."""
    rng = np.random.default_rng(12)
    size = (6, 7, 3) if channels == 3 else (6, 7)
    paths, decoded = _write(tmp_path, [rng.uniform(0.0, 0.9, size) for _ in range(4)])
    shift = np.array([[1.0, 0, 2.0], [0, 1.0, 1.0], [0, 0, 1]])  # a warp the copies skip
    homographies = [shift if warped else None] * 4
    total, _, _, _, kept, _ = dask.compute(
        weighted_sum_graph(paths, homographies, [0.4, 0.0, 0.3, 0.3], (6, 7), keep=(0, 1, 3)),
        scheduler=scheduler,
    )[0]
    assert sorted(kept) == [0, 3]  # 1 has weight 0, 2 was not asked for
    for i in (0, 3):
        assert kept[i].dtype == np.float32 and kept[i].shape == (6, 7)
        grey = decoded[i].mean(axis=2) if channels == 3 else decoded[i]
        np.testing.assert_allclose(kept[i], grey, rtol=1e-6, atol=1e-7)
    assert total.shape == size
    plain = dask.compute(weighted_sum_graph(paths, homographies, [0.4, 0.0, 0.3, 0.3], (6, 7)))
    np.testing.assert_array_equal(total, plain[0][0])  # keeping changes nothing of the sum
    assert plain[0][4] == {}


@pytest.mark.parametrize("channels", [1, 3])
def test_detail_sums_the_frames_grey_images_by_their_maps(tmp_path, channels):
    """The inner frames' detail composite: ``(sum_i m_i g_i, sum_i m_i)`` over the frames
    given a map (a frame of weight 0 is never read, so lends nothing), checked against a
    numpy sum of the channel means; the weighted sum itself is unchanged."""
    rng = np.random.default_rng(21)
    size = (6, 7, 3) if channels == 3 else (6, 7)
    paths, decoded = _write(tmp_path, [rng.uniform(0.0, 0.9, size) for _ in range(4)])
    maps = {i: rng.uniform(0.0, 1.0, (6, 7)).astype(np.float32) for i in (1, 2, 3)}
    weights = [0.4, 0.3, 0.0, 0.3]
    lends = SimpleNamespace(inner=[1, 2, 3], weight=maps.get)
    graph = weighted_sum_graph(paths, [None] * 4, weights, (6, 7), detail=lends)
    total, _, _, _, _, (weighted, summed) = dask.compute(graph, scheduler="sync")[0]
    grey = [d.mean(axis=2) if channels == 3 else d for d in decoded]
    np.testing.assert_allclose(weighted, maps[1] * grey[1] + maps[3] * grey[3], rtol=1e-5)
    np.testing.assert_allclose(summed, maps[1] + maps[3], rtol=1e-6)
    plain = dask.compute(weighted_sum_graph(paths, [None] * 4, weights, (6, 7)))[0]
    np.testing.assert_array_equal(total, plain[0])
    assert plain[5] is None


def test_detail_warps_the_grey_frame_bicubically(tmp_path):
    """A half-pixel shift: the composite's grey frame is interpolated with the cubic
    convolution kernel (Keys, a = -0.75, OpenCV's), whose weights at half a pixel are
    0.59375 for the two nearest samples and -0.09375 for the next two (from the kernel's
    formula), not bilinearly (0.5 and 0.5)."""
    rng = np.random.default_rng(8)
    paths, decoded = _write(tmp_path, [rng.uniform(0.1, 0.9, (8, 12))])
    shift = np.array([[1.0, 0, 0.5], [0, 1.0, 0], [0, 0, 1]])
    ones = np.ones((8, 12), np.float32)
    lends = SimpleNamespace(inner=[0], weight=lambda i: ones)
    graph = weighted_sum_graph(paths, [shift], [1.0], (8, 12), detail=lends)
    *_, (weighted, _) = dask.compute(graph, scheduler="sync")[0]
    f = decoded[0]
    a = -0.75
    near = (a + 2) * 0.5**3 - (a + 3) * 0.5**2 + 1  # |s| = 0.5
    far = a * 1.5**3 - 5 * a * 1.5**2 + 8 * a * 1.5 - 4 * a  # |s| = 1.5
    assert near == pytest.approx(0.59375) and far == pytest.approx(-0.09375)
    # the frame lands 0.5 px to the right: dst(x) = src(x - 0.5)
    want = near * (f[:, 1:-2] + f[:, 2:-1]) + far * (f[:, :-3] + f[:, 3:])
    np.testing.assert_allclose(weighted[:, 2:-1], want, atol=2e-4)


def test_detail_warps_the_grey_frame_and_brings_the_map_to_the_frame_size(tmp_path):
    """A frame shifted by (1, 2) px with a map given at half size: its grey image lands
    shifted (bicubic, exact for whole pixels) and the map is resized to the frame."""
    rng = np.random.default_rng(5)
    paths, decoded = _write(tmp_path, [rng.uniform(0.1, 0.9, (8, 10))])
    shift = np.array([[1.0, 0, 2.0], [0, 1.0, 1.0], [0, 0, 1]])
    half = np.full((4, 5), 0.5, np.float32)
    lends = SimpleNamespace(inner=[0], weight=lambda i: half)
    graph = weighted_sum_graph(paths, [shift], [1.0], (8, 10), detail=lends)
    *_, (weighted, summed) = dask.compute(graph, scheduler="sync")[0]
    np.testing.assert_allclose(summed, 0.5)
    np.testing.assert_allclose(weighted[1:, 2:], 0.5 * decoded[0][:-1, :-2], rtol=1e-5)
