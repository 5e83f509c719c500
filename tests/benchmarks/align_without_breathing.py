"""Alignment on focal stacks with and without focus breathing (issue 13).

Renders the accuracy benchmark's depth-edge scene (:func:`pipeline.paper.bench.scenes.edges_scene`)
as focal stacks of 8 and 24 frames, clean and noisy, once with the magnification change of a
real lens (every frame scaled by ``p_i / p_ref``) and once without it (every frame rendered
at its own scale: the true alignment is the identity). For each, the main job runs with
``--align none`` and with the alignment estimated under each motion model; it reports the
PSNR of the result against the scene (the ground truth) and, for the stacks without
breathing, the estimate's largest displacement of a frame corner (px) from the identity.

    python tests/benchmarks/align_without_breathing.py [--out tests/benchmarks/results/align]
"""

from __future__ import annotations

import argparse
import itertools
import tempfile
from pathlib import Path

import numpy as np

from pipeline.core import simulate
from pipeline.core.scene import Scene
from pipeline.io import profiles, write
from pipeline.jobs.options import StackOptions
from pipeline.jobs.stack import process_stack
from pipeline.paper.bench import scenes

SHAPE = (480, 640)
MODELS = ("homography", "affine", "similarity")
BORDER_PX = 24  # PSNR away from the frame's edge (no data beyond it in any frame)


def write_without_breathing(directory: Path, radiance, depth, lens, frames: int, noisy: bool):
    """Like :func:`scenes.write_stack`, but each frame at its own scale (no breathing)."""
    directory.mkdir(parents=True, exist_ok=True)
    scene = Scene.from_depth(radiance, depth)
    positions = scenes.stack_positions(lens, frames)
    (directory / "lens.toml").write_text(profiles.lens_to_toml(lens), encoding="utf-8")
    lines = ['lens = "lens.toml"', 'kind = "focal-stack"']
    for i, p in enumerate(positions):
        images, _ = simulate.render_focal_stack(
            scene, lens, [p], exposure_s=0.1, exposure=scenes.NOISE if noisy else None,
            reference_image_distance_mm=float(p), tolerance=1e-3, seed=100 + i,
        )  # fmt: skip
        write.write_image(directory / f"frame_{i:02d}.tif", images[0], encoding="float32")
        lines += ["", "[[frames]]", f'file = "frame_{i:02d}.tif"', f"image_distance_mm = {p:.9f}"]
    (directory / "stack.toml").write_text("\n".join(lines) + "\n", encoding="utf-8")


def psnr(image: np.ndarray, truth: np.ndarray) -> float:
    b = BORDER_PX
    error = np.clip(image[b:-b, b:-b], 0.0, 1.0) - truth[b:-b, b:-b]
    return float(10 * np.log10(1.0 / np.mean(error**2)))


def corner_error_px(homographies, shape) -> float:
    rows, cols = shape[:2]
    corners = np.array(
        [[0, cols - 1, 0, cols - 1], [0, 0, rows - 1, rows - 1], [1, 1, 1, 1]], float
    )
    worst = 0.0
    for h in homographies:
        moved = np.asarray(h) @ corners
        worst = max(worst, float(np.max(np.hypot(*(moved[:2] / moved[2] - corners[:2])))))
    return worst


def compare_models(stack: Path, out: Path, truth, breathing: bool):
    """PSNR cells (``--align none``, then each model) and corner displacements of a stack."""
    cells = [f"{psnr(process_stack(stack, out, StackOptions(align='none')).image, truth):.2f}"]
    corners = []
    for model in MODELS:
        result = process_stack(stack, out, StackOptions(align_model=model))
        cells.append(f"{psnr(result.image, truth):.2f}")
        homographies = [f["homography"] for f in result.sidecar["frames"]]
        corners.append("-" if breathing else f"{corner_error_px(homographies, SHAPE):.2f}")
    return cells, corners


def write_table(path: Path, rows: list[str]) -> None:
    """Write a results table (markdown lines), creating its folder, and say where."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")
    print(f"wrote {path}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "align")
    args = parser.parse_args(argv)
    radiance, depth = scenes.edges_scene(SHAPE)
    lens = scenes.scene_lens(SHAPE)
    rows = [
        "# Alignment with and without focus breathing (issue 13)",
        "",
        "`python tests/benchmarks/align_without_breathing.py`: the depth-edge scene, 640x480, "
        "PSNR (dB) of `flexdof stack` against the truth; corner = the largest displacement of "
        "a frame corner from the identity (px), on the stacks without breathing.",
        "",
        "| breathing | frames | noise | none | " + " | ".join(MODELS) + " | corner px: "
        + ", ".join(MODELS) + " |",
        "|---|---|---|---|" + "---|" * len(MODELS) + "---|",
    ]
    with tempfile.TemporaryDirectory(prefix="align_bench_") as tmp:
        for breathing, frames, noisy in itertools.product((False, True), (8, 24), (False, True)):
            d = Path(tmp) / f"{breathing}_{frames}_{noisy}"
            if breathing:
                scenes.write_stack(d, radiance, depth, lens, frames, noisy=noisy, tolerance=1e-3)
            else:
                write_without_breathing(d, radiance, depth, lens, frames, noisy)
            cells, corners = compare_models(d, Path(tmp) / "out.tif", radiance, breathing)
            line = (
                f"| {'yes' if breathing else 'no'} | {frames} | {'yes' if noisy else 'no'} | "
                + " | ".join(cells) + " | " + ", ".join(corners) + " |"
            )
            print(line, flush=True)
            rows.append(line)
    write_table(args.out / "align_without_breathing.md", rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
