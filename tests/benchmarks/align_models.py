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
* **a wide-angle lens turned** (where the keystone is needed): pcb7's reduced copies, each
  warped as a camera with a 16 mm lens on APS-C (82 degrees across the diagonal) sees the
  scene when turned by a seeded angle of up to 0.25, 0.5 or 1 degree about its vertical axis
  (``K R K^-1``, a keystone), or about both axes and shifted by up to 1% of the side,
  cropped alike; the largest distance of a corner from the still stack's estimate
  conjugated by the known moves (px of the 768 px copies).

* **what "auto" sees**: the statistics its choice is made on (``align._turn_evidence``), for
  the real stacks as shot, cropped and at 384 px, two rendered stacks and pcb7 turned by up
  to 0.1-1 degree.

"auto" (not the default): where it is the similarity's figure, it chose the similarity.

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

MODELS = ("similarity", "keystone", "affine", "homography", "auto")
SHAPE = (480, 640)
SIDE_PX = 768  # the main job's matching copies (StackOptions.align_max_side_px)
CROPS = (0.08, 0.16)


def _mapped(h: np.ndarray, points: np.ndarray) -> np.ndarray:
    q = np.asarray(h) @ points
    return q[:2] / q[2]


def _grid(rows: int, cols: int, step: int = 16) -> np.ndarray:
    ys, xs = np.mgrid[0:rows:step, 0:cols:step]
    return np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)]).astype(np.float64)


CORNERS = np.array(
    [[0, SHAPE[1] - 1, 0, SHAPE[1] - 1], [0, 0, SHAPE[0] - 1, SHAPE[0] - 1], [1, 1, 1, 1.0]]
)


def worst_corner(found, truth) -> float:
    """The largest distance (px) of a frame's corner from where ``truth`` puts it."""
    return max(
        float(np.hypot(*(_mapped(np.asarray(a), CORNERS) - _mapped(np.asarray(t), CORNERS))).max())
        for a, t in zip(found, truth)
    )


def rendered_stacks():
    """The rendered breathing stacks (8 and 24 frames, clean and with shot noise): yields
    ``(frames, noisy, grey images, true homographies)``."""
    radiance, depth = scenes.edges_scene(SHAPE)
    lens = scenes.scene_lens(SHAPE)
    with tempfile.TemporaryDirectory(prefix="align_models_") as tmp:
        for frames, noisy in itertools.product((8, 24), (False, True)):
            folder = Path(tmp) / f"{frames}_{noisy}"
            scenes.write_stack(folder, radiance, depth, lens, frames, noisy=noisy, tolerance=1e-3)
            listed = tomllib.loads((folder / "stack.toml").read_text())["frames"]
            images = [read_frame(folder / f["file"]).mean(axis=-1) for f in listed]
            truth = align.analytic_alignment([f["image_distance_mm"] for f in listed], SHAPE)
            yield frames, noisy, images, [t.homography for t in truth]


def rendered_corners() -> list[str]:
    """Rows: frames, noise, then each model's worst corner error against the truth (px)."""
    lines = []
    for frames, noisy, images, truth in rendered_stacks():
        cells = []
        for model in MODELS:
            found = align.estimate_alignment(images, model=model)
            cells.append(f"{worst_corner([a.homography for a in found], truth):.3f}")
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


def crop_moved(first, again, shape, margin: int, to_full: float) -> list[float]:
    """Per frame, the largest distance (full-resolution px) over the crop between the
    estimate on the whole copies (``first``, of ``shape``) and on the copies cropped by
    ``margin`` on every side (``again``); ``to_full`` converts the copies' px."""
    shift = np.array([[1, 0, margin], [0, 1, margin], [0, 0, 1.0]])
    back = np.linalg.inv(shift)
    points = _grid(shape[0] - 2 * margin, shape[1] - 2 * margin)
    return [
        float(np.hypot(*(_mapped(back @ a @ shift, points) - _mapped(b, points))).max()) * to_full
        for a, b in zip(first, again)
    ]


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
            cells = []
            for model in MODELS:
                again = align.estimate_alignment(cropped, model=model)
                apart = crop_moved(
                    [a.homography for a in estimates[model]],
                    [b.homography for b in again],
                    previews[0].shape,
                    m,
                    to_full,
                )
                cells.append(f"{max(apart):.2f} ({np.median(apart):.2f})")
            crop_rows.append(f"| {name} | {share:.0%} | " + " | ".join(cells) + " |")
        print(feature_rows[-1], *crop_rows[-len(CROPS) :], sep="\n", flush=True)
    return feature_rows, crop_rows


