"""The real-stack region measures (tests/benchmarks/region_measures.py) cannot be gamed.

A synthetic focal stack: a checkerboard (32 px squares, levels 60 and 190) seen
in focus (Gaussian blur 0.7 px) and defocused (2 and 4 px), each with sensor
noise of 2 levels. Results under test are derived from the in-focus frame. Each
test also shows that a trivial stand-in (the plain 10-90% width, the Laplacian
variance, a constant) would let the trick through.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.core.quality import edge_widths as plain_edge_widths

sys.path.insert(0, str(Path(__file__).resolve().parent / "benchmarks"))
import region_measures as rm

SIDE = 288


def _blur(image: np.ndarray, sigma: float) -> np.ndarray:
    return cv2.GaussianBlur(image, (0, 0), sigma)


def _median(values: np.ndarray) -> float:
    assert np.count_nonzero(np.isfinite(values)) >= 5, values  # measured in most regions
    return float(np.nanmedian(values))


@pytest.fixture(scope="module")
def stack():
    rng = np.random.default_rng(7)
    x = np.arange(SIDE)
    board = np.where(((x[:, None] // 32) + (x[None, :] // 32)) % 2 == 0, 60.0, 190.0)
    board = board.astype(np.float32)
    frames = []
    for sigma in (0.7, 2.0, 4.0):
        grey = _blur(board, sigma) + rng.normal(0, 2, board.shape).astype(np.float32)
        frames.append(np.repeat(grey[..., None], 3, axis=2))
    return rm.Reference(frames), frames


def _scores(ref, image):
    return {m: _median(v) for m, v in ref.measure(image).items() if m != "sharpness"} | {
        "sharpness": _median(ref.sharpness(image))
    }


def test_ringing_on_a_sharp_edge_is_not_sharpness_but_halo(stack):
    ref, frames = stack
    clean = frames[0]
    ringing = clean + 2.0 * (clean - _blur(clean, 1.0))  # over/undershoot lobes at every edge
    a, b = _scores(ref, clean), _scores(ref, ringing)
    assert b["sharpness"] >= a["sharpness"]  # not sharper ...
    assert b["halo"] > a["halo"] + 2.0  # ... and the rims are counted
    assert a["halo"] < 0.2  # a frame never leaves the frames' range
    # the plain 10-90% width and the Laplacian variance would both call it sharper
    g_clean, g_ring = clean.mean(axis=-1), ringing.mean(axis=-1)
    plain = [np.nanmedian(plain_edge_widths(g, ref.points, ref.normals)) for g in (g_clean, g_ring)]
    assert plain[1] < plain[0]
    assert np.var(cv2.Laplacian(g_ring, cv2.CV_32F)) > np.var(cv2.Laplacian(g_clean, cv2.CV_32F))
    # and the measure is not a constant: real blur widens edges
    assert _median(ref.sharpness(_blur(clean, 2.0))) > a["sharpness"] + 1.0


def test_unsharp_masking_a_soft_frame_is_not_sharpness_but_halo(stack):
    ref, frames = stack
    soft = frames[1]
    sharpened = soft + 1.5 * (soft - _blur(soft, 3.0))
    a, b = _scores(ref, soft), _scores(ref, sharpened)
    assert b["sharpness"] >= a["sharpness"]
    assert b["halo"] > a["halo"] + 2.0


def test_smoothing_lowers_noise_but_costs_sharpness_and_haze(stack):
    ref, frames = stack
    clean = frames[0]
    a = _scores(ref, clean)
    smooth = _scores(ref, _blur(clean, 1.5))
    assert smooth["noise"] < 0.5 * a["noise"]  # the noise measure sees the smoothing ...
    assert smooth["sharpness"] > a["sharpness"] + 1.0  # ... and sharpness sees its cost
    heavy = _scores(ref, _blur(clean, 6.0))
    assert heavy["haze"] > a["haze"] + 0.15  # heavier smoothing also loses contrast


def test_a_veil_is_haze(stack):
    ref, frames = stack
    clean = frames[0]
    hazy = 0.6 * clean + 0.4 * float(clean.mean())
    a, b = _scores(ref, clean), _scores(ref, hazy)
    assert abs(a["haze"]) < 0.03  # the sharpest frame is its own reference
    assert b["haze"] > a["haze"] + 0.3
    assert abs(b["sharpness"] - a["sharpness"]) <= 0.5  # a veil does not move edges


def test_a_contrast_stretch_cannot_buy_haze(stack):
    ref, frames = stack
    clean = frames[0]
    mean = float(clean.mean())
    stretched = mean + 1.4 * (clean - mean)
    a, b = _scores(ref, clean), _scores(ref, stretched)
    assert b["haze"] < a["haze"] - 0.2  # less "haze" than the truth ...
    assert b["halo"] > a["halo"] + 5.0  # ... bought by leaving the frames' range


def test_verdicts_have_tolerances():
    assert rm.verdict("sharpness", 3.0, 3.05) == "tie"
    assert rm.verdict("sharpness", 2.0, 3.0) == "win"
    assert rm.verdict("noise", 2.0, 1.0) == "loss"
    assert rm.verdict("haze", np.nan, 0.1) == "-"
    assert rm.at_least_as_good("halo", 0.3, 0.2) is True
    assert rm.at_least_as_good("halo", 2.0, 0.2) is False
    assert rm.at_least_as_good("halo", np.nan, 0.2) is None


def test_paired_sharpness_compares_the_same_edges(stack):
    # the in-focus frame against itself: no difference; against its blur, narrower at most
    # edges; the order of the two matters (a flipped sign would read the soft one as sharp)
    ref, frames = stack
    clean = frames[0]
    same = ref.paired_sharpness(clean, clean)
    measured = np.isfinite(same[:, 0])
    assert measured.sum() >= 5
    assert np.all(same[measured, 0] == 0) and np.all(same[measured, 1:] == 0)
    soft = _blur(clean, 2.0)
    paired = ref.paired_sharpness(clean, soft)[measured]
    assert np.all(paired[:, 0] < -1.0) and np.all(paired[:, 1] > 0.8)
    flipped = ref.paired_sharpness(soft, clean)[measured]
    np.testing.assert_allclose(flipped[:, 0], -paired[:, 0])
    np.testing.assert_allclose(flipped[:, 2], paired[:, 1])
