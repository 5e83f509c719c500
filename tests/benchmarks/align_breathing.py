"""Would a stack-wide breathing model align better than a similarity per frame? (issue 13)

    python tests/benchmarks/align_breathing.py [--out tests/benchmarks/results/align]

Issue 13 asks for corners well under 0.1 px from the truth; a similarity per frame
(chained between neighbours; ``breathing_px=None``) lands 0.17-0.21 px from it on the
rendered breathing stacks. Focus breathing alone is a scaling of every frame about one
centre, the optical axis: ``x -> c + s_k (x - c)``, one scale per frame and one centre for
the stack. This fits that model to the per-frame similarities (least squares over a grid of
each frame's points, alternating the scales and the centre) and measures:

* **rendered breathing stacks**: the worst corner against the lens's geometry, for the
  similarity per frame, the model with its centre fitted, the model about the image centre
  (where the renderer puts the axis) and the default (which snaps the similarities to the
  model about the image centre where they all lie within ``align.BREATHING_TOLERANCE_PX``
  of the matching copy from it), with the model it fitted; the fitted centre's distance
  from the image centre; and, as a control on
  the shift alone, phase correlation (``cv2.phaseCorrelate``, Hanning window) of each
  frame warped by the true alignment against the reference, the median (largest) shift it
  reads over the frames (0 for an unbiased shift estimator);
* **real stacks** (the main job's 768 px matching copies): the fitted centre against the
  image centre, how far the similarity of each frame lies from the model (the largest over
  the frame, full-resolution px) and from the model about the image centre (px of the
  matching copy: what the default's snap compares with its tolerance), the largest turn;
  and the crop test of ``align_models.py`` (the estimate on copies cropped by 8% / 16%
  against the uncropped one) for the similarity and the model.

Writes ``OUT/align_breathing.md``.
"""

from __future__ import annotations

import argparse
import glob
import logging
import math
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from align_models import (
    CROPS,
    SHAPE,
    SIDE_PX,
    _grid,
    _mapped,
    crop_moved,
    rendered_stacks,
    worst_corner,
)
from align_without_breathing import write_table
from real_stacks import SHARED, STACKS

from pipeline.core import align
from pipeline.io.read import read_frame, read_preview


def scaling_about(centre: np.ndarray, scale: float) -> np.ndarray:
    """The homography ``x -> centre + scale (x - centre)``."""
    return np.array(
        [[scale, 0, (1 - scale) * centre[0]], [0, scale, (1 - scale) * centre[1]], [0, 0, 1.0]]
    )


