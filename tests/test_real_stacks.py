"""The main job on real focal stacks (../shared/data): breathing recovered, result sharper.

Sharpness is the median 10-90% edge width (pipeline.quality), which noise and
ringing cannot shrink; frames are compared in the result's geometry (warped by
the homographies the job reports).
"""

import importlib

import cv2
import numpy as np
import pytest

from pipeline.core import align, colour
from pipeline.core import frame_support as fs
from pipeline.core.quality import sharpness_against_frames
from pipeline.io.read import read_frame
from pipeline.jobs.options import StackOptions
from pipeline.jobs.stack import process_stack
from pipeline.parallel.scheduler import scheduler_context

pytestmark = pytest.mark.shared_data


def run(shared_data, pattern, tmp_path):
    with scheduler_context(threads=2):
        job = process_stack([str(shared_data / pattern)], tmp_path / "out.tif", StackOptions())
    frames = [
        align.warp(read_frame(path), np.array(meta["homography"]), job.image.shape)
        for meta, path in zip(job.sidecar["frames"], job.sidecar["inputs"])
    ]
    return job, sharpness_against_frames(job.image, frames)


@pytest.mark.parametrize(
    ("pattern", "scale_range"),
    [
        ("focusstack-pcb/pcb7/pcb_*.jpg", (0.979, 1.023)),
        ("shinestacker-amber/*.jpg", None),
    ],
    ids=["pcb7", "amber"],
)
def test_result_is_sharper_than_the_best_frame(shared_data, tmp_path, pattern, scale_range):
    job, score = run(shared_data, pattern, tmp_path)
    assert score["result_px"] < 0.9 * score["frames_px"][score["best"]], score
    assert score["regions_sharper"] >= score["regions"] - 2, score
    assert np.all(np.isfinite(job.image))
    if scale_range:
        scales = [f["scale"] for f in job.sidecar["frames"]]
        assert min(scales) == pytest.approx(scale_range[0], abs=0.01)
        assert max(scales) == pytest.approx(scale_range[1], abs=0.01)


def _pcb7_crops(shared_data, folder, noise_rng=None):
    """pcb7's frames, their centre 1024x768 crop, as 16-bit sRGB PNGs in ``folder``; with
    ``noise_rng``, an APS-C sensor's shot and read noise at ISO 3200 added in linear light
    (780 e- at white, 3 e- read noise: 0.015 at mid-grey)."""
    for path in sorted((shared_data / "focusstack-pcb" / "pcb7").glob("pcb_*.jpg")):
        linear = read_frame(path)[384:1152, 512:1536]
        if noise_rng is not None:
            electrons = noise_rng.poisson(linear * 780.0) + noise_rng.normal(0, 3.0, linear.shape)
            linear = np.clip(electrons / 780.0, 0.0, 1.0)
        codes = np.round(colour.linear_to_srgb(linear) * 65535).astype(np.uint16)
        cv2.imwrite(str(folder / path.with_suffix(".png").name), codes[..., ::-1])


def test_noisy_frames_hold_the_wiener_result_to_the_visible_noise(shared_data, tmp_path):
    """On a real stack GCV's lam lies under the white-noise-gain ceiling's floor with and
    without high-ISO noise (its residual is the single kernel's mismatch), so the ceiling
    (gain 10) alone set the result's grain: with ISO 3200 noise 10x the average's. Now,
    where the ceiling sets lam and the frames read noisier than their average, the
    result's noise (gain x sigma) is held to VISIBLE_NOISE (0.006 linear). The clean
    frames' limit (their median frame reads noisier than the average; until stop 42 only
    frame 0's noise was compared, which did not) binds only where gain 10 would pass it,
    and barely: their gain stays near 10."""
    wiener = importlib.import_module("pipeline.core.deconvolve.wiener")
    dispatch = importlib.import_module("pipeline.core.deconvolve.dispatch")
    planned = {}
    plan = dispatch._plan_wiener

    def spy(y, valid, k, sigma, **options):  # the real planner, its inputs and lam kept
        params, pad = plan(y, valid, k, sigma, **options)
        planned.update(kernel=k, sigma=np.asarray(sigma, float), lam=params["lam"])
        return params, pad

    jobs = {}
    for name, rng in (("clean", None), ("iso3200", np.random.default_rng(3200))):
        folder = tmp_path / name
        folder.mkdir()
        _pcb7_crops(shared_data, folder, rng)
        dispatch._plan_wiener = spy
        try:
            with scheduler_context(threads=2):
                job = process_stack(folder, tmp_path / f"{name}.tif", StackOptions())
        finally:
            dispatch._plan_wiener = plan
        floor = wiener.lam_for_noise_gain(planned["kernel"], wiener.MAX_NOISE_GAIN)
        gain = np.array([wiener.white_noise_gain(planned["kernel"], lam) for lam in planned["lam"]])
        jobs[name] = job, planned["sigma"], planned["lam"], floor, gain
    job, sigma, lam, floor, gain = jobs["clean"]
    assert np.all(lam >= floor * (1 - 1e-6)), (lam, floor)  # at least the ceiling's lam
    np.testing.assert_allclose(job.sidecar["noise_limit"]["std"], fs.VISIBLE_NOISE)
    # held only where gain 10 would pass the limit, and there to it; elsewhere gain 10
    held = np.array(job.sidecar["noise_limit"]["held"])
    np.testing.assert_array_equal(held, wiener.MAX_NOISE_GAIN * sigma > fs.VISIBLE_NOISE)
    np.testing.assert_allclose(gain[held] * sigma[held], fs.VISIBLE_NOISE, rtol=0.03)
    np.testing.assert_allclose(gain[~held], wiener.MAX_NOISE_GAIN, rtol=0.02)
    assert np.all(gain > 0.8 * wiener.MAX_NOISE_GAIN), gain  # barely: the clean detail stays
    job, sigma, lam, floor, gain = jobs["iso3200"]
    assert np.all(sigma > 4 * jobs["clean"][1])  # the noise is there
    np.testing.assert_allclose(job.sidecar["noise_limit"]["std"], fs.VISIBLE_NOISE)
    assert job.sidecar["noise_limit"]["held"] == [True, True, True]
    np.testing.assert_allclose(gain * sigma, fs.VISIBLE_NOISE, rtol=0.03)
    assert np.all(lam > 10 * floor) and np.all(gain < 3)


def test_a_stack_run_twice_gives_the_same_bits(shared_data, tmp_path):
    """The same frames make the same result, to the bit: under OpenCV 5.1 two runs of
    pcb10 differed by up to 2 codes of 65535 in 4523 pixels (bilinear warps in the two
    accumulation lanes, side by side, split OpenCV's rows differently; see
    pipeline.core.align.warp). Three runs of six pcb10 frames (2 lanes side by side)."""
    frames = sorted((shared_data / "focusstack-pcb" / "pcb10").glob("pcb_*.JPG"))[:6]
    images = []
    for k in range(3):
        with scheduler_context(threads=2):
            job = process_stack([str(f) for f in frames], tmp_path / f"run{k}.tif", StackOptions())
        images.append(job.image)
    for image in images[1:]:
        np.testing.assert_array_equal(image, images[0])
    written = [(tmp_path / f"run{k}.tif").read_bytes() for k in range(3)]
    assert written[0] == written[1] == written[2]
