"""Frames at different exposures (pipeline.core.exposure and its use in the main job): the
gains a stack was rendered with are found, clipped pixels are found as shot, and a stack
whose exposure drifts comes out as the same stack shot at one exposure."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from skimage import data
from test_engine import blur, make_stack, positions_for

from pipeline.core.colour import srgb_to_linear
from pipeline.core.exposure import DEAD_BAND, exposure_gains
from pipeline.core.frame_support import from_codes
from pipeline.core.psf import raster_pillbox
from pipeline.core.quality import psnr
from pipeline.io.read import read_frame
from pipeline.io.write import write_image
from pipeline.jobs.options import StackOptions
from pipeline.jobs.stack import process_stack
from pipeline.parallel.accumulate import weighted_sum_graph


@pytest.fixture(scope="module")
def scene():
    grey = srgb_to_linear(data.camera()[::2, ::2].astype(np.float32) / 255)
    return grey * np.float32(0.9)


def _defocused(scene, radii):
    """The scene blurred by pillboxes of ``radii`` (px): a focal stack's frames, one exposure."""
    return [
        scene if r == 0 else blur(scene[..., None], raster_pillbox(2 * r, r + 1))[..., 0]
        for r in radii
    ]


@settings(max_examples=25, deadline=None)
@given(
    gains=st.lists(st.floats(0.7, 1.3), min_size=3, max_size=7),
    seed=st.integers(0, 2**16),
)
@example(gains=[1.25, 0.74, 1.0, 1.13], seed=0)  # the beetle's flash-lit spread
def test_the_gains_a_stack_was_rendered_with_are_found(scene, gains, seed):
    """Frames defocused by 0-8 px (brute-force pillbox blur), each times its gain, with
    noise and a highlight clipped in the sharpest frames: the estimate is the rendered
    gains, normalised as documented (``sum w g = 1``), within 0.5%."""
    rng = np.random.default_rng(seed)
    n = len(gains)
    radii = rng.permutation(np.linspace(0, 8, n).round().astype(int))
    lit = scene.copy()
    lit[20:30, 200:215] = 3.0  # a highlight: clipped in focus, spread when defocused
    frames = [
        np.clip(g * f + rng.normal(0, 0.003, f.shape), 0, 1).astype(np.float32)
        for g, f in zip(gains, _defocused(lit, radii))
    ]
    weights = rng.uniform(0.5, 1.5, n)
    got = exposure_gains(frames, weights)
    want = np.asarray(gains) / np.dot(weights / weights.sum(), gains)
    if np.all(np.abs(want - 1) <= DEAD_BAND):
        want = np.ones(n)
    np.testing.assert_allclose(got, want, rtol=5e-3)
    assert np.dot(weights, got) / weights.sum() == pytest.approx(1.0, abs=1e-9) or np.all(
        got == 1
    )


def test_one_exposure_reads_as_one_and_odd_input_as_as_shot(scene):
    frames = _defocused(scene, [0, 3, 6])
    np.testing.assert_array_equal(exposure_gains(frames, [1, 1, 1]), np.ones(3))
    white = [np.ones_like(f) for f in frames]  # every pixel clipped: nothing to compare
    np.testing.assert_array_equal(exposure_gains(white, [1, 1, 1]), np.ones(3))
    broken = [f.copy() for f in frames]
    broken[1][5, 5] = np.nan
    np.testing.assert_array_equal(exposure_gains(broken, [1, 1, 1]), np.ones(3))
    black = [frames[0], np.zeros_like(frames[1]), frames[2]]  # no gain to divide by
    np.testing.assert_array_equal(exposure_gains(black, [1, 1, 1]), np.ones(3))
    for weights in ([0, 0, 0], [1, np.nan, 1], [1, -1, 1]):  # no weighted sum
        np.testing.assert_array_equal(exposure_gains(frames, weights), np.ones(3))
    dark = [f * np.float32(g) for f, g in zip(frames, (1.0, 0.5, 2.0))]  # per-row weights
    got = exposure_gains(dark, np.ones((4, 3)))
    np.testing.assert_allclose(got / got[0], [1.0, 0.5, 2.0], rtol=3e-3)


