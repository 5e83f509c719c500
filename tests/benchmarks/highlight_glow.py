"""Glow round clipped highlights on the real stacks: flexdof (as run, and with
``--variant`` flags) against focus-stack and the frames.

    python tests/benchmarks/highlight_glow.py [--stacks pcb7,pcb10] [--out DIR] \
        [--work DIR] [--top N] [--variant "--frame-guard"]...

For each stack: runs ``flexdof stack`` (and once per ``--variant``, with those flags),
warps the frames into the result's geometry with the sidecar's homographies, registers
focus-stack's shared result to it (``real_stack_regions.register``), and finds the
highlights: sets of pixels clipped (8-bit 255 in some channel) in some frame, with a
frame that clips none of them within the blur's reach (else no frame shows their
light, and nothing can be put back). For the ``--top`` largest it measures, in linear
light (green channel), over the ring 3-20 px from the clipped pixels:

* **glow**: the mean of the image minus the frames' per-pixel minimum there. A defocused
  frame adds its highlight's disk to the ring, so the minimum over the frames is the
  ring without the highlight's light, what the frame focused there shows (below);
* the same of the **sharpest frame** (the most Laplacian energy within the ring's outer
  radius), the level a faithful result matches.

The measure is signed, so a result darker than the frames reads low: below the sharpest
frame's figure means darker than the frame focused there, not less glow (read it beside
that figure). flexdof's default clips every unclipped pixel to the frames' 3x3 range
(a little below the per-pixel minimum at most); ``--no-frame-range`` and the peers are not
held. In the committed run no stack's mean reads below its sharpest frame's. Writes
``DIR/highlight_glow.md``, ``DIR/highlight_glow.json`` and ``DIR/NAME_glow.png`` (four of
the largest highlights: flexdof | each variant | focus-stack | sharpest frame, 3x
nearest-neighbour).
"""

from __future__ import annotations

import argparse
import glob
import json
import shlex
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_stack_regions import FOCUS_STACK, frames_composite, read_srgb, register, warp
from real_stacks import SHARED, STACKS

from pipeline.core.colour import srgb_to_linear

RING_PX = (3.0, 20.0)
CROP_HALF = 50


def linear(srgb: np.ndarray) -> np.ndarray:
    """sRGB code values 0-255 -> linear light (the decoder's own EOTF)."""
    return srgb_to_linear(srgb / 255.0)


def run(name: str, pattern: str, work: Path, extra: list[str], tag: str) -> Path:
    out = work / f"{name}_{tag}.tif"
    files = sorted(glob.glob(str(SHARED / pattern)))
    subprocess.run(["flexdof", "stack", *files, "-o", str(out), *extra], check=True)
    return out


def run_beside_peer(name: str, pattern: str, work: Path, variants: list[str]):
    """Run flexdof on a stack (and once per ``variants`` flags), warp its frames into the
    result's geometry by the sidecar's homographies, and register focus-stack's shared
    result to the frames' composite (as ``real_stack_regions.py`` does, so the peer's
    placement does not depend on the result judged). Returns the images by label (sRGB
    levels), the frames, the pixels every image covers, and the sidecar."""
    default = run(name, pattern, work, [], "default")
    meta = json.loads(Path(f"{default}.json").read_text())
    base = Path(sorted(glob.glob(str(SHARED / pattern)))[0]).parent
    images = {"flexdof": read_srgb(default)}
    for number, flags in enumerate(variants, 1):
        made = run(name, pattern, work, shlex.split(flags), f"variant{number}")
        images[f"flexdof {flags}"] = read_srgb(made)
    shape = images["flexdof"].shape
    frames, cover = [], np.ones(shape[:2], bool)
    for entry in meta["frames"]:
        frame, covered = warp(read_srgb(base / entry["file"]), np.array(entry["homography"]), shape)
        frames.append(frame)
        cover &= covered
    peer = FOCUS_STACK / f"{name}.png"
    if peer.exists():
        moving = read_srgb(peer)
        h, _ = register(moving, frames_composite(frames))
        images["focus-stack"], covered = warp(moving, h, shape)
        cover &= covered
    return images, frames, cover, meta


def highlights(frames: list[np.ndarray], reach: int) -> list[np.ndarray]:
    """Masks of the clipped sets that some frame leaves unclipped within ``reach``,
    largest first."""
    clipped = [f.max(axis=2) >= 255 for f in frames]
    union = np.logical_or.reduce(clipped).astype(np.uint8)
    _, labels, stats, _ = cv2.connectedComponentsWithStats(union, connectivity=8)
    kernel = np.ones((2 * reach + 1,) * 2, np.uint8)
    found = []
    for label in np.argsort(-stats[1:, cv2.CC_STAT_AREA]) + 1:
        mask = labels == label
        near = cv2.dilate(mask.astype(np.uint8), kernel) > 0
        if any(not c[near].any() for c in clipped):
            found.append(mask)
    return found