def breathing_fit(homographies, shape, rounds: int = 5000):
    """The breathing model nearest to per-frame homographies, its centre fitted (the main
    job's, about the image centre, is :func:`pipeline.core.align.breathing_about_centre`).

    Parameters
    ----------
    homographies : sequence of (3, 3) arrays
        Each frame's map onto the reference (pixel coordinates of ``shape``).
    shape : (rows, cols)
    rounds : int
        Alternations of the scales (each frame's, given the centre) and the centre
        (given the scales); both steps are linear least squares.

    Returns
    -------
    models : list of (3, 3) arrays
        ``scaling_about(c, s_k)`` per frame.
    centre : ndarray (2,)
    residuals : ndarray
        Per frame, the largest distance (px) over a grid of its points between the given
        homography and the model.
    """
    points = _grid(*shape, step=max(1, min(shape) // 16))
    mapped = [_mapped(np.asarray(h), points) for h in homographies]
    c = np.array([(shape[1] - 1) / 2, (shape[0] - 1) / 2])  # the first round's centre
    for _ in range(rounds):
        d = points[:2] - c[:, None]
        scales = np.array([np.sum(d * (m - c[:, None])) / np.sum(d * d) for m in mapped])
        # m = (1 - s) c + s p for every point: (1 - s) c = m - s p, summed over frames
        weight = np.sum((1 - scales) ** 2) * points.shape[1]
        if weight < 1e-18:  # no frame scales: the centre is not seen
            break
        moved = sum((1 - s) * np.sum(m - s * points[:2], axis=1) for s, m in zip(scales, mapped))
        c_new = moved / weight
        converged = np.allclose(c_new, c, rtol=0, atol=1e-10)
        c = c_new
        if converged:
            break
    models = [scaling_about(c, s) for s in scales]
    residuals = np.array(
        [float(np.hypot(*(m - _mapped(h, points))).max()) for m, h in zip(mapped, models)]
    )
    return models, c, residuals


def rendered_rows() -> list[str]:
    """One row per rendered stack."""
    window = cv2.createHanningWindow(SHAPE[::-1], cv2.CV_64F)
    axis = np.array([(SHAPE[1] - 1) / 2, (SHAPE[0] - 1) / 2])
    lines = []
    for frames, noisy, images, truth in rendered_stacks():
        found = [a.homography for a in align.estimate_alignment(images, breathing_px=None)]
        fitted, centre, _ = breathing_fit(found, SHAPE)
        about_axis, _ = align.breathing_about_centre(found, SHAPE)
        default = align.estimate_alignment(images)
        reference = np.asarray(images[len(images) // 2], np.float64)
        shifts = []
        for image, h in zip(images, truth):
            warped = cv2.warpPerspective(
                np.asarray(image, np.float64), h, SHAPE[::-1], flags=cv2.INTER_CUBIC
            )
            (dx, dy), _ = cv2.phaseCorrelate(reference, warped, window)
            shifts.append(math.hypot(dx, dy))
        chosen = [a.homography for a in default]
        cells = [f"{worst_corner(m, truth):.3f}" for m in (found, fitted, about_axis)] + [
            f"{worst_corner(chosen, truth):.3f} ({default[0].model})",
            f"{np.hypot(*(centre - axis)):.1f}",
            f"{np.median(shifts):.2f} ({max(shifts):.1f})",
        ]
        line = f"| {frames} | {'yes' if noisy else 'no'} | " + " | ".join(cells) + " |"
        print(line, flush=True)
        lines.append(line)
    return lines


def real_rows() -> tuple[list[str], list[str]]:
    """Rows of the model's fit and of the crop test, per real stack."""
    fit_rows, crop_rows = [], []
    for name, pattern in STACKS.items():
        files = sorted(glob.glob(str(SHARED / pattern)))
        previews = [read_preview(f, SIDE_PX) for f in files]
        shape = previews[0].shape[:2]
        to_full = max(read_frame(files[0]).shape[:2]) / max(shape)
        found = [a.homography for a in align.estimate_alignment(previews, breathing_px=None)]
        model, centre, residuals = breathing_fit(found, shape)
        axis = np.array([(shape[1] - 1) / 2, (shape[0] - 1) / 2])
        _, from_axis = align.breathing_about_centre(found, shape)
        turn = max(abs(math.degrees(math.atan2(h[1, 0], h[0, 0]))) for h in found)
        scales = [align.scale_of(h) for h in found]
        fit_rows.append(
            f"| {name} | {len(files)} | {100 * (max(scales) - min(scales)):.2f} | "
            f"({centre[0] * to_full:.0f}, {centre[1] * to_full:.0f}) against "
            f"({axis[0] * to_full:.0f}, {axis[1] * to_full:.0f}) | "
            f"{residuals.max() * to_full:.2f} ({np.median(residuals) * to_full:.2f}) | "
            f"{from_axis.max():.2f} | {turn:.3f} |"
        )
        rows_, cols_ = shape
        for share in CROPS:
            margin = int(share * min(rows_, cols_))
            cropped = [p[margin : rows_ - margin, margin : cols_ - margin].copy() for p in previews]
            again = [a.homography for a in align.estimate_alignment(cropped, breathing_px=None)]
            again_model, _, _ = breathing_fit(again, cropped[0].shape[:2])
            moved = (
                max(crop_moved(a, b, shape, margin, to_full))
                for a, b in ((found, again), (model, again_model))
            )
            crop_rows.append(
                f"| {name} | {share:.0%} | " + " | ".join(f"{v:.2f}" for v in moved) + " |"
            )
        print(fit_rows[-1], *crop_rows[-len(CROPS) :], sep="\n", flush=True)
    return fit_rows, crop_rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "align")
    args = parser.parse_args(argv)
    logging.disable(logging.WARNING)  # the scene lens's sensor is larger than the frames
    fit_rows, crop_rows = real_rows()
    rows = [
        "# A stack-wide breathing model against a similarity per frame (issue 13)",
        "",
        "`python tests/benchmarks/align_breathing.py`. The model: every frame a scaling",
        "about one centre, `x -> c + s_k (x - c)`, fitted to the per-frame similarities",
        "(chained; `breathing_px=None`). The default snaps them to the model about the image",
        f"centre where they all lie within {align.BREATHING_TOLERANCE_PX} px of the matching",
        "copy from it.",
        "",
        "**Rendered breathing stacks** (the depth-edge scene, 640x480): the worst corner's",
        "distance (px) from the lens's geometry; the fitted centre's distance from the image",
        "centre, where the renderer's axis is; the median (largest) shift phase correlation",
        "reads between a frame warped by the true alignment and the reference (0 if",
        "unbiased).",
        "",
        "| frames | noise | similarity per frame | model, centre fitted "
        "| model about the image centre | default (its model) | centre off, px "
        "| phase correlation at the truth, px |",
        "|---|---|---|---|---|---|---|---|",
        *rendered_rows(),
        "",
        "**Real stacks** (768 px matching copies; full-resolution px): the spread of the",
        "frames' magnifications, the fitted centre against the image centre, the",
        "similarity's largest (median) distance from the model over a frame, its largest",
        "distance from the model about the image centre (px of the matching copy: the",
        "default's snap needs it within the tolerance), the largest turn.",
        "",
        "| stack | frames | magnifications, % | centre | similarity from the model, px "
        "| from the model about the image centre, matching px | turn, degrees |",
        "|---|---|---|---|---|---|---|",
        *fit_rows,
        "",
        "**Real stacks cropped** (`align_models.py`'s test): the largest distance over the",
        "crop (full-resolution px, worst frame) between the estimates on the whole and on",
        "the cropped copies.",
        "",
        "| stack | crop | similarity | model |",
        "|---|---|---|---|",
        *crop_rows,
    ]
    write_table(args.out / "align_breathing.md", rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