def test_a_frame_is_clipped_as_shot_and_summed_at_the_stack_exposure(tmp_path):
    """Clipped pixels are found before the gain: a frame shot brighter (gain 1.25) clips at
    1.0, which divided by its gain reads 0.8; a darker frame's 0.9 (gain 0.8) reads 1.125 and
    is no clipped pixel. The sum and the frames' range see the frames divided by their gains."""
    bright, dark = np.full((4, 5), 0.5, np.float32), np.full((4, 5), 0.45, np.float32)
    bright[1, 1], dark[2, 3] = 1.0, 0.9
    paths = []
    for name, frame in (("b.tif", bright), ("d.tif", dark)):
        write_image(tmp_path / name, frame, encoding="float32")
        paths.append(tmp_path / name)
    graph = weighted_sum_graph(paths, [None, None], [0.5, 0.5], (4, 5), gains=[1.25, 0.8],
                               support="range")  # fmt: skip
    total, clipped, _, support, _, _ = graph.compute(scheduler="synchronous")
    assert clipped[1, 1] and not clipped[2, 3] and np.count_nonzero(clipped) == 1
    want = 0.5 * bright / 1.25 + 0.5 * dark / 0.8
    np.testing.assert_allclose(total, want, rtol=1e-6)
    assert total[0, 0] == pytest.approx(0.2 + 0.28125)
    # the range of the frames divided by their gains (16-bit codes, capped at white)
    low, high = (from_codes(x) for x in (support.low, support.high))
    assert low[0, 0] == pytest.approx(0.4, abs=2e-5)
    assert high[0, 0] == pytest.approx(0.5625, abs=2e-5)
    assert high[2, 3] == pytest.approx(1.0, abs=2e-5)  # 1.125, capped


def test_a_stack_whose_exposure_drifts_comes_out_as_shot_at_one(tmp_path, caplog):
    """Frames rendered by brute-force lens PSFs (Eqs. 2-3), a plane beyond the far end, then
    each scaled by its own gain: the result is the undrifted stack's to 55.9 dB (the rest is
    the estimate's 0.5% error, inside the dead band for the undrifted stack and outside for
    this one), as far from the truth as that stack's, and the sidecar's exposures are the
    rendered gains."""
    sharp = srgb_to_linear(data.astronaut()[40:296, 130:386].astype(np.float32) / 255)
    positions = positions_for(450, 1200, 9)  # the 1600 mm plane beyond the far end
    # a flicker of 0.7-1, the end frames darkest (none brighter than as rendered: no pixel
    # clips that did not)
    gains = np.array([0.7, 0.85, 1.0, 0.95, 0.9, 0.8, 0.92, 1.0, 0.75])
    for name in ("plain", "drift"):
        (tmp_path / name).mkdir()
        make_stack(tmp_path / name, sharp, [500.0, 800.0, 1600.0], positions)
    for frame, g in zip(sorted((tmp_path / "drift").glob("frame_*.tif")), gains):
        write_image(frame, read_frame(frame) * np.float32(g), encoding="float32")
    options = StackOptions(encoding="float32", match_exposure=True)
    plain = process_stack(tmp_path / "plain", tmp_path / "p.tif", options)
    drift = process_stack(tmp_path / "drift", tmp_path / "d.tif", options)
    as_shot = process_stack(tmp_path / "drift", tmp_path / "a.tif", StackOptions())
    assert drift.sidecar["exposure_matched"] and not as_shot.sidecar["exposure_matched"]
    assert [f["exposure"] for f in as_shot.sidecar["frames"]] == [
        f["exposure"] for f in drift.sidecar["frames"]
    ]  # measured and reported as shot too
    assert "--match-exposure" in caplog.text  # as shot, a 0.7-1 spread is warned of
    weights = np.array([f["weight"] for f in drift.sidecar["frames"]])
    exposures = np.array([f["exposure"] for f in drift.sidecar["frames"]])
    np.testing.assert_allclose(exposures, gains / np.dot(weights, gains), rtol=8e-3)
    assert all(f["exposure"] == 1.0 for f in plain.sidecar["frames"])
    k = float(np.sum(drift.image * plain.image) / np.sum(drift.image**2))
    # measured: 55.89 dB; 41.69 with the sum's frames as shot, 53.73 with the end frame's
    # check, 55.43 with the end frames' detail (the grey copies kept) as shot
    assert psnr(k * drift.image, plain.image) > 55.65
    k = float(np.sum(drift.image * sharp) / np.sum(drift.image**2))
    assert psnr(k * drift.image, sharp) > psnr(plain.image, sharp) - 0.1  # 28.71 vs 28.74


