"""A real stack as other cameras and shooting would deliver it, region by region (issue 13).

Each variant is the stack's frames decoded once and re-encoded (JPEG quality 95, their EXIF
kept), so that they differ only in what the variant changes:

* ``as shot``: nothing else (the control: what the re-encoding itself costs);
* ``portrait``: EXIF Orientation 6, the camera turned a quarter clockwise (the pixels as
  stored; viewers, OpenCV and focus-stack show them turned);
* ``exposure ramp``: gains of +8% .. -8% in linear light from the first frame to the last (the
  effective aperture of a macro lens changing with its magnification);
* ``flicker``: gains of 0.85-1.10 frame to frame (mains-lit scenes, flash recycling).
* ``handheld``: every frame moved as a hand holding the camera moves it, a seeded shift of up
  to 1.5% of the frame's side and a turn of up to 0.5 degrees about its centre, then all
  frames cropped to the same window inside what every moved frame covers (so no frame shows a
  border): the case a focusing rail never gives and a handheld or bumped stack always does.
  The move is interpolated (Lanczos), which smooths each frame's finest detail and noise a
  little, by an amount that differs from frame to frame;
* ``cropped``: the control of ``handheld``, the same crop without the move;
* ``loose hand`` and its control ``cropped more``: shifts of up to 6% and turns of up to
  3 degrees. (A control and variant reduced to half size were tried: the region measures'
  windows and scales are in pixels, and at half size their flat mask took pcb7's fine board
  texture for flat.)
* ``high ISO``: each frame with a sensor's shot and read noise added in linear light (seeded per
  frame), as an APS-C sensor at ISO 3200 records it: a full well of 780 electrons (25,000 at ISO
  100, over 32) and a read noise of 3 electrons, so mid-grey (0.18) carries a noise of 0.015 in
  linear light, about 4.6 levels of 8-bit sRGB. Camera JPEGs would smooth some of it away; these
  do not (the harder case for a deconvolution, which amplifies noise);
* ``wide-angle turned`` and its control ``cropped as turned``: every frame seen as a camera
  with a 16 mm lens on APS-C (82 degrees across the diagonal) sees it when turned by a
  seeded angle of up to 0.5 degree about each of its three axes (``K R K^-1``: a shift, a
  roll and a keystone), cropped alike: a handheld wide-angle stack, the case for
  ``--align-model keystone`` (and what "auto" must find).

Each variant is scored by ``real_stack_regions.py`` against focus-stack made from the same
files (``--focus-stack``; its default matches each frame's contrast and white balance, its
run "as shot" does not). Prints, and writes to ``OUT/camera_variants.md``, the regions as
good as each peer.

    python tests/benchmarks/camera_variants.py --focus-stack PATH [--stack pcb7]
        [--flexdof-args --match-exposure --label match]
"""

from __future__ import annotations

import argparse
import glob
import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_stack_regions import good_regions  # the region counts of the main benchmark
from real_stacks import SHARED, STACKS

HERE = Path(__file__).resolve().parent
# (largest shift as a share of the frame's side, largest turn in degrees) of a hand's move
STEADY_HAND = (0.015, 0.5)
LOOSE_HAND = (0.06, 3.0)
# (largest turn about each axis in degrees, half the diagonal field of view in degrees)
WIDE_TURN = (0.5, 41.0)
# (full well, read noise), electrons: an APS-C sensor at ISO 3200
ISO_3200 = (780.0, 3.0)


class Variant(NamedTuple):
    """How a variant's frames differ from the stack's."""

    orientation: int  # EXIF orientation
    gains: Callable[[int], np.ndarray]  # per-frame gain in linear light, of n frames
    # how the frames are moved: None, or (how, hand) with how "crop" (cropped as that
    # hand's moves would crop them, not moved) or "move" (moved and cropped)
    motion: tuple | None = None
    noise: tuple[float, float] | None = None  # (full well, read noise) in electrons


def _steady(n: int) -> np.ndarray:
    return np.ones(n)


