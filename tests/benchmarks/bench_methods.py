"""PSNR of each deconvolution method against the sharp image and the best single frame.

    python tests/benchmarks/bench_methods.py

Synthetic focal stacks (9 frames, 450-2500 mm) of three planes (500, 800, 1600 mm)
rendered with exact lens PSFs (Eqs. 2-3) by the engine tests' renderer, noise-free
and with noise sigma 0.01, plus the shipped sample (stacks/motorcycle, noisy,
rendered with occlusion and breathing).
"""

from __future__ import annotations

import logging
import sys
import tempfile
from pathlib import Path

import numpy as np
from skimage import data

TESTS = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(TESTS))

from test_engine import make_stack, positions_for  # noqa: E402  (the tests' renderer)

from pipeline.core.colour import srgb_to_linear  # noqa: E402
from pipeline.core.quality import psnr  # noqa: E402
from pipeline.io.read import read_frame  # noqa: E402
from pipeline.jobs.options import StackOptions  # noqa: E402
from pipeline.jobs.stack import process_stack  # noqa: E402
from pipeline.parallel.scheduler import scheduler_context  # noqa: E402

METHODS = ("wiener", "rl", "sparse")


def table_row(name: str, stack: Path, truth: np.ndarray, frames) -> str:
    best = max(psnr(read_frame(f), truth) for f in frames)
    scores = []
    with scheduler_context(threads=2), tempfile.TemporaryDirectory() as tmp:
        for method in METHODS:
            options = StackOptions(method=method, encoding="float32")
            job = process_stack([stack], Path(tmp) / f"{method}.tif", options)
            scores.append(psnr(job.image, truth))
    return f"| {name} | {best:.2f} | " + " | ".join(f"{s:.2f}" for s in scores) + " |"


def main() -> None:
    logging.disable(logging.WARNING)
    print("| stack | best frame dB | " + " | ".join(f"{m} dB" for m in METHODS) + " |")
    print("|---" * (2 + len(METHODS)) + "|")
    sharp = srgb_to_linear(data.astronaut()[40:296, 130:386].astype(np.float32) / 255)
    for noise in (0.0, 0.01):
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            positions = positions_for(450, 2500, 9)
            make_stack(folder, sharp, [500.0, 800.0, 1600.0], positions, noise=noise)
            frames = sorted(folder.glob("frame_*.tif"))
            print(table_row(f"3 planes, noise {noise}", folder, sharp, frames))
    sample = TESTS.parent / "stacks" / "motorcycle"
    truth = read_frame(sample / "ground_truth.tif")
    print(table_row("stacks/motorcycle (noisy)", sample, truth, sorted(sample.glob("frame_*.png"))))


if __name__ == "__main__":
    main()
