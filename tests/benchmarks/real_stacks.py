"""Extended DOF on the real focal stacks of ../shared/data: sharpness against every frame.

    python tests/benchmarks/real_stacks.py [--out DIR] [--method wiener]

For each stack: runs the main job, warps every frame into the result's geometry
with the homographies of the result's sidecar, and measures the median edge
width (:mod:`pipeline.quality`, 10-90% rise at strong edges, which noise and
ringing cannot shrink) of the result and of each frame, over the whole image
and in a 3x3 grid of regions. Writes ``real_stacks.md`` and, per stack, a PNG of
crops: best single frame (left) beside the result (right).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from pipeline.core import align
from pipeline.core.colour import linear_to_srgb
from pipeline.core.quality import sharpness_against_frames
from pipeline.io.read import read_frame
from pipeline.jobs.options import StackOptions
from pipeline.jobs.stack import process_stack
from pipeline.parallel.scheduler import scheduler_context

SHARED = Path(__file__).resolve().parents[3] / "shared" / "data"
STACKS = {
    "pcb7": "focusstack-pcb/pcb7/pcb_*.jpg",
    "pcb10": "focusstack-pcb/pcb10/pcb_*.JPG",
    "beetle": "chimpstackr-beetle/DSC_*.jpg",
    "amber": "shinestacker-amber/*.jpg",
}


def evaluate(result: np.ndarray, sidecar: dict) -> tuple[dict, list[np.ndarray]]:
    """Sharpness of the result against every frame warped into its geometry."""
    frames = [
        align.warp(read_frame(path), np.array(meta["homography"]), result.shape)
        for meta, path in zip(sidecar["frames"], sidecar["inputs"])
    ]
    return sharpness_against_frames(result, frames), frames


def crops_png(path: Path, best: np.ndarray, result: np.ndarray, size: int = 240) -> None:
    rows, cols = result.shape[:2]
    size = min(size, rows // 2, cols // 2)
    tiles = []
    for fy, fx in ((0.2, 0.2), (0.5, 0.5), (0.75, 0.75)):
        y0 = int(np.clip(fy * rows - size // 2, 0, rows - size))
        x0 = int(np.clip(fx * cols - size // 2, 0, cols - size))
        pair = [
            best[y0 : y0 + size, x0 : x0 + size],
            np.ones((size, 6, 3), np.float32),
            result[y0 : y0 + size, x0 : x0 + size],
        ]
        tiles += [np.concatenate(pair, axis=1), np.ones((6, 2 * size + 6, 3), np.float32)]
    grid = np.clip(linear_to_srgb(np.clip(np.concatenate(tiles), 0, 1)), 0, 1)
    cv2.imwrite(str(path), np.round(grid * 255).astype(np.uint8)[..., ::-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).resolve().parent / "results" / "real_stacks"
    )
    parser.add_argument("--method", default="wiener")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    lines = [
        "| stack | frames | scale range | blur span px | result edge px | best frame | "
        "best frame edge px | regions sharper | time s |",
        "|---" * 9 + "|",
    ]
    with scheduler_context(threads=2), tempfile.TemporaryDirectory() as tmp:
        for name, pattern in STACKS.items():
            out = Path(tmp) / f"{name}.tif"  # only the crops and the table are kept
            job = process_stack([str(SHARED / pattern)], out, StackOptions(method=args.method))
            side = job.sidecar
            scores, frames = evaluate(job.image, side)
            crops_png(args.out / f"{name}_crops.png", frames[scores["best"]], job.image)
            scales = [f["scale"] for f in side["frames"]]
            lines.append(
                f"| {name} | {len(scales)} | {min(scales):.3f}-{max(scales):.3f} | "
                f"{side['kernel']['blur_span_px']:.0f} | {scores['result_px']:.2f} | "
                f"{Path(side['inputs'][scores['best']]).name} | "
                f"{scores['frames_px'][scores['best']]:.2f} | "
                f"{scores['regions_sharper']}/{scores['regions']} | "
                f"{side['timings_s']['total']:.1f} |"
            )
            print(lines[-1], flush=True)
    (args.out / "real_stacks.md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