VARIANTS = {
    "as shot": Variant(1, _steady),
    "portrait": Variant(6, _steady),
    "exposure ramp": Variant(1, lambda n: np.linspace(1.08, 0.92, n)),
    "flicker": Variant(1, lambda n: np.resize([1.0, 0.85, 1.0, 1.10, 1.0, 0.90], n)),
    "cropped": Variant(1, _steady, ("crop", STEADY_HAND)),
    "handheld": Variant(1, _steady, ("move", STEADY_HAND)),
    "cropped more": Variant(1, _steady, ("crop", LOOSE_HAND)),
    "loose hand": Variant(1, _steady, ("move", LOOSE_HAND)),
    "cropped as turned": Variant(1, _steady, ("crop", WIDE_TURN)),
    "wide-angle turned": Variant(1, _steady, ("move", WIDE_TURN)),
    "high ISO": Variant(1, _steady, noise=ISO_3200),
}


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _linear_to_srgb(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.abs(x) ** (1 / 2.4) - 0.055)


def hand_motions(
    n: int, shape: tuple[int, int], hand: tuple[float, float], seed: int = 13
) -> tuple[list, tuple]:
    """Seeded 2x3 rigid motions of ``n`` frames of ``shape`` by ``hand`` (largest shift, as
    a share of the side, and turn in degrees) and the crop ``(y0, x0, h, w)``
    inside what every moved frame covers (the turn's corners and the largest shift kept out)."""
    rows, cols = shape
    rng = np.random.default_rng(seed)
    margin = 0
    motions = []
    for _ in range(n):
        dy, dx = rng.uniform(-hand[0], hand[0], 2) * np.array([rows, cols])
        turn = rng.uniform(-hand[1], hand[1])
        m = cv2.getRotationMatrix2D(((cols - 1) / 2, (rows - 1) / 2), turn, 1.0)
        m[:, 2] += (dx, dy)
        motions.append(m)
        turn_px = abs(np.sin(np.radians(turn))) * max(rows, cols) / 2
        margin = max(margin, int(np.ceil(max(abs(dx), abs(dy)) + turn_px)) + 2)
    return motions, (margin, margin, rows - 2 * margin, cols - 2 * margin)


def turn_motions(
    n: int, shape: tuple[int, int], turn: tuple[float, float], seed: int = 13
) -> tuple[list, tuple]:
    """Seeded 3x3 maps ``K R K^-1`` of ``n`` frames of ``shape`` seen by a camera whose
    diagonal field is ``2 * turn[1]`` degrees, turned by up to ``turn[0]`` degrees about each
    axis, and the crop ``(y0, x0, h, w)`` inside what every turned frame covers."""
    rows, cols = shape
    focal = 0.5 * np.hypot(rows, cols) / np.tan(np.radians(turn[1]))
    k = np.array([[focal, 0, (cols - 1) / 2], [0, focal, (rows - 1) / 2], [0, 0, 1.0]])
    rng = np.random.default_rng(seed)
    corners = np.array([[0, cols - 1, 0, cols - 1], [0, 0, rows - 1, rows - 1], [1, 1, 1, 1.0]])
    margin = 0
    motions = []
    for _ in range(n):
        rotation = cv2.Rodrigues(np.radians(rng.uniform(-turn[0], turn[0], 3)))[0]
        h = k @ rotation @ np.linalg.inv(k)
        motions.append(h / h[2, 2])
        moved = h @ corners
        margin = max(margin, int(np.ceil(np.abs(moved[:2] / moved[2] - corners[:2]).max())) + 2)
    return motions, (margin, margin, rows - 2 * margin, cols - 2 * margin)


def make_variant(frames: list[Path], folder: Path, variant: Variant) -> None:
    """The frames re-encoded into ``folder`` with the variant's gains and EXIF orientation;
    with its motion ("move", hand) moved as by that hand and cropped, with ("crop", hand)
    only cropped alike; with its noise, a sensor's shot and read noise added."""
    folder.mkdir(parents=True, exist_ok=True)
    motion = variant.motion
    for k, (path, gain) in enumerate(zip(frames, variant.gains(len(frames)))):
        with Image.open(path) as image:
            exif = image.getexif()
            codes = np.asarray(image.convert("RGB"), np.float64) / 255
        exif[0x0112] = variant.orientation
        linear = np.clip(_srgb_to_linear(codes) * gain, 0, 1)
        if variant.noise is not None:
            well, read = variant.noise
            rng = np.random.default_rng(100 + k)
            electrons = rng.poisson(linear * well) + rng.normal(0, read, linear.shape)
            linear = np.clip(electrons / well, 0, 1)
        linear = linear.astype(np.float32)
        if motion is not None:
            how, hand = motion
            moves = turn_motions if hand == WIDE_TURN else hand_motions
            motions, (y0, x0, h, w) = moves(len(frames), linear.shape[:2], hand)
            if how == "move":
                size = (linear.shape[1], linear.shape[0])
                warp = cv2.warpPerspective if motions[k].shape == (3, 3) else cv2.warpAffine
                linear = warp(linear, motions[k], size, flags=cv2.INTER_LANCZOS4)
            linear = np.clip(linear[y0 : y0 + h, x0 : x0 + w], 0, 1)
        out = np.round(_linear_to_srgb(linear) * 255).astype(np.uint8)
        Image.fromarray(out).save(folder / f"{path.stem}.jpg", quality=95, exif=exif)


