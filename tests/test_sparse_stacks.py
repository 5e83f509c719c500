"""Stacks whose frames lie too far apart, for their blur, for one kernel to fit every depth
(``pipeline.jobs.stack.check_sparse_stack``): the user is told, and how to help it."""

from __future__ import annotations

import logging

import pytest

from pipeline.jobs.options import StackOptions
from pipeline.jobs.stack import SPARSE_SPREAD, process_stack

WARNED = "too far apart for one kernel"


def _run(tmp_path, frames, caplog, **options):
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pipeline.jobs.stack"):
        job = process_stack(frames, tmp_path / "edof.tif", StackOptions(**options))
    messages = [r.getMessage() for r in caplog.records if WARNED in r.getMessage()]
    return job, messages


@pytest.mark.parametrize(
    ("indices", "warned"),
    [
        # two frames 106 px of blur apart: softer than the sharpest frame in 6 of 7 regions
        ((0, 5), True),
        # three frames 42 px apart: as good as focus-stack in 7 of 9 regions, not warned
        ((0, 2, 4), False),
    ],
)
def test_frames_too_far_apart_for_one_kernel_are_warned_about(
    tmp_path, shared_data, caplog, indices, warned
):
    """amber's frames 0 and 5: the per-depth kernels' mean Eq. 8 spread from the stack's IPSF
    is 4.8 (the real stacks: 0.02-0.82), so the user is told and pointed to --frame-guard;
    frames 0, 2 and 4 (spread 2.4) are not warned of. The spread is the sidecar's, so the
    warning and the record agree."""
    folder = shared_data / "shinestacker-amber"
    frames = [folder / f"000{i}.jpg" for i in indices]
    job, messages = _run(tmp_path, frames, caplog)
    spread = job.sidecar["kernel"]["depth_invariance_eq8"]["mean"]
    assert (spread > SPARSE_SPREAD) == warned, spread
    assert bool(messages) == warned, messages
    if warned:
        (message,) = messages
        assert "shinestacker-amber (2 frames, 0000.jpg .. 0005.jpg)" in message
        assert f"spread {spread:.1f}" in message and "--frame-guard" in message


def test_the_warning_is_not_given_when_its_advice_is_taken(tmp_path, shared_data, caplog):
    """With --frame-guard, the advice the warning gives, the same two frames are not warned
    of again."""
    folder = shared_data / "shinestacker-amber"
    frames = [folder / "0000.jpg", folder / "0005.jpg"]
    _, messages = _run(tmp_path, frames, caplog, frame_guard=True)
    assert not messages
