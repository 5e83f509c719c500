"""Which motion an estimated alignment should fit: similarity, affine or homography (issue 13).

    python tests/benchmarks/align_models.py [--out tests/benchmarks/results/align]

Three measures, none of which the estimate can satisfy by fitting blur instead of motion:

* **rendered breathing stacks** (the depth-edge scene, 640x480, 8 and 24 frames, clean and
  with shot noise, the lens's breathing and exact defocus): the largest distance (px) of a
  frame's corner from where the lens's geometry puts it (``analytic_alignment``);
* **real stacks against feature matches**: each frame's magnification against SIFT matches
  at full resolution and a RANSAC similarity (an estimator that shares nothing with ECC's
  intensity fit), the largest and the mean difference;
* **real stacks cropped**: the estimate on the frames' reduced copies and on the same copies
  cropped by 8% and 16% of their shorter side. Both describe one camera motion, so where they
  disagree (the largest distance over the crop, in full-resolution px, worst frame) the
  estimate followed the content instead;
* **a wide-angle lens turned** (where a homography is needed): pcb7's reduced copies, each
  warped as a camera with a 16 mm lens on APS-C (82 degrees across the diagonal) sees the
  scene when turned by a seeded angle of up to 0.25, 0.5 or 1 degree about its vertical axis
  (``K R K^-1``, a keystone), cropped alike; the largest distance of a corner from the still
  stack's estimate conjugated by the known turns (px of the 768 px copies).

Writes ``OUT/align_models.md``.
"""

from __future__ import annotations

import argparse
import glob
import itertools
import logging
import math
import sys
import tempfile
import tomllib
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from align_without_breathing import write_table
from real_stacks import SHARED, STACKS

from pipeline.core import align
from pipeline.io.read import read_frame, read_preview
from pipeline.paper.bench import scenes

MODELS = ("similarity", "affine", "homography")
SHAPE = (480, 640)
SIDE_PX = 768  # the main job's matching copies (StackOptions.align_max_side_px)
CROPS = (0.08, 0.16)


def _mapped(h: np.ndarray, points: np.ndarray) -> np.ndarray:
    q = np.asarray(h) @ points
    return q[:2] / q[2]


def _grid(rows: int, cols: int, step: int = 16) -> np.ndarray:
    ys, xs = np.mgrid[0:rows:step, 0:cols:step]
    return np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)]).astype(np.float64)


def rendered_corners() -> list[str]:
    """Rows: frames, noise, then each model's worst corner error against the truth (px)."""
    radiance, depth = scenes.edges_scene(SHAPE)
    lens = scenes.scene_lens(SHAPE)
    rows_, cols_ = SHAPE
    corners = np.array([[0, cols_ - 1, 0, cols_ - 1], [0, 0, rows_ - 1, rows_ - 1], [1, 1, 1, 1.0]])
    lines = []
    with tempfile.TemporaryDirectory(prefix="align_models_") as tmp:
        for frames, noisy in itertools.product((8, 24), (False, True)):
            folder = Path(tmp) / f"{frames}_{noisy}"
            scenes.write_stack(folder, radiance, depth, lens, frames, noisy=noisy, tolerance=1e-3)
            listed = tomllib.loads((folder / "stack.toml").read_text())["frames"]
            images = [read_frame(folder / f["file"]).mean(axis=-1) for f in listed]
            truth = align.analytic_alignment([f["image_distance_mm"] for f in listed], SHAPE)
            cells = []
            for model in MODELS:
                found = align.estimate_alignment(images, model=model)
                apart = [
                    _mapped(a.homography, corners) - _mapped(t.homography, corners)
                    for a, t in zip(found, truth)
                ]
                worst = max(float(np.hypot(*d).max()) for d in apart)
                cells.append(f"{worst:.3f}")
            line = f"| {frames} | {'yes' if noisy else 'no'} | " + " | ".join(cells) + " |"
            print(line, flush=True)
            lines.append(line)
    return lines


def feature_scales(files: list[str]) -> np.ndarray:
    """Magnification of each frame against the middle one: SIFT + RANSAC similarity."""
    sift = cv2.SIFT_create(8000)
    found = [sift.detectAndCompute(cv2.imread(f, cv2.IMREAD_GRAYSCALE), None) for f in files]
    ref_points, ref_descriptors = found[len(files) // 2]
    scales = []
    for points, descriptors in found:
        pairs = cv2.BFMatcher().knnMatch(descriptors, ref_descriptors, k=2)
        good = [a for a, b in pairs if a.distance < 0.7 * b.distance]
        src = np.float32([points[a.queryIdx].pt for a in good])
        dst = np.float32([ref_points[a.trainIdx].pt for a in good])
        m, _ = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC, ransacReprojThreshold=1.5)
        scales.append(1 / math.sqrt(abs(np.linalg.det(m[:, :2]))))
    return np.array(scales)


