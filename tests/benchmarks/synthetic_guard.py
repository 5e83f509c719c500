"""``--frame-guard`` and the quality method on stacks with ground truth (issue 13): PSNR and
SSIM of the main job with and without the guard and with ``--method multiframe``, against a
Wiener filter tuned on the truth and the best frame.

    python tests/benchmarks/synthetic_guard.py [--out results/real_regions/synthetic.md]

Scenes:

* ``3 planes``: the engine tests' renderer (exact lens PSFs, Eqs. 2-3; 9 frames of a
  256 px astronaut crop split into planes at 500, 800 and 1600 mm), noise sigma 0, 0.01,
  0.02, the lens and focus positions known (the kernel from the lens);
* ``3 planes, no lens``: the same at sigma 0.01 with the lens removed from stack.toml, so
  the blur span is fitted (and, with the guard, doubled);
* ``3 planes, plain folder``: the same with no stack.toml at all (no lens, no positions:
  the frames' order stands for them, and the alignment check decides whether the
  magnification ECC reads is real);
* ``3 planes, far plane beyond the frames``: sigma 0.01, frames focused from 450 to 1200 mm
  only, so the 1600 mm plane is in focus in none (Sec. 4.1; ``pipeline.jobs.ends``);
* ``3 planes, end frames on the near and far planes``: sigma 0.01, frames focused from 500
  to 1600 mm, so the end frames' content lies at their own depths (Sec. 4.1's end effect),
  next to an occlusion edge;
* ``depth edge``: two 1/f textures at 500 mm (left, in front) and 1500 mm, ray traced
  with occlusion and the lens's breathing (``tests/reference/raytrace.py``, independent of
  pipeline.simulate), 9 frames focused from 400 to 2500 mm, sigma 0 and 0.01; PSNR also
  within 12 px of the edge and beyond 24 px of it;
* ``motorcycle``: the shipped sample (pipeline.simulate with occlusion, breathing and
  noise); near/away split at its depth map's discontinuities.

Columns: the best frame; ``default`` (no guard); ``--frame-guard``; ``tuned`` = Wiener
with ``lam`` chosen on the truth (20 values, 1e-7..1e-1) on the default's average and
kernel; ``multiframe`` (the quality method, :mod:`pipeline.core.multiframe`); each job's time.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import ndimage
from skimage import data
from skimage.metrics import structural_similarity

TESTS = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(TESTS))

from reference.depth_edge import depth_edge  # noqa: E402
from test_engine import make_stack, positions_for  # noqa: E402

from pipeline.core.colour import srgb_to_linear  # noqa: E402
from pipeline.core.quality import psnr  # noqa: E402
from pipeline.core.stack_kernel import wiener_options  # noqa: E402
from pipeline.io.read import read_frame  # noqa: E402
from pipeline.jobs import stack as stack_job  # noqa: E402
from pipeline.jobs.options import StackOptions  # noqa: E402
from pipeline.parallel.scheduler import scheduler_context  # noqa: E402
from pipeline.parallel.tiling import deconvolve_tiled  # noqa: E402


def ssim(image, truth) -> float:
    image = np.clip(np.asarray(image, np.float64), 0, 1)
    axis = 2 if image.ndim == 3 else None
    return float(structural_similarity(image, truth, channel_axis=axis, data_range=1.0))


def run_job(folder: Path, out: Path, **options):
    """The main job; also returns the average, kernel, samples and clipped mask it
    deconvolved (for the tuned Wiener)."""
    seen = {}
    restore = stack_job.restore_image

    def spy(image, kernel, opts, **kw):
        seen.update(image=image.copy(), kernel=kernel, samples=kw.get("kernel_samples"),
                    clipped=kw.get("clipped"))
        return restore(image, kernel, opts, **kw)

    stack_job.restore_image = spy
    try:
        t0 = time.perf_counter()
        job = stack_job.process_stack(folder, out, StackOptions(encoding="float32", **options))
        seconds = time.perf_counter() - t0
    finally:
        stack_job.restore_image = restore
    return job.image, seconds, seen


def tuned_wiener(seen, truth) -> np.ndarray:
    best, best_db = None, -np.inf
    extra = wiener_options(seen["kernel"], seen["samples"])
    for lam in np.logspace(-7, -1, 20):
        out = deconvolve_tiled(seen["image"], seen["kernel"], method="wiener",
                               censored=seen["clipped"], regularization=lam, **extra)
        db = psnr(out, truth)
        if db > best_db:
            best, best_db = out, db
    return best


def scores(image, truth, regions) -> list[str]:
    """PSNR / SSIM, then PSNR near the depth edges and away from them (or "-")."""
    cells = [f"{psnr(image, truth):.2f} / {ssim(image, truth):.3f}"]
    for key in ("near edge", "away"):
        mask = (regions or {}).get(key)
        cells.append("-" if mask is None else f"{psnr(image[mask], truth[mask]):.2f}")
    return cells


def evaluate(name, folder: Path, truth, frames, regions) -> list[str]:
    rows = []
    with scheduler_context(threads=2), tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        best = max(frames, key=lambda f: psnr(read_frame(f), truth))
        results = {"best frame": (read_frame(best), None)}
        default, t_default, seen = run_job(folder, tmp / "default.tif")
        results["default"] = (default, t_default)
        results["--frame-guard"] = run_job(folder, tmp / "guard.tif", frame_guard=True)[:2]
        results["tuned Wiener"] = (tuned_wiener(seen, truth), None)
        results["multiframe"] = run_job(folder, tmp / "multi.tif", method="multiframe")[:2]
    for label, (image, seconds) in results.items():
        time_s = "" if seconds is None else f"{seconds:.2f}"
        rows.append(f"| {name} | {label} | " + " | ".join(scores(image, truth, regions))
                    + f" | {time_s} |")
    return rows


def planes(
    folder: Path, noise: float, lens: bool, far_mm: float = 2500.0, near_mm: float = 450.0
):
    sharp = srgb_to_linear(data.astronaut()[40:296, 130:386].astype(np.float32) / 255)
    positions = positions_for(near_mm, far_mm, 9)
    make_stack(folder, sharp, [500.0, 800.0, 1600.0], positions, noise=noise)
    if not lens:
        toml = folder / "stack.toml"
        toml.write_text("\n".join(line for line in toml.read_text().splitlines()
                                  if not line.startswith("lens")))
    return sharp, sorted(folder.glob("frame_*.tif"))


def motorcycle_regions(sample: Path, truth):
    depth = np.load(sample / "depth_mm.npy")
    inv = 1.0 / depth
    jump = ndimage.maximum_filter(inv, 3) - ndimage.minimum_filter(inv, 3)
    edges = jump > 0.1 * np.ptp(inv)
    near = ndimage.binary_dilation(edges, iterations=8)
    far = ~ndimage.binary_dilation(edges, iterations=20)
    inner = np.zeros(truth.shape[:2], bool)
    inner[16:-16, 16:-16] = True
    return {"near edge": near & inner, "away": far & inner}


def print_and_save(lines: list[str], out: Path | None) -> None:
    """Print a table's lines and, with ``out``, write them there."""
    text = "\n".join(lines)
    print(text)
    if out:
        out.write_text(text + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    logging.disable(logging.WARNING)
    lines = [
        "| scene | result | PSNR dB / SSIM | PSNR near edge | PSNR away | time s |",
        "|---|---|---|---|---|---|",
    ]
    with tempfile.TemporaryDirectory() as tmp:
        for noise in (0.0, 0.01, 0.02):
            folder = Path(tmp) / f"planes{noise}"
            folder.mkdir()
            truth, frames = planes(folder, noise, lens=True)
            lines += evaluate(f"3 planes, sigma {noise}", folder, truth, frames, None)
            print("\n".join(lines[-5:]), flush=True)
        folder = Path(tmp) / "nolens"
        folder.mkdir()
        truth, frames = planes(folder, 0.01, lens=False)
        lines += evaluate("3 planes, sigma 0.01, no lens", folder, truth, frames, None)
        folder = Path(tmp) / "plain"
        folder.mkdir()
        truth, frames = planes(folder, 0.01, lens=True)
        (folder / "stack.toml").unlink()
        lines += evaluate("3 planes, sigma 0.01, plain folder", folder, truth, frames, None)
        folder = Path(tmp) / "beyond"
        folder.mkdir()
        truth, frames = planes(folder, 0.01, lens=True, far_mm=1200.0)
        lines += evaluate("3 planes, sigma 0.01, far plane beyond the frames", folder, truth,
                          frames, None)
        folder = Path(tmp) / "ends"
        folder.mkdir()
        truth, frames = planes(folder, 0.01, lens=True, far_mm=1600.0, near_mm=500.0)
        lines += evaluate("3 planes, sigma 0.01, end frames on the near and far planes", folder,
                          truth, frames, None)
        for noise in (0.0, 0.01):
            folder = Path(tmp) / f"edge{noise}"
            folder.mkdir()
            truth, frames, regions = depth_edge(folder, noise)
            lines += evaluate(f"depth edge, sigma {noise}", folder, truth, frames, regions)
            print("\n".join(lines[-5:]), flush=True)
    sample = TESTS.parent / "stacks" / "motorcycle"
    truth = read_frame(sample / "ground_truth.tif")
    regions = motorcycle_regions(sample, truth)
    lines += evaluate("motorcycle (noisy)", sample, truth, sorted(sample.glob("frame_*.png")),
                      regions)
    print_and_save(lines, args.out)


if __name__ == "__main__":
    main()