def glow(image: np.ndarray, floor: np.ndarray, ring: np.ndarray) -> float:
    return float(np.mean(image[ring] - floor[ring]))


def measure(
    name: str, pattern: str, work: Path, out: Path, top: int, variants: list[str]
) -> list[dict]:
    results, frames, cover, meta = run_beside_peer(name, pattern, work, variants)
    shape = results["flexdof"].shape
    reach = int(meta["kernel"]["size"]) // 2
    green = {k: linear(v[..., 1]) for k, v in results.items()}
    lin_frames = np.stack([linear(f[..., 1]) for f in frames])
    floor = lin_frames.min(axis=0)
    rows, crops = [], []
    for mask in highlights(frames, reach)[:top]:
        dist = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5)
        ring = (dist >= RING_PX[0]) & (dist <= RING_PX[1]) & cover
        if ring.sum() < 50:
            continue
        near = dist <= RING_PX[1]  # the sharpest frame there: the most Laplacian energy
        energy = [float(np.var(cv2.Laplacian(f, cv2.CV_32F)[near])) for f in lin_frames]
        sharpest = int(np.argmax(energy))
        ys, xs = np.nonzero(mask)
        row = {
            "at": [int(xs.mean()), int(ys.mean())],
            "clipped_px": int(mask.sum()),
            "sharpest frame": glow(lin_frames[sharpest], floor, ring),
        }
        row.update({k: glow(v, floor, ring) for k, v in green.items()})
        rows.append(row)
        y, x = row["at"][1], row["at"][0]
        inside = CROP_HALF <= y < shape[0] - CROP_HALF and CROP_HALF <= x < shape[1] - CROP_HALF
        if len(crops) < 4 and inside:
            crops.append(crop_row([*results.values(), frames[sharpest]], (y, x), CROP_HALF))
    if crops:
        save_grid(out / f"{name}_glow.png", crops, 3)
    return rows


def crop_row(images: list[np.ndarray], centre: tuple[int, int], half: int) -> np.ndarray:
    """The ``2 half`` px square round ``centre`` (row, column) of each image, side by side
    (8-bit, RGB)."""
    y, x = centre
    box = (slice(y - half, y + half), slice(x - half, x + half))
    return np.hstack([np.clip(image[box], 0, 255).astype(np.uint8) for image in images])


def save_grid(path: Path, rows: list[np.ndarray], scale: int) -> None:
    """Rows of :func:`crop_row` one above the other, ``scale`` x nearest-neighbour, as a
    PNG."""
    grid = cv2.resize(np.vstack(rows), None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(path), grid[..., ::-1])


def variant_parser(description: str, results: str, work: str) -> argparse.ArgumentParser:
    """The options of a benchmark that runs flexdof (and ``--variant`` flags) on the real
    stacks: ``--stacks``, ``--out`` (default ``results/RESULTS`` beside this file),
    ``--work`` (default ``/tmp/WORK``) and ``--variant``."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--stacks", default=",".join(STACKS))
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results"
                        / results)
    parser.add_argument("--work", type=Path, default=Path("/tmp") / work)
    parser.add_argument(
        "--variant", action="append", default=[], help="flexdof flags to compare (repeatable)"
    )
    return parser


def main() -> None:
    parser = variant_parser(__doc__.splitlines()[0], "highlights", "flexdof-glow")
    parser.add_argument("--top", type=int, default=10)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    args.work.mkdir(parents=True, exist_ok=True)
    lines = [
        "# Glow round clipped highlights",
        "",
        "`python tests/benchmarks/highlight_glow.py`: mean of image minus the frames' "
        f"per-pixel minimum over the ring {RING_PX[0]:g}-{RING_PX[1]:g} px from each "
        "highlight's clipped pixels (linear light, green; 0 = no light beyond what every "
        "frame shows). The sharpest frame is the level a faithful result matches.",
        "",
    ]
    summary = {}
    for name in args.stacks.split(","):
        rows = measure(name, STACKS[name], args.work, args.out, args.top, args.variant)
        if not rows:
            lines += [f"## {name}", "", "no highlight that some frame leaves unclipped", ""]
            continue
        keys = [k for k in rows[0] if k not in ("at", "clipped_px")]
        lines += [f"## {name}", "", "| at (x, y) | clipped px | " + " | ".join(keys) + " |"]
        lines.append("|---|---|" + "---|" * len(keys))
        for row in rows:
            values = " | ".join(f"{row[k]:.4f}" for k in keys)
            lines.append(f"| {row['at'][0]}, {row['at'][1]} | {row['clipped_px']} | {values} |")
        means = {k: float(np.mean([r[k] for r in rows])) for k in keys}
        lines.append("| **mean** | | " + " | ".join(f"**{means[k]:.4f}**" for k in keys) + " |")
        lines.append("")
        summary[name] = means
        print(name, {k: round(v, 4) for k, v in means.items()}, flush=True)
    (args.out / "highlight_glow.md").write_text("\n".join(lines) + "\n")
    (args.out / "highlight_glow.json").write_text(json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main()