def verdict_cell(result: dict, peer: str) -> str:
    """The regions of 9 where flexdof is at least as good as ``peer``, or why none count:
    the peer gave no result, or one that is not the scene any more."""
    if peer in result.get("peer_failures", {}):
        return "failed"
    if peer in result.get("unusable_peers", {}):
        return f"unusable (registration {result['unusable_peers'][peer]:.2f})"
    return "{}/{}".format(*good_regions(result["scores"], peer))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stack", default="pcb7", choices=sorted(STACKS))
    parser.add_argument("--focus-stack", metavar="PATH", required=True)
    parser.add_argument(
        "--out", type=Path, default=HERE / "results" / "real_regions" / "camera_variants"
    )
    parser.add_argument("--flexdof-args", default="", help="added to --threads 2")
    parser.add_argument(
        "--variants",
        default=",".join(VARIANTS),
        help=f"comma-separated, of: {', '.join(VARIANTS)} (default all)",
    )
    parser.add_argument(
        "--label", default="", help="names the results: OUT/camera_variants_LABEL.md"
    )
    args = parser.parse_args()
    frames = [Path(p) for p in sorted(glob.glob(str(SHARED / STACKS[args.stack])))]
    rows, failures = [], {}
    chosen = [v.strip() for v in args.variants.split(",")]
    unknown = sorted(set(chosen) - set(VARIANTS))
    if unknown:
        parser.error(f"--variants: unknown {', '.join(unknown)}; choose from {', '.join(VARIANTS)}")
    for variant in chosen:
        label = f"-{args.label}" if args.label else ""
        name = f"{args.stack}-{variant.replace(' ', '-')}{label}"
        folder = args.out / "frames" / name
        make_variant(frames, folder, VARIANTS[variant])
        scored = args.out / name
        subprocess.run(
            [
                sys.executable,
                str(HERE / "real_stack_regions.py"),
                f"--stack={name}={folder}/*.jpg",
                f"--stacks={name}",
                f"--focus-stack={args.focus_stack}",
                f"--out={scored}",
                f"--flexdof-args=--threads 2 {args.flexdof_args}".strip(),
            ],
            check=True,
        )
        result = json.loads((scored / "real_regions.json").read_text())[name]
        failed = result.get("peer_failures", {})
        counts = [verdict_cell(result, peer) for peer in PEERS]
        ecc = result["registration_ecc"].get("focus-stack", float("nan"))
        rows.append((variant, counts, ecc))
        failures.update({f"{variant}, {peer}": said for peer, said in failed.items()})
    given = f" --variants='{args.variants}'" if chosen != list(VARIANTS) else ""
    given += f" --flexdof-args='{args.flexdof_args}' --label={args.label}" if args.label else ""
    lines = [
        f"# {args.stack} as other cameras and shooting deliver it",
        "",
        f"`python tests/benchmarks/camera_variants.py --focus-stack PATH{given}`:",
        "regions of 9 where flexdof is at least as good as the peer on all four measures",
        "(the peer made from the same files), and focus-stack's registration to the frames",
        "(ECC).",
        "",
        "| variant | vs focus-stack | vs focus-stack as shot | vs enfuse | registration |",
        "|---|---|---|---|---|",
    ]
    for variant, counts, ecc in rows:
        lines.append(f"| {variant} | {' | '.join(counts)} | {ecc:.4f} |")
    lines += ["", *(f"- {where} gave no result: {said}" for where, said in failures.items())]
    text = "\n".join(lines) + "\n"
    suffix = f"_{args.label}" if args.label else ""
    (args.out / f"camera_variants{suffix}.md").write_text(text)
    print(text)
    return 0


PEERS = ("focus-stack", "focus-stack as shot", "enfuse")

if __name__ == "__main__":
    sys.exit(main())
