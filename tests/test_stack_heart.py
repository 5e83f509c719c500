"""The main job's heart against independent computations (issue 11).

* ``focal_stack_psf``: brute-force averaging of per-frame lens PSFs rasterised by
  supersampling (points inside the disk), not by the code's exact disk/square areas;
* ``stack_kernel``: the kernel choice (stack average vs Eq. 6) where each must win;
* ``positions_from_scales``: rising, falling, noisy and flat sequences;
* ``weighted_sum_graph``: a plain numpy sum on uneven chunk layouts and odd frame counts.
"""

from __future__ import annotations

import dask
import numpy as np
import pytest

from pipeline.core import optics
from pipeline.core.lens import Lens
from pipeline.core.stack_kernel import focal_stack_psf, positions_from_scales, stack_kernel
from pipeline.errors import InputError
from pipeline.io.read import read_frame
from pipeline.io.write import write_image
from pipeline.parallel.accumulate import SATURATION, weighted_sum_graph


# ----------------------------------------------------------------------------- brute force
def supersampled_pillbox(diameter: float, half: int, n: int = 48) -> np.ndarray:
    """Eq. 3 averaged over n x n points per pixel (brute force), unit sum."""
    s = (np.arange(n) + 0.5) / n - 0.5
    coords = np.arange(-half, half + 1)
    xs = (coords[:, None] + s[None, :]).ravel()
    inside = (xs[:, None] ** 2 + xs[None, :] ** 2) <= (0.5 * diameter) ** 2
    if not inside.any():  # smaller than a sample spacing: a point
        k = np.zeros((2 * half + 1,) * 2)
        k[half, half] = 1.0
        return k
    k = inside.reshape(2 * half + 1, n, 2 * half + 1, n).sum(axis=(1, 3)).astype(float)
    return k / k.sum()


def brute_focal_stack(x, w, blur, samples, half):
    per = []
    for s in samples:
        k = sum(wi * supersampled_pillbox(float(blur(xi, s)), half) for xi, wi in zip(x, w))
        per.append(k / k.sum())
    per = np.array(per)
    mean = per.mean(axis=0)
    return mean / mean.sum(), per


@pytest.mark.parametrize(
    ("positions", "weights", "span"),
    [
        ([0.0, 1.0, 2.0], [0.2, 0.5, 0.3], 6.0),  # uneven weights, 3 frames
        ([0.0, 0.7, 1.1, 2.6, 4.0], [0.1, 0.3, 0.2, 0.25, 0.15], 9.0),  # uneven spacing
    ],
)
def test_focal_stack_psf_equals_brute_force_average_of_frame_psfs(positions, weights, span):
    x = np.array(positions)
    w = np.array(weights)

    def blur(p, s):
        return span * np.abs(p - s) / np.ptp(x)

    samples = 5
    kernel, per = focal_stack_psf(x, w, blur, focus_samples=samples)
    half = kernel.shape[0] // 2
    ref, ref_per = brute_focal_stack(x, w, blur, np.linspace(x.min(), x.max(), samples), half)
    assert per.shape == (samples, *kernel.shape)
    for k, r in zip(per, ref_per):
        assert np.abs(k - r).sum() < 0.02
    assert np.abs(kernel - ref).sum() < 0.01
    # weights matter: the equal-weight brute force is farther than the tolerance
    equal, _ = brute_focal_stack(x, np.full(x.size, 1 / x.size), blur,
                                 np.linspace(x.min(), x.max(), samples), half)
    assert np.abs(equal - ref).sum() > 0.03


def test_focal_stack_psf_single_position_is_the_weighted_frame_sum():
    x = np.array([3.0, 3.0])
    kernel, per = focal_stack_psf(x, [0.5, 0.5], lambda p, s: np.full(p.shape, 4.0))
    assert per.shape[0] == 1
    half = kernel.shape[0] // 2
    assert np.abs(kernel - supersampled_pillbox(4.0, half)).sum() < 0.02


# ----------------------------------------------------------------------------- kernel choice
@pytest.fixture(scope="module")
def lens() -> Lens:
    return Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=4.65, width_px=640,
                height_px=480, psf_model="pillbox")