def turned_copies(
    previews: list[np.ndarray], largest: float, seed: int = 3, both: bool = False
) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """``previews`` as a 16 mm lens on APS-C sees them turned by a seeded angle of up to
    ``largest`` degrees about the vertical axis (``both``: about both axes, and shifted by
    up to 1% of the side), cropped alike: the copies, the moves and the crop."""
    rows_, cols_ = previews[0].shape
    focal = 0.5 * math.hypot(rows_, cols_) / math.tan(math.radians(41))
    k = np.array([[focal, 0, (cols_ - 1) / 2], [0, focal, (rows_ - 1) / 2], [0, 0, 1.0]])

    def turned(pan_deg: float, tilt_deg: float = 0.0) -> np.ndarray:
        a, b = math.radians(pan_deg), math.radians(tilt_deg)
        pan = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        tilt = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
        return k @ pan @ tilt @ np.linalg.inv(k)

    def shifted(rng, share: float) -> np.ndarray:
        d = np.eye(3)
        d[:2, 2] = rng.uniform(-share, share, 2) * np.array([cols_, rows_])
        return d

    m = 60  # px cropped on each side (the largest turn moves the corners by about 45)
    rng = np.random.default_rng(seed)
    if both:
        moves = [shifted(rng, 0.01) @ turned(*rng.uniform(-largest, largest, 2)) for _ in previews]
    else:
        moves = [turned(rng.uniform(-largest, largest)) for _ in previews]
    moved = [
        np.ascontiguousarray(cv2.warpPerspective(p, mv, (cols_, rows_))[m:-m, m:-m])
        for p, mv in zip(previews, moves)
    ]
    return moved, moves, np.array([[1, 0, -m], [0, 1, -m], [0, 0, 1.0]])


def keystone_rows() -> list[str]:
    """Rows: the largest turn, then each model's worst corner against the prediction."""
    files = sorted(glob.glob(str(SHARED / STACKS["pcb7"])))
    previews = [read_preview(f, SIDE_PX) for f in files]
    still = align.estimate_alignment(previews, model="similarity")
    ref = len(previews) // 2
    lines = []
    for largest, both in [(0.25, False), (0.5, False), (1.0, False), (0.5, True)]:
        moved, moves, crop = turned_copies(previews, largest, 3, both)
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
        what = f"{largest}, both axes, shifted by up to 1%" if both else f"{largest}"
        line = f"| {what} | " + " | ".join(cells) + " |"
        print(line, flush=True)
        lines.append(line)
    return lines


def _evidence(frames: list[np.ndarray]) -> tuple[tuple[float, float, float], str]:
    """The neighbour pairs' strongest turn evidence (``align._turn_evidence``: the pair
    whose halves agree best, or, where no pair's are measured, the largest share), and the
    model "auto" fits."""
    similarity = align.estimate_alignment(frames, model="similarity")
    pyramids = [align._pyramid(align._matching_image(f, SIDE_PX)) for f in frames]
    shape, reduced = frames[0].shape[:2], pyramids[0][-1].shape
    ref = len(frames) // 2
    found = []
    for i in range(len(frames)):
        if i == ref:
            continue
        j = i + 1 if i < ref else i - 1
        pair = np.linalg.inv(similarity[j].homography) @ similarity[i].homography
        w = align.rescale_homography(pair, shape, reduced)
        found.append(align._turn_evidence(pyramids[i], pyramids[j], w))
    strongest = min(found, key=lambda e: (e[2], -e[0]))
    return strongest, align.estimate_alignment(frames, model="auto")[0].model


