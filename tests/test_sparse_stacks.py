"""Stacks whose frames lie too far apart, for their blur, for one kernel to fit every depth
(``pipeline.jobs.stack.sparse_spread``): the default runs them with the frame guard, says
so, and records it; ``--no-frame-range`` only warns."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from test_engine import make_stack, positions_for

import pipeline.jobs.stack as stack_job
from pipeline.core.quality import psnr
from pipeline.io.read import read_frame
from pipeline.jobs.options import StackOptions
from pipeline.jobs.stack import SPARSE_SPREAD, process_stack

FOUND = "too far apart for one kernel"


def _run(out, frames, caplog, **options):
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pipeline.jobs.stack"):
        job = process_stack(frames, out, StackOptions(**options))
    messages = [r.getMessage() for r in caplog.records if FOUND in r.getMessage()]
    return job, messages


def _amber(shared_data, *indices):
    return [shared_data / "shinestacker-amber" / f"000{i}.jpg" for i in indices]


def test_two_frames_far_apart_take_the_frame_guard(tmp_path, shared_data, caplog):
    """amber's frames 0 and 5, 106 px of blur apart: the per-depth kernels' mean Eq. 8
    spread from the stack's IPSF is 4.8 (the real stacks: 0.02-0.82). The user is told once,
    the sidecar records the spread the guard was chosen for, and the image is the one
    ``--frame-guard`` makes, bit for bit (one result written, not two)."""
    job, messages = _run(tmp_path / "auto.tif", _amber(shared_data, 0, 5), caplog)
    (message,) = messages
    assert "shinestacker-amber (2 frames, 0000.jpg .. 0005.jpg)" in message
    assert "as --frame-guard" in message and "--no-frame-range" in message
    spread = job.sidecar["frame_guard"]["chosen_for_spread"]
    assert spread > SPARSE_SPREAD and f"spread {spread:.1f}" in message
    asked, messages = _run(
        tmp_path / "asked.tif", _amber(shared_data, 0, 5), caplog, frame_guard=True
    )
    assert not messages and "chosen_for_spread" not in asked.sidecar["frame_guard"]
    np.testing.assert_array_equal(job.image, asked.image)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "asked.tif", "asked.tif.json", "auto.tif", "auto.tif.json"
    ]


def test_three_frames_keep_the_default(tmp_path, shared_data, caplog):
    """amber's frames 0, 2 and 4 (42 px apart, spread 2.4): as good as focus-stack in 7 of
    9 regions with the default, 5 with the frame guard, so the default stays."""
    job, messages = _run(tmp_path / "edof.tif", _amber(shared_data, 0, 2, 4), caplog)
    assert job.sidecar["kernel"]["depth_invariance_eq8"]["mean"] < SPARSE_SPREAD
    assert not messages and "frame_guard" not in job.sidecar


def test_the_linear_result_asked_for_is_kept_and_warned_of(tmp_path, shared_data, caplog):
    """With --no-frame-range (the paper's linear result) the same two frames are not
    guarded, only warned of, with what to do."""
    job, messages = _run(
        tmp_path / "edof.tif", _amber(shared_data, 0, 5), caplog, frame_range=False
    )
    (message,) = messages
    assert "drop --no-frame-range" in message and "frame_guard" not in job.sidecar


def test_the_guard_beats_one_kernel_on_two_frames_at_their_planes(tmp_path, monkeypatch):
    """Two frames (500 and 1600 mm) of two textured planes at those depths, noise 0.01, no
    lens (the span fitted): against the truth the guarded result is 28.21 dB, one kernel's
    27.91 (the same job with the switch turned off). Where a third plane lies between the
    frames the guard gives 0.39 dB instead, and where both lie between them it gains
    0.52 dB (NOTE.md, part 28)."""
    from skimage import data

    from pipeline.core.colour import srgb_to_linear

    sharp = srgb_to_linear(data.astronaut()[40:296, 130:386].astype(np.float32) / 255)
    (tmp_path / "stack").mkdir()
    folder = make_stack(
        tmp_path / "stack", sharp, [500.0, 1600.0], positions_for(500, 1600, 2), noise=0.01
    )
    (folder / "stack.toml").unlink()  # no lens: the blur span is fitted
    options = StackOptions(encoding="float32")
    guarded = process_stack(folder, tmp_path / "guarded.tif", options)
    assert "chosen_for_spread" in guarded.sidecar["frame_guard"]
    monkeypatch.setattr(stack_job, "SPARSE_SPREAD", np.inf)
    single = process_stack(folder, tmp_path / "single.tif", options)
    assert "frame_guard" not in single.sidecar
    gains = psnr(read_frame(tmp_path / "guarded.tif"), sharp) - psnr(
        read_frame(tmp_path / "single.tif"), sharp
    )
    assert gains > 0.15, gains
    best = max(psnr(read_frame(f), sharp) for f in sorted(folder.glob("frame_*.tif")))
    assert psnr(read_frame(tmp_path / "guarded.tif"), sharp) > best + 5.0


@pytest.mark.parametrize("spread", [SPARSE_SPREAD - 1e-6, SPARSE_SPREAD, SPARSE_SPREAD + 1e-6])
def test_the_threshold_is_strict(spread):
    """Only a spread above ``SPARSE_SPREAD`` counts as too sparse."""
    found = stack_job.sparse_spread({"depth_invariance_eq8": {"mean": spread}})
    assert found == (spread if spread > SPARSE_SPREAD else None)