def real_stacks() -> tuple[list[str], list[str]]:
    """Rows of the feature-match table and of the crop table, per real stack."""
    feature_rows, crop_rows = [], []
    for name, pattern in STACKS.items():
        files = sorted(glob.glob(str(SHARED / pattern)))
        previews = [read_preview(f, SIDE_PX) for f in files]
        full_side = max(read_frame(files[0]).shape[:2])
        to_full = full_side / max(previews[0].shape)
        estimates = {m: align.estimate_alignment(previews, model=m) for m in MODELS}
        sift = feature_scales(files)
        cells = []
        for model in MODELS:
            d = np.abs(np.array([a.scale for a in estimates[model]]) - sift)
            cells.append(f"{100 * d.max():.2f} / {100 * d.mean():.2f}")
        feature_rows.append(f"| {name} | " + " | ".join(cells) + " |")
        rows_, cols_ = previews[0].shape
        for share in CROPS:
            m = int(share * min(rows_, cols_))
            cropped = [p[m : rows_ - m, m : cols_ - m].copy() for p in previews]
            shift = np.array([[1, 0, m], [0, 1, m], [0, 0, 1.0]])
            points = _grid(rows_ - 2 * m, cols_ - 2 * m)
            cells = []
            for model in MODELS:
                again = align.estimate_alignment(cropped, model=model)
                apart = [
                    float(
                        np.hypot(
                            *(
                                _mapped(np.linalg.inv(shift) @ a.homography @ shift, points)
                                - _mapped(b.homography, points)
                            )
                        ).max()
                    )
                    * to_full
                    for a, b in zip(estimates[model], again)
                ]
                cells.append(f"{max(apart):.2f} ({np.median(apart):.2f})")
            crop_rows.append(f"| {name} | {share:.0%} | " + " | ".join(cells) + " |")
        print(feature_rows[-1], *crop_rows[-len(CROPS) :], sep="\n", flush=True)
    return feature_rows, crop_rows


def keystone_rows() -> list[str]:
    """Rows: the largest turn, then each model's worst corner against the prediction."""
    files = sorted(glob.glob(str(SHARED / STACKS["pcb7"])))
    previews = [read_preview(f, SIDE_PX) for f in files]
    rows_, cols_ = previews[0].shape
    still = align.estimate_alignment(previews)
    ref = len(previews) // 2
    focal = 0.5 * math.hypot(rows_, cols_) / math.tan(math.radians(41))
    k = np.array([[focal, 0, (cols_ - 1) / 2], [0, focal, (rows_ - 1) / 2], [0, 0, 1.0]])

    def turned(deg: float) -> np.ndarray:
        t = math.radians(deg)
        r = np.array([[math.cos(t), 0, math.sin(t)], [0, 1, 0], [-math.sin(t), 0, math.cos(t)]])
        return k @ r @ np.linalg.inv(k)

    m = 60  # px cropped on each side (the largest turn moves the corners by about 45)
    crop = np.array([[1, 0, -m], [0, 1, -m], [0, 0, 1.0]])
    lines = []
    for largest in (0.25, 0.5, 1.0):
        rng = np.random.default_rng(3)
        moves = [turned(rng.uniform(-largest, largest)) for _ in previews]
        moved = [
            np.ascontiguousarray(cv2.warpPerspective(p, mv, (cols_, rows_))[m:-m, m:-m])
            for p, mv in zip(previews, moves)
        ]
        h, w = moved[0].shape
        points = np.array([[0, w - 1, 0, w - 1], [0, 0, h - 1, h - 1], [1, 1, 1, 1.0]])
        cells = []
        for model in MODELS:
            found = align.estimate_alignment(moved, model=model)
            worst = 0.0
            for i, a in enumerate(found):
                predicted = crop @ moves[ref] @ still[i].homography @ np.linalg.inv(crop @ moves[i])
                d = _mapped(a.homography, points) - _mapped(predicted, points)
                worst = max(worst, float(np.hypot(*d).max()))
            cells.append(f"{worst:.2f}")
        line = f"| {largest} | " + " | ".join(cells) + " |"
        print(line, flush=True)
        lines.append(line)
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "align")
    args = parser.parse_args(argv)
    logging.disable(logging.WARNING)  # the scene lens's sensor is larger than the frames
    heads = " | ".join(MODELS)
    rows = [
        "# Which motion the estimated alignment fits (issue 13)",
        "",
        "`python tests/benchmarks/align_models.py`. The default is `similarity` (since stop 37;",
        "`--align-model`).",
        "",
        "**Rendered breathing stacks** (the depth-edge scene, 640x480): the largest distance (px)",
        "of a frame's corner from where the lens's geometry puts it.",
        "",
        f"| frames | noise | {heads} |",
        "|---|---|" + "---|" * len(MODELS),
        *rendered_corners(),
    ]
    feature_rows, crop_rows = real_stacks()
    rows += [
        "",
        "**Real stacks against feature matches**: each frame's magnification against SIFT",
        "matches at full resolution fitted by a RANSAC similarity; the largest / the mean",
        "difference over the frames, in %.",
        "",
        f"| stack | {heads} |",
        "|---|" + "---|" * len(MODELS),
        *feature_rows,
        "",
        "**Real stacks cropped**: the estimate on the frames' reduced copies against the",
        "estimate on the same copies cropped by a share of their shorter side; the largest",
        "distance over the crop (full-resolution px) of the worst frame (the median frame's).",
        "",
        f"| stack | crop | {heads} |",
        "|---|---|" + "---|" * len(MODELS),
        *crop_rows,
        "",
        "**A wide-angle lens turned** (the case for `--align-model homography`): pcb7's 768 px",
        "copies as a 16 mm lens on APS-C sees them turned by up to the angle given; the worst",
        "corner's distance (px of the copies) from the still estimate conjugated by the turns.",
        "",
        f"| largest turn, degrees | {heads} |",
        "|---|" + "---|" * len(MODELS),
        *keystone_rows(),
    ]
    write_table(args.out / "align_models.md", rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
