"""Colours no frame shows, on the real stacks: flexdof (as run, and with ``--variant``
flags) against focus-stack and the frames' own composite.

    python tests/benchmarks/colour_fringes.py [--stacks pcb7,pcb10] [--out DIR] \
        [--work DIR] [--variant "--no-frame-range"]...

A true all-in-focus pixel is one of the frames' pixels (the frame in focus there), so its
colour lies within the frames' colours there. Per pixel, in 8-bit sRGB display levels,
the measure is how far the image's colour differences ``R - G`` and ``B - G`` leave
``[min, max]`` of the aligned frames' over a 5x5 neighbourhood (the registration slack of
the region benchmark's halo measure), the larger of the two. It is two-sided: a
desaturated result leaves the range where every frame is coloured, so greying the
image cannot pass. It is taken in display terms, not in the linear chromaticity
:func:`pipeline.core.frame_support.clip_to_frames` bounds since stop 34. Over the frames'
common area less a 20 px border:

* **mean**: the mean excess (levels);
* **per 10k**: pixels more than ``FRINGE_LEVELS`` out, per 10 000 (red rims beside
  clipped highlights are a few pixels wide: the mean hides them, the count does not).

The frames' composite (per pixel the frame with the most Laplacian energy, the region
benchmark's) is the check of the measure: made of frames' pixels, it reads about 0.
Writes ``DIR/colour_fringes.md``, ``DIR/colour_fringes.json`` and ``DIR/NAME_fringes.png``:
the ``CROPS`` windows of ``2 CROP_HALF`` px with the most of flexdof's pixels over
``FRINGE_LEVELS`` (flexdof | each variant | focus-stack | the frames' composite, 4x
nearest-neighbour).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from highlight_glow import crop_row, run_beside_peer, save_grid, variant_parser
from real_stack_regions import frames_composite
from real_stacks import STACKS

SLACK_PX = 2  # 5x5, as the halo measure's
BORDER_PX = 20
FRINGE_LEVELS = 10.0
CROPS = 3
CROP_HALF = 30


def colour_excess(image: np.ndarray, frames: list[np.ndarray]) -> np.ndarray:
    """Per pixel, levels by which ``image``'s ``R - G`` or ``B - G`` leaves the frames'
    range over the neighbourhood (the larger)."""
    box = np.ones((2 * SLACK_PX + 1,) * 2, np.uint8)
    excess = np.zeros(image.shape[:2], np.float32)
    for a in (0, 2):
        differences = np.stack([f[..., a] - f[..., 1] for f in frames])
        low = cv2.erode(differences.min(axis=0), box)
        high = cv2.dilate(differences.max(axis=0), box)
        d = image[..., a] - image[..., 1]
        np.maximum(excess, np.maximum(d - high, low - d), out=excess)
    return excess


def fringe_windows(fringes: np.ndarray, count: int, half: int) -> list[tuple[int, int]]:
    """Centres (row, column) of up to ``count`` non-overlapping ``2 half`` px windows with
    the most ``fringes`` pixels, densest first (windows with none are left out)."""
    density = cv2.boxFilter(fringes.astype(np.float32), -1, (2 * half + 1,) * 2,
                            normalize=False)
    rows, cols = density.shape
    density[:half], density[rows - half:], density[:, :half], density[:, cols - half:] = 0, 0, 0, 0
    centres = []
    while len(centres) < count and density.max() > 0:
        y, x = np.unravel_index(int(np.argmax(density)), density.shape)
        centres.append((int(y), int(x)))
        density[max(0, y - 2 * half) : y + 2 * half, max(0, x - 2 * half) : x + 2 * half] = 0
    return centres


def measure(name: str, pattern: str, work: Path, variants: list[str], out: Path) -> dict:
    images, frames, cover, _ = run_beside_peer(name, pattern, work, variants)
    images["frames' composite"] = frames_composite(frames)
    inner = cv2.erode(cover.astype(np.uint8), np.ones((2 * BORDER_PX + 1,) * 2, np.uint8)) > 0
    row, fringes = {}, None
    for label, image in images.items():
        excess = colour_excess(image, frames)
        if fringes is None:  # flexdof's, the first
            fringes = (excess > FRINGE_LEVELS) & inner
        excess = excess[inner]
        row[label] = {"mean": float(excess.mean()),
                      "per_10k": float(np.mean(excess > FRINGE_LEVELS) * 1e4)}
    crops = [crop_row(list(images.values()), centre, CROP_HALF)
             for centre in fringe_windows(fringes, CROPS, CROP_HALF)]
    if crops:
        save_grid(out / f"{name}_fringes.png", crops, 4)
    return row


def main() -> None:
    args = variant_parser(__doc__.splitlines()[0], "colour", "flexdof-colour").parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    args.work.mkdir(parents=True, exist_ok=True)
    summary = {name: measure(name, STACKS[name], args.work, args.variant, args.out)
               for name in args.stacks.split(",")}
    labels = list(next(iter(summary.values())))
    lines = [
        "# Colours no frame shows",
        "",
        "`python tests/benchmarks/colour_fringes.py`: per pixel, 8-bit sRGB levels by which "
        f"R-G or B-G leaves the aligned frames' range over {2 * SLACK_PX + 1}x"
        f"{2 * SLACK_PX + 1} px; mean, and pixels over {FRINGE_LEVELS:g} levels per 10 000.",
        "",
        "| stack | " + " | ".join(labels) + " |",
        "|---|" + "---|" * len(labels),
    ]
    for name, row in summary.items():
        cells = [f"{row[k]['mean']:.3f} / {row[k]['per_10k']:.1f}" if k in row else "-"
                 for k in labels]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
        print(name, {k: (round(v["mean"], 3), round(v["per_10k"], 1)) for k, v in row.items()},
              flush=True)
    (args.out / "colour_fringes.md").write_text("\n".join(lines) + "\n")
    (args.out / "colour_fringes.json").write_text(json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main()
