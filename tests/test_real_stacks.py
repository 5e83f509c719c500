"""The main job on real focal stacks (../shared/data): breathing recovered, result sharper.

Sharpness is the median 10-90% edge width (pipeline.quality), which noise and
ringing cannot shrink; frames are compared in the result's geometry (warped by
the homographies the job reports).
"""

import numpy as np
import pytest

from pipeline.core import align
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