def test_sparse_stack_keeps_its_stack_average(lens):
    """Three frames far apart: per-depth kernels are three separate disks, nothing like Eq. 6."""
    p = np.array([optics.image_distance(12.5, u) for u in (2000.0, 1000.0, 600.0)])
    w = np.full(3, 1 / 3)
    kernel, samples, summary = stack_kernel(p, w, lens=lens, absolute=True, blur_span_px=None)
    d = summary["dissimilarity"]
    assert summary["source"] == "stack-average" and d["stack-average"] < d["analytic-eq6"]
    assert samples.shape[1:] == kernel.shape
    # and the kept kernel is the stack average (brute force, uniform in image distance)
    a = lens.aperture_mm

    def blur(pi, v):
        return a * np.abs(v - pi) / v / lens.pixel_pitch_mm

    ref, _ = brute_focal_stack(p, w, blur, np.linspace(p.min(), p.max(), 33), kernel.shape[0] // 2)
    assert np.abs(kernel - ref).sum() < 0.01
    assert summary["blur_span_px"] == pytest.approx(blur(p.max(), p.min()), rel=1e-9)


def test_eq6_wins_when_it_is_closer_to_the_per_depth_kernels(lens, monkeypatch):
    """The choice itself: a stack average spoiled to a point loses to Eq. 6.

    (With the real average, Eq. 6 lost in every stack tried: 3-200 frames, 450 mm-2 m,
    pillbox and Gaussian; the mean of the per-depth kernels is close to their Eq. 8
    centroid. So the choice is exercised by spoiling the average.)
    """
    import pipeline.core.stack_kernel as sk

    real = sk.focal_stack_psf

    def spoiled(*args, **kwargs):
        kernel, per = real(*args, **kwargs)
        point = np.zeros_like(kernel)
        point[kernel.shape[0] // 2, kernel.shape[1] // 2] = 1.0
        return point, per

    monkeypatch.setattr(sk, "focal_stack_psf", spoiled)
    p = np.linspace(optics.image_distance(12.5, 2000.0), optics.image_distance(12.5, 1000.0), 15)
    w = np.full(p.size, 1 / p.size)
    kernel, _, summary = stack_kernel(p, w, lens=lens, absolute=True, blur_span_px=None)
    d = summary["dissimilarity"]
    assert summary["source"] == "analytic-eq6" and d["analytic-eq6"] < d["stack-average"]
    assert kernel.max() < 0.5  # not the point
    # Eq. 6 (corrected) for the sweep over the stack's range, centred at the middle depth
    middle = optics.focus_distance(12.5, 0.5 * (p.min() + p.max()))
    from pipeline.core import psf
    from pipeline.core.motion import constant_speed

    expected = psf.integrated_psf(lens, middle, constant_speed(p.min(), np.ptp(p), 1.0),
                                  size=kernel.shape[0], method="numeric")
    assert np.abs(kernel - expected).sum() < 1e-3


def test_relative_positions_use_the_blur_span(lens):
    x = np.array([0.0, 1.0, 2.0, 3.0])
    w = np.full(4, 0.25)
    kernel, _, summary = stack_kernel(x, w, lens=None, absolute=False, blur_span_px=8.0)
    assert summary["source"] == "stack-average" and summary["blur_span_px"] == 8.0
    ref, _ = brute_focal_stack(x, w, lambda pi, s: 8.0 * np.abs(pi - s) / 3.0,
                               np.linspace(0, 3, 33), kernel.shape[0] // 2)
    assert np.abs(kernel - ref).sum() < 0.01


# ----------------------------------------------------------------------------- positions
@pytest.mark.parametrize(
    ("scales", "source"),
    [
        (np.linspace(1.0, 1.03, 7), "magnification"),  # rising
        (np.linspace(1.03, 1.0, 7), "magnification"),  # falling
        (np.linspace(1.0, 1.03, 9) + 2e-3 * np.array([0, 1, -1, 1, -1, 1, -1, 1, 0]),
         "magnification"),  # noisy but steady: correlation > 0.97
        (1.0 + 0.004 * np.array([0.0, 1, 0, 1, 0, 1]), "frame-order"),  # span < 0.5%
        (np.full(5, 1.01), "frame-order"),  # flat
        (np.array([1.0, 1.03, 1.0, 1.03, 1.0]), "frame-order"),  # large but unordered
        (np.array([1.0, 1.03]), "frame-order"),  # too few frames to tell
    ],
)
def test_positions_from_scales(scales, source):
    positions, how = positions_from_scales(scales)
    assert how == source
    if source == "magnification":
        np.testing.assert_array_equal(positions, scales)
    else:
        np.testing.assert_array_equal(positions, np.arange(len(scales)))


def test_positions_from_scales_thresholds_at_their_edges():
    assert positions_from_scales([1.0, 1.002, 1.0051])[1] == "magnification"  # span 0.51%
    assert positions_from_scales([1.0, 1.002, 1.0049])[1] == "frame-order"  # span 0.49%
    # not monotone: correlation 0.977 > 0.97 is used, 0.956 < 0.97 is not
    s = np.array([1.0, 1.011, 1.01, 1.02, 1.03, 1.04])
    assert abs(np.corrcoef(s, np.arange(s.size))[0, 1]) > 0.97
    assert positions_from_scales(s)[1] == "magnification"
    assert positions_from_scales(s[::-1])[1] == "magnification"  # falling: |r|
    s = np.array([1.0, 1.012, 1.01, 1.03, 1.04])
    assert abs(np.corrcoef(s, np.arange(s.size))[0, 1]) < 0.97
    assert positions_from_scales(s)[1] == "frame-order"


# ----------------------------------------------------------------------------- weighted sum
def _frames(tmp_path, n, shape, seed, colour=False):
    rng = np.random.default_rng(seed)
    paths, arrays = [], []
    for i in range(n):
        a = rng.uniform(0.0, 0.9, (*shape, 3) if colour else shape).astype(np.float32)
        if i == 1:
            a[2, 3] = 1.0  # clipped in one frame only
        path = tmp_path / f"f{i:02d}.tif"
        write_image(path, a)
        paths.append(path)
        arrays.append(read_frame(path))  # as decoded (the file quantises)
    return paths, arrays


@pytest.mark.parametrize("n", [1, 2, 3, 5, 7])
@pytest.mark.parametrize("colour", [False, True])
def test_weighted_sum_graph_equals_a_numpy_sum(tmp_path, n, colour):
    shape = (9, 13)
    paths, arrays = _frames(tmp_path, n, shape, seed=n, colour=colour)
    weights = np.random.default_rng(10 + n).uniform(0.1, 1.0, n)
    weights[n // 2] = 0.0 if n > 2 else weights[n // 2]  # a skipped frame
    total, clipped, read_s, _, _, _ = dask.compute(
        weighted_sum_graph(paths, [None] * n, weights, shape), scheduler="sync"
    )[0]
    ref = sum(np.float64(w) * a.astype(np.float64) for w, a in zip(weights, arrays))
    np.testing.assert_allclose(total, ref, rtol=1e-5, atol=1e-6)
    ref_clip = np.zeros(shape, bool)
    for w, a in zip(weights, arrays):
        if w > 0:
            ref_clip |= np.any(a >= SATURATION, axis=-1) if colour else a >= SATURATION
    np.testing.assert_array_equal(clipped, ref_clip)
    assert read_s >= 0


def test_weighted_sum_graph_per_row_weights_and_identity_warps(tmp_path):
    shape = (6, 5)
    paths, arrays = _frames(tmp_path, 4, shape, seed=3)
    rows = np.random.default_rng(4).uniform(0.0, 1.0, (4, shape[0]))
    rows[2] = 0.0  # never read
    homographies = [np.eye(3)] * 4
    total, _, _, _, _, _ = dask.compute(
        weighted_sum_graph(paths, homographies, list(rows), shape), scheduler="threads"
    )[0]
    ref = sum(r[:, None] * a for r, a in zip(rows, arrays))
    np.testing.assert_allclose(total, ref, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("lanes", [1, 2, 3])
def test_weighted_sum_graph_is_one_chain_per_lane(tmp_path, lanes):
    """Memory flat in the frame count (issue 15): each frame's step depends on at most
    one earlier step (its lane's running sum), never on a tree of partial sums, and
    the lanes decode side by side; the sum is the numpy sum whatever the lane count."""
    n, shape = 7, (5, 6)
    paths, arrays = _frames(tmp_path, n, shape, seed=11)
    weights = np.random.default_rng(12).uniform(0.1, 1.0, n)
    graph = weighted_sum_graph(paths, [None] * n, weights, shape, lanes=lanes)
    layers = dict(graph.dask)
    steps = {k: v for k, v in layers.items() if str(k).startswith("_add_frame")}
    assert len(steps) == n
    deps = graph.dask.get_all_dependencies()
    firsts = [k for k in steps if not any(str(d).startswith("_add_frame") for d in deps[k])]
    assert len(firsts) == lanes
    for key in steps:
        assert sum(str(d).startswith("_add_frame") for d in deps[key]) <= 1
    total, _, _, _, _, _ = dask.compute(graph, scheduler="threads")[0]
    ref = sum(np.float64(w) * a.astype(np.float64) for w, a in zip(weights, arrays))
    np.testing.assert_allclose(total, ref, rtol=1e-5, atol=1e-6)


# ----------------------------------------------------------------------------- details
def test_focal_stack_psf_samples_33_positions_by_default():
    x = np.array([0.0, 1.0, 2.0])
    _, per = focal_stack_psf(x, np.full(3, 1 / 3), lambda p, s: 3.0 * np.abs(p - s))
    assert per.shape[0] == 33


def test_stack_kernel_summary_against_its_own_per_depth_kernels(lens):
    from pipeline.core import spectra

    p = np.array([optics.image_distance(12.5, u) for u in (2000.0, 1200.0, 800.0, 600.0)])
    w = np.array([0.1, 0.4, 0.3, 0.2])
    kernel, samples, summary = stack_kernel(p, w, lens=lens, absolute=True, blur_span_px=None)

    def blur(pi, v):
        return lens.aperture_mm * np.abs(v - pi) / v / lens.pixel_pitch_mm

    _, per = focal_stack_psf(p, w, blur, size=kernel.shape[0])
    assert samples.shape == (9, *kernel.shape)  # every 4th of 33
    np.testing.assert_allclose(samples, per[::4], atol=1e-12)
    spread = [spectra.dissimilarity(k, kernel) for k in per]
    assert summary["depth_invariance_eq8"]["mean"] == pytest.approx(np.mean(spread), rel=1e-9)
    assert summary["depth_invariance_eq8"]["max"] == pytest.approx(np.max(spread), rel=1e-9)
    assert summary["size"] == kernel.shape[0]


def test_no_eq6_comparison_without_a_range(lens):
    p = np.full(3, optics.image_distance(12.5, 1000.0))
    _, _, summary = stack_kernel(p, np.full(3, 1 / 3), lens=lens, absolute=True,
                                 blur_span_px=None)
    assert "dissimilarity" not in summary and summary["source"] == "stack-average"


@pytest.mark.parametrize(("mix", "kept"), [(1.0, True), (0.5, False)])
def test_wiener_options_keep_the_kernel_variance_only_for_a_large_spread(mix, kept):
    from pipeline.core import spectra
    from pipeline.core.stack_kernel import KERNEL_VARIANCE_SPREAD, wiener_options

    kernel = supersampled_pillbox(5.0, 4)
    other = supersampled_pillbox(4.6, 4)  # spread 0.134 (mix 1) and ~0.034 (mix 0.5)
    samples = np.array([(1 - mix) * kernel + mix * other, kernel])
    spread = np.mean([spectra.dissimilarity(k, kernel) for k in samples])
    assert (spread > 0.1) == kept and KERNEL_VARIANCE_SPREAD == 0.1  # the case is as meant
    out = wiener_options(kernel, samples)["kernel_samples"]
    assert (out is samples) if kept else (out is None)
    assert wiener_options(kernel)["kernel_samples"] is None


@pytest.mark.parametrize(
    "s",
    [
        np.array([1.0, 1.0, 1.0, 1.012, 1.0]),
        np.array([1.0, 1.0001, 1.0001, 1.0002, 1.01]),  # steps >= 0 with a repeat; |r| < 0.97
        np.array([1.0, 1.0001, 1.0001, 1.0002, 1.01])[::-1],  # steps <= 0 with a repeat
    ],
)
def test_positions_with_a_repeated_scale_are_not_monotone(s):
    assert abs(np.corrcoef(s, np.arange(s.size))[0, 1]) < 0.97
    assert positions_from_scales(s)[1] == "frame-order"


# ----------------------------------------------------------------------------- mutation kills
@pytest.mark.parametrize("direction", [1, -1])
def test_monotone_scales_are_used_even_when_far_from_a_line(direction):
    """Steady in one direction but bunched (correlation 0.75): the monotone test decides."""
    s = np.array([1.0, 1.0001, 1.0002, 1.0003, 1.01])[::direction]
    assert abs(np.corrcoef(s, np.arange(s.size))[0, 1]) < 0.97
    assert positions_from_scales(s)[1] == "magnification"


@pytest.mark.parametrize("bad", [-0.5, np.nan])
def test_focal_stack_psf_refuses_a_negative_or_missing_blur(bad):
    with pytest.raises(InputError, match="negative or non-finite"):
        focal_stack_psf([0.0, 1.0], [0.5, 0.5], lambda p, x: np.array([3.0, bad]))


def test_focal_stack_psf_gaussian_default_is_eq4_with_g_one():
    """The default g is 1 (Eq. 4's Gaussian of std g b / 2), not 2 or 0."""
    def blur(p, x):
        return 6.0 * np.abs(p - x)

    args = ([0.0, 0.5, 1.0], [0.25, 0.5, 0.25], blur)
    default, _ = focal_stack_psf(*args, model="gaussian")
    one, _ = focal_stack_psf(*args, model="gaussian", gaussian_g=1.0)
    two, _ = focal_stack_psf(*args, model="gaussian", gaussian_g=2.0)
    np.testing.assert_array_equal(default, one)
    assert default.shape != two.shape or np.abs(default - two).sum() > 0.05


def test_relative_positions_in_any_unit_span_the_blur(lens):
    """Scales (a 4% range, not frame numbers): the far ends are still D apart in blur."""
    x = np.linspace(0.98, 1.02, 5)
    w = np.full(5, 0.2)
    kernel, _, summary = stack_kernel(x, w, lens=lens, absolute=False, blur_span_px=20.0)
    assert summary["blur_span_px"] == 20.0 and "dissimilarity" not in summary  # no Eq. 6
    ref, _ = brute_focal_stack(x, w, lambda pi, s: 20.0 * np.abs(pi - s) / 0.04,
                               np.linspace(0.98, 1.02, 33), kernel.shape[0] // 2)
    assert np.abs(kernel - ref).sum() < 0.01


def test_absolute_positions_without_a_lens_use_the_blur_span():
    kernel, _, summary = stack_kernel(np.array([12.6, 12.7, 12.8]), np.full(3, 1 / 3),
                                      lens=None, absolute=True, blur_span_px=6.0)
    assert summary["blur_span_px"] == 6.0 and summary["source"] == "stack-average"
    assert kernel.shape[0] >= 7


def test_one_focus_position_gives_a_point_kernel():
    kernel, _, _ = stack_kernel(np.full(3, 5.0), np.full(3, 1 / 3), lens=None, absolute=False,
                                blur_span_px=10.0)
    c = kernel.shape[0] // 2
    assert kernel[c, c] == pytest.approx(1.0)


def test_the_stack_job_gives_the_same_bytes_whatever_the_thread_count(tmp_path):
    """The weighted sum's float32 order is fixed (LANES), not one chain per worker: with
    a chain per worker, 2% of pcb7's 16-bit values moved by 1 code between --threads 1
    and 2."""
    from pathlib import Path

    from pipeline.jobs.stack import process_stack
    from pipeline.parallel.scheduler import scheduler_context

    sample = Path(__file__).resolve().parents[1] / "stacks" / "motorcycle"
    outputs = []
    for threads in (1, 3):
        out = tmp_path / f"t{threads}.tif"
        with scheduler_context(None, threads):
            process_stack(sample, out)
        outputs.append(out.read_bytes())
    assert outputs[0] == outputs[1]
