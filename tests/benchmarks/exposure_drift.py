"""Frames shot at different exposures, against the truth (issue 13).

The truth scenes of ``regions_vs_truth.py`` (rendered once there, into its ``--work``
folder) with each frame's linear light scaled by a gain, written again as 8-bit sRGB PNGs:

* ``none``: every gain 1 (the scene as rendered, re-encoded);
* ``ramp``: 1.12 .. 0.90 from the first frame to the last (a macro lens's effective
  aperture changing with its focus; pcb10's frames read 1.08 .. 0.95);
* ``flicker``: 1, 0.85, 1, 1.10, 1, 0.90, ... (mains light, a recycling flash);
* ``flash``: the gains beetle's flash-lit frames read, 0.76 .. 1.25.

``flexdof stack`` runs on each as shot (the default) and with ``--match-exposure``. The
score is the PSNR (8-bit sRGB display terms, 8 px border left out) against the truth after
the best global gain, since which exposure the result takes is a choice.

    python tests/benchmarks/exposure_drift.py [--work DIR] [--scenes ...]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from pipeline.core import colour

HERE = Path(__file__).resolve().parent
TRUTH_WORK = HERE / "results" / "regions_vs_truth" / "work"
DRIFTS = {
    "none": lambda n: np.ones(n),
    "ramp": lambda n: np.linspace(1.12, 0.90, n),
    "flicker": lambda n: np.resize([1.0, 0.85, 1.0, 1.10, 1.0, 0.90], n),
    "flash": lambda n: np.resize([0.76, 1.25, 1.04, 1.02, 0.98, 0.83, 0.74, 1.18, 1.13], n),
}
SCENES = ("board", "board_ends", "board_22px", "board_7frames", "motorcycle")
VERSIONS = {"as shot": [], "--match-exposure": ["--match-exposure"]}


def read_linear(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[..., ::-1]
    codes = image.astype(np.float32) / (65535.0 if image.dtype == np.uint16 else 255.0)
    return colour.srgb_to_linear(codes)


def write_srgb8(path: Path, linear: np.ndarray) -> None:
    encoded = colour.linear_to_srgb(np.clip(linear, 0, 1))
    cv2.imwrite(str(path), np.round(255 * encoded).astype(np.uint8)[..., ::-1])


def psnr_fitted(result: np.ndarray, truth: np.ndarray, border: int = 8) -> float:
    """PSNR (sRGB display terms) of ``result`` times its best global gain (linear light)."""
    a, b = (x[border:-border, border:-border] for x in (result, truth))
    gain = float(np.sum(a * b) / np.sum(a * a))
    shown = [colour.linear_to_srgb(np.clip(x, 0, 1)) for x in (gain * a, b)]
    return float(10 * np.log10(1 / np.mean((shown[0] - shown[1]) ** 2)))


def run(frames: list[Path], out: Path, flags: list[str]) -> None:
    args = ["-q", "stack", *map(str, frames), "-o", str(out), "--threads", "2", *flags]
    subprocess.run(["flexdof", *args], check=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=TRUTH_WORK, help="regions_vs_truth's work")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "exposure_drift")
    parser.add_argument("--scenes", default=",".join(SCENES))
    args = parser.parse_args()
    rows = []
    for scene in args.scenes.split(","):
        source = sorted((args.work / scene / "frames").glob("frame_*.png"))
        if not source:
            raise SystemExit(
                f"{args.work / scene}: no rendered frames; run regions_vs_truth.py first"
            )
        truth = read_linear(args.work / scene / "truth.png")
        for drift, gains in DRIFTS.items():
            folder = args.out / "work" / scene / drift
            folder.mkdir(parents=True, exist_ok=True)
            frames = [folder / f.name for f in source]
            for src, dst, g in zip(source, frames, gains(len(source))):
                write_srgb8(dst, read_linear(src) * np.float32(g))
            scores = {}
            for name, flags in VERSIONS.items():
                out = folder / f"{name.strip('-').replace(' ', '_')}.tif"
                run(frames, out, flags)
                scores[name] = psnr_fitted(read_linear(out), truth)
            rows.append((scene, drift, scores))
            print(scene, drift, {k: round(v, 2) for k, v in scores.items()}, flush=True)
    names = list(VERSIONS)
    lines = [
        "# Frames shot at different exposures, against the truth",
        "",
        "`python tests/benchmarks/exposure_drift.py`: PSNR (dB, 8-bit sRGB, after the best",
        "global gain) against the truth.",
        "",
        "| scene | drift | " + " | ".join(names) + " |",
        "|---|---|" + "---|" * len(names),
    ]
    for scene, drift, scores in rows:
        cells = " | ".join(f"{scores[n]:.2f}" for n in names)
        lines.append(f"| {scene} | {drift} | {cells} |")
    text = "\n".join(lines) + "\n"
    (args.out / "exposure_drift.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