def turn_evidence_rows() -> list[str]:
    """Rows: a stack, its strongest pair's share / corner px / halves' spread, what "auto"
    fits."""
    cases: list[tuple[str, list[np.ndarray]]] = []
    for name, pattern in STACKS.items():
        files = sorted(glob.glob(str(SHARED / pattern)))
        previews = [read_preview(f, SIDE_PX) for f in files]
        rows_, cols_ = previews[0].shape
        cases.append((name, previews))
        for share in (*CROPS, 0.2):
            m = int(share * min(rows_, cols_))
            cases.append((f"{name} cropped {share:.0%}", [p[m:-m, m:-m].copy() for p in previews]))
        cases += [
            (f"{name}, its left half", [p[:, : cols_ // 2 + 64].copy() for p in previews]),
            (f"{name} at 384 px", [read_preview(f, 384) for f in files]),
            (f"{name} at 1024 px", [read_preview(f, 1024) for f in files]),
        ]
    radiance, depth = scenes.edges_scene(SHAPE)
    with tempfile.TemporaryDirectory(prefix="align_models_") as tmp:
        for noisy in (False, True):
            folder = Path(tmp) / str(noisy)
            lens = scenes.scene_lens(SHAPE)
            scenes.write_stack(folder, radiance, depth, lens, 8, noisy=noisy, tolerance=1e-3)
            listed = tomllib.loads((folder / "stack.toml").read_text())["frames"]
            frames = [read_frame(folder / f["file"]).mean(axis=-1) for f in listed]
            cases.append((f"rendered, 8 frames{', noisy' if noisy else ''}", frames))
    for largest in (0.1, 0.25, 0.5, 1.0):
        for seed in (3, 4):
            moved = turned_copies(cases[0][1], largest, seed)[0]
            cases.append((f"pcb7 turned by up to {largest} degree, seed {seed}", moved))
    for seed in (2, 19):  # a hand's shifts mixed in: the shift no longer points as a turn's
        moved = turned_copies(cases[0][1], 0.5, seed, both=True)[0]
        cases.append((f"pcb7 turned by up to 0.5 degree about both axes, shifted, seed {seed}",
                      moved))  # fmt: skip
    lines = []
    for label, frames in cases:
        (share, corner, spread), model = _evidence(frames)
        apart = f"{spread:.2f}" if np.isfinite(spread) else "-"
        lines.append(f"| {label} | {share:.3f} | {corner:.2f} | {apart} | {model} |")
        print(lines[-1], flush=True)
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
        "`--align-model`; `keystone` for a wide-angle lens turned, `auto` to choose).",
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
        "**A wide-angle lens turned** (the case for the keystone): pcb7's 768 px copies as a",
        "16 mm lens on APS-C sees them turned by up to the angle given; the worst corner's",
        "distance (px of the copies) from the still estimate conjugated by the moves.",
        "",
        f"| largest turn, degrees | {heads} |",
        "|---|" + "---|" * len(MODELS),
        *keystone_rows(),
        "",
        "**What \"auto\" sees**: of each stack's neighbour pairs, the one whose similarity,",
        "refined as a keystone at half resolution, gains most: the share of the decorrelation",
        "it takes away, how far it moves a corner (px of the matching copy) and, where these",
        "pass, how far apart the perspective rows fitted on the frame's halves are (in units of",
        "the whole frame's; a turn's keystone is one for the whole frame); the pair whose halves",
        "agree best is shown, else the largest share. \"auto\" fits the keystone where a pair",
        f"reaches a share of {align._TURN_SHARE} and {align._TURN_CORNER_PX} px with halves "
        f"at most {align._TURN_SPREAD} apart.",
        "",
        "| stack | share | corner px | halves apart | auto fits |",
        "|---|---|---|---|---|",
        *turn_evidence_rows(),
    ]
    write_table(args.out / "align_models.md", rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