def test_the_flash_lit_beetle_reads_its_frames_exposures(tmp_path, shared_data, caplog):
    """The real beetle stack (1/200 s, ISO 400: a flash whose output varies): the exposures
    the job reports agree within 2% with an independent reading, the mean of each frame at
    full resolution, warped by the sidecar's homography, over the interior; as shot the
    spread is warned of, and ``--match-exposure`` (the command line) divides it out."""
    from pipeline.cli import main
    from pipeline.core import align
    from pipeline.core.colour import mean_grey

    beetle = shared_data / "chimpstackr-beetle"
    with caplog.at_level("WARNING"):
        assert main(["stack", str(beetle), "-o", str(tmp_path / "a.tif")]) == 0
    assert "--match-exposure" in caplog.text
    matched_out = str(tmp_path / "m.tif")
    assert main(["-q", "stack", str(beetle), "-o", matched_out, "--match-exposure"]) == 0
    shot, matched = (
        json.loads((tmp_path / f"{n}.tif.json").read_text()) for n in ("a", "m")
    )
    assert not shot["exposure_matched"] and matched["exposure_matched"]
    got = np.array([f["exposure"] for f in shot["frames"]])
    assert got.max() - got.min() > 0.4  # 0.74-1.26
    means = []
    for path, meta in zip(shot["inputs"], shot["frames"]):
        grey = mean_grey(read_frame(path))
        warped = align.warp(grey, np.array(meta["homography"]), grey.shape)
        means.append(float(warped[40:-40, 60:-60].mean()))
    means = np.array(means)
    np.testing.assert_allclose(got / got[3], means / means[3], rtol=0.02)


def test_the_quality_method_reads_the_frames_divided_too(tmp_path):
    """``--method multiframe`` reads the frames again: with ``--match-exposure`` it divides
    them as the sum did, so a drifting stack's result is the undrifted one's."""
    sharp = srgb_to_linear(data.astronaut()[40:296, 130:386].astype(np.float32) / 255)
    positions = positions_for(450, 1200, 7)
    gains = np.array([0.7, 1.0, 0.85, 0.95, 0.8, 1.0, 0.75])
    for name in ("plain", "drift"):
        (tmp_path / name).mkdir()
        make_stack(tmp_path / name, sharp, [500.0, 800.0, 1600.0], positions)
    for frame, g in zip(sorted((tmp_path / "drift").glob("frame_*.tif")), gains):
        write_image(frame, read_frame(frame) * np.float32(g), encoding="float32")
    options = StackOptions(encoding="float32", match_exposure=True, method="multiframe")
    plain = process_stack(tmp_path / "plain", tmp_path / "p.tif", options)
    drift = process_stack(tmp_path / "drift", tmp_path / "d.tif", options)
    assert drift.sidecar["multiframe"]["share"] > 0.3
    k = float(np.sum(drift.image * plain.image) / np.sum(drift.image**2))
    # measured: 53.17 dB; 46.63 with the quality method's frames read as shot
    assert psnr(k * drift.image, plain.image) > 50.0


def test_clipped_and_black_areas_are_left_out_of_the_ratios():
    """A third of the scene at 0.9 (clipped to white in the frame shot at 1.25) and a
    third black (its ratios are noise over noise): over what is left the gains are found
    within 0.2%. Counting the clipped block read the bright frame 2.5% low, the black area
    the dark frame 0.9% high (measured with those steps removed)."""
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.random((256, 256)).astype(np.float32), (0, 0), 2)
    scene = 0.25 + 0.3 * (texture - texture.min()) / np.ptp(texture)
    scene[:, :96] = 0.9
    scene[:, 180:] = 0.0
    gains = np.array([1.0, 1.25, 0.8])
    frames = [
        np.clip(g * cv2.GaussianBlur(scene, (0, 0), 1 + 2 * k)
                + rng.normal(0, 0.003, scene.shape), 0, 1).astype(np.float32)
        for k, g in enumerate(gains)
    ]
    np.testing.assert_allclose(exposure_gains(frames, [1, 1, 1]), gains / gains.mean(),
                               rtol=2e-3)


def test_a_frame_weighted_zero_is_measured_and_a_negative_weight_refused(scene):
    """Gains 1, 0.5, 2: with weights 1, 0, 1 the stack's exposure is frames 0 and 2's
    (``sum w g = 1``: 1.5 in all), so the gains read 1 / 1.5, 0.5 / 1.5, 2 / 1.5; a
    negative weight is no weighted sum: all 1."""
    frames = _defocused(scene, [0, 3, 6])
    lit = [f * np.float32(g) for f, g in zip(frames, (1.0, 0.5, 2.0))]
    np.testing.assert_allclose(exposure_gains(lit, [1, 0, 1]), np.array([1.0, 0.5, 2.0]) / 1.5,
                               rtol=3e-3)
    np.testing.assert_array_equal(exposure_gains(lit, [1, -0.5, 1]), np.ones(3))
